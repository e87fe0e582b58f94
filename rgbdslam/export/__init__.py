"""Exports of a finished run folder into the formats other tools read (``rgbdslam export``).

One module per family of formats, each a function ``write_<format>(run, out_dir) -> [paths]``
over a :class:`~rgbdslam.export.run.RunExport` (the run folder read once):

- :mod:`.trajectories`  TUM, KITTI (``poses.txt`` + ``times.txt``), EuRoC CSV, evo's result zip
- :mod:`.colmap`        COLMAP text model (``sparse/0/cameras.txt, images.txt, points3D.txt`` + ``images/``)
- :mod:`.nerfstudio`    nerfstudio / Instant-NGP ``transforms.json`` + keyframe images and depth
- :mod:`.maps`          the fused map as PCD (cloud), OBJ and GLB (mesh)

Every file is written atomically, and a format that writes a folder (colmap/, nerfstudio/)
builds it beside its final place and swaps it in only when complete: an interrupted export
leaves the earlier export as it was. What an export may replace and what it refuses:
docs/outputs.md.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable

from rgbdslam.errors import InputError
from rgbdslam.io.atomic import make_dirs
from rgbdslam.io.manifest import EXPORT, Manifest

# name -> (module, function, one-line description, what it writes into --out); modules are imported when used
FORMATS: dict[str, tuple[str, str, str, tuple[str, ...]]] = {
    "tum": ("trajectories", "write_tum_export", "trajectory.tum: 'timestamp tx ty tz qx qy qz qw' (TUM RGB-D)",
            ("trajectory.tum",)),
    "kitti": ("trajectories", "write_kitti_export", "poses.txt (3x4 camera-to-world per line) and times.txt (KITTI)",
              ("poses.txt", "times.txt")),
    "euroc": ("trajectories", "write_euroc_export", "trajectory.csv: ns, position, quaternion w x y z (EuRoC)",
              ("trajectory.csv",)),
    "evo": ("trajectories", "write_evo_export",
            "evo_ape.zip: evo's APE result against the ground truth, for evo_res (needs evo and ground truth)",
            ("evo_ape.zip",)),
    "colmap": ("colmap", "write_colmap", "colmap/: images/ and sparse/0/{cameras,images,points3D}.txt", ("colmap",)),
    "nerfstudio": ("nerfstudio", "write_nerfstudio",
                   "nerfstudio/: transforms.json, images/, depth/ (16-bit mm), sparse_pc.ply (also Instant-NGP)",
                   ("nerfstudio",)),
    "pcd": ("maps", "write_pcd", "cloud.pcd: the fused coloured cloud (PCL)", ("cloud.pcd",)),
    "obj": ("maps", "write_obj", "mesh.obj: the TSDF mesh with vertex colours", ("mesh.obj",)),
    "glb": ("maps", "write_glb", "mesh.glb: the TSDF mesh as binary glTF", ("mesh.glb",)),
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

    module, func, _, _ = FORMATS[name]
    return getattr(importlib.import_module(f"rgbdslam.export.{module}"), func)


def _check(run, name: str) -> None:
    """Raise InputError when the run lacks what format ``name`` needs."""
    if name == "evo":
        from rgbdslam.export.trajectories import check_evo

        check_evo(run)
    elif name == "pcd":
        run.map_ply("cloud.ply")  # read and checked: a damaged map is one line before any file is written
    elif name in ("obj", "glb"):
        run.map_ply("mesh.ply")
    elif name in ("colmap", "nerfstudio"):
        run.keyframes  # opens the sequence and matches the keyframes to the trajectory  # noqa: B018


def export_run(run_dir: str | Path, formats: list[str], out_dir: str | Path | None = None,
               max_points: int = 100_000, progress: bool = True) -> dict[str, list[Path]]:
    """Write the exports ``formats`` of the finished run folder ``run_dir`` into ``out_dir``
    (default RUN_DIR/export); returns the written paths per format.

    The run folder is locked for the export (a run still writing there is one error line) and
    must hold a finished run. The export never writes into or over its own run, and replaces only
    what an earlier export listed in the folder's manifest (:mod:`rgbdslam.io.manifest`):
    anything else where it would write is an InputError naming it, before any file is written."""
    from rgbdslam.export.run import RunExport
    from rgbdslam.runfolder.folder import folder_lock
    from rgbdslam.runfolder.read import read_run, run_status

    if out_dir is not None and not str(out_dir).strip():
        raise InputError("--out must not be empty; give the folder to export into (default: RUN_DIR/export)")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        read_run(run_dir)  # the one-line error of a path that is no run folder
    with folder_lock(run_dir, "export"):  # never while a run or a fusion writes there
        status = run_status(run_dir / "run.json")
        if status not in ("finished", "unreadable"):  # unreadable: read_run names the problem
            raise InputError(f"{run_dir / 'run.json'} says the run is {status!r}, not finished (still running, or "
                             f"stopped or killed before its end); export a finished run: re-run `rgbdslam run`")
        run = RunExport(run_dir, max_points=max_points, progress=progress)
        out = Path(out_dir) if out_dir is not None else run.run_dir / "export"
        root, prefix = export_root(run.run_dir, out, formats)
        for name in formats:  # every format's inputs first: a missing one stops the export before any file is written
            _check(run, name)
        with contextlib.ExitStack() as stack:
            if root != run.run_dir:
                stack.enter_context(folder_lock(make_dirs(out), "export"))  # two exports into one folder: one line
            return _write_formats(run, formats, out, Manifest(root), prefix)


def _write_formats(run, formats: list[str], out: Path, manifest: Manifest, prefix: str) -> dict[str, list[Path]]:
    """The formats into ``out``, each listed in ``manifest`` (of ``out``, or of the run folder for
    RUN_DIR/export: names under ``prefix``) once written."""
    names = [prefix + n for f in formats for n in FORMATS[f][3]]
    fix = "move it away or choose another --out (an export replaces only what an earlier export wrote there)"
    if prefix:  # RUN_DIR/export itself: a folder of an earlier export, or new
        manifest.check_way([prefix.rstrip("/")], [EXPORT], fix, below=False)
        manifest.unlink_links([prefix.rstrip("/")])
    manifest.check_way(names, [EXPORT], fix)
    manifest.unlink_links(names)
    make_dirs(out)
    if prefix:
        manifest.record([prefix.rstrip("/")], EXPORT, below=False)
    written: dict[str, list[Path]] = {}
    for name in formats:
        written[name] = writer(name)(run, out)
        manifest.record([prefix + n for n in FORMATS[name][3]], EXPORT)
    return written


def export_root(run_dir: Path, out: Path, formats: list[str]) -> tuple[Path, str]:
    """The folder whose manifest lists the export's files and the export's names' prefix in it:
    the run folder for its own ``export/`` folder, else ``out``. An InputError when the export
    would write into its own run folder (anywhere but ``export/``) or over it (a format's folder,
    e.g. ``colmap/``, that is or holds the run folder)."""
    run, o = run_dir.resolve(), out.resolve()
    if out.name == "export" and out.absolute().parent.resolve() == run:  # RUN_DIR/export (a link there too)
        return run_dir, "export/"
    if o == run or run in o.parents:
        raise InputError(f"--out {out} is inside the run folder {run_dir}, the source of this export; an export "
                         f"writes only into {run_dir / 'export'} (the default) or a folder outside the run")
    for name in (n for f in formats for n in FORMATS[f][3]):
        if o / name == run or (o / name) in run.parents:
            raise InputError(f"{out / name} would replace the run folder {run_dir}, the source of this export; "
                             f"choose another --out")
    return out, ""
