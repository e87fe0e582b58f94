"""The pose-graph tool's file commands (``rgbdslam posegraph init|optimize``): a graph file in,
an initial guess or an optimised graph (g2o) out, a report line back."""

from __future__ import annotations

import time

from rgbdslam.errors import InputError
from rgbdslam.posegraph.convergence import CRITERIA, check_iteration_options
from rgbdslam.posegraph.factors import chi2, degrees_of_freedom
from rgbdslam.posegraph.graph_io import read_graph, write_g2o
from rgbdslam.posegraph.initializers import initialize
from rgbdslam.posegraph.optimize import OPTIMIZERS, run_gauss_newton


def initialize_file(path, method: str, out, fmt: str = "auto") -> str:
    """Read a pose-graph file, build the ``method`` initial guess, write it as g2o; returns a report line."""
    graph = read_graph(path, fmt)
    t0 = time.perf_counter()
    poses = initialize(graph, method)
    dt = time.perf_counter() - t0
    write_g2o(out, graph, poses)
    c = chi2(graph, poses)
    notes = f" ({'; '.join(graph.notes)})" if graph.notes else ""
    return (f"{graph.summary()}{notes}\n{method} initial guess in {dt * 1e3:.1f} ms: chi2 {c:.6g}, "
            f"reduced chi2 {c / max(degrees_of_freedom(graph), 1):.4g}; written to {out}")


def optimize_file(path, init: str = "masat", out=None, max_iter: int = 50, tol: float = 1e-6,
                  criterion: str = "relative", fmt: str = "auto", progress: bool = True,
                  optimizer: str = "gtsam") -> str:
    """Read a graph, initialise it (``init`` method or ``"file"`` for the file's own vertices), run
    Gauss–Newton with a progress bar, optionally write the result as g2o; returns the χ² report."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    check_iteration_options(max_iter, tol)
    if criterion not in CRITERIA:
        raise InputError(f"unknown convergence criterion {criterion!r}; use relative or absolute")
    if optimizer not in OPTIMIZERS:
        raise InputError(f"unknown optimizer {optimizer!r}; use {' or '.join(OPTIMIZERS)}")
    graph = read_graph(path, fmt)
    if optimizer == "g2o" and graph.dim != 2:
        raise InputError(f"{path} is an SE(3) graph and --optimizer g2o is SE(2) only; use --optimizer gtsam or lm")
    t0 = time.perf_counter()
    if init == "file":
        if not graph.has_poses:
            raise InputError(f"{path} has no vertex estimates for every vertex; choose --init masat (or another method)")
        poses = graph.poses
    else:
        poses = initialize(graph, init)
    t_init = time.perf_counter() - t0
    label = "Levenberg-Marquardt" if optimizer == "lm" else "Gauss-Newton"
    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TextColumn("chi2 {task.fields[chi2]}"),
                  TimeElapsedColumn(), disable=not progress) as bar:
        job = bar.add_task("gn", total=max_iter, chi2="")

        def cb(it, c):
            bar.update(job, completed=it, chi2=f"{c:.6g}")

        res = run_gauss_newton(graph, poses, optimizer, max_iter=max_iter, tol=tol, criterion=criterion, callback=cb)
    if res.poses is None:
        hint = "try another --init" + ("" if optimizer == "lm" else " or --optimizer lm")
        if "near vertex" in res.failure:
            hint += ", and check that the information of that vertex's edges constrains all of its pose"
        raise InputError(f"{path}: {label} failed at iteration {res.iterations} ({res.failure}); {hint}")
    if out is not None:
        write_g2o(out, graph, res.poses)
    dof = max(degrees_of_freedom(graph), 1)
    status = "converged" if res.converged else ("failed: " + res.failure if res.failure else "not converged")
    return (f"{graph.summary()}\ninit {init}: {t_init * 1e3:.1f} ms; optimizer {optimizer}\n"
            f"initial chi2 {res.chi2_initial:.6g} (reduced {res.chi2_initial / dof:.4g}); "
            f"final chi2 {res.chi2_final:.6g} (reduced {res.chi2_final / dof:.4g}); "
            f"{res.iterations} iteration(s), {status}; {res.seconds:.2f} s"
            + (f"\nwritten to {out}" if out is not None else ""))
