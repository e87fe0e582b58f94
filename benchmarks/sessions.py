"""Saved maps and sessions: map a place in session 1, then localise in / extend that
map with session 2, against one run over both.

For every case:

* ``full``: one run over all frames (the reference);
* ``s1``: session 1 alone; it saves ``map.npz``;
* ``localize``: session 2 with ``--map s1 --localize``;
* ``extend``: session 2 with ``--map s1`` (the joined map is saved in its folder).

Reported: the ATE (RMSE, m) of session 1's trajectory followed by session 2's, with **one**
SE(3) alignment for both, against the full run's ATE (target: ratio <= 1.2); session 2's first
localised frame (target: within 10 frames of its start); frames left out as not localised;
load time (map file + descriptor index rebuilt) and size of session 1's map per 100 keyframes.

Also: the same alignment's errors over each session's poses alone, and what a fixed map allows
(session 1's own errors at the map keyframes session 2 is registered to, ``map_limit``).

Cases: fr1/rpy head200 (0-99 / 100-199, one TUM folder, ``dataset.first_frame`` /
``max_frames``); 7-Scenes redkitchen 0-149 / 150-299 (the 7-Scenes reader on the data set's own
folder; colour and depth are not registered in this data set); synthetic scenes where session 2
starts elsewhere: ``loop`` (phase 0) then ``loop`` (phase 0.5, the far side of the room), and
``loop`` then ``circle``; their reference run goes over both sequences one after the other (the
jump between them is a tracking loss, the run relocalises with the loop closer, like any run
after a loss).

    python -m benchmarks.sessions [--cases fr1_rpy,redkitchen,synth_half,synth_circle]
        [--work /tmp/rgbdslam_bench_sessions] [--json out.json] [--reuse] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DATA


# ----------------------------------------------------------------------------- sequences
def joined(a: Path, b: Path, out: Path) -> Path:
    """A TUM folder listing ``a``'s frames then ``b``'s (files linked, not copied)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        text = ""
        for src in (a, b):
            for line in (src / name).read_text().splitlines():
                if line.startswith("#") or not line.strip():
                    continue
                parts = line.split()
                if name != "groundtruth.txt":
                    parts[1] = str((src / parts[1]).resolve())
                text += " ".join(parts) + "\n"
        (out / name).write_text(text)
    (out / "camera.yaml").write_text((a / "camera.yaml").read_text())
    return out


def synth_pair(work: Path, second: str) -> tuple[Path, Path, Path]:
    from rgbdslam.datasets.synthetic import generate_sequence

    s1, s2 = work / "synth_loop", work / f"synth_{second}"
    if not (s1 / "groundtruth.txt").exists():
        generate_sequence(s1, frames=120, motion="loop", noise=True, seed=0)
    if not (s2 / "groundtruth.txt").exists():
        if second == "half":
            generate_sequence(s2, frames=120, motion="loop", noise=True, seed=0, phase=0.5, time_offset=100.0)
        else:
            generate_sequence(s2, frames=90, motion="circle", noise=True, seed=0, time_offset=100.0)
    return s1, s2, joined(s1, s2, work / f"synth_loop+{second}")


# ----------------------------------------------------------------------------- runs
REUSE = False  # --reuse: read finished run folders instead of running again (metrics only)
EXTRA: list[str] = []  # --set KEY=VALUE: config overrides of every run


def run(seq: Path, out: Path, config: str | None, overrides: list[str], **kw) -> dict:
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_sequence

    if REUSE and (out / "run.json").is_file():
        info = json.loads((out / "run.json").read_text())
        if info.get("status") == "finished":
            return info

    cfg = load_config(config, [*overrides, "mapping.enabled=false", "output.plots=false", *EXTRA])
    return run_sequence(seq, out, cfg, progress=False, **kw)


