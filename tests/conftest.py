"""Shared fixtures: where the real data lives (RGBDSLAM_DATA, default ../shared/data)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("RGBDSLAM_DATA", REPO.parent / "shared" / "data"))
TUM_DESK9 = DATA / "tum" / "rgbd_dataset_freiburg1_desk_9frames"
TUM_RPY200 = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
POSEGRAPH = DATA / "posegraph"


def need(path: Path) -> Path:
    """Skip the test, saying why, when a data folder is absent."""
    if not path.exists():
        pytest.skip(f"data not found at {path} (set RGBDSLAM_DATA to the shared data folder)")
    return path


@pytest.fixture
def desk9() -> Path:
    return need(TUM_DESK9)


@pytest.fixture
def rpy200() -> Path:
    return need(TUM_RPY200)
