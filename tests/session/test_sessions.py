"""Saved maps (issue 19): map.npz written and read back, its checks, localising in it and
extending it on real fr1/rpy frames (session 1: frames 0-49, session 2: frames 50-89)."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rgbdslam.config import load_config
from rgbdslam.evaluation.ate import ate
from rgbdslam.geometry.camera import CAMERAS
from rgbdslam.io.trajectory import Trajectory, read_tum
from rgbdslam.pipeline import run_sequence
from rgbdslam.session.mapfile import VERSION, MapFileError, load_map, read_header
from tests.conftest import TUM_RPY200, assert_cli_error, cli, need
from tests.viz.test_rerun_log import entity_paths

pytestmark = pytest.mark.data  # fr1/rpy frames
FR1 = ["--config", "tum_fr1"]


def _cfg(*extra):
    return load_config("tum_fr1", ["mapping.enabled=false", "output.plots=false", *extra])


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _joint_ate(*trajs: Path) -> float:
    parts = [read_tum(p) for p in trajs]
    t = Trajectory(np.concatenate([p.timestamps for p in parts]), np.concatenate([p.poses for p in parts]))
    return ate(read_tum(TUM_RPY200 / "groundtruth.txt"), t).rmse


@pytest.fixture(scope="module")
def session1(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("maps") / "s1"
    run_sequence(need(TUM_RPY200), out, _cfg("dataset.max_frames=50"), progress=False)
    return out


def test_map_file_holds_the_run(session1):
    info = json.loads((session1 / "run.json").read_text())
    m = load_map(session1 / "map.npz")
    assert info["map_file"]["keyframes"] == m.n_keyframes == len(info["keyframes"])
    assert list(m.arrays["kf_frame"]) == info["keyframes"]
    assert m.camera.name == "fr1" and m.camera.fx == 517.3
    assert m.sessions[0]["sequence"] == str(TUM_RPY200.resolve()) and m.sessions[0]["dataset"]["max_frames"] == 50
    assert m.config["loop"]["relocalize_confirm"] == 2
    # the default tracks against the landmark map, and the map file carries it (and that fr1's depth is registered)
    assert m.landmarks is not None and m.n_landmarks == info["landmarks"]["size"] > 0 and m.camera.depth_registered
    # every tracked frame comes back at its trajectory.tum pose from its keyframe and relative pose
    stamps, poses = m.session_poses(0)
    traj = read_tum(session1 / "trajectory.tum")
    assert np.allclose(stamps, traj.timestamps) and np.allclose(poses, traj.poses, atol=1e-5)
    # key points lifted with depth: camera points in front of the camera, reprojecting to their pixels
    f = m.features(0)
    pts, uv = f["pts"][f["valid"]].astype(float), f["uv"][f["valid"]].astype(float)
    assert len(pts) > 200 and np.all(pts[:, 2] > 0.2)
    assert np.allclose(m.camera.project(pts), uv, atol=0.05)
    assert read_header(session1 / "map.npz")["version"] == VERSION


def _rewrite(src: Path, dst: Path, header=None, arrays=None) -> None:
    """A copy of the map file with its header or some arrays replaced (a zip of .npy members)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            name = item.filename[:-4]
            if name == "header" and header is not None:
                data = _npy(np.frombuffer(json.dumps(header).encode(), np.uint8))
            elif arrays and name in arrays:
                data = _npy(arrays[name])
            zout.writestr(item, data)


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _bad_map_dir(tmp_path: Path, session1: Path, kind: str) -> Path:
    bad = tmp_path / f"bad_{kind}"
    bad.mkdir()
    src = session1 / "map.npz"
    if kind == "truncated":
        (bad / "map.npz").write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    elif kind == "version":
        h = read_header(src)
        h["version"] = VERSION + 1
        _rewrite(src, bad / "map.npz", header=h)
    elif kind == "altered":
        with np.load(src) as z:
            pose = z["kf_pose"].copy()
        pose[1, 0, 3] += 0.01  # one keyframe moved by 1 cm: still a valid array, but not the saved one
        _rewrite(src, bad / "map.npz", arrays={"kf_pose": pose})
    return bad


