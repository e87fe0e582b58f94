"""Does information weighting help MASAT when the edges' noise differs?  A study beyond the paper.

Usage::

    .venv/bin/python scripts/masat/study_heterogeneous_noise.py [--dataset m3500] [--noise 0.2,0.2,0.2]
        [--model loguniform|loops] [--spread 3] [--instances 30] [--seed 1] [--workers 2]
        [--methods masat,weighted_masat,chordal,ground_truth] [--out DIR]

In the MASAT paper's protocol every edge gets the same noise and the same information matrix, so
weighting the ancestors' predictions by their edges' information cannot change anything; only
the accumulated (path) variance separates weighted MASAT from MASAT there, and the two are
statistically the same (``scripts/masat/compare_to_paper.py --paired weighted_masat,masat``).  SLAM
graphs are not like that: odometry and loop-closure edges, or edges from different sensors, carry
different information.  This study keeps the protocol (noise-free graph, GTSAM Gauss–Newton, at
most 50 iterations, converged when ``|Δχ²|/χ² < 1e-6``, Table 1c's "at the optimum" rule) but draws
each edge's noise with its own standard deviation ``s_e · σ`` and gives the edge the matching
information ``diag(1/(s_e σ)²)``:

* ``loguniform``: ``s_e`` log-uniform in ``[1/spread, spread]``, independently per edge;
* ``loops``: odometry edges (``j = i + 1``) ``s_e = 1/spread``, every other edge ``s_e = spread``.

It prints the paired comparison of weighted MASAT against MASAT (exact McNemar test, see
``paper_stats.paired_comparison`` beside this script), the rates of every start, and writes a
``runs.csv`` (``--out``) that ``scripts/masat/compare_to_paper.py --paired`` reads.  Seed 1 by default:
these instances are not the protocol's.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from rgbdslam.posegraph import bench as pb
import paper_stats as ps  # beside this script
from rgbdslam.errors import InputError

_STATE: dict = {}


def edge_scales(ref, model: str, spread: float, rng: np.random.Generator) -> np.ndarray:
    """Per-edge factor s_e on the base standard deviations."""
    if model == "loguniform":
        return np.exp(rng.uniform(-np.log(spread), np.log(spread), ref.n_edges))
    if model == "loops":
        odo = ref.edges_j == ref.edges_i + 1
        return np.where(odo, 1.0 / spread, spread)
    raise InputError(f"unknown noise model {model!r}; use loguniform or loops")


def heterogeneous_instance(ref, sigma, model: str, spread: float, rng: np.random.Generator):
    """A noisy copy of ``ref``: edge e gets N(0, s_e σ) noise and information diag(1/(s_e σ)²)."""
    sig = np.asarray(sigma, float)[None, :] * edge_scales(ref, model, spread, rng)[:, None]
    return pb.noisy_instance(ref, sig, rng)


def _run(instance: int) -> list[pb.RunRecord]:
    st = _STATE
    rng = np.random.default_rng([st["seed"], pb.DATASETS.index(st["dataset"]), 777, instance])
    g = heterogeneous_instance(st["ref"], st["sigma"], st["model"], st["spread"], rng)
    return pb.run_starts(g, st["gt"], st["dataset"], st["sigma"], instance, st["methods"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="m3500", choices=pb.DATASETS)
    ap.add_argument("--noise", default="0.2,0.2,0.2", help="base sx,sy,stheta")
    ap.add_argument("--model", default="loguniform", choices=("loguniform", "loops"))
    ap.add_argument("--spread", type=float, default=3.0)
    ap.add_argument("--instances", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--methods", default="masat,weighted_masat,chordal,ground_truth")
    ap.add_argument("--out", type=Path, default=None, help="folder for runs.csv and report.md")
    ap.add_argument("--data", default=os.environ.get("RGBDSLAM_DATA", str(Path(__file__).resolve().parents[3] / "shared" / "data")))
    a = ap.parse_args(argv)
    try:
        (sigma,) = pb.parse_noise(a.noise)
        methods = tuple(m.strip() for m in a.methods.split(",") if m.strip())
        if "ground_truth" not in methods:
            raise InputError("--methods must include ground_truth (the reference of 'at the optimum')")
        ref, gt, note = pb.reference_graph(a.dataset, a.data)
    except (InputError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    _STATE.update(ref=ref, gt=gt, dataset=a.dataset, sigma=sigma, model=a.model, spread=a.spread, seed=a.seed,
                  methods=methods)
    t0 = time.perf_counter()
    if a.workers > 1:
        with mp.get_context("fork").Pool(a.workers) as pool:
            recs = [r for rs in pool.map(_run, range(a.instances)) for r in rs]
    else:
        recs = [r for i in range(a.instances) for r in _run(i)]
    wall = time.perf_counter() - t0
    S = pb.summarise(recs)
    cmd = " ".join(["scripts/masat/study_heterogeneous_noise.py"] + [shlex.quote(x) for x in (argv or sys.argv[1:])])
    lines = [f"`{cmd}` — {pb.DATASET_NAMES[a.dataset]}, base noise {a.noise}, model {a.model} (spread {a.spread:g}), "
             f"{a.instances} instances of seed {a.seed}; {a.workers} worker(s), {os.cpu_count()} CPUs "
             f"({platform.machine()}), wall time {wall:.0f} s", "",
             "| start | converged | converged to the optimum | init (mean ms) |", "|---|---|---|---|"]
    for m in methods:
        s = S[(tuple(sigma), m)]
        lines.append(f"| {pb.METHOD_NAMES[m]} | {s['rate']:.2f} | {s['opt_rate']:.2f} | {1e3 * s['init_s']:.0f} |")
    if "masat" in methods and "weighted_masat" in methods:
        lines += ["", "Paired, same instances (exact McNemar):", "",
                  ps.format_paired(ps.paired_comparison(recs, "weighted_masat", "masat"), "weighted_masat", "masat")]
    report = "\n".join(lines) + "\n"
    print(report)
    if a.out is not None:
        pb.write_outputs(a.out, recs, a.dataset, methods, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
