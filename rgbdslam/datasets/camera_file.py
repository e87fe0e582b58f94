"""Which camera a sequence is seen through, and where that came from.

A *camera file* (YAML, ``--camera FILE`` or ``dataset.camera_file``; also ``camera.yaml`` in a
sequence folder) gives the colour camera and, optionally, how the depth images relate to it::

    camera: fr1            # optional: start from a known camera, keys below override it
    fx: 585.0              # colour intrinsics (pixels)
    fy: 585.0
    cx: 320.0
    cy: 240.0
    size: [640, 480]       # or width: / height:
    distortion: [0, 0, 0, 0, 0]   # OpenCV k1 k2 p1 p2 [k3] (alias: dist)
    depth_scale: 1000      # raw depth units per metre (TUM 5000, millimetres 1000)
    rolling_shutter: 0.0175  # seconds from the first row read to the last (0 = global shutter;
                           # `rgbdslam calibrate rolling-shutter` measures it from a recording)
    # depth images not registered to colour (two sensors): the depth camera and the pose of the
    # depth camera in the colour camera's frame; the reader then re-projects every depth image
    # into the colour image (DepthRegistration)
    depth_camera: {fx: 585, fy: 585, cx: 320, cy: 240, size: [640, 480]}
    depth_to_color: [0.025, 0, 0]            # a translation in metres, or a 3x4 / 4x4 matrix

:func:`resolve_camera` applies the one order every reader uses: the camera file given in the
config (a path, or the name of a camera file shipped in ``rgbdslam/cameras/``: ``7scenes``), then a named ``dataset.camera``, then ``camera.yaml`` in the folder, then what the source
itself says (a bag's CameraInfo, 7-Scenes' camera-intrinsics.txt, ETH3D's calibration.txt, the
folder name), else the reader's default, flagged as a fallback so the run warns.
"""

from __future__ import annotations

import importlib.resources
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rgbdslam.errors import InputError, cut, shorten
from rgbdslam.io import validate
from rgbdslam.io.yamlfile import load_yaml
from rgbdslam.geometry.camera import CAMERAS, Camera
from rgbdslam.io.text import read_text

CAMERA_FILE = "camera.yaml"
_INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "size", "dist", "distortion")
KNOWN_KEYS = {"camera", *_INTRINSIC_KEYS, "depth_scale", "depth_camera", "depth_to_color", "rolling_shutter"}
MAX_READOUT = 0.1  # seconds: a rolling shutter's readout is shorter than a frame


@dataclass(frozen=True)
class CameraSetup:
    """The colour camera of a sequence, where it came from, and what the depth needs."""

    camera: Camera
    source: str  # e.g. "--camera cams/d435.yaml", "CameraInfo on /camera/color/camera_info"
    depth_scale: float | None = None  # raw units per metre, if the source says
    depth_camera: Camera | None = None  # set when depth is not registered to colour
    depth_to_color: np.ndarray | None = None  # 4x4 pose of the depth camera in the colour frame
    fallback: bool = False  # nothing said which camera: a guess the run warns about

    def __post_init__(self) -> None:  # the colour camera says whether its depth is registered to it
        registered = self.depth_camera is None and self.depth_to_color is None
        if self.camera.depth_registered != registered:
            object.__setattr__(self, "camera", replace(self.camera, depth_registered=registered))

    def describe(self) -> str:
        c = self.camera
        text = (f"camera {c.name or 'custom'}: fx {c.fx:g} fy {c.fy:g} cx {c.cx:g} cy {c.cy:g}, "
                f"{c.width}x{c.height}" + (", with distortion" if c.has_distortion else "")
                + f" (from {self.source})")
        if self.depth_to_color is not None:
            t = self.depth_to_color[:3, 3]
            text += f"; depth re-projected into colour (depth-to-colour t = {t[0]:.3f} {t[1]:.3f} {t[2]:.3f} m)"
        return text

    def fallback_warning(self) -> str | None:
        if not self.fallback:
            return None
        c = self.camera
        return (f"no camera given for this sequence: assuming '{c.name}' (fx {c.fx:g} fy {c.fy:g} cx {c.cx:g} "
                f"cy {c.cy:g}); if it is not your camera, pass --camera FILE (fx, fy, cx, cy, size, distortion, "
                f"depth_scale), a preset such as -c tum_fr1, or put a camera.yaml in the sequence folder")


def _camera(data: dict, where: str, base: Camera | None, name: str) -> Camera:
    """A Camera from the intrinsic keys of ``data`` over ``base``; InputError naming ``where``."""
    vals: dict = {}
    if base is not None:
        vals = dict(fx=base.fx, fy=base.fy, cx=base.cx, cy=base.cy, width=base.width, height=base.height,
                    dist=base.dist, readout=base.readout)
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        if k in data:
            vals[k] = data[k]
    if "size" in data:
        size = data["size"]
        if not (isinstance(size, (list, tuple)) and len(size) == 2):
            raise InputError(f"{where}: size must be [width, height]; got {shorten(size)}")
        vals["width"], vals["height"] = size
    if "dist" in data or "distortion" in data:
        vals["dist"] = data.get("distortion", data.get("dist"))
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in vals]
    if missing:
        raise InputError(f"{where}: missing {', '.join(missing)}; give 'camera: <name>' or all of fx, fy, cx, cy")
    dist = vals.get("dist")
    return validate.camera(vals["fx"], vals["fy"], vals["cx"], vals["cy"], vals.get("width", 640),
                           vals.get("height", 480), (0.0,) * 5 if dist is None else dist, name,
                           _readout(data.get("rolling_shutter", vals.get("readout", 0.0)), where), where=where)


