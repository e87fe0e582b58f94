"""Evaluation report: ATE + RPE of one estimate, as JSON, plots and a rich table.

``evaluate_files`` serves ``rgbdslam evaluate``; ``evaluate_trajectories`` serves the
pipeline at the end of a run. Both return an :class:`EvaluationReport`.
``compare_and_print`` serves ``rgbdslam evaluate GT EST EST ...``: one report per estimate,
one table with a row each, one top view with all of them.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rgbdslam.errors import InputError, RgbdslamError
from rgbdslam.evaluation.ate import AteResult, ErrorStats, PairingError, ate
from rgbdslam.evaluation.rpe import RpeResult, check_delta, rpe
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.trajectory import Trajectory, read_tum


@dataclass
class EvaluationReport:
    ate: AteResult
    rpe: RpeResult | None
    settings: dict[str, Any]
    gt_name: str = "ground truth"
    est_name: str = "estimate"
    rpe_note: str | None = None  # why RPE is missing, when it is
    plots: list[str] = field(default_factory=list)
    json_path: str | None = None
    kitti: Any = None  # evaluation.kitti.KittiResult: KITTI's relative metric, when a segment fits

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-pose arrays)."""
        a = self.ate
        d: dict[str, Any] = {
            "ground_truth": self.gt_name,
            "estimate": self.est_name,
            "settings": dict(self.settings),
            "ate": {
                **_stats_dict(a),
                "n_pairs": a.n_pairs,
                "align": a.align,
                "scale": a.scale,
                "transform": a.transform.tolist(),
                "unit": "m",
            },
            "rpe": None,
            "plots": list(self.plots),
        }
        if self.rpe is not None:
            r = self.rpe
            d["rpe"] = {
                "delta": r.delta,
                "delta_unit": r.delta_unit,
                "n_pairs": r.n_pairs,
                "trans": {**_stats_dict(r.trans), "unit": "m"},
                "rot": {**_stats_dict(r.rot), "unit": "deg"},
            }
        elif self.rpe_note:
            d["rpe_note"] = self.rpe_note
        d["kitti"] = self.kitti.to_dict() if self.kitti is not None else None
        return d


def _stats_dict(s: ErrorStats) -> dict[str, float | None]:
    keys = [f.name for f in fields(ErrorStats)]
    return {k: (None if math.isnan(getattr(s, k)) else getattr(s, k)) for k in keys}


def evaluate_trajectories(
    gt: Trajectory,
    est: Trajectory,
    align: str = "se3",
    delta: float = 1.0,
    delta_unit: str = "f",
    max_difference: float = 0.02,
    offset: float = 0.0,
    json_path: str | Path | None = None,
    plot_dir: str | Path | None = None,
    plot_prefix: str = "",
    gt_name: str = "ground truth",
    est_name: str = "estimate",
) -> EvaluationReport:
    """ATE and RPE of ``est`` against ``gt``; optional JSON summary and PNG plots.

    RPE uses the same association; with ``align='sim3'`` the estimate's relative
    translations are multiplied by the ATE scale. If no RPE pair fits (e.g. ``delta`` longer
    than the overlap) the report carries ``rpe=None`` and ``rpe_note`` instead of failing.
    Raises InputError when no timestamps associate, and for the cases :func:`ate` rejects;
    ``delta`` is checked first, before any work.
    """
    check_delta(delta, delta_unit)
    a = ate(gt, est, max_difference=max_difference, offset=offset, align=align)
    r: RpeResult | None = None
    note = None
    try:
        r = rpe(gt, est, delta=delta, delta_unit=delta_unit, max_difference=max_difference,
                offset=offset, scale=a.scale)
    except InputError as e:
        if not str(e).startswith("no RPE pairs"):
            raise
        note = str(e)
    settings = {"align": align, "delta": float(delta), "delta_unit": delta_unit,
                "max_difference": float(max_difference), "offset": float(offset)}
    from rgbdslam.evaluation.kitti import kitti_metric

    rep = EvaluationReport(ate=a, rpe=r, settings=settings, gt_name=gt_name, est_name=est_name, rpe_note=note,
                           kitti=kitti_metric(gt, est, max_difference, offset))
    if plot_dir is not None:
        rep.plots = write_plots(rep, plot_dir, plot_prefix)
    if json_path is not None:
        _write(json_path, lambda p: atomic_write_text(p, json.dumps(rep.to_dict(), indent=2) + "\n"))
        rep.json_path = str(json_path)
    return rep


def evaluate_files(
    gt_path: str | Path,
    est_path: str | Path,
    align: str = "se3",
    delta: float = 1.0,
    delta_unit: str = "f",
    max_difference: float = 0.02,
    offset: float = 0.0,
    json_path: str | Path | None = None,
    plot_dir: str | Path | None = None,
    plot_prefix: str = "",
) -> EvaluationReport:
    """Read two TUM trajectory files and evaluate ``est_path`` against ``gt_path``."""
    gt = _read(gt_path)
    est = _read(est_path)
    try:
        return evaluate_trajectories(
            gt, est, align=align, delta=delta, delta_unit=delta_unit, max_difference=max_difference,
            offset=offset, json_path=json_path, plot_dir=plot_dir, plot_prefix=plot_prefix,
            gt_name=str(gt_path), est_name=str(est_path),
        )
    except PairingError as e:  # about the two files together: name both
        raise InputError(f"{gt_path} and {est_path}: {e}") from None