@pytest.mark.parametrize("kind, message", [
    ("truncated", "is truncated or corrupt"),
    ("version", f"is map format version {VERSION + 1}, this rgbdslam reads version {VERSION}; update rgbdslam"),
    ("altered", "is corrupt: its contents do not match the checksum in its header"),
    ("missing", "does not exist; --map takes the folder of a finished `rgbdslam run`"),
])
def test_a_bad_map_is_one_line_and_touches_nothing(session1, tmp_path, kind, message):
    bad = tmp_path / "nothing_here" if kind == "missing" else _bad_map_dir(tmp_path, session1, kind)
    out = tmp_path / "out"
    res = cli(["run", TUM_RPY200, *FR1, "--map", bad, "--localize", "--out", out, "-q", "--no-map"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, res.output
    assert res.stderr.startswith(f"error: {bad / 'map.npz'} {message}") and res.stderr.count("\n") == 1
    assert not out.exists()


def test_another_camera_is_refused(session1, tmp_path):
    res = cli(["run", TUM_RPY200, "--set", "dataset.camera=fr3", "--map", session1, "--out", tmp_path / "o", "-q"])
    assert_cli_error(res, f"{session1 / 'map.npz'} was made with camera fr1 (fx 517.3, fy 516.5, cx 318.6, cy 255.3, "
                          f"640x480), this sequence's camera is fr3 (fx 535.4, fy 539.2, cx 320.1, cy 247.6, 640x480): "
                          f"a map serves only the camera it was made with (check --config / dataset.camera)")
    assert not (tmp_path / "o").exists()


def test_map_folder_is_not_the_output(session1):
    before = _digest(session1)
    res = cli(["run", TUM_RPY200, *FR1, "--map", session1, "--out", session1, "-q"])
    assert_cli_error(res, f"--out {session1} is the folder of the map given with --map; the saved run must stay "
                          f"untouched: choose another --out")
    assert _digest(session1) == before
    assert_cli_error(cli(["run", TUM_RPY200, "--localize", "--out", session1.parent / "x", "-q"]),
                     "--localize needs --map RUN_DIR (the run whose map to localise in)")


@pytest.mark.parametrize("localize", [True, False])
def test_second_session_lands_in_the_map(session1, tmp_path, localize):
    before = _digest(session1)
    out = tmp_path / ("loc" if localize else "ext")
    cfg = _cfg("dataset.first_frame=50", "dataset.max_frames=40")
    cfg.mapping.enabled = not localize  # extending: the joined map is fused, both sessions' frames
    if not localize:
        cfg.output.rerun_save = str(tmp_path / "rec.rrd")
    s = run_sequence(TUM_RPY200, out, cfg, progress=False, map_dir=session1, localize=localize)
    assert _digest(session1) == before  # the old run is untouched
    ss = s["session"]
    assert ss["mode"] == ("localize" if localize else "extend") and ss["session"] == 1
    assert ss["relocalized"] and ss["first_localized_frame"] <= 10
    assert s["map_loops"] and all(x["session"] == 0 for x in s["map_loops"])
    traj = read_tum(out / "trajectory.tum")
    n_out = sum(b - a + 1 for a, b in ss["not_localized"])
    assert len(traj) == (s["tracked"] - n_out if localize else s["tracked"])
    # both sessions in one frame: one alignment for session 1's and session 2's poses
    assert _joint_ate(session1 / "trajectory.tum", out / "trajectory.tum") < 0.035
    if localize:
        assert s["map_file"] is None and not (out / "map.npz").exists()
        # tracked against the map: most frames registered to a map keyframe near their predicted pose
        mt = s["map_tracking"]
        assert mt["frames_tried"] == s["tracked"] - ss["first_localized_frame"]  # every frame from the first localised
        assert mt["frames_anchored"] >= 0.6 * mt["frames_tried"] and mt["edges"] >= mt["frames_anchored"]
        assert mt["rejected_prediction"] <= 2
        assert len(s["map_loops"]) >= mt["edges"]
        # their edges go to the last keyframe: an anchored frame is not made a keyframe for them
        assert len(s["keyframes"]) < mt["frames_anchored"]
        return
    m = load_map(out / "map.npz")
    assert [x["session"] for x in m.sessions] == [0, 1]
    assert m.n_keyframes == len(load_map(session1 / "map.npz").arrays["kf_frame"]) + len(s["keyframes"])
    assert set(np.unique(m.arrays["kf_segment"])) == {0}  # one connected map
    assert _joint_ate(out / "sessions" / "session_0.tum", out / "sessions" / "session_1.tum") < 0.035
    fused = s["map"]["frames_fused_per_session"]
    assert fused == {0: int(np.sum(m.arrays["kf_session"] == 0)), 1: len(s["keyframes"])}
    assert (out / "map" / "cloud.ply").stat().st_size > 0 and (out / "map" / "map2d.png").is_file()
    # Rerun: each session's trajectory apart (its own entity and colour)
    assert {"/world/trajectory/session_0", "/world/trajectory/session_1"} <= entity_paths(tmp_path / "rec.rrd")


def test_a_session_elsewhere_stays_apart(session1, tmp_path):
    """Frames of another scene (synthetic room, same fr1 camera) never relocalise: localising
    leaves every frame out, extending keeps the session as its own segment of the map."""
    from rgbdslam.datasets.synthetic import generate_sequence

    seq = tmp_path / "room"
    generate_sequence(seq, frames=12, motion="xyz", camera="fr1", seed=5)
    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "dataset.camera=fr1"])
    loc = run_sequence(seq, tmp_path / "loc", cfg, progress=False, map_dir=session1, localize=True)
    assert not loc["session"]["relocalized"] and loc["session"]["not_localized"] == [[0, 11]]
    assert not [x for x in (tmp_path / "loc" / "trajectory.tum").read_text().splitlines() if not x.startswith("#")]
    ext = run_sequence(seq, tmp_path / "ext", cfg, progress=False, map_dir=session1)
    assert not ext["session"]["relocalized"] and not ext["map_loops"]
    m = load_map(tmp_path / "ext" / "map.npz")
    seg = m.arrays["kf_segment"]
    assert set(seg[m.arrays["kf_session"] == 0]) == {0} and set(seg[m.arrays["kf_session"] == 1]) == {1}
    with pytest.raises(MapFileError, match="was made with camera fr1"):
        load_map(tmp_path / "ext" / "map.npz", camera=CAMERAS["fr3"])


