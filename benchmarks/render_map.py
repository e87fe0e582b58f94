"""Render a run's fused map to PNG without a display, for the docs (rgbdslam.viz.render; the
same pictures as `rgbdslam fuse --render`, here into another folder with a name prefix, and the
2-D map preview copied beside them).

    python -m benchmarks.render_map RUN_DIR --out docs/ [--prefix rpy200_] [--width 640]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from rgbdslam.errors import RgbdslamError
from rgbdslam.viz.render import render_run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--prefix", default="")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--back", type=float, default=1.0, help="metres behind the cameras' mean position")
    ap.add_argument("--lift", type=float, default=0.8, help="metres above it")
    a = ap.parse_args(argv)
    try:
        written = render_run(a.run_dir, a.out, a.prefix, a.width, a.back, a.lift)
    except RgbdslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    preview = a.run_dir / "map" / "map2d_preview.png"
    if preview.is_file():
        written.append(a.out / f"{a.prefix}map2d_preview.png")
        shutil.copyfile(preview, written[-1])
    for p in written:
        print(f"{p}  ({p.stat().st_size // 1024} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