def groundtruth(seq: Path, config: str | None):
    """The sequence's ground truth as its reader gives it (TUM groundtruth.txt, 7-Scenes pose.txt files)."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence

    return open_sequence(seq, load_config(config, []).dataset).groundtruth()


def ate_of(gt, first: Path, second: Path) -> dict:
    """ATE (RMSE) of ``first`` then ``second`` with one SE(3) alignment, and the RMSE of that same
    alignment's errors over each session's poses alone."""
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import Trajectory, read_tum

    parts = [read_tum(first), read_tum(second)]
    stamps = np.concatenate([t.timestamps for t in parts])
    poses = np.concatenate([t.poses for t in parts])
    order = np.argsort(stamps, kind="stable")
    r = ate(gt, Trajectory(stamps[order], poses[order]))
    in_second = np.isin(r.aligned.timestamps, parts[1].timestamps)  # the estimate's stamps, as read
    rms = lambda e: float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan")  # noqa: E731
    return {"rmse": float(r.rmse), "pairs": int(r.n_pairs), "session1_rmse": rms(r.errors[~in_second]),
            "session2_rmse": rms(r.errors[in_second]), "session1_pairs": int(np.sum(~in_second)),
            "session2_pairs": int(np.sum(in_second))}


def _ate(gt, traj: Path) -> float:
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import read_tum

    return float(ate(gt, read_tum(traj)).rmse)


def load_cost(run_dir: Path, seq: Path, config: str | None, overrides: list[str]) -> dict:
    """Medians of 5: read + check map.npz (version, checksum, shapes, camera), then put it into a
    SLAM chain built beforehand (loop closer with the descriptor index rebuilt, pose graph)."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.session.sessions import open_map
    from rgbdslam.slam import SLAM

    cfg = load_config(config, overrides)
    camera = open_sequence(seq, cfg.dataset).camera
    read, attach = [], []
    for _ in range(5):
        slam = SLAM(cfg, camera)
        t0 = time.perf_counter()
        s = open_map(run_dir, camera, Path("/nonexistent-out"), localize=False)
        t1 = time.perf_counter()
        s.attach(slam)
        t2 = time.perf_counter()
        read.append(t1 - t0)
        attach.append(t2 - t1)
        slam.frontend.close()
    k = s.data.n_keyframes
    size = (run_dir / "map.npz").stat().st_size
    r, a = float(np.median(read)), float(np.median(attach))
    # the descriptor index alone, rebuilt keyframe by keyframe (as before) and in one pass, alternately
    from rgbdslam.loop.index import LshIndex

    desc, starts = s.data.arrays["feat_desc"], s.data.arrays["kf_feature_start"]
    one, bulk = [], []
    for _ in range(5):
        t0 = time.perf_counter()
        ix = LshIndex(cfg.loop.lsh_tables, cfg.loop.lsh_bits, cfg.loop.seed)
        for j in range(k):
            ix.add(j, desc[starts[j]:starts[j + 1]])
        t1 = time.perf_counter()
        LshIndex(cfg.loop.lsh_tables, cfg.loop.lsh_bits, cfg.loop.seed).add_many(desc, starts)
        t2 = time.perf_counter()
        one.append(t1 - t0)
        bulk.append(t2 - t1)
    return {"keyframes": k, "bytes": size, "read_s": r, "attach_s": a, "load_s": r + a,
            "mb_per_100_kf": size / 1e6 * 100 / k, "load_s_per_100_kf": (r + a) * 100 / k,
            "index_one_by_one_s": float(np.median(one)), "index_one_pass_s": float(np.median(bulk)),
            "index_entries": int(ix.size)}


