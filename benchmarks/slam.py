"""Full-SLAM benchmark: thesis table 4.3 columns, a synthetic loop, loop-closure cost.

Usage::

    python -m benchmarks.slam [--data DIR] [--out DIR] [--write-docs] [--skip-synthetic]
                                           [--skip-index] [--frames N] [--repeat N]
                                           [--landmark-ablation [--ablation-motions M,..] [--ablation-seeds S,..]
                                            [--landmark-section HEADING] [--json FILE]]

For each available TUM sequence (``$RGBDSLAM_DATA/tum/*``, default ``../shared/data``) it runs
``rgbdslam.pipeline.run_sequence`` with the configurations

* ``ISVD``          registration.method=isvd, no loop closure, no DIF, no pose graph;
* ``ISVD+LC``       + sharpness-gated loop closure and the GTSAM pose graph;
* ``ISVD+LC+DIF``   + the DIF depth filter;
* ``ISLAM``, ``best (ISLAM+LC)``, ``ISLAM+LC+DIF``: this project's default registration
  (ISLAM, MP=4) alone, with loop closure (the best measured), and with DIF too;
* ``ISLAM+LC+landmarks`` and its ablations: the landmark map (``landmarks.enabled``) fused with
  ISLAM; the map pose alone (seed mode); Kalman off; uniform RANSAC sampling; one
  k-d tree instead of the multi-tree;

and prints ATE RMSE, frames/s, loops and false loops (a loop edge whose relative pose
disagrees with the ground truth by more than 0.10 m or 5 degrees) as markdown. Then:

* a synthetic loop sequence (``rgbdslam.datasets.synthetic.generate_sequence(motion='loop',
  noise=True)``): loop found? ATE of trajectory.tum vs odometry.tum;
* the descriptor index: query time against the number of keyframes for the LSH index and
  the exhaustive baseline (real ORB descriptors from fr1/rpy with bit noise).

``--landmark-ablation`` runs ``LANDMARK_ABLATION`` — today's default (landmark tracking); the thesis'
frame-to-frame chain (``landmarks.enabled=false``); Kalman off; uniform instead of old-first RANSAC sampling; one k-d tree
instead of the multi-tree; the map pose alone (seed mode) — on fr1/rpy head200, 7-Scenes redkitchen
0-299 and the synthetic motions x seeds (``--synthetic-frames``), with benchmarks/landmarks.py's
tables plus the landmark stage's cost per variant, as its own section (``--landmark-section``).
With ``--skip-table --skip-ablation --skip-synthetic --skip-index`` it runs alone.

``--write-docs`` replaces the "## Full SLAM" section of docs/benchmarks.md with the tables (and the
landmark ablation's section, appended when new).
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

from benchmarks import common
from benchmarks.common import ROOT
from rgbdslam.config import Config, merge
from rgbdslam.evaluation.ate import ate
from rgbdslam.geometry.se3 import inv, rotation_angle

FALSE_LOOP_T = 0.10
FALSE_LOOP_R_DEG = 5.0


def data_root(arg: str | None) -> Path:
    return Path(arg) if arg else common.DATA


def configs() -> dict[str, list[str]]:
    """name -> config settings (``section.key=value``) on top of the defaults (map and plots off)."""
    on = {True: "true", False: "false"}
    out = {}
    for name, method, lc, dif in [("ISVD", "isvd", False, False), ("ISVD+LC", "isvd", True, False),
                                  ("ISVD+LC+DIF", "isvd", True, True), ("ISLAM", "islam", False, False),
                                  ("best (ISLAM+LC)", "islam", True, False), ("ISLAM+LC+DIF", "islam", True, True)]:
        out[name] = [f"registration.method={method}", f"loop.enabled={on[lc]}", f"backend.enabled={on[lc]}",
                     f"depth_filter.enabled={on[dif]}", "landmarks.enabled=false"]  # the thesis' chains
    # the landmark map on top of the best: fused with ISLAM, alone (seed mode),
    # and its ablations (Kalman off, uniform RANSAC sampling, single k-d tree); docs/landmarks.md "The ablation"
    for name, sets in [("ISLAM+LC+landmarks", []), ("… seed mode", ["landmarks.mode=seed"]),
                       ("… Kalman off", ["landmarks.kalman=false"]),
                       ("… uniform sampling", ["landmarks.sampling=uniform"]),
                       ("… single k-d tree", ["landmarks.store=single"])]:
        out[name] = ["landmarks.enabled=true", *sets]
    return out


def config(sets: list[str], max_frames: int | None = None) -> Config:
    return common.load_config(None, [*sets, *([f"dataset.max_frames={max_frames}"] if max_frames else [])])


def loop_edges(run_dir: Path) -> list[tuple[int, int, np.ndarray]]:
    """The loop edges ``(i, j, T_ij)`` of a finished run: the edges of its posegraph.g2o (vertex ids =
    frame indices) between the frame pairs run.json lists as loops."""
    from rgbdslam.posegraph.graph_io import read_graph

    pairs = {tuple(p) for p in json.loads((run_dir / "run.json").read_text())["loops"]}
    g = read_graph(run_dir / "posegraph.g2o")
    return [(int(g.ids[a]), int(g.ids[b]), T) for a, b, T in zip(g.edges_i, g.edges_j, g.meas)
            if (int(g.ids[a]), int(g.ids[b])) in pairs]


def gt_pose_lookup(seq):
    gt = seq.groundtruth()
    if gt is None:
        return None
    ts = np.asarray(seq.timestamps)

    def pose(i: int) -> np.ndarray | None:
        k = int(np.argmin(np.abs(gt.timestamps - ts[i])))
        return gt.poses[k] if abs(gt.timestamps[k] - ts[i]) < 0.02 else None

    return pose


def loop_errors(edges, gt_pose) -> list[tuple[float, float]]:
    out = []
    for i, j, T_ij in edges:
        a, b = gt_pose(i), gt_pose(j)
        if a is None or b is None:
            continue
        d = inv(inv(a) @ b) @ T_ij
        out.append((float(np.linalg.norm(d[:3, 3])), float(np.degrees(rotation_angle(d[:3, :3])))))
    return out


def timed_runs(seq, out: Path, cfg: Config, repeat: int) -> dict:
    """``run_sequence`` ``repeat`` times; the first run's summary with the *median* frames/s.

    Runs are seeded, so every repeat must give the same trajectory (checked on the ATE)."""
    from rgbdslam.pipeline import run_sequence

    runs = [run_sequence(seq, out if k == 0 else out.with_name(f"{out.name}_r{k}"), cfg, progress=False)
            for k in range(max(1, repeat))]
    ates = {((r.get("evaluation") or {}).get("ate") or {}).get("rmse") for r in runs}
    if len(ates) != 1:
        raise SystemExit(f"repeated runs of {out.name} differ (ATE {sorted(ates)}): a random choice is not seeded")
    s = dict(runs[0])
    s["fps"] = float(np.median([r["fps"] for r in runs]))
    s["processing_fps"] = float(np.median([r["processing_fps"] for r in runs]))
    s["fps_range"] = (min(r["fps"] for r in runs), max(r["fps"] for r in runs))
    return s


def run_table(data: Path, out: Path, max_frames: int | None, repeat: int = 1) -> list[dict]:
    from rgbdslam.datasets import open_sequence

    rows = []
    seqs = sorted(p for p in (data / "tum").glob("rgbd_dataset_*") if p.is_dir())
    for sp in seqs:
        for name, sets in configs().items():
            cfg = config(sets, max_frames)
            seq = open_sequence(sp, cfg.dataset)
            if len(seq) < 20:  # too short for loop closure to mean anything
                break
            t0 = time.perf_counter()
            run_dir = out / sp.name / "".join(ch if ch.isalnum() or ch in "+-" else "_" for ch in name)
            s = timed_runs(seq, run_dir, cfg, repeat)
            wall = (time.perf_counter() - t0) / max(1, repeat)
            ev = (s.get("evaluation") or {}).get("ate") or {}
            errs = loop_errors(loop_edges(run_dir), gt_pose_lookup(seq))  # the first run's loops
            false = sum(1 for t, r in errs if t > FALSE_LOOP_T or r > FALSE_LOOP_R_DEG)
            lc = s.get("loop_closure") or {}
            rows.append({
                "sequence": sp.name.replace("rgbd_dataset_", ""), "config": name, "frames": s["frames"],
                "ate": ev.get("rmse", float("nan")), "fps": s["fps"], "processing_fps": s["processing_fps"],
                "fps_range": s["fps_range"],
                "wall": wall, "loops": len(s["loops"]), "false_loops": false, "sharp": s["sharp_frames"],
                "keyframes": len(s["keyframes"]),
                "loop_err_max": (max(t for t, _ in errs), max(r for _, r in errs)) if errs else None,
                "lc_ms_per_sharp": lc.get("time_per_query_ms"),
                "dif_ms": (s["timings"].get("depth_filter") or {}).get("median_ms"),
            })
            r = rows[-1]
            print(f"  {r['sequence']:28s} {name:22s} ATE {r['ate']:.4f} m  {r['fps']:.1f} fps  "
                  f"loops {r['loops']} (false {false})", flush=True)
    return rows


def run_synthetic(out: Path, frames: int) -> dict:
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.io.trajectory import read_tum
    from rgbdslam.pipeline import run_sequence

    seq_dir = out / "synthetic_loop"
    if not (seq_dir / "groundtruth.txt").exists():
        generate_sequence(seq_dir, frames=frames, motion="loop", noise=True, seed=0)
    cfg = config(configs()["best (ISLAM+LC)"])
    s = run_sequence(seq_dir, out / "synthetic_run", cfg, progress=False)
    gt = read_tum(seq_dir / "groundtruth.txt")
    res = {"frames": frames, "loops": len(s["loops"]), "sharp": s["sharp_frames"], "fps": s["fps"]}
    for name in ("odometry", "trajectory"):
        res[name] = ate(gt, read_tum(out / "synthetic_run" / f"{name}.tum")).rmse
    from rgbdslam.datasets import open_sequence

    errs = loop_errors(loop_edges(out / "synthetic_run"), gt_pose_lookup(open_sequence(seq_dir, cfg.dataset)))
    res["false_loops"] = sum(1 for t, r in errs if t > FALSE_LOOP_T or r > FALSE_LOOP_R_DEG)
    print(f"  synthetic loop: {res}", flush=True)
    return res


def run_index_scaling(data: Path, sizes=(50, 100, 200, 400, 800, 1600, 3200), n_queries: int = 20) -> list[dict]:
    """Query time of the keyframe index against the number of keyframes.

    The map holds distinct places: descriptors drawn bit by bit with the per-bit frequencies
    of real ORB descriptors (fr1/rpy), so the bias of ORB bits (which makes random LSH
    collisions more frequent than for uniform bits) is kept. Queries are real frames.
    """
    from rgbdslam.loop.index import BruteIndex, LshIndex

    rng = np.random.default_rng(0)
    pool = _orb_pool(data)
    p_bit = np.unpackbits(np.concatenate(pool), axis=1).mean(axis=0)
    lc = Config().loop
    rows = []
    for kind in ("lsh", "brute"):
        idx = LshIndex(lc.lsh_tables, lc.lsh_bits, lc.seed) if kind == "lsh" else BruteIndex(64)
        n = 0
        t_add = 0.0
        for size in sizes:
            if kind == "brute" and size > 400:
                break
            while n < size:
                d = np.packbits((rng.random((1000, 256)) < p_bit).astype(np.uint8), axis=1)
                t0 = time.perf_counter()
                idx.add(n, d)
                t_add += time.perf_counter() - t0
                n += 1
            qs = [pool[rng.integers(len(pool))] for _ in range(n_queries if kind == "lsh" else 3)]
            idx.votes(qs[0])  # warm-up (brute: concatenation of the map)
            t0 = time.perf_counter()
            for q in qs:
                idx.votes(q)
            rows.append({"index": kind, "keyframes": n, "query_ms": 1e3 * (time.perf_counter() - t0) / len(qs),
                         "add_ms": 1e3 * t_add / n})
            print(f"  {kind:5s} {n:5d} keyframes: {rows[-1]['query_ms']:.2f} ms/query, "
                  f"{rows[-1]['add_ms']:.2f} ms/insert", flush=True)
    return rows


ABLATION = {
    "ISLAM+LC+DIF K=0 (spatial only)": {"depth_filter.window": 0},
    "ISLAM+LC+DIF K=1": {"depth_filter.window": 1},
    "ISLAM+LC+DIF K=3": {"depth_filter.window": 3},
    "ISLAM+LC+DIF min_support=2": {"depth_filter.min_support": 2},
    "ISLAM+LC+DIF temporal only (spatial_radius=0, min_support=1)": {"depth_filter.spatial_radius": 0,
                                                                      "depth_filter.min_support": 1},
    "ISLAM+LC gate on the sum of ORB responses": {"depth_filter.enabled": False,
                                                   "loop.sharpness_measure": "response"},
    "ISLAM+LC sharp frames only (loop.query_gap=0)": {"depth_filter.enabled": False, "loop.query_gap": 0},
    "ISLAM+LC frames read in the loop (dataset.prefetch=0)": {"depth_filter.enabled": False,
                                                               "dataset.prefetch": 0},
    "ISLAM+LC stop at the first verified loop (loop.stop_at_first=true)": {"depth_filter.enabled": False,
                                                                          "loop.stop_at_first": True},
    "ISLAM+LC init=odometry": {"depth_filter.enabled": False, "backend.init": "odometry"},
    "ISLAM+LC no robust kernel": {"depth_filter.enabled": False, "backend.robust_kernel": "none"},
    "ISLAM+LC Cauchy without chain scaling": {"depth_filter.enabled": False, "backend.kernel_chain_scaling": False},
}


def run_ablation(data: Path, out: Path, max_frames: int | None, repeat: int = 1) -> list[dict]:
    """DIF and back-end variants on fr1/rpy head200 (ISLAM + LC + DIF as the base)."""

    sp = data / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    if not sp.is_dir():
        return []
    rows = []
    for name, sets in ABLATION.items():
        cfg = config(configs()["ISLAM+LC+DIF"], max_frames)
        nested: dict[str, dict] = {}
        for k, v in sets.items():
            sec, key = k.split(".")
            nested.setdefault(sec, {})[key] = v
        merge(cfg, nested, f"ablation {name}")
        s = timed_runs(sp, out / "ablation" / f"{len(rows):02d}", cfg, repeat)
        rows.append({"config": name, "ate": ((s.get("evaluation") or {}).get("ate") or {}).get("rmse", float("nan")),
                     "loops": len(s["loops"]), "fps": s["fps"],
                     "verified": s["loop_closure"].get("n_verified", 0),
                     "lc_ms": s["loop_closure"].get("time_per_query_ms", 0.0),
                     "dif_ms": (s["timings"].get("depth_filter") or {}).get("median_ms")})
        print(f"  ablation {name:40s} ATE {rows[-1]['ate']:.4f} m", flush=True)
    return rows


# the landmark map's ablation: today's default (landmark tracking); the thesis' frame-to-frame chain; Kalman on/off; old-first vs uniform RANSAC sampling; multi vs single k-d tree; the map pose alone (seed mode)
LANDMARK_ABLATION = {
    "default": [],
    "thesis": ["landmarks.enabled=false"],
    "landmarks, Kalman off": ["landmarks.enabled=true", "landmarks.kalman=false"],
    "landmarks, uniform sampling": ["landmarks.enabled=true", "landmarks.sampling=uniform"],
    "landmarks, single k-d tree": ["landmarks.enabled=true", "landmarks.store=single"],
    "landmarks, seed mode": ["landmarks.enabled=true", "landmarks.mode=seed"],
}


def landmark_sequences(data: Path, out: Path, motions: list[str], seeds: list[int], frames: int) -> list[tuple]:
    """(name, folder, extra config) of fr1/rpy head200, 7-Scenes redkitchen 0-299 (the 7-Scenes reader with
    rgbdslam/cameras/7scenes.yaml) and the synthetic generator's motions x seeds (Kinect noise, rendered once
    into ``out``), as benchmarks/landmarks.py names them."""
    from rgbdslam.datasets.synthetic import generate_sequence

    seqs = []
    rpy = data / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    if rpy.is_dir():
        seqs.append(("fr1/rpy head200", rpy, []))
    ss = data / "7scenes" / "frames_0000_0299"
    if ss.is_dir():
        seqs.append(("7-Scenes redkitchen 0-299", ss, [f"dataset.camera_file={ROOT / 'rgbdslam' / 'cameras' / '7scenes.yaml'}"]))
    for motion in motions:
        for seed in seeds:
            d = out / "synthetic" / f"{motion}_s{seed}_{frames}"
            if not (d / "groundtruth.txt").exists():
                generate_sequence(d, frames=frames, motion=motion, noise=True, seed=seed)
            seqs.append((f"{motion} seed {seed}", d, []))
    return seqs


def run_landmark_ablation(data: Path, out: Path, motions: list[str], seeds: list[int], frames: int,
                          repeat: int = 1, variants: dict | None = None) -> list[dict]:
    """Every :data:`LANDMARK_ABLATION` variant on every sequence of :func:`landmark_sequences` (map
    fusion off): ATE, 1-frame RPE, frames/s, the landmark stage's median ms, the
    share of old landmarks matched, and first visit / revisit ATE on the loop-type motions."""
    from benchmarks.landmarks import LOOP_TYPE, summary_metrics, revisit_errors, run_dir_name

    from rgbdslam.config import load_config

    rows = []
    for name, d, extra in landmark_sequences(data, out, motions, seeds, frames):
        for vname, sets in (variants or LANDMARK_ABLATION).items():
            cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *extra, *sets])
            run = out / "landmark_ablation" / run_dir_name(name, vname.replace(",", "").replace("+", "plus"))
            s = timed_runs(d, run, cfg, repeat)
            lm = s.get("landmarks") or {}
            row = {"sequence": name, "variant": vname, "dir": str(d), **summary_metrics(s),
                   "landmarks_ms": (s["timings"].get("landmarks") or {}).get("median_ms"),
                   "store_trees": lm.get("store_trees")}
            if " seed " in name and name.split(" ")[0] in LOOP_TYPE:
                rv = revisit_errors(d, run)
                if rv:
                    row["first_visit"], row["revisit"] = rv
            rows.append(row)
            print(f"  {name:28s} {vname:30s} ATE {row['ate']:.4f}  RPE {row['rpe']:.4f}  {row['fps']:5.1f} fps  "
                  f"landmarks {row['landmarks_ms'] or 0:.1f} ms", flush=True)
    return rows


def landmark_markdown(rows: list[dict], section: str, command: str, machine: str) -> str:
    """bench_landmarks.py's tables (per sequence x variant, revisit, synthetic medians and ratios) and the
    landmark stage's cost per variant (median over the sequences of each run's median ms per frame)."""
    from benchmarks.landmarks import markdown as lm_markdown

    text = lm_markdown(rows, section, [command], machine)
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    L = ["", "Cost of the landmark stage per variant (median over the sequences of each run's median; wall time "
         "of the stage in the run, on this shared machine):", "",
         "| variant | landmark stage ms/frame | frames/s, median ratio to the default |",
         "|---|---|---|"]
    by = {(r["sequence"], r["variant"]): r for r in rows}
    for v in variants:
        if v == "default":
            continue
        rs = [r for r in rows if r["variant"] == v]
        ms = [r["landmarks_ms"] for r in rs if r.get("landmarks_ms") is not None]
        ratio = [r["fps"] / by[(r["sequence"], "default")]["fps"] for r in rs if (r["sequence"], "default") in by]
        L.append(f"| {v} | {np.median(ms):.1f} | {f'{np.median(ratio):.2f}' if ratio else '-'} |")
    return text + "\n".join(L) + "\n"


def _flip(rng, desc, n_flips):
    bits = np.unpackbits(desc, axis=1)
    idx = rng.integers(0, 256, (len(desc), n_flips))
    np.bitwise_xor.at(bits, (np.arange(len(desc))[:, None], idx), 1)
    return np.packbits(bits, axis=1)


def _orb_pool(data: Path) -> list[np.ndarray]:
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import extract_features

    cfg = Config()
    sp = data / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    if not sp.is_dir():
        rng = np.random.default_rng(1)
        return [rng.integers(0, 256, (1000, 32), dtype=np.uint8) for _ in range(20)]
    seq = open_sequence(sp, cfg.dataset)
    return [extract_features(seq.load(i), cfg.features, cfg.matching).desc for i in range(0, len(seq), 10)]


# ------------------------------------------------------------------------------ markdown


def markdown(rows, synth, index_rows, command: str, ablation=(), repeat: int = 1, reference=()) -> str:
    L = ["## Full SLAM", "",
         f"Command: `{command}`  ",
         *[f"Speed of the machine, {when}: {ref}  " for when, ref in reference],
         f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
         f"Python {platform.python_version()}, {time.strftime('%Y-%m-%d')}; shared with other jobs, "
         f"so frames/s are noisy: each is the median of {repeat} identical runs (same trajectory, checked), "
         "lower bounds of an idle machine's.", "",
         "Thesis table 4.3 columns (ATE RMSE in metres, whole pipeline frames/s including image "
         "decoding, which a background thread overlaps with tracking (`dataset.prefetch`, 4 frames); "
         f"a false loop is an accepted loop edge off the ground truth by > {FALSE_LOOP_T} m "
         f"or > {FALSE_LOOP_R_DEG} deg):", "",
         "| sequence | configuration | frames | ATE RMSE (m) | frames/s (min–max) | keyframes | sharp | loops | false loops | LC ms/sharp frame | DIF ms |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lcms = f"{r['lc_ms_per_sharp']:.1f}" if r["lc_ms_per_sharp"] is not None else "-"
        dif = f"{r['dif_ms']:.1f}" if r["dif_ms"] is not None else "-"
        lo, hi = r["fps_range"]
        L.append(f"| {r['sequence']} | {r['config']} | {r['frames']} | {r['ate']:.4f} | {r['fps']:.1f} ({lo:.1f}–{hi:.1f}) | "
                 f"{r['keyframes']} | {r['sharp']} | {r['loops']} | {r['false_loops']} | {lcms} | {dif} |")
    if ablation:
        L += ["", "Ablation on freiburg1_rpy_head200 (base: ISLAM + LC + DIF with the defaults K=2, "
              "min_support=3, spatial_radius=1, MASAT init, chain-scaled Cauchy kernel):", "",
              "| variant | ATE RMSE (m) | loops | loop verifications | LC ms/search | frames/s | DIF ms |",
              "|---|---|---|---|---|---|---|"]
        for r in ablation:
            dif = f"{r['dif_ms']:.1f}" if r["dif_ms"] is not None else "-"
            L.append(f"| {r['config']} | {r['ate']:.4f} | {r['loops']} | {r['verified']} | {r['lc_ms']:.1f} | "
                     f"{r['fps']:.1f} | {dif} |")
    if synth:
        L += ["", f"Synthetic loop (`generate_sequence(motion='loop', noise=True, frames={synth['frames']})`, "
              "best configuration):", "",
              "| loops | false loops | ATE odometry.tum (m) | ATE trajectory.tum (m) | ratio |", "|---|---|---|---|---|",
              f"| {synth['loops']} | {synth['false_loops']} | {synth['odometry']:.4f} | {synth['trajectory']:.4f} | "
              f"{synth['trajectory'] / synth['odometry']:.2f} |"]
    if index_rows:
        L += ["", "Loop-candidate index: time of one query (a real fr1/rpy frame, 1000 ORB descriptors) against the "
              "number of keyframes in the map (distinct places: 1000 descriptors each, bits drawn with the per-bit "
              "frequencies of real ORB descriptors). A sharp frame's loop-closure cost is this query plus at most "
              "`max_candidates` registrations, independent of the map size:", "",
              "| keyframes | LSH ms/query | exhaustive ms/query |", "|---|---|---|"]
        by = {(r["index"], r["keyframes"]): r["query_ms"] for r in index_rows}
        for n in sorted({r["keyframes"] for r in index_rows}):
            b = by.get(("brute", n))
            L.append(f"| {n} | {by.get(('lsh', n), float('nan')):.2f} | {'-' if b is None else f'{b:.2f}'} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data")
    ap.add_argument("--out", default=None, help="run folders (default: a temporary folder)")
    ap.add_argument("--frames", type=int, default=None, help="limit frames per sequence")
    ap.add_argument("--synthetic-frames", type=int, default=150)
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--skip-index", action="store_true")
    ap.add_argument("--skip-table", action="store_true")
    ap.add_argument("--skip-ablation", action="store_true")
    ap.add_argument("--repeat", type=int, default=3, help="runs per configuration; frames/s is their median")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--landmark-ablation", action="store_true",
                    help="also run the landmark map's ablation (LANDMARK_ABLATION) on fr1/rpy head200, 7-Scenes 0-299 "
                         "and the synthetic --ablation-motions x --ablation-seeds; its own section")
    ap.add_argument("--ablation-motions", default="loop,circle,xyz,rpy,figure8,revisit")
    ap.add_argument("--ablation-seeds", default="0")
    ap.add_argument("--landmark-section", default="## Landmark map ablation (benchmarks/slam.py)",
                    help="heading of the landmark ablation's section (--write-docs replaces it or appends it)")
    ap.add_argument("--json", default=None, help="write the landmark ablation's rows here")
    a = ap.parse_args(argv)
    command = "python -m benchmarks.slam " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    data = data_root(a.data)
    out = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="bench_slam_"))
    from benchmarks.common import publish_markdown as publish, reference_timing

    if a.landmark_ablation:
        load0 = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        lrows = run_landmark_ablation(data, out, a.ablation_motions.split(","),
                                      [int(x) for x in a.ablation_seeds.split(",")], a.synthetic_frames, a.repeat)
        machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
                   f"{time.strftime('%Y-%m-%d %H:%M')}, load average at the start {load0} and at the end "
                   f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}")
        if a.json:
            from rgbdslam.io.atomic import atomic_write_text

            atomic_write_text(Path(a.json), json.dumps({"command": command, "machine": machine, "rows": lrows}, indent=1))
        publish(landmark_markdown(lrows, a.landmark_section, command, machine), a.write_docs)
        if a.skip_table and a.skip_ablation and a.skip_synthetic and a.skip_index:
            return 0
    reference = [("before the runs", reference_timing())]
    rows = [] if a.skip_table else run_table(data, out, a.frames, a.repeat)
    ablation = [] if a.skip_ablation else run_ablation(data, out, a.frames, a.repeat)
    synth = None if a.skip_synthetic else run_synthetic(out, a.synthetic_frames)
    index_rows = [] if a.skip_index else run_index_scaling(data)
    reference.append(("after them", reference_timing()))
    md = markdown(rows, synth, index_rows, command, ablation, a.repeat, reference)
    return publish(md, a.write_docs)


if __name__ == "__main__":
    raise SystemExit(main())
