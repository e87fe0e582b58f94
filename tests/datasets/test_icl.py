"""ICL-NUIM's TUM-compatible archives, written here in the data set's exact layout and
conventions from the project's synthetic renderer: ``rgb/N.png``, ``depth/N.png`` (5000 per
metre), ``associations.txt`` ('N depth/N.png N rgb/N.png'), and the ground truth whose first
column is the frame number and whose poses live in the renderer's y-up world (the images' poses
reflected about the XZ plane, T -> F T F, F = diag(1, -1, 1)). The living-room layout counts
frames from 0 (``livingRoom2.gt.freiburg``), the office layout from 1 (``traj0.gt.freiburg``)."""

from __future__ import annotations

import csv
import json
import zipfile

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import cli
from rgbdslam.datasets import describe_sequence, open_sequence
from rgbdslam.datasets.synthetic import Rays, Scene, make_trajectory
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.io.trajectory import Trajectory, read_tum, write_tum

# ICL-NUIM's published intrinsics (fy positive: the PNGs are stored top-down)
ICL_CAMERA = Camera(481.20, 480.00, 319.5, 239.5, 640, 480, (0.0,) * 5, "icl_nuim")
F = np.diag([1.0, -1.0, 1.0, 1.0])


def helix(frames: int) -> np.ndarray:
    """Camera-to-world poses along a helix (one turn of radius 0.15 m rising 0.3 m, the view
    turning +-0.15 rad) from the synthetic room's usual start pose. A helix is chiral: its mirror
    image is no rigid motion of it, so a ground truth left reflected cannot be aligned onto it
    (a short arc or a planar path could: a plane's mirror image is a rotation of it)."""
    start = make_trajectory("xyz", 1)[0]
    u = np.linspace(0.0, 1.0, frames)
    poses = np.repeat(start[None], frames, axis=0)
    poses[:, :3, 3] += np.stack([0.15 * np.cos(2 * np.pi * u) - 0.15, 0.15 * np.sin(2 * np.pi * u), 0.3 * u], 1)
    turn = Rotation.from_rotvec(np.outer(0.15 * np.sin(2 * np.pi * u), [0.0, 0.0, 1.0])).as_matrix()
    poses[:, :3, :3] = turn @ start[:3, :3]
    return poses


