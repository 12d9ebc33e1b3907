"""Heterogeneous media: density grids in the scene format (``.npy``, ``.vdb``, ``.vol``),
their files, the planner's choices, and their renders by ``raymarch`` and ``voxel``.

Renders (PoCL CPU, measured values; bounds about 2x above them):

* a constant density grid equals a homogeneous medium filling the same box: ``raymarch``
  relMSE 1.9e-7, mean ratio 1.00000 (jittered against mid-stratum samples: the only
  difference), surfaces within 2e-5; ``voxel``: identical images (the same fields);
* pure absorption by a linear density ramp seen against a lit wall: every pixel is the
  unattenuated wall times exp(-closed-form optical depth / |d_x|), optical depth 0.01 ..
  10, for a ray somewhere in the pixel's footprint (bounds: the footprint's extremes, and
  1e-6 for float32);
* ``raymarch`` (256 steps) with a density grid, a point light without and a spot light
  with a scene medium (which the grid replaces in its box), the floor in the smoke's
  shadow, against a NumPy quadrature of the same integrals along the same view rays (its
  own density sampling, optical depths, phase, light falloff): medium term relMSE 1.8e-9
  and 2.1e-6, surface 6.2e-10 and 2.9e-10 (bounds in ``CASES``);
* the built-in smoke plume renders finite with ``raymarch`` (``auto``), and the darkest
  lit floor pixel keeps 22 % of the light it has without the smoke (bound: under 45 %).
"""
from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from reference_checks import assert_matches_reference
from setup_installs import setup_installs_here

import clscatter
from clscatter.errors import SceneError
from clscatter.scene import grids
from clscatter.scene.loader import scene_from_dict

REPO = Path(__file__).resolve().parents[1]
HAVE_VDB = grids.openvdb() is not None
NO_VDB = "pyopenvdb is not importable (scripts/setup.sh installs python3-openvdb and links it)"


@pytest.fixture
def vdb_module():
    """pyopenvdb must be there where the set-up installs it; elsewhere its absence skips."""
    if not HAVE_VDB:
        required = setup_installs_here()
        if required:
            pytest.fail(f"{NO_VDB}; it is required here ({required})", pytrace=False)
        pytest.skip(NO_VDB)


needs_vdb = pytest.mark.usefixtures("vdb_module")


def _scene(volumes, **extra) -> dict:
    return {"camera": {"origin": [0.0, 1.0, 4.0], "target": [0.0, 0.5, 0.0], "fov": 40.0,
                       "resolution": [16, 12], "spp": 1},
            "lights": [{"type": "point", "position": [0.3, 2.2, 0.4], "intensity": 6.0}],
            "volumes": volumes, **extra}


def _load(tmp_path: Path, volumes, **extra):
    return scene_from_dict(_scene(volumes, **extra), tmp_path)


BOX = {"min": [-0.5, 0.3, -0.5], "max": [0.5, 1.1, 0.5]}
RAY_EPS = 2e-5            # common.h: a shadow ray's offset along the normal (normalised units)


# ---- scene format and files -------------------------------------------------------------

def test_npy_density_volume(tmp_path):
    d = np.random.default_rng(0).uniform(0, 2, (4, 5, 6))
    np.save(tmp_path / "d.npy", d)
    s = _load(tmp_path, [{"density": "d.npy", "bounds": BOX, "sigma_s": 0.5, "sigma_a": 0.1}])
    v = s.volumes[0]
    assert v.density.dtype == np.float32 and np.array_equal(v.density, d.astype(np.float32))
    np.testing.assert_array_equal(v.grid_bounds[0], BOX["min"])
    np.testing.assert_array_equal(v.grid_bounds[1], BOX["max"])
    assert v.ior == 1.0 and not v.refracts and v.grid is None and v.resolution == 6
    assert s.density_volumes() == [v]
    lo, hi = s.bbox()
    np.testing.assert_array_equal(lo, BOX["min"])


def _write_vol(path: Path, values: np.ndarray, box) -> None:
    nx, ny, nz = values.shape
    head = struct.pack("<3sBiiiii6f", b"VOL", 3, 1, nx, ny, nz, 1, *box)
    path.write_bytes(head + np.ascontiguousarray(values.transpose(2, 1, 0), "<f4").tobytes())


def test_vol_is_read_with_x_fastest_and_placed_by_its_box(tmp_path):
    d = np.random.default_rng(1).uniform(0, 1, (3, 4, 5)).astype(np.float32)
    box = [-1.0, 0.0, -2.0, 1.0, 2.0, 3.0]
    _write_vol(tmp_path / "d.vol", d, box)
    s = _load(tmp_path, [{"density": "d.vol", "sigma_s": 1.0}])
    v = s.volumes[0]
    assert np.array_equal(v.density, d)
    np.testing.assert_array_equal(v.grid_bounds[0], box[:3])
    np.testing.assert_array_equal(v.grid_bounds[1], box[3:])
    s = _load(tmp_path, [{"density": "d.vol", "bounds": BOX}])     # bounds win
    np.testing.assert_array_equal(s.volumes[0].grid_bounds[1], BOX["max"])


