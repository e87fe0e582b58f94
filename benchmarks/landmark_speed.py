"""Speed of chain variants against today's default (the landmark map), interleaved in one run
(results: docs/speed.md).

Usage::

    python -m benchmarks.landmark_speed [--sequence DIR] [--repeat 3] [--work DIR]
        [--variant NAME=KEY=VALUE[,KEY=VALUE...]] ... [--code NAME=DIR] ... [--json FILE]
        [--profile VARIANT] [--profile-cpu]

Every run is a fresh ``python`` process running ``rgbdslam.pipeline.run_sequence`` on the sequence
(default: TUM fr1/rpy head200; map fusion and plots off, as ``bench_landmarks.py``). The variants
(``default`` = no settings: the landmark map, ``thesis`` = ``landmarks.enabled=false``: the frame-to-frame
chain, unless ``--variant`` names others) run **interleaved**: repeat 1 of
every variant, then repeat 2, ..., so a change of the machine's load hits all of them alike.
``--code NAME=DIR`` also runs every variant from another checkout's ``rgbdslam`` package (e.g. an
unpacked ``git archive`` of main: the code before a change), interleaved too. Per variant: the
median (and range) of frames/s over the repeats (whole tracking loop, images included), its ratio
to the default's median, the CPU time per frame of the run's process (all its threads, start-up
and the end of the run included: less sensitive to the machine's load than frames/s), the same for
the run without its start-up's imports and its end (``run_sequence``'s CPU time less run.json's
``after_tracking_s.cpu``: the tracking loop, which frames/s measures, and the run's small set-up) and that of its
child processes, the ATE, the per-stage medians (ms) from run.json; ``uptime``'s load before and after. ``--profile VARIANT`` runs that variant once
more under cProfile and prints the 30 most expensive functions (own time); ``--profile-cpu`` times
that profile in CPU time (``time.process_time``: the waiting of a loaded machine does not count).
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

import numpy as np

from benchmarks.common import DATA, ROOT, command_line
DEFAULT_VARIANTS = {"default": [], "thesis": ["landmarks.enabled=false"]}

_CHILD = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
from rgbdslam.config import load_config
import time
from rgbdslam.pipeline import run_sequence
sets = json.loads(sys.argv[4])
cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *sets])
if sys.argv[5]:
    import cProfile, pstats, time
    pr = cProfile.Profile(time.process_time) if sys.argv[5] == "cpu" else cProfile.Profile(); pr.enable()
c0 = time.process_time()
s = run_sequence(sys.argv[2], sys.argv[3], cfg, progress=False)
# the run's CPU time less that of its end (run.json after_tracking_s.cpu): the tracking loop's
loop_cpu = time.process_time() - c0 - s["after_tracking_s"]["cpu"]
if sys.argv[5]:
    pr.disable(); pstats.Stats(pr, stream=sys.stderr).sort_stats("tottime").print_stats(30)
import resource
me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
ev = s.get("evaluation") or {}
print("RESULT " + json.dumps({"fps": s["fps"], "processing_fps": s["processing_fps"],
      "ate": (ev.get("ate") or {}).get("rmse"), "timings": s.get("timings", {}),
      "keyframes": len(s.get("keyframes", [])), "frames": s["frames"],
      "cpu_s": me.ru_utime + me.ru_stime, "loop_cpu_s": loop_cpu, "child_cpu_s": kids.ru_utime + kids.ru_stime}))
"""


