"""Which differences from the MASAT paper's Table 1 are larger than sampling noise?

Usage::

    python -m benchmarks.masat.compare_to_paper RUNS.csv [RUNS.csv ...] [--methods masat,weighted_masat]
        [--alpha 0.05] [--paper-instances 50] [--paired weighted_masat,masat]

Reads the ``runs.csv`` files of ``rgbdslam posegraph bench`` (several files of one data set are
merged as ``--merge-runs`` does: a later file's (noise, instance, method) rows replace earlier
ones) and prints, for every noise level and method, our convergence count ``k/n`` (the protocol's
relative test), its 95 % Wilson interval, the paper's rate, and the two-sided Fisher exact p-value
of "our rate equals the paper's" (the paper's count is its rate × ``--paper-instances``).  The
paper has no weighted MASAT or chordal column; those are compared with the paper's MASAT column,
which is what the issue's target for weighted MASAT asks.

``--paired A,B`` adds a paired comparison of two of our starts on the same instances (exact
McNemar test: of the instances where exactly one of them converged, how many were A's), both for
"converged" and for "converged to the optimum" (Table 1c's rule, needs ground-truth runs).  This
answers "is A better than B?" with more power than comparing each with the paper.

A verdict ``above`` / ``below`` means p < ``--alpha``; ``same`` means the difference is within
sampling noise at these sample sizes.  With 50 instances on each side the Wilson interval of a
rate near 0.5 is about ±0.13 wide, so most differences of 0.1 are ``same``.  A table compares
dozens of cells, so some p < 0.05 are expected by chance alone (about 1 in 20 when nothing
differs); the "Holm" columns adjust the p-values for the number of cells in the table
(Holm–Bonferroni, family-wise error <= alpha).
"""

from __future__ import annotations

import argparse
import sys

from benchmarks.masat import paper_stats as ps
from rgbdslam.errors import InputError
from rgbdslam.posegraph import bench as pb


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="runs.csv files of one data set (later rows replace earlier)")
    ap.add_argument("--methods", default="odometry,spanning_tree,masat,weighted_masat,ground_truth")
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--paper-instances", type=int, default=50)
    ap.add_argument("--paired", default="", help="A,B: also compare our starts A and B on the same instances")
    a = ap.parse_args(argv)
    merged: dict = {}
    try:
        for path in a.runs:
            for r in pb.load_runs(path):
                merged[(r.dataset, r.sigma_x, r.sigma_y, r.sigma_theta, r.instance, r.method)] = r
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    records = list(merged.values())
    if not records or len({r.dataset for r in records}) != 1:
        print("error: give runs.csv files of exactly one data set", file=sys.stderr)
        return 2
    rows = pb.compare_with_paper(records, [m.strip() for m in a.methods.split(",") if m.strip()], a.alpha, a.paper_instances)
    print(f"{pb.DATASET_NAMES[records[0].dataset]} — `{' '.join(['python -m benchmarks.masat.compare_to_paper'] + (argv or sys.argv[1:]))}`\n")
    print(ps.format_paper_comparison(rows))
    for key, what in (("verdict", "each cell on its own"), ("verdict_holm", "Holm-adjusted over the table")):
        tally = {v: sum(r[key] == v for r in rows) for v in ("above", "same", "below")}
        print(f"\n{len(rows)} comparisons at alpha {a.alpha}, {what}: {tally['above']} above, {tally['same']} same, "
              f"{tally['below']} below the paper")
    if a.paired:
        m = [x.strip() for x in a.paired.split(",")]
        if len(m) != 2:
            print("error: --paired needs two starts, e.g. weighted_masat,masat", file=sys.stderr)
            return 2
        print(f"\nPaired: {pb.METHOD_NAMES.get(m[0], m[0])} against {pb.METHOD_NAMES.get(m[1], m[1])} "
              "on the same instances (exact McNemar test)\n")
        print(ps.format_paired(ps.paired_comparison(records, m[0], m[1], a.alpha), m[0], m[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
