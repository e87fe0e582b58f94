"""What the benchmarks share: data folders, rgbdslam and its peers on a sequence, metrics, tables, publishing.

* :func:`run_rgbdslam` takes every frame of a sequence through :class:`rgbdslam.slam.SLAM` (the
  chain ``rgbdslam run`` drives, without its reader thread, map and outputs), timing each frame,
  and :func:`run_pipeline` runs the whole command (:func:`rgbdslam.pipeline.run_sequence`) into a
  run folder.
* :func:`metrics` is ATE RMSE (SE(3) alignment), the Sim(3) scale correction and the 1-frame RPE,
  all from :mod:`rgbdslam.evaluation` (TUM association, 0.02 s).
* :func:`run_orbslam3` runs the ORB-SLAM3 peer (``pyorbslam3`` in a venv of its own,
  ``../shared/peers/orbslam3``) in a subprocess; :func:`open3d_odometry` Open3D's hybrid RGB-D
  odometry (frame to frame).
* :func:`markdown_table`, :func:`machine` and :func:`publish`: a table, the machine it ran on, and
  the table put into ``docs/benchmarks.md`` between ``<!-- benchmark:NAME -->`` and
  ``<!-- /benchmark:NAME -->`` with the exact command above it.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("RGBDSLAM_DATA", ROOT.parent / "shared" / "data"))
BENCHMARKS_MD = ROOT / "docs" / "benchmarks.md"
WORK = Path(os.environ.get("RGBDSLAM_BENCH_WORK", "/tmp/rgbdslam_benchmarks"))

# the development sequences (../shared/data/README.md)
FR1_RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
FR1_DESK9 = DATA / "tum" / "rgbd_dataset_freiburg1_desk_9frames"
FR3_TEDDY = DATA / "tum" / "rgbd_dataset_freiburg3_teddy_frames_0000_0119"
SEVENSCENES = DATA / "7scenes" / "frames_0000_0299"
KITTI06 = DATA / "kitti" / "odometry_06_head51"
LOOP_TYPE = ("loop", "circle", "figure8", "revisit")  # synthetic motions that return to where they began

# the ORB-SLAM3 peer (../shared/peers/orbslam3/README.md)
ORB_HOME = Path(os.environ.get("RGBDSLAM_ORBPEER", "/root/orbpeer"))
ORB_SCRIPTS = Path(os.environ.get("RGBDSLAM_ORBPEER_SCRIPTS", DATA.parent / "peers" / "orbslam3"))


# ----------------------------------------------------------------------------- metrics
@dataclass
class Metrics:
    """One trajectory against its ground truth; ``ms``: tracking time per frame (median)."""

    ate: float = float("nan")  # RMSE, metres, SE(3) alignment
    scale: float = float("nan")  # Sim(3) alignment's scale correction
    rpe: float = float("nan")  # 1-frame RPE, translation RMSE, metres
    frames: int = 0
    tracked: int = 0
    ms: float = float("nan")
    extra: dict = field(default_factory=dict)

    @property
    def lost(self) -> int:
        return self.frames - self.tracked


def metrics(gt, est, frames: int, ms: float = float("nan"), **extra) -> Metrics:
    """ATE (SE(3)), Sim(3) scale and 1-frame RPE of ``est`` against ``gt`` (rgbdslam.evaluation);
    ``tracked`` is the number of estimated poses."""
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.evaluation.rpe import rpe

    if est is None or len(est) < 3:
        return Metrics(frames=frames, tracked=0 if est is None else len(est), ms=ms, extra=extra)
    return Metrics(ate=ate(gt, est, align="se3").rmse, scale=ate(gt, est, align="sim3").scale,
                   rpe=rpe(gt, est, delta=1, delta_unit="f").trans.rmse, frames=frames, tracked=len(est), ms=ms,
                   extra=extra)


# ----------------------------------------------------------------------------- rgbdslam
def load_config(preset: str | None = None, sets: list[str] | tuple[str, ...] = (), camera: Path | None = None):
    """rgbdslam's config as ``rgbdslam run -c PRESET --camera CAMERA -s ...`` builds it (no map, no plots)."""
    from rgbdslam.config import load_config as load

    extra = [f"dataset.camera_file={camera}"] if camera is not None else []
    return load(preset, ["mapping.enabled=false", "output.plots=false", *extra, *sets])