@pytest.fixture(scope="module")
def landmark_runs(tmp_path_factory) -> tuple[Path, Path, dict, dict]:
    """fr1/rpy frames 0-29 mapped with the landmark map on, then frames 30-49 extending that map."""
    base = tmp_path_factory.mktemp("lm")
    s1 = run_sequence(need(TUM_RPY200), base / "s1", _cfg("dataset.max_frames=30", "landmarks.enabled=true"),
                      progress=False)
    s2 = run_sequence(TUM_RPY200, base / "s2", _cfg("dataset.first_frame=30", "dataset.max_frames=20",
                                                    "landmarks.enabled=true"),
                      progress=False, map_dir=base / "s1")
    return base / "s1", base / "s2", s1, s2


def test_landmark_section_round_trip(landmark_runs):
    from rgbdslam.session.mapfile import LANDMARK_VERSION
    from rgbdslam.session.sessions import MAP_ID_BASE, landmark_map

    s1, s2, info1, info2 = landmark_runs
    m = load_map(s1 / "map.npz")
    lm = m.landmarks
    assert read_header(s1 / "map.npz")["landmarks"]["version"] == LANDMARK_VERSION
    # every live landmark of the run, with its own statistics
    assert m.n_landmarks == info1["landmarks"]["size"] == info1["map_file"]["landmarks"] > 300
    assert set(lm["lm_session"]) == {0} and lm["lm_first"].min() >= 0 and lm["lm_last"].max() <= 29
    assert np.all(lm["lm_last"] >= lm["lm_first"]) and lm["lm_seen"].min() >= 1
    assert np.all(np.linalg.eigvalsh(lm["lm_cov"]) > 0)  # covariances stay positive definite
    # anchored to a keyframe of the map, and near where that keyframe sees it (fr1/rpy: a desk 0.5-3 m away)
    assert lm["lm_anchor"].min() >= 0 and lm["lm_anchor"].max() < m.n_keyframes
    kf = m.arrays["kf_pose"][lm["lm_anchor"]]
    in_cam = np.einsum("nji,nj->ni", kf[:, :3, :3], lm["lm_pos"] - kf[:, :3, 3])
    assert np.median(in_cam[:, 2]) > 0.4 and np.percentile(in_cam[:, 2], 5) > 0.1
    # the descriptors are the key points' own: most match a keyframe descriptor exactly
    assert np.isin(lm["lm_desc"].view("V32").ravel(), m.arrays["feat_desc"].view("V32").ravel()).mean() > 0.9
    # back into a landmark map: same landmarks, anchored to the map keyframes' ids, found by position
    lmap = landmark_map(m, _cfg())
    ids = lmap.live_ids()
    assert len(ids) == m.n_landmarks and np.array_equal(lmap.pos[ids], lm["lm_pos"])
    assert np.array_equal(lmap.seen[ids], lm["lm_seen"]) and np.all(lmap.anchor[ids] >= MAP_ID_BASE)
    assert 0 in lmap.near(lm["lm_pos"][0], 1e-6)
    # extending: the old landmarks (moved with their keyframes, re-anchored) then session 1's own
    j = load_map(s2 / "map.npz").landmarks
    old = j["lm_session"] == 0
    assert old.sum() == m.n_landmarks and (~old).sum() == info2["landmarks"]["size"] > 100
    assert np.array_equal(j["lm_desc"][old], lm["lm_desc"]) and np.array_equal(j["lm_seen"][old], lm["lm_seen"])
    assert np.abs(j["lm_pos"][old] - lm["lm_pos"]).max() < 0.1  # the pose graph moves them a little, if at all
    joined = load_map(s2 / "map.npz")
    assert np.array_equal(joined.arrays["kf_frame"][j["lm_anchor"][old]], m.arrays["kf_frame"][lm["lm_anchor"]])
    assert set(joined.arrays["kf_session"][j["lm_anchor"][~old]]) == {1}


