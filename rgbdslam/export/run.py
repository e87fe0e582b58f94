"""A finished run folder, read once for the exports: trajectory, keyframes, views, map."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Iterator

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.io.atomic import in_final_place, interrupts_deferred, plain_permissions
from rgbdslam.io.trajectory import Trajectory

DEPTH_MM = 1000.0  # exported depth PNGs: 16-bit millimetres (nerfstudio's default depth_unit_scale_factor 1e-3)


@dataclass
class View:
    """One keyframe as exported: images remapped to the ideal pinhole ``camera``."""

    index: int  # frame index in the sequence
    timestamp: float
    pose: np.ndarray  # camera-to-world (OpenCV axes: x right, y down, z forward)
    rgb: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, 0 = none


class RunExport:
    """What the exporters read of a run folder (see ``docs/formats.md``)."""

    def __init__(self, run_dir: str | Path, max_points: int = 100_000, progress: bool = True):
        from rgbdslam.runfolder.read import read_run

        self.run_dir = Path(run_dir)
        if max_points < 1:
            raise InputError(f"--max-points must be at least 1 (got {max_points})")
        self.max_points = int(max_points)
        self.progress = progress
        self.info, self.cfg, self.trajectory = read_run(self.run_dir)
        self._plys: dict[str, dict[str, np.ndarray]] = {}

    # ------------------------------------------------------------------ the sequence
    @cached_property
    def sequence(self):
        from rgbdslam.datasets import open_sequence
        from rgbdslam.runfolder.read import check_run_frames

        try:
            seq = open_sequence(self.info["sequence"], self.cfg.dataset)
        except InputError as e:
            raise InputError(f"this export needs the run's images, but the sequence cannot be opened: {e}") from None
        check_run_frames(self.run_dir, self.info, len(seq))
        return seq

    @property
    def camera(self) -> Camera:
        """The pinhole the exported images follow: the sequence's camera without distortion
        (images are remapped when the camera has distortion, as in map fusion)."""
        c = self.sequence.camera
        return Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height, (0.0,) * 5, c.name)

    def groundtruth(self) -> Trajectory | None:
        return self.sequence.groundtruth()

    # ------------------------------------------------------------------ keyframes
    @cached_property
    def keyframes(self) -> list[tuple[int, int]]:
        """``(frame index, trajectory row)`` of the run's keyframes that have a pose and lie in a
        tracking segment of the map (as map fusion chooses them; every tracked frame picked by
        motion when run.json lists no keyframes)."""
        from rgbdslam.mapping.fusion import match_frames, select_by_motion

        rows = match_frames(np.asarray(self.sequence.timestamps), self.trajectory)
        kfs = [int(i) for i in self.info.get("keyframes") or []]
        if not kfs:
            tracked = np.flatnonzero(rows >= 0)
            m = self.cfg.mapping
            pick = select_by_motion(self.trajectory.poses[rows[tracked]], m.select_translation, m.select_rotation_deg)
            kfs = [int(tracked[k]) for k in pick]
        off = [g for g in self.info.get("segments") or [] if not g.get("map", True)]
        out = [(i, int(rows[i])) for i in kfs
               if rows[i] >= 0 and not any(g["first"] <= i <= g["last"] for g in off)]
        if not out:
            raise InputError(f"{self.run_dir / 'run.json'}: no keyframe has a pose in trajectory.tum; "
                             f"re-run `rgbdslam run` to rewrite the run folder")
        return out

    def views(self) -> Iterator[View]:
        """The keyframes' colour and depth (the run's DIF-filtered depth where it saved one),
        undistorted to :attr:`camera`, one at a time."""
        from rgbdslam.mapping.fusion import Undistorter
        from rgbdslam.runfolder.depth import keyframe_depth_path, read_keyframe_depth
        from rgbdslam.ui import frame_progress

        seq = self.sequence
        undistort = Undistorter(seq.camera, True)
        depth_dir = self.run_dir / "keyframes"
        with frame_progress(len(self.keyframes), "exporting keyframes", enabled=self.progress) as advance:
            for i, r in self.keyframes:
                frame = seq.load(i)
                depth = frame.depth
                png = keyframe_depth_path(depth_dir, i)
                if png.is_file():
                    depth = read_keyframe_depth(png)
                rgb, depth = undistort(frame.rgb, depth.astype(np.float32, copy=False))
                if rgb.ndim == 2:  # grey images (stereo): three equal channels for the tools downstream
                    rgb = np.repeat(rgb[:, :, None], 3, axis=2)
                yield View(i, float(self.trajectory.timestamps[r]), self.trajectory.poses[r], rgb, depth)
                advance()

    # ------------------------------------------------------------------ map
    def map_file(self, name: str) -> Path:
        p = self.run_dir / "map" / name
        if not p.is_file():
            raise InputError(f"{p} is missing; make the map first with `rgbdslam fuse {self.run_dir}`"
                             + (" (mapping.mesh=true)" if name == "mesh.ply" else ""))
        return p

    def map_ply(self, name: str) -> dict[str, np.ndarray]:
        """map/``name`` read (:func:`rgbdslam.io.ply.read_ply`, once); an InputError names a
        missing, cut-short or damaged file."""
        from rgbdslam.io.ply import read_ply

        if name not in self._plys:
            p = self.map_file(name)
            try:
                self._plys[name] = read_ply(p)
            except ValueError as e:
                raise InputError(f"{p} is damaged ({e}); make the map again with `rgbdslam fuse {self.run_dir}`"
                                 ) from None
        return self._plys[name]

    def points(self, seed: int = 0) -> tuple[np.ndarray, np.ndarray, str]:
        """At most ``max_points`` coloured points (float64 (N, 3), uint8 (N, 3)) for a sparse
        model: the fused cloud (map/cloud.ply) subsampled with a seeded choice, else the keyframes'
        depth back-projected; and a word on where they came from."""
        cloud = self.run_dir / "map" / "cloud.ply"
        if cloud.is_file():
            ply = self.map_ply("cloud.ply")
            P, C = ply["points"], ply.get("colors", np.zeros((0, 3)))
            source = f"{cloud} (subsampled)" if len(P) > self.max_points else str(cloud)
            C = (np.clip(C, 0, 1) * 255 + 0.5).astype(np.uint8) if len(C) == len(P) else np.full((len(P), 3), 128,
                                                                                                np.uint8)
        else:
            P, C = self._backprojected()
            source = "keyframe depth (no map/cloud.ply)"
        if len(P) > self.max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(P), self.max_points, replace=False))
            P, C = P[keep], C[keep]
        return np.asarray(P, np.float64), np.asarray(C, np.uint8), source

    def _backprojected(self) -> tuple[np.ndarray, np.ndarray]:
        from rgbdslam.mapping.fusion import VoxelCloud, backproject_image

        m = self.cfg.mapping
        acc = VoxelCloud(m.voxel_size)
        cam = self.camera
        for v in self.views():
            d = np.where((v.depth >= m.depth_min) & (v.depth <= m.depth_max), v.depth, 0).astype(np.float32)
            pts, flat = backproject_image(d, cam, m.cloud_pixel_stride)
            acc.add(pts @ v.pose[:3, :3].T.astype(np.float32) + v.pose[:3, 3].astype(np.float32),
                    v.rgb.reshape(-1, 3)[flat])
        P, C = acc.result()
        if len(P) == 0:
            raise InputError(f"no keyframe of {self.run_dir} has depth between mapping.depth_min and "
                             f"mapping.depth_max; nothing to export as points")
        return P, C


@contextlib.contextmanager
def staged_folder(final: Path) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``final``; on success it replaces ``final`` (an
    earlier folder there is removed only after the new one is in place)."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=final.parent))
    try:
        try:
            yield stage
        except OSError as e:  # a full disk: name the file in its final place, not in our temporary folder
            raise in_final_place(e, stage, final) from None
        plain_permissions(stage)
        old = None
        with interrupts_deferred():
            if final.exists():
                if not final.is_dir():
                    raise InputError(f"{final} exists and is not a folder; move it away or choose another --out")
                old = Path(tempfile.mkdtemp(prefix=f".{final.name}-old-", dir=final.parent))
                os.replace(final, old / final.name)
            os.replace(stage, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)
