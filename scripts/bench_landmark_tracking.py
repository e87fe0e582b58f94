"""The landmark stage alone, replayed on recorded inputs: its CPU time per frame and whether a
change of its code changes its answers (issue 17's speed target).

Usage::

    # record every call the pipeline makes to the landmark stage on a sequence (one run)
    .venv/bin/python scripts/bench_landmark_tracking.py record OUT.pkl [--sequence DIR] [--set KEY=VALUE ...]
    # replay the calls (fresh process per code, interleaved repeats), time them, compare the answers
    .venv/bin/python scripts/bench_landmark_tracking.py replay OUT.pkl [--code NAME=DIR ...] [--repeat 3]
        [--set KEY=VALUE ...]

``record`` runs ``rgbdslam.pipeline.run_sequence`` (map fusion and plots off, as
``bench_landmark_speed.py``; ``landmarks.enabled=true`` is added) with
:class:`rgbdslam.landmarks.stage.LandmarkTracker` wrapped: every call the per-frame chain makes
(``track``, ``add_keyframe``, ``end_frame``, ``holds``) is stored with a copy of its arguments and its answer. ``replay`` makes a fresh
tracker from the recorded configuration (``--set`` changes it, e.g. ``landmarks.stale_check=false``)
and camera and makes the same calls in the same order: the inputs are the pipeline's, whatever the
answers, so the replay of the recording code reproduces every answer bit for bit, and another
code's replay shows where its answers part (the first frame whose map pose differs, the largest
difference in translation and rotation) without the rest of the pipeline in the way. Times are
CPU seconds (``time.process_time``) per call kind, so a shared machine's load counts less; each
code runs in its own process (``--code NAME=DIR``: a checkout's ``rgbdslam`` package, e.g. an
unpacked ``git archive``; ``this`` = this checkout, run last), repeats interleaved; the ratio
column is to the first code.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import pickle
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CALLS = ("track", "add_keyframe", "end_frame", "holds")


def _strip(feats):
    """A copy of a frame's features without its cached k-d tree (not needed by the landmark stage)."""
    f = copy.copy(feats)
    f._tree = None
    f._tree_index = None
    return copy.deepcopy(f)


def record(out: Path, seq: Path, sets: list[str]) -> None:
    sys.path.insert(0, str(ROOT))
    from rgbdslam.config import load_config
    from rgbdslam.landmarks import stage
    from rgbdslam.pipeline import run_sequence

    log: list = []
    init = {}
    cls = stage.LandmarkTracker
    orig_init = cls.__init__

    def init_wrap(self, cfg, camera, *rest):
        init["cfg"], init["camera"] = copy.deepcopy(cfg), copy.deepcopy(camera)
        orig_init(self, cfg, camera, *rest)

    def wrap(name):
        fn = getattr(cls, name)

        def call(self, *args):
            stored = tuple(_strip(a) if hasattr(a, "desc") and hasattr(a, "uv") else copy.deepcopy(a) for a in args)
            res = fn(self, *args)
            log.append((name, stored, copy.deepcopy(res)))
            return res

        return call

    cls.__init__ = init_wrap
    for name in CALLS:
        setattr(cls, name, wrap(name))
    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "landmarks.enabled=true", *sets])
    with_tmp = out.with_suffix(".run")
    s = run_sequence(str(seq), str(with_tmp), cfg, progress=False)
    with open(out, "wb") as f:
        pickle.dump({"init": init, "log": log, "sets": sets, "sequence": str(seq),
                     "ate": ((s.get("evaluation") or {}).get("ate") or {}).get("rmse")}, f)
    n = sum(1 for c in log if c[0] == "track")
    print(f"recorded {len(log)} calls ({n} frames) to {out}; ATE {s['evaluation']['ate']['rmse']:.6f}")


_CHILD = r"""
import json, pickle, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
from rgbdslam.config import load_config
from rgbdslam.landmarks.stage import LandmarkTracker
rec = pickle.load(open(sys.argv[2], "rb"))
cfg = rec["init"]["cfg"]
sets = json.loads(sys.argv[3])
if sets:
    over = load_config(None, ["landmarks." + s if not s.startswith("landmarks.") else s for s in sets]).landmarks
    for k in sets:
        key = k.split("=", 1)[0].split(".")[-1]
        setattr(cfg, key, getattr(over, key))
tr = LandmarkTracker(cfg, rec["init"]["camera"])
cpu, count, out = {}, {}, []
for name, args, _ in rec["log"]:
    fn = getattr(tr, name)
    t0 = time.process_time()
    res = fn(*args)
    dt = time.process_time() - t0
    cpu[name] = cpu.get(name, 0.0) + dt
    count[name] = count.get(name, 0) + 1
    out.append(res)
pickle.dump({"cpu": cpu, "count": count, "answers": out, "summary": tr.summary()}, open(sys.argv[4], "wb"))
"""


def _rot_deg(R: np.ndarray) -> float:
    """Rotation angle (degrees) of R; from ||R - I|| (exact near zero, where arccos of the trace is not)."""
    return float(np.degrees(2.0 * np.arcsin(min(1.0, np.linalg.norm(R - np.eye(3)) / (2.0 * np.sqrt(2.0))))))