@pytest.mark.parametrize("kind, message", [
    ("altered", "is corrupt: its landmark section does not match the checksum in its header"),
    ("missing", "is corrupt: array 'lm_cov' is missing"),
    ("version", "has landmark section version 2, this rgbdslam reads version 1; update rgbdslam"),
    ("anchor", "is corrupt: lm_anchor names a keyframe outside"),
])
def test_a_bad_landmark_section_is_one_line(landmark_runs, tmp_path, kind, message):
    s1 = landmark_runs[0]
    src, bad = s1 / "map.npz", tmp_path / "map.npz"
    h = read_header(src)
    with np.load(src) as z:
        pos, anchor = z["lm_pos"].copy(), z["lm_anchor"].copy()
    if kind == "altered":
        pos[3, 1] += 0.005
        _rewrite(src, bad, arrays={"lm_pos": pos})
    elif kind == "missing":
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bad, "w") as zout:
            for item in zin.infolist():
                if item.filename != "lm_cov.npy":
                    zout.writestr(item, zin.read(item.filename))
    elif kind == "version":
        h["landmarks"]["version"] = 2
        _rewrite(src, bad, header=h)
    else:  # a landmark anchored to a keyframe the file does not have, with a matching checksum
        from rgbdslam.session.mapfile import checksum

        anchor[0] = 10_000
        with np.load(src) as z:
            lm = {n: z[n] for n in z.files if n.startswith("lm_")}
        lm["lm_anchor"] = anchor
        h["landmarks"]["sha256"] = checksum(lm)
        _rewrite(src, bad, header=h, arrays={"lm_anchor": anchor})
    with pytest.raises(MapFileError) as e:
        load_map(bad)
    assert str(e.value).startswith(f"{bad} {message}") and "\n" not in str(e.value)
    # the keyframes' own checksum does not cover the section: a reader that ignores it still loads the map
    h0 = read_header(src)
    assert h0["sha256"] == read_header(bad)["sha256"]


