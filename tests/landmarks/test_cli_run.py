"""The landmark map end to end from the command line: `rgbdslam run` on fr1/desk (9 frames, a
keyframe every 3), and every output it adds read back — the trajectory, the map and its 2-D outputs
with the landmarks' top view, run.json's landmark summary, and the Rerun recording (read with Rerun's
own reader, `rerun.chunk.RrdReader`): the landmarks coloured by age, the frame's matches to the map."""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest
import yaml

from tests.conftest import cli


def _entities(rrd, paths) -> dict[str, dict[int, dict]]:
    """{entity: {frame: {column: value}}} of the rows logged on ``paths`` (Rerun's RrdReader)."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[int, dict]] = defaultdict(dict)
    for ch in RrdReader(rrd).stream():
        if ch.entity_path in paths:
            d = ch.to_record_batch().to_pydict()
            for i, frame in enumerate(d["frame"]):
                out[ch.entity_path].setdefault(frame, {}).update({k: v[i] for k, v in d.items() if ":" in k})
    return out


def _rgb(packed) -> np.ndarray:
    """Rerun's packed 0xRRGGBBAA colours as (N, 3) uint8."""
    c = np.asarray(packed, np.uint64)
    return np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], axis=1).astype(np.uint8)


@pytest.fixture(scope="module")
def landmark_run(tmp_path_factory):
    from tests.conftest import TUM_DESK9, need

    seq = need(TUM_DESK9)
    out = tmp_path_factory.mktemp("lm_cli") / "run"
    rrd = out.parent / "run.rrd"
    res = cli(["run", seq, "-o", out, "-q", "--rerun-save", rrd, "-s", "landmarks.enabled=true",
               "-s", "keyframes.max_gap=3"])
    assert res.exit_code == 0, res.output
    return out, rrd


@pytest.mark.data
def test_run_writes_trajectory_map_and_landmark_summary(landmark_run):
    out, _ = landmark_run
    saved = yaml.safe_load((out / "config.yaml").read_text())["landmarks"]
    assert saved["enabled"] is True  # the run can be repeated from its folder
    rows = [ln for ln in (out / "trajectory.tum").read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 9
    run = json.loads((out / "run.json").read_text())
    assert run["evaluation"]["ate"]["rmse"] < 0.02 and run["keyframes"] == [0, 3, 6]
    lm = run["landmarks"]
    assert lm["map_poses"] >= 6 and lm["median_inliers"] >= 100 and lm["size"] > 500
    assert lm["store"] == "multi"
    assert sum(lm["store_trees"]) == lm["size"]
    # the 3-D map and the 2-D map outputs, the landmarks' top view among them
    for name in ("cloud.ply", "mesh.ply", "landmarks_topview.png"):
        assert (out / "map" / name).stat().st_size > 10000, name
    import cv2

    grid = cv2.imread(str(out / "map" / "map2d.png"), cv2.IMREAD_UNCHANGED)
    assert grid is not None and grid.size > 100 and "resolution" in yaml.safe_load((out / "map" / "map2d.yaml").read_text())

    top = cv2.imread(str(out / "map" / "landmarks_topview.png"))
    assert top is not None and top.shape[0] > 500 and top.shape[1] > 500
    coloured = np.abs(top.astype(int) - top.mean(axis=2, keepdims=True)).max(axis=2) > 40  # not grey: landmarks
    assert coloured.sum() > 500


@pytest.mark.data
def test_recording_has_landmarks_by_age_and_map_matches(landmark_run):
    out, rrd = landmark_run
    run = json.loads((out / "run.json").read_text())
    ent = _entities(rrd, {"/world/landmarks", "/world/camera/image/map_matches"})
    # the landmark map at every frame; at the last one, every live landmark
    lms = ent["/world/landmarks"]
    assert sorted(lms) == list(range(9))
    assert len(lms[8]["Points3D:positions"]) == run["landmarks"]["size"]
    assert len(lms[0]["Points3D:positions"]) < len(lms[3]["Points3D:positions"]) < len(lms[6]["Points3D:positions"])
    # coloured by age: made at keyframes 0, 3, 6, so at frame 8 exactly the ages 8, 5, 2 (red -> blue over 300 frames)
    got = {tuple(c) for c in _rgb(lms[8]["Points3D:colors"])}
    want = {tuple(((1 - a / 300) * np.array([230, 50, 40]) + a / 300 * np.array([40, 90, 230])).astype(np.uint8))
            for a in (8, 5, 2)}
    assert got == want
    # the frame's matches to the map: pixels in the image, on every frame after the first
    mm = ent["/world/camera/image/map_matches"]
    assert sorted(mm) == list(range(1, 9)) and min(len(r["Points2D:positions"]) for r in mm.values()) >= 100
    uv = np.asarray(mm[8]["Points2D:positions"])
    assert (uv >= 0).all() and (uv[:, 0] < 640).all() and (uv[:, 1] < 480).all()


@pytest.mark.data
def test_view_of_the_finished_run_shows_its_landmark_map(landmark_run, tmp_path, monkeypatch):
    """`rgbdslam view RUN --save X.rrd` (no display: it only records) puts the landmark map saved in
    map.npz into the recording: every live landmark, at its position after the pose graph."""
    from rgbdslam.session.mapfile import load_map
    from rgbdslam.viz import rerun_log

    monkeypatch.setattr(rerun_log, "has_display", lambda: False)
    out, _ = landmark_run
    rrd = tmp_path / "view.rrd"
    res = cli(["view", out, "--save", rrd])
    assert res.exit_code == 0, res.output
    lm = _entities(rrd, {"/world/landmarks"})["/world/landmarks"]
    saved = load_map(out / "map.npz").landmarks
    assert list(lm) == [8] and len(saved["lm_pos"]) == json.loads((out / "run.json").read_text())["landmarks"]["size"]
    assert np.allclose(np.asarray(lm[8]["Points3D:positions"]), saved["lm_pos"], atol=1e-6)
    ages = {tuple(c) for c in _rgb(lm[8]["Points3D:colors"])}
    assert len(ages) == 3  # made at keyframes 0, 3 and 6
