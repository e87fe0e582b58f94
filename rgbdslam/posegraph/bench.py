"""The MASAT paper's benchmark protocol (docs/references.md §5, the paper's §4), reproduced with GTSAM.

For a dataset (M3500, City10k, M10000) and a noise level (σx, σy, σθ):

1. take the noise-free graph: M3500 / City10k — the ground-truth edge files shipped with iSAM
   (``iSAM/groundtruth/*``); M10000 has no public ground truth, so the original TORO graph
   (``hog-man/w10000.graph``) is optimised to convergence and noise-free measurements are
   regenerated from that optimum (the report says so);
2. make ``instances`` noisy copies: every edge's (x, y, θ) gets independent N(0, σ) noise,
   information Ω = diag(1/σ²); instance k of level l uses the seed ``(seed, dataset, l, k)``
   so results do not depend on the number of workers;
3. build each initial guess (odometry, spanning tree, MASAT, weighted MASAT, LAGO and the
   ground truth as control), time it, run at most ``max_iter`` Gauss–Newton iterations with
   a prior on vertex 0, and record convergence (see :mod:`rgbdslam.posegraph.optimize`),
   iterations and reduced χ² (χ² / dof);
4. summarise: Table 1 (convergence rate) and Table 2 (mean iterations and mean reduced χ² over
   converged runs), with the paper's numbers beside ours, plus mean init time per method.
"""

from __future__ import annotations

import csv
import io
import os
import platform
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from rgbdslam.posegraph.graph import PoseGraphData, se2_between, wrap_angle
from rgbdslam.posegraph.graph_io import read_graph
from rgbdslam.posegraph.initializers import initialize
from rgbdslam.errors import InputError
from rgbdslam.posegraph.convergence import check_iteration_options, chi2_floor, has_converged
from rgbdslam.posegraph.factors import degrees_of_freedom
from rgbdslam.posegraph.optimize import OPTIMIZERS, gauss_newton, run_gauss_newton
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.manifest import record_tables, tables_ready
from rgbdslam.io.text import read_text

DATASETS = ("m3500", "city10k", "m10000")
DATASET_NAMES = {"m3500": "M3500", "city10k": "City10k", "m10000": "M10000"}
BENCH_METHODS = ("odometry", "spanning_tree", "masat", "weighted_masat", "lago", "chordal", "ground_truth")
METHOD_NAMES = {"odometry": "Odometry", "spanning_tree": "Sp. tree", "masat": "MASAT",
                "weighted_masat": "w-MASAT", "lago": "LAGO", "chordal": "Chordal", "ground_truth": "GT"}
NOISE_LEVELS = ((0.1, 0.1, 0.1), (0.15, 0.15, 0.15), (0.2, 0.2, 0.2), (0.25, 0.25, 0.25),
                (0.3, 0.3, 0.3), (0.35, 0.35, 0.35), (0.15, 0.15, 0.3), (0.3, 0.3, 0.15))

# The MASAT paper (docs/references.md), Table 1: convergence rate of (Odometry, Spanning tree, MASAT, Ground truth) + GN
PAPER_TABLE1 = {
    "m3500": [(.64, 1.0, 1.0, 1.0), (.36, .96, 1.0, 1.0), (.26, .82, .96, 1.0), (.28, .72, .94, 1.0),
              (.20, .52, .80, 1.0), (.08, .42, .70, .98), (.04, .28, .76, 1.0), (.76, 1.0, 1.0, 1.0)],
    "city10k": [(0.0, .96, 1.0, 1.0), (0.0, .50, 1.0, 1.0), (.02, .20, .96, 1.0), (0.0, .12, .66, 1.0),
                (0.0, .02, .34, .96), (0.0, 0.0, .18, .98), (0.0, 0.0, .22, .80), (0.0, .80, 1.0, 1.0)],
    "m10000": [(.22, .96, 1.0, 1.0), (.10, .78, .98, 1.0), (.08, .46, .96, 1.0), (.02, .18, .88, 1.0),
               (0.0, .10, .82, 1.0), (0.0, .02, .60, .94), (0.0, .02, .84, 1.0), (.30, .84, 1.0, 1.0)],
}
_PAPER_T1_COLS = ("odometry", "spanning_tree", "masat", "ground_truth")
# The MASAT paper, Table 2 (MASAT + GN): mean iterations, mean reduced χ² over converged runs
PAPER_TABLE2 = {
    "m3500": [(6.3, 1.0), (9.14, 1.04), (12.92, 1.07), (16.36, 1.1), (21.05, 1.16), (22.77, 1.18), (19.95, 1.07), (6.88, 1.0)],
    "city10k": [(6.16, 1.0), (7.8, 1.0), (11.83, 1.01), (12.45, 1.02), (23.94, 1.05), (29.33, 1.09), (23.81, 1.01), (6.68, 1.0)],
    "m10000": [(5.36, 1.0), (6.81, 1.0), (9.52, 1.0), (11.29, 1.0), (15.66, 1.0), (19.23, 1.0), (19.5, 1.0), (5.98, 1.0)],
}