def case(name: str, work: Path) -> dict:
    tum = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    if name == "fr1_rpy":
        full = s1 = s2 = tum
        config, n1 = "tum_fr1", 100
        o_full, o1, o2 = [], [f"dataset.max_frames={n1}"], [f"dataset.first_frame={n1}"]
    elif name == "redkitchen":  # the 7-Scenes reader on the data set's own folder
        full = s1 = s2 = DATA / "7scenes" / "frames_0000_0299"
        config, n1 = None, 150
        o_full, o1, o2 = [], [f"dataset.max_frames={n1}"], [f"dataset.first_frame={n1}"]
    else:
        s1, s2, full = synth_pair(work, name.split("_")[1])
        config, o_full, o1, o2 = None, [], [], []
    d = work / "runs" / name
    res: dict = {"case": name}
    t0 = time.perf_counter()
    sf = run(full, d / "full", config, o_full)
    gt = groundtruth(full, config)
    res["full"] = {"ate": _ate(gt, d / "full" / "trajectory.tum"),
                   "frames": sf["frames"], "restarts": sf["restarts"], "relocalized": sf["relocalized"]}
    a = run(s1, d / "s1", config, o1)
    res["s1"] = {"ate": a.get("evaluation", {}).get("ate", {}).get("rmse"), "frames": a["frames"],
                 "keyframes": len(a["keyframes"])}
    res["map"] = load_cost(d / "s1", s1, config, o1)
    for mode in ("localize", "extend"):
        s = run(s2, d / mode, config, o2, map_dir=d / "s1", localize=mode == "localize")
        # localising: session 1 as its run left it; extending: both sessions as the joined map has them
        first = d / "s1" / "trajectory.tum" if mode == "localize" else d / mode / "sessions" / "session_0.tum"
        second = d / mode / "trajectory.tum" if mode == "localize" else d / mode / "sessions" / "session_1.tum"
        j = ate_of(gt, first, second)
        ss = s["session"]
        res[mode] = {"ate_joint": j["rmse"], "pairs": j["pairs"], "ratio": j["rmse"] / res["full"]["ate"],
                     "joint_split": j,
                     "first_localized_frame": ss["first_localized_frame"],
                     "not_localized": sum(b - a + 1 for a, b in ss["not_localized"]), "frames": s["frames"],
                     "map_loops": len(s.get("map_loops", [])), "loops": len(s["loops"]),
                     "map_tracking": s.get("map_tracking"), "processing_fps": s.get("processing_fps"),
                     "keyframes": len(s["keyframes"]),
                     "session2_ate_own_alignment": s.get("evaluation", {}).get("ate", {}).get("rmse"),
                     "map_file": s.get("map_file")}
    res["localize"]["map_limit"] = map_limit(gt, d)
    # the full run's errors over the same two parts (its own alignment)
    res["full"]["split"] = _split(gt, d / "full" / "trajectory.tum", d / "localize" / "odometry.tum")
    res["seconds"] = time.perf_counter() - t0
    return res


def map_limit(gt, d: Path) -> dict:
    """What a fixed map allows: a localised pose is as good as the map keyframes it is registered
    to. Session 1's errors under its own alignment (the map's best fit to the ground truth), at
    the map keyframes of session 2's edges into the map (mean over each frame's edges, RMS over
    the frames with one), and the joint ATE if every session-2 pose had that error:
    sqrt((n1 e1² + n2 ea²) / (n1 + n2))."""
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import read_tum
    from rgbdslam.session.mapfile import load_map

    s1 = ate(gt, read_tum(d / "s1" / "trajectory.tum"))
    err = dict(zip(s1.aligned.timestamps, s1.errors))
    m = load_map(d / "s1" / "map.npz")
    kf_err = {int(f): err.get(t, np.nan) for f, t in zip(m.arrays["kf_frame"], m.arrays["kf_timestamp"])}
    info = json.loads((d / "localize" / "run.json").read_text())
    per: dict[int, list[float]] = {}
    for x in info.get("map_loops", []):
        per.setdefault(x["frame"], []).append(kf_err[x["map_frame"]])
    ea = np.array([np.nanmean(v) for v in per.values()])
    n1, n2 = int(s1.n_pairs), len(read_tum(d / "localize" / "trajectory.tum"))
    e_a = float(np.sqrt(np.nanmean(ea ** 2))) if len(ea) else float("nan")
    return {"session1_own": float(s1.rmse), "anchor_rmse": e_a, "frames_with_edges": len(per),
            "joint_limit": float(np.sqrt((n1 * s1.rmse ** 2 + n2 * e_a ** 2) / (n1 + n2)))}


