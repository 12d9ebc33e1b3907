"""Write the built-in smoke plume's density grid: ``clscatter/scene/data/smoke.npy`` (what
``builtin:smoke_plume`` reads, everywhere) and the same grid as ``smoke.vdb`` (OpenVDB,
placed by its transform; written when ``pyopenvdb`` is installed).

The plume is procedural and deterministic (NumPy only, a fixed seed): a column rising from
a source just above the floor, drifting and widening with height, its density a Gaussian
profile across the column, thinning upwards, broken up by three octaves of value noise
and brought smoothly to 0 before the box faces. 32 x 48 x 32 voxels of 0.0375 scene units
over the box ``BOUNDS``; densities in [0, 1], below 0.002 set to 0 (inactive in the .vdb).

    .venv/bin/python tools/make_smoke.py          # rewrite both files
    .venv/bin/python tools/make_smoke.py --check  # exit 1 unless the files match
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "clscatter" / "scene" / "data"
SHAPE = (32, 48, 32)
BOUNDS = (np.array([-0.6, 0.0, -0.6]), np.array([0.6, 1.8, 0.6]))
SEED = 20240611


def value_noise(shape: tuple[int, int, int], cells: int, rng: np.random.Generator) -> np.ndarray:
    """Random values on a lattice of ``cells`` cells per unit side, trilinear at the voxel
    centres of ``shape`` (the lattice spans the grid's longest side)."""
    side = max(shape)
    lat = rng.random(tuple(int(np.ceil(cells * n / side)) + 2 for n in shape))
    axes = [(np.arange(n) + 0.5) * cells / side for n in shape]
    idx = [np.floor(a).astype(int) for a in axes]
    frac = [a - i for a, i in zip(axes, idx)]
    out = np.zeros(shape)
    for corner in np.ndindex(2, 2, 2):
        w = np.ones(shape)
        ix = []
        for axis, c in enumerate(corner):
            f = frac[axis] if c else 1.0 - frac[axis]
            w = w * f.reshape([-1 if k == axis else 1 for k in range(3)])
            ix.append((idx[axis] + c).reshape([-1 if k == axis else 1 for k in range(3)]))
        out += w * lat[ix[0], ix[1], ix[2]]
    return out


def plume() -> np.ndarray:
    """The density grid, (32, 48, 32) float32 in [0, 1] (x, y, z)."""
    rng = np.random.default_rng(SEED)
    lo, hi = BOUNDS
    c = [lo[a] + (np.arange(n) + 0.5) * (hi[a] - lo[a]) / n for a, n in enumerate(SHAPE)]
    x, y, z = np.meshgrid(*c, indexing="ij")
    h = y / hi[1]                                           # 0 at the floor, 1 at the top
    cx = 0.12 * np.sin(3.0 * y) * h                         # the column drifts and sways
    cz = -0.08 * h + 0.05 * np.sin(4.5 * y + 1.0) * h
    radius = 0.07 + 0.28 * h ** 0.9
    rho = np.hypot(x - cx, z - cz) / radius
    profile = np.exp(-2.0 * rho ** 2) * (1.0 - 0.55 * h)
    source = np.clip((y - 0.03) / 0.12, 0.0, 1.0)          # starts just above the floor
    noise = sum(0.5 ** o * value_noise(SHAPE, 4 * 2 ** o, rng) for o in range(3)) / 1.75
    dens = profile * source * np.clip(2.0 * noise - 0.45, 0.0, None)
    fade = np.ones(SHAPE)                                   # smoothly 0 at the box faces
    for a, n in enumerate(SHAPE):
        i = np.arange(n)
        edge = np.clip(np.minimum(i + 0.5, n - 0.5 - i) / 3.0, 0.0, 1.0)
        fade = fade * (edge ** 2 * (3 - 2 * edge)).reshape([-1 if k == a else 1 for k in range(3)])
    dens = dens * fade
    dens = dens / dens.max()
    return np.where(dens < 2e-3, 0.0, dens).astype(np.float32)    # empty voxels stay off


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare instead of writing")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from clscatter.scene import grids

    dens = plume()
    npy, vdb = DATA / "smoke.npy", DATA / "smoke.vdb"
    if args.check:
        same = npy.is_file() and np.array_equal(np.load(npy), dens)
        print(f"{npy.name}: {'matches' if same else 'differs'}")
        return 0 if same else 1
    DATA.mkdir(parents=True, exist_ok=True)
    np.save(npy, dens)
    print(f"wrote {npy.relative_to(REPO)} {dens.shape} ({npy.stat().st_size} bytes)")
    if grids.openvdb() is None:
        print(f"pyopenvdb missing ({grids.OPENVDB_PACKAGE}): {vdb.name} not written", file=sys.stderr)
        return 0
    grids.write_vdb(vdb, dens, BOUNDS)
    print(f"wrote {vdb.relative_to(REPO)} ({vdb.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