def run_rgbdslam(path: Path, sets: list[str] | tuple[str, ...] = (), preset: str | None = None,
                 camera: Path | None = None):
    """Every frame of the sequence at ``path`` through :class:`rgbdslam.slam.SLAM`, then its final
    pose graph; returns ``(Metrics, trajectory)``. ``ms`` is the median time of one frame's
    ``SLAM.track`` (its key points found inside it, as ORB-SLAM3's ``track_rgbd`` does; for a
    stereo reader, which finds its key points while reading the pair, the pair's preparation counts
    too: from the decoded images, as ORB-SLAM3's runners decode before their timer starts)."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    cfg = load_config(preset, sets, camera)
    seq = open_sequence(path, cfg)
    slam = SLAM(cfg, seq.camera)
    with_reading = seq.own_key_points
    times = []
    for i in range(len(seq)):
        if with_reading:  # a stereo reader: the decoded pair, then its key points and depth inside the timer
            pair = seq.read_pair(i)
            t0 = time.perf_counter()
            frame = seq.frame_from_pair(i, *pair)
        else:
            frame = seq.load(i)
            t0 = time.perf_counter()
        slam.track(frame)
        times.append(time.perf_counter() - t0)
    est = slam.finish()
    gt = seq.groundtruth()
    m = metrics(gt, est, len(seq), 1e3 * float(np.median(times)))
    m.tracked = len(slam.state.records)
    return m, est


def sequence_view(seq, load):
    """``seq`` with its frames read through ``load(seq, i)`` (a :class:`rgbdslam.datasets.base.Sequence`
    that ``run_sequence`` takes in its place): a benchmark sees or changes each frame without
    patching the reader."""
    from rgbdslam.datasets.base import Sequence

    class View(Sequence):
        def __init__(self):
            self.name, self.root, self.camera, self.camera_setup = seq.name, seq.root, seq.camera, seq.camera_setup
            self.streaming, self.parallel_load, self.own_key_points = (seq.streaming, seq.parallel_load,
                                                                       seq.own_key_points)
            self.wrapped = seq

        def __getattr__(self, name):  # what a reader has beyond Sequence (rig, depth scale, ...)
            return getattr(seq, name)

        @property
        def timestamps(self):
            return seq.timestamps

        def groundtruth(self):
            return seq.groundtruth()

        def load(self, i: int):
            return load(seq, i)

    return View()


def run_pipeline(path: Path, out: Path, sets: list[str] | tuple[str, ...] = (), preset: str | None = None,
                 camera: Path | None = None) -> dict:
    """The whole ``rgbdslam run`` (map fusion and plots off) into ``out``; its run summary."""
    from rgbdslam.pipeline import run_sequence

    return run_sequence(path, out, load_config(preset, sets, camera), progress=False)


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME=section.key=value[,section.key=value...]`` -> ``(NAME, ["section.key=value", ...])``."""
    name, sep, rest = text.partition("=")
    if not name or not sep or "=" not in rest:
        raise SystemExit(f"--variant {text!r}: expected NAME=section.key=value[,section.key=value...]")
    return name, rest.split(",")


# ----------------------------------------------------------------------------- peers
def orbslam3_missing() -> str | None:
    """Why the ORB-SLAM3 peer cannot run here (None: it can)."""
    for p, what in [(ORB_HOME / "bin" / "python", "its venv"), (ORB_HOME / "voc.txt", "its vocabulary"),
                    (ORB_SCRIPTS / "run_orb.py", "its run scripts")]:
        if not p.exists():
            return f"ORB-SLAM3 peer not installed ({what}: {p} is missing; see ../shared/peers/orbslam3/README.md)"
    return None


