"""Accuracy suite for map-based tracking: every sequence, several configurations, one run.

Usage::

    python -m benchmarks.landmarks [--work DIR] [--data DIR] [--sevenscenes DIR]
        [--frames 150] [--seeds 0,1,2] [--motions loop,circle,xyz,rpy,figure8,revisit] [--no-open3d]
        [--variant NAME=KEY=VALUE[,KEY=VALUE...]] ... [--json FILE] [--skip-real] [--skip-synthetic]
        [--open3d-only]

Sequences: TUM fr1/rpy head200 (``--data``/tum), 7-Scenes redkitchen 0-299 through the 7-Scenes
reader with ``rgbdslam/cameras/7scenes.yaml`` (``--data``/7scenes/frames_0000_0299, or ``--sevenscenes``:
another folder; a TUM-layout copy runs with its own camera.yaml), and the project's synthetic generator (every motion x seed, Kinect-like noise, exact ground truth). Every
variant (``default`` always first) runs on every sequence through ``rgbdslam.pipeline.run_sequence``
(map fusion off). Per run: ATE RMSE, 1-frame RPE RMSE (translation), frames/s, loops, and from
``run.json['landmarks']`` (when landmark tracking ran) the share of matched landmarks first seen
>= 100 frames earlier. On the loop-type synthetic sequences (loop, circle, figure8, revisit: they
come back to their start) Open3D's hybrid RGB-D odometry is measured in the same run as the
reference the issue names, and the ATE of the first visit and of the revisit (the frame ranges
synthetic.yaml records for the revisit motion, else the first and last 15 % of the frames). Speed: the machine is
shared; compare frames/s only as ratios within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import common
from benchmarks.common import DATA, LOOP_TYPE, ROOT, parse_variant
from rgbdslam.config import load_config


def summary_metrics(s: dict) -> dict:
    ev = s.get("evaluation") or {}
    ate = (ev.get("ate") or {}).get("rmse", float("nan"))
    rpe = ((ev.get("rpe") or {}).get("trans") or {}).get("rmse", float("nan"))
    lm = s.get("landmarks") or {}
    return {"ate": ate, "rpe": rpe, "fps": s.get("processing_fps", float("nan")), "loops": len(s.get("loops", [])),
            "lost": s.get("lost", 0), "old_share": lm.get("old_share"), "landmarks": lm.get("size")}


def visit_ranges(seq_dir: Path, n: int, share: float = 0.15) -> tuple[range, range]:
    """Frames of the first visit and of the revisit: the ranges synthetic.yaml records (revisit
    motion), else the first and the last ``share`` of the ``n`` frames (a loop-type motion comes
    back to its start)."""
    import yaml

    meta = seq_dir / "synthetic.yaml"
    info = yaml.safe_load(meta.read_text()) if meta.is_file() else {}
    if isinstance(info, dict) and "first_visit" in info and "revisit" in info and info.get("frames") == n:
        (a0, a1), (b0, b1) = info["first_visit"], info["revisit"]
        return range(a0, a1 + 1), range(b0, b1 + 1)
    k = max(1, int(share * n))
    return range(0, k), range(n - k, n)


def revisit_errors(seq_dir: Path, run_dir: Path) -> tuple[float, float] | None:
    """ATE RMSE of the first visit and of the revisit (:func:`visit_ranges`) under the whole run's
    alignment: the thesis' requirement is a revisit no worse than the first visit."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.config import Config
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import read_tum

    if not (run_dir / "trajectory.tum").is_file():
        return None
    a = ate(open_sequence(seq_dir, Config().dataset).groundtruth(), read_tum(run_dir / "trajectory.tum"))
    if len(a.errors) != len(open_sequence(seq_dir, Config().dataset)):
        return None  # frames missing from the estimate (tracking lost): the ranges would not line up
    first, again = visit_ranges(seq_dir, len(a.errors))
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    return rms(a.errors[list(first)]), rms(a.errors[list(again)])


def run_dir_name(seq_name: str, variant: str) -> str:
    return f"{seq_name.replace('/', '_').replace(' ', '_')}__{variant.replace(' ', '_')}"


def open3d_odometry(seq_dir: Path) -> dict:
    """Open3D's hybrid RGB-D odometry (frame to frame, no loop closure) on a TUM-layout folder."""
    m = common.open3d_odometry(seq_dir)
    return {"ate": m.ate, "rpe": m.rpe, "fps": 1e3 / m.ms}


