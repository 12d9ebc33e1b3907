"""Shared fixtures: one OpenCL engine for the whole session, repo paths."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # for `import analytic`

MODELS = REPO / "models"


@pytest.fixture(scope="session")
def engine():
    from clscatter.device import get_engine
    return get_engine()
