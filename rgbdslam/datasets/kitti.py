"""KITTI odometry layout (Geiger et al. 2012): ``sequences/NN/image_0/`` (left),
``image_1/`` (right), ``calib.txt`` (``P0:``, ``P1:`` rectified projection matrices; baseline
``B = -P1[0,3] / P1[0,0]``), optional ``times.txt`` (else 10 Hz), ground truth
``poses/NN.txt`` beside ``sequences/`` (left camera-to-world, one 3x4 row per frame).

Give either the sequence folder (``.../sequences/06``) or a data-set root holding one sequence
(``.../odometry_06_head51``). ``image_2``/``image_3`` (the colour pair) are used instead when
the grey pair is absent.
"""

from __future__ import annotations

from pathlib import Path


from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.stereo_base import StereoSequence, check_baseline, frame_times, image_files
from rgbdslam.datasets.tum import select_frames
from rgbdslam.errors import InputError
from rgbdslam.io import validate
from rgbdslam.io.images import read_image
from rgbdslam.io.text import optional_file
from rgbdslam.geometry.stereo import StereoRig
from rgbdslam.io.kitti import read_kitti_calib, read_kitti_poses
from rgbdslam.io.trajectory import Trajectory

KITTI_HZ = 10.0
PAIRS = (("image_0", "image_1", "P0", "P1"), ("image_2", "image_3", "P2", "P3"))


def _sequence_dir(path: Path) -> Path | None:
    if (path / "calib.txt").exists() and any((path / a).is_dir() for a, *_ in PAIRS):
        return path
    seqs = path / "sequences"
    if seqs.is_dir():
        found = [p for p in sorted(seqs.iterdir()) if _sequence_dir_direct(p)]
        if len(found) == 1:
            return found[0]
    return None


def _sequence_dir_direct(p: Path) -> bool:
    return p.is_dir() and (p / "calib.txt").exists() and any((p / a).is_dir() for a, *_ in PAIRS)


def _is_kitti(path: Path) -> bool:
    return _sequence_dir(path) is not None


@reader("kitti", _is_kitti)
class KittiSequence(StereoSequence):
    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig

        cfg = cfg or DatasetConfig()
        root = Path(root)
        seq = _sequence_dir(root)
        if seq is None:
            raise InputError(f"{root} is not a KITTI odometry sequence: expected calib.txt with image_0/ and image_1/ "
                             f"(or a sequences/ folder holding one such sequence)")
        pair = next(((a, b, pa, pb) for a, b, pa, pb in PAIRS if (seq / a).is_dir()), None)
        a, b, pa, pb = pair
        if not (seq / b).is_dir():
            raise InputError(f"{seq} has {a}/ but no {b}/ (the right images); a stereo sequence needs both")
        calib = read_kitti_calib(seq / "calib.txt")
        for k in (pa, pb):
            if k not in calib:
                raise InputError(f"{seq / 'calib.txt'} has no {k}: line; KITTI calibration needs {pa}: and {pb}: "
                                 f"(3x4 projection matrices)")
        P0, P1 = calib[pa], calib[pb]
        fx = P0[0, 0]
        for k, P in ((pa, P0), (pb, P1)):  # the rectified pair's pinhole cameras, before any image is read
            validate.camera(P[0, 0], P[1, 1], P[0, 2], P[1, 2], 1, 1, where=f"{seq / 'calib.txt'} ({k})")
        baseline = check_baseline(-(P1[0, 3] - P0[0, 3]) / P1[0, 0], seq / "calib.txt")
        left, right = image_files(seq / a), image_files(seq / b)
        if len(left) != len(right):
            raise InputError(f"{seq} has {len(left)} left images ({a}/) and {len(right)} right images ({b}/); "
                             f"a stereo sequence needs one right image per left image")
        if not left:
            raise InputError(f"{seq / a} holds no images")
        n = len(left)
        ts = frame_times(seq / "times.txt", n, KITTI_HZ)
        gt_all = None
        gt_path = seq.parent.parent / "poses" / f"{seq.name}.txt"
        if optional_file(gt_path, "KITTI pose file") is not None:
            gt_all = read_kitti_poses(gt_path)
        keep = select_frames(n, cfg, seq)
        first, why = read_image(left[0])
        if first is None:
            raise InputError(f"left image {left[0]} cannot be decoded ({why}); replace it with a valid PNG")
        h, w = first.shape[:2]
        cam = validate.camera(float(fx), float(P0[1, 1]), float(P0[0, 2]), float(P0[1, 2]), w, h,
                              name=f"kitti_{seq.name}", where=f"{seq / 'calib.txt'} ({pa})")
        gt = None
        if gt_all is not None:
            m = min(len(gt_all), n)
            sel = keep[keep < m]
            # poses of the left camera (P0) of frame k; a KITTI pose file starts at frame 0 = identity
            gt = Trajectory(ts[sel], gt_all[sel])
        super().__init__(seq, f"kitti_{seq.name}", StereoRig(cam, baseline), ts[keep], [left[k] for k in keep],
                         [right[k] for k in keep], gt)
