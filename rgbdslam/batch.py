"""Several sequences with one config: ``rgbdslam run A B C --out DIR``.

Each sequence is an ordinary run (:func:`rgbdslam.pipeline.run_sequence`) into ``DIR/<name>``;
this module adds the folder names, the error handling between sequences and the results table
(``DIR/summary.md`` and ``.csv``, docs/formats.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rgbdslam.config import Config
from rgbdslam.errors import RgbdslamError
from rgbdslam.io.atomic import atomic_write_text, make_dirs
from rgbdslam.pipeline import run_sequence
from rgbdslam.io.manifest import record_tables, tables_ready


def _run_dirs(sequences: list[Path], out_root: Path) -> list[Path]:
    """One output folder per sequence, named after it; a name already taken (also one that only
    differs in case, for case-insensitive file systems) gets _2, _3, ... until it is free."""
    used: set[str] = set()
    out = []
    for s in sequences:
        name = Path(s).resolve().name or "sequence"
        cand, k = name, 2
        while cand.lower() in used:
            cand, k = f"{name}_{k}", k + 1
        used.add(cand.lower())
        out.append(out_root / cand)
    return out


def run_sequences(sequences: list[str | Path], out_root: str | Path, cfg: Config | list[Config], progress: bool = True,
                  engine: str = "local", workers: int = 1, address: str | None = None,
                  notes: list[str | None] | None = None) -> list[dict[str, Any]]:
    """Run SLAM on several sequences, each into ``out_root/<sequence name>``, with one config (or
    a list: one per sequence, as the command line gives each its own preset; ``notes``: a line for
    each that its run prints when it starts, the preset chosen and why).

    A sequence that fails with an input error (missing folder, no trackable frame, ...) is
    reported and the others still run. Returns one row per sequence (``status`` "ok" or the
    error) and writes them to ``out_root/summary.csv`` and ``summary.md`` after every sequence,
    so an interrupted batch keeps the rows it finished. Ctrl-C stops the batch.

    With one local worker the sequences run here one after the other (with progress bars);
    otherwise they are jobs of the engine (:mod:`rgbdslam.engine`), quiet, a line per finished one.
    """
    from rgbdslam.engine import build_engine
    from rgbdslam.ui import console

    out_root = Path(out_root)
    tables_ready(out_root, SUMMARY_FILES)
    make_dirs(out_root)
    dirs = _run_dirs([Path(s) for s in sequences], out_root)
    rows: list[dict[str, Any] | None] = [None] * len(sequences)
    serial = engine == "local" and workers == 1
    cfgs = cfg if isinstance(cfg, list) else [cfg] * len(sequences)
    notes = notes or [None] * len(sequences)
    jobs = [(str(seq), str(d), c, progress and serial, not serial, f"{k + 1}/{len(sequences)}", note)
            for k, (seq, d, c, note) in enumerate(zip(sequences, dirs, cfgs, notes))]
    with build_engine(engine, workers, address) as eng:
        if not serial:
            console.print(f"{len(sequences)} sequences on {eng.describe()}")
        for k, row in eng.map(run_one, jobs):
            rows[k] = row
            if not serial:
                console.print(f"done {Path(row['sequence']).name}: {row['status'] if row['status'] != 'ok' else _brief(row)}")
            _write_batch_summary([r for r in rows if r is not None], out_root)
    return [r for r in rows if r is not None]


def _brief(row: dict[str, Any]) -> str:
    ate = row.get("ate_rmse")
    return f"{row['tracked']}/{row['frames']} tracked" + (f", ATE {ate:.4f} m" if ate is not None else "")


def run_one(seq: str, out_dir: str, cfg: Config, progress: bool, quiet: bool, position: str,
            note: str | None = None) -> dict[str, Any]:
    """One sequence of the batch (in this process or an engine's worker) -> its row."""
    import copy

    from rich.markup import escape

    from rgbdslam.ui import console

    quiet_before = console.quiet
    console.quiet = quiet or quiet_before
    row: dict[str, Any] = {"sequence": str(seq), "out": str(out_dir)}
    try:
        console.rule(f"[bold]{position}[/] {seq}")
        s = run_sequence(seq, out_dir, copy.deepcopy(cfg), progress=progress, announce=note)
    except RgbdslamError as e:  # one bad sequence does not stop the batch
        console.print(f"[red]error:[/] {escape(str(e))}")
        row["status"] = str(e)
        return row
    finally:
        console.quiet = quiet_before
    ate = ((s.get("evaluation") or {}).get("ate") or {}).get("rmse")
    row.update(status="ok", frames=s["frames"], tracked=s["tracked"], lost=s["lost"],
               restarts=len(s["restarts"]), keyframes=len(s["keyframes"]), loops=len(s["loops"]),
               ate_rmse=ate, fps=s["fps"])
    return row


SUMMARY_FILES = ("summary.csv", "summary.md")  # what a batch writes into --out beside the run folders
BATCH_COLUMNS = ("sequence", "status", "frames", "tracked", "lost", "restarts", "keyframes", "loops",
                 "ate_rmse", "fps", "out")


def format_batch_table(rows: list[dict[str, Any]]) -> str:
    """The rows of :func:`run_sequences` as a markdown table (ATE in metres)."""

    def cell(r, c):
        v = r.get(c)
        if v is None:
            return "-"
        if c == "sequence":
            return Path(v).name
        if c == "ate_rmse":
            return f"{v:.4f}"
        if c == "fps":
            return f"{v:.1f}"
        return str(v).replace("|", "/")

    cols = [c for c in BATCH_COLUMNS if c != "out"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(cell(r, c) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def _write_batch_summary(rows: list[dict[str, Any]], out_root: Path) -> None:
    import csv
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(BATCH_COLUMNS), extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else r[c]) for c in BATCH_COLUMNS})
    atomic_write_text(out_root / "summary.csv", buf.getvalue())
    atomic_write_text(out_root / "summary.md", format_batch_table(rows) + "\n")
    record_tables(out_root, SUMMARY_FILES)