@dataclass
class RunRecord:
    """One (instance, initial guess) run, judged by both readings of the paper's test:
    ``abs``: |Δχ²| < tol, ``rel``: |Δχ²|/χ² < tol (read off the same χ² history)."""

    dataset: str
    sigma_x: float
    sigma_y: float
    sigma_theta: float
    instance: int
    method: str
    chi2_initial: float
    converged_abs: bool
    iterations_abs: int
    reduced_chi2_abs: float
    converged_rel: bool
    iterations_rel: int
    reduced_chi2_rel: float
    init_seconds: float
    gn_seconds: float
    failure: str = ""

    def verdict(self, criterion: str) -> tuple[bool, int, float]:
        if criterion == "relative":
            return self.converged_rel, self.iterations_rel, self.reduced_chi2_rel
        return self.converged_abs, self.iterations_abs, self.reduced_chi2_abs


def default_data_dir() -> Path:
    """``$RGBDSLAM_DATA`` (the development data folder); an installed package has no other default."""
    env = os.environ.get("RGBDSLAM_DATA")
    if env:
        return Path(env)
    raise InputError("no data folder: pass --data FOLDER (the one holding posegraph/) or set RGBDSLAM_DATA")


def parse_noise(text: str) -> list[tuple[float, float, float]]:
    """``"0.2,0.2,0.2"`` -> one level; ``"0.2"`` -> (0.2, 0.2, 0.2); ``"all"`` -> the MASAT paper's 8 levels;
    several levels separated by ``;``."""
    text = text.strip()
    if text == "all":
        return list(NOISE_LEVELS)
    levels = []
    for part in text.split(";"):
        try:
            vals = [float(v) for v in part.split(",")]
        except ValueError:
            raise InputError(f"--noise {text!r} is not 'all' or numbers like 0.2,0.2,0.2") from None
        if len(vals) == 1:
            vals = vals * 3
        if len(vals) != 3 or not all(v > 0 for v in vals):  # "not v > 0" also catches nan
            raise InputError(f"--noise {part!r} needs three positive standard deviations sx,sy,stheta")
        check_noise_level(vals, f"--noise {part!r}")
        levels.append(tuple(vals))
    return levels


def check_noise_level(sigma, what: str = "noise level") -> None:
    """Three finite standard deviations > 0 whose information 1/σ² is a usable (finite, non-zero)
    number; an :class:`InputError` naming ``what`` otherwise."""
    try:
        vals = np.array([float(v) for v in sigma])
    except (TypeError, ValueError):
        raise InputError(f"{what} is not three numbers sx,sy,stheta; give e.g. 0.2,0.2,0.2") from None
    if len(vals) != 3 or not np.all(vals > 0):  # "not v > 0" also catches nan
        raise InputError(f"{what} needs three positive standard deviations sx,sy,stheta")
    if not np.all(np.isfinite(vals)):
        raise InputError(f"{what} has an infinite standard deviation; give finite values like 0.2,0.2,0.2")
    with np.errstate(over="ignore", under="ignore", divide="ignore"):
        info = 1.0 / np.square(vals)
    if not np.all(np.isfinite(info) & (info > 0)):
        raise InputError(f"{what} has a standard deviation so {'small' if np.any(~np.isfinite(info)) else 'large'} "
                         f"that its information 1/σ² is not a usable number; give values like 0.2,0.2,0.2")


