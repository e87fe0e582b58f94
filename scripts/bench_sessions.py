"""Saved maps and sessions (issue 19): map a place in session 1, then localise in / extend that
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

Cases: fr1/rpy head200 (0-99 / 100-199, one TUM folder, ``dataset.first_frame`` /
``max_frames``); 7-Scenes redkitchen 0-149 / 150-299 (converted once into a TUM-layout folder in
``--work``: colour as is, depth mm -> 1/5000 m PNG with 65535 -> 0, fx = fy = 585, cx 320,
cy 240, ground truth = pose.txt at 30 Hz; colour and depth are not registered in this data
set); synthetic scenes where session 2 starts elsewhere: ``loop`` (phase 0) then ``loop``
(phase 0.5, the far side of the room), and ``loop`` then ``circle``; their reference run goes
over both sequences one after the other (the jump between them is a tracking loss, the run
relocalises with the loop closer, like any run after a loss).

    .venv/bin/python scripts/bench_sessions.py [--cases fr1_rpy,redkitchen,synth_half,synth_circle]
        [--work /tmp/rgbdslam_bench_sessions] [--json out.json] [--reuse]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("RGBDSLAM_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))


# ----------------------------------------------------------------------------- sequences
def redkitchen_as_tum(work: Path) -> Path:
    """7-Scenes redkitchen 0-299 as a TUM folder in ``work`` (made once)."""
    import cv2

    src = DATA / "7scenes" / "frames_0000_0299"
    out = work / "redkitchen_tum"
    if (out / "groundtruth.txt").exists():
        return out
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    rgb, dep, gt = [], [], []
    for k in range(300):
        ts = 1000.0 + k / 30.0
        name = f"{ts:.6f}"
        d = cv2.imread(str(src / f"frame-{k:06d}.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        d[d >= 65535] = 0
        cv2.imwrite(str(out / "depth" / f"{name}.png"), np.clip(np.round(d * 5.0), 0, 65535).astype(np.uint16))
        (out / "rgb" / f"{name}.jpg").unlink(missing_ok=True)
        os.symlink(src / f"frame-{k:06d}.color.jpg", out / "rgb" / f"{name}.jpg")
        rgb.append(f"{name} rgb/{name}.jpg\n")
        dep.append(f"{name} depth/{name}.png\n")
        T = np.loadtxt(src / f"frame-{k:06d}.pose.txt")
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        gt.append(f"{name} {T[0, 3]:.6f} {T[1, 3]:.6f} {T[2, 3]:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}\n")
    (out / "rgb.txt").write_text("".join(rgb))
    (out / "depth.txt").write_text("".join(dep))
    (out / "camera.yaml").write_text("fx: 585.0\nfy: 585.0\ncx: 320.0\ncy: 240.0\nwidth: 640\nheight: 480\n"
                                     "dist: [0, 0, 0, 0, 0]\n")
    (out / "groundtruth.txt").write_text("".join(gt))
    return out


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


def run(seq: Path, out: Path, config: str | None, overrides: list[str], **kw) -> dict:
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_sequence

    if REUSE and (out / "run.json").is_file():
        info = json.loads((out / "run.json").read_text())
        if info.get("status") == "finished":
            return info

    cfg = load_config(config, [*overrides, "mapping.enabled=false", "output.plots=false"])
    return run_sequence(seq, out, cfg, progress=False, **kw)


def ate_of(gt_path: Path, *trajs: Path) -> tuple[float, int]:
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import Trajectory, read_tum

    parts = [read_tum(p) for p in trajs]
    stamps = np.concatenate([t.timestamps for t in parts])
    poses = np.concatenate([t.poses for t in parts])
    order = np.argsort(stamps, kind="stable")
    r = ate(read_tum(gt_path), Trajectory(stamps[order], poses[order]))
    return float(r.rmse), int(r.n_pairs)


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
    return {"keyframes": k, "bytes": size, "read_s": r, "attach_s": a, "load_s": r + a,
            "mb_per_100_kf": size / 1e6 * 100 / k, "load_s_per_100_kf": (r + a) * 100 / k}


def case(name: str, work: Path) -> dict:
    tum = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    if name == "fr1_rpy":
        full = s1 = s2 = tum
        config, n1 = "tum_fr1", 100
        o_full, o1, o2 = [], [f"dataset.max_frames={n1}"], [f"dataset.first_frame={n1}"]
    elif name == "redkitchen":
        full = s1 = s2 = redkitchen_as_tum(work)
        config, n1 = None, 150
        o_full, o1, o2 = [], [f"dataset.max_frames={n1}"], [f"dataset.first_frame={n1}"]
    else:
        s1, s2, full = synth_pair(work, name.split("_")[1])
        config, o_full, o1, o2 = None, [], [], []
    d = work / "runs" / name
    res: dict = {"case": name}
    t0 = time.perf_counter()
    sf = run(full, d / "full", config, o_full)
    res["full"] = {"ate": ate_of(full / "groundtruth.txt", d / "full" / "trajectory.tum")[0],
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
        ate, n = ate_of(full / "groundtruth.txt", first, second)
        ss = s["session"]
        res[mode] = {"ate_joint": ate, "pairs": n, "ratio": ate / res["full"]["ate"],
                     "first_localized_frame": ss["first_localized_frame"],
                     "not_localized": sum(b - a + 1 for a, b in ss["not_localized"]), "frames": s["frames"],
                     "map_loops": len(s.get("map_loops", [])), "loops": len(s["loops"]),
                     "session2_ate_own_alignment": s.get("evaluation", {}).get("ate", {}).get("rmse"),
                     "map_file": s.get("map_file")}
    res["seconds"] = time.perf_counter() - t0
    return res


def table(rows: list[dict]) -> str:
    L = ["| case | full run ATE | mode | joint ATE (one alignment) | ratio | first localised frame of session 2 | "
         "not localised | map loops |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for mode in ("localize", "extend"):
            m = r[mode]
            L.append(f"| {r['case']} | {r['full']['ate']:.4f} | {mode} | {m['ate_joint']:.4f} ({m['pairs']} poses) | "
                     f"{m['ratio']:.2f} | {m['first_localized_frame']} | {m['not_localized']} | {m['map_loops']} |")
    L += ["", "| case | session-1 map keyframes | map.npz | MB per 100 keyframes | read + check | into the chain "
          "(index rebuilt) | s per 100 keyframes |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["map"]
        L.append(f"| {r['case']} | {m['keyframes']} | {m['bytes'] / 1e6:.2f} MB | {m['mb_per_100_kf']:.2f} | "
                 f"{m['read_s'] * 1e3:.0f} ms | {m['attach_s'] * 1e3:.0f} ms | {m['load_s_per_100_kf']:.3f} |")
    return "\n".join(L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="fr1_rpy,redkitchen,synth_half,synth_circle")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rgbdslam_bench_sessions"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--reuse", action="store_true", help="read finished run folders in --work instead of re-running")
    args = ap.parse_args()
    global REUSE
    REUSE = args.reuse
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.cases.split(","):
        rows.append(case(name, args.work))
        print(json.dumps(rows[-1], default=str), flush=True)
    print(f"\nmachine: {platform.machine()} {os.cpu_count()} cores (shared), Python {platform.python_version()}")
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, default=str))


if __name__ == "__main__":
    main()