def _split(gt, traj: Path, second: Path) -> dict:
    """RMSE of ``traj``'s ATE errors over the frames of session 1 and over those of session 2
    (``second``'s time stamps), one alignment for all."""
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import read_tum

    r = ate(gt, read_tum(traj))
    in_second = np.isin(r.aligned.timestamps, read_tum(second).timestamps)
    rms = lambda e: float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan")  # noqa: E731
    return {"session1_rmse": rms(r.errors[~in_second]), "session2_rmse": rms(r.errors[in_second])}


def table(rows: list[dict]) -> str:
    L = ["| case | full run ATE (s1 / s2 frames) | mode | joint ATE (one alignment) | s1 / s2 poses under it | ratio | "
         "first localised frame of session 2 | not localised | map loops |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        f = r["full"]
        for mode in ("localize", "extend"):
            m, j = r[mode], r[mode]["joint_split"]
            L.append(f"| {r['case']} | {f['ate']:.4f} ({f['split']['session1_rmse']:.4f} / "
                     f"{f['split']['session2_rmse']:.4f}) | {mode} | {m['ate_joint']:.4f} ({m['pairs']} poses) | "
                     f"{j['session1_rmse']:.4f} / {j['session2_rmse']:.4f} | {m['ratio']:.2f} | "
                     f"{m['first_localized_frame']} | {m['not_localized']} | {m['map_loops']} |")
    L += ["", "| case | session 1 alone (own alignment) | its error at the map keyframes session 2 is registered to "
          "| joint ATE if session 2 had that error | as a ratio of the full run | localised: joint ATE |",
          "|---|---|---|---|---|---|"]
    for r in rows:
        x = r["localize"]["map_limit"]
        L.append(f"| {r['case']} | {x['session1_own']:.4f} | {x['anchor_rmse']:.4f} ({x['frames_with_edges']} frames) | "
                 f"{x['joint_limit']:.4f} | {x['joint_limit'] / r['full']['ate']:.2f} | {r['localize']['ate_joint']:.4f} |")
    L += ["", "| case | session-1 map keyframes | map.npz | MB per 100 keyframes | read + check | into the chain "
          "(index rebuilt) | s per 100 keyframes | index: one by one / one pass |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["map"]
        L.append(f"| {r['case']} | {m['keyframes']} | {m['bytes'] / 1e6:.2f} MB | {m['mb_per_100_kf']:.2f} | "
                 f"{m['read_s'] * 1e3:.0f} ms | {m['attach_s'] * 1e3:.0f} ms | {m['load_s_per_100_kf']:.3f} | "
                 f"{m['index_one_by_one_s'] * 1e3:.0f} / {m['index_one_pass_s'] * 1e3:.0f} ms |")
    return "\n".join(L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="fr1_rpy,redkitchen,synth_half,synth_circle")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rgbdslam_bench_sessions"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--reuse", action="store_true", help="read finished run folders in --work instead of re-running")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override of every run")
    args = ap.parse_args()
    global REUSE, EXTRA
    REUSE, EXTRA = args.reuse, args.set
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.cases.split(","):
        rows.append(case(name, args.work))
        print(json.dumps(rows[-1], default=str), flush=True)
    print(f"\nmachine: {platform.machine()} {os.cpu_count()} cores (shared), Python {platform.python_version()}")
    print(table(rows))
    if args.json:
        from rgbdslam.io.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps(rows, indent=2, default=str))


if __name__ == "__main__":
    main()