def test_the_map_file_says_whether_the_cameras_depth_is_registered(session1, tmp_path):
    """The camera entry's ``depth_registered`` comes back from the file (a localising run poses frames
    against the saved landmarks with the map's camera: an unregistered one gets the 3-D refit there
    too); a map written before the key existed reads as registered."""
    h = read_header(session1 / "map.npz")
    assert h["camera"]["depth_registered"] is True
    h["camera"]["depth_registered"] = False
    _rewrite(session1 / "map.npz", tmp_path / "two.npz", header=h)
    assert not load_map(tmp_path / "two.npz").camera.depth_registered
    del h["camera"]["depth_registered"]
    _rewrite(session1 / "map.npz", tmp_path / "old.npz", header=h)
    assert load_map(tmp_path / "old.npz").camera.depth_registered


def test_map_tracking_off_leaves_loops_only(session1, tmp_path):
    """``loop.map_track_every=0``: between relocalisations only the loop closer's matches tie the
    session to the map (far fewer edges into it than with map tracking, the default)."""
    cfg = _cfg("dataset.first_frame=50", "dataset.max_frames=40", "loop.map_track_every=0")
    s = run_sequence(TUM_RPY200, tmp_path / "off", cfg, progress=False, map_dir=session1, localize=True)
    assert "map_tracking" not in s and s["session"]["relocalized"]
    # with map tracking (test_second_session_lands_in_the_map) at least 0.6 x 40 frames have an edge into the map
    assert 0 < len(s["map_loops"]) < 20


def test_map_tracker_picks_the_nearest_map_keyframes():
    """Neighbours by predicted pose: camera centres within map_track_distance, viewing directions
    within map_track_angle_deg, nearest first (distance + 0.25 m per radian)."""
    from rgbdslam.frontend.features import FrameFeatures
    from rgbdslam.geometry.se3 import make_pose
    from rgbdslam.loop.detector import build_loop_closer
    from rgbdslam.session.sessions import MAP_ID_BASE
    from rgbdslam.session.tracking import MapTracker
    from scipy.spatial.transform import Rotation

    cfg = load_config(None, ["loop.map_track_neighbours=3"])
    lc = build_loop_closer(cfg)
    rng = np.random.default_rng(0)
    # map keyframes along x every 0.3 m looking along +z; keyframe 5 at x = 0.6 turned 90 degrees
    poses = [make_pose(np.eye(3), np.array([0.3 * k, 0.0, 0.0])) for k in range(5)]
    poses.append(make_pose(Rotation.from_euler("y", 90, degrees=True).as_matrix(), np.array([0.6, 0.0, 0.0])))
    kfs = []
    for k, P in enumerate(poses):
        f = FrameFeatures(MAP_ID_BASE + k, float(k), np.zeros((10, 2)), rng.integers(0, 256, (10, 32), dtype=np.uint8),
                          np.ones((10, 3)), np.ones(10, bool), 10)
        kfs.append((f, P, 0.3 * k, 0.0, 0))
    lc.add_map_keyframes(kfs, np.concatenate([f.desc for f, *_ in kfs]), np.arange(0, 61, 10))
    lc.begin_session(map_only=True)
    mt = MapTracker(lc, cfg.loop)
    pred = make_pose(np.eye(3), np.array([0.62, 0.1, 0.0]))
    # distances 0.63, 0.33, 0.11, 0.33, 0.57 (k = 0..4); keyframe 5 is 0.10 away but looks sideways
    assert mt.neighbours(pred, set()) == [2, 3, 1]
    assert mt.neighbours(pred, {MAP_ID_BASE + 2}) == [3, 1, 4]
    tilted = make_pose(Rotation.from_euler("y", 80, degrees=True).as_matrix(), pred[:3, 3])
    assert mt.neighbours(tilted, set()) == [5]  # only the sideways keyframe looks within 45 degrees of it
    assert mt.neighbours(make_pose(np.eye(3), np.array([5.0, 0, 0])), set()) == []
    # another segment of the map (its own coordinates) is never a neighbour of this one's
    lc.keyframes[3].segment = mt.segments[3] = 1
    assert mt.neighbours(pred, set(), segment=0) == [2, 1, 4] and mt.neighbours(pred, set(), segment=1) == [3]


