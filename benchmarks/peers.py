"""rgbdslam against ORB-SLAM3 and Open3D's RGB-D odometry, side by side on every development sequence.

Usage::

    python -m benchmarks.peers [--sequences rpy,teddy,7scenes,kitti,synthetic]
        [--seeds 0,1,2] [--motions loop,circle,figure8,revisit] [--frames 150] [--rounds 2]
        [--variant NAME=section.key=value[,...]] ... [--no-orb] [--no-open3d] [--json FILE] [--write-docs]

In one run, on each selected sequence:

* rgbdslam's default configuration (and each ``--variant``), every frame through its SLAM chain
  (:func:`benchmarks.common.run_rgbdslam`): fr1/rpy head200 and fr3/teddy frames 0-119 as found;
  7-Scenes frames 0-299 through its reader (``7scenes``, the 7-Scenes camera rgbdslam ships); KITTI 06 frames 0-50 stereo with ``-c kitti``;
  synthetic sequences (``--seeds`` x ``--motions``, Kinect noise, fr3 camera);
* ORB-SLAM3 (RGB-D, or stereo on KITTI) on the same frames: TUM1 settings on fr1, TUM3 on fr3,
  TUM3 with the sequence's own intrinsics (its camera.yaml) on the synthetic ones, SEVEN on
  7-Scenes' TUM conversion (written to the work folder), KITTI04-12;
  skipped with a message when ``/root/orbpeer`` is absent;
* Open3D's hybrid RGB-D odometry on the RGB-D sequences (frame to frame, once).

rgbdslam and ORB-SLAM3 run in ``--rounds`` interleaved rounds (A B A B ...), so a change of the
machine's load hits both alike: rgbdslam's accuracy is deterministic (the rounds must agree),
ORB-SLAM3's varies (each round is a run of its own, all listed). One table: ATE RMSE (SE(3)),
Sim(3) scale, 1-frame RPE, tracked / lost frames, tracking ms per frame (median over the frames,
then over the rounds), and the ratios to ORB-SLAM3 (ATE: rgbdslam ÷ ORB-SLAM3's median, < 1
better; rate: ORB-SLAM3's ms ÷ rgbdslam's, > 1 faster); then the median ratio over all sequences
and the worst one, per configuration.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from benchmarks import common
from benchmarks.common import Metrics, fmt

ORB = "ORB-SLAM3"
OPEN3D = "Open3D hybrid odometry"
SEQUENCE_KEYS = ("rpy", "teddy", "7scenes", "kitti", "synthetic")


@dataclass
class Case:
    """One sequence of the comparison: how rgbdslam and the peers read it."""

    name: str
    path: Path
    preset: str | None = None  # rgbdslam -c
    camera: Path | None = None  # rgbdslam --camera
    orb_camera: str | None = None  # common.orb_settings key, "synthetic" (the folder's camera.yaml); None: none
    orb_input: Path | None = None  # TUM-layout folder (RGB-D) or KITTI sequences/NN (stereo)
    stereo: bool = False
    open3d: bool = True


@dataclass
class Row:
    """One method on one sequence: a Metrics per run (rounds for rgbdslam and ORB-SLAM3)."""

    sequence: str
    method: str
    runs: list[Metrics] = field(default_factory=list)

    def value(self, attr: str) -> float:
        """Median over the runs (NaN when none has it)."""
        v = [getattr(m, attr) for m in self.runs]
        v = [x for x in v if x is not None and np.isfinite(x)]
        return float(np.median(v)) if v else float("nan")


def cases(keys: list[str], seeds: list[int], motions: list[str], frames: int, work: Path) -> list[Case]:
    """The selected development sequences (those whose data is here)."""
    out = []
    for key in keys:
        if key == "rpy":
            out.append(Case("fr1/rpy head200", common.FR1_RPY, orb_camera="fr1", orb_input=common.FR1_RPY))
        elif key == "desk9":  # a quick check (the tests)
            out.append(Case("fr1/desk 9 frames", common.FR1_DESK9, orb_camera="fr1", orb_input=common.FR1_DESK9))
        elif key == "teddy":
            out.append(Case("fr3/teddy 0-119", common.FR3_TEDDY, orb_camera="fr3", orb_input=common.FR3_TEDDY))
        elif key == "7scenes":  # its reader, with the 7-Scenes camera rgbdslam ships (its default there)
            out.append(Case("7-Scenes 0-299", common.SEVENSCENES, orb_camera="7scenes",
                            orb_input=work / "7scenes_tum"))
        elif key == "kitti":
            out.append(Case("KITTI 06 0-50 stereo", common.KITTI06, preset="kitti", orb_camera="kitti",
                            orb_input=common.KITTI06 / "sequences" / "06", stereo=True, open3d=False))
        elif key == "synthetic":
            for motion in motions:
                for seed in seeds:
                    d = work / "synthetic" / f"{motion}_s{seed}_{frames}"
                    out.append(Case(f"synthetic {motion} seed {seed}", d, orb_camera="synthetic", orb_input=d))
        else:
            raise SystemExit(f"--sequences: unknown '{key}'; choose from {', '.join(SEQUENCE_KEYS)}")
    return [c for c in out if c.path.exists() or c.name.startswith("synthetic")]


def prepare(case: Case, frames: int) -> None:
    """Render a synthetic sequence / convert 7-Scenes for the peer, when not done yet."""
    if case.name.startswith("synthetic"):
        motion, seed = case.path.name.split("_s")[0], int(case.path.name.split("_s")[1].split("_")[0])
        common.synthetic_sequence(motion, seed, frames, case.path.parent.parent)
    if case.orb_camera == "7scenes":
        common.sevenscenes_as_tum(case.path, case.orb_input)


def run_case(case: Case, variants: dict[str, list[str]], rounds: int, orb: bool, open3d: bool, work: Path,
             log=print) -> list[Row]:
    """rgbdslam's variants and ORB-SLAM3 in ``rounds`` interleaved rounds, then Open3D once."""
    from rgbdslam.datasets import open_sequence

    rows = {name: Row(case.name, name) for name in variants}
    if orb and case.orb_camera:
        rows[ORB] = Row(case.name, ORB)
    gt = open_sequence(case.path, common.load_config(case.preset, (), case.camera)).groundtruth()
    for r in range(rounds):
        for name, sets in variants.items():
            m, _ = common.run_rgbdslam(case.path, sets, case.preset, case.camera)
            rows[name].runs.append(m)
            log(f"{case.name:38s} {name:22s} round {r + 1}: ATE {m.ate:.4f} scale {m.scale:.3f} "
                f"RPE {1e3 * m.rpe:.2f} mm  {m.ms:6.1f} ms/frame  lost {m.lost}")
        if ORB in rows:
            settings = case.orb_camera if case.orb_camera != "synthetic" else \
                common.orb_settings_for_folder(case.orb_input, work / "orb" / f"{slug(case.name)}.yaml")
            try:
                m = common.run_orbslam3(case.orb_input, settings, work / "orb" / f"{slug(case.name)}_{r}", gt,
                                        stereo=case.stereo)
            except RuntimeError as e:
                log(f"{case.name:38s} {ORB:22s} round {r + 1}: {e}")
                m = Metrics()
            rows[ORB].runs.append(m)
            log(f"{case.name:38s} {ORB:22s} round {r + 1}: ATE {m.ate:.4f} scale {m.scale:.3f} "
                f"RPE {1e3 * m.rpe:.2f} mm  {m.ms:6.1f} ms/frame  lost {m.lost}")
    if open3d and case.open3d:
        m = common.open3d_odometry(case.path, case.camera)
        rows[OPEN3D] = Row(case.name, OPEN3D, [m])
        log(f"{case.name:38s} {OPEN3D:22s}: ATE {m.ate:.4f} scale {m.scale:.3f} RPE {1e3 * m.rpe:.2f} mm  "
            f"{m.ms:6.1f} ms/frame")
    return list(rows.values())


def slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_")


# ----------------------------------------------------------------------------- the table
def ratios(rows: list[Row]) -> dict[str, dict[str, tuple[float, float]]]:
    """``{method: {sequence: (ATE ratio, rate ratio)}}`` for every rgbdslam method on every
    sequence with ORB-SLAM3 results: ATE ÷ ORB-SLAM3's median ATE; ORB-SLAM3's median ms ÷ its ms."""
    orb = {r.sequence: r for r in rows if r.method == ORB}
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for r in rows:
        if r.method in (ORB, OPEN3D) or r.sequence not in orb:
            continue
        o = orb[r.sequence]
        out.setdefault(r.method, {})[r.sequence] = (r.value("ate") / o.value("ate"), o.value("ms") / r.value("ms"))
    return out


def summarise(per_sequence: dict[str, tuple[float, float]]) -> dict[str, tuple[float, str, float]]:
    """Per ratio (``ate``, ``rate``): (median over the sequences, the worst sequence, its ratio);
    worst = highest ATE ratio, lowest rate ratio. Sequences with a NaN ratio are left out."""
    out = {}
    for k, (key, worst) in enumerate([("ate", max), ("rate", min)]):
        vals = {s: v[k] for s, v in per_sequence.items() if np.isfinite(v[k])}
        if not vals:
            continue
        name = worst(vals, key=vals.get)
        out[key] = (float(np.median(list(vals.values()))), name, vals[name])
    return out


