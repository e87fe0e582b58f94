"""Our g2o-style Gauss–Newton (``--optimizer g2o``) against the real g2o, and the protocol run with g2o.

Usage::

    # the protocol's instances, optimised by g2o itself; --compare checks run-by-run agreement
    python -m benchmarks.masat.g2o_parity --dataset m3500 --noise 0.15,0.15,0.3 --method masat \\
        --instances 50 [--first-instance 0] [--seed 0] [--compare RUNS.csv]

    # re-record the reference file the test suite compares gn2d.py with
    python -m benchmarks.masat.g2o_parity --record tests/data/g2o_reference.json

The MASAT paper ran g2o; ``rgbdslam/posegraph/gn2d.py`` re-implements g2o's SE(2) edge, vertex update
and Gauss–Newton step in NumPy.  This script checks that claim against g2o itself, through the
PyPI binding ``g2o-python`` 0.0.12.  That wheel is built against NumPy 1.x and crashes under the
NumPy 2 this project pins, so it lives in its own environment, ``.venv-g2o`` (numpy 1.26.4 +
g2o-python 0.0.12, created from the package registry on first use; delete it to rebuild).  The
script runs g2o there in a subprocess (``--worker``, which imports only numpy and g2o) and passes
the graphs as ``.npz`` files.  The g2o side: ``SparseOptimizer`` + ``BlockSolverSE2`` with the
Eigen sparse Cholesky, ``OptimizationAlgorithmGaussNewton``, vertex 0 fixed, one ``optimize(1)``
per iteration and χ² recomputed after it (g2o's own ``activeChi2`` after ``optimize`` is the χ²
*before* the last update).

Output: per instance, g2o's verdict (the protocol's relative test on g2o's χ² history), its
iterations and reduced χ², and — with ``--compare`` — ours from a ``runs.csv`` of ``rgbdslam
posegraph bench --optimizer g2o``; then the rate, its Wilson interval and the paper's value.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository (this file is in benchmarks/masat/)
G2O_VENV = ROOT / ".venv-g2o"
G2O_PINS = ("numpy==1.26.4", "g2o-python==0.0.12")


# --------------------------------------------------------------------------- g2o side (.venv-g2o)
def g2o_worker(in_path: str, out_path: str) -> None:
    """Run g2o's GN on every start in ``in_path``; write each χ² history (entry 0 = initial) to ``out_path``."""
    import g2o
    import numpy as np

    d = np.load(in_path)
    ei, ej, info, max_iter = d["ei"], d["ej"], d["info"], int(d["max_iter"])
    own_guess = bool(d["g2o_guess"])
    out = []
    for meas, init in zip(d["meas"], d["init"]):
        opt = g2o.SparseOptimizer()
        opt.set_algorithm(g2o.OptimizationAlgorithmGaussNewton(g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())))
        keep = []  # the binding does not take ownership: keep the Python objects alive
        for i, p in enumerate(init):
            v = g2o.VertexSE2()
            v.set_id(i)
            v.set_estimate(g2o.SE2(*map(float, p)))
            v.set_fixed(i == 0)
            opt.add_vertex(v)
            keep.append(v)
        for a, b, z, om in zip(ei, ej, meas, info):
            e = g2o.EdgeSE2()
            e.set_vertex(0, opt.vertex(int(a)))
            e.set_vertex(1, opt.vertex(int(b)))
            e.set_measurement(g2o.SE2(*map(float, z)))
            e.set_information(np.array(om, dtype=float))
            opt.add_edge(e)
            keep.append(e)
        opt.initialize_optimization()
        if own_guess:  # g2o's spanning tree (EstimatePropagator, unit edge costs) from the fixed vertex 0
            opt.compute_initial_guess()
        opt.compute_active_errors()
        hist = [opt.active_chi2()]
        t0 = time.perf_counter()
        for _ in range(max_iter):
            opt.optimize(1)
            opt.compute_active_errors()
            hist.append(opt.active_chi2())
        out.append({"chi2": hist, "seconds": time.perf_counter() - t0})
    Path(out_path).write_text(json.dumps(out))