def check_seed(seed) -> None:
    """The noise seed: a whole number >= 0 (NumPy's generators refuse negative seeds)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"--seed must be a whole number >= 0, not {seed!r}; give e.g. --seed 0")


def parse_methods(text: str, allowed=BENCH_METHODS) -> tuple[str, ...]:
    """``"masat, odometry"`` -> ``("masat", "odometry")`` (repeats dropped); an empty list or an
    unknown name is an :class:`InputError`."""
    out: list[str] = []
    for m in (text or "").split(","):
        m = m.strip()
        if m and m not in out:
            out.append(m)
    if not out:
        raise InputError(f"--methods {text!r} names no initial guess; give a comma-separated list from "
                         f"{','.join(allowed)}")
    unknown = [m for m in out if m not in allowed]
    if unknown:
        raise InputError(f"--methods: unknown initial guess(es) {', '.join(unknown)}; use {','.join(allowed)}")
    return tuple(out)


# --------------------------------------------------------------------------- noise-free graphs


def _regenerate(graph: PoseGraphData, poses: np.ndarray) -> PoseGraphData:
    g = graph.with_poses(poses)
    g.meas = se2_between(poses[g.edges_i], poses[g.edges_j])
    return g


def reference_graph(dataset: str, data_dir: str | Path | None = None) -> tuple[PoseGraphData, np.ndarray, str]:
    """Noise-free graph, ground-truth poses (vertex 0 at the origin) and a note on where they come from."""
    data_dir = Path(data_dir) if data_dir else default_data_dir()
    root = data_dir / "posegraph"
    if dataset not in DATASETS:
        raise InputError(f"unknown benchmark dataset {dataset!r}; use one of {', '.join(DATASETS)}")
    if dataset in ("m3500", "city10k"):
        name = "manhattanOlson3500" if dataset == "m3500" else "city10000"
        path = root / "iSAM" / "groundtruth" / f"{name}_groundtruth.txt"
        if not path.is_file():
            raise InputError(f"ground-truth edges {path} not found; set RGBDSLAM_DATA or --data to the data folder")
        g = read_graph(path, "isam")
        gt = initialize(g, "odometry")  # the noise-free edges are consistent: chaining them is exact
        g = _regenerate(g, gt)  # remove the files' 6-digit rounding so the noise-free χ² is 0
        return g, gt, f"noise-free edges: {path.name} (iSAM ground truth)"
    path = root / "hog-man" / "w10000.graph"
    if not path.is_file():
        raise InputError(f"M10000 graph {path} not found; set RGBDSLAM_DATA or --data to the data folder")
    g = read_graph(path, "toro")
    init = initialize(g, "masat")
    res = gauss_newton(g, init, max_iter=100, tol=1e-10, criterion="relative")
    if not res.converged:
        raise InputError(f"{path}: optimising the original M10000 graph did not converge; cannot build a reference")
    opt = res.poses
    # put vertex 0 at the origin
    from rgbdslam.posegraph.graph import se2_compose, se2_inverse
    opt = se2_compose(se2_inverse(opt[0]), opt)
    g = _regenerate(g, opt)
    note = (f"M10000 has no public ground truth: {path.name} was optimised to convergence "
            f"(MASAT + {res.iterations} GN iterations, reduced chi2 {res.chi2_final / degrees_of_freedom(g):.3f}) "
            f"and noise-free measurements were regenerated from that optimum")
    return g, opt, note


def noisy_instance(ref: PoseGraphData, sigma, rng: np.random.Generator) -> PoseGraphData:
    """A noisy copy of ``ref``: N(0, σ) on each edge's (x, y, θ) (θ wrapped), information diag(1/σ²).
    ``sigma`` is one (3,) triple for every edge, or an (n_edges, 3) array of per-edge deviations."""
    sigma = np.broadcast_to(np.asarray(sigma, float), ref.meas.shape)
    g = ref.copy()
    g.meas = ref.meas + rng.normal(size=ref.meas.shape) * sigma
    g.meas[:, 2] = wrap_angle(g.meas[:, 2])
    g.info = np.zeros((ref.n_edges, 3, 3))
    g.info[:, [0, 1, 2], [0, 1, 2]] = 1.0 / sigma**2
    g.has_poses = False
    return g


# ------------------------------------------------------------------------------ running it

def _engine_task(shared, *args):
    """One instance on an engine's worker; ``shared`` = (dataset, reference graph, ground truth), sent once."""
    dataset, ref, gt = shared
    sigma, level, instance, seed, methods, max_iter, tol, optimizer = args
    return run_instance(ref, gt, dataset, sigma, level, instance, seed, methods, max_iter, tol, optimizer)


def run_instance(ref: PoseGraphData, gt: np.ndarray, dataset: str, sigma, level: int, instance: int, seed: int,
                 methods=BENCH_METHODS, max_iter: int = 50, tol: float = 1e-6,
                 optimizer: str = "gtsam", custom: dict | None = None) -> list[RunRecord]:
    """All initial guesses + GN on one noisy instance (seeded by ``(seed, dataset, level, instance)``)."""
    return run_starts(protocol_instance(ref, dataset, sigma, level, instance, seed), gt, dataset, sigma, instance,
                      methods, max_iter, tol, optimizer, custom)


def protocol_instance(ref: PoseGraphData, dataset: str, sigma, level: int, instance: int, seed: int) -> PoseGraphData:
    """Noisy instance ``instance`` of noise level ``level`` — the same graph every run of the protocol uses."""
    check_seed(seed)
    rng = np.random.default_rng([seed, DATASETS.index(dataset) if dataset in DATASETS else 99, level, instance])
    return noisy_instance(ref, sigma, rng)


def run_starts(g: PoseGraphData, gt: np.ndarray, dataset: str, sigma, instance: int, methods=BENCH_METHODS,
               max_iter: int = 50, tol: float = 1e-6, optimizer: str = "gtsam",
               custom: dict | None = None) -> list[RunRecord]:
    """Each initial guess of ``methods`` + at most ``max_iter`` GN iterations on the noisy graph ``g``;
    one :class:`RunRecord` per method (``sigma`` and ``instance`` only label the records).
    ``custom`` maps extra method labels to functions ``graph -> poses`` (for studies of variants)."""
    dof = degrees_of_freedom(g)
    custom = custom or {}
    out = []
    for m in methods:
        t0 = time.perf_counter()
        try:
            p = gt if m == "ground_truth" else custom[m](g) if m in custom else initialize(g, m)
            fail = ""
        except InputError as e:
            p, fail = None, str(e)
        t_init = time.perf_counter() - t0
        if p is None:
            nan = float("nan")
            out.append(RunRecord(dataset, *map(float, sigma), instance, m, nan, False, 0, nan, False, 0, nan,
                                 t_init, 0.0, fail))
            continue
        # run to the stricter absolute test; the relative verdict is read off the same χ² history
        r = run_gauss_newton(g, p, optimizer, max_iter=max_iter, tol=tol, criterion="absolute", keep_poses=False)
        ca, ia, xa = first_convergence(r.chi2_history, tol, "absolute")
        cr, ir, xr = first_convergence(r.chi2_history, tol, "relative", chi2_floor(g, p))
        out.append(RunRecord(dataset, *map(float, sigma), instance, m, r.chi2_initial, ca, ia, xa / dof, cr, ir,
                             xr / dof, t_init, r.seconds, r.failure))
    return out