def write_icl(root, frames: int, first: int, gt_name: str, seed: int = 3, associations: bool = True) -> np.ndarray:
    """An ICL-NUIM folder of ``frames`` frames numbered from ``first`` (without ``associations``
    the frames are the numbers that have both images); returns the true camera-to-world poses of
    the images (the y-down world the images are rendered in)."""
    poses = helix(frames)
    scene, rays = Scene(seed), Rays(ICL_CAMERA)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    assoc, gt = [], []
    for k, T in enumerate(poses):
        n = first + k
        rgb, depth, _ = scene.render(rays, T)
        cv2.imwrite(str(root / "rgb" / f"{n}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "depth" / f"{n}.png"), np.round(depth * 5000).astype(np.uint16))
        assoc.append(f"{n} depth/{n}.png {n} rgb/{n}.png\n")
        Ty = F @ T @ F  # as the data set publishes it: the renderer's y-up world
        q = Rotation.from_matrix(Ty[:3, :3]).as_quat()  # x y z w
        gt.append(f"{n} " + " ".join(f"{v:.9f}" for v in (*Ty[:3, 3], *q)) + "\n")
    if associations:
        (root / "associations.txt").write_text("".join(assoc))
    (root / gt_name).write_text("".join(gt))
    return poses


@pytest.fixture(scope="module")
def living_room(tmp_path_factory):
    root = tmp_path_factory.mktemp("icl") / "living_room_traj2_frei_png"
    return root, write_icl(root, 40, 0, "livingRoom2.gt.freiburg")


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    root = tmp_path_factory.mktemp("icl") / "traj0_frei_png"
    return root, write_icl(root, 12, 1, "traj0.gt.freiburg", seed=5, associations=False)


@pytest.mark.parametrize("which", ["living_room", "office"])
def test_frames_are_numbered_at_30_hz_and_the_ground_truth_is_reflected(which, request):
    root, poses = request.getfixturevalue(which)
    first = 0 if which == "living_room" else 1
    seq = open_sequence(root)
    n = np.arange(first, first + len(poses))
    np.testing.assert_allclose(seq.timestamps, n / 30.0, rtol=0, atol=1e-12)
    assert (seq.camera.fx, seq.camera.fy, seq.camera.cx) == (481.2, 480.0, 319.5)
    frame = seq.load(5)  # image N.png <-> pose N: frame 5 is the file numbered first + 5
    assert frame.name == f"rgb/{first + 5}.png"
    assert abs(float(np.median(frame.depth[frame.depth > 0])) - float(np.median(
        cv2.imread(str(root / "depth" / f"{first + 5}.png"), cv2.IMREAD_UNCHANGED)[frame.depth > 0])) / 5000) < 1e-6
    gt = seq.groundtruth()
    np.testing.assert_allclose(gt.timestamps, n / 30.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gt.poses, poses, atol=1e-6)  # reflected back into the images' world
    assert "reflected about the XZ plane" in seq.groundtruth_convention


@pytest.mark.slow
def test_run_batch_table_and_export_agree_on_the_right_ate(living_room, office, tmp_path):
    """Both layouts in one `rgbdslam run`, no flags: the frames are tracked (synthetic, exact
    depth) and the ATE against the converted ground truth is millimetres (0.096 m against the
    published y-up poses: no rigid alignment undoes a reflection); the batch table, evaluation.json
    and the evo export (which reads the ground truth again through the reader) agree."""
    (root, poses), (office_root, office_poses) = living_room, office
    res = cli(["run", root, office_root, "--out", tmp_path / "runs", "--no-map", "-q"])
    assert res.exit_code == 0, res.output
    rows = {r["sequence"]: r for r in csv.DictReader(open(tmp_path / "runs" / "summary.csv"))}
    for seq, p, first in ((root, poses, 0), (office_root, office_poses, 1)):
        run = tmp_path / "runs" / seq.name
        s = json.loads((run / "run.json").read_text())
        ev = json.loads((run / "evaluation.json").read_text())
        assert s["tracked"] == len(p) and ev["ate"]["n_pairs"] == len(p)
        assert ev["ate"]["rmse"] < 0.005, ev["ate"]
        assert float(rows[str(seq)]["ate_rmse"]) == pytest.approx(ev["ate"]["rmse"], abs=1e-6)
        est = read_tum(run / "trajectory.tum")
        np.testing.assert_allclose(est.timestamps, np.arange(first, first + len(p)) / 30.0, atol=1e-6)
    assert "livingRoom2.gt.freiburg read as ICL-NUIM" in res.output and "traj0.gt.freiburg read as" in res.output
    run = tmp_path / "runs" / root.name
    assert cli(["export", run, "-f", "evo", "-q"]).exit_code == 0
    evo = json.loads(zipfile.ZipFile(run / "export" / "evo_ape.zip").read("stats.json"))
    ours = json.loads((run / "evaluation.json").read_text())["ate"]["rmse"]
    assert evo["rmse"] == pytest.approx(ours, rel=1e-3, abs=1e-6)


def test_evaluate_agrees_for_the_folder_and_the_gt_freiburg_file(office, tmp_path):
    """`rgbdslam evaluate` on the office layout (frames from 1): the true trajectory of the
    images, stamped N/30 s, has an ATE of zero without any alignment, whether the ground truth
    is given as the sequence folder or as ICL-NUIM's own file."""
    root, poses = office
    est = tmp_path / "true.tum"
    write_tum(Trajectory(np.arange(1, 1 + len(poses)) / 30.0, poses), est)
    for gt in (root, root / "traj0.gt.freiburg"):
        out = tmp_path / f"{gt.name}.json"
        res = cli(["evaluate", gt, est, "--align", "none", "--json", out])
        assert res.exit_code == 0, res.output
        assert "traj0.gt.freiburg read as ICL-NUIM: frame N at N/30 s" in res.output
        ate = json.loads(out.read_text())["ate"]
        assert ate["n_pairs"] == len(poses) and ate["rmse"] < 1e-6, ate


def test_info_says_30_hz_and_the_convention(living_room):
    root, poses = living_room
    text = describe_sequence(root)
    assert "reader      IclSequence" in text
    assert "frames      40 over 1.30 s (30.8 Hz)" in text  # 40 frames, 39 intervals of 1/30 s
    assert "groundtruth 40 poses (livingRoom2.gt.freiburg read as ICL-NUIM" in text


def test_associations_in_either_order_and_a_bad_line_named(tmp_path):
    root = tmp_path / "living_room_traj0_frei_png"
    write_icl(root, 3, 0, "livingRoom0.gt.freiburg")
    (root / "associations.txt").write_text("0 rgb/0.png 0 depth/0.png\n1 rgb/1.png 1 depth/1.png\n")
    seq = open_sequence(root)
    assert len(seq) == 2 and seq.depth_files[1].name == "1.png" and seq.depth_files[1].parent.name == "depth"
    (root / "associations.txt").write_text("0 depth/0.png 0 rgb/0.png\n1 depth/1.png 2 rgb/2.png\n")
    with pytest.raises(InputError, match=r"associations.txt:2: expected 'N depth/N.png N rgb/N.png'"):
        open_sequence(root)
    (root / "livingRoom0.gt.freiburg").write_text("0.5 0 0 0 0 0 0 1\n")
    (root / "associations.txt").unlink()
    with pytest.raises(InputError, match="the first column of an ICL-NUIM ground truth is the frame number"):
        open_sequence(root).groundtruth()
