"""Long sequences: does the whole pipeline stay faster than real time, and its memory flat, as the
map grows?

Usage::

    .venv/bin/python scripts/bench_long.py [--frames 1500] [--motion loop] [--seed 0] [--window 300]
                                           [--work DIR] [--write-docs]

A synthetic sequence with Kinect-like noise and exact ground truth
(``rgbdslam.datasets.synthetic.generate_sequence``; rendered once into ``--work``) is run with the
default configuration (map fusion off: it runs after tracking and is measured in "Mapping").
A thin wrapper around the sequence notes, in the reader thread, when each frame is read and the
process's resident memory every ``--window`` frames; the reader runs at most
``dataset.prefetch`` frames ahead, so the read times follow the tracking. Reported per window of
frames: frames/s and memory, plus the run's ATE, loops, keyframes and loop-closure cost.
``--write-docs`` replaces the "## Long sequences" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.datasets.base import Sequence  # noqa: E402


def rss_mb() -> float:
    """Resident memory of this process now (Linux /proc; NaN elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


class TimedSequence:
    """A sequence that records when each frame is read (and the memory every ``every`` frames)."""

    prefetched = Sequence.prefetched  # reads through this wrapper's load, in the reader thread

    def __init__(self, seq, every: int):
        self._seq, self._every = seq, every
        self.read_at: dict[int, float] = {}
        self.rss: dict[int, float] = {}

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def __len__(self):
        return len(self._seq)

    def load(self, i):
        self.read_at[i] = time.perf_counter()
        if i % self._every == 0:
            self.rss[i] = rss_mb()
        return self._seq.load(i)


def run(frames: int, motion: str, seed: int, window: int, work: Path, sets: list[str] | None = None) -> dict:
    import rgbdslam.pipeline as pipeline
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic import generate_sequence

    seq_dir = work / f"{motion}_{frames}_seed{seed}"
    if not (seq_dir / "synthetic.yaml").is_file():
        print(f"rendering {frames} frames into {seq_dir}", flush=True)
        generate_sequence(seq_dir, frames=frames, motion=motion, noise=True, seed=seed, progress=False)
    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *(sets or [])])
    timed = TimedSequence(open_sequence(seq_dir, cfg.dataset), window)
    pipeline.open_sequence = lambda *a, **k: timed  # run_sequence opens the sequence through this name
    s = pipeline.run_sequence(seq_dir, work / ("run" if not sets else "run_" + "_".join(sets).replace("/", "_")), cfg,
                              progress=False)
    t = np.array([timed.read_at[i] for i in range(frames)])
    rows = []
    for a in range(0, frames, window):
        b = min(a + window, frames) - 1
        dt = t[b] - t[a]
        rows.append({"frames": f"{a}–{b}", "fps": (b - a) / dt if dt > 0 else float("nan"),
                     "rss": timed.rss.get(a, float("nan"))})
    lc = s["loop_closure"]
    return {"frames": frames, "motion": motion, "seed": seed, "ate": s["evaluation"]["ate"]["rmse"],
            "fps": s["fps"], "keyframes": len(s["keyframes"]), "loops": len(s["loops"]),
            "queries": lc["n_queries"], "verified": lc["n_verified"], "lc_ms": lc["time_per_query_ms"],
            "windows": rows, "sets": sets or [], "landmarks": s.get("landmarks") or {}}


def markdown(r: dict, command: str, reference: str, section: str = "## Long sequences") -> str:
    L = [section, "",
         f"Command: `{command}`  ",
         f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
         f"{time.strftime('%Y-%m-%d')}; shared with other jobs, so frames/s are noisy.  ",
         f"Speed of the machine: {reference}", "",
         f"A synthetic `{r['motion']}` sequence of {r['frames']} frames (seed {r['seed']}, Kinect-like noise, "
         "exact ground truth), " + (", ".join(f"`{x}`" for x in r["sets"]) if r["sets"] else "default configuration")
         + ", map fusion off. Whole run: "
         f"ATE RMSE {r['ate']:.4f} m, {r['fps']:.1f} frames/s, {r['keyframes']} keyframes, {r['loops']} loops; "
         f"{r['queries']} loop searches verified {r['verified']} candidates at {r['lc_ms']:.1f} ms per search. "
         "Per window of frames (frames/s from the times the reader thread read them; memory = the "
         "process's resident size when the window's first frame was read):", "",
         "| frames | frames/s | resident MB |", "|---|---|---|"]
    for w in r["windows"]:
        L.append(f"| {w['frames']} | {w['fps']:.1f} | {w['rss']:.0f} |")
    if r["landmarks"]:
        lm = r["landmarks"]
        L += ["", f"Landmark map at the end: {lm['size']} live landmarks ({lm['made']} made, {lm['culled']} culled), "
                  f"store trees {lm['store_trees']}."]
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--motion", default="loop")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--window", type=int, default=300)
    ap.add_argument("--work", default=None, help="folder for the sequence and the run (default: temporary)")
    ap.add_argument("--set", action="append", default=[], help="config override SECTION.KEY=VALUE (repeatable)")
    ap.add_argument("--section", default="## Long sequences", help="heading of the docs section")
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args(argv)
    command = "python scripts/bench_long.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_long_"))
    work.mkdir(parents=True, exist_ok=True)
    from _docs import publish, reference_timing

    reference = reference_timing()
    r = run(a.frames, a.motion, a.seed, a.window, work, a.set)
    return publish(markdown(r, command, reference, a.section), a.write_docs)


if __name__ == "__main__":
    raise SystemExit(main())
