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
    helpers (scipy, trimesh); ``--help`` does not even import pyopencl."""
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


@pytest.mark.parametrize("linear", ["exr", "npy", "pfm"])
def test_diff_refuses_a_linear_image_against_a_tone_mapped_one(tmp_path, capsys, linear):
    """PNG is tone-mapped (clamped 8-bit sRGB): against a linear file, in either order,
    ``diff`` prints no metrics but one error line saying why, exit status 2, no heatmap."""
    from clscatter.io.image import write_image
    img = np.linspace(0.0, 3.0, 4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)  # above 1: clamped
    lin, png = tmp_path / f"a.{linear}", tmp_path / "b.png"
    write_image(lin, img)
    write_image(png, img)
    for a, b in ((lin, png), (png, lin)):
        for extra in ([], ["--json"], ["--heatmap", str(tmp_path / "h.png")]):
            code, out, err = _run(["diff", str(a), str(b), *extra], capsys)
            assert code == 2 and out == "", (a, b, extra, out)
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("clscatter: error: "), err
            assert "comparing a linear image with a tone-mapped one" in lines[0]
            assert "compare two linear images" in lines[0] and "two PNGs" in lines[0]
            assert str(a) in lines[0] and str(b) in lines[0]
            assert not (tmp_path / "h.png").exists()
    # like with like still gives the metrics: two PNGs, two linear files
    write_image(tmp_path / "c.png", img * 0.5)
    code, out, err = _run(["diff", str(png), str(tmp_path / "c.png")], capsys)
    assert code == 0 and "rmse:" in out and err == ""
    np.save(tmp_path / "d.npy", img * 0.5)
    code, out, err = _run(["diff", str(lin), str(tmp_path / "d.npy"), "--json"], capsys)
    assert code == 0 and json.loads(out)["max_error"] == pytest.approx(1.5, rel=1e-5)


def test_render_prints_the_plan_notes_that_leave_light_out(tmp_path, capsys):
    """raymarch on the glass scene leaves its caustics out: ``render`` says so on stderr, in
    the planner's own words, once; ``auto`` computes every term and says nothing of the kind."""
    from clscatter.pipeline.planner import DROPS_LIGHT, dropped_light
    from clscatter.pipeline.render import check
    from clscatter.scene import load_scene

    sets = ["--set", "camera.resolution=[32,24]", "--set", "camera.spp=1", "--no-progress"]
    code, out, err = _run(["render", "builtin:glass", "--method", "raymarch", *sets,
                           "-o", str(tmp_path / "out.png")], capsys)
    assert code == 0, err
    notes = [ln for ln in err.splitlines() if ln.startswith("clscatter: note: ")]
    expected = dropped_light(check(load_scene("builtin:glass"), "raymarch").notes)
    assert len(expected) == 1 and "caustics" in expected[0]
    assert notes == [f"clscatter: note: {expected[0]}"], err
    assert notes[0].endswith(DROPS_LIGHT)
    assert (tmp_path / "out.png").is_file()

    code, out, err = _run(["render", "builtin:glass", "--method", "auto", *sets,
                           "-o", str(tmp_path / "auto.png")], capsys)
    assert code == 0, err
    assert not [ln for ln in err.splitlines() if ln.endswith(DROPS_LIGHT)], err
    assert "by raymarch+" in out               # auto did add the caustic passes


# the README's example, `clscatter relight builtin:volume_sphere --frames 24 --orbit light
# -o frames/`, at 48 x 36, 1 spp, with 4 frames (90 degrees apart). Measured on PoCL (CPU):
# with the old orbit (radius 0.1, the light's own distance from the axis) consecutive frames
# differ by a relative mean absolute difference of 0.28 .. 0.36 (sampling noise: the beam
# hardly moves); with the widened orbit (radius 1.0) by 1.12 .. 1.66.
RELIGHT_MIN_CHANGE = 0.6


def test_relight_readme_example_moves_the_light_visibly(tmp_path, capsys):
    out = tmp_path / "frames"
    code, stdout, err = _run(["relight", "builtin:volume_sphere", "--frames", "4", "--orbit",
                              "light", "-o", str(out), "--format", "npy", "--no-progress",
                              "--set", "camera.resolution=[48,36]", "--set", "camera.spp=1"],
                             capsys)
    assert code == 0, err
    assert "radius 1" in stdout
    assert "lights[0].position is close to the orbit's axis" in err      # said, not silent
    rec = json.loads((out / "frames.json").read_text())
    assert rec["axis"]["direction"] == pytest.approx([0.0, 1.0, 0.0])
    assert rec["axis"]["point"] == pytest.approx([0.0, 1.05, 0.0])      # the bbox centre
    assert rec["radius"] == pytest.approx(1.0)          # a quarter of the 4-unit scene
    (mover,) = rec["movers"]
    assert mover["key"] == "lights[0].position" and mover["widened"] is True
    assert mover["start"] == pytest.approx([1.0, 3.3, 0.0])   # the light's height kept
    imgs = [np.load(out / name) for name in rec["files"]]
    assert len(imgs) == 4 and all(np.isfinite(i).all() and i.max() > 0 for i in imgs)
    for k, (a, b) in enumerate(zip(imgs, imgs[1:])):
        change = float(np.abs(a - b).mean() / np.abs(b).mean())
        assert change > RELIGHT_MIN_CHANGE, f"frames {k} and {k + 1} differ by only {change:.3f}"