def compare(log: list, answers: list) -> dict:
    """Where the replayed answers part from the recorded ones: calls that differ, the first frame
    whose ``track`` pose differs, the largest pose difference (m, degrees) over ``track`` and ``add_keyframe``."""
    differ, first, dt, dr = 0, None, 0.0, 0.0
    for (name, args, want), got in zip(log, answers):
        same = True
        if name == "track":
            d = np.linalg.inv(want) @ got
            dt, dr = max(dt, float(np.linalg.norm(d[:3, 3]))), max(dr, _rot_deg(d[:3, :3]))
            same = bool(np.array_equal(want, got))
        elif name == "add_keyframe":
            same = want.keys() == got.keys() and all(np.array_equal(want[k], got[k]) for k in want)
            for k in set(want) & set(got):
                d = np.linalg.inv(want[k]) @ got[k]
                dt, dr = max(dt, float(np.linalg.norm(d[:3, 3]))), max(dr, _rot_deg(d[:3, :3]))
        elif name == "holds":
            same = want == got
        if not same:
            differ += 1
            if first is None:
                first = f"{name} frame {args[0]}"
    return {"calls_differ": differ, "first": first, "max_dt_m": dt, "max_dr_deg": dr}


def replay(rec_path: Path, codes: dict[str, Path], repeat: int, sets: list[str], work: Path) -> None:
    with open(rec_path, "rb") as f:
        rec = pickle.load(f)
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    load0 = os.getloadavg()
    rows: dict[str, list] = {name: [] for name in codes}
    for r in range(repeat):
        for name, code in codes.items():
            out = work / f"{name}_{r}.pkl"
            p = subprocess.run([sys.executable, "-c", _CHILD, str(code), str(rec_path), json.dumps(sets), str(out)],
                               capture_output=True, text=True, env=env)
            if p.returncode != 0:
                raise SystemExit(f"replay {name} failed:\n{p.stderr[-3000:]}")
            with open(out, "rb") as f:
                rows[name].append(pickle.load(f))
            res = rows[name][-1]
            print(f"repeat {r + 1}: {name:12s} CPU {sum(res['cpu'].values()):.2f} s", flush=True)
    load1 = os.getloadavg()
    n = sum(1 for c in rec["log"] if c[0] == "track")
    print(f"\nRecording: {rec_path} ({rec['sequence']}, {n} frames, sets {rec['sets']}); replay sets {sets}")
    print(f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; load average {', '.join(f'{x:.2f}' for x in load0)} "
          f"at the start, {', '.join(f'{x:.2f}' for x in load1)} at the end\n")
    kinds = [k for k in CALLS if any(k in res["cpu"] for rs in rows.values() for res in rs)]
    base = next(iter(codes))
    base_total = float(np.median([sum(x["cpu"].values()) for x in rows[base]]))
    print("| code | CPU ms/frame, median (range) | x " + base + " | " +
          " | ".join(f"{k} ms/call" for k in kinds) + " | calls differing from the recording | first | max pose diff (m, deg) |")
    print("|" + "---|" * (6 + len(kinds)))
    for name, rs in rows.items():
        tot = [1e3 * sum(x["cpu"].values()) / n for x in rs]
        per = [float(np.median([1e3 * x["cpu"].get(k, 0.0) / max(1, x["count"].get(k, 0)) for x in rs])) for k in kinds]
        c = compare(rec["log"], rs[0]["answers"])
        same = all(compare(rec["log"], x["answers"]) == c for x in rs)
        print(f"| {name} | {np.median(tot):.2f} ({min(tot):.2f}-{max(tot):.2f}) | "
              f"{np.median(tot) / (1e3 * base_total / n):.2f} | "
              + " | ".join(f"{p:.2f}" for p in per)
              + f" | {c['calls_differ']}{'' if same else ' (repeats differ!)'} | {c['first'] or '-'} | "
              f"{c['max_dt_m']:.2e}, {c['max_dr_deg']:.2e} |")
    print("\nsummaries:")
    for name, rs in rows.items():
        s = rs[0]["summary"]
        print(f"  {name}: map_poses {s['map_poses']} rejected {s['rejected']} stale_left_out {s['stale_left_out']} "
              f"stale_joined {s['stale_joined']} median_inliers {s['median_inliers']} size {s['size']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("record")
    a.add_argument("out", type=Path)
    a.add_argument("--sequence", type=Path, default=Path(os.environ.get("RGBDSLAM_DATA", ROOT.parent / "shared" / "data"))
                   / "tum" / "rgbd_dataset_freiburg1_rpy_head200")
    a.add_argument("--set", action="append", default=[])
    b = sub.add_parser("replay")
    b.add_argument("recording", type=Path)
    b.add_argument("--code", action="append", default=[], help="NAME=DIR: replay with another checkout's package")
    b.add_argument("--repeat", type=int, default=3)
    b.add_argument("--set", action="append", default=[], help="landmarks.KEY=VALUE changed for the replay")
    b.add_argument("--work", type=Path, default=Path("/tmp/bench_landmark_tracking"))
    args = ap.parse_args()
    if args.cmd == "record":
        record(args.out, args.sequence, args.set)
    else:
        codes = {}
        for c in args.code:
            name, _, d = c.partition("=")
            codes[name] = Path(d).resolve()
        codes["this"] = ROOT
        replay(args.recording, codes, args.repeat, args.set, args.work)


if __name__ == "__main__":
    main()