def _readout(value, where: str) -> float:
    """The ``rolling_shutter`` key: the readout time in seconds, 0 to :data:`MAX_READOUT`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= MAX_READOUT:
        raise InputError(f"{where}: rolling_shutter must be the readout time in seconds from 0 (global shutter) "
                         f"to {MAX_READOUT:g}; got {shorten(value)}")
    return float(value)


def _extrinsic(value, where: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    T = np.eye(4)
    if a.shape == (3,):
        T[:3, 3] = a
    elif a.shape in ((3, 4), (4, 4)):
        T[:3] = a[:3]
    else:
        raise InputError(f"{where}: depth_to_color must be a translation [x, y, z] in metres or a 3x4/4x4 matrix")
    R = T[:3, :3]
    if not (np.isfinite(T).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
        raise InputError(f"{where}: depth_to_color's rotation is not a rotation matrix (R R^T must be I)")
    return T


def read_camera_file(path: str | Path, source: str | None = None) -> CameraSetup:
    """A :class:`CameraSetup` from a camera YAML file (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"camera file {path} does not exist; give a YAML file with fx, fy, cx, cy (and size)")
    data = load_yaml(read_text(path, "camera file"), str(path), what="YAML (a camera file)")
    if not isinstance(data, dict):
        raise InputError(f"{path} must be a mapping with 'camera: <name>' or fx, fy, cx, cy, width, height, dist")
    unknown = set(data) - KNOWN_KEYS
    if unknown:
        names = sorted(map(str, unknown))
        shown = ", ".join(cut(k, 30) for k in names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
        raise InputError(f"{path}: unknown key(s) {shown}; allowed: {', '.join(sorted(KNOWN_KEYS))}")
    name = data.get("camera")
    base = None
    if name is not None:
        if not isinstance(name, str) or name not in CAMERAS:
            raise InputError(f"{path}: unknown camera {shorten(name)}; choose one of {', '.join(CAMERAS)} or give "
                             f"fx, fy, cx, cy")
        base = CAMERAS[name]
    cam = _camera(data, str(path), base, str(name or "custom"))
    scale = data.get("depth_scale")
    if scale is not None:
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not np.isfinite(scale) \
                or not 1e-3 <= scale <= 1e6:  # the range of the config key dataset.depth_scale
            raise InputError(f"{path}: depth_scale must be a number of raw units per metre from 0.001 to 1e6; "
                             f"got {shorten(scale)}")
        scale = float(scale)
    depth_cam = T = None
    if data.get("depth_camera") is not None or data.get("depth_to_color") is not None:
        dc = data.get("depth_camera")
        if dc is not None and not isinstance(dc, dict):
            raise InputError(f"{path}: depth_camera must be a mapping of fx, fy, cx, cy, size")
        # its own intrinsics (size defaults to the colour images', distortion to none), else the colour camera's
        depth_cam = cam if dc is None else _camera({"width": cam.width, "height": cam.height, **dc},
                                                   f"{path} (depth_camera)", None, "depth")
        T = _extrinsic(data.get("depth_to_color", [0.0, 0.0, 0.0]), str(path))
    return CameraSetup(cam, source or str(path), scale, depth_cam, T)


def shipped_cameras() -> dict[str, object]:
    """Name -> resource of every camera file shipped inside the package (``rgbdslam/cameras/*.yaml``)."""
    root = importlib.resources.files("rgbdslam") / "cameras"
    return {e.name[:-5]: e for e in root.iterdir() if e.name.endswith(".yaml") and e.is_file()}


def read_shipped_camera(name: str, source: str) -> CameraSetup:
    """The camera file ``name`` shipped with rgbdslam (``7scenes``), as :func:`read_camera_file` reads it."""
    with importlib.resources.as_file(shipped_cameras()[name]) as path:
        return read_camera_file(path, source)


def named_camera(name: str, source: str) -> CameraSetup:
    if name not in CAMERAS:
        raise InputError(f"unknown camera '{name}'; choose one of {', '.join(CAMERAS)}")
    return CameraSetup(CAMERAS[name], source)


def resolve_camera(cfg, root: Path | None, own: CameraSetup | None, default: str = "ros_default") -> CameraSetup:
    """The camera of a sequence, first match wins: ``dataset.camera_file`` (``--camera``), a named
    ``dataset.camera``, ``camera.yaml`` in ``root``, ``own`` (what the source says), else the
    camera ``default`` marked as a fallback."""
    camera_file = getattr(cfg, "camera_file", None)
    if camera_file:
        if not Path(camera_file).exists() and str(camera_file) in shipped_cameras():
            return read_shipped_camera(str(camera_file), f"--camera {camera_file}, shipped with rgbdslam")
        return read_camera_file(camera_file, f"--camera {camera_file}")
    if cfg.camera != "auto":
        return named_camera(cfg.camera, f"dataset.camera = {cfg.camera}")
    if root is not None and (root / CAMERA_FILE).is_file():
        return read_camera_file(root / CAMERA_FILE)
    if own is not None:
        return own
    return CameraSetup(CAMERAS[default], f"the default '{default}': nothing else said which camera", fallback=True)