def _list(row: Row, attr: str, spec: str, scale: float = 1.0) -> str:
    """One value per run when they differ (ORB-SLAM3), else the one value."""
    vals = [getattr(m, attr) for m in row.runs]
    cells = [fmt(None if v is None or not np.isfinite(v) else v * scale, spec) for v in vals]
    return cells[0] if len(set(cells)) == 1 else " / ".join(cells)


def markdown(rows: list[Row]) -> str:
    """The comparison table (rows grouped by sequence, in the order the sequences first appear),
    then the median and worst ratios per rgbdslam configuration."""
    first = {}
    for k, r in enumerate(rows):
        first.setdefault(r.sequence, k)
    rows = sorted(rows, key=lambda r: first[r.sequence])
    rat = ratios(rows)
    table = []
    for r in rows:
        ar, rr = rat.get(r.method, {}).get(r.sequence, (float("nan"), float("nan")))
        tracked = " / ".join(sorted({f"{m.tracked}/{m.lost}" for m in r.runs}))
        table.append([r.sequence, r.method, _list(r, "ate", "{:.4f}"), _list(r, "scale", "{:.3f}"),
                      _list(r, "rpe", "{:.2f}", 1e3), tracked, fmt(r.value("ms"), "{:.1f}"),
                      fmt(ar, "{:.2f}"), fmt(rr, "{:.2f}")])
    text = common.markdown_table(
        ["sequence", "method", "ATE RMSE (m)", "Sim(3) scale", "RPE 1 frame (mm)", "tracked/lost", "ms/frame",
         "ATE ÷ ORB-SLAM3", "rate × ORB-SLAM3"], table)
    lines = []
    for method, per in rat.items():
        groups = {"": per}
        real = {q: v for q, v in per.items() if not q.startswith("synthetic")}
        if real and len(real) < len(per):  # the real sequences and the synthetic ones on their own too
            groups.update({"real ": real, "synthetic ": {q: v for q, v in per.items() if q not in real}})
        for label, group in groups.items():
            s = summarise(group)
            if "ate" not in s:
                continue
            line = (f"- **{method}** over {len(group)} {label}sequences: ATE ÷ ORB-SLAM3 median **{s['ate'][0]:.2f}**, "
                    f"worst {s['ate'][2]:.2f} ({s['ate'][1]})")
            if "rate" in s:
                line += f"; rate × ORB-SLAM3 median {s['rate'][0]:.2f}, worst {s['rate'][2]:.2f} ({s['rate'][1]})"
            lines.append(line if not label else "  " + line)
    return text + ("\n\n" + "\n".join(lines) if lines else "")


def to_json(rows: list[Row]) -> list[dict]:
    return [{"sequence": r.sequence, "method": r.method, "runs": [asdict(m) for m in r.runs]} for r in rows]


def from_json(data: list[dict]) -> list[Row]:
    return [Row(d["sequence"], d["method"], [Metrics(**m) for m in d["runs"]]) for d in data]


