"""The installed package must contain every subpackage and the kernels: pyproject.toml
lists packages explicitly (cl_kernels/ is mapped to clscatter.cl_kernels), so check that
the list keeps up with the tree."""
from __future__ import annotations

import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    listed = set(cfg["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "clscatter").rglob("__init__.py")}
    assert found - listed == set(), f"add to pyproject.toml [tool.setuptools] packages: {sorted(found - listed)}"
    assert "clscatter.cl_kernels" in listed
    data = cfg["tool"]["setuptools"]["package-data"]["clscatter.cl_kernels"]
    for group in ("shared", "transport", "estimators", "methods"):
        assert f"{group}/*.cl" in data or f"{group}/*.h" in data


def test_kernel_sources_are_found():
    from clscatter.device import kernel_dir
    kd = kernel_dir()
    assert (kd / "shared" / "common.h").is_file() and (kd / "transport" / "view_paths.cl").is_file()


def test_nothing_points_outside_the_repository():
    """The format, meshes and papers a user needs are in the repository; no file refers to
    the workplace's shared folder or its copy of the format."""
    import re
    bad = re.compile(r"\.\./shared|/work/shared|parent\s*/\s*\"shared\"|SCENE_FORMAT\.md")
    skip = {".git", ".venv", "bench_out", "__pycache__", ".pytest_cache", "clscatter.egg-info"}
    hits = []
    for p in REPO.rglob("*"):
        if any(part in skip for part in p.relative_to(REPO).parts) or not p.is_file():
            continue
        if p.suffix not in (".py", ".md", ".toml", ".sh", ".cl", ".h", ".txt", ".cfg", "") or p.name == "test_packaging.py":
            continue
        try:
            text = p.read_text()
        except (UnicodeDecodeError, OSError):
            continue
        hits += [f"{p.relative_to(REPO)}:{i + 1}" for i, line in enumerate(text.splitlines())
                 if bad.search(line)]
    assert hits == [], f"references outside the repository: {hits}"