def orb_settings(camera: str) -> Path:
    """The peer's settings file for a camera: ``fr1``, ``fr3`` (also rgbdslam's synthetic
    sequences), ``7scenes`` (its TUM conversion) or ``kitti`` (stereo, KITTI 04-12)."""
    return ORB_SCRIPTS / {"fr1": "TUM1_v1.yaml", "fr3": "TUM3_v1.yaml", "7scenes": "SEVEN_v1.yaml",
                          "kitti": "KITTI04-12_v1.yaml"}[camera]


def orb_settings_for_folder(seq_dir: Path, out: Path) -> Path:
    """A settings file for the peer on a sequence that carries its own pinhole ``camera.yaml``
    (rgbdslam's synthetic sequences: fx fy cx cy, no distortion, depth 5000 per metre): TUM3's
    settings with the folder's intrinsics, written to ``out``."""
    import yaml

    cam = yaml.safe_load((seq_dir / "camera.yaml").read_text())
    text = orb_settings("fr3").read_text()
    for key in ("fx", "fy", "cx", "cy"):
        text = re.sub(rf"^Camera1\.{key}: .*$", f"Camera1.{key}: {float(cam[key])}", text, flags=re.M)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out


def run_orbslam3(seq_dir: Path, camera: str | Path, out: Path, gt, stereo: bool = False) -> Metrics:
    """ORB-SLAM3 (RGB-D on a TUM-layout folder, paced at the recording's rate as a live camera; or
    stereo on a KITTI ``sequences/NN`` folder) on the same frames, in its own venv; its metrics
    against ``gt``. ``camera``: a key of :func:`orb_settings` or a settings file. ``ms``: its median
    ``track_rgbd`` / ``track_stereo`` time."""
    from rgbdslam.io.trajectory import read_tum

    out.mkdir(parents=True, exist_ok=True)
    script = ORB_SCRIPTS / ("run_orb_stereo.py" if stereo else "run_orb.py")
    cmd = [str(ORB_HOME / "bin" / "python"), str(script), str(seq_dir), str(out), "--vocab", str(ORB_HOME / "voc.txt"),
           "--settings", str(camera if isinstance(camera, Path) else orb_settings(camera))]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ORB_SCRIPTS)
    traj_file = out / "CameraTrajectory.txt"
    if proc.returncode != 0 or not traj_file.exists():
        tail = proc.stderr.strip().splitlines()[-3:]
        raise RuntimeError(f"ORB-SLAM3 failed on {seq_dir} (exit {proc.returncode}): {' | '.join(tail)}")
    if stereo:
        m = re.search(r"median ms ([\d.]+) frames (\d+)", proc.stderr)
        ms, frames = float(m.group(1)), int(m.group(2))
    else:
        summary = json.loads((out / "summary.json").read_text())
        ms, frames = summary["median_ms"], summary["frames"]
    est = read_tum(traj_file) if traj_file.stat().st_size else None
    return metrics(gt, est, frames, ms)


def open3d_trajectory(frames, camera):
    """Open3D's hybrid (photometric + geometric) RGB-D odometry, frame to frame, no loop closure, on
    loaded frames: ``(Trajectory, wall s per pair, CPU s per pair, failed pairs)``; a pair it fails
    on keeps the previous pose."""
    import open3d as o3d

    from rgbdslam.io.trajectory import Trajectory

    intr = o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
    opt = o3d.pipelines.odometry.OdometryOption()
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    prev, pose, poses, stamps, times, cpu, failed = None, np.eye(4), [], [], [], [], 0
    for f in frames:
        c0, t0 = time.process_time(), time.perf_counter()
        img = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(f.rgb)), o3d.geometry.Image(f.depth.astype(np.float32)),
            depth_scale=1.0, depth_trunc=4.0, convert_rgb_to_intensity=True)
        if prev is not None:
            ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(img, prev, intr, np.eye(4), jac, opt)
            failed += not ok
            pose = pose @ (T if ok else np.eye(4))
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        prev = img
        poses.append(pose.copy())
        stamps.append(f.timestamp)
    est = Trajectory(np.array(stamps), np.array(poses))
    return est, np.array(times), np.array(cpu), failed


