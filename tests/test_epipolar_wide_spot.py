"""``auto`` passes epipolar over under a wide spot light (half-angle above WIDE_SPOT), where
its error at equal samples was several times ray marching's
(docs/bench/epipolar_wide_spot.json), and keeps it for the narrower cones it handles."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from clscatter.methods.epipolar import WIDE_SPOT
from clscatter.pipeline.planner import plan
from clscatter.scene.builtin.epipolar import epi_wide_spot
from clscatter.scene.loader import scene_from_dict

BENCH = Path(__file__).resolve().parents[1] / "docs" / "bench" / "epipolar_wide_spot.json"


@pytest.mark.parametrize("cutoff, expected", [(30, "epipolar"), (50, "epipolar"),
                                              (60, "raymarch"), (80, "raymarch"),
                                              (90, "raymarch")])
def test_auto_chooses_by_the_cone(cutoff, expected):
    passes, notes = plan(scene_from_dict(epi_wide_spot(cutoff, (32, 24))), "auto")
    direct = [p.method for p in passes if p.role == "direct"]
    assert direct == [expected], notes
    if expected == "raymarch":
        assert any("half-angle" in n for n in notes)


def test_the_threshold_follows_the_recorded_sweep():
    """Every recorded cone wider than WIDE_SPOT has epipolar's error above ray marching's;
    the rule is the record's, not a guess."""
    rows = json.loads(BENCH.read_text())["rows"]
    wide = [r for r in rows if r["cutoff"] > WIDE_SPOT]
    assert wide and all(r["epipolar"] > 2 * r["raymarch"] for r in wide)
