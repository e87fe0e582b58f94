"""The folder a map is made in: every file of one fusion is written into a temporary folder inside
the map folder and moved into place only when all of them are complete (:func:`staged`), so a
failure or Ctrl-C part-way leaves the earlier map as it was and the folder never mixes two
fusions; and what a fusion made (:class:`FuseResult`). Apart from :mod:`rgbdslam.mapping.fusion`
because it needs neither Open3D nor OpenCV: the run process of a live map (:mod:`rgbdslam.mapping.live`)
makes the folder and gets the map from the map and cloud processes without importing Open3D (~1 s
of CPU after the last frame)."""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rgbdslam.io.atomic import interrupts_deferred, make_dirs


@dataclass
class FuseResult:
    """What a fusion (:func:`rgbdslam.mapping.fusion.fuse`, the live map) wrote and what it cost."""

    out_dir: Path
    cloud_path: Path | None
    mesh_path: Path | None
    map2d_path: Path | None
    frames: list[int]  # sequence indices that were fused
    n_points: int
    n_vertices: int
    n_triangles: int
    seconds: float
    peak_rss_mb: float  # process peak resident memory (ru_maxrss) after fusing
    rss_growth_mb: float  # peak RSS minus the RSS when fusion started (upper bound on fusion's own use)
    timings: dict[str, float] = field(default_factory=dict)
    cloud_points: np.ndarray | None = None  # (N, 3) float32, world frame
    cloud_colors: np.ndarray | None = None  # (N, 3) uint8 RGB
    map2d: Any = None  # Map2D when the 2-D map was made
    sessions: dict[int, int] | None = None  # frames fused per session (a map joined over sessions)

    def summary(self) -> dict[str, Any]:
        return {
            "frames_fused": len(self.frames),
            "cloud_points": self.n_points,
            "mesh_vertices": self.n_vertices,
            "mesh_triangles": self.n_triangles,
            "seconds": round(self.seconds, 3),
            "peak_rss_mb": round(self.peak_rss_mb, 1),
            "rss_growth_mb": round(self.rss_growth_mb, 1),
            "timings": {k: round(v, 3) if isinstance(v, float) else v for k, v in self.timings.items()},
            "cloud": str(self.cloud_path) if self.cloud_path else None,
            "mesh": str(self.mesh_path) if self.mesh_path else None,
            "map2d": str(self.map2d_path) if self.map2d_path else None,
            **({"frames_fused_per_session": self.sessions} if self.sessions else {}),
        }


# the files a fusion writes into its folder: all of them come from one fusion (see _commit)
# (cloud.png and mesh.png are the renders of `fuse --render`: a new fusion removes older ones)
MAP_FILES = ("cloud.ply", "mesh.ply", "map2d.png", "map2d.yaml", "map2d_preview.png", "cloud.png", "mesh.png")
STAGE_PREFIX = ".fusing-"  # + the fusing process's id: the temporary folder a map is made in


def remove_stale_stages(out_dir: Path) -> None:
    """Remove the temporary folders that fusions killed part-way left in ``out_dir`` (their
    process is gone; a folder of a fusion still running is left alone)."""
    for d in out_dir.glob(f"{STAGE_PREFIX}*"):
        pid = d.name[len(STAGE_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and _alive(int(pid)):
            continue
        shutil.rmtree(d, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _commit(stage: Path, out_dir: Path) -> None:
    """Move the finished map files from ``stage`` into ``out_dir`` and remove the files of
    :data:`MAP_FILES` this fusion did not make (an older mesh, a 2-D map made with other
    settings), so the folder never mixes two fusions. Nothing is computed here, so nothing
    can fail part-way: only renames, after every file was written completely."""
    made = [name for name in MAP_FILES if (stage / name).is_file()]
    with interrupts_deferred():  # a Ctrl-C waits for the renames: never half an old, half a new map
        for name in made:
            os.replace(stage / name, out_dir / name)
        for name in MAP_FILES:  # checked to be ours by the caller (rgbdslam.mapping.fusion.map_of); a link stays a link
            if name not in made and ((out_dir / name).is_file() or (out_dir / name).is_symlink()):
                (out_dir / name).unlink()


def staged(out_dir: Path, work) -> FuseResult:
    """Run ``work(stage)`` writing into a temporary folder inside ``out_dir``, then move its files
    into place (:func:`_commit`); a failure or Ctrl-C part-way leaves the earlier map as it was."""
    created = not out_dir.exists()
    make_dirs(out_dir)
    remove_stale_stages(out_dir)
    stage = Path(tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=out_dir))
    try:
        res = work(stage)
        _commit(stage, out_dir)
    except BaseException as e:
        shutil.rmtree(stage, ignore_errors=True)
        if created and not any(out_dir.iterdir()):
            out_dir.rmdir()  # a failed first fusion leaves no empty map folder
        if isinstance(e, OSError) and e.filename and Path(e.filename).parent == stage:
            # a full disk while writing: name the map file, not the temporary folder it was made in
            raise OSError(e.errno, e.strerror, str(out_dir / Path(e.filename).name)) from None
        raise
    shutil.rmtree(stage, ignore_errors=True)
    res.out_dir = out_dir
    for attr in ("cloud_path", "mesh_path", "map2d_path"):
        if getattr(res, attr) is not None:
            setattr(res, attr, out_dir / getattr(res, attr).name)
    return res