# --------------------------------------------------------------------------- project side (.venv)
def ensure_g2o_venv() -> Path:
    """``.venv-g2o/bin/python``, creating the environment on first use."""
    py = G2O_VENV / "bin" / "python"
    probe = [str(py), "-c", "import g2o, numpy; assert numpy.__version__.startswith('1.')"]
    if py.exists() and subprocess.run(probe, capture_output=True).returncode == 0:
        return py
    print(f"setting up {G2O_VENV.name} ({', '.join(G2O_PINS)}) ...", file=sys.stderr)
    base = getattr(sys, "_base_executable", sys.executable)
    subprocess.run([base, "-m", "venv", "--clear", str(G2O_VENV)], check=True)
    # --no-deps: the wheel lists scikit-build, a build-time tool it does not need at run time
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", *G2O_PINS], capture_output=True, text=True)
    if r.returncode != 0 or subprocess.run(probe, capture_output=True).returncode != 0:
        raise RuntimeError(f"could not install {' '.join(G2O_PINS)} into {G2O_VENV}: {r.stderr.strip()[-300:]}; "
                           "check access to the package registry and run again")
    return py


def run_g2o(ei, ej, info, meas_list, init_list, max_iter: int, g2o_guess: bool = False) -> list[dict]:
    """g2o's χ² histories for several (measurements, start) pairs of one graph structure;
    ``g2o_guess``: replace each start by g2o's own ``computeInitialGuess`` first."""
    import numpy as np

    py = ensure_g2o_venv()
    with tempfile.TemporaryDirectory() as tmp:
        inp, outp = Path(tmp) / "in.npz", Path(tmp) / "out.json"
        np.savez(inp, ei=ei, ej=ej, info=info, meas=np.stack(meas_list), init=np.stack(init_list), max_iter=max_iter,
                 g2o_guess=g2o_guess)
        subprocess.run([str(py), __file__, "--worker", str(inp), str(outp)], check=True)
        return json.loads(outp.read_text())


def protocol(a) -> int:
    import numpy as np
    from scipy.stats import binomtest

    from rgbdslam.posegraph import bench as pb
    from rgbdslam.posegraph.initializers import initialize
    from rgbdslam.posegraph.factors import degrees_of_freedom

    (sigma,) = pb.parse_noise(a.noise)
    level = pb.level_index(sigma)
    ref, gt, _ = pb.reference_graph(a.dataset, a.data)
    insts = list(range(a.first_instance, a.first_instance + a.instances))
    t0 = time.perf_counter()
    graphs = [pb.protocol_instance(ref, a.dataset, sigma, level, i, a.seed) for i in insts]
    own = a.method == "g2o_tree"
    starts = [gt if a.method == "ground_truth" else np.zeros_like(gt) if own else initialize(g, a.method)
              for g in graphs]
    res = []
    for k in range(0, len(insts), a.batch):  # batches keep the .npz small
        res += run_g2o(ref.edges_i, ref.edges_j, graphs[0].info, [g.meas for g in graphs[k:k + a.batch]],
                       starts[k:k + a.batch], a.max_iter, own)
    wall = time.perf_counter() - t0
    dof = degrees_of_freedom(ref)
    ours = {}
    if a.compare:
        for r in pb.load_runs(a.compare):
            if (r.dataset, (r.sigma_x, r.sigma_y, r.sigma_theta), r.method) == (a.dataset, tuple(sigma), a.method):
                ours[r.instance] = r
    lines = [f"`python -m benchmarks.masat.g2o_parity {' '.join(sys.argv[1:])}` — {pb.DATASET_NAMES[a.dataset]}, noise {a.noise}, "
             f"start {a.method}, instances {insts[0]}-{insts[-1]} of seed {a.seed}; g2o-python 0.0.12 in .venv-g2o; "
             f"{os.cpu_count()} CPUs ({platform.machine()}), wall time {wall:.0f} s", "",
             "| instance | g2o: converged / iterations / reduced χ² | ours (--compare) | same verdict |",
             "|---|---|---|---|"]
    conv, agree, compared = 0, 0, 0
    for i, r in zip(insts, res):
        ok, it, x = pb.first_convergence(r["chi2"], a.tol, "relative")
        conv += ok
        cell = "–"
        same = "–"
        if i in ours:
            o = ours[i]
            cell = f"{o.converged_rel} / {o.iterations_rel} / {o.reduced_chi2_rel:.4f}"
            s = (o.converged_rel, o.iterations_rel) == (ok, it)
            same = "yes" if s else "**no**"
            agree += s
            compared += 1
        lines.append(f"| {i} | {ok} / {it} / {x / dof:.4f} | {cell} | {same} |")
    ci = binomtest(conv, len(insts)).proportion_ci(0.95, method="wilson")
    paper = pb.paper_rate(a.dataset, level, "spanning_tree" if own else pb.PAPER_COLUMN.get(a.method))
    lines += ["", f"g2o converged {conv}/{len(insts)} = {conv / len(insts):.2f} [{ci.low:.2f}, {ci.high:.2f}]"
              + (f"; the paper {paper:.2f}" if paper is not None else "")
              + (f"; same verdict and iteration as ours on {agree}/{compared} instances" if compared else "")
              + f"; g2o's mean time per iteration {1e3 * sum(r['seconds'] for r in res) / (len(res) * a.max_iter):.0f} ms."]
    print("\n".join(lines))
    return 0


