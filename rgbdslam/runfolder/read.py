"""Reading a run folder (docs/formats.md): run.json with its fields checked, the configuration the
run used and its final trajectory, as map fusion, the viewer and the exports take them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rgbdslam.config import Config, load_config
from rgbdslam.errors import InputError
from rgbdslam.io.text import read_text
from rgbdslam.io.trajectory import Trajectory, read_tum


def run_status(run_json: Path) -> str:
    """What ``run_json`` says of its run: "finished", "running" (still writing, or killed),
    "interrupted", "failed"; older run.json files without a status count as finished unless they
    say ``interrupted``; "unreadable" when it is no run summary."""
    try:
        info = json.loads(run_json.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return "unreadable"
    if not isinstance(info, dict):
        return "unreadable"
    status = info.get("status", "interrupted" if info.get("interrupted") else "finished")
    return status if isinstance(status, str) else "unreadable"


def finished_run(run_json: Path) -> bool:
    """True when ``run_json`` records a run that ran to its end (:func:`run_status`)."""
    return run_status(run_json) == "finished"


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def check_run_info(info: Any, path: Path) -> dict[str, Any]:
    """The fields of run.json that fusion and the viewer read, with the types they need;
    an InputError names ``path`` and the field otherwise."""
    fix = "re-run `rgbdslam run` to rewrite it, or correct the field"
    if not isinstance(info, dict):
        raise InputError(f"{path} must hold a JSON object (the run summary), not {type(info).__name__}; {fix}")
    if "sequence" not in info:
        raise InputError(f"{path} has no 'sequence' entry; it must name the sequence folder the run used")
    if not isinstance(info["sequence"], str) or not info["sequence"].strip():
        raise InputError(f"{path}: 'sequence' must be the path of the sequence folder as a string; got "
                         f"{info['sequence']!r}; {fix}")
    kf = info.get("keyframes")
    if kf is not None and not (isinstance(kf, list) and all(_is_int(i) for i in kf)):
        bad = kf if not isinstance(kf, list) else next(i for i in kf if not _is_int(i))
        raise InputError(f"{path}: 'keyframes' must be a list of frame numbers (whole numbers); found {bad!r}; {fix}")
    loops = info.get("loops")
    if loops is not None and not (isinstance(loops, list) and all(
            isinstance(x, list) and len(x) == 2 and all(_is_int(i) for i in x) for x in loops)):
        raise InputError(f"{path}: 'loops' must be a list of frame-number pairs [i, j]; got {loops!r:.60}; {fix}")
    segs = info.get("segments")
    if segs is not None:
        ok = isinstance(segs, list) and all(
            isinstance(g, dict) and _is_int(g.get("first")) and _is_int(g.get("last"))
            and isinstance(g.get("map", True), bool) for g in segs)
        if not ok:
            raise InputError(f"{path}: 'segments' must be a list of objects with whole numbers 'first' and 'last' "
                             f"(and true/false 'map'); got {segs!r:.60}; {fix}")
    return info


def read_run(run_dir: str | Path) -> tuple[dict[str, Any], Config, Trajectory]:
    """run.json (its fields checked, see :func:`check_run_info`), the configuration used and the
    final trajectory of a run folder."""
    run_dir = Path(run_dir)
    info_path = run_dir / "run.json"
    if not info_path.is_file():
        raise InputError(f"{run_dir} is not a run folder: {info_path.name} is missing; give the --out folder of `rgbdslam run`")
    try:
        info = json.loads(read_text(info_path, "run file"))
    except json.JSONDecodeError as e:
        raise InputError(f"{info_path} is not valid JSON (line {e.lineno}); re-run `rgbdslam run` to rewrite it") from None
    except (ValueError, RecursionError):  # a number of thousands of digits; nesting deeper than Python recurses
        raise InputError(f"{info_path} is not a run file rgbdslam wrote (nested too deeply or a number too long); "
                         f"re-run `rgbdslam run` to rewrite it") from None
    info = check_run_info(info, info_path)
    cfg_path = run_dir / "config.yaml"
    if cfg_path.is_file():
        cfg = load_config(cfg_path)
    else:  # the camera, depth scale and frame selection of the run are unknown: say so
        from rgbdslam.ui import console

        console.print(f"[yellow]warning:[/] {cfg_path} is missing; the default config is used to re-read the sequence "
                      f"(if the run used a preset or --set, copy its config.yaml back)")
        cfg = Config()
    traj = read_tum(run_dir / "trajectory.tum")
    return info, cfg, traj


def check_run_frames(run_dir: str | Path, info: dict[str, Any], n_frames: int) -> None:
    """run.json's keyframes and loop frames must be frames of its sequence (``n_frames`` of them):
    one outside means run.json does not belong to the sequence as it is now."""
    path = Path(run_dir) / "run.json"
    frames = list(info.get("keyframes") or []) + [i for pair in info.get("loops") or [] for i in pair]
    bad = [i for i in frames if not 0 <= i < n_frames]
    if bad:
        raise InputError(f"{path}: frame {bad[0]} is not in the sequence {info['sequence']} (frames 0..{n_frames - 1}); "
                         f"run.json does not belong to this sequence as it is now: re-run `rgbdslam run`")
