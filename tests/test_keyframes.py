"""Keyframed animations (clscatter/keyframes.py, ``clscatter relight --keyframes``): values
interpolated between keyframes (numbers and vectors linearly, anything else held), every
frame an absolute override list; a keyframed frame renders as a fresh render of the scene
at that pose; bad keyframe files are one line naming the file and the key."""
from __future__ import annotations

import json

import numpy as np
import pytest

from clscatter import keyframes
from clscatter.cli import main
from clscatter.errors import ClscatterError
from clscatter.pipeline.render import render
from clscatter.pipeline.session import RenderSession
from clscatter.scene import load_scene

SMALL = ["camera.resolution=[32,24]", "camera.spp=1"]


def test_tracks_interpolate_numbers_and_hold_the_rest():
    keys = keyframes.parse({"key": [
        {"frame": 4, "a.x": 2.0, "v": [1.0, 1.0, 3.0], "file": "g1.npy"},
        {"frame": 0, "a.x": 0.0, "v": [0.0, 1.0, 2.0], "file": "g0.npy", "on": True},
        {"frame": 6, "file": "g2.npy"},
    ]})
    assert [f for f, _ in keys] == [0, 4, 6]
    frames = keyframes.frames(keys)
    assert len(frames) == 7
    at = [dict(s.split("=", 1) for s in f) for f in frames]
    assert [float(a["a.x"]) for a in at] == [0.0, 0.5, 1.0, 1.5, 2.0, 2.0, 2.0]
    assert at[2]["v"] == "[0.5, 1.0, 2.5]"
    assert [a["file"] for a in at] == ['"g0.npy"'] * 4 + ['"g1.npy"'] * 2 + ['"g2.npy"']
    assert all(a["on"] == "true" for a in at)         # one keyframe: held everywhere


@pytest.mark.parametrize("data, message", [
    ({}, "needs at least one"),
    ({"key": [{"frame": -1, "a": 1}]}, "key[0].frame"),
    ({"key": [{"frame": 1.5, "a": 1}]}, "key[0].frame"),
    ({"key": [{"frame": 0, "a": 1}, {"frame": 0, "a": 2}]}, "frame 0 is given twice"),
    ({"key": [{"frame": 0}]}, "sets no scene key"),
    ({"key": [{"frame": 0, "a": 1}], "extra": 1}, "unknown table or key 'extra'"),
])
def test_bad_keyframes_are_one_line(data, message):
    with pytest.raises(ClscatterError, match=message.replace("[", r"\[").replace("]", r"\]")):
        keyframes.parse(data, "k.toml")


def test_a_keyframed_frame_equals_a_fresh_render_at_that_pose(engine):
    """An object moving between keyframes (a new BVH each frame) and a light changing: each
    frame of a session equals a fresh render of the scene with that frame's overrides."""
    frames = keyframes.frames(keyframes.parse({"key": [
        {"frame": 0, "objects[1].center": [0.0, 1.0, 0.0], "lights[0].intensity": 10.0},
        {"frame": 2, "objects[1].center": [0.6, 1.3, 0.2], "lights[0].intensity": 16.0}]}))
    with RenderSession.from_source("builtin:occluder", SMALL, engine=engine) as s:
        for sets in frames:
            s.set(sets, replace=True)
            warm = s.render(show_progress=False)
            fresh = render(load_scene("builtin:occluder", SMALL + sets), engine=engine,
                           show_progress=False)
            np.testing.assert_allclose(warm.image, fresh.image, rtol=1e-5, atol=1e-7)
    mid = dict(x.split("=", 1) for x in frames[1])
    assert mid["objects[1].center"] == "[0.3, 1.15, 0.1]"


def test_relight_with_keyframes(tmp_path, capsys):
    keys = tmp_path / "keys.toml"
    keys.write_text('[[key]]\nframe = 0\n"objects[1].center" = [0.0, 1.0, 0.0]\n'
                    '[[key]]\nframe = 2\n"objects[1].center" = [0.4, 1.0, 0.0]\n')
    out = tmp_path / "frames"
    args = ["relight", "builtin:occluder", "-o", str(out), "--keyframes", str(keys),
            "--no-progress", *[a for o in SMALL for a in ("--set", o)]]
    assert main(args) == 0
    record = json.loads((out / "frames.json").read_text())
    assert record["count"] == 3 and len(record["files"]) == 3
    assert record["overrides"][1] == ["objects[1].center=[0.2, 1.0, 0.0]"]
    assert "3 frames (keyframes keys.toml)" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text('[[key]]\nframe = 0\n"objects[1].radius" = -1.0\n')
    assert main([*args[:3], str(tmp_path / "f2"), "--keyframes", str(bad), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "objects[1].radius" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "f2").exists()
    assert main([*args[:3], str(tmp_path / "f3"), "--keyframes", str(tmp_path / "none.toml")]) == 2
    assert "keyframe file not found" in capsys.readouterr().err
