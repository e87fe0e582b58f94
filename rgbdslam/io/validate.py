"""The one check every reader applies to the numbers it reads: cameras, poses and time stamps.

Every reader (camera files, ``stereo.yaml``, EuRoC ``sensor.yaml`` and ``data.csv``, KITTI
``calib.txt``/poses/times, 7-Scenes intrinsics and poses, a bag's ``CameraInfo``, a RealSense
stream, a saved ``map.npz``) passes what it read through :func:`camera`, :func:`poses` and
:func:`stamps` before anything else (OpenCV, an SVD, the tracker) sees it, so a value that is
not a number, not finite or absurd is one :class:`InputError` naming the file and the value,
never a traceback, a segmentation fault, a hang or "ATE inf" later.

The limits:

- a camera: fx, fy in (0, :data:`MAX_PIXELS`], cx, cy within ±:data:`MAX_PIXELS`, width and
  height whole numbers from 1 to :data:`MAX_IMAGE_SIDE` with at most :data:`MAX_IMAGE_PIXELS`
  pixels, 4, 5 or 8 distortion coefficients within ±:data:`MAX_DIST`;
- a pose: a finite 4x4 (or 3x4) rigid transform (R R^T = I within :data:`ROTATION_TOL`,
  det R = +1, last row 0 0 0 1), translation within ±:data:`MAX_COORD` metres;
- time stamps: finite seconds within ±:data:`MAX_STAMP`, increasing (:func:`stamps`
  ``strict``) and at most :data:`MAX_RATE` frames per second; a frame rate (``fps``) from
  :data:`MIN_RATE` to :data:`MAX_RATE`.

Values are taken as they are written: a YAML ``true`` or ``"12345"`` is not a number, and a
width of ``640.5`` is not a size (no silent coercion).
"""

from __future__ import annotations

import math
from numbers import Integral, Real

import numpy as np

from rgbdslam.errors import InputError, shorten
from rgbdslam.io.numbers import MAX_COORD, MAX_STAMP

MAX_IMAGE_SIDE = 65535  # pixels (16-bit image sizes)
MAX_IMAGE_PIXELS = 1 << 28  # 268 M pixels: a frame's buffers stay far below the memory of any machine
MAX_PIXELS = 1e6  # focal lengths and principal point (pixels)
MAX_DIST = 1e3  # distortion coefficients
ROTATION_TOL = 1e-3  # |R R^T - I| allowed for a rotation read from a file (printed with 6-9 digits)
MIN_RATE = 1e-3  # frames per second (one frame in ~17 minutes)
MAX_RATE = 1e4  # frames per second


def number(value, where: str, what: str, lo: float = -math.inf, hi: float = math.inf,
           integer: bool = False, lo_open: bool = False) -> float | int:
    """``value`` as a float (an int with ``integer``) when it is a real number (not a bool, not
    text) within [``lo``, ``hi``] (``lo`` excluded with ``lo_open``); else InputError naming
    ``where`` and ``what``."""
    kind = "a whole number" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, Real):
        raise InputError(f"{where}: {what} must be {kind}; got {shorten(value)}")
    v = float(value)
    if integer:
        if not (math.isfinite(v) and v == int(v)):
            raise InputError(f"{where}: {what} must be {kind}; got {shorten(value)}")
        v = int(value) if isinstance(value, Integral) else int(v)
    below = v <= lo if lo_open else v < lo
    if not math.isfinite(v) or below or v > hi:
        rng = "" if math.isinf(lo) and math.isinf(hi) else \
            f" {'above' if lo_open else 'from'} {lo:g} {'and at most' if lo_open else 'to'} {hi:g}"
        raise InputError(f"{where}: {what} must be a finite number{rng}; got {shorten(value)}")
    return v


