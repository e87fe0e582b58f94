"""Sequence readers behind one interface (``base.Sequence``), one module per source, and
:func:`open_sequence`, which picks the reader for a folder.

Each source's module declares its reader with :func:`rgbdslam.datasets.registry.reader`:
``tum`` (TUM RGB-D layout, also what ``rgbdslam synth`` writes, and ETH3D SLAM), ``icl``
(ICL-NUIM's TUM-compatible archives: frame numbers, a y-up world), ``put`` (POZNAN/PUT Kinect layout), ``7scenes`` (Microsoft 7-Scenes) and
``rosbag`` (ROS 1 / ROS 2 bags and RealSense recordings); stereo: ``kitti`` (KITTI odometry),
``euroc`` (EuRoC/ASL) and ``stereo`` (a plain left/right folder), which compute depth from the
pair (``datasets.stereo_base``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.datasets.registry import READERS
from rgbdslam.errors import InputError


def available() -> list[str]:
    _load_builtin()
    return sorted(READERS)


def _load_builtin() -> None:
    # Importing the modules declares their readers (tum first: it is tried first).
    from rgbdslam.datasets import tum  # noqa: F401
    from rgbdslam.datasets import icl  # noqa: F401  (asked before tum: a special case of its layout)
    from rgbdslam.datasets import put  # noqa: F401
    from rgbdslam.datasets import sevenscenes  # noqa: F401
    from rgbdslam.datasets import rosbag  # noqa: F401
    from rgbdslam.datasets import euroc, kitti, stereo_folder  # noqa: F401  (stereo readers)


def detect_kind(path: Path, cfg) -> str | None:
    """The reader for ``path``: ``cfg.kind`` (the dataset section) unless it is ``auto``, else the
    first reader that recognises the folder (None: none does)."""
    _load_builtin()
    if cfg.kind not in ("auto", "synthetic"):
        return cfg.kind
    return next((n for n, (detect, _) in READERS.items() if detect(Path(path))), None)


def check_sequence_path(path: str | Path) -> Path:
    """``path`` when it is a folder or a recording a reader takes (.bag, .db3, .mcap); InputError
    otherwise. Every command that takes sequences (run, info, sweep) checks them this one way."""
    _load_builtin()
    path = Path(path)
    if not path.exists():
        raise InputError(f"sequence folder {path} does not exist; check the path (TUM data sets live under ../shared/data/tum)")
    if not path.is_dir() and not any(detect(path) for detect, _ in READERS.values()):
        raise InputError(f"{path} is not a folder or a known recording (.bag, .db3, .mcap); give the sequence's "
                         f"folder (the one with rgb.txt or matched) or a bag")
    return path


def open_sequence(path: str | Path, cfg=None, purpose: str = "track") -> Sequence:
    """Open the sequence in ``path`` with the reader named by ``cfg.kind`` (or detected).

    ``cfg`` is the dataset section, or the whole config: stereo readers then also take their
    depth method from it (``stereo.depth``; ``stereo.map_depth`` with ``purpose="map"``)."""
    from rgbdslam.datasets.config import DatasetConfig

    _load_builtin()
    full = cfg if hasattr(cfg, "dataset") else None  # the whole config (its sections), not the dataset section
    cfg = full.dataset if full is not None else (cfg or DatasetConfig())
    path = check_sequence_path(path)
    kind = detect_kind(path, cfg)
    if kind is None:
        raise InputError(
            f"{path} is not a known sequence layout: expected rgb.txt and depth.txt, or rgb/ and depth/ "
            f"with time-stamp-named PNGs (TUM, ETH3D), rgb/N.png with a *.gt.freiburg (ICL-NUIM), "
            f"frame-NNNNNN.color.jpg (7-Scenes), "
            f"a 'matched' file (PUT), a ROS bag (metadata.yaml, .bag, .db3, .mcap), calib.txt with image_0/ "
            f"and image_1/ (KITTI), mav0/cam0 and mav0/cam1 (EuRoC), or left/, right/ and stereo.yaml (stereo)"
        )
    if kind not in READERS:
        raise InputError(f"unknown dataset kind '{kind}'; choose one of {', '.join(available())}")
    seq = READERS[kind][1](path, cfg)
    if full is not None:
        seq.configure(full, purpose)
    return seq


def describe_sequence(path: str | Path, cfg=None) -> str:
    """A few lines on a sequence: reader, camera, frames, span, ground truth."""
    seq = open_sequence(path, cfg)
    ts = seq.timestamps
    cam = seq.camera
    gt = seq.groundtruth()
    span = float(ts[-1] - ts[0]) if len(ts) else 0.0
    setup = seq.camera_setup
    lines = [
        f"sequence    {seq.root}",
        f"reader      {type(seq).__name__}",
        f"camera      {cam.name or 'custom'}: fx {cam.fx} fy {cam.fy} cx {cam.cx} cy {cam.cy}, "
        f"{cam.width}x{cam.height}, distortion {' '.join(f'{d:g}' for d in cam.dist)}"
        + (f" (from {setup.source})" if setup is not None else "")
        + ("; depth re-projected into colour" if setup is not None and setup.depth_camera is not None else ""),
        f"frames      {len(seq)} over {span:.2f} s ({len(seq) / span if span > 0 else 0:.1f} Hz)",
        f"groundtruth {f'{len(gt)} poses' if gt is not None else 'none'}"
        + (f" ({seq.groundtruth_convention})" if gt is not None and seq.groundtruth_convention else ""),
    ]
    if len(seq):
        from rgbdslam.stereo.depth import frame_warning

        first = seq.load(0)
        valid = first.depth[first.depth > 0]
        if seq.rig is not None:  # stereo: the pair's geometry and the depth method
            lines.append(f"stereo      baseline {seq.rig.baseline:.4f} m, depth from the pair: {seq.method} "
                         f"(sigma {first.depth_noise.sigma(10.0):.3f} m at 10 m)")
            lines.append(f"depth       frame 0: {valid.size} pixels, median "
                         f"{float(np.median(valid)) if valid.size else 0:.2f} m")
        else:
            lines.append(f"depth       frame 0: {valid.size / first.depth.size:.0%} valid, median "
                         f"{float(np.median(valid)) if valid.size else 0:.2f} m")
        warning = frame_warning(first)
        if warning:
            lines.append(f"warning     {warning}")
    if setup is not None and setup.fallback_warning():
        lines.append(f"warning     {setup.fallback_warning()}")
    return "\n".join(lines)


__all__ = ["Frame", "Sequence", "open_sequence", "detect_kind", "available", "describe_sequence"]