@needs_vdb
def test_vdb_round_trip_equals_npy(tmp_path):
    """A grid written to .vdb and read back: the same values and the same box."""
    d = np.random.default_rng(2).uniform(0.1, 3, (6, 4, 5)).astype(np.float32)
    d[0, 0, 0] = 0.0                                 # a zero corner still spans the box
    np.save(tmp_path / "d.npy", d)
    bounds = (np.array([-1.25, 0.5, 2.0]), np.array([0.75, 1.5, 4.5]))
    grids.write_vdb(tmp_path / "d.vdb", d, bounds)
    a = _load(tmp_path, [{"density": "d.npy", "bounds": {"min": list(bounds[0]),
                                                          "max": list(bounds[1])}}]).volumes[0]
    b = _load(tmp_path, [{"density": "d.vdb"}]).volumes[0]
    assert np.array_equal(a.density, b.density)
    for x, y in zip(a.grid_bounds, b.grid_bounds):
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-12)


@needs_vdb
def test_vdb_transform_places_the_grid(tmp_path):
    """A grid made with pyopenvdb: non-uniform voxel size, a translation, voxels at
    negative and offset indices; voxel (i, j, k) is centred at transform(i, j, k)."""
    vdb = grids.openvdb()
    g = vdb.FloatGrid()
    g.name = "smoke"
    t = vdb.createLinearTransform(1.0)
    t.scale((0.5, 0.25, 2.0))
    t.translate((1.0, -2.0, 3.0))
    g.transform = t
    acc = g.getAccessor()
    rng = np.random.default_rng(3)
    lo = np.array([-3, 2, 5])
    dense = rng.uniform(0.5, 1.0, (4, 3, 2)).astype(np.float32)
    for ijk in np.ndindex(*dense.shape):
        acc.setValueOn(tuple(int(x) for x in lo + ijk), float(dense[ijk]))
    vdb.write(str(tmp_path / "t.vdb"), grids=[g])
    v = _load(tmp_path, [{"density": "t.vdb", "density_grid": "smoke"}]).volumes[0]
    assert np.array_equal(v.density, dense)
    size, origin = np.array([0.5, 0.25, 2.0]), np.array([1.0, -2.0, 3.0])
    np.testing.assert_allclose(v.grid_bounds[0], origin + (lo - 0.5) * size, atol=1e-12)
    np.testing.assert_allclose(v.grid_bounds[1], origin + (lo + np.array(dense.shape) - 0.5) * size,
                               atol=1e-12)


@needs_vdb
def test_rotated_vdb_needs_bounds_and_takes_them(tmp_path):
    """A rotated transform cannot place the grid (one line asking for bounds); with
    ``bounds`` the transform is not read and the values load as they are."""
    from clscatter.errors import SceneError
    vdb = grids.openvdb()
    g = vdb.FloatGrid()
    g.name = "density"
    t = vdb.createLinearTransform(1.0)
    t.rotate(0.3, vdb.Axis.Y)
    g.transform = t
    acc = g.getAccessor()
    dense = np.arange(1, 9, dtype=np.float32).reshape(2, 2, 2)
    for ijk in np.ndindex(*dense.shape):
        acc.setValueOn(ijk, float(dense[ijk]))
    vdb.write(str(tmp_path / "r.vdb"), grids=[g])
    with pytest.raises(SceneError, match="give the volume's bounds"):
        _load(tmp_path, [{"density": "r.vdb"}])
    v = _load(tmp_path, [{"density": "r.vdb", "bounds": {"min": [0, 0, 0],
                                                         "max": [1, 1, 1]}}]).volumes[0]
    assert np.array_equal(v.density, dense)
    np.testing.assert_array_equal(v.grid_bounds[1], [1.0, 1.0, 1.0])


@needs_vdb
def test_sparse_vdb_with_tiles_and_empty_space(tmp_path):
    """Two blobs far apart with inactive space between them, and an active tile (a
    16^3 region of one value, stored above the leaves): the dense array holds the tile's
    value over its whole region and the background (0) in the empty space."""
    vdb = grids.openvdb()
    g = vdb.FloatGrid()
    g.name = "density"
    g.fill((32, 0, 0), (47, 15, 15), 0.75, True)          # a tile, aligned to 16^3
    acc = g.getAccessor()
    acc.setValueOn((0, 0, 0), 2.0)
    acc.setValueOn((2, 1, 3), 1.5)
    vdb.write(str(tmp_path / "s.vdb"), grids=[g])
    tiles = [x for x in vdb.read(str(tmp_path / "s.vdb"), "density").iterOnValues() if x["min"] != x["max"]]
    assert tiles, "the fill is stored as a tile"
    got = grids.load_density(tmp_path / "s.vdb", "k").values
    want = np.zeros((48, 16, 16), np.float32)
    want[32:48, 0:16, 0:16] = 0.75
    want[0, 0, 0], want[2, 1, 3] = 2.0, 1.5
    assert np.array_equal(got, want)