def _read(path: str | Path) -> Trajectory:
    try:
        return read_tum(path)
    except (OSError, UnicodeDecodeError) as e:
        reason = e.strerror if isinstance(e, OSError) and e.strerror else e.__class__.__name__
        raise InputError(f"cannot read trajectory file {path} ({reason}); pass a readable TUM text file") from None


def evaluate_and_print(
    gt_path: str | Path,
    est_path: str | Path,
    plot_dir: str | Path | None = None,
    plots: bool = True,
    console: Console | None = None,
    **options: Any,
) -> EvaluationReport:
    """``rgbdslam evaluate``: evaluate, print the table and list the written files.

    ``options`` are passed to :func:`evaluate_files` (align, delta, delta_unit,
    max_difference, offset, json_path).

    Plots (``ate_topview.png``, ``ate_over_time.png``, ``rpe_over_time.png``) are written only
    into ``plot_dir``, when it is given (as evo writes plots only when asked).
    """
    console = console or Console()
    rep = evaluate_files(gt_path, est_path, plot_dir=plot_dir if plots else None, **options)
    _print_names(console, [("estimate", est_path), ("ground truth", gt_path)])
    console.print(format_table(rep))
    for p in rep.plots + ([rep.json_path] if rep.json_path else []):
        console.print(f"wrote {escape(p)}")
    return rep


def compare_and_print(
    gt_path: str | Path,
    est_paths: list[str | Path],
    plot_dir: str | Path | None = None,
    plots: bool = True,
    json_path: str | Path | None = None,
    console: Console | None = None,
    **options: Any,
) -> list[EvaluationReport]:
    """``rgbdslam evaluate GT EST EST ...``: every estimate against the same ground truth with the
    same settings; prints one comparison table (best ATE RMSE in bold).

    Plots, only when ``plot_dir`` is given: each estimate's own plots prefixed with its short
    name (``runA_trajectory_ate_topview.png``) and ``comparison_topview.png`` with all estimates.
    ``json_path`` gets ``{"ground_truth", "estimates": [report, ...]}``. ``options`` as for
    :func:`evaluate_files` (align, delta, ...).
    """
    console = console or Console()
    seen: set[str] = set()
    for p in est_paths:
        if str(p) in seen:
            raise InputError(f"estimate file {p} is given twice; pass each EST once")
        seen.add(str(p))
    reports = []
    names = _short_names([str(p) for p in est_paths])
    for est in est_paths:  # every estimate first: one that fails stops the command before any file is written
        reports.append(evaluate_files(gt_path, est, **options))
    plots = plots and plot_dir is not None
    _print_names(console, [("ground truth", gt_path)])
    console.print(format_comparison(reports))
    for est, name, rep in zip(est_paths, names, reports):
        if not plots:
            break
        # one folder for all: prefixes that tell runA/trajectory.tum from runB/trajectory.tum
        rep.plots = write_plots(rep, Path(plot_dir), f"{Path(name).with_suffix('').as_posix().replace('/', '_')}_")
    written = [p for r in reports for p in r.plots]
    if plots:
        path = Path(plot_dir) / "comparison_topview.png"
        from rgbdslam.evaluation.plots import plot_trajectories_topview  # matplotlib: only when drawing

        _write(path, lambda p: plot_trajectories_topview(
            reports[0].ate.gt, {n: r.ate.aligned for n, r in zip(names, reports)}, p))
        written.append(str(path))
    if json_path is not None:
        doc = {"ground_truth": str(gt_path), "estimates": [r.to_dict() for r in reports]}
        _write(json_path, lambda p: atomic_write_text(p, json.dumps(doc, indent=2) + "\n"))
        written.append(str(json_path))
    for p in written:
        console.print(f"wrote {escape(p)}")
    return reports


def _print_names(console: Console, named: list[tuple[str, str | Path]]) -> None:
    """One line per file above a table (a table title would break a long path across lines)."""
    for what, path in named:
        console.print(f"{what}: {escape(str(path))}", soft_wrap=True, highlight=False)


def _short_names(paths: list[str]) -> list[str]:
    """The shortest path suffixes (file, parent/file, ...) that tell the estimates apart."""
    parts = [Path(p).parts for p in paths]
    for k in range(1, max(len(x) for x in parts) + 1):
        names = [str(Path(*x[-k:])) for x in parts]
        if len(set(names)) == len(names):
            return names
    return [str(p) for p in paths]


