"""Long sequences: does the whole pipeline stay faster than real time, and its memory flat, as the
map grows?

Usage::

    python -m benchmarks.long [--frames 1500] [--motion loop] [--seed 0] [--window 300]
                                           [--size W H] [--set KEY=VALUE ...] [--work DIR] [--json FILE]
                                           [--write-docs]
    python -m benchmarks.long --report A.json B.json ... [--section TITLE] [--write-docs]

A synthetic sequence with Kinect-like noise and exact ground truth
(``rgbdslam.datasets.synthetic.generate_sequence``; rendered once into ``--work``) is run with the
default configuration (map fusion off: it runs after tracking and is measured in "Mapping").
A thin wrapper around the sequence notes, in the reader thread, when each frame is read and the
process's resident memory every ``--window`` frames and at the last frame; the reader runs at
most ``dataset.prefetch`` frames ahead, so the read times follow the tracking. Reported per window
of frames: frames/s and memory, plus the run's ATE, loops, keyframes and loop-closure cost, the
peak resident size and the ratio of the memory at the last frame to that at frame ``--window``
(memory flat within 1.5x from frame 300 to frame 1500).
``--write-docs`` replaces the "## Long sequences" section of docs/benchmarks.md. ``--json`` keeps
a run's numbers; ``--report`` joins several runs (one configuration per process, so that each
process's memory is its own) into one memory table under ``--section``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import sequence_view

from rgbdslam.config import load_config


def rss_mb() -> float:
    """Resident memory of this process now (Linux /proc; NaN elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


class FrameClock:
    """Records when each frame is read (and the memory every ``every`` frames): the ``load`` of
    :func:`benchmarks.common.sequence_view` (``run_sequence``'s reader thread reads through it)."""

    def __init__(self, every: int):
        self.every = every
        self.read_at: dict[int, float] = {}
        self.rss: dict[int, float] = {}

    def __call__(self, seq, i: int):
        self.read_at[i] = time.perf_counter()
        if i % self.every == 0 or i == len(seq) - 1:
            self.rss[i] = rss_mb()
        return seq.load(i)


def run(frames: int, motion: str, seed: int, window: int, work: Path, sets: list[str] | None = None,
        size: tuple[int, int] = (640, 480)) -> dict:
    import resource

    from rgbdslam.datasets import open_sequence
    from rgbdslam.pipeline import run_sequence
    from rgbdslam.datasets.synthetic import generate_sequence

    seq_dir = work / (f"{motion}_{frames}_seed{seed}" + ("" if tuple(size) == (640, 480) else f"_{size[0]}x{size[1]}"))
    if not (seq_dir / "synthetic.yaml").is_file():
        print(f"rendering {frames} frames into {seq_dir}", flush=True)
        generate_sequence(seq_dir, frames=frames, motion=motion, noise=True, seed=seed, progress=False,
                          width=size[0], height=size[1])
    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *(sets or [])])
    timed = FrameClock(window)
    s = run_sequence(sequence_view(open_sequence(seq_dir, cfg.dataset), timed), work / ("run" if not sets else "run_" + "_".join(sets).replace("/", "_")), cfg,
                     progress=False)
    t = np.array([timed.read_at[i] for i in range(frames)])
    rows = []
    for a in range(0, frames, window):
        b = min(a + window, frames) - 1
        dt = t[b] - t[a]
        rows.append({"frames": f"{a}–{b}", "fps": (b - a) / dt if dt > 0 else float("nan"),
                     "rss": timed.rss.get(a, float("nan"))})
    lc = s["loop_closure"]
    memory = {i: timed.rss[i] for i in sorted(timed.rss)}  # frame read -> resident MB
    return {"frames": frames, "motion": motion, "seed": seed, "size": list(size), "window": window, "ate": s["evaluation"]["ate"]["rmse"],
            "fps": s["fps"], "keyframes": len(s["keyframes"]), "loops": len(s["loops"]),
            "queries": lc["n_queries"], "verified": lc["n_verified"], "lc_ms": lc["time_per_query_ms"],
            "windows": rows, "sets": sets or [], "landmarks": _landmark_summary(s.get("landmarks") or {}),
            "memory": memory, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "flat_ratio": memory.get(frames - 1, float("nan")) / memory.get(window, float("nan"))
            if window in memory else float("nan")}


