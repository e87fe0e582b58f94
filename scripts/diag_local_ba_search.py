"""Exact-ground-truth audit of the local BA with the keyframe projection search (synthetic sequences).

Usage::

    python scripts/diag_local_ba_search.py SEQ [--set KEY=VALUE ...]

Runs the landmark map with ``landmarks.local_ba=true`` on SEQ (a synthetic sequence: exact ground
truth) and, at every local BA, solves the same problem four ways: as run; with the held keyframes
at their true poses (relative to the newest held one); without the landmark priors; both. Prints
the median error (mm) of the window's moved keyframes relative to the newest held keyframe before
the solve and after each, the median observations per moved keyframe and landmarks per solve. The
run itself goes on with the BA as configured (the audit solves are not written back).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from rgbdslam.config import load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.local_ba import LocalBA, make_problem, solve_problem
from rgbdslam.slam import SLAM


class AuditBA(LocalBA):
    """The local BA that also solves each problem with true held poses / without priors (not applied)."""

    def __init__(self, cfg, camera, gt):
        super().__init__(cfg, camera)
        self.gt = gt
        self.rows = {k: [] for k in ("before", "as_run", "held_true", "no_prior", "held_true_no_prior")}
        self.n_obs, self.n_lm = [], []

    def _err(self, P, ref, k):
        G = inv(self.gt[ref]) @ self.gt[k]
        E = inv(P[ref]) @ P[k]
        return 1e3 * float(np.linalg.norm(G[:3, 3] - E[:3, 3]))

    def run(self, lmap, keyframes, kf_pose):
        p = make_problem(self.cfg, lmap, keyframes, kf_pose)
        if p is not None and p.fixed:
            ref, moved = max(p.fixed), sorted(p.window - p.fixed)
            self.rows["before"] += [self._err(p.poses, ref, k) for k in moved]
            nobs = {o[0]: len(o[1]) for o in p.obs}
            self.n_obs += [nobs.get(k, 0) for k in moved]
            self.n_lm.append(len(p.use))
            A = p.poses[ref] @ inv(self.gt[ref])
            held = replace(p, poses={k: (A @ self.gt[k] if k in p.fixed else P) for k, P in p.poses.items()})
            no_prior = replace(self.cfg, ba_landmark_prior=False)
            for name, prob, c in (("as_run", p, self.cfg), ("held_true", held, self.cfg), ("no_prior", p, no_prior),
                                  ("held_true_no_prior", held, no_prior)):
                res = solve_problem(c, self.factors, prob)
                if res is not None and res.poses:
                    after = {**prob.poses, **res.poses}
                    self.rows[name] += [self._err(after, ref, k) for k in moved]
        return super().run(lmap, keyframes, kf_pose)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    cfg = load_config(None, ["landmarks.enabled=true", "landmarks.local_ba=true", "mapping.enabled=false", *a.set])
    seq = open_sequence(a.sequence, cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    audit = AuditBA(cfg.landmarks, seq.camera, seq.groundtruth().poses)
    slam.landmarks.ba = audit
    for i in range(len(seq)):
        slam.track(seq[i])
    out = {k: round(float(np.median(v)), 3) for k, v in audit.rows.items() if v}
    out.update(solves=len(audit.n_lm), obs_per_keyframe=float(np.median(audit.n_obs)),
               landmarks=float(np.median(audit.n_lm)))
    print(json.dumps({"sequence": a.sequence, **out}))


if __name__ == "__main__":
    main()