def parse_log(path: Path) -> dict:
    """The rows of a (possibly unfinished) run from its printed lines (fixed-width name and variant)."""
    import re

    rows = []
    num = r"([0-9.]+|nan)"
    pat = re.compile(rf"ATE {num}\s+RPE {num}\s+{num} fps(?:\s+loops (\d+)\s+old (\S+))?")
    for line in path.read_text().splitlines():
        m = pat.search(line)
        if not m or len(line) < 58:
            continue
        old = m.group(5)
        rows.append({"sequence": line[:28].strip(), "variant": line[29:57].strip(), "ate": float(m.group(1)),
                     "rpe": float(m.group(2)), "fps": float(m.group(3)),
                     "loops": int(m.group(4)) if m.group(4) else "-",
                     "old_share": None if old in (None, "None") else float(old)})
    return {"command": f"(unfinished run, rows from its log {path.name})", "rows": rows}


def _f(x, fmt="{:.4f}") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def markdown(rows: list[dict], section: str, commands: list[str], machine: str) -> str:
    """Per sequence x variant: ATE, 1-frame RPE, frames/s (+ ratio to the default in the same run),
    old-landmark share; then medians over the synthetic sequences and their ratios to the default."""
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    by = {(r["sequence"], r["variant"]): r for r in rows}
    L = [section, ""] + [f"Command: `{c}`  " for c in commands]
    L += [f"Machine: {machine}; shared with other engineers' jobs, so frames/s are noisy: compare them only as "
          "ratios to the default of the same sequence (run right before it).", "",
          "ATE RMSE and 1-frame RPE RMSE (translation) in metres; fps = frames/s without waiting for images "
          "(x default); old = share of the map-matched landmarks first seen >= 100 frames earlier.", "",
          "| sequence | variant | ATE | RPE 1 frame | fps (x default) | loops | old |", "|---|---|---|---|---|---|---|"]
    for q in seqs:
        d = by.get((q, "default"))
        for v in variants:
            r = by.get((q, v))
            if r is None:
                continue
            ratio = f" ({r['fps'] / d['fps']:.2f}x)" if d and v != "default" and d.get("fps") else ""
            L.append(f"| {q} | {v} | {_f(r['ate'])} | {_f(r['rpe'])} | {_f(r.get('fps'), '{:.1f}')}{ratio} | "
                     f"{r.get('loops', '-')} | {_f(r.get('old_share'), '{:.3f}')} |")
    rv = [r for r in rows if "revisit" in r]
    if rv:
        L += ["", "Revisit (loop-type sequences): ATE RMSE of the first visit and of the revisit under the whole "
                  "run's alignment: for the revisit motion the frame ranges in its synthetic.yaml (150 frames: "
                  "0-21 and 128-149, the same poses), else the first and the last 15 % of the frames (back at the "
                  "start).", "",
              "| sequence | variant | first visit | revisit | old landmarks matched |", "|---|---|---|---|---|"]
        for r in rv:
            L.append(f"| {r['sequence']} | {r['variant']} | {r['first_visit']:.4f} | {r['revisit']:.4f} | "
                     f"{_f(r.get('old_share'), '{:.3f}')} |")
    o3d = [q for q in seqs if (q, "Open3D hybrid odometry") in by]
    if o3d:  # at or below Open3D's hybrid RGB-D odometry on each loop-type sequence, same run
        others = [v for v in variants if v != "Open3D hybrid odometry"]
        L += ["", "Against Open3D's hybrid RGB-D odometry (frame to frame, no loop closure) measured in the same run "
                  "on each loop-type sequence: ATE / 1-frame RPE of each variant, `<=` where it is at or below "
                  "Open3D's.", "",
              "| sequence | Open3D ATE / RPE | " + " | ".join(others) + " |", "|---|---|" + "---|" * len(others)]
        count = {v: [0, 0, 0] for v in others}  # ATE <=, RPE <=, sequences
        for q in o3d:
            ref = by[(q, "Open3D hybrid odometry")]
            cells = []
            for v in others:
                r = by.get((q, v))
                if r is None:
                    cells.append("-")
                    continue
                a, p = r["ate"] <= ref["ate"], r["rpe"] <= ref["rpe"]
                count[v][0] += a
                count[v][1] += p
                count[v][2] += 1
                cells.append(f"{_f(r['ate'])}{' <=' if a else ''} / {_f(r['rpe'])}{' <=' if p else ''}")
            L.append(f"| {q} | {_f(ref['ate'])} / {_f(ref['rpe'])} | " + " | ".join(cells) + " |")
        L.append("| at or below Open3D (ATE / RPE) | | " + " | ".join(
            f"{count[v][0]} / {count[v][1]} of {count[v][2]}" for v in others) + " |")
    syn = [q for q in seqs if " seed " in q]
    if syn:
        L += ["", "Synthetic sequences (every motion x seed): medians and the median of the per-sequence ratio to "
                  "the default.", "", "| variant | median ATE | median RPE | median ATE ratio | median RPE ratio | "
                  "better / worse ATE by > 5 % |", "|---|---|---|---|---|---|"]
        for v in variants:
            if v == "Open3D hybrid odometry":  # measured on the loop-type sequences only: in the table above
                continue
            rs = [(by[(q, v)], by.get((q, "default"))) for q in syn if (q, v) in by]
            if not rs:
                continue
            ate = np.median([r["ate"] for r, _ in rs])
            rpe = np.median([r["rpe"] for r, _ in rs])
            pairs = [(r, d) for r, d in rs if d]
            ra = np.median([r["ate"] / d["ate"] for r, d in pairs]) if pairs else float("nan")
            rr = np.median([r["rpe"] / d["rpe"] for r, d in pairs]) if pairs else float("nan")
            nb = sum(r["ate"] < 0.95 * d["ate"] for r, d in pairs)
            nw = sum(r["ate"] > 1.05 * d["ate"] for r, d in pairs)
            L.append(f"| {v} | {ate:.4f} | {rpe:.4f} | {ra:.2f} | {rr:.2f} | {nb} / {nw} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--sevenscenes", type=Path, default=None,
                    help="7-Scenes frames 0-299 (default DATA/7scenes/frames_0000_0299, read by the 7-Scenes reader "
                         "with rgbdslam/cameras/7scenes.yaml; a TUM-layout copy is run as it is)")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--motions", default="loop,circle,xyz,rpy,figure8,revisit")
    ap.add_argument("--blur", type=float, default=None, metavar="MS",
                    help="render the synthetic sequences with this exposure (ms; 0 = sharp) instead of each motion's "
                         "default (figure8: 16 ms, others sharp); the names then say it")
    ap.add_argument("--depth-delay", type=float, default=0.0, metavar="S",
                    help="render the synthetic depth images this many seconds after the colour ones (rgbdslam synth "
                         "--depth-delay; TUM fr1-like); the names then say it")
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--open3d-only", action="store_true",
                    help="only Open3D's odometry on the loop-type sequences (its rows join a run's with --report)")
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--real", default="rpy,7scenes",
                    help="which real sequences to run (comma list of rpy, 7scenes; default both)")
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--skip-default", action="store_true",
                    help="do not run the default configuration (its rows come from an earlier --json via --report)")
    ap.add_argument("--json", type=Path, default=None, help="write every row here")
    ap.add_argument("--report", type=Path, nargs="+", default=None,
                    help="only build the markdown from earlier --json files (several runs' rows joined)")
    ap.add_argument("--section", default="## Landmark map", help="heading of the markdown section")
    ap.add_argument("--write-docs", action="store_true", help="replace that section of docs/benchmarks.md")
    a = ap.parse_args(argv)
    if a.report:
        data = [json.loads(p.read_text()) if p.suffix == ".json" else parse_log(p) for p in a.report]
        rows = [r for d in data for r in d["rows"]]
        if a.work is not None:  # first visit vs revisit on the loop-type sequences, from the run folders
            for r in rows:
                motion, _, seed = r["sequence"].partition(" seed ")
                if motion.split(" ")[0] in LOOP_TYPE and r["variant"] != "Open3D hybrid odometry":
                    seq_dir = Path(r["dir"]) if r.get("dir") else a.work / f"{motion}_s{seed}_{a.frames}"
                    rv = revisit_errors(seq_dir, a.work / "runs" / run_dir_name(r["sequence"], r["variant"]))
                    if rv:
                        r["first_visit"], r["revisit"] = rv
        machine = next((d["machine"] for d in data if d.get("machine")),
                       f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
                       f"{time.strftime('%Y-%m-%d')}")
        text = markdown(rows, a.section, [d["command"] for d in data], machine)
        from benchmarks.common import publish_markdown as publish

        return publish(text, a.write_docs)
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.pipeline import run_sequence

    load0 = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_landmarks_"))
    work.mkdir(parents=True, exist_ok=True)
    variants = {} if a.skip_default else {"default": []}
    variants.update(dict(parse_variant(v) for v in a.variant))
    seqs: list[tuple[str, Path]] = []
    if not a.skip_real:
        rpy = a.data / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
        if rpy.is_dir() and "rpy" in a.real.split(","):
            seqs.append(("fr1/rpy head200", rpy))
        ss = a.sevenscenes or a.data / "7scenes" / "frames_0000_0299"
        if ss.is_dir() and "7scenes" in a.real.split(","):  # the 7-Scenes reader with the colour camera of rgbdslam/cameras/7scenes.yaml
            seqs.append(("7-Scenes redkitchen 0-299", ss))
    if not a.skip_synthetic:
        for motion in a.motions.split(","):
            for seed in [int(s) for s in a.seeds.split(",")]:
                tag = ("" if a.blur is None else f"_blur{a.blur:g}") + (f"_delay{a.depth_delay:g}" if a.depth_delay else "")
                d = work / f"{motion}_s{seed}_{a.frames}{tag}"
                if not (d / "groundtruth.txt").exists():
                    generate_sequence(d, frames=a.frames, motion=motion, noise=True, seed=seed, blur=a.blur,
                                      depth_delay=a.depth_delay)
                label = ("" if a.blur is None else f" blur {a.blur:g} ms") + \
                    (f" depth {1e3 * a.depth_delay:g} ms late" if a.depth_delay else "")
                seqs.append((f"{motion}{label} seed {seed}", d))
    rows = []
    for name, d in seqs:
        for vname, sets in ({} if a.open3d_only else variants).items():
            extra = [f"dataset.camera_file={ROOT / 'rgbdslam' / 'cameras' / '7scenes.yaml'}"] if name.startswith("7-Scenes") \
                and not (d / "rgb.txt").exists() else []
            cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *extra, *sets])
            s = run_sequence(d, work / "runs" / run_dir_name(name, vname), cfg, progress=False)
            row = {"sequence": name, "variant": vname, "dir": str(d), **summary_metrics(s)}
            if " seed " in name and name.split(" ")[0] in LOOP_TYPE:
                rv = revisit_errors(d, work / "runs" / run_dir_name(name, vname))
                if rv:
                    row["first_visit"], row["revisit"] = rv
            rows.append(row)
            print(f"{name:28s} {vname:28s} ATE {row['ate']:.4f}  RPE {row['rpe']:.4f}  {row['fps']:5.1f} fps  "
                  f"loops {row['loops']}  old {row['old_share']}", flush=True)
        if not a.no_open3d and any(name.startswith(m) for m in LOOP_TYPE):
            o = open3d_odometry(d)
            rows.append({"sequence": name, "variant": "Open3D hybrid odometry", **o})
            print(f"{name:28s} {'Open3D hybrid odometry':28s} ATE {o['ate']:.4f}  RPE {o['rpe']:.4f}  {o['fps']:5.1f} fps",
                  flush=True)
    # summary: medians over the synthetic sequences
    print()
    print(f"# {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"{time.strftime('%Y-%m-%d %H:%M')}; command: python {' '.join(shlex.quote(x) for x in sys.argv)}")
    for vname in variants:
        syn = [r for r in rows if r["variant"] == vname and " seed " in r["sequence"]]
        if syn:
            print(f"{vname:28s} synthetic median ATE {np.median([r['ate'] for r in syn]):.4f}  median RPE "
                  f"{np.median([r['rpe'] for r in syn]):.4f}  median fps {np.median([r['fps'] for r in syn]):.1f}")
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
                   f"{time.strftime('%Y-%m-%d')}, load average at the start {load0} and at the end "
                   f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}")
        from rgbdslam.io.atomic import atomic_write_text

        atomic_write_text(a.json, json.dumps({"command": "python " + " ".join(shlex.quote(x) for x in sys.argv),
                                              "machine": machine, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
