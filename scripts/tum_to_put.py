#!/usr/bin/env python
"""Convert a TUM RGB-D folder into the POZNAN/PUT Kinect layout (for testing the PUT reader).

    python scripts/tum_to_put.py SRC_TUM_FOLDER DST_FOLDER [--max-frames N]

Writes rgb_%05d.png, depth_%05d.png (millimetres), matched, groundtruth.txt,
initialPosition and camera.yaml; see docs/formats.md.
"""

from __future__ import annotations

import argparse
import sys

from rgbdslam.datasets.put import convert_tum_to_put
from rgbdslam.errors import RgbdslamError


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", help="TUM sequence folder (rgb.txt, depth.txt, ...)")
    ap.add_argument("dst", help="new or empty output folder")
    ap.add_argument("--max-frames", type=int, default=None, help="convert only the first N associated frames")
    args = ap.parse_args(argv)
    try:
        out = convert_tum_to_put(args.src, args.dst, max_frames=args.max_frames)
    except RgbdslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
