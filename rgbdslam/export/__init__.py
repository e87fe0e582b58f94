"""Exports of a finished run folder into the formats other tools read (``rgbdslam export``).

One module per family of formats, each a function ``write_<format>(run, out_dir) -> [paths]``
over a :class:`~rgbdslam.export.run.RunExport` (the run folder read once):

- :mod:`.trajectories`  TUM, KITTI (``poses.txt`` + ``times.txt``), EuRoC CSV, evo's result zip
- :mod:`.colmap`        COLMAP text model (``sparse/0/cameras.txt, images.txt, points3D.txt`` + ``images/``)
- :mod:`.nerfstudio`    nerfstudio / Instant-NGP ``transforms.json`` + keyframe images and depth
- :mod:`.maps`          the fused map as PCD (cloud), OBJ and GLB (mesh)

Every file is written atomically, and a format that writes a folder (colmap/, nerfstudio/)
builds it beside its final place and swaps it in only when complete: an interrupted export
leaves the earlier export as it was.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from rgbdslam.errors import InputError

# name -> (module, function, one-line description); modules are imported when used
FORMATS: dict[str, tuple[str, str, str]] = {
    "tum": ("trajectories", "write_tum_export", "trajectory.tum: 'timestamp tx ty tz qx qy qz qw' (TUM RGB-D)"),
    "kitti": ("trajectories", "write_kitti_export", "poses.txt (3x4 camera-to-world per line) and times.txt (KITTI)"),
    "euroc": ("trajectories", "write_euroc_export", "trajectory.csv: ns, position, quaternion w x y z (EuRoC)"),
    "evo": ("trajectories", "write_evo_export",
            "evo_ape.zip: evo's APE result against the ground truth, for evo_res (needs evo and ground truth)"),
    "colmap": ("colmap", "write_colmap", "colmap/: images/ and sparse/0/{cameras,images,points3D}.txt"),
    "nerfstudio": ("nerfstudio", "write_nerfstudio",
                   "nerfstudio/: transforms.json, images/, depth/ (16-bit mm), sparse_pc.ply (also Instant-NGP)"),
    "pcd": ("maps", "write_pcd", "cloud.pcd: the fused coloured cloud (PCL)"),
    "obj": ("maps", "write_obj", "mesh.obj: the TSDF mesh with vertex colours"),
    "glb": ("maps", "write_glb", "mesh.glb: the TSDF mesh as binary glTF"),
}


def parse_formats(items: tuple[str, ...] | list[str]) -> list[str]:
    """``--format`` values (repeatable, comma-separated, ``all``) -> format names in FORMATS order."""
    wanted: list[str] = []
    for item in items:
        for name in (s.strip().lower() for s in item.split(",")):
            if not name:
                continue
            if name == "all":
                wanted.extend(FORMATS)
            elif name not in FORMATS:
                raise InputError(f"unknown export format '{name}'; choose from {', '.join(FORMATS)} (or all)")
            else:
                wanted.append(name)
    if not wanted:
        raise InputError(f"give at least one --format: {', '.join(FORMATS)} (or all)")
    return [f for f in FORMATS if f in wanted]


def writer(name: str) -> Callable:
    import importlib

    module, func, _ = FORMATS[name]
    return getattr(importlib.import_module(f"rgbdslam.export.{module}"), func)


def _check(run, name: str) -> None:
    """Raise InputError when the run lacks what format ``name`` needs."""
    if name == "evo":
        from rgbdslam.export.trajectories import check_evo

        check_evo(run)
    elif name == "pcd":
        run.map_file("cloud.ply")
    elif name in ("obj", "glb"):
        run.map_file("mesh.ply")
    elif name in ("colmap", "nerfstudio"):
        run.keyframes  # opens the sequence and matches the keyframes to the trajectory  # noqa: B018


def export_run(run_dir: str | Path, formats: list[str], out_dir: str | Path | None = None,
               max_points: int = 100_000, progress: bool = True) -> dict[str, list[Path]]:
    """Write the exports ``formats`` of the run folder ``run_dir`` into ``out_dir``
    (default RUN_DIR/export); returns the written paths per format."""
    from rgbdslam.export.run import RunExport

    run = RunExport(run_dir, max_points=max_points, progress=progress)
    out = Path(out_dir) if out_dir is not None else run.run_dir / "export"
    for name in formats:  # every format's inputs first: a missing one stops the export before any file is written
        _check(run, name)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, list[Path]] = {}
    for name in formats:
        written[name] = writer(name)(run, out)
    return written
