"""How much does the spanning-tree column depend on which BFS parent wins a tie?

Usage::

    .venv/bin/python scripts/masat/study_spanning_tree_ties.py [--dataset city10k] [--noise 0.15,0.15,0.15]
        [--instances 50] [--seed 0] [--workers 2] [--optimizer g2o] [--ties index,edge_order,r0,r1]
        [--out DIR]

The MASAT paper's spanning-tree start is g2o's ``computeInitialGuess``: a breadth-first tree from
vertex 0 with unit edge costs, each vertex placed from its parent.  Whenever a vertex has several
neighbours one level up, the one dequeued first becomes its parent, and that depends on the order
in which each vertex's edges are visited — in g2o the pointer order of a ``std::set`` of edges, in
this project increasing vertex index.  On the benchmark graphs such ties are common (City10k: 3594
of 10000 vertices, M3500: 795 of 3500), so "the" spanning tree is not one tree.

This study runs the protocol's own seeded instances (``--seed 0`` = the published tables; the
``index`` tree reproduces the benchmark's spanning-tree column exactly) with several tie-breaking
rules — ``index`` (the benchmark's), ``edge_order`` (neighbours in file order, g2o's allocation
order), ``rK`` (a random neighbour order, seed K) — and reports each tree's convergence rate,
rate at the optimum (Table 1c rule), the spread between trees, and the paper's value.  The
trees differ only in tie-breaking; with noise-free measurements every one of them gives the ground
truth exactly.
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing as mp
import os
import platform
import shlex
import sys
import time
from pathlib import Path

from scipy.stats import binomtest

from rgbdslam.posegraph import bench as pb
import paper_stats as ps  # beside this script
from rgbdslam.posegraph.initializers import spanning_tree
from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_write_text

_STATE: dict = {}


def tie_rule(label: str):
    """``index`` / ``edge_order`` / ``rK`` -> the ``tie_break`` argument of ``spanning_tree``."""
    if label in ("index", "edge_order"):
        return label
    if label.startswith("r") and label[1:].isdigit():
        return int(label[1:])
    raise InputError(f"unknown tie-breaking rule {label!r}; use index, edge_order or rK (K an integer seed)")


def _run(instance: int) -> list[pb.RunRecord]:
    st = _STATE
    return pb.run_instance(st["ref"], st["gt"], st["dataset"], st["sigma"], st["level"], instance, st["seed"],
                           st["methods"], optimizer=st["optimizer"], custom=st["custom"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="city10k", choices=pb.DATASETS)
    ap.add_argument("--noise", default="0.15,0.15,0.15", help="sx,sy,stheta (one level)")
    ap.add_argument("--instances", type=int, default=50)
    ap.add_argument("--first-instance", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--optimizer", default="g2o", choices=("gtsam", "g2o", "lm"))
    ap.add_argument("--ties", default="index,edge_order,r0,r1")
    ap.add_argument("--out", type=Path, default=None, help="folder for runs.csv and report.md")
    ap.add_argument("--data", default=os.environ.get("RGBDSLAM_DATA", str(Path(__file__).resolve().parents[3] / "shared" / "data")))
    a = ap.parse_args(argv)
    try:
        (sigma,) = pb.parse_noise(a.noise)
        labels = [t.strip() for t in a.ties.split(",") if t.strip()]
        custom = {f"spanning_tree[{t}]": functools.partial(spanning_tree, tie_break=tie_rule(t)) for t in labels}
        ref, gt, _note = pb.reference_graph(a.dataset, a.data)
    except (InputError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    methods = tuple(custom) + ("ground_truth",)
    _STATE.update(ref=ref, gt=gt, dataset=a.dataset, sigma=sigma, level=pb.level_index(sigma), seed=a.seed,
                  methods=methods, optimizer=a.optimizer, custom=custom)
    instances = range(a.first_instance, a.first_instance + a.instances)
    t0 = time.perf_counter()
    if a.workers > 1:
        with mp.get_context("fork").Pool(a.workers) as pool:
            recs = [r for rs in pool.imap(_run, instances) for r in rs]
    else:
        recs = [r for i in instances for r in _run(i)]
    wall = time.perf_counter() - t0
    S = pb.summarise(recs)
    k = pb.level_index(sigma)
    paper = pb.paper_rate(a.dataset, k, "spanning_tree")
    paper_txt = "–" if paper is None else f"{paper:.2f}"
    cmd = " ".join(["scripts/masat/study_spanning_tree_ties.py"] + [shlex.quote(x) for x in (argv or sys.argv[1:])])
    lines = [f"`{cmd}` — {pb.DATASET_NAMES[a.dataset]}, noise {a.noise}, instances {instances.start}-"
             f"{instances.stop - 1} of seed {a.seed}, optimizer {a.optimizer}; {a.workers} worker(s), "
             f"{os.cpu_count()} CPUs ({platform.machine()}), wall time {wall:.0f} s", "",
             "| spanning tree, ties by | converged [95 % interval] | converged to the optimum | the paper |",
             "|---|---|---|---|"]
    rates = []
    for m in custom:
        s = S[(tuple(sigma), m)]
        ci = binomtest(round(s["rate"] * s["n"]), s["n"]).proportion_ci(0.95, method="wilson")
        rates.append(s["rate"])
        lines.append(f"| {m[len('spanning_tree['):-1]} | {s['rate']:.2f} [{ci.low:.2f}, {ci.high:.2f}] | "
                     f"{s['opt_rate']:.2f} | {paper_txt} |")
    s = S[(tuple(sigma), "ground_truth")]
    lines.append(f"| (ground truth start) | {s['rate']:.2f} | {s['opt_rate']:.2f} | |")
    lines += ["", f"Spread of the convergence rate over the {len(rates)} trees: {min(rates):.2f}-{max(rates):.2f}."]
    if len(custom) > 1:
        first = next(iter(custom))
        for m in list(custom)[1:]:
            lines += ["", ps.format_paired(ps.paired_comparison(recs, m, first), m, first)]
    report = "\n".join(lines) + "\n"
    print(report)
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        pb.write_runs_csv(a.out / "runs.csv", recs)
        atomic_write_text(a.out / "report.md", report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
