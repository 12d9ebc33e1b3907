"""Output files: checked before any work starts, written all or nothing afterwards.

``check_output(path, suffixes, option)`` runs before a render: the suffix is known, the
folder exists and is writable, and the path is not a folder, so a render is never wasted on
an output that cannot be written. :func:`write_all` writes every output to a hidden staging
name beside its destination and renames them into place only when all were written; on any
failure (or Ctrl-C) the staged files are removed and no destination is touched.
:func:`staged_folder` does the same for a folder of files written one at a time (an
animation's frames).
"""
from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from pathlib import Path
from typing import Callable, Iterator, Sequence

from ..errors import ClscatterError


def check_output(path: str | os.PathLike, suffixes: Sequence[str], option: str) -> Path:
    """``path`` as a Path if it can be written; ClscatterError naming it (and ``option``)
    otherwise."""
    p = Path(path)
    text = os.fspath(path)
    if not text.strip():
        raise ClscatterError(f"{option}: empty output path")
    if p.is_dir():
        raise ClscatterError(f"{text}: is a folder, not a file ({option})")
    if p.suffix.lower() not in suffixes:
        raise ClscatterError(f"{text}: unsupported {option} format (use {', '.join(suffixes)})")
    folder = p.resolve().parent
    if not folder.is_dir():
        raise ClscatterError(f"{text}: output folder {folder} does not exist ({option})")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ClscatterError(f"{text}: output folder {folder} is not writable ({option})")
    if p.exists() and not os.access(p, os.W_OK):
        raise ClscatterError(f"{text}: file exists and is not writable ({option})")
    return p


def _staging_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{secrets.token_hex(4)}.staging{path.suffix}")


def write_all(writes: Sequence[tuple[Path, Callable[[Path], None]]]) -> None:
    """Run every ``writer(staging_path)``, then rename each staged file to its path.

    All or nothing: if a writer fails, the staged files are deleted and no destination
    changes. (The final renames are atomic each; they only fail if the file system does.)
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for dest, writer in writes:
            tmp = _staging_name(dest)
            staged.append((tmp, dest))
            writer(tmp)
        for tmp, dest in staged:
            os.replace(tmp, dest)
        staged.clear()
    finally:
        for tmp, _ in staged:
            try:
                tmp.unlink()
            except OSError:
                pass


@contextlib.contextmanager
def staged_folder(dest: str | os.PathLike) -> Iterator[Path]:
    """A hidden staging folder beside ``dest`` for files written one at a time: the
    ``with`` body writes into it; when the body ends normally every file is moved into
    ``dest`` (created if missing), and on any failure or interruption the staging folder
    is deleted and ``dest`` is neither created nor changed."""
    dest = Path(dest)
    stage = dest.resolve().parent / f".{dest.name}.{secrets.token_hex(4)}.staging"
    stage.mkdir()
    try:
        yield stage
        dest.mkdir(exist_ok=True)
        for f in sorted(stage.iterdir()):
            os.replace(f, dest / f.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
