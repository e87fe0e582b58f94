"""The 2-D top view of the landmark map (the thesis' own map): landmarks seen from above.

Drawn with OpenCV into a NumPy image (no matplotlib: importing it and drawing one figure cost the
run ~0.8 s of CPU after the last frame, docs/benchmarks.md "Landmark map speed: the top view without
matplotlib, refine and BA options"): each landmark one 2x2 px dot coloured by log2(times seen)
(viridis), the keyframe path in red, axes with metre ticks, a colour bar, the title with the count.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

SIZE = 770  # px, square image (7 in at 110 dpi, as the matplotlib figure it replaces)
MARGIN = (70, 40, 130, 60)  # px: left, top, right (colour bar), bottom
RED = (40, 39, 214)  # BGR of matplotlib's tab:red
FONT = cv2.FONT_HERSHEY_SIMPLEX


def up_axis(poses: list[np.ndarray]) -> int:
    """The world axis the cameras' y axes (image down) point along most: the vertical one."""
    if not poses:
        return 1
    down = np.mean([P[:3, 1] for P in poses], axis=0)
    return int(np.argmax(np.abs(down)))


def nice_step(span: float, ticks: int = 6) -> float:
    """A tick spacing of 1, 2 or 5 × 10^k giving at most ~``ticks`` intervals over ``span`` (> 0)."""
    raw = span / ticks
    k = 10.0 ** np.floor(np.log10(raw))
    return float(next(m * k for m in (1.0, 2.0, 5.0, 10.0) if m * k >= raw))


def viridis(values: np.ndarray) -> np.ndarray:
    """BGR colours (N, 3) uint8 of ``values`` in [0, 1] (OpenCV's viridis map, 256 steps)."""
    idx = np.clip(np.round(np.asarray(values, float) * 255), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(idx.reshape(-1, 1), cv2.COLORMAP_VIRIDIS).reshape(-1, 3)


class _Frame:
    """World (a, b) metres -> image pixels (column, row) of the plot area, equal scale on both axes."""

    def __init__(self, pts: np.ndarray):
        left, top, right, bottom = MARGIN
        self.w, self.h = SIZE - left - right, SIZE - top - bottom
        lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(2), np.ones(2))
        span = np.maximum(hi - lo, 1e-3)
        lo, hi = lo - 0.05 * span, hi + 0.05 * span
        self.scale = min(self.w / (hi[0] - lo[0]), self.h / (hi[1] - lo[1]))  # px per metre
        centre = (lo + hi) / 2
        self.lo = centre - np.array([self.w, self.h]) / (2 * self.scale)  # world at the area's lower left
        self.hi = self.lo + np.array([self.w, self.h]) / self.scale
        self.left, self.top = left, top

    def px(self, ab: np.ndarray) -> np.ndarray:
        """Float pixel coordinates (N, 2) of world points (N, 2); b grows upwards."""
        col = self.left + (ab[:, 0] - self.lo[0]) * self.scale
        row = self.top + self.h - (ab[:, 1] - self.lo[1]) * self.scale
        return np.stack([col, row], axis=1)


