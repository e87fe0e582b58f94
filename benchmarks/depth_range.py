"""Where a sequence's key points lie in depth, and which of them the chain can use.

Usage::

    python -m benchmarks.depth_range SEQ [--every 15] [--set SECTION.KEY=VALUE ...]

Every frame goes through the default chain (``SLAM.track``, the preset chosen from the layout as
``rgbdslam run`` does); every ``--every``-th frame prints its key points by the depth read at their
pixel — none (a hole), nearer than 1.5 m, 1.5 m to ``matching.max_depth``, beyond it — the number the
chain uses (``FrameFeatures.valid``: inside ``[matching.min_depth, matching.max_depth]``), and the
spread of the usable ones across the image (the standard deviation of their column, px). A scene whose
usable points all lie on one near object in a narrow part of the image cannot tell a sideways
translation from a rotation (docs/landmarks.md "Far points"). Writes nothing.
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv: list[str] | None = None) -> None:
    from rgbdslam.cli import sequence_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--every", type=int, default=15, help="print every n-th frame (default 15)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE")
    a = ap.parse_args(argv)
    cfg, _ = sequence_config(a.sequence, None, tuple(["mapping.enabled=false", *a.sets]))
    seq = open_sequence(a.sequence, cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    top = cfg.matching.max_depth
    print(f"frame  key points  no depth  <1.5 m  1.5-{top:g} m  >{top:g} m  used  used >1.5 m  column spread (px)")
    for i in range(len(seq)):
        frame = seq[i]
        res = slam.track(frame)
        if i % a.every or res.features is None:
            continue
        f = res.features
        h, w = frame.depth.shape[:2]
        u = np.clip(np.rint(f.uv_raw[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.rint(f.uv_raw[:, 1]).astype(int), 0, h - 1)
        z = np.nan_to_num(frame.depth[v, u].astype(np.float64))
        used = f.valid
        spread = float(np.std(f.uv_raw[used, 0])) if used.any() else float("nan")
        print(f"{i:5d}  {len(z):10d}  {int((z <= 0).sum()):8d}  {int(((z > 0) & (z < 1.5)).sum()):6d}  "
              f"{int(((z >= 1.5) & (z <= top)).sum()):{7 + len(f'{top:g}')}d}  {int((z > top).sum()):{4 + len(f'{top:g}')}d}  "
              f"{int(used.sum()):4d}  {int((used & (z >= 1.5)).sum()):11d}  {spread:18.0f}")


if __name__ == "__main__":
    main()