def record(path: Path) -> int:
    """Reference χ² histories of g2o on a seeded synthetic grid world (three noise / start cases)."""
    import numpy as np

    from rgbdslam.posegraph import bench as pb
    from rgbdslam.posegraph.initializers import initialize
    from rgbdslam.posegraph.synthetic import manhattan_world

    ref, _ = manhattan_world(300, seed=11)
    cases = []
    for name, sigma, method, seed in (("mild noise, MASAT start", (0.1, 0.1, 0.1), "masat", 1),
                                      ("heading noise, spanning-tree start", (0.15, 0.15, 0.3), "spanning_tree", 2),
                                      ("large noise, odometry start", (0.3, 0.3, 0.3), "odometry", 3)):
        g = pb.noisy_instance(ref, sigma, np.random.default_rng(seed))
        init = initialize(g, method)
        (r,) = run_g2o(g.edges_i, g.edges_j, g.info, [g.meas], [init], 20)
        cases.append(dict(name=name, sigma=list(sigma), start=method, n=g.n_vertices, ei=g.edges_i.tolist(),
                          ej=g.edges_j.tolist(), meas=g.meas.tolist(),
                          info_diag=np.diagonal(g.info, axis1=1, axis2=2).tolist(), init=init.tolist(),
                          g2o_chi2=r["chi2"]))
    doc = dict(source="g2o via g2o-python 0.0.12 (numpy 1.26.4), SparseOptimizer + BlockSolverSE2 + "
                      "LinearSolverEigenSE2 + OptimizationAlgorithmGaussNewton, vertex 0 fixed, "
                      "chi2 recomputed after each optimize(1); graph: manhattan_world(300, seed=11)",
               command="python -m benchmarks.masat.g2o_parity --record " + str(path), cases=cases)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc) + "\n")
    print(f"wrote {path}: {len(cases)} cases")
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        g2o_worker(argv[1], argv[2])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="m3500", choices=("m3500", "city10k", "m10000"))
    ap.add_argument("--noise", default="0.15,0.15,0.3")
    ap.add_argument("--method", default="masat",
                    help="our initial guess (masat, spanning_tree, ...), ground_truth, or g2o_tree: g2o's own "
                         "computeInitialGuess, the paper's spanning-tree start")
    ap.add_argument("--instances", type=int, default=10)
    ap.add_argument("--first-instance", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-iter", type=int, default=50)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--batch", type=int, default=10)
    ap.add_argument("--compare", default=None, help="runs.csv of rgbdslam posegraph bench --optimizer g2o")
    ap.add_argument("--record", type=Path, default=None, help="write the test suite's g2o reference file")
    ap.add_argument("--data", default=os.environ.get("RGBDSLAM_DATA", str(Path(__file__).resolve().parents[3] / "shared" / "data")))
    a = ap.parse_args(argv)
    try:
        return record(a.record) if a.record else protocol(a)
    except (RuntimeError, OSError, ValueError, subprocess.CalledProcessError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