def run_once(code: Path, seq: Path, out: Path, sets: list[str], profile: bool | str = False) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    p = subprocess.run([sys.executable, "-c", _CHILD, str(code), str(seq), str(out), json.dumps(sets),
                        ("cpu" if profile == "cpu" else "1") if profile else ""], capture_output=True, text=True,
                       env=env)
    if p.returncode != 0:
        raise SystemExit(f"run {out.name} failed:\n{p.stderr[-3000:]}")
    if profile:
        print(p.stderr)
    line = next(x for x in p.stdout.splitlines() if x.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


def load() -> str:
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def parse_kv(text: str, what: str) -> tuple[str, str]:
    name, sep, rest = text.partition("=")
    if not sep or not rest:
        raise SystemExit(f"{what} {text!r}: expected NAME=...")
    return name, rest


def summarise(runs: dict[str, list[dict]]) -> list[dict]:
    base = float(np.median([r["fps"] for r in runs["default"]])) if "default" in runs else float("nan")
    rows = []
    for name, rs in runs.items():
        fps = [r["fps"] for r in rs]
        stages = {}
        for k in sorted({k for r in rs for k in r["timings"]}):
            v = [r["timings"][k]["median_ms"] for r in rs if k in r["timings"]]
            stages[k] = float(np.median(v))
        cpu = [1e3 * r["cpu_s"] / r["frames"] for r in rs]
        kid = [1e3 * r["child_cpu_s"] / r["frames"] for r in rs]
        loop = [1e3 * r.get("loop_cpu_s", float("nan")) / r["frames"] for r in rs]
        rows.append({"variant": name, "cpu_ms": float(np.median(cpu)), "child_cpu_ms": float(np.median(kid)),
                     "loop_cpu_ms": float(np.median(loop)), "loop_cpu_range": [min(loop), max(loop)],
                     "fps": float(np.median(fps)), "fps_min": min(fps), "fps_max": max(fps),
                     "ratio": float(np.median(fps)) / base, "ate": sorted({round(r["ate"], 5) for r in rs if r["ate"]}),
                     "stages_ms": stages,
                     "keyframes": rs[0]["keyframes"], "repeats": len(rs)})
    return rows


def markdown(rows: list[dict], command: str, machine: str) -> str:
    stages = sorted({k for r in rows for k in r["stages_ms"]})
    head = ("| variant | frames/s median (range) | × default | CPU ms/frame: run process (× default) | "
            "CPU ms/frame: tracking loop (× default) | + child processes | ATE (m) | "
            + " | ".join(f"{s} ms" for s in stages) + " |")
    out = [f"Command: `{command}`  ", f"Machine: {machine}", "", head, "|" + "---|" * (7 + len(stages))]
    cpu0 = next((r["cpu_ms"] for r in rows if r["variant"] == "default"), float("nan"))
    loop0 = next((r.get("loop_cpu_ms", float("nan")) for r in rows if r["variant"] == "default"), float("nan"))
    for r in rows:
        out.append(f"| {r['variant']} | {r['fps']:.1f} ({r['fps_min']:.1f}–{r['fps_max']:.1f}) | {r['ratio']:.2f} | "
                   f"{r['cpu_ms']:.1f} ({r['cpu_ms'] / cpu0:.2f}) | "
                   f"{r.get('loop_cpu_ms', float('nan')):.1f} ({r.get('loop_cpu_ms', float('nan')) / loop0:.2f}) | "
                   f"{r['child_cpu_ms']:.1f} | "
                   + ", ".join(f"{a:.4f}" for a in r["ate"]) + " | "
                   + " | ".join(f"{r['stages_ms'][s]:.1f}" if s in r["stages_ms"] else "" for s in stages) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, default=DATA
                    / "tum" / "rgbd_dataset_freiburg1_rpy_head200")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--code", action="append", default=[], help="NAME=DIR: also run from another checkout")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--profile", default=None, metavar="VARIANT")
    ap.add_argument("--profile-cpu", action="store_true", help="time the profile in CPU time")
    a = ap.parse_args(argv)
    variants = dict(DEFAULT_VARIANTS) if not a.variant else {"default": []}
    for v in a.variant:
        name, rest = parse_kv(v, "--variant")
        variants[name] = rest.split(",")
    codes = {"": ROOT}
    for c in a.code:
        name, d = parse_kv(c, "--code")
        codes[name] = Path(d).resolve()
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_lmspeed_"))
    load0 = load()
    runs: dict[str, list[dict]] = {}
    for k in range(a.repeat):
        for cname, code in codes.items():
            for vname, sets in variants.items():
                name = vname if not cname else f"{vname} [{cname}]"
                r = run_once(code, a.sequence, work / f"{name.replace(' ', '_').replace('/', '_')}_r{k}", sets)
                runs.setdefault(name, []).append(r)
                print(f"repeat {k + 1}: {name:32s} {r['fps']:5.1f} frames/s  ATE {r['ate']:.4f}  load {load()}",
                      flush=True)
    if a.profile:
        run_once(ROOT, a.sequence, work / "profile", variants[a.profile], profile="cpu" if a.profile_cpu else True)
    rows = summarise(runs)
    machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
               f"{time.strftime('%Y-%m-%d %H:%M')} UTC, shared; load average (1, 5, 15 min) {load0} at the start, "
               f"{load()} at the end")
    command = command_line("benchmarks.landmark_speed", argv)
    print(markdown(rows, command, machine))
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({"command": command, "machine": machine, "rows": rows, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
