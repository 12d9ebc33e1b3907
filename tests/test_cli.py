"""The command-line contract: outputs in every format, --set, --stats, errors as one line
with exit status 2 and nothing written, devices/scenes/diff subcommands."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clscatter.cli import main
from clscatter.io.image import read_image

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--set", "camera.resolution=[16,12]", "--set", "camera.spp=1", "--no-progress"]
REQUIRED_STATS = {"method", "device", "seconds_total", "stages", "peak_bytes", "width", "height"}

GOOD = """
[camera]
origin = [0.0, 1.0, 4.0]
target = [0.0, 0.5, 0.0]
resolution = [16, 12]
spp = 1

[medium]
sigma_s = 0.2
sigma_a = 0.05
g = 0.2

[[lights]]
type = "point"
position = [0.0, 2.0, 0.0]
intensity = 5.0

[[objects]]
shape = "quad"
origin = [-2.0, 0.0, -2.0]
edge_u = [4.0, 0.0, 0.0]
edge_v = [0.0, 0.0, 4.0]
material = { type = "diffuse", albedo = 0.5 }
"""


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_render_writes_every_format_and_stats(tmp_path, capsys):
    outs = [tmp_path / f"img.{s}" for s in ("png", "exr", "npy", "pfm")]
    argv = ["render", "builtin:occluder", *SMALL, "--stats", str(tmp_path / "s.json")]
    for o in outs:
        argv += ["-o", str(o)]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    imgs = [read_image(o) for o in outs]
    assert imgs[2].shape == (12, 16, 3) and imgs[2].dtype == np.float32
    assert np.array_equal(imgs[1], imgs[2]) and np.array_equal(imgs[2], imgs[3])
    assert np.isfinite(imgs[2]).all() and imgs[2].max() > 0
    stats = json.loads((tmp_path / "s.json").read_text())
    assert REQUIRED_STATS <= set(stats)
    assert (stats["width"], stats["height"]) == (16, 12)
    assert stats["peak_bytes"] > 0 and stats["seconds_total"] > 0


def test_set_and_method_overrides(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(GOOD)
    o = tmp_path / "a.npy"
    code, _, err = _run(["render", str(scene), "-o", str(o), "--method", "raymarch", "--no-progress",
                         "--set", "render.raymarch.steps=4", "--set", "lights[0].intensity=0.0",
                         "--stats", str(tmp_path / "st.json")], capsys)
    assert code == 0, err
    assert np.all(read_image(o) == 0.0)          # the override switched the only light off
    st = json.loads((tmp_path / "st.json").read_text())
    assert st["method"] == "raymarch" and st["raymarch_steps"] == 4


BAD_CASES = [
    ("medium.sigma_s", "[medium]\nsigma_s = -1.0\n"),
    ("medium.g", "[medium]\nsigma_s = 0.1\ng = 1.0\n"),
    ("camera.resolution", None),
    ("camera.bogus", None),
    ("lights[0]", "[[lights]]\ntype = \"directional\"\ndirection = [0, -1, 0]\nirradiance = 1.0\n"
                  "[medium]\nsigma_s = 0.1\n"),
    ("objects[0].file", "[[objects]]\nshape = \"mesh\"\nfile = \"nowhere.obj\"\nmaterial = { type = \"black\" }\n"),
]


@pytest.mark.parametrize("key,extra", BAD_CASES)
def test_bad_scenes_exit_2_with_one_line(tmp_path, capsys, key, extra):
    base = GOOD.replace("[medium]\nsigma_s = 0.2\nsigma_a = 0.05\ng = 0.2\n", "")
    base = base.replace("[[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 0.0]\nintensity = 5.0\n", "") \
        if key == "lights[0]" else base
    if key == "camera.resolution":
        text = base.replace("resolution = [16, 12]", "resolution = [0, 12]")
    elif key == "camera.bogus":
        text = base.replace("spp = 1", "spp = 1\nbogus = 3")
    else:
        text = base + extra
    scene = tmp_path / "bad.toml"
    scene.write_text(text)
    o = tmp_path / "never.png"
    code, out, err = _run(["render", str(scene), "-o", str(o), "--no-progress"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert key.split("[")[0] in lines[0] and "Traceback" not in err
    assert not o.exists() and not list(tmp_path.glob("never*"))


def test_bad_toml_missing_file_bad_suffix_bad_set(tmp_path, capsys):
    bad = tmp_path / "broken.toml"
    bad.write_text("[camera\norigin = 1\n")
    for argv, needle in [(["render", str(bad)], "broken.toml"),
                         (["render", str(tmp_path / "missing.toml")], "missing.toml"),
                         (["render", "builtin:occluder", "-o", str(tmp_path / "x.gif")], "x.gif"),
                         (["render", "builtin:occluder", "--set", "camera.nothing=1"], "camera.nothing"),
                         (["render", "builtin:nope"], "nope"),
                         (["render", "builtin:occluder", "--method", "bogus"], "render.method"),
                         (["diff", str(tmp_path / "a.npy"), str(tmp_path / "b.npy")], "a.npy")]:
        code, _, err = _run(argv + ["--no-progress"] if argv[0] == "render" else argv, capsys)
        assert code == 2, argv
        assert len(err.strip().splitlines()) == 1 and needle in err, (argv, err)


def test_diff_devices_scenes(tmp_path, capsys):
    a = np.ones((4, 5, 3), np.float32)
    np.save(tmp_path / "a.npy", a)
    np.save(tmp_path / "b.npy", a * 1.1)
    code, out, _ = _run(["diff", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--json",
                         "--heatmap", str(tmp_path / "h.png")], capsys)
    assert code == 0
    m = json.loads(out)
    assert abs(m["rmse"] - 0.1) < 1e-5 and (tmp_path / "h.png").is_file()
    code, out, _ = _run(["devices"], capsys)
    assert code == 0 and "chosen:" in out and " ok" in out
    code, out, _ = _run(["scenes"], capsys)
    assert code == 0 and "builtin:shafts (default)" in out
    code, out, _ = _run(["scenes", "--dump", "shafts"], capsys)
    assert code == 0 and "[camera]" in out


def test_bare_command_renders_the_demo(tmp_path):
    """The real entry point, in a fresh process, with no arguments at all."""
    r = subprocess.run([sys.executable, "-m", "clscatter"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=300, env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0, r.stderr
    img = read_image(tmp_path / "clscatter-demo.png")
    assert img.shape[2] == 3 and img.max() > 0.1


def test_error_in_a_fresh_process_is_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "clscatter", "render", str(tmp_path / "nope.toml")],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "nope.toml" in r.stderr


@pytest.mark.parametrize("argv", [["--help"], ["render", "--help"], ["devices"]])
def test_start_up_imports_only_what_the_command_uses(argv):
    """``--help`` and ``devices`` load no method, no scene builder and no NumPy-heavy
    helpers (scipy, trimesh); ``--help`` does not even import pyopencl (issue 16)."""
    import subprocess
    import sys
    code = ("import sys\nfrom clscatter.cli import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "mods = sorted(m for m in sys.modules if m.startswith(('clscatter.methods', "
            "'scipy', 'trimesh', 'pyopencl', 'clscatter.scene.builtin')))\n"
            "print('MODULES', ','.join(mods))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120).stdout
    line = [x for x in out.splitlines() if x.startswith("MODULES")][-1]
    mods = [m for m in line.split(" ", 1)[1].split(",") if m]
    assert not [m for m in mods if m.startswith(("clscatter.methods", "scipy", "trimesh",
                                                 "clscatter.scene.builtin"))], mods
    if "--help" in argv:
        assert not [m for m in mods if m.startswith("pyopencl")], mods
