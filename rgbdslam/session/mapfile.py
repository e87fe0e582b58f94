"""The map file ``map.npz`` (docs/formats.md): a run's keyframes, pose graph, camera and config.

A plain NumPy ``.npz`` (a zip of ``.npy`` arrays, read with ``allow_pickle=False``: no Python
object is ever unpickled from disk) whose array ``header`` holds UTF-8 JSON: format name,
version, camera, config, sessions, counts, the SHA-256 of every other array (name, dtype, shape
and bytes), so that a truncated or altered file is refused with one line instead of loading
wrong numbers, and the optional landmark section (``lm_*`` arrays, :data:`LANDMARK_ARRAYS`) with
its own version and checksum.

Keyframes are numbered by their position ``k`` in the file; edges name positions. The loop
candidate index is not stored: it is rebuilt from the descriptors at load time in one pass
(``LshIndex.add_many``; the LSH index is deterministic given its seed; docs/benchmarks.md
measures the time and what storing it would cost).
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from rgbdslam.errors import InputError, shorten
from rgbdslam.geometry.camera import Camera
from rgbdslam.io import validate
from rgbdslam.io.atomic import atomic_path

FORMAT = "rgbdslam-map"
VERSION = 1
MAP_NAME = "map.npz"

# array name -> (dtype, shape with -1 = free, 'K' = keyframes, 'N' = features, 'E'/'L' = edges)
ARRAYS: dict[str, tuple[str, tuple]] = {
    "kf_session": ("int32", ("K",)),  # session number (header sessions[])
    "kf_frame": ("int64", ("K",)),  # frame index in its session's sequence
    "kf_timestamp": ("float64", ("K",)),
    "kf_pose": ("float64", ("K", 4, 4)),  # camera-to-map, after the pose graph
    "kf_segment": ("int32", ("K",)),  # connected component of the pose graph (0 = the largest)
    "kf_path": ("float64", ("K",)),  # metres travelled in its tracking segment (loop consistency)
    "kf_turn": ("float64", ("K",)),  # degrees turned in its tracking segment
    "kf_n_detected": ("int64", ("K",)),
    "kf_feature_start": ("int64", ("K+1",)),  # features of keyframe k: rows start[k]:start[k+1]
    "feat_uv": ("float32", ("N", 2)),  # undistorted pixels
    "feat_uv_raw": ("float32", ("N", 2)),  # distorted pixels
    "feat_desc": ("uint8", ("N", 32)),  # ORB descriptors
    "feat_pts": ("float32", ("N", 3)),  # depth-lifted camera points (m), NaN without depth
    "feat_valid": ("bool", ("N",)),
    "feat_response": ("float32", ("N",)),
    "frame_session": ("int32", ("F",)),  # every tracked frame of every session:
    "frame_index": ("int64", ("F",)),  # its index in its session's sequence,
    "frame_timestamp": ("float64", ("F",)),
    "frame_kf": ("int64", ("F",)),  # the keyframe it hangs from (position),
    "frame_rel": ("float64", ("F", 4, 4)),  # and its pose relative to it: pose = kf_pose[frame_kf] @ frame_rel
    "odo_ij": ("int64", ("E", 2)),  # odometry edges (keyframe positions)
    "odo_T": ("float64", ("E", 4, 4)),  # pose_i^-1 pose_j
    "odo_info": ("float64", ("E", 6, 6)),  # information, GTSAM order (rotation first)
    "loop_ij": ("int64", ("L", 2)),
    "loop_T": ("float64", ("L", 4, 4)),
    "loop_info": ("float64", ("L", 6, 6)),
    "loop_inliers": ("int64", ("L",)),
    "loop_residual": ("float64", ("L",)),
}

# the optional landmark section (landmarks.enabled runs; header "landmarks" = {"version", "count", "sha256"}):
# 'M' = live landmarks of the landmark map, positions in the map's frame after the pose graph
LANDMARK_VERSION = 1
LANDMARK_ARRAYS: dict[str, tuple[str, tuple]] = {
    "lm_pos": ("float64", ("M", 3)),  # map-frame position (m)
    "lm_cov": ("float64", ("M", 3, 3)),  # its covariance (m^2), Kalman-smoothed
    "lm_desc": ("uint8", ("M", 32)),  # ORB descriptor of its first observation
    "lm_session": ("int32", ("M",)),  # session it was first seen in
    "lm_first": ("int64", ("M",)),  # frame index (in that session's sequence) it was first seen in,
    "lm_last": ("int64", ("M",)),  # and last seen in
    "lm_seen": ("int64", ("M",)),  # times seen
    "lm_anchor": ("int64", ("M",)),  # keyframe position that anchors it (moves with it), -1: none
}


@dataclass
class MapData:
    """The contents of a map file (arrays as in :data:`ARRAYS`, header fields as attributes)."""

    arrays: dict[str, np.ndarray]
    camera: Camera
    config: dict[str, Any] = field(default_factory=dict)
    sessions: list[dict[str, Any]] = field(default_factory=list)
    landmarks: dict[str, np.ndarray] | None = None  # LANDMARK_ARRAYS when the run had a landmark map, else None
    created_by: str = ""

    @property
    def n_landmarks(self) -> int:
        return 0 if self.landmarks is None else int(len(self.landmarks["lm_pos"]))

    @property
    def n_keyframes(self) -> int:
        return int(len(self.arrays["kf_frame"]))

    def session_poses(self, session: int) -> tuple[np.ndarray, np.ndarray]:
        """(time stamps, camera-to-map poses) of every tracked frame of ``session``, in time order."""
        a = self.arrays
        sel = np.flatnonzero(a["frame_session"] == session)
        sel = sel[np.argsort(a["frame_timestamp"][sel], kind="stable")]
        return a["frame_timestamp"][sel], a["kf_pose"][a["frame_kf"][sel]] @ a["frame_rel"][sel]

    def features(self, k: int) -> dict[str, np.ndarray]:
        s, e = self.arrays["kf_feature_start"][k], self.arrays["kf_feature_start"][k + 1]
        return {name[5:]: self.arrays[name][s:e] for name in ARRAYS if name.startswith("feat_")}


class MapFileError(InputError):
    """A map file that cannot be used (the message is the one line the CLI prints)."""


def camera_dict(cam: Camera) -> dict[str, Any]:
    return {"name": cam.name, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
            "height": cam.height, "dist": list(cam.dist), "depth_registered": cam.depth_registered}


def _camera_text(cam: Camera) -> str:
    return (f"{cam.name or 'unnamed'} (fx {cam.fx:g}, fy {cam.fy:g}, cx {cam.cx:g}, cy {cam.cy:g}, "
            f"{cam.width}x{cam.height})")


def same_camera(a: Camera, b: Camera, rtol: float = 1e-6) -> bool:
    """Same intrinsics, image size and distortion (the name does not matter)."""
    va = np.array([a.fx, a.fy, a.cx, a.cy, a.width, a.height, *a.dist], float)
    vb = np.array([b.fx, b.fy, b.cx, b.cy, b.width, b.height, *b.dist], float)
    return va.shape == vb.shape and bool(np.allclose(va, vb, rtol=rtol, atol=1e-9))


def checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _check_shapes(arrays: dict[str, np.ndarray], where: str, spec: dict[str, tuple[str, tuple]] = ARRAYS) -> None:
    """Every array of ``spec`` present, of its dtype, with sizes that agree (K keyframes, N features,
    E, L edges; M landmarks)."""
    missing = [n for n in spec if n not in arrays]
    if missing:
        raise MapFileError(f"{where} is corrupt: array {missing[0]!r} is missing; re-run `rgbdslam run` to make it again")
    sizes: dict[str, int] = {}
    for name, (dtype, shape) in spec.items():
        a = arrays[name]
        if a.dtype != np.dtype(dtype) or a.ndim != len(shape):
            raise MapFileError(f"{where} is corrupt: array {name!r} is {a.dtype}{list(a.shape)}, expected {dtype} with "
                               f"{len(shape)} dimensions; re-run `rgbdslam run` to make it again")
        for n, s in zip(a.shape, shape):
            if isinstance(s, int):
                ok = n == s
            else:
                sym, extra = (s[0], 1) if s.endswith("+1") else (s, 0)
                ok = sizes.setdefault(sym, n - extra) == n - extra
            if not ok:
                raise MapFileError(f"{where} is corrupt: array {name!r} has shape {list(a.shape)}, which does not agree "
                                   f"with the others; re-run `rgbdslam run` to make it again")
    if spec is not ARRAYS:
        return
    start = arrays["kf_feature_start"]
    if len(start) and (start[0] != 0 or start[-1] != len(arrays["feat_desc"]) or np.any(np.diff(start) < 0)):
        raise MapFileError(f"{where} is corrupt: keyframe feature ranges do not cover the features")
    K = len(arrays["kf_frame"])
    for name in ("odo_ij", "loop_ij", "frame_kf"):
        if arrays[name].size and (arrays[name].min() < 0 or arrays[name].max() >= K):
            raise MapFileError(f"{where} is corrupt: {name} names a keyframe outside 0..{K - 1}")


def save_map(path: str | Path, data: MapData) -> Path:
    """Write ``data`` to ``path`` atomically (a reader sees the old file or the whole new one)."""
    path = Path(path)
    arrays = {n: np.ascontiguousarray(data.arrays[n], dtype=ARRAYS[n][0]) for n in ARRAYS}
    _check_shapes(arrays, str(path))
    landmarks = None
    if data.landmarks is not None:
        lm = {n: np.ascontiguousarray(data.landmarks[n], dtype=LANDMARK_ARRAYS[n][0]) for n in LANDMARK_ARRAYS}
        _check_shapes(lm, str(path), LANDMARK_ARRAYS)
        _check_anchors(lm, data.n_keyframes, str(path))
        landmarks = {"version": LANDMARK_VERSION, "count": int(len(lm["lm_pos"])), "sha256": checksum(lm)}
    header = {
        "format": FORMAT, "version": VERSION, "created_by": data.created_by,
        "camera": camera_dict(data.camera), "config": data.config, "sessions": data.sessions,
        "counts": {"keyframes": data.n_keyframes, "features": int(len(arrays["feat_desc"])),
                   "frames": int(len(arrays["frame_index"])),
                   "odometry_edges": int(len(arrays["odo_ij"])), "loop_edges": int(len(arrays["loop_ij"]))},
        "landmarks": landmarks,  # its own version and checksum: a reader without the section ignores it
        "sha256": checksum(arrays),
    }
    blob = np.frombuffer(json.dumps(header).encode("utf-8"), np.uint8)
    if landmarks is not None:
        arrays.update(lm)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, header=blob, **arrays)
    return path


def read_header(path: str | Path) -> dict[str, Any]:
    """The JSON header alone (cheap: one member of the zip)."""
    path = Path(path)
    _regular(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return _header(z, path)
    except MapFileError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as e:
        raise _corrupt(path, e) from None


def _regular(path: Path) -> None:
    """Nothing but a regular file is opened (a FIFO named map.npz would block the read for ever)."""
    import os
    import stat

    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # missing or unreadable: np.load names it (_corrupt)
    if not stat.S_ISREG(mode):
        raise MapFileError(f"{path} is not a regular file (a folder, FIFO or device); --map takes the folder of "
                           f"a finished `rgbdslam run` (it saves map.npz)")


def _corrupt(path: Path, e: Exception) -> MapFileError:
    if isinstance(e, FileNotFoundError):
        return MapFileError(f"{path} does not exist; --map takes the folder of a finished `rgbdslam run` (it saves map.npz)")
    return MapFileError(f"{path} is truncated or corrupt ({type(e).__name__}: {str(e).strip().splitlines()[0][:80] if str(e).strip() else 'unreadable'}); "
                        f"re-run `rgbdslam run` to make it again")


def _header(z, path: Path) -> dict[str, Any]:
    if "header" not in z.files:
        raise MapFileError(f"{path} is not an rgbdslam map file (no header); --map takes the folder of an `rgbdslam run`")
    header = json.loads(bytes(z["header"]).decode("utf-8"))
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise MapFileError(f"{path} is not an rgbdslam map file (format {header.get('format') if isinstance(header, dict) else '?'!r})")
    version = header.get("version")
    if version != VERSION:
        newer = isinstance(version, int) and version > VERSION
        raise MapFileError(f"{path} is map format version {version}, this rgbdslam reads version {VERSION}; "
                           + ("update rgbdslam to use it" if newer else "re-run `rgbdslam run` to make the map again"))
    return header


def load_map(path: str | Path, camera: Camera | None = None) -> MapData:
    """Read and check a map file: format, version, integrity (SHA-256, shapes), then the camera
    (when given: a map serves only the camera it was made with). Every failure is one
    :class:`MapFileError` line; nothing is written."""
    path = Path(path)
    _regular(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            header = _header(z, path)
            arrays = {n: z[n] for n in z.files if n != "header"}
    except MapFileError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError, UnicodeDecodeError) as e:
        raise _corrupt(path, e) from None
    _check_shapes(arrays, str(path))
    if checksum({n: arrays[n] for n in ARRAYS}) != header.get("sha256"):
        raise MapFileError(f"{path} is corrupt: its contents do not match the checksum in its header (changed or "
                           f"damaged after it was written); re-run `rgbdslam run` to make it again")
    try:
        c = header["camera"]
        cam = validate.camera(c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"], c["dist"],
                              str(c.get("name", "")), where=f"{path} (camera)")
        cam = replace(cam, depth_registered=bool(c.get("depth_registered", True)))  # absent in older maps
    except (KeyError, TypeError, AttributeError) as e:
        raise MapFileError(f"{path} is corrupt: its camera entry is unreadable ({shorten(e)})") from None
    except InputError as e:
        raise MapFileError(f"{e}; the map is corrupt: re-run `rgbdslam run` to make it again") from None
    check_values(arrays, path)
    if camera is not None and not same_camera(cam, camera):
        raise MapFileError(f"{path} was made with camera {_camera_text(cam)}, this sequence's camera is "
                           f"{_camera_text(camera)}: a map serves only the camera it was made with "
                           f"(check --config / dataset.camera)")
    landmarks = _load_landmarks(arrays, header.get("landmarks"), len(arrays["kf_frame"]), path)
    return MapData({n: arrays[n] for n in ARRAYS}, cam, header.get("config") or {}, header.get("sessions") or [],
                   landmarks, header.get("created_by", ""))


def check_values(arrays: dict[str, np.ndarray], path: Path) -> None:
    """The numbers a valid checksum does not vouch for (a crafted file can carry one): every
    pose rigid and finite (:func:`rgbdslam.io.validate.poses`), every time stamp and
    information matrix finite (the indices are checked with the shapes); MapFileError naming
    the array otherwise."""
    try:
        for name in ("kf_pose", "frame_rel", "odo_T", "loop_T"):
            if len(arrays[name]):
                validate.poses(arrays[name], f"{path} ({name})")
        for name in ("kf_timestamp", "frame_timestamp"):
            validate.stamps(arrays[name], f"{path} ({name})", strict=False)
    except InputError as e:
        raise MapFileError(f"{e}; the map is corrupt: re-run `rgbdslam run` to make it again") from None
    for name in ("odo_info", "loop_info", "kf_path", "kf_turn", "loop_residual", "feat_uv", "feat_uv_raw"):
        if not np.isfinite(arrays[name]).all():
            raise MapFileError(f"{path} is corrupt: {name} holds a value that is not a finite number")


def _check_anchors(lm: dict[str, np.ndarray], n_keyframes: int, where: str) -> None:
    a = lm["lm_anchor"]
    if a.size and (a.min() < -1 or a.max() >= n_keyframes):
        raise MapFileError(f"{where} is corrupt: lm_anchor names a keyframe outside 0..{n_keyframes - 1}")


def _load_landmarks(arrays: dict[str, np.ndarray], section: Any, n_keyframes: int,
                    path: Path) -> dict[str, np.ndarray] | None:
    """The landmark section's arrays, checked (its version, shapes, anchors, checksum); None
    when the map has none (a run without ``landmarks.enabled``)."""
    if section is None:
        return None
    version = section.get("version") if isinstance(section, dict) else None
    if version != LANDMARK_VERSION:
        newer = isinstance(version, int) and version > LANDMARK_VERSION
        raise MapFileError(f"{path} has landmark section version {version}, this rgbdslam reads version "
                           f"{LANDMARK_VERSION}; " + ("update rgbdslam to use it" if newer else
                                                      "re-run `rgbdslam run` to make the map again"))
    lm = {n: arrays[n] for n in LANDMARK_ARRAYS if n in arrays}
    _check_shapes(lm, str(path), LANDMARK_ARRAYS)
    _check_anchors(lm, n_keyframes, str(path))
    if len(lm["lm_pos"]) != section.get("count") or checksum(lm) != section.get("sha256"):
        raise MapFileError(f"{path} is corrupt: its landmark section does not match the checksum in its header "
                           f"(changed or damaged after it was written); re-run `rgbdslam run` to make it again")
    return lm


def map_path(run_dir: str | Path) -> Path:
    """``RUN_DIR/map.npz`` (a path to the file itself is accepted too)."""
    p = Path(run_dir)
    return p if p.suffix == ".npz" else p / MAP_NAME