@needs_vdb
def test_shipped_smoke_vdb_equals_npy_and_the_tool_reproduces_them():
    sys.path.insert(0, str(REPO / "tools"))
    import make_smoke

    from clscatter.scene.builtin.smoke import DATA_DIR, SMOKE_BOUNDS
    npy = np.load(DATA_DIR / "smoke.npy")
    assert np.array_equal(make_smoke.plume(), npy)
    got = grids.load_density(DATA_DIR / "smoke.vdb", "k")
    assert np.array_equal(got.values, npy)
    np.testing.assert_allclose(got.bounds[0], SMOKE_BOUNDS["min"], atol=1e-12)
    np.testing.assert_allclose(got.bounds[1], SMOKE_BOUNDS["max"], atol=1e-12)


@needs_vdb
def test_openvdb_import_prints_nothing():
    """pyopenvdb (built for NumPy 1.x) prints an ABI warning on import: it is swallowed."""
    out = subprocess.run([sys.executable, "-c", "from clscatter.scene import grids; "
                          "assert grids.openvdb() is not None; print('ok')"],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok" and out.stderr == ""


@needs_vdb
def test_cli_convert_round_trip(tmp_path, capsys):
    from clscatter.cli import main
    d = np.random.default_rng(4).uniform(0, 1, (3, 4, 2)).astype(np.float32)
    np.save(tmp_path / "a.npy", d)
    assert main(["volume", "convert", str(tmp_path / "a.npy"), "-o", str(tmp_path / "a.vdb"),
                 "--bounds", "0", "0", "0", "3", "2", "1"]) == 0
    assert main(["volume", "convert", str(tmp_path / "a.vdb"), "-o", str(tmp_path / "b.npy")]) == 0
    assert np.array_equal(np.load(tmp_path / "b.npy"), d)
    assert "bounds = { min = [0, 0, 0], max = [3, 2, 1] }" in capsys.readouterr().out


BAD = [
    ("neg.npy", -1.0, "volumes[0].density", "must be finite and >= 0"),
    ("nan.npy", float("nan"), "volumes[0].density", "must be finite and >= 0"),
    ("missing.npy", None, "volumes[0].density", "not found"),
]


@pytest.mark.parametrize("name, bad, key, text", BAD, ids=[b[0] for b in BAD])
def test_bad_density_files(tmp_path, name, bad, key, text):
    if bad is not None:
        d = np.ones((3, 3, 3))
        d[1, 2, 0] = bad
        np.save(tmp_path / name, d)
    with pytest.raises(SceneError) as e:
        _load(tmp_path, [{"density": name, "bounds": BOX}])
    assert e.value.key == key and text in str(e.value) and "\n" not in str(e.value)
    if bad is not None:
        assert "(1, 2, 0)" in str(e.value)


def test_density_key_errors(tmp_path):
    np.save(tmp_path / "d.npy", np.ones((2, 2, 2)))
    cases = [({"density": "d.npy"}, "volumes[0].bounds"),                      # .npy: no place
             ({"density": "d.npy", "bounds": BOX, "density_grid": "x"}, "volumes[0].density_grid"),
             ({"density": "d.npy", "bounds": BOX, "ior": 1.2}, "volumes[0].ior"),
             ({"density": "d.txt", "bounds": BOX}, "volumes[0].density")]
    (tmp_path / "d.txt").write_text("1 2 3")
    for vol, key in cases:
        with pytest.raises(SceneError) as e:
            _load(tmp_path, [vol])
        assert e.value.key == key and "\n" not in str(e.value), (vol, str(e.value))


def test_at_most_eight_density_volumes(tmp_path):
    """The device merges the boxes along a ray in registers: the loader refuses a ninth
    density volume, and the limit is the kernels' (density.h)."""
    np.save(tmp_path / "d.npy", np.ones((2, 2, 2)))
    vol = {"density": "d.npy", "bounds": BOX}
    assert len(_load(tmp_path, [vol] * 8).density_volumes()) == 8
    with pytest.raises(SceneError) as e:
        _load(tmp_path, [vol] * 9)
    assert e.value.key == "volumes[8].density"
    header = (REPO / "cl_kernels" / "shared" / "density.h").read_text()
    assert f"#define DENSITY_MAX_GRIDS {grids.MAX_DENSITY_VOLUMES}\n" in header


@needs_vdb
def test_unknown_vdb_grid_name(tmp_path):
    grids.write_vdb(tmp_path / "d.vdb", np.ones((2, 2, 2)), None, name="density")
    with pytest.raises(SceneError) as e:
        _load(tmp_path, [{"density": "d.vdb", "density_grid": "temperature"}])
    assert e.value.key == "volumes[0].density_grid"
    assert "no grid named 'temperature'" in str(e.value) and "'density'" in str(e.value)


def test_vdb_without_pyopenvdb_names_the_package(tmp_path, monkeypatch):
    (tmp_path / "d.vdb").write_bytes(b"\x20BDV")
    monkeypatch.setattr(grids, "_OPENVDB", [None])
    with pytest.raises(SceneError) as e:
        _load(tmp_path, [{"density": "d.vdb"}])
    assert e.value.key == "volumes[0].density" and "python3-openvdb" in str(e.value)


def test_cli_bad_density_is_one_line(tmp_path, capsys):
    from clscatter.cli import main
    np.save(tmp_path / "neg.npy", -np.ones((2, 2, 2)))
    text = (tmp_path / "s.toml")
    text.write_text('[camera]\norigin = [0.0, 1.0, 4.0]\ntarget = [0.0, 0.5, 0.0]\n'
                    '[[volumes]]\ndensity = "neg.npy"\n'
                    'bounds = { min = [0.0, 0.0, 0.0], max = [1.0, 1.0, 1.0] }\n')
    assert main(["check", str(text)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "volumes[0].density" in err and "Traceback" not in err


# ---- the planner ------------------------------------------------------------------------

def test_auto_picks_raymarch_for_smoke_and_voxel_where_light_bends(tmp_path):
    from clscatter.pipeline.planner import DROPS_LIGHT, plan
    np.save(tmp_path / "d.npy", np.ones((2, 2, 2)))
    np.save(tmp_path / "n.npy", np.full((2, 2, 2), 1.1))
    smoke = _load(tmp_path, [{"density": "d.npy", "bounds": BOX, "sigma_s": 1.0}])
    passes, notes = plan(smoke, "auto")
    assert [p.method for p in passes] == ["raymarch"], notes
    bent = _load(tmp_path, [{"density": "d.npy", "grid": "n.npy", "bounds": BOX, "sigma_s": 1.0}])
    assert [p.method for p in plan(bent, "auto")[0]] == ["voxel"]
    for method in ("epipolar", "lsg", "vpm"):
        _, notes = plan(smoke, method)
        dropped = [n for n in notes if "volumes[0].density" in n]
        assert len(dropped) == 1 and dropped[0].endswith(DROPS_LIGHT), notes
    for method in ("raymarch", "voxel"):
        assert not [n for n in plan(smoke, method)[1] if "density" in n]


# ---- renders ----------------------------------------------------------------------------

def _render(scene, method, **params):
    scene.render.params = {method: params} if params else {}
    return clscatter.render(scene, method=method, show_progress=False)


def test_constant_density_equals_homogeneous_medium_raymarch(tmp_path):
    """Density 2 with sigma (0.6, 0.15) per unit density against a [medium] of (1.2, 0.3)
    bounded to the same box, a floor below lit through it: medium and surface alike."""
    np.save(tmp_path / "c.npy", np.full((5, 4, 6), 2.0))
    floor = {"materials": {"f": {"type": "diffuse", "albedo": 0.5}},
             "objects": [{"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
                          "edge_v": [0.0, 0.0, 4.0], "material": "f"}]}
    grid = _load(tmp_path, [{"density": "c.npy", "bounds": BOX, "sigma_s": [0.6, 0.5, 0.4],
                             "sigma_a": 0.15}], **floor)
    hom = _load(tmp_path, [], medium={"sigma_s": [1.2, 1.0, 0.8], "sigma_a": 0.3, "bounds": BOX},
                **floor)
    for s in (grid, hom):
        s.camera.width, s.camera.height, s.camera.spp = 40, 30, 4
    a, b = _render(grid, "raymarch"), _render(hom, "raymarch")
    assert_matches_reference(a.image, b.image, 4e-7, "constant density, raymarch", mean_tol=2e-4)
    np.testing.assert_allclose(a.surface, b.surface, rtol=2e-5, atol=1e-7)


def test_constant_density_equals_constant_coefficient_volume_voxel(tmp_path):
    """The same with ``voxel``: a density volume of 2 x (0.6, 0.15) against a grid volume
    (index 1 everywhere) of (1.2, 0.3): the same voxel fields, the same image."""
    np.save(tmp_path / "c.npy", np.full((5, 4, 6), 2.0))
    np.save(tmp_path / "one.npy", np.ones((5, 4, 6)))
    grid = _load(tmp_path, [{"density": "c.npy", "bounds": BOX, "sigma_s": 0.6, "sigma_a": 0.15}])
    coef = _load(tmp_path, [{"grid": "one.npy", "bounds": BOX, "sigma_s": 1.2, "sigma_a": 0.3}])
    quick = {"resolution": 24, "photons": 4096}
    a, b = _render(grid, "voxel", **quick), _render(coef, "voxel", **quick)
    assert float(b.image.max()) > 0
    assert_matches_reference(a.image, b.image, 1e-10, "constant density, voxel", mean_tol=1e-6)


@pytest.mark.parametrize("depth", [0.01, 0.1, 1.0, 3.0, 10.0])
def test_absorbing_ramp_against_closed_form(tmp_path, depth):
    """A wall lit by a point light behind a box of absorbing smoke (sigma_s 0), density a
    linear ramp along x: each pixel is the wall's unattenuated radiance times
    exp(-kappa F / |d_x|), F the ramp's closed-form integral across the box (as in
    tests/test_density_kernels.py) and d the pixel's ray (the camera looks along -x with a
    1 degree field of view, so every ray crosses both x faces)."""
    nx, h = 8, 2.0 / 8
    v = 0.5 + 0.25 * np.arange(nx)
    np.save(tmp_path / "ramp.npy", np.broadcast_to(v[:, None, None], (nx, 2, 3)).copy())
    F = h / 2 * v[0] + h * np.sum((v[1:] + v[:-1]) / 2) + h / 2 * v[-1]
    base = {"camera": {"origin": [6.0, 0.0, 0.0], "target": [0.0, 0.0, 0.0], "fov": 1.0,
                       "resolution": [8, 6], "spp": 1},
            "lights": [{"type": "point", "position": [-2.0, 0.2, 1.5], "intensity": 5.0}],
            "materials": {"w": {"type": "diffuse", "albedo": 0.8}},
            "objects": [{"shape": "quad", "origin": [-3.0, -2.0, -2.0], "edge_u": [0.0, 4.0, 0.0],
                         "edge_v": [0.0, 0.0, 4.0], "material": "w"}]}
    vol = {"density": "ramp.npy", "bounds": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]},
           "sigma_a": depth / F}
    smoke = scene_from_dict({**base, "volumes": [vol]}, tmp_path)
    clear = scene_from_dict({**base, "volumes": [{**vol, "sigma_a": 0.0}]}, tmp_path)
    a, b = _render(smoke, "raymarch"), _render(clear, "raymarch")
    # 1 / |d_x| of a ray through the image plane at (x, y), the plane 1 unit along -x
    cam = smoke.camera
    tx = np.tan(np.radians(cam.fov) / 2)
    ty = tx * cam.height / cam.width

    def inv_dx(sx, sy):
        return np.sqrt(1 + (sx * tx) ** 2 + (sy * ty) ** 2)

    def nearest(e):        # |coordinate| nearest 0 and farthest from it over each pixel
        return np.where(e[:-1] * e[1:] <= 0, 0.0, np.minimum(abs(e[:-1]), abs(e[1:])))

    def farthest(e):
        return np.maximum(abs(e[:-1]), abs(e[1:]))

    ex = np.linspace(-1, 1, cam.width + 1)               # pixel edges, -1 .. 1
    ey = np.linspace(-1, 1, cam.height + 1)
    lo = inv_dx(nearest(ex)[None, :], nearest(ey)[:, None])   # over each pixel's footprint
    hi = inv_dx(farthest(ex)[None, :], farthest(ey)[:, None])
    ratio = (a.image / b.image)[..., 0]
    assert float(b.image.min()) > 0 and float(np.max(a.medium)) == 0.0
    # each pixel's one sample lies in its footprint: exp(-depth / |d_x|) between the ends
    tol = 1e-6
    assert np.all(ratio <= np.exp(-depth * lo) * (1 + tol)), f"optical depth {depth}: too bright"
    assert np.all(ratio >= np.exp(-depth * hi) * (1 - tol)), f"optical depth {depth}: too dark"
    assert np.allclose(a.image[..., 0], a.image[..., 2], rtol=1e-6)       # grey absorption


# ---- raymarch against a NumPy quadrature of the same integrals --------------------------

def _blob(shape) -> np.ndarray:
    """A smooth lumpy density (0 .. ~3), deterministic."""
    c = [np.linspace(-1, 1, n) for n in shape]
    x, y, z = np.meshgrid(*c, indexing="ij")
    return (2.5 * np.exp(-2.0 * ((x - 0.2) ** 2 + y ** 2 + (z + 0.1) ** 2))
            + 0.5 * (1 + np.sin(3 * x + 2 * z)) * (y + 1) / 2)


class Reference:
    """Single scattering of direct light and direct light on a diffuse floor through density
    grids and a bounded homogeneous medium, in float64 world units, by quadrature: the
    density sampled by its own trilinear code (``ref_density`` of the kernel tests), the
    optical depths inside the in-scattering integral by the midpoint rule on ``n_tau``
    steps, that integral by the midpoint rule on ``n_seg`` steps, and the floor's two
    optical depths piece by piece (``ref_integral``, ``ref_hom_length``: exact)."""

    def __init__(self, scene, n_seg=300, n_tau=300):
        from test_density_kernels import ref_density, ref_hom_length, ref_integral
        self.ref_density, self.ref_integral, self.ref_hom = ref_density, ref_integral, ref_hom_length
        self.s, self.n_seg, self.n_tau = scene, n_seg, n_tau
        self.vols = scene.density_volumes()
        self.med = scene.medium if scene.has_medium() else None
        self.g = scene.medium.g if scene.medium is not None else 0.0

    def _inside(self, p, lo, hi):
        return np.all((p >= lo) & (p <= hi), axis=-1)

    def coefficients(self, p):
        """(sigma_s, kappa) at points p (..., 3), rgb."""
        shape = p.shape[:-1]
        flat = p.reshape(-1, 3)
        ss, kap = np.zeros((len(flat), 3)), np.zeros((len(flat), 3))
        any_box = np.zeros(len(flat), bool)
        for v in self.vols:
            d = self.ref_density(v.density, *v.grid_bounds, flat)[:, None]
            ss += d * v.sigma_s
            kap += d * (v.sigma_s + v.sigma_a)
            any_box |= self._inside(flat, *v.grid_bounds)
        if self.med is not None:
            m = (~any_box) & self._inside(flat, *self.med.bounds)
            ss[m], kap[m] = self.med.sigma_s, self.med.kappa
        return ss.reshape(*shape, 3), kap.reshape(*shape, 3)

    def depth(self, a, b):
        """Optical depth (rgb) of the straight paths a -> b (arrays (..., 3))."""
        u = (np.arange(self.n_tau) + 0.5) / self.n_tau
        pts = a[..., None, :] + u[:, None] * (b - a)[..., None, :]
        _, kap = self.coefficients(pts)
        return kap.sum(axis=-2) * (np.linalg.norm(b - a, axis=-1) / self.n_tau)[..., None]

    def exact_depth(self, a, b):
        """Optical depth (rgb) of the path a -> b, piece by piece."""
        L = float(np.linalg.norm(b - a))
        d = (b - a) / L
        tau = np.zeros(3)
        for v in self.vols:
            tau += (v.sigma_s + v.sigma_a) * self.ref_integral(
                v.density.astype(np.float64), *v.grid_bounds, a, d, 0.0, L)
        if self.med is not None:
            tau += self.med.kappa * self.ref_hom(*self.med.bounds,
                                                 [v.grid_bounds for v in self.vols], a, d, 0.0, L)
        return tau

    def arrival(self, light, x):
        """(irradiance on a facing surface, unit direction to the light) at points x."""
        to = light.position - x
        d2 = np.sum(to * to, axis=-1)
        wi = to / np.sqrt(d2)[..., None]
        E = light.power / d2[..., None]
        if light.type == "spot":
            ok = np.sum(-wi * light.direction, axis=-1) >= np.cos(np.radians(light.cutoff_angle))
            E = E * ok[..., None]
        return E, wi

    def segment(self, a, b):
        """Radiance scattered towards a along the segment a -> b (weight 1)."""
        L = np.linalg.norm(b - a)
        w = (b - a) / L
        t = (np.arange(self.n_seg) + 0.5) / self.n_seg * L
        x = a + t[:, None] * w
        ss, kap = self.coefficients(x)
        T_view = np.exp(-(np.cumsum(kap, axis=0) - 0.5 * kap) * (L / self.n_seg))
        out = np.zeros(3)
        for light in self.s.lights:
            E, wi = self.arrival(light, x)
            T_light = np.exp(-self.depth(x, np.broadcast_to(light.position, x.shape)))
            cos = np.sum(wi * w, axis=-1)          # light travels -wi, the camera is at -w
            ph = (1 - self.g ** 2) / (4 * np.pi * (1 + self.g ** 2 - 2 * self.g * cos) ** 1.5)
            out += np.sum(ss * E * T_light * T_view * ph[:, None], axis=0) * (L / self.n_seg)
        return out

    def floor_point(self, p, eye, albedo, lift=0.0):
        """Radiance of the diffuse floor point p (normal +y) seen from eye; its shadow
        rays leave ``lift`` above it (the engine's offset along the normal)."""
        T_view = np.exp(-self.exact_depth(eye, p))
        out = np.zeros(3)
        for light in self.s.lights:
            E, wi = self.arrival(light, p[None])
            cos = max(float(wi[0, 1]), 0.0)
            start = p + np.array([0.0, lift, 0.0])
            out += E[0] * cos * np.exp(-self.exact_depth(start, light.position))
        return albedo / np.pi * T_view * out


def _smoke_scene(tmp_path, light, medium=None):
    np.save(tmp_path / "blob.npy", _blob((6, 5, 7)))
    data = {"camera": {"origin": [0.0, 0.9, 3.2], "target": [0.0, 0.5, 0.0], "fov": 34.0,
                       "resolution": [12, 9], "spp": 1},
            "lights": [light],
            "materials": {"f": {"type": "diffuse", "albedo": 0.6}},
            "objects": [{"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
                         "edge_v": [0.0, 0.0, 4.0], "material": "f"}],
            "volumes": [{"density": "blob.npy", "bounds": BOX, "sigma_s": [1.5, 1.2, 1.0],
                         "sigma_a": 0.3}]}
    if medium is not None:
        data["medium"] = medium
    else:
        data["medium"] = {"g": 0.3}                   # no medium: only the phase's g
    return scene_from_dict(data, tmp_path)


# light, scene medium, relMSE bounds (medium, surface): 2x the measured 1.8e-9, 6.2e-10
# and 2.1e-6, 2.9e-10 (the fog case's medium term: both quadratures' midpoint error where
# sigma_s jumps at the smoke box's faces, from the fog's to the smoke's)
CASES = {
    "point": ({"type": "point", "position": [0.6, 2.0, 0.3], "intensity": 6.0}, None,
              (4e-9, 1.3e-9)),
    "spot_in_fog": ({"type": "spot", "position": [0.4, 2.4, 0.5], "target": [0.0, 0.4, 0.0],
                     "intensity": 9.0, "cutoff_angle": 75.0},
                    {"sigma_s": 0.08, "sigma_a": 0.02, "g": -0.2,
                     "bounds": {"min": [-0.9, 0.0, -0.8], "max": [0.8, 1.4, 0.9]}},
                    (4.2e-6, 6e-10)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_raymarch_against_numpy_quadrature(tmp_path, engine, case):
    """The image of ``raymarch`` (256 steps) against the reference, per pixel, on the
    view rays the render used: the medium term from its view segments (their ends and
    their pixel; depth-0 segments carry weight 1/spp, nothing before them attenuates),
    the surface term from its diffuse hits (hit point and pixel), everything else
    recomputed. The spot's cone covers the fog box, so no edge crosses a segment."""
    from clscatter.device import structs
    from clscatter.estimators.density_march import density_scene, upload
    from clscatter.transport.prepared import prepare_scene
    from clscatter.transport.view_paths import trace_view_paths

    light, medium, (bound_medium, bound_surface) = CASES[case]
    scene = _smoke_scene(tmp_path, light, medium)
    res = _render(scene, "raymarch", steps=256)
    ps = prepare_scene(scene, engine)
    dens = upload(ps)
    paths = trace_view_paths(density_scene(ps, dens), show_progress=False, keep_hits=True,
                             program="density_view")
    try:
        segs = paths.segments
        hits = engine.read(paths.hits.buf, paths.hits.count, structs.DIFFUSE_HIT)
    finally:
        paths.release()
        dens.release()
        ps.release()
    f = ps.frame

    def world(p):
        return np.asarray(p[..., :3], np.float64) * f.scale + f.centre
    cam = scene.camera
    ref = Reference(scene)
    medium_ref = np.zeros((cam.height * cam.width, 3))
    assert len(segs) > 30 and np.all(segs["depth"] == 0)
    np.testing.assert_allclose(segs["weight"][:, :3], 1.0 / cam.spp, rtol=1e-6)
    for sg in segs:
        medium_ref[sg["pixel"]] += ref.segment(world(sg["a"]), world(sg["b"])) / cam.spp
    surface_ref = np.zeros_like(medium_ref)
    eye = np.asarray(cam.origin, np.float64)
    lift = RAY_EPS * f.scale                       # view_paths.cl: shadow rays leave above
    for h in hits:
        surface_ref[h["pixel"]] += ref.floor_point(world(h["p"]), eye, 0.6, lift) / cam.spp
    shape = (cam.height, cam.width, 3)
    assert_matches_reference(res.medium, medium_ref.reshape(shape), bound_medium,
                             f"{case}: medium")
    assert_matches_reference(res.surface, surface_ref.reshape(shape), bound_surface,
                             f"{case}: surface")
    # the floor lies in the smoke's shadow: some of its points keep under half their light
    clear = Reference(scene)
    clear.vols = []
    kept = [ref.floor_point(world(h["p"]), eye, 0.6)[0] / clear.floor_point(world(h["p"]), eye, 0.6)[0]
            for h in hits]
    print(f"{case}: darkest floor point keeps {min(kept):.3f} of its light")
    assert min(kept) < 0.5


def test_builtin_smoke_plume_renders_with_a_shadow():
    """``builtin:smoke_plume`` at 80 x 60, 1 spp: finite, the smoke glows, and the floor
    keeps far less light in the plume's shadow than the same scene with a clear volume."""
    opts = ["camera.resolution=[80, 60]", "camera.spp=1"]
    smoke = clscatter.load("builtin:smoke_plume", opts)
    clear = clscatter.load("builtin:smoke_plume", opts + ["volumes[0].sigma_s=0.0",
                                                          "volumes[0].sigma_a=0.0"])
    a = clscatter.render(smoke, show_progress=False)
    b = clscatter.render(clear, show_progress=False)
    assert a.stats["method"] == "raymarch"
    assert np.all(np.isfinite(a.image)) and float(a.medium.max()) > 0.05
    lit = b.surface[..., 1] > 0.2 * float(b.surface[..., 1].max())
    ratio = a.surface[..., 1][lit] / b.surface[..., 1][lit]
    assert ratio.max() <= 1.0 + 1e-6
    assert ratio.min() < 0.45, f"the darkest shadowed floor pixel keeps {ratio.min():.2f}"
    assert float(np.mean(ratio < 0.9)) > 0.01


@pytest.mark.slow
@pytest.mark.parametrize("method", ["raymarch", "voxel"])
def test_density_renders_clean_under_oclgrind(method, tmp_path):
    """The density kernels (density_view, density_march, voxel's shadow rays through the
    grids) under Oclgrind, as tests/test_oclgrind.py runs every method: the built-in smoke
    plume at 12 x 9, 1 spp; any report of an invalid access or a race fails."""
    import os
    import shutil

    from setup_installs import setup_installs_here
    from test_oclgrind import NO_OCLGRIND, REPORTS, TINY
    if shutil.which("oclgrind") is None:
        if setup_installs_here():
            pytest.fail(NO_OCLGRIND, pytrace=False)
        pytest.skip(NO_OCLGRIND)
    out = tmp_path / "img.npy"
    args = ["oclgrind", "--data-races", sys.executable, "-m", "clscatter", "render",
            "builtin:smoke_plume", "--method", method, "--no-progress", "-o", str(out)]
    for kv in TINY:
        args += ["--set", kv]
    env = {**os.environ, "CLSCATTER_CACHE_DIR": str(tmp_path / "cache")}
    env.pop("CLSCATTER_DEVICE", None)
    r = subprocess.run(args, capture_output=True, text=True, timeout=900, env=env)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-3000:]
    found = [line for line in log.splitlines() if any(k in line for k in REPORTS)]
    assert not found, "\n".join(found[:20])
    img = np.load(out)
    assert img.shape == (9, 12, 3) and np.isfinite(img).all() and img.max() > 0


def test_density_marching_is_deterministic(tmp_path, engine):
    """The density build places every sample at the middle of its stratum: the same view
    segments marched with two different render seeds give the same radiance to the bit,
    a point light inside the smoke included (its glow has no noise); the jittered
    homogeneous build does not (the comparison can fail)."""
    from clscatter.estimators.density_march import density_scene, upload
    from clscatter.estimators.segment_march import march_segments
    from clscatter.io.stats import Stats
    from clscatter.transport.prepared import prepare_scene
    from clscatter.transport.view_paths import trace_view_paths

    inside = {"type": "point", "position": [0.0, 0.7, 0.0], "intensity": 2.0}
    scene = _smoke_scene(tmp_path, inside, {"sigma_s": 0.05, "sigma_a": 0.01, "g": 0.0,
                                            "bounds": {"min": [-1.0, 0.0, -1.0],
                                                       "max": [1.0, 1.5, 1.0]}})
    ps = prepare_scene(scene, engine)
    dens = upload(ps)
    dps = density_scene(ps, dens)
    paths = trace_view_paths(dps, show_progress=False, program="density_view")
    plain = trace_view_paths(ps, show_progress=False)
    try:
        out = {}
        for seed in (0, 5):
            scene.render.seed = seed
            out["density", seed] = march_segments(dps, paths.device, 32, Stats(), False,
                                                  program="density_march")
            out["plain", seed] = march_segments(ps, plain.device, 32, Stats(), False)
    finally:
        paths.release()
        plain.release()
        dens.release()
        ps.release()
    assert np.all(np.isfinite(out["density", 0])) and float(out["density", 0].max()) > 0
    assert np.array_equal(out["density", 0], out["density", 5])
    assert not np.array_equal(out["plain", 0], out["plain", 5])