NOTES = """ATE RMSE with SE(3) alignment and the Sim(3) scale correction (evo's `-as`), 1-frame RPE
(translation RMSE), all through `rgbdslam.evaluation` (TUM association, 0.02 s). rgbdslam: every
frame through `rgbdslam.slam.SLAM` and its final pose graph, as `rgbdslam run` (no map); its ms are
the median `SLAM.track` per frame with its key points found inside it (on KITTI the preparation of the
decoded pair too, where the stereo reader finds both images' key points, at once in two threads as
ORB-SLAM3 does; both runners decode the images before their timer starts). ORB-SLAM3: `../shared/peers/orbslam3/run_orb.py`
(paced at the recording's rate) / `run_orb_stereo.py`, a vocabulary built from fr1/rpy, its median
`track_rgbd` / `track_stereo`; one value per run where its runs differ. Open3D: hybrid RGB-D odometry
frame to frame on rgbdslam's frames (undistorted, registered), no loop closure. Ratios: ATE ÷
ORB-SLAM3's median ATE (< 1 better); rate × = ORB-SLAM3's ms ÷ rgbdslam's (> 1 faster). The speed
columns come from a shared machine whose load varies: read them as a ratio measured in the same
rounds, not as rates."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequences", default=",".join(SEQUENCE_KEYS),
                    help=f"comma list of {', '.join(SEQUENCE_KEYS)} (desk9: a 9-frame check)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--motions", default=",".join(common.LOOP_TYPE))
    ap.add_argument("--frames", type=int, default=150, help="frames per synthetic sequence")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds of rgbdslam and ORB-SLAM3")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=section.key=value[,...]",
                    help="another rgbdslam configuration beside the default (repeatable)")
    ap.add_argument("--no-orb", action="store_true")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--open3d-only", action="store_true",
                    help="only Open3D's odometry (its rows join another run's with --report)")
    ap.add_argument("--work", type=Path, default=common.WORK / "peers")
    ap.add_argument("--json", type=Path, help="write every run's numbers here")
    ap.add_argument("--report", type=Path, nargs="+", help="only build the table from earlier --json files "
                    "(several runs' rows joined, e.g. the real and the synthetic sequences run at the same time)")
    ap.add_argument("--write-docs", action="store_true", help="put the table into docs/benchmarks.md")
    a = ap.parse_args(argv)
    command = common.command_line("benchmarks.peers", argv)
    if a.report:
        data = [json.loads(p.read_text()) for p in a.report]
        return _publish([r for d in data for r in from_json(d["rows"])], "\n".join(d["command"] for d in data),
                        joined_machine([d["machine"] for d in data]), a.write_docs)
    orb = not a.no_orb
    if orb and (why := common.orbslam3_missing()):
        print(f"{why}: ORB-SLAM3 left out", file=sys.stderr)
        orb = False
    variants = {} if a.open3d_only else {"rgbdslam default": []}
    variants.update({} if a.open3d_only else dict(common.parse_variant(v) for v in a.variant))
    orb = orb and not a.open3d_only
    machine_before = common.machine()
    rows: list[Row] = []
    for case in cases(a.sequences.split(","), [int(s) for s in a.seeds.split(",")], a.motions.split(","), a.frames,
                      a.work):
        prepare(case, a.frames)
        rows += run_case(case, variants, a.rounds, orb, not a.no_open3d, a.work)
        machine = f"{machine_before} before, {common.load_average()} after"
        if a.json:  # after every sequence: a run cut short keeps what it measured
            from rgbdslam.io.atomic import atomic_write_text

            a.json.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(a.json, json.dumps({"command": command, "machine": machine, "rows": to_json(rows)}, indent=1))
    return _publish(rows, command, f"{machine_before} before, {common.load_average()} after", a.write_docs)


def joined_machine(lines: list[str]) -> str:
    """Several runs' machine lines (``common.machine()`` + the load after) as one: the machine, the
    first start, and the range of the 1-minute load averages they saw."""
    if len(set(lines)) == 1:
        return lines[0]
    loads = [float(x) for ln in lines for x in re.findall(r"(?:load average |, |after, |before, )?(\d+\.\d), \d+\.\d, \d+\.\d", ln)]
    head = min(lines).split(", load average")[0]
    return f"{head} (the first of {len(lines)} runs at the same time); 1-minute load average {min(loads):.0f}–{max(loads):.0f}"


def _publish(rows: list[Row], command: str, machine: str, write: bool) -> int:
    common.publish("peers", markdown(rows), command, machine, NOTES, write=write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
