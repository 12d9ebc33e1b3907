"""Every second of a render is accounted for: the stages in ``--stats`` sum to at least
95% of ``seconds_total`` for every method, through the real command line."""
from __future__ import annotations

import json

import pytest

from clscatter.cli import main
from clscatter.methods import all_methods

SCENES = {"raymarch": "builtin:occluder", "epipolar": "builtin:shafts",
          "lsg": "builtin:caustic_sphere", "vpm": "builtin:caustic_sphere"}
SMALL = ["--set", "camera.resolution=[48,36]", "--set", "camera.spp=1", "--no-progress"]
QUICK = {"lsg": ["--set", "render.lsg.light_rays=20000"],
         "vpm": ["--set", "render.vpm.photons=100000"]}


@pytest.mark.parametrize("method", sorted(all_methods()))
def test_stages_cover_the_render(method, tmp_path, capsys):
    scene = SCENES.get(method, "builtin:caustic_sphere")
    stats = tmp_path / "s.json"
    code = main(["render", scene, "--method", method, "-o", str(tmp_path / "o.npy"),
                 "--stats", str(stats), *SMALL, *QUICK.get(method, [])])
    assert code == 0, capsys.readouterr().err
    st = json.loads(stats.read_text())
    covered = sum(st["stages"].values())
    assert covered >= 0.95 * st["seconds_total"], (covered, st["seconds_total"], st["stages"])
    assert {"startup", "load_scene", "configure", "device", "view_paths",
            "write_outputs"} <= set(st["stages"])