def open3d_odometry(path: Path, camera: Path | None = None) -> Metrics:
    """:func:`open3d_trajectory` on the frames rgbdslam's reader gives (undistortion and depth
    registration as rgbdslam's), against the sequence's ground truth."""
    from rgbdslam.datasets import open_sequence

    seq = open_sequence(path, load_config(None, (), camera))
    est, times, _, failed = open3d_trajectory((seq.load(i) for i in range(len(seq))), seq.camera)
    m = metrics(seq.groundtruth(), est, len(seq), 1e3 * float(np.median(times)))
    m.tracked = len(seq) - failed
    return m


# ----------------------------------------------------------------------------- data conversions
def sevenscenes_as_tum(src: Path, dst: Path) -> Path:
    """7-Scenes frames (``frame-NNNNNN.color.jpg``, ``.depth.png`` in mm, 65535 = none,
    ``.pose.txt``) as a TUM-layout folder for the peer: colour linked, depth rewritten at 5000
    per metre (0 = none), stamps at 30 Hz, ``groundtruth.txt`` from the poses. Kept when done."""
    import cv2

    from rgbdslam.geometry.se3 import pose_to_tum

    if (dst / "groundtruth.txt").exists():
        return dst
    (dst / "rgb").mkdir(parents=True, exist_ok=True)
    (dst / "depth").mkdir(parents=True, exist_ok=True)
    colours = sorted(src.glob("frame-*.color.jpg"))
    rgb_lines, depth_lines, gt_lines = [], [], []
    for i, c in enumerate(colours):
        stem = c.name[: -len(".color.jpg")]
        t = f"{i / 30.0:.6f}"
        link = dst / "rgb" / f"{stem}.jpg"
        if not link.exists():
            link.symlink_to(c.resolve())
        d = cv2.imread(str(src / f"{stem}.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.uint32)
        d = np.where(d == 65535, 0, d * 5).clip(0, 65535).astype(np.uint16)
        cv2.imwrite(str(dst / "depth" / f"{stem}.png"), d)
        pos, q = (np.ravel(x) for x in pose_to_tum(np.loadtxt(src / f"{stem}.pose.txt")))
        rgb_lines.append(f"{t} rgb/{stem}.jpg")
        depth_lines.append(f"{t} depth/{stem}.png")
        gt_lines.append(t + " " + " ".join(f"{v:.7f}" for v in (*pos, *q)))
    (dst / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (dst / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (dst / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return dst


def synthetic_sequence(motion: str, seed: int, frames: int, work: Path = WORK) -> Path:
    """A synthetic RGB-D sequence (Kinect noise, TUM layout, the fr3 camera), rendered once into ``work``."""
    from rgbdslam.datasets.synthetic import generate_sequence

    d = work / "synthetic" / f"{motion}_s{seed}_{frames}"
    if not (d / "groundtruth.txt").exists():
        generate_sequence(d, frames=frames, motion=motion, noise=True, seed=seed)
    return d


# ----------------------------------------------------------------------------- tables and docs
def fmt(x, spec: str = "{:.4f}") -> str:
    """A number for a table; NaN / None as an en dash."""
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return spec.format(x)


def markdown_table(headers: list[str], rows: list[list[str]]) -> str:
    """A GitHub markdown table (cells already formatted)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def load_average() -> str:
    return ", ".join(f"{x:.1f}" for x in os.getloadavg())


def machine() -> str:
    """The machine and its load, for the line above a table."""
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load average {load_average()}")


def command_line(module: str, argv: list[str] | None = None) -> str:
    """The command that reproduces this run: ``python -m benchmarks.NAME ARGS``."""
    args = sys.argv[1:] if argv is None else argv
    return shlex.join(["python", "-m", module, *[a for a in args if a != "--write-docs"]])


def replace_block(text: str, name: str, block: str) -> str:
    """``text`` with the part between ``<!-- benchmark:NAME -->`` and ``<!-- /benchmark:NAME -->``
    replaced by ``block`` (markers kept); appended as a new block when the markers are absent."""
    begin, end = f"<!-- benchmark:{name} -->", f"<!-- /benchmark:{name} -->"
    inner = f"{begin}\n{block.strip()}\n{end}"
    i, j = text.find(begin), text.find(end)
    if i >= 0 and j > i:
        return text[:i] + inner + text[j + len(end):]
    if (i >= 0) != (j >= 0) or (i >= 0 and j < i):
        raise ValueError(f"docs: the markers of benchmark '{name}' are broken (one missing or out of order)")
    return text.rstrip("\n") + "\n\n" + inner + "\n"


def publish(name: str, table: str, command: str, machine_line: str, notes: str = "",
            path: Path = BENCHMARKS_MD, write: bool = False) -> str:
    """The block a benchmark publishes (the command and the machine above the table, ``notes``
    below); printed, and with ``write`` put into ``path`` between the benchmark's markers
    (written atomically, the rest of the page left alone)."""
    block = f"```bash\n{command.strip()}\n```\n\n{machine_line}\n\n{table.strip()}\n" + (f"\n{notes.strip()}\n" if notes else "")
    print(block)
    if write:
        from rgbdslam.io.atomic import atomic_write_text

        text = path.read_text() if path.exists() else "# Benchmarks\n"
        atomic_write_text(path, replace_block(text, name, block))
    return block


def publish_markdown(text: str, write: bool, name: str | None = None, path: Path = BENCHMARKS_MD) -> int:
    """A benchmark's whole markdown (its command and machine inside) printed, and with ``write`` put
    into ``path`` between the markers of ``name`` (default: the text's "## " heading as a slug);
    the heading itself stays the page's (it is not written into the block)."""
    print(text)
    lines = text.strip().splitlines()
    heading = lines[0].lstrip("#").strip() if lines and lines[0].startswith("#") else None
    name = name or re.sub(r"[^a-z0-9]+", "-", (heading or "benchmark").lower()).strip("-")
    if write:
        from rgbdslam.io.atomic import atomic_write_text

        body = "\n".join(lines[1:] if heading else lines)
        doc = path.read_text() if path.exists() else "# Benchmarks\n"
        atomic_write_text(path, replace_block(doc, name, body))
    return 0


def reference_timing(reps: int = 20) -> str:
    """A fixed workload timed on this machine now, printed next to a benchmark's numbers, so that
    runs on different days (the machines are shared and their speed varies) can be compared:
    ORB (1000 features) on a seeded 640x480 texture and a 1000x1000 Hamming matrix (NumPy)."""
    import cv2

    from rgbdslam.frontend.features import descriptor_words
    from rgbdslam.frontend.matching import hamming_matrix

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 1.5)
    orb = cv2.ORB_create(1000)
    words = descriptor_words(rng.integers(0, 256, (1000, 32), dtype=np.uint8))

    def median_ms(fn) -> float:
        fn()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return 1e3 * float(np.median(times))

    return (f"reference workload (median of {reps}): ORB on 640x480 {median_ms(lambda: orb.detectAndCompute(img, None)):.1f} ms, "
            f"1000x1000 Hamming matrix {median_ms(lambda: hamming_matrix(words, words)):.1f} ms")