def numbers(values, where: str, what: str, lengths: tuple[int, ...] | None = None) -> list[float | int]:
    """A list of finite real numbers (no text, no bools) of one of ``lengths`` (whole numbers stay
    ints); InputError otherwise."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
        raise InputError(f"{where}: {what} must be a list of numbers; got {shorten(values)}")
    if lengths is not None and len(values) not in lengths:
        raise InputError(f"{where}: {what} must have {' or '.join(map(str, lengths))} values; got {len(values)}")
    out = []
    for i, v in enumerate(values):
        number(v, where, f"value {i + 1} of {what}")
        out.append(v if isinstance(v, Integral) else float(v))
    return out


def camera(fx, fy, cx, cy, width, height, dist=(0.0,) * 5, name: str = "", readout: float = 0.0, *,
           where: str):
    """A :class:`~rgbdslam.geometry.camera.Camera` from values read at ``where`` once every one
    is a number within the limits of the module docstring; InputError naming the first that is
    not."""
    from rgbdslam.geometry.camera import Camera

    fx = number(fx, where, "fx", 0.0, MAX_PIXELS, lo_open=True)
    fy = number(fy, where, "fy", 0.0, MAX_PIXELS, lo_open=True)
    cx = number(cx, where, "cx", -MAX_PIXELS, MAX_PIXELS)
    cy = number(cy, where, "cy", -MAX_PIXELS, MAX_PIXELS)
    w = number(width, where, "width", 1, MAX_IMAGE_SIDE, integer=True)
    h = number(height, where, "height", 1, MAX_IMAGE_SIDE, integer=True)
    if w * h > MAX_IMAGE_PIXELS:
        raise InputError(f"{where}: an image of {w}x{h} pixels is larger than {MAX_IMAGE_PIXELS:,} pixels; "
                         f"check width and height")
    d = numbers(dist, where, "distortion", (4, 5, 8))
    for i, k in enumerate(d):
        if abs(k) > MAX_DIST:
            raise InputError(f"{where}: distortion coefficient {i + 1} must be within ±{MAX_DIST:g}; got {k:g}")
    return Camera(fx, fy, cx, cy, w, h, tuple(d), name, float(readout))


def poses(P, where: str, lines=None, what: str = "pose") -> np.ndarray:
    """``P`` (N, 4, 4) or (N, 3, 4) as (N, 4, 4) float64 once every pose is a finite rigid
    transform within ±:data:`MAX_COORD` m; InputError naming ``where`` (and ``lines[i]``, the
    line of pose i, when given)."""
    P = np.asarray(P, dtype=np.float64)
    if P.ndim == 2:
        P = P[None]
    if P.ndim != 3 or P.shape[1:] not in ((4, 4), (3, 4)):
        raise InputError(f"{where}: a {what} must be a 4x4 (or 3x4) matrix; got shape {P.shape[1:]}")
    out = np.tile(np.eye(4), (len(P), 1, 1))
    out[:, :3] = P[:, :3]
    bottom_ok = np.ones(len(P), bool) if P.shape[1] == 3 else np.all(np.abs(P[:, 3] - [0, 0, 0, 1]) <= 1e-6, axis=1)
    finite = np.isfinite(P).all(axis=(1, 2))
    R = np.where(finite[:, None, None], out[:, :3, :3], np.eye(3))
    with np.errstate(over="ignore", invalid="ignore"):  # entries of 1e300: not a rotation, said below
        ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)) <= ROTATION_TOL
        det_ok = np.linalg.det(R) > 0
    t_ok = np.all(np.abs(np.where(finite[:, None], out[:, :3, 3], 0.0)) <= MAX_COORD, axis=1)
    bad = np.flatnonzero(~(finite & ortho & det_ok & t_ok & bottom_ok))
    if len(bad):
        i = int(bad[0])
        at = f"{where}:{lines[i]}" if lines is not None else (f"{where} ({what} {i})" if len(P) > 1 else where)
        if not finite[i]:
            why = "holds a value that is not a finite number"
        elif not t_ok[i]:
            why = f"has a translation beyond ±{MAX_COORD:g} m"
        elif not bottom_ok[i]:
            why = "does not end with the row 0 0 0 1"
        else:
            why = f"has no rotation matrix (R R^T must be I within {ROTATION_TOL:g} and det R = +1)"
        raise InputError(f"{at}: the {what} {why}; write rigid camera poses")
    return out


def stamps(t, where: str, lines=None, strict: bool = True) -> np.ndarray:
    """Time stamps (N,) in seconds as float64 once finite, within ±:data:`MAX_STAMP` and, with
    ``strict``, increasing at most :data:`MAX_RATE` times per second; InputError naming ``where``
    (and ``lines[i]``)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)

    def at(i: int) -> str:
        return f"{where}:{lines[i]}" if lines is not None else f"{where} (time stamp {i})"

    bad = np.flatnonzero(~(np.abs(t) <= MAX_STAMP))
    if len(bad):
        raise InputError(f"{at(int(bad[0]))}: time stamp {t[bad[0]]:g} is not a finite number of seconds within "
                         f"±{MAX_STAMP:g}; time stamps must be seconds (e.g. 1305031102.175304)")
    if strict and len(t) > 1:
        step = np.diff(t)
        bad = np.flatnonzero(~(step >= 1.0 / MAX_RATE))
        if len(bad):
            i = int(bad[0]) + 1
            raise InputError(f"{at(i)}: time stamp {t[i]:.9g} follows {t[i - 1]:.9g}; time stamps must increase, "
                             f"by at least {1.0 / MAX_RATE:g} s (at most {MAX_RATE:g} frames per second)")
    return t


def rate(value, where: str, what: str = "fps") -> float:
    """A frame rate in frames per second, from :data:`MIN_RATE` to :data:`MAX_RATE`."""
    return float(number(value, where, what, MIN_RATE, MAX_RATE))


def stamp_ns(text: str, where: str) -> int:
    """An integer nanosecond time stamp (EuRoC's ``data.csv``) within ±:data:`MAX_STAMP` s;
    InputError naming ``where`` otherwise (26-digit numbers included)."""
    s = text.strip()
    if not (s.lstrip("+-").isdigit() and s.isascii()):
        raise InputError(f"{where}: expected a time stamp in nanoseconds (a whole number); got {shorten(s)}")
    v = int(s) if len(s) <= 21 else None
    if v is None or abs(v) > MAX_STAMP * 1e9 or abs(v) >= 2 ** 63:
        raise InputError(f"{where}: time stamp {shorten(s)} ns is beyond ±{MAX_STAMP:g} s")
    return v
