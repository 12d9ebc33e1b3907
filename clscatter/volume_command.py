"""``clscatter volume convert IN -o OUT [--bounds X0 Y0 Z0 X1 Y1 Z1] [--name NAME]``:
density grids between ``.npy`` and OpenVDB ``.vdb`` (``.vol`` is read too).

The grid is read as a scene's ``density`` is (``clscatter.scene.grids``: finite values
>= 0; a ``.vdb`` grid by ``--name``, default ``density``) and written to OUT:

* ``.vdb``: grid ``--name``, placed by ``--bounds`` when given, else where the input
  places it (``.vdb`` transform, ``.vol`` box), else (a ``.npy``) with voxel (i, j, k)
  centred at (i, j, k);
* ``.npy``: the array (nx, ny, nz); its placement is printed as the ``bounds`` line a
  scene needs for it.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .errors import ClscatterError, SceneError

OUTPUTS = (".npy", ".vdb")


def add_volume_command(sub) -> None:
    """Add ``volume`` (with its ``convert`` action) to the command line's subparsers."""
    v = sub.add_parser("volume", help="density grids: convert between .npy and OpenVDB .vdb")
    actions = v.add_subparsers(dest="volume_action", parser_class=type(v))
    c = actions.add_parser("convert", help="convert a density grid (.npy, .vdb, .vol) to "
                                           ".npy or .vdb")
    c.add_argument("input", help="grid file: .npy, .vdb or .vol")
    c.add_argument("-o", "--output", required=True, metavar="OUT", help="output: .npy or .vdb")
    c.add_argument("--bounds", type=float, nargs=6, default=None,
                   metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="the box the .vdb is placed in (min then max corner)")
    c.add_argument("--name", default="density", help="grid name in a .vdb (default: density)")


def run_volume(args: argparse.Namespace) -> int:
    """The ``volume`` command; errors are :class:`ClscatterError` (one line)."""
    if args.volume_action != "convert":
        raise ClscatterError("volume: give an action: clscatter volume convert IN -o OUT")
    from .scene import grids

    src, dst = Path(args.input), Path(args.output)
    if dst.suffix.lower() not in OUTPUTS:
        raise SceneError(str(dst), f"unknown output format '{dst.suffix}' (one of "
                         f"{', '.join(OUTPUTS)})")
    bounds = None
    if args.bounds is not None:
        lo, hi = np.array(args.bounds[:3]), np.array(args.bounds[3:])
        if not (np.all(np.isfinite(args.bounds)) and np.all(lo < hi)):
            raise SceneError("--bounds", "must be finite with min < max on every axis")
        if dst.suffix.lower() != ".vdb":
            raise SceneError("--bounds", "places a .vdb output; a .npy carries no placement")
        bounds = (lo, hi)
    name = args.name if src.suffix.lower() == ".vdb" else None
    got = grids.load_density(src, str(src), name)
    if dst.suffix.lower() == ".vdb":
        place = bounds or got.bounds
        grids.write_vdb(dst, got.values, place, args.name, str(dst))
        if place is None:
            place = (np.full(3, -0.5), np.array(got.values.shape) - 0.5)
    else:
        try:
            np.save(dst, got.values)
        except OSError as exc:
            raise SceneError(str(dst), f"cannot write: {exc.strerror or exc}") from None
        place = got.bounds
    shape = " x ".join(str(n) for n in got.values.shape)
    print(f"wrote {dst}: {shape} voxels, density {float(got.values.min()):g} .. "
          f"{float(got.values.max()):g}")
    if place is not None:
        print(f"bounds = {{ min = {_vec(place[0])}, max = {_vec(place[1])} }}")
    return 0


def _vec(v) -> str:
    return "[" + ", ".join(f"{float(x):.9g}" for x in v) + "]"
