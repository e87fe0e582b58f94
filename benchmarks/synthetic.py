"""Configuration variants on synthetic sequences with exact ground truth (several motions and seeds).

Usage::

    python -m benchmarks.synthetic [--frames 150] [--seeds 0,1] [--motions loop,circle,xyz,rpy]
        [--variant NAME=KEY=VALUE[,KEY=VALUE...]] ... [--work DIR] [--write-docs]

Every (motion, seed) sequence is rendered once (``rgbdslam.datasets.synthetic.generate_sequence``
with Kinect-like noise) and run with each variant (``default`` is always included). The table
gives the ATE RMSE per sequence and variant, and per variant the median ATE, the median of its
ratio to the default's, and the number of sequences where it is better / worse than the default
by more than 5 %. One real sequence cannot tell a better default from a lucky one; this adds
sequences whose truth is exact. ``--write-docs`` replaces the "## Synthetic variants" section of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import parse_variant
from rgbdslam.config import load_config

DEFAULT_VARIANTS = ["sharp frames only=loop.query_gap=0",
                    "ORB response gate, sharp frames only=loop.sharpness_measure=response,loop.query_gap=0",
                    "newest reference by brute force always=registration.predicted_gate=null"]


def run_all(frames: int, seeds: list[int], motions: list[str], variants: dict[str, list[str]],
            work: Path) -> list[dict]:
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.pipeline import run_sequence

    rows = []
    for motion in motions:
        for seed in seeds:
            seq = work / f"{motion}_s{seed}"
            if not (seq / "groundtruth.txt").exists():
                generate_sequence(seq, frames=frames, motion=motion, noise=True, seed=seed)
            for name, sets in variants.items():
                cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *sets])
                s = run_sequence(seq, work / "runs" / f"{motion}_s{seed}_{len(rows)}", cfg, progress=False)
                ate = ((s.get("evaluation") or {}).get("ate") or {}).get("rmse", float("nan"))
                rows.append({"sequence": f"{motion} seed {seed}", "variant": name, "ate": ate,
                             "loops": len(s["loops"]), "lost": s["lost"]})
                print(f"  {motion:7s} seed {seed}  {name:40s} ATE {ate:.4f} m  loops {len(s['loops'])}", flush=True)
    return rows


def markdown(rows: list[dict], variants: dict[str, list[str]], frames: int, command: str) -> str:
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    ate = {(r["sequence"], r["variant"]): r for r in rows}
    L = ["## Synthetic variants", "",
         f"Command: `{command}`  ",
         f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
         f"{time.strftime('%Y-%m-%d')}. Synthetic sequences of {frames} frames with Kinect-like noise and exact "
         "ground truth; ATE RMSE in metres (loops in brackets). Variants:", ""]
    for name, sets in variants.items():
        L.append(f"- **{name}**: " + (", ".join(f"`{s}`" for s in sets) if sets else "the defaults"))
    L += ["", "| sequence | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
    for q in seqs:
        L.append(f"| {q} | " + " | ".join(f"{ate[q, v]['ate']:.4f} ({ate[q, v]['loops']})" for v in variants) + " |")
    base = np.array([ate[q, "default"]["ate"] for q in seqs])
    med, ratio, better = [], [], []
    for v in variants:
        a = np.array([ate[q, v]["ate"] for q in seqs])
        med.append(f"{np.median(a):.4f}")
        ratio.append(f"{np.median(a / base):.2f}")
        better.append(f"{int(np.sum(a < 0.95 * base))} / {int(np.sum(a > 1.05 * base))}")
    L += ["| **median ATE** | " + " | ".join(med) + " |",
          "| **median ratio to default** | " + " | ".join(ratio) + " |",
          "| **better / worse by > 5 %** | " + " | ".join(better) + " |"]
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--motions", default="loop,circle,xyz,rpy")
    ap.add_argument("--variant", action="append", default=None,
                    help="NAME=KEY=VALUE[,KEY=VALUE...]; repeatable (default: the loop gate before 2026-11-30 "
                         "and the thesis' gate alone)")
    ap.add_argument("--work", default=None, help="folder for sequences and runs (default: temporary)")
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args(argv)
    command = "python -m benchmarks.synthetic " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    variants = {"default": []}
    variants.update(dict(parse_variant(v) for v in (a.variant or DEFAULT_VARIANTS)))
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_synth_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = run_all(a.frames, [int(x) for x in a.seeds.split(",")], a.motions.split(","), variants, work)
    from benchmarks.common import publish_markdown as publish

    return publish(markdown(rows, variants, a.frames, command), a.write_docs)


if __name__ == "__main__":
    raise SystemExit(main())