def first_convergence(history: list[float], tol: float, criterion: str,
                      floor: float = 0.0) -> tuple[bool, int, float]:
    """(converged, iteration, χ² at that iteration) of the first iteration passing ``criterion``
    (relative: with the rounding ``floor``, :func:`rgbdslam.posegraph.convergence.chi2_floor`) in a χ²
    history (entry 0 = initial χ²); (False, last iteration, last χ²) if none does."""
    for k in range(1, len(history)):
        if has_converged(history[k - 1], history[k], tol, criterion, floor):
            return True, k, history[k]
    return False, len(history) - 1, history[-1]


def run_benchmark(dataset: str, noise_levels, instances: int = 50, max_iter: int = 50, workers: int = 1,
                  seed: int = 0, out_dir: str | Path | None = None, data_dir: str | Path | None = None,
                  methods=BENCH_METHODS, tol: float = 1e-6, criterion: str = "relative",
                  progress: bool = True, reference: tuple[PoseGraphData, np.ndarray, str] | None = None,
                  first_instance: int = 0, optimizer: str = "gtsam", engine: str = "local",
                  address: str | None = None) -> dict:
    """Run the protocol (GN: ``optimizer`` ``"gtsam"`` or ``"g2o"``, see :mod:`rgbdslam.posegraph.gn2d`); write ``runs.csv``, ``table1.csv``, ``table2.csv``, ``report.md`` into ``out_dir``.

    The instances run on ``engine`` (:mod:`rgbdslam.engine`: ``local`` processes, or ``ray`` with
    ``workers`` CPUs or the cluster at ``address``); the graph travels to each worker once.
    Instances ``first_instance .. first_instance + instances - 1`` are run (so a later call can add
    instances; merge the runs.csv files with :func:`merge_runs`).
    ``reference`` = ``(noise-free graph, ground-truth poses, note)`` replaces the dataset's files
    (tests, other graphs).  Returns ``{"records": [...], "report": markdown, "note": reference note}``.
    """
    for name, v, low in (("--instances", instances, 1), ("--workers", workers, 1), ("--first-instance", first_instance, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
            raise InputError(f"{name} must be a whole number >= {low}, not {v!r}")
    cap = 4 * (os.cpu_count() or 1)
    if workers > cap:
        raise InputError(f"--workers {workers} is more than 4x this machine's {os.cpu_count()} CPUs; give at most {cap} "
                         f"(each worker holds a copy of the graph)")
    check_iteration_options(max_iter, tol)
    check_seed(seed)
    methods = tuple(methods)
    if not methods:
        raise InputError(f"no initial guesses to compare; give --methods from {','.join(BENCH_METHODS)}")
    unknown = [m for m in methods if m not in BENCH_METHODS]
    if unknown:
        raise InputError(f"unknown benchmark method(s) {unknown}; use {', '.join(BENCH_METHODS)}")
    if len(set(methods)) < len(methods):
        raise InputError(f"a benchmark method is listed twice in {','.join(methods)}; list each once")
    noise_levels = list(noise_levels)
    if not noise_levels:
        raise InputError("no noise levels given; give --noise, e.g. 0.2,0.2,0.2 or all")
    for s in noise_levels:
        check_noise_level(s, f"noise level {s!r}")
    noise_levels = [tuple(float(v) for v in s) for s in noise_levels]
    if criterion not in ("absolute", "relative"):
        raise InputError(f"unknown convergence criterion {criterion!r}; use absolute or relative")
    if optimizer not in OPTIMIZERS:
        raise InputError(f"unknown optimizer {optimizer!r}; use {' or '.join(OPTIMIZERS)}")
    t_start = time.perf_counter()
    ref, gt, note = reference if reference is not None else reference_graph(dataset, data_dir)
    tasks = [(tuple(s), level_index(s), k, seed, tuple(methods), max_iter, tol, optimizer)
             for s in noise_levels for k in range(first_instance, first_instance + instances)]
    records: list[RunRecord] = []
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    cols = (TextColumn(f"posegraph bench {DATASET_NAMES.get(dataset, dataset)}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*cols, disable=not progress, transient=False) as bar:
        job = bar.add_task("instances", total=len(tasks))
        from rgbdslam.engine import build_engine

        with build_engine(engine, workers, address) as eng:
            engine_text = eng.describe()
            for _, recs in eng.map(_engine_task, tasks, shared=(dataset, ref, gt)):
                records.extend(recs)
                bar.advance(job)
    records.sort(key=lambda r: (level_index((r.sigma_x, r.sigma_y, r.sigma_theta)), r.sigma_x, r.sigma_theta,
                                r.instance, methods.index(r.method)))
    wall = time.perf_counter() - t_start
    header = (f"dataset {DATASET_NAMES.get(dataset, dataset)}; {instances} instance(s) per level"
              + (f" (instances {first_instance}..{first_instance + instances - 1})" if first_instance else "")
              + f"; max {max_iter} GN ({optimizer}) "
              f"iterations; converged when {_crit_text(criterion, tol)}; seed {seed}; "
              f"engine {engine_text}; wall time {wall:.0f} s; machine: {platform.processor() or platform.machine()}, "
              f"{os.cpu_count()} CPUs, Python {platform.python_version()}\n\n{note}.\n")
    report = header + "\n" + format_report(records, dataset, methods, criterion, tol)
    if out_dir is not None:
        write_outputs(Path(out_dir), records, dataset, methods, report, criterion)
    return {"records": records, "report": report, "note": note}


def level_index(sigma) -> int:
    """Index of ``sigma`` in the MASAT paper's 8 noise levels (100 if it is not one of them)."""
    s = tuple(round(float(v), 6) for v in sigma)
    for k, lv in enumerate(NOISE_LEVELS):
        if s == tuple(round(v, 6) for v in lv):
            return k
    return 100


# ------------------------------------------------------------------------------ summaries


OPTIMUM_RTOL = 1e-3  # "reached the optimum": final χ² within 0.1 % of ground truth + GN's on the same instance


def summarise(records: list[RunRecord], criterion: str = "relative") -> dict:
    """{(sigma, method): dict(n, rate, opt_rate, iters, rchi2, init_s, gn_s)}; iters/rchi2 over converged runs.

    ``opt_rate``: fraction of runs that converged *and* ended within :data:`OPTIMUM_RTOL` of the χ²
    that ground truth + GN reached on the same instance (NaN without ground-truth runs) — a run
    that "converged" into a local minimum does not count."""
    groups: dict = {}
    gt_chi2: dict = {}
    for r in records:
        groups.setdefault(((r.sigma_x, r.sigma_y, r.sigma_theta), r.method), []).append(r)
        if r.method == "ground_truth":
            gt_chi2[((r.sigma_x, r.sigma_y, r.sigma_theta), r.instance)] = r.verdict(criterion)[2]
    out = {}
    for key, rs in groups.items():
        v = [r.verdict(criterion) for r in rs]
        conv = [x for x in v if x[0]]
        refs = [gt_chi2.get((key[0], r.instance)) for r in rs]
        if all(ref is not None and np.isfinite(ref) for ref in refs):
            opt_rate = float(np.mean([at_optimum(x[0], x[2], ref) for x, ref in zip(v, refs)]))
        else:
            opt_rate = float("nan")
        out[key] = dict(
            n=len(rs), rate=len(conv) / len(rs), opt_rate=opt_rate,
            iters=float(np.mean([x[1] for x in conv])) if conv else float("nan"),
            rchi2=float(np.mean([x[2] for x in conv])) if conv else float("nan"),
            init_s=float(np.mean([r.init_seconds for r in rs])), gn_s=float(np.mean([r.gn_seconds for r in rs])))
    return out


def noise_text(sigma) -> str:
    return ",".join(f"{v:g}" for v in sigma)


def at_optimum(converged: bool, reduced_chi2: float, reference: float) -> bool:
    """Table 1c's rule: converged, and within :data:`OPTIMUM_RTOL` of ground truth + GN's reduced χ²."""
    return bool(converged and reduced_chi2 <= reference * (1 + OPTIMUM_RTOL))


def _fmt(v, nd=2):
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{nd}f}"


def _levels(records):
    return sorted({(r.sigma_x, r.sigma_y, r.sigma_theta) for r in records}, key=lambda s: (level_index(s), s))


def table_rows(records, dataset, methods, criterion: str = "relative"):
    """Rows for table1.csv and table2.csv: ours (by ``criterion``; Table 1 also the other criterion)
    and the paper's numbers."""
    S = summarise(records, criterion)
    other = "relative" if criterion == "absolute" else "absolute"
    S2 = summarise(records, other)
    t1, t2 = [], []
    for s in _levels(records):
        k = level_index(s)
        p1 = PAPER_TABLE1[dataset][k] if k < 8 and dataset in PAPER_TABLE1 else None
        p2 = PAPER_TABLE2[dataset][k] if k < 8 and dataset in PAPER_TABLE2 else None
        counts = sorted({S[(s, m)]["n"] for m in methods})
        row1 = {"noise": noise_text(s), "instances": "/".join(map(str, counts)), "criterion": criterion}
        row2 = dict(row1)
        for m in methods:
            row1[f"{m}_n"] = S[(s, m)]["n"]
        for m in methods:
            row1[f"{m}_rate"] = S[(s, m)]["rate"]
        for m in methods:
            row1[f"{m}_rate_{other}"] = S2[(s, m)]["rate"]
        for m in methods:
            row1[f"{m}_optimum_rate"] = S[(s, m)]["opt_rate"]
        for m in methods:
            row1[f"{m}_init_ms"] = 1e3 * S[(s, m)]["init_s"]
        for j, m in enumerate(_PAPER_T1_COLS):
            row1[f"paper_{m}_rate"] = p1[j] if p1 else float("nan")
        for m in methods:
            row2[f"{m}_iters"] = S[(s, m)]["iters"]
            row2[f"{m}_reduced_chi2"] = S[(s, m)]["rchi2"]
        row2["paper_masat_iters"] = p2[0] if p2 else float("nan")
        row2["paper_masat_reduced_chi2"] = p2[1] if p2 else float("nan")
        t1.append(row1)
        t2.append(row2)
    return t1, t2


def _crit_text(criterion, tol=1e-6):
    return f"|Δχ²| < {tol:g}" if criterion == "absolute" else f"|Δχ²|/χ² < {tol:g}"


def format_report(records, dataset, methods=BENCH_METHODS, criterion: str = "relative", tol: float = 1e-6) -> str:
    t1, t2 = table_rows(records, dataset, methods, criterion)
    other = "relative" if criterion == "absolute" else "absolute"
    head = " | ".join(METHOD_NAMES[m] for m in methods)
    lines = [f"Table 1 — convergence rate ({_crit_text(criterion, tol)}), ours (paper):", "",
             f"| noise | n | {head} |", "|---|---|" + "---|" * len(methods)]
    for r in t1:
        cells = [_fmt(r[f"{m}_rate"]) + (f" ({_fmt(r[f'paper_{m}_rate'])})" if m in _PAPER_T1_COLS else "")
                 for m in methods]
        lines.append(f"| {r['noise']} | {r['instances']} | " + " | ".join(cells) + " |")
    lines += ["", f"Table 1b — the same runs judged by {_crit_text(other, tol)}:", "",
              f"| noise | {head} |", "|---|" + "---|" * len(methods)]
    for r in t1:
        lines.append(f"| {r['noise']} | " + " | ".join(_fmt(r[f"{m}_rate_{other}"]) for m in methods) + " |")
    if any(np.isfinite(r[f"{m}_optimum_rate"]) for r in t1 for m in methods):
        lines += ["", f"Table 1c — converged *to the optimum*: χ² within {OPTIMUM_RTOL:.1%} of what ground truth + GN "
                  "reached on the same instance (local minima do not count):", "",
                  f"| noise | {head} |", "|---|" + "---|" * len(methods)]
        for r in t1:
            lines.append(f"| {r['noise']} | " + " | ".join(_fmt(r[f"{m}_optimum_rate"]) for m in methods) + " |")
    if dataset in PAPER_TABLE1:
        cmp_rows = compare_with_paper(records, methods, criterion=criterion)
        n_cmp = len(cmp_rows)
        diff = [r for r in cmp_rows if r["verdict"] != "same"]
        lines += ["", "Differences from the paper's Table 1 beyond sampling noise (two-sided Fisher exact test, "
                  "p < 0.05, the paper's count = rate × 50; w-MASAT and chordal against the paper's MASAT): "
                  + ("; ".join(f"{noise_text(r['sigma'])} {METHOD_NAMES[r['method']]} {r['rate']:.2f} vs "
                               + ("the paper's MASAT " if r["paper_column"] != r["method"] else "")
                               + f"{r['paper']:.2f} ({r['verdict']}, p = {r['p']:.3f}, Holm-adjusted over the "
                               f"table's {n_cmp} comparisons {r['p_holm']:.3f})" for r in diff) or "none") + "."]
    lines += ["", "Table 2 — mean GN iterations / mean reduced χ² over converged runs "
              "(paper's MASAT+GN in brackets):", "", f"| noise | {head} |", "|---|" + "---|" * len(methods)]
    for r in t2:
        cells = []
        for m in methods:
            c = f"{_fmt(r[f'{m}_iters'], 1)} / {_fmt(r[f'{m}_reduced_chi2'], 3)}"
            if m == "masat":
                c += f" ({_fmt(r['paper_masat_iters'], 2)} / {_fmt(r['paper_masat_reduced_chi2'], 2)})"
            cells.append(c)
        lines.append(f"| {r['noise']} | " + " | ".join(cells) + " |")
    lines += ["", "Mean initialisation time per method (ms):", "", f"| noise | {head} |", "|---|" + "---|" * len(methods)]
    for r in t1:
        lines.append(f"| {r['noise']} | " + " | ".join(_fmt(r[f'{m}_init_ms'], 1) for m in methods) + " |")
    return "\n".join(lines) + "\n"


# the paper column a start is compared with (it has no weighted MASAT or chordal column)
PAPER_COLUMN = {"odometry": "odometry", "spanning_tree": "spanning_tree", "masat": "masat",
                 "weighted_masat": "masat", "chordal": "masat", "ground_truth": "ground_truth"}


def paper_rate(dataset: str, level: int, column: str | None) -> float | None:
    """The paper's Table 1 convergence rate of ``column`` (one of its four starts) at noise level
    ``level``; None where the paper has no such cell."""
    if dataset not in PAPER_TABLE1 or column not in _PAPER_T1_COLS or not 0 <= level < len(NOISE_LEVELS):
        return None
    return PAPER_TABLE1[dataset][level][_PAPER_T1_COLS.index(column)]


def compare_with_paper(records, methods, alpha: float = 0.05, paper_n: int = 50,
                       criterion: str = "relative") -> list[dict]:
    """Our Table 1 rates against the paper's, one row per (noise level, start) that has a paper
    column (:data:`PAPER_COLUMN`): count ``k/n``, 95 % Wilson interval ``lo..hi``, the two-sided
    Fisher exact p of "same rate" (the paper's count = its rate × ``paper_n``) and a verdict
    ``above`` / ``below`` (p < ``alpha``) or ``same``; ``p_holm`` / ``verdict_holm`` are the same
    after a Holm–Bonferroni adjustment over all the rows returned (:func:`holm_adjust`)."""
    from scipy.stats import binomtest, fisher_exact

    dataset = records[0].dataset
    groups: dict = {}
    for r in records:
        groups.setdefault(((r.sigma_x, r.sigma_y, r.sigma_theta), r.method), []).append(r.verdict(criterion)[0])
    rows = []
    for sigma in sorted({k[0] for k in groups}, key=lambda s: (level_index(s), s)):
        level = level_index(sigma)
        for m in methods:
            paper = paper_rate(dataset, level, PAPER_COLUMN.get(m))
            if paper is None or (sigma, m) not in groups:
                continue
            conv = groups[(sigma, m)]
            k, n = sum(conv), len(conv)
            pk = round(paper * paper_n)
            ci = binomtest(k, n).proportion_ci(0.95, method="wilson")
            p = float(fisher_exact([[k, n - k], [pk, paper_n - pk]])[1])
            verdict = "same" if p >= alpha else ("above" if k / n > paper else "below")
            rows.append(dict(dataset=dataset, sigma=sigma, method=m, k=k, n=n, rate=k / n, lo=ci.low, hi=ci.high,
                             paper=paper, paper_column=PAPER_COLUMN[m], p=p, verdict=verdict))
    for r, ph in zip(rows, holm_adjust([r["p"] for r in rows])):
        r["p_holm"] = ph
        r["verdict_holm"] = "same" if ph >= alpha else r["verdict"]
    return rows


def holm_adjust(p) -> np.ndarray:
    """Holm–Bonferroni adjusted p-values of a family of tests: the i-th smallest p becomes
    ``max over j <= i of min(1, (m - j + 1) p_(j))``.  A cell whose adjusted p is below alpha differs
    from the paper even after allowing for the number of cells compared (family-wise error <= alpha)."""
    p = np.asarray(p, float)
    m = len(p)
    if m == 0:
        return p
    idx = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[idx]))
    out = np.empty(m)
    out[idx] = adj
    return out


def _csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    return buf.getvalue()


def write_runs_csv(path: Path, records) -> None:
    """One row per :class:`RunRecord` (what ``--merge-runs`` and ``benchmarks/masat/compare_to_paper.py`` read)."""
    atomic_write_text(path, _csv_text([asdict(r) for r in records]))


BENCH_FILES = ("runs.csv", "table1.csv", "table2.csv", "report.md")  # what --out receives


def write_outputs(out_dir: Path, records, dataset, methods, report: str, criterion: str = "relative") -> None:
    """The tables into ``out_dir``, replacing only earlier tables (its manifest, docs/outputs.md)."""
    tables_ready(out_dir, BENCH_FILES)
    write_runs_csv(out_dir / "runs.csv", records)
    t1, t2 = table_rows(records, dataset, methods, criterion)
    atomic_write_text(out_dir / "table1.csv", _csv_text(t1))
    atomic_write_text(out_dir / "table2.csv", _csv_text(t2))
    atomic_write_text(out_dir / "report.md", report)
    record_tables(out_dir, BENCH_FILES)


def bench_command(dataset: str, noise: str, instances: int = 50, max_iter: int = 50, workers: int = 1, seed: int = 0,
                  criterion: str = "relative", methods: str = ",".join(BENCH_METHODS), out_dir=None, data_dir=None,
                  progress: bool = True, timing_only: bool = False, merge: tuple = (), first_instance: int = 0,
                  optimizer: str = "gtsam", engine: str = "local", address: str | None = None) -> str:
    """CLI entry: parse the option strings, run :func:`run_benchmark` (or only
    :func:`time_initialisers`, or only :func:`merge_runs`), return the markdown report."""
    if merge:
        return merge_runs(list(merge), out_dir, criterion)
    if dataset is None:
        raise InputError("--dataset is required (m3500, city10k or m10000) unless --merge-runs is given")
    levels = parse_noise(noise)
    mlist = parse_methods(methods)
    check_seed(seed)
    if timing_only:
        timed = tuple(m for m in mlist if m != "ground_truth")
        if not timed:
            raise InputError("--timing-only times initial guesses and ground_truth is none; add a method to --methods")
        return time_initialisers(dataset, levels, seed=seed, data_dir=data_dir, methods=timed)
    if out_dir is not None:  # a file of the user's in the way: said before the benchmark runs
        tables_ready(Path(out_dir), BENCH_FILES)
    res = run_benchmark(dataset, levels, instances=instances, max_iter=max_iter, workers=workers, seed=seed,
                        first_instance=first_instance, optimizer=optimizer, engine=engine, address=address,
                        out_dir=out_dir, data_dir=data_dir, methods=mlist, criterion=criterion, progress=progress)
    return res["report"] + (f"\nwritten to {out_dir}/ (runs.csv, table1.csv, table2.csv, report.md)" if out_dir else "")


def time_initialisers(dataset: str, noise_levels, repeats: int = 5, seed: int = 0, data_dir=None,
                      methods=("odometry", "spanning_tree", "masat", "weighted_masat", "lago", "chordal")) -> str:
    """Best-of-``repeats`` wall time (ms) of each initial guess on one noisy instance per level.

    MASAT's cost depends only on the graph, so its row should be flat across noise levels.
    """
    check_seed(seed)
    if not methods:
        raise InputError("no initial guesses to time; give --methods")
    if isinstance(repeats, bool) or not isinstance(repeats, (int, np.integer)) or repeats < 1:
        raise InputError(f"repeats must be a whole number >= 1, not {repeats!r}")
    for s in noise_levels:
        check_noise_level(s, f"noise level {s!r}")
    ref, _, note = reference_graph(dataset, data_dir)
    lines = [f"Initialisation time on {DATASET_NAMES.get(dataset, dataset)} ({ref.n_vertices} vertices, "
             f"{ref.n_edges} edges), best of {repeats}, ms:", "",
             "| noise | " + " | ".join(METHOD_NAMES[m] for m in methods) + " |", "|---|" + "---|" * len(methods)]
    for s in noise_levels:
        g = noisy_instance(ref, s, np.random.default_rng([seed, 7, level_index(s)]))
        cells = []
        for m in methods:
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                initialize(g, m)
                best = min(best, time.perf_counter() - t0)
            cells.append(f"{best * 1e3:.1f}")
        lines.append(f"| {noise_text(s)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def load_runs(path: str | Path) -> list[RunRecord]:
    """Read a ``runs.csv`` written by :func:`run_benchmark`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"benchmark runs file {path} does not exist; give the runs.csv of a bench --out folder")
    types = {f.name: f.type for f in fields(RunRecord)}
    out = []
    text = read_text(path, "benchmark runs file")
    try:
        for lineno, row in enumerate(csv.DictReader(io.StringIO(text, newline="")), 2):
            try:
                kw = {}
                for k, v in row.items():
                    t = types[k]
                    kw[k] = (v == "True") if t in ("bool", bool) else int(v) if t in ("int", int) else \
                        float(v) if t in ("float", float) else v
                out.append(RunRecord(**kw))
            except (KeyError, ValueError, TypeError):
                raise InputError(f"{path}:{lineno}: not a runs.csv row of rgbdslam posegraph bench; give the runs.csv "
                                 f"of a bench --out folder") from None
    except csv.Error as e:
        raise InputError(f"{path}: not a readable CSV file ({e}); give the runs.csv of a bench --out folder") from None
    return out


def merge_runs(paths, out_dir=None, criterion: str = "relative") -> str:
    """Merge ``runs.csv`` files of one dataset (a later file's (noise, instance, method) rows
    replace earlier ones, e.g. a re-run of one method) and rebuild the report."""
    merged: dict = {}
    for p in paths:
        for r in load_runs(p):
            merged[(r.dataset, r.sigma_x, r.sigma_y, r.sigma_theta, r.instance, r.method)] = r
    records = list(merged.values())
    if not records:
        raise InputError("the runs.csv files hold no runs; give runs.csv files of rgbdslam posegraph bench")
    datasets = {r.dataset for r in records}
    if len(datasets) != 1:
        raise InputError(f"merge runs.csv files of one dataset at a time (found {', '.join(sorted(datasets))})")
    dataset = datasets.pop()
    methods = tuple(m for m in BENCH_METHODS if any(r.method == m for r in records))
    records.sort(key=lambda r: (level_index((r.sigma_x, r.sigma_y, r.sigma_theta)), r.sigma_x, r.sigma_theta,
                                r.instance, methods.index(r.method)))
    counts = sorted({sum(1 for r in records if r.method == m and (r.sigma_x, r.sigma_theta) == (q.sigma_x, q.sigma_theta))
                     for q in records for m in methods})
    header = (f"dataset {DATASET_NAMES.get(dataset, dataset)}; merged from {', '.join(str(p) for p in paths)}; "
              f"instances per (level, method): {', '.join(map(str, counts))}\n")
    report = header + "\n" + format_report(records, dataset, methods, criterion)
    if out_dir is not None:
        write_outputs(Path(out_dir), records, dataset, methods, report, criterion)
    return report
