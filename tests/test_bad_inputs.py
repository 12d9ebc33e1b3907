"""Every bad input gets the contract's answer: exit status 2, exactly one line on stderr
that names the key or file, no traceback, and no output file afterwards.

The cases run the real CLI entry point in-process (``clscatter.cli.main``), so an
unexpected exception fails the test with its traceback instead of being hidden.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clscatter.cli import main

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--set", "camera.resolution=[8,6]", "--set", "camera.spp=1", "--no-progress"]


def _scene_file(tmp: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp / name
    p.write_text(text)
    return p


BASE_TOML = """
[camera]
origin = [0.0, 1.0, 5.0]
target = [0.0, 0.5, 0.0]
resolution = [8, 6]
spp = 1
[medium]
sigma_s = 0.1
sigma_a = 0.05
bounds = { min = [-3.0, -1.0, -3.0], max = [3.0, 3.0, 3.0] }
[[lights]]
type = "point"
position = [0.0, 2.0, 0.0]
intensity = 5.0
[[objects]]
shape = "sphere"
center = [0.0, 0.5, 0.0]
radius = 0.4
material = { type = "diffuse" }
"""

# (--set override, text the one-line message must contain)
SCENE_CASES = [
    ("camera.fov=0", "camera.fov"), ("camera.fov=180", "camera.fov"), ('camera.fov="wide"', "camera.fov"),
    ("camera.fov=nan", "camera.fov"), ("camera.fov=inf", "camera.fov"),
    ("camera.resolution=[0,10]", "camera.resolution"), ("camera.resolution=[10]", "camera.resolution"),
    ("camera.resolution=[-4,5]", "camera.resolution"), ("camera.resolution=[4.5,5]", "camera.resolution"),
    ("camera.spp=0", "camera.spp"), ("camera.spp=-1", "camera.spp"), ("camera.spp=1.5", "camera.spp"),
    ("camera.spp=true", "camera.spp"),
    ("camera.origin=[0,0]", "camera.origin"), ("camera.origin=[nan,0,0]", "camera.origin"),
    ("camera.origin=[inf,0,0]", "camera.origin"), ('camera.origin="here"', "camera.origin"),
    ("camera.target=[0.0,1.0,5.0]", "camera.target"), ("camera.up=[0,0,0]", "camera.up"),
    ('camera.fov_axis="z"', "camera.fov_axis"), ("camera.zoom=2", "camera.zoom"),
    ("medium.sigma_s=-1", "medium.sigma_s"), ("medium.sigma_a=nan", "medium.sigma_a"),
    ("medium.sigma_s=[1,2]", "medium.sigma_s"), ("medium.sigma_s=inf", "medium.sigma_s"),
    ("medium.g=1", "medium.g"), ("medium.g=-1", "medium.g"), ("medium.g=2", "medium.g"),
    ("medium.g=nan", "medium.g"),
    ("medium.bounds.min=[5,5,5]", "medium.bounds"), ("medium.density=1", "medium.density"),
    ('lights[0].type="area"', "lights[0].type"), ("lights[0].intensity=-1", "lights[0].intensity"),
    ("lights[0].intensity=inf", "lights[0].intensity"), ("lights[0].intensity=nan", "lights[0].intensity"),
    ("lights[0].position=[0,0]", "lights[0].position"), ("lights[0].colour=1", "lights[0].colour"),
    ('lights[0].type="spot"', "lights[0]"),
    ('lights[0].type="directional"', "lights[0]"),
    ("objects[0].radius=0", "objects[0].radius"), ("objects[0].radius=-1", "objects[0].radius"),
    ("objects[0].radius=nan", "objects[0].radius"), ('objects[0].shape="cone"', "objects[0].shape"),
    ('objects[0].material="nope"', "objects[0].material"), ("objects[0].material=3", "objects[0].material"),
    ('objects[0].material.type="glassy"', "objects[0].material.type"),
    ("objects[0].material.albedo=-0.5", "objects[0].material.albedo"),
    ("objects[0].center=[0,0]", "objects[0].center"), ("objects[0].subdivisions=99", "objects[0].subdivisions"),
    ("render.method=bogus", "render.method"), ("render.max_depth=-1", "render.max_depth"),
    ("render.seed=-1", "render.seed"), ("render.seed=1.5", "render.seed"),
    ("render.lsg.radius=-0.01", "render.lsg.radius"), ("render.lsg.light_rays=0", "render.lsg.light_rays"),
    ("render.lsg.radius=nan", "render.lsg.radius"), ("render.lsg.radius=inf", "render.lsg.radius"),
    ("render.raymarch.steps=0", "render.raymarch.steps"), ("render.raymarch.stepz=3", "render.raymarch.stepz"),
    ("render.raymarch.steps=1.5", "render.raymarch.steps"), ("render.raymarch.steps=true", "render.raymarch.steps"),
    ("render.vpm.knn=1", "render.vpm.knn"), ('render.epipolar.lookup="x"', "render.epipolar.lookup"),
    ("render.epipolar.svd_samples=2", "render.epipolar.svd_samples"),
    ("render.epipolar.light_rays=1", "render.epipolar.light_rays"),
    ("render.vpm.dx=0", "render.vpm.dx"), ("render.bogus=1", "render.bogus"),
    ("render.nope.x=1", "render.nope"),
    ("render.lsg=3", "render.lsg"),
    # beyond float32, in which the device computes (such values gave black images)
    ("lights[0].intensity=1e39", "lights[0].intensity"), ("medium.sigma_s=1e300", "medium.sigma_s"),
    ("camera.origin=[1e39,0,0]", "camera.origin"), ("medium.sigma_a=[0,0,-1e39]", "medium.sigma_a"),
    ("lights[0].intensity=3e38", "lights[0].intensity"),    # float32 until divided by 0.8^2
    ('volumes=[{shape="quad",origin=[0,0,0],edge_u=[1,0,0],edge_v=[0,1,0],ior=1.2}]',
     "volumes[0].shape: a quad encloses nothing"),
]


@pytest.mark.parametrize("override, expect", SCENE_CASES, ids=[c[0] for c in SCENE_CASES])
def test_bad_scene_values(override, expect, tmp_path, capsys):
    scene = _scene_file(tmp_path, BASE_TOML)
    out = tmp_path / "out.png"
    _expect_error(capsys, ["render", str(scene), "-o", str(out), "--no-progress", "--set", override],
                  expect, [out])


def _expect_error(capsys, argv, expect, must_not_exist=()):
    code = main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, f"exit {code}: {err}"
    assert len(lines) == 1, f"expected one line, got: {err!r}"
    assert expect in lines[0], f"{expect!r} not in {lines[0]!r}"
    assert "Traceback" not in err
    for p in must_not_exist:
        assert not Path(p).exists(), f"{p} was written"
    return lines[0]


def _files(tmp: Path) -> dict[str, Path]:
    (tmp / "adir").mkdir()
    (tmp / "notes.txt").write_text("x")
    (tmp / "empty.toml").write_text("")
    (tmp / "bad.toml").write_text("[camera\norigin = ")
    (tmp / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    (tmp / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    (tmp / "garbage.obj").write_bytes(b"\x00\x01\x02 not a mesh")
    (tmp / "img.npy").write_bytes(b"no")
    np.save(tmp / "small.npy", np.zeros((2, 2, 3), np.float32))
    np.save(tmp / "big.npy", np.zeros((3, 3, 3), np.float32))
    np.save(tmp / "nan.npy", np.where(np.eye(2)[..., None] > 0, np.nan, 1.0).repeat(3, -1)
            .astype(np.float32))
    np.save(tmp / "inf.npy", np.full((2, 2, 3), np.inf, np.float32))
    np.save(tmp / "grid2d.npy", np.ones((4, 4)))
    np.save(tmp / "gridneg.npy", -np.ones((4, 4, 4)))
    return {p.name: p for p in tmp.iterdir()}


def _mesh_scene(tmp: Path, file: str) -> Path:
    return _scene_file(tmp, BASE_TOML.replace(
        'shape = "sphere"\ncenter = [0.0, 0.5, 0.0]\nradius = 0.4',
        f'shape = "mesh"\nfile = "{file}"'), f"mesh_{file}.toml")


def _grid_scene(tmp: Path, file: str) -> Path:
    return _scene_file(tmp, BASE_TOML + f'[[volumes]]\ngrid = "{file}"\n'
                       'bounds = {{ min = [-1.0, 0.0, -1.0], max = [1.0, 1.0, 1.0] }}\n'.replace("{{", "{").replace("}}", "}"),
                       f"grid_{file}.toml")


# (argv builder over the temp folder, text the message must contain, outputs that must not exist)
def _cli_cases():
    def scene(t):
        return str(_scene_file(t, BASE_TOML))
    return [
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--exposure", "nan"], "--exposure", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--exposure", "inf"], "--exposure", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--exposure", "-inf"], "--exposure", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--exposure", "abc"], "--exposure", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--method", ""], "render.method", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--method", "fastest"], "render.method", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--max-memory", "abc"], "--max-memory", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--max-memory", "0"], "--max-memory", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--max-memory", "-5G"], "--max-memory", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--device", "no-such-device-xyz"],
         "no-such-device-xyz", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.txt")], "o.txt", ["o.txt"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o")], "o", ["o"]),
        (lambda t: ["render", scene(t), "-o", str(t / "adir")], "adir", []),
        (lambda t: ["render", scene(t), "-o", str(t / "missing" / "o.png")], "missing", []),
        (lambda t: ["render", scene(t), "-o", ""], "-o", []),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "-o", str(t / "adir")], "adir", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "-o", str(t / "o.png")], "o.png", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--stats", str(t / "s.txt")], "s.txt", ["o.png", "s.txt"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--stats", str(t / "adir")], "adir", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--stats", str(t / "nope" / "s.json")], "nope",
         ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--stats", str(t / "o.png")], "o.png", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--frobnicate"], "--frobnicate", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--set", "camera.fov"], "camera.fov", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--set", "camera.resolution=[64,"],
         "camera.resolution", ["o.png"]),
        (lambda t: ["render", scene(t), "-o", str(t / "o.png"), "--set", "lights[9].intensity=1"], "lights[9]",
         ["o.png"]),
        (lambda t: ["render", str(t / "nothere.toml"), "-o", str(t / "o.png")], "nothere.toml", ["o.png"]),
        (lambda t: ["render", str(t / "adir"), "-o", str(t / "o.png")], "adir", ["o.png"]),
        (lambda t: ["render", str(t / "bad.toml"), "-o", str(t / "o.png")], "bad.toml", ["o.png"]),
        (lambda t: ["render", str(t / "empty.toml"), "-o", str(t / "o.png")], "camera", ["o.png"]),
        (lambda t: ["render", str(t / "notes.txt"), "-o", str(t / "o.png")], "notes.txt", ["o.png"]),
        (lambda t: ["render", "builtin:nope", "-o", str(t / "o.png")], "builtin:nope", ["o.png"]),
        (lambda t: ["render", str(_mesh_scene(t, "nan.obj")), "-o", str(t / "o.png")], "nan.obj", ["o.png"]),
        (lambda t: ["render", str(_mesh_scene(t, "flat.obj")), "-o", str(t / "o.png")], "objects[0]", ["o.png"]),
        (lambda t: ["render", str(_mesh_scene(t, "garbage.obj")), "-o", str(t / "o.png")], "garbage.obj", ["o.png"]),
        (lambda t: ["render", str(_mesh_scene(t, "absent.obj")), "-o", str(t / "o.png")], "absent.obj", ["o.png"]),
        (lambda t: ["render", str(_mesh_scene(t, "adir")), "-o", str(t / "o.png")], "adir", ["o.png"]),
        (lambda t: ["render", str(_grid_scene(t, "grid2d.npy")), "-o", str(t / "o.png")], "grid2d.npy", ["o.png"]),
        (lambda t: ["render", str(_grid_scene(t, "gridneg.npy")), "-o", str(t / "o.png")], "gridneg.npy", ["o.png"]),
        (lambda t: ["render", str(_grid_scene(t, "nogrid.npy")), "-o", str(t / "o.png")], "nogrid.npy", ["o.png"]),
        (lambda t: ["render", str(_grid_scene(t, "img.npy")), "-o", str(t / "o.png")], "img.npy", ["o.png"]),
        (lambda t: ["diff", str(t / "small.npy"), str(t / "big.npy")], "small.npy", []),
        (lambda t: ["diff", str(t / "small.npy"), str(t / "nothere.exr")], "nothere.exr", []),
        (lambda t: ["diff", str(t / "nan.npy"), str(t / "small.npy")], "nan.npy: 2 pixels", []),
        (lambda t: ["diff", str(t / "small.npy"), str(t / "inf.npy")], "inf.npy: 4 pixels", []),
        (lambda t: ["diff", str(t / "img.npy"), str(t / "small.npy")], "img.npy", []),
        (lambda t: ["diff", str(t / "small.npy"), str(t / "small.npy"), "--heatmap", str(t / "h.txt")], "h.txt",
         ["h.txt"]),
        (lambda t: ["scenes", "--dump", "nope"], "nope", []),
        (lambda t: ["check", str(t / "nothere.toml")], "nothere.toml", []),
        (lambda t: ["check", scene(t), "--set", "render.raymarch.steps=0"], "render.raymarch.steps", []),
        (lambda t: ["check", scene(t), "--set", "camera.resolution=[100000,100000]"], "camera.resolution", []),
        (lambda t: ["check", scene(t), "--device", "no-such-device-xyz"], "no-such-device-xyz", []),
        (lambda t: ["nosuchcommand"], "nosuchcommand", []),
        (lambda t: ["relight", scene(t), "-o", str(t / "fr"), "--frames", "1000000000"], "--frames",
         ["fr"]),
        (lambda t: ["relight", scene(t), "-o", str(t / "fr"), "--frames", "90000", "--format", "exr",
                    "--set", "camera.resolution=[4000,3000]"], "GiB", ["fr"]),
        (lambda t: ["relight", scene(t), "-o", str(t / "fr"), "--frames", "0"], "--frames", ["fr"]),
        (lambda t: ["relight", scene(t), "-o", str(t / "notes.txt")], "notes.txt", []),
    ]


CLI_CASES = _cli_cases()


@pytest.mark.parametrize("case", range(len(CLI_CASES)))
def test_bad_cli_input(case, tmp_path, capsys):
    build, expect, outs = CLI_CASES[case]
    files = _files(tmp_path)
    assert files
    _expect_error(capsys, build(tmp_path), expect, [tmp_path / o for o in outs])


# ---- resource budgets: refused quickly, with the estimate, naming the key ---------------

BUDGET_CASES = [     # (arguments, the key named, the estimate's unit in the message)
    (["--set", "camera.resolution=[100000,100000]"], "camera.resolution", "iB"),
    (["--set", "camera.spp=100000000"], "camera.spp", "iB"),
    (["--set", "camera.resolution=[4000,3000]", "--set", "camera.spp=64", "--max-memory", "1G"],
     "camera", "iB"),
    (["--method", "vpm", "--set", "render.vpm.photons=100000000000"], "render.vpm.photons", "iB"),
    # lsg's chunks are fitted to the memory (max_bytes lowered), so the work refuses it
    (["--method", "lsg", "--set", "render.lsg.light_rays=1000000000000",
      "--set", "render.lsg.max_bytes=1000000000000"], "render.lsg.light_rays", "pair tests"),
    (["--max-memory", "1K"], "--max-memory", "iB"),
]


@pytest.mark.parametrize("args, key, unit", BUDGET_CASES, ids=[c[1] for c in BUDGET_CASES])
def test_oversized_requests_are_refused_quickly(args, key, unit, tmp_path, capsys, monkeypatch):
    """Refused from the estimates, before the scene is prepared on the device (no BVH, no
    upload, no launch): preparing it fails the test (an event, not a wall-clock bound)."""
    from clscatter.pipeline import session

    def no_work(*a, **k):
        raise AssertionError("the scene was prepared on the device before the refusal")

    monkeypatch.setattr(session, "prepare_scene", no_work)
    out = tmp_path / "o.png"
    line = _expect_error(capsys, ["render", str(_scene_file(tmp_path, BASE_TOML)), "-o", str(out),
                                  "--no-progress", *args], key, [out])
    assert "about" in line and unit in line            # the estimate is in the message


def test_check_bounds_the_budget_by_the_device_as_render_does(tmp_path, capsys, monkeypatch):
    """``clscatter check`` refuses what ``render`` would (it must not approve a render
    that the device's memory then refuses): with the chosen device
    reporting 1 MiB, both refuse a 2 MiB render naming device memory."""
    from types import SimpleNamespace

    from clscatter import device as dev
    small = SimpleNamespace(global_mem_size=1 << 20)
    monkeypatch.setattr(dev, "choose_device", lambda spec=None: SimpleNamespace(handle=small))
    scene = str(_scene_file(tmp_path, BASE_TOML))
    line = _expect_error(capsys, ["check", scene, "--set", "camera.resolution=[64,48]"],
                         "camera.resolution")
    assert "(device memory)" in line
    assert main(["check", scene]) == 0                  # 8 x 6 fits in 1 MiB
    assert "of 1 MiB (device memory)" in capsys.readouterr().out


def test_a_good_render_still_works_after_all_that(tmp_path, capsys):
    out, stats = tmp_path / "o.exr", tmp_path / "s.json"
    assert main(["render", str(_scene_file(tmp_path, BASE_TOML)), "-o", str(out), "--stats",
                 str(stats), "--exposure", "1e6", "--no-progress"]) == 0
    assert out.exists() and stats.exists()
    assert main(["render", str(_scene_file(tmp_path, BASE_TOML)), "-o", str(tmp_path / "p.png"),
                 "--exposure=-1e6", "--no-progress"]) == 0


def test_degenerate_triangles_are_dropped_and_counted(tmp_path, capsys):
    (tmp_path / "some.obj").write_text(
        "v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nv 3 0 3\n"
        "f 1 2 3\nf 1 3 4\nf 1 2 1\nf 1 3 5\n")    # two good faces, a repeated vertex, collinear
    scene = _mesh_scene(tmp_path, "some.obj")
    stats = tmp_path / "s.json"
    assert main(["render", str(scene), "-o", str(tmp_path / "o.npy"), "--stats", str(stats),
                 "--no-progress"]) == 0
    import json
    st = json.loads(stats.read_text())
    assert st["degenerate_triangles_dropped"] == 2 and st["triangles"] == 2
    assert "2 zero-area triangles dropped" in capsys.readouterr().err
    img = np.load(tmp_path / "o.npy")
    assert np.all(np.isfinite(img))


def test_float32_overflow_is_said_not_silent(tmp_path, capsys):
    """An intensity float32 holds but whose light overflows it in the image: those pixels
    are set to 0 (never NaN or Inf in an output), counted in the stats and said in a note
    on stderr."""
    scene = _scene_file(tmp_path, BASE_TOML)
    stats = tmp_path / "s.json"
    assert main(["render", str(scene), "-o", str(tmp_path / "o.npy"), "--stats", str(stats),
                 "--no-progress", "--method", "raymarch", "--set", "lights[0].intensity=1e38"]) == 0
    import json
    zeroed = json.loads(stats.read_text())["nonfinite_pixels_zeroed"]
    assert zeroed > 0
    assert f"{zeroed} pixels overflowed float32" in capsys.readouterr().err
    assert np.all(np.isfinite(np.load(tmp_path / "o.npy")))


def test_surfaces_reflecting_more_than_they_receive_are_noted(tmp_path, capsys):
    """Albedo or reflectance above 1 renders (as in other renderers) with a note naming
    the key."""
    scene = _scene_file(tmp_path, BASE_TOML + '[materials.shiny]\ntype = "mirror"\n'
                        'reflectance = [0.5, 2.0, 0.5]\n[[objects]]\nshape = "box"\n'
                        'min = [1.0, 0.0, 0.0]\nmax = [1.2, 0.2, 0.2]\nmaterial = "shiny"\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "o.npy"), "--no-progress",
                 "--method", "raymarch", "--set", "objects[0].material.albedo=1.5"]) == 0
    err = capsys.readouterr().err
    assert "objects[0].material.albedo: 1.5 > 1" in err
    assert "materials.shiny.reflectance: 2 > 1" in err


_SPHERE_AT = '''
[[objects]]
shape = "sphere"
center = {}
radius = 0.4
material = {{ type = "diffuse" }}
'''
_VAST_FLOOR = '''
[[objects]]
shape = "quad"
origin = [-1e7, 0.0, -1e7]
edge_u = [2e7, 0.0, 0.0]
edge_v = [0.0, 0.0, 2e7]
material = { type = "diffuse" }
'''
_SUN = '''
[[lights]]
type = "directional"
direction = [0.0, -1.0, 0.0]
irradiance = 1.0
'''


@pytest.mark.parametrize("extra, noted", [
    (_SPHERE_AT.format([1e3, 0.0, 0.0]), None),
    (_SPHERE_AT.format([1e7, 0.0, 0.0]), None),      # far: the device frame leaves it out
    (_VAST_FLOOR, "objects[1] is furthest off"),      # near, and 4e6 x the view distance
    (_SUN + _SPHERE_AT.format([0.0, 1e7, 0.0]), "objects[1] is far off but in the way of lights[1]"),
])
def test_a_scene_too_wide_for_float32_is_noted(extra, noted, tmp_path):
    """Where float32 may not resolve what the camera sees, a note names the object: a near
    object reaching 1e5 times the view distance off widens the normalised frame, and a far
    one in a directional light's way into the scene moves that light's ray starts out.
    An object far off elsewhere (1e7) is out of the frame and not noted."""
    from clscatter.pipeline.render import scene_notes
    from clscatter.scene import load_scene
    scene = load_scene(_scene_file(tmp_path, BASE_TOML + extra))
    got = [n for n in scene_notes(scene) if "float32" in n]
    assert len(got) == (noted is not None), got
    assert all(noted in n for n in got)


# Runs the command line with one line on stderr once the first ray-marching launch has
# returned: the signal is sent then, mid-render, whatever the machine's speed.
_MARK = "clscatter-test: launched"
_MARKED_MAIN = f"""
import sys
from clscatter.transport.prepared import PreparedScene
call = PreparedScene.call
def marked(self, program, *a, **k):
    call(self, program, *a, **k)
    if program == "raymarch" and not marked.done:
        marked.done = True
        print("{_MARK}", file=sys.stderr, flush=True)
marked.done = False
PreparedScene.call = marked
from clscatter.cli import main
sys.exit(main())
"""


def test_interrupting_a_long_render_leaves_no_output(tmp_path):
    """SIGINT and SIGTERM stop a render between launches; nothing is written. The signal
    goes once the first of the render's many launches has returned (an event, not a
    sleep); the 60 s of ``communicate`` only keep a hung process from hanging the run."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        out = tmp_path / f"o{int(sig)}.png"
        p = subprocess.Popen([sys.executable, "-c", _MARKED_MAIN, "render", "builtin:shafts",
                              "--method", "raymarch", "--set", "render.raymarch.steps=4096",
                              "--set", "render.raymarch.segments_per_launch=256",
                              "-o", str(out), "--no-progress"],
                             cwd=tmp_path, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONPATH": str(REPO), "PYTHONFAULTHANDLER": "1"})
        seen = []
        for line in p.stderr:                  # until the mark, or the end of the process
            seen.append(line)
            if line.strip() == _MARK:
                break
        assert seen and seen[-1].strip() == _MARK, "".join(seen)
        assert p.poll() is None, "the render ended before the signal: make it longer"
        p.send_signal(sig)
        err = p.communicate(timeout=60)[1]
        assert p.returncode == 130, err
        assert "nothing was written" in err and "Traceback" not in err
        assert not out.exists() and not [f for f in tmp_path.iterdir() if "staging" in f.name]


def test_interrupting_an_animation_leaves_no_frames(tmp_path):
    """SIGTERM during ``relight``: the frames rendered so far were staged beside the
    output folder and are deleted; the folder is not created (no frames are left behind
    under "nothing was written"). The child runs with faulthandler: a crash prints its
    stack here."""
    out = tmp_path / "frames"
    p = subprocess.Popen([sys.executable, "-m", "clscatter", "relight", "builtin:occluder",
                          "--frames", "5000", "--format", "npy", "-o", str(out), "--no-progress",
                          "--set", "camera.resolution=[32,24]", "--set", "camera.spp=1"],
                         cwd=tmp_path, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO), "PYTHONFAULTHANDLER": "1"})
    deadline = time.monotonic() + 60.0
    staged = []
    while time.monotonic() < deadline and p.poll() is None:
        staged = [f for d in tmp_path.glob(".frames.*.staging") for f in d.glob("frame_*.npy")]
        if len(staged) >= 3:
            break
        time.sleep(0.2)
    assert p.poll() is None and len(staged) >= 3, p.stderr.read()
    p.send_signal(signal.SIGTERM)
    err = p.communicate(timeout=60)[1]
    assert p.returncode == 130, err
    assert "nothing was written" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_an_animation_lands_whole(tmp_path, capsys):
    """A finished ``relight`` moves every frame and ``frames.json`` into the folder and
    leaves no staging folder beside it."""
    out = tmp_path / "frames"
    assert main(["relight", "builtin:occluder", "--frames", "3", "--format", "npy", "-o", str(out),
                 *SMALL]) == 0
    assert sorted(f.name for f in out.iterdir()) == [
        "frame_0000.npy", "frame_0001.npy", "frame_0002.npy", "frames.json"]
    assert [f.name for f in tmp_path.iterdir()] == ["frames"]
    assert np.all(np.isfinite(np.load(out / "frame_0001.npy")))


def test_an_interrupt_a_library_turned_into_another_error_still_interrupts(tmp_path, monkeypatch,
                                                                           capsys):
    """A signal's KeyboardInterrupt that library code replaced with an error of its own
    (NumPy's structured compares do) ends the command as an interruption: status 130,
    one line, no traceback, nothing written; the same error without a signal is not
    hidden."""
    import clscatter.cli as cli

    def converted(args):
        try:
            cli._terminate(signal.SIGTERM, None)
        except KeyboardInterrupt:
            raise TypeError("Cannot compare structured arrays") from None

    monkeypatch.setattr(cli, "_cmd_render", converted)
    out = tmp_path / "out.png"
    assert cli.main(["render", "builtin:occluder", "-o", str(out)]) == 130
    assert capsys.readouterr().err == "clscatter: interrupted; nothing was written\n"
    assert not out.exists()

    def plain(args):
        raise TypeError("a bug")

    monkeypatch.setattr(cli, "_cmd_render", plain)
    with pytest.raises(TypeError, match="a bug"):
        cli.main(["render", "builtin:occluder", "-o", str(out)])
