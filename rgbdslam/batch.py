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


def run_sequences(sequences: list[str | Path], out_root: str | Path, cfg: Config,
                  progress: bool = True) -> list[dict[str, Any]]:
    """Run SLAM on several sequences, each into ``out_root/<sequence name>``, with one config.

    A sequence that fails with an input error (missing folder, no trackable frame, ...) is
    reported and the others still run. Returns one row per sequence (``status`` "ok" or the
    error) and writes them to ``out_root/summary.csv`` and ``summary.md`` after every sequence,
    so an interrupted batch keeps the rows it finished. Ctrl-C stops the batch.
    """
    import copy

    from rich.markup import escape

    from rgbdslam.ui import console

    out_root = Path(out_root)
    make_dirs(out_root)
    rows: list[dict[str, Any]] = []
    for k, (seq, out_dir) in enumerate(zip(sequences, _run_dirs([Path(s) for s in sequences], out_root))):
        console.rule(f"[bold]{k + 1}/{len(sequences)}[/] {seq}")
        row: dict[str, Any] = {"sequence": str(seq), "out": str(out_dir)}
        try:
            s = run_sequence(seq, out_dir, copy.deepcopy(cfg), progress=progress)
        except RgbdslamError as e:  # one bad sequence does not stop the batch
            console.print(f"[red]error:[/] {escape(str(e))}")
            row["status"] = str(e)
        else:
            ate = ((s.get("evaluation") or {}).get("ate") or {}).get("rmse")
            row.update(status="ok", frames=s["frames"], tracked=s["tracked"], lost=s["lost"],
                       restarts=len(s["restarts"]), keyframes=len(s["keyframes"]), loops=len(s["loops"]),
                       ate_rmse=ate, fps=s["fps"])
        rows.append(row)
        _write_batch_summary(rows, out_root)
    return rows


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