def format_comparison(reports: list[EvaluationReport]) -> Table:
    """One row per estimate: ATE RMSE and max, RPE RMSE (translation, rotation), poses (the rest of the
    statistics are in each report / the JSON)."""
    names = _short_names([r.est_name for r in reports])
    best = min(range(len(reports)), key=lambda k: reports[k].ate.rmse)
    first = reports[0]
    table = Table(title=f"{len(reports)} estimates vs the ground truth", title_justify="left")
    table.add_column("estimate", overflow="fold", min_width=min(36, max(len(n) for n in names)))
    for col in ("ATE\nrmse", "ATE\nmax", "RPE t\nrmse", "RPE r\nrmse", "poses"):
        table.add_column(col, justify="right", no_wrap=True)
    for k, (name, rep) in enumerate(zip(names, reports)):
        a, r = rep.ate, rep.rpe
        cells = [f"{a.rmse:.4f}", f"{a.max:.4f}",
                 "-" if r is None else f"{r.trans.rmse:.4f}", "-" if r is None else f"{r.rot.rmse:.3f}",
                 str(a.n_pairs)]
        style = "bold" if k == best and len(reports) > 1 else None
        table.add_row(escape(name), *cells, style=style)
    s = first.settings
    table.caption = (f"ATE and RPE translation in m, RPE rotation in deg; alignment {s['align']}; association max difference {s['max_difference']:g} s, offset "
                     f"{s['offset']:g} s; RPE delta {s['delta']:g} {s['delta_unit']}; bold: lowest ATE RMSE; "
                     "all statistics in --json")
    return table


def write_plots(rep: EvaluationReport, plot_dir: str | Path, prefix: str = "") -> list[str]:
    """Write the top view, the ATE-over-time and (if present) the RPE plot; return their paths."""
    from rgbdslam.evaluation.plots import plot_error_over_time, plot_rpe, plot_trajectory_topview  # matplotlib

    plot_dir = Path(plot_dir)
    jobs = [
        (f"{prefix}ate_topview.png", lambda p: plot_trajectory_topview(rep.ate.gt, rep.ate.aligned, p)),
        (f"{prefix}ate_over_time.png", lambda p: plot_error_over_time(rep.ate, p)),
    ]
    if rep.rpe is not None:
        jobs.append((f"{prefix}rpe_over_time.png", lambda p: plot_rpe(rep.rpe, p)))
    out = []
    for name, draw in jobs:
        _write(plot_dir / name, draw)
        out.append(str(plot_dir / name))
    return out


def _write(path: str | Path, writer) -> None:
    try:
        writer(path)
    except OSError as e:
        where = f"{e.filename}: " if e.filename and str(e.filename) != str(path) else ""
        raise RgbdslamError(
            f"cannot write {path} ({where}{e.strerror or e}); choose a writable place for it (evaluate: "
            f"--plot-dir, --json; run: --out, or --set output.plots=false)"
        ) from None


def format_table(report: EvaluationReport) -> Table:
    """A rich table: ATE and RPE statistics, pair counts and the settings in the caption."""
    a, r = report.ate, report.rpe
    table = Table(title="estimate vs ground truth", title_justify="left")
    table.add_column("metric")
    for col in ("rmse", "mean", "median", "std", "min", "max"):
        table.add_column(col, justify="right")
    table.add_column("pairs", justify="right")

    def row(name: str, s: ErrorStats, n: int, fmt: str) -> None:
        vals = [getattr(s, k) for k in ("rmse", "mean", "median", "std", "min", "max")]
        table.add_row(name, *[format(v, fmt) for v in vals], str(n))

    row("ATE (m)", a, a.n_pairs, ".4f")
    if r is not None:
        row("RPE trans (m)", r.trans, r.n_pairs, ".4f")
        row("RPE rot (deg)", r.rot, r.n_pairs, ".3f")
    k = report.kitti
    if k is not None:
        table.add_row("KITTI t_err (%)", f"{k.t_err_pct:.3f}", *[""] * 5, str(k.n_segments))
        table.add_row("KITTI r_err (deg/m)", f"{k.r_err_deg_per_m:.5f}", *[""] * 5, str(k.n_segments))
        table.add_row("end drift (%)", f"{k.end_drift_pct:.3f}", *[""] * 5, f"{k.path_length:.1f} m")
    caption = f"alignment {a.align}"
    if a.align == "sim3":
        caption += f" (scale {a.scale:.4f})"
    caption += (f"; association max difference {report.settings['max_difference']:g} s, "
                f"offset {report.settings['offset']:g} s")
    if r is not None:
        caption += f"; RPE delta {r.delta:g} {r.delta_unit}"
    if r is None and report.rpe_note:
        caption += escape(f"; RPE not computed: {report.rpe_note}")
    if k is not None:
        caption += (f"; KITTI metric: mean over segments of {', '.join(f'{L:g}' for L in k.lengths)} m every "
                    f"{k.step} frame(s), no alignment" + escape(f" ({k.note})" if k.note else ""))
    table.caption = caption
    return table