def _text(img, s: str, org, scale: float = 0.45, align: str = "left") -> None:
    (tw, th), _ = cv2.getTextSize(s, FONT, scale, 1)
    x = org[0] - (tw if align == "right" else tw // 2 if align == "centre" else 0)
    cv2.putText(img, s, (int(x), int(org[1] + th // 2)), FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def _fmt(v: float, step: float) -> str:
    digits = max(0, int(-np.floor(np.log10(step) + 1e-9)))
    return f"{0.0 if abs(v) < 1e-6 * step else v:.{digits}f}"  # no "-0.0" from a rounded zero tick


def render_top_view(pos: np.ndarray, seen: np.ndarray, kf_poses: list[np.ndarray],
                    title: str = "landmarks (top view)") -> np.ndarray:
    """The top view as a BGR image (SIZE x SIZE): landmarks ``pos`` (N, 3) projected onto the
    horizontal plane (the axis the cameras' image-down direction is closest to is dropped), coloured
    by how often each was seen (``seen``), with the keyframe positions as a red path."""
    up = up_axis(kf_poses)
    ax_i = [k for k in range(3) if k != up]
    pos = np.asarray(pos, float).reshape(-1, 3)
    ok = np.isfinite(pos).all(axis=1)  # a non-finite landmark is not drawn (it would break the axes)
    pos, seen = pos[ok], np.asarray(seen).reshape(-1)[ok]
    C = np.array([P[:3, 3] for P in kf_poses]).reshape(-1, 3)
    C = C[np.isfinite(C).all(axis=1)]
    ab, kab = pos[:, ax_i], C[:, ax_i]
    fr = _Frame(np.concatenate([ab, kab]))
    img = np.full((SIZE, SIZE, 3), 255, np.uint8)
    left, top = fr.left, fr.top
    # ticks and grid labels (metres), then the data, then the frame on top
    for axis in (0, 1):
        step = nice_step(fr.hi[axis] - fr.lo[axis])
        for v in np.arange(np.ceil(fr.lo[axis] / step) * step, fr.hi[axis] + 1e-12, step):
            p = fr.px(np.array([[v, fr.lo[1]]] if axis == 0 else [[fr.lo[0], v]]))[0]
            if axis == 0:
                x = int(round(p[0]))
                cv2.line(img, (x, top + fr.h), (x, top + fr.h + 5), (0, 0, 0), 1)
                _text(img, _fmt(v, step), (x, top + fr.h + 16), align="centre")
            else:
                y = int(round(p[1]))
                cv2.line(img, (left - 5, y), (left, y), (0, 0, 0), 1)
                _text(img, _fmt(v, step), (left - 8, y), align="right")
    vmax = 1.0
    if len(pos):
        c = np.log2(np.maximum(np.asarray(seen, float), 1.0))
        vmax = max(float(c.max()), 1e-9)
        uv = np.floor(fr.px(ab)).astype(np.int64)
        col = viridis(c / vmax)
        for du in (0, 1):  # 2x2 px dots, later landmarks over earlier ones
            for dv in (0, 1):
                u, v = uv[:, 0] + du, uv[:, 1] + dv
                ok = (u >= left) & (u < left + fr.w) & (v >= top) & (v < top + fr.h)
                img[v[ok], u[ok]] = col[ok]
    if len(kab):
        pts = np.round(fr.px(kab) * 16).astype(np.int32)  # 4 fractional bits
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, RED, 1, cv2.LINE_AA, shift=4)
        lx, ly = left + fr.w - 110, top + 14  # legend
        cv2.line(img, (lx, ly), (lx + 25, ly), RED, 2, cv2.LINE_AA)
        _text(img, "keyframes", (lx + 32, ly))
    cv2.rectangle(img, (left, top), (left + fr.w, top + fr.h), (0, 0, 0), 1)
    # colour bar: log2(times seen) from 0 (bottom) to the largest (top)
    bx, bw = left + fr.w + 20, 18
    ramp = viridis(np.linspace(1.0, 0.0, fr.h))
    img[top:top + fr.h, bx:bx + bw] = ramp[:, None, :]
    cv2.rectangle(img, (bx, top), (bx + bw, top + fr.h), (0, 0, 0), 1)
    step = nice_step(vmax, 5)
    for v in np.arange(0.0, vmax + 1e-9, step):
        y = int(round(top + fr.h - v / vmax * fr.h))
        cv2.line(img, (bx + bw, y), (bx + bw + 4, y), (0, 0, 0), 1)
        _text(img, _fmt(v, step), (bx + bw + 7, y))
    _text(img, "log2(times seen)", (bx + bw // 2, top - 14), 0.4, "centre")
    _text(img, f"{'xyz'[ax_i[0]]} (m)", (left + fr.w // 2, top + fr.h + 38), 0.5, "centre")
    _text(img, f"{'xyz'[ax_i[1]]} (m)", (left - 8, top - 14), 0.5, "right")
    _text(img, f"{title}: {len(pos)} landmarks", (SIZE // 2, 16), 0.55, "centre")
    return img


def plot_top_view(path: str | Path, pos: np.ndarray, seen: np.ndarray, kf_poses: list[np.ndarray],
                  title: str = "landmarks (top view)") -> Path:
    """PNG of :func:`render_top_view` at ``path``, written atomically."""
    from rgbdslam.errors import InputError
    from rgbdslam.io.atomic import atomic_path

    img = render_top_view(pos, seen, kf_poses, title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise InputError(f"could not encode {path}")
        tmp.write_bytes(buf.tobytes())
    return path
