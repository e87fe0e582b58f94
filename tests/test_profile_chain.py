"""benchmarks/profile_chain.py: the per-stage split of SLAM.track adds up and names the stages."""

from __future__ import annotations

import pytest

from benchmarks.profile_chain import CHAINS, run_chain
from tests.conftest import DATA, TUM_DESK9, need


@pytest.mark.data
def test_profile_splits_the_tracking_time_into_the_stages_it_calls():
    seq = need(TUM_DESK9)
    plain = run_chain(seq, CHAINS["default"], None, profile=False)
    prof = run_chain(seq, CHAINS["default"], None, profile=True)
    assert plain["frames"] == prof["frames"] == 9 and plain["tracked"] == 9
    assert plain["orb_ms"] > 0 and plain["detect_ms"] > 0 and plain["track_ms"] > 0
    st = prof["stages_ms"]
    # the orchestrator's calls into the stage packages: the front end and the landmark map every frame
    assert {"front end", "landmark map"} <= set(st) and st["front end"] > 0 and st["landmark map"] > 0
    # the stages are parts of SLAM.track: together no more than its profiled total (timer granularity aside)
    assert sum(st.values()) <= prof["track_ms"] * 1.02
    inner = prof["inner_ms"]
    assert inner["front end: undistort + lift to 3-D"] > 0 and inner["  map: match to the projected landmarks"] > 0
    assert inner["landmark map: tracking (match + pose)"] <= st["landmark map"] * 1.02
    # the slowest function by own time is one of ours or NumPy's, with its calls counted
    own = prof["own"]
    assert own == sorted(own, reverse=True) and own[0][1] > 0


@pytest.mark.data
def test_a_preset_profiles_the_stereo_chain():
    seq = need(DATA / "kitti" / "odometry_06_head51")
    with_preset = run_chain(seq, CHAINS["default"], 6, profile=False, config="kitti")
    assert with_preset["frames"] == with_preset["tracked"] == 6 and with_preset["track_ms"] > 0
    # the defaults (an RGB-D camera's) do not track this stereo sequence: the preset is what is profiled
    assert run_chain(seq, CHAINS["default"], 6, profile=False)["tracked"] < 6