@pytest.mark.parametrize("array, value, message", [
    ("kf_pose", np.nan, "(kf_pose) (pose 1): the pose holds a value that is not a finite number"),
    ("kf_pose", 1e300, "(kf_pose) (pose 1): the pose has a translation beyond ±1e+09 m"),
    ("odo_T", 2.0, "(odo_T) (pose 1): the pose has no rotation matrix"),
    ("odo_info", np.nan, "is corrupt: odo_info holds a value that is not a finite number"),
    ("kf_timestamp", np.inf, "(kf_timestamp) (time stamp 1): time stamp inf is not a finite number"),
])
def test_a_crafted_map_with_a_valid_checksum_is_checked_too(session1, tmp_path, array, value, message):
    """A checksum vouches only that the file is the one written: a crafted file carries a valid
    one. Its numbers are checked as any reader's are (rgbdslam.io.validate): one line, exit 2."""
    from rgbdslam.session.mapfile import ARRAYS, checksum

    src = session1 / "map.npz"
    with np.load(src) as z:
        arrays = {n: z[n].copy() for n in ARRAYS}
    a = arrays[array]
    if array in ("odo_T", "odo_info"):
        a[1, 0, 0] = value  # a scaled rotation, an information matrix with NaN
    elif a.ndim == 3:
        a[1, 0, 3] = value
    else:
        a[1] = value
    h = read_header(src)
    h["sha256"] = checksum(arrays)
    bad = tmp_path / "crafted"
    bad.mkdir()
    _rewrite(src, bad / "map.npz", header=h, arrays={array: a})
    res = cli(["run", TUM_RPY200, *FR1, "--map", bad, "--localize", "--out", tmp_path / "out", "-q", "--no-map"])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
    assert res.stderr.startswith(f"error: {bad / 'map.npz'}") and message in res.stderr, res.stderr
    assert not (tmp_path / "out").exists()


def test_a_fifo_named_map_npz_is_refused_not_waited_on(tmp_path):
    import os
    import signal

    (tmp_path / "m").mkdir()
    os.mkfifo(tmp_path / "m" / "map.npz")

    def hang(signum, frame):
        raise TimeoutError("opening the FIFO blocked")

    previous = signal.signal(signal.SIGALRM, hang)
    signal.alarm(5)
    try:
        with pytest.raises(MapFileError, match="is not a regular file"):
            read_header(tmp_path / "m" / "map.npz")
        with pytest.raises(MapFileError, match="is not a regular file"):
            load_map(tmp_path / "m" / "map.npz")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
