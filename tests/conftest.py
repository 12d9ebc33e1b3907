"""Shared fixtures: one OpenCL engine for the whole session, repo paths."""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # for `import analytic`

MODELS = REPO / "models"

# the suite's renders (and the CLI processes it starts) learn their costs into a file of
# their own: the user's calibration (clscatter/pipeline/calibration.py) stays their renders'
os.environ["CLSCATTER_COSTS"] = str(Path(tempfile.mkdtemp(prefix="clscatter-costs-"))
                                    / "costs.json")


@pytest.fixture(scope="session")
def engine():
    from clscatter.device import get_engine
    return get_engine()
