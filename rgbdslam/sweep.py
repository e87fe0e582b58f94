"""Parameter sweeps: ``rgbdslam sweep SEQ... --grid section.key=v1,v2 ... --out DIR``.

Every combination of the grid values (the cells) runs on every sequence, each as an ordinary
run (:func:`rgbdslam.pipeline.run_sequence`) into ``DIR/cells/<sequence>/<k=v,...>``; the jobs go
to an engine (:mod:`rgbdslam.engine`: in this process, a local process pool or a Ray cluster).
One results table gathers them: ``DIR/results.md`` and ``results.csv`` (ATE, RPE and rate per
cell) and ``results.png`` (ATE per cell and sequence), rewritten atomically after every finished
cell, so an interrupted sweep keeps what it finished.

Resuming: a finished cell writes ``cell.json`` (its row and its settings) last; a re-run keeps
every cell whose ``cell.json`` has the same sequence and configuration and runs only the others.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rgbdslam.config import Config, load_config
from rgbdslam.errors import ConfigError, InputError, RgbdslamError
from rgbdslam.io.atomic import atomic_path, atomic_write_text, make_dirs
from rgbdslam.io.manifest import record_tables, tables_ready

CELL_FILE = "cell.json"
MAX_CELLS = 1000  # sequences x settings: a sweep beyond this is refused before any cell is planned
TABLES = ("results.csv", "results.md", "results.png")  # what a sweep writes into --out beside cells/
METRICS = ("status", "frames", "tracked", "keyframes", "loops", "ate_rmse", "rpe_trans_rmse", "rpe_rot_rmse",
           "tracking_fps", "cell_fps")
TIMING_COLUMNS = ("tracking_fps", "cell_fps", "cell_s")  # differ between runs; everything else must not


@dataclass
class Cell:
    sequence: Path
    assignment: tuple[tuple[str, str], ...]  # (section.key, value text) in grid order
    out_dir: Path
    config: Config

    @property
    def label(self) -> str:
        return ",".join(f"{k}={v}" for k, v in self.assignment) or "default"

    def settings(self) -> dict[str, Any]:
        """What makes a finished cell reusable: the same sequence and the same configuration."""
        return {"sequence": str(self.sequence.resolve()), "grid": dict(self.assignment), "config": self.config.to_dict()}


def parse_grid(items: list[str] | tuple[str, ...]) -> list[tuple[str, list[str]]]:
    """``["registration.mp=2,4,6", "loop.enabled=true,false"]`` -> ``[(key, [values]), ...]``."""
    grid: list[tuple[str, list[str]]] = []
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or "." not in key or not raw.strip():
            raise ConfigError(f"--grid '{item}' must look like section.key=value1,value2,...")
        values = [v.strip() for v in raw.split(",")]
        if any(v == "" for v in values):
            raise ConfigError(f"--grid '{item}' has an empty value; separate the values by single commas")
        if len(set(values)) < len(values):
            raise ConfigError(f"--grid '{item}' lists a value twice; list each once")
        if key in (k for k, _ in grid):
            raise ConfigError(f"--grid {key} is given twice; give all its values in one --grid")
        grid.append((key, values))
    return grid


def _safe(text: str) -> str:
    return "".join(c if c.isalnum() or c in "=.,-_+" else "_" for c in text)


def cell_names(labels: list[str]) -> list[str]:
    """A folder name per cell label: the label with every character a folder name should not
    hold replaced by ``_``; labels whose names would then be equal (``a/b.txt`` and ``a_b.txt``,
    also equal but for case) get ``~`` and 8 hex digits of the label's SHA-1 each, so no two
    cells share a folder, whatever the order of the grid."""
    import hashlib

    safe = [_safe(label) or "default" for label in labels]
    count: dict[str, int] = {}
    for name in safe:
        count[name.lower()] = count.get(name.lower(), 0) + 1
    return [name if count[name.lower()] == 1 else f"{name}~{hashlib.sha1(label.encode()).hexdigest()[:8]}"
            for name, label in zip(safe, labels)]


def check_size(n_sequences: int, grid: list[tuple[str, list[str]]]) -> None:
    """A ConfigError when the sweep would have more than :data:`MAX_CELLS` cells."""
    n = n_sequences * math.prod(len(values) for _, values in grid)
    if n > MAX_CELLS:
        raise ConfigError(f"the sweep would run {n} cells ({n_sequences} sequence(s) x "
                          f"{' x '.join(str(len(v)) for _, v in grid)} values); at most {MAX_CELLS} are allowed: "
                          f"split it into several sweeps")


def plan_cells(sequences: list[Path], grid: list[tuple[str, list[str]]], out_root: Path,
               config_path: str | None = None, overrides: tuple[str, ...] = (), mapping: bool = False) -> list[Cell]:
    """Every (sequence, grid combination), its config checked now (a bad value fails before any run).
    The map is not fused unless ``mapping`` (a sweep compares trajectories); plots are not drawn."""
    from rgbdslam.batch import _run_dirs

    check_size(len(sequences), grid)
    combos = list(itertools.product(*[[(k, v) for v in vals] for k, vals in grid])) or [()]
    names = cell_names([",".join(f"{k}={v}" for k, v in combo) for combo in combos])
    cells = []
    for seq, seq_dir in zip(sequences, _run_dirs(sequences, out_root / "cells")):
        for combo, name in zip(combos, names):
            cfg = load_config(config_path, tuple(overrides) + tuple(f"{k}={v}" for k, v in combo))
            cfg.mapping.enabled = cfg.mapping.enabled and mapping
            cfg.output.plots = False
            cfg.output.rerun = False
            cfg.output.rerun_save = None
            cells.append(Cell(Path(seq), tuple(combo), seq_dir / name, cfg))
    return cells


def run_cell(sequence: str, out_dir: str, cfg: Config, assignment: tuple) -> dict[str, Any]:
    """One cell in a worker: the run (quiet) and its row; an input error is the row's status."""
    from rgbdslam.pipeline import run_sequence
    from rgbdslam.ui import console

    t0 = time.perf_counter()
    quiet, console.quiet = console.quiet, True
    row: dict[str, Any] = {"sequence": Path(sequence).name, **dict(assignment)}
    try:
        s = run_sequence(sequence, out_dir, cfg, progress=False)
    except RgbdslamError as e:
        row["status"] = f"error: {e}"
        return row
    finally:
        console.quiet = quiet
    ev = s.get("evaluation") or {}
    rpe = ev.get("rpe") or {}
    row.update(status="ok", frames=s["frames"], tracked=s["tracked"], keyframes=len(s["keyframes"]),
               loops=len(s["loops"]), ate_rmse=(ev.get("ate") or {}).get("rmse"),
               rpe_trans_rmse=(rpe.get("trans") or {}).get("rmse"), rpe_rot_rmse=(rpe.get("rot") or {}).get("rmse"),
               tracking_fps=s["fps"])
    cell_s = time.perf_counter() - t0
    row.update(cell_s=cell_s, cell_fps=s["frames"] / cell_s if cell_s > 0 else None)
    return row