def _landmark_summary(lm: dict) -> dict:
    return {k: lm[k] for k in ("size", "made", "culled", "store_trees") if k in lm}


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
        L += ["", f"Landmark map at the end: {_landmark_text(r['landmarks'])}."]
    return "\n".join(L) + "\n"


def _landmark_text(lm: dict) -> str:
    return (f"{lm.get('size', '?')} live landmarks ({lm.get('made', '?')} made, {lm.get('culled', '?')} culled), "
            f"store trees {lm.get('store_trees', '?')}")


def memory_markdown(runs: list[dict], section: str) -> str:
    """One table: per configuration, resident memory at the frames sampled, the last over the
    ``window``-th frame's, peak, ATE and frames/s."""
    frames = sorted({int(i) for r in runs for i in r["memory"]})
    first = runs[0]
    L = [section, ""] + [f"Command: `{r['command']}`  " for r in runs]
    L += [f"Machine: {first['machine']}; shared with other engineers' jobs (frames/s are only a rough guide).", "",
          f"A synthetic `{first['motion']}` sequence of {first['frames']} frames, {first['size'][0]}x{first['size'][1]} "
          f"(seed {first['seed']}, Kinect-like noise), map fusion off, one configuration per process. Resident memory "
          "(MB) of the run process when the reader thread read the frame (it reads at most `dataset.prefetch` frames "
          f"ahead of the tracking); last/{first.get('window', 300)} = memory at the last frame over memory at frame "
          f"{first.get('window', 300)} (target <= 1.5); "
          "peak = the process's peak resident size, the final optimisation and evaluation included.", "",
          "| configuration | " + " | ".join(f"frame {i}" for i in frames) + f" | last/{first.get('window', 300)} | peak MB | ATE m | frames/s "
          "| landmarks at the end |",
          "|---|" + "---|" * (len(frames) + 5)]
    for r in runs:
        name = " ".join(f"`{x}`" for x in r["sets"]) or "default"
        mem = {int(k): v for k, v in r["memory"].items()}
        L.append(f"| {name} | " + " | ".join(f"{mem[i]:.0f}" if i in mem else "-" for i in frames)
                 + f" | {r['flat_ratio']:.2f} | {r['peak_mb']:.0f} | {r['ate']:.4f} | {r['fps']:.1f} | "
                 + (_landmark_text(r["landmarks"]) if r["landmarks"] else "-") + " |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--motion", default="loop")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--window", type=int, default=300)
    ap.add_argument("--work", default=None, help="folder for the sequence and the run (default: temporary)")
    ap.add_argument("--set", action="append", default=[], help="config override SECTION.KEY=VALUE (repeatable)")
    ap.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"), help="image size")
    ap.add_argument("--section", default="## Long sequences", help="heading of the docs section")
    ap.add_argument("--json", type=Path, default=None, help="also write the run's numbers here")
    ap.add_argument("--report", type=Path, nargs="+", default=None,
                    help="only build one memory table from earlier --json files (one per configuration)")
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args(argv)
    from benchmarks.common import publish_markdown as publish, reference_timing

    if a.report:
        runs = [json.loads(p.read_text()) for p in a.report]
        return publish(memory_markdown(runs, a.section), a.write_docs)
    command = "python -m benchmarks.long " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_long_"))
    work.mkdir(parents=True, exist_ok=True)
    load0 = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    reference = reference_timing()
    r = run(a.frames, a.motion, a.seed, a.window, work, a.set, tuple(a.size))
    if a.json is not None:
        from rgbdslam.io.atomic import atomic_write_text

        r.update(command=command, machine=f"{platform.machine()}, {os.cpu_count()} cores, Python "
                 f"{platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M')}, load average at the start {load0}, "
                 f"at the end {', '.join(f'{x:.1f}' for x in os.getloadavg())}; {reference}")
        a.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.json, json.dumps(r, indent=1))
    return publish(markdown(r, command, reference, a.section), a.write_docs)


if __name__ == "__main__":
    raise SystemExit(main())
