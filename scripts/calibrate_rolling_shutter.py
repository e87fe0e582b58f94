"""Rolling-shutter readout time of an RGB-D camera from its own recording, without ground truth.

A rolling shutter reads the image rows one after the other; under rotation the rows read later see
the scene from a turned camera, and a yaw shears the image, which the registration takes partly for
a roll (``features.rolling_shutter``, docs/slam.md "Rolling shutter"). Its error does not average
out: the odometry's rotation drifts. Loop closures measure the same relative poses independently
of the chain of frames between them, so the readout that makes the odometry agree best with the
loop-closure edges is the estimate: for each candidate readout the whole pipeline runs
(``rgbdslam.pipeline.run_sequence``, map fusion off), and each loop edge of ``posegraph.g2o`` is
compared with the relative pose of its two keyframes in ``odometry.tum`` (before the pose graph).
Printed per readout: the median and RMS rotation (deg) and translation (mm) of those discrepancies.
The readout with the smallest median rotation discrepancy is the estimate. Ground truth is not
used (the ATE is printed for information only when the sequence has one).

What does *not* work as a criterion (measured on fr1/rpy, docs/benchmarks.md): the residuals of
consecutive frames' registrations (3-D or reprojected) — neighbouring frames share nearly the same
distortion, which the registration absorbs.

Usage::

    .venv/bin/python scripts/calibrate_rolling_shutter.py SEQUENCE [--readouts 0,0.01,...] [--work DIR]
        [--set K=V ...]

The same criterion for another camera parameter: ``--camera-key fx,fy --values 520,530,540`` writes a
copy of the camera file ``dataset.camera_file`` (``--set``) per value with those keys set to it
(e.g. the colour focal length of 7-Scenes' unregistered Kinect), ``--key CONFIG.KEY --values ...``
any config key.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.geometry.se3 import inv  # noqa: E402


def loop_discrepancies(run: Path) -> np.ndarray:
    """(K, 2): per loop edge of ``run``'s pose graph, the translation (m) and rotation (deg) between
    the edge's measured relative pose and the one of its keyframes in the run's odometry."""
    from rgbdslam.io.trajectory import read_tum
    from rgbdslam.posegraph.graph_io import read_graph

    g = read_graph(run / "posegraph.g2o")
    odo = read_tum(run / "odometry.tum")
    ids = [int(x) for x in g.ids]
    rank = {v: k for k, v in enumerate(sorted(ids))}
    out = []
    for k in range(g.n_edges):
        i, j = ids[g.edges_i[k]], ids[g.edges_j[k]]
        if abs(rank[i] - rank[j]) == 1:
            continue  # an odometry edge
        E = inv(inv(odo.poses[i]) @ odo.poses[j]) @ g.meas[k]
        out.append((np.linalg.norm(E[:3, 3]), np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))))
    return np.array(out).reshape(-1, 2)


def camera_variant(a, value: float, work: Path) -> Path:
    """A copy of the camera file of ``--set dataset.camera_file=...`` with ``--camera-key`` set to ``value``."""
    import yaml

    src = next((s.split("=", 1)[1] for s in a.set if s.startswith("dataset.camera_file=")), None)
    if src is None:
        raise SystemExit("--camera-key needs --set dataset.camera_file=FILE")
    data = yaml.safe_load(Path(src).read_text())
    for k in a.camera_key.split(","):
        data[k] = value
    out = work / f"camera_{value:g}.yaml"
    out.write_text(yaml.safe_dump(data))
    return out


def main(argv=None) -> int:
    from rgbdslam.pipeline import run_sequence

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--readouts", "--values", dest="values", default="0,0.005,0.01,0.015,0.02,0.025,0.03")
    ap.add_argument("--key", default="features.rolling_shutter", help="the config key the values are for")
    ap.add_argument("--camera-key", default=None, help="camera-file keys (comma-separated) the values are for")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="calibrate_rs_"))
    best = None
    work.mkdir(parents=True, exist_ok=True)
    what = a.camera_key or a.key
    for r in [float(x) for x in a.values.split(",")]:
        sets = [*a.set, f"{a.key}={r}"] if a.camera_key is None else [*a.set, f"dataset.camera_file={camera_variant(a, r, work)}"]
        cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *sets])
        s = run_sequence(a.sequence, work / f"value_{r:g}", cfg, progress=False)
        d = loop_discrepancies(work / f"value_{r:g}")
        ate = ((s.get("evaluation") or {}).get("ate") or {}).get("rmse")
        if len(d) == 0:
            print(f"{what} {r:g}: no loop closures; nothing to compare")
            continue
        med = float(np.median(d[:, 1]))
        print(f"{what} {r:g}: {len(d)} loop edges vs odometry: rotation median {med:.2f} deg, RMS "
              f"{np.sqrt(np.mean(d[:, 1] ** 2)):.2f} deg; translation median {1e3 * np.median(d[:, 0]):.1f} mm, RMS "
              f"{1e3 * np.sqrt(np.mean(d[:, 0] ** 2)):.1f} mm" + ("" if ate is None else f"   (ATE {ate:.4f} m, "
                                                                   f"evaluation only)"), flush=True)
        if best is None or med < best[1]:
            best = (r, med)
    if best is not None:
        print(f"smallest loop/odometry rotation discrepancy at {what} = {best[0]:g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