def _finished(cell: Cell) -> dict[str, Any] | None:
    """The row of an earlier run of this very cell, if it finished."""
    try:
        info = json.loads((cell.out_dir / CELL_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # unreadable, not JSON, too deep: run the cell again
        return None
    if not isinstance(info, dict) or info.get("settings") != json.loads(json.dumps(cell.settings())):
        return None
    row = info.get("row")
    return row if isinstance(row, dict) and row.get("status") == "ok" else None


def run_sweep(sequences: list[str | Path], grid_items, out_root: str | Path, config_path: str | None = None,
              overrides: tuple[str, ...] = (), engine: str = "local", workers: int = 1, address: str | None = None,
              mapping: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run the sweep (see the module doc); returns ``{"rows", "columns", "kept", "ran", "wall_s", "engine"}``."""
    from rich.markup import escape

    from rgbdslam.engine import build_engine
    from rgbdslam.ui import console

    if not sequences:
        raise InputError("give at least one SEQUENCE to sweep over")
    from rgbdslam.datasets import check_sequence_path

    for s in sequences:  # folders and recordings, as `run` takes them
        check_sequence_path(s)
    grid = parse_grid(grid_items)
    out_root = Path(out_root)
    cells = plan_cells([Path(s) for s in sequences], grid, out_root, config_path, tuple(overrides), mapping)
    keys = [k for k, _ in grid]
    columns = ["sequence", *keys, *METRICS]
    rows: list[dict[str, Any] | None] = [None] * len(cells)
    for k, c in enumerate(cells):
        rows[k] = _finished(c)
    todo = [k for k, r in enumerate(rows) if r is None]
    kept = len(cells) - len(todo)
    tables_ready(out_root, TABLES)
    make_dirs(out_root)
    console.print(f"sweep: {len(cells)} cells ({len(sequences)} sequence(s) x {len(cells) // len(sequences)} "
                  f"setting(s)); {kept} kept from an earlier run, {len(todo)} to run")
    t0 = time.perf_counter()
    eng_name = "none"
    if todo:
        with build_engine(engine, workers, address) as eng:
            eng_name = eng.describe()
            console.print(f"engine: {eng_name}")
            jobs = [(str(cells[k].sequence), str(cells[k].out_dir), cells[k].config, cells[k].assignment)
                    for k in todo]
            for n, (j, row) in enumerate(eng.map(run_cell, jobs), 1):
                cell = cells[todo[j]]
                rows[todo[j]] = row
                if row.get("status") == "ok":
                    atomic_write_text(cell.out_dir / CELL_FILE,
                                      json.dumps({"settings": cell.settings(), "row": row}, indent=1))
                ate = row.get("ate_rmse")
                console.print(f"[{n}/{len(todo)}] {escape(Path(cell.sequence).name)} {escape(cell.label)}: "
                              + (f"ATE {ate:.4f} m, " if ate is not None else "")
                              + (f"{row['cell_fps']:.1f} frames/s" if row.get("cell_fps") else escape(row["status"])))
                write_table([r for r in rows if r is not None], columns, out_root)
    wall = time.perf_counter() - t0
    done = [r for r in rows if r is not None]
    write_table(done, columns, out_root, plot=True)
    return {"rows": done, "columns": columns, "kept": kept, "ran": len(todo), "wall_s": wall, "engine": eng_name}


def _cell_text(v: Any, col: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.1f}" if col.endswith("fps") else f"{v:.5f}" if col != "rpe_rot_rmse" else f"{v:.4f}"
    return str(v).replace("|", "/")


def format_table(rows: list[dict[str, Any]], columns: list[str]) -> str:
    """Markdown table: ATE/RPE translation in metres, RPE rotation in degrees, rates in frames/s."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell_text(r.get(c), c) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def csv_text(rows: list[dict[str, Any]], columns: list[str]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else r[c]) for c in columns})
    return buf.getvalue()


def write_table(rows: list[dict[str, Any]], columns: list[str], out_root: Path, plot: bool = False) -> None:
    atomic_write_text(out_root / "results.csv", csv_text(rows, columns))
    atomic_write_text(out_root / "results.md", format_table(rows, columns) + "\n")
    if plot and rows:
        plot_results(rows, columns, out_root / "results.png")
    record_tables(out_root, TABLES)


def plot_results(rows: list[dict[str, Any]], columns: list[str], path: Path) -> None:
    """ATE RMSE per setting (x) with one bar per sequence; a failed cell has no bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    keys = [c for c in columns if c not in METRICS and c != "sequence"]
    label = lambda r: "\n".join(f"{k}={r.get(k)}" for k in keys) or "default"  # noqa: E731
    settings = list(dict.fromkeys(label(r) for r in rows))
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    width = 0.8 / max(len(seqs), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(settings) + 2), 4.5))
    x = np.arange(len(settings))
    for s_i, seq in enumerate(seqs):
        vals = [next((r.get("ate_rmse") for r in rows if r["sequence"] == seq and label(r) == st), None)
                for st in settings]
        ax.bar(x + (s_i - (len(seqs) - 1) / 2) * width, [np.nan if v is None else v for v in vals], width, label=seq)
    ax.set_xticks(x, settings, fontsize=7)
    ax.set_ylabel("ATE RMSE [m]")
    ax.set_title("sweep: ATE per setting and sequence")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