def test_scenes_lists_whole_first_paragraphs(capsys):
    """``clscatter scenes`` shows each description's whole first paragraph (never cut
    mid-sentence) and the descriptions describe the scene, not the project's history."""
    import re

    from clscatter.cli import scene_summary
    from clscatter.scene import BUILTIN

    code, out, _ = _run(["scenes"], capsys)
    assert code == 0
    listed = {}
    for line in out.splitlines():
        label, _, desc = line.partition("  ")
        listed[label.split()[0].removeprefix("builtin:")] = desc.strip()
    assert set(listed) == set(BUILTIN)
    for name, desc in listed.items():
        doc = " ".join((BUILTIN[name].__doc__ or "").replace("``", "").split())
        first = (BUILTIN[name].__doc__ or "").strip().split("\n\n")[0]
        assert desc and desc[-1] in ".!?", f"{name}: {desc!r} does not end a sentence"
        assert doc.startswith(desc), (name, desc)
        assert desc == " ".join(first.replace("``", "").split()), name      # all of it
        assert desc == scene_summary(BUILTIN[name].__doc__)
        assert not re.search(r"\bissues?\b", BUILTIN[name].__doc__ or "", re.I), name
    # the description that used to be cut mid-parenthesis is whole now
    assert listed["epi_fog"].endswith("the sun behind the camera.")
    assert scene_summary("One.\n    Two, still the first\n    paragraph.\n\n    Later.") == \
        "One. Two, still the first paragraph."


# ---- CLSCATTER_DEVICE ------------------------------------------------------------------------
def _run_with_device_env(tmp_path, value, *extra):
    """``clscatter render`` in a fresh process with ``CLSCATTER_DEVICE=value``."""
    import os
    env = {**os.environ, "PYTHONPATH": str(REPO), "CLSCATTER_DEVICE": value}
    out = tmp_path / "img.npy"
    stats = tmp_path / "stats.json"
    r = subprocess.run([sys.executable, "-m", "clscatter", "render", "builtin:occluder",
                        "-o", str(out), "--stats", str(stats), *SMALL, *extra],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    return r, out, stats


def test_clscatter_device_substring_chooses_the_device(tmp_path):
    """A substring of the device's name (in another case: the match ignores case) picks it;
    ``--stats`` names the device the render ran on."""
    from clscatter.device import choose_device
    info = choose_device("0:0")
    sub = info.name[: max(4, len(info.name) // 2)].swapcase()
    r, out, stats = _run_with_device_env(tmp_path, sub)
    assert r.returncode == 0, r.stderr
    st = json.loads(stats.read_text())
    assert st["device"] == f"{info.platform} / {info.name}"
    assert sub.lower() in st["device"].lower()
    assert read_image(out).max() > 0


def test_clscatter_device_matching_nothing_is_one_line_exit_2(tmp_path):
    r, out, stats = _run_with_device_env(tmp_path, "no-such-device-xyz")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("clscatter: error: "), r.stderr
    assert "'no-such-device-xyz'" in lines[0] and "not found" in lines[0]
    assert not out.exists() and not stats.exists() and not list(tmp_path.iterdir())


def test_device_option_takes_precedence_over_clscatter_device(tmp_path):
    """``--device`` names the device; the variable is only the default."""
    r, out, stats = _run_with_device_env(tmp_path, "no-such-device-xyz", "--device", "0:0")
    assert r.returncode == 0, r.stderr
    assert read_image(out).max() > 0
    assert json.loads(stats.read_text())["device"]


def test_quiet_prints_nothing_and_stats_keep_the_notes(tmp_path, capsys):
    """``-q``: no progress, no notes, no closing line; the image is written and ``--stats``
    holds the notes a plain run prints (here: raymarch leaves the glass's caustics out)."""
    sets = ["--set", "camera.resolution=[16,12]", "--set", "camera.spp=1"]
    argv = ["render", "builtin:glass", "--method", "raymarch", *sets]
    code, out, err = _run([*argv, "-o", str(tmp_path / "loud.png"), "--no-progress",
                           "--stats", str(tmp_path / "loud.json")], capsys)
    assert code == 0 and out.strip() and err.count("clscatter: note: ") >= 1, (out, err)
    printed = [ln.removeprefix("clscatter: note: ") for ln in err.splitlines()]
    code, out, err = _run([*argv, "-o", str(tmp_path / "quiet.png"), "-q",
                           "--stats", str(tmp_path / "quiet.json")], capsys)
    assert code == 0 and out == "" and err == "", (out, err)
    assert (tmp_path / "quiet.png").is_file()
    notes = json.loads((tmp_path / "quiet.json").read_text())["notes"]
    assert notes == printed
    assert json.loads((tmp_path / "loud.json").read_text())["notes"] == printed
    code, out, err = _run(["relight", "builtin:volume_sphere", "--frames", "2", *sets,
                           "-o", str(tmp_path / "frames"), "--quiet"], capsys)
    assert code == 0 and out == "" and err == "", (out, err)
    assert len(list((tmp_path / "frames").glob("frame_*.png"))) == 2
