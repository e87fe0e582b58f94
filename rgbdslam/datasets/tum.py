"""TUM RGB-D sequence reader (also reads what ``rgbdslam synth`` writes).

Layout: ``rgb.txt`` and ``depth.txt`` ('timestamp filename' lines, '#' comments), the
images they name (colour 8-bit, depth 16-bit PNG with 5000 units per metre, 0 = no
measurement) and an optional ``groundtruth.txt`` (TUM trajectory). Without the two lists,
folders ``rgb/`` and ``depth/`` of PNGs named by their time stamps (``1305031102.175304.png``,
as TUM's and many bag-extraction tools write them) are read in time order. Colour and depth are
paired with TUM ``associate.py`` semantics, or read from an associations file
('rgb_ts rgb_file depth_ts depth_file').

Camera choice, first match wins: ``dataset.camera`` if not ``auto``; a ``camera.yaml`` in
the folder; ``freiburg1/2/3`` in the folder name; else ``ros_default`` (TUM's default).

The image loading here is shared with the PUT reader (:class:`RgbdFileSequence`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from rgbdslam.io.text import read_lines, read_text
from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import CAMERAS, Camera
from rgbdslam.io.trajectory import Trajectory, read_tum

TUM_DEPTH_SCALE = 5000.0
CAMERA_FILE = "camera.yaml"


# ------------------------------------------------------------------ shared image loading


def select_frames(n: int, cfg, where: Path) -> np.ndarray:
    """Indices of the ``n`` paired frames kept by ``first_frame``, ``stride``, ``max_frames``."""
    if cfg.stride < 1:
        raise InputError(f"dataset.stride must be >= 1 (got {cfg.stride}); set --set dataset.stride=1 or more")
    if cfg.first_frame < 0 or cfg.first_frame >= n:
        raise InputError(
            f"dataset.first_frame={cfg.first_frame} but {where} has {n} paired frames; choose 0..{n - 1}"
        )
    idx = np.arange(cfg.first_frame, n, cfg.stride)
    if cfg.max_frames is not None:
        if cfg.max_frames < 1:
            raise InputError(f"dataset.max_frames must be >= 1 or null (got {cfg.max_frames})")
        idx = idx[: cfg.max_frames]
    return idx


def read_rgb(path: Path, camera: Camera) -> np.ndarray:
    """A colour image as (H, W, 3) uint8 RGB; InputError naming the file if it is unusable."""
    if not path.is_file():
        raise InputError(f"colour image {path} is missing; restore it or remove its line from the list")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"colour image {path} cannot be decoded; replace it with a valid PNG/JPEG")
    if img.dtype != np.uint8:
        raise InputError(f"colour image {path} is {img.dtype}, expected 8-bit; convert it to 8-bit RGB")
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        ch = 1 if img.ndim == 2 else img.shape[2]
        raise InputError(f"colour image {path} has {ch} channel(s), expected 3 (RGB); convert it to colour")
    _check_size(path, img, camera)
    code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
    return cv2.cvtColor(img, code)


def read_depth(path: Path, camera: Camera, metres_per_unit: float) -> np.ndarray:
    """A 16-bit depth image as (H, W) float32 metres (0 = no measurement)."""
    if not path.is_file():
        raise InputError(f"depth image {path} is missing; restore it or remove its line from the list")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"depth image {path} cannot be decoded; replace it with a valid 16-bit PNG")
    if img.ndim != 2:
        raise InputError(f"depth image {path} has {img.shape[2]} channels, expected one 16-bit channel")
    if img.dtype != np.uint16:
        raise InputError(f"depth image {path} is {img.dtype}, expected 16-bit unsigned; save depth as 16-bit PNG")
    _check_size(path, img, camera)
    return img.astype(np.float32) * np.float32(metres_per_unit)


def _check_size(path: Path, img: np.ndarray, camera: Camera) -> None:
    h, w = img.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(
            f"image {path} is {w}x{h} but camera '{camera.name}' is {camera.width}x{camera.height}; "
            f"set dataset.camera or a {CAMERA_FILE} matching the images"
        )


class RgbdFileSequence(Sequence):
    """Frames stored as one colour and one depth image file each."""

    def __init__(
        self,
        root: Path,
        name: str,
        camera: Camera,
        timestamps: np.ndarray,
        rgb_files: list[Path],
        depth_files: list[Path],
        depth_scale: float,
        depth_correction: float = 1.0,
        depth_timestamps: np.ndarray | None = None,
    ) -> None:
        self.root = Path(root)
        self.name = name
        self.camera = camera
        self._timestamps = np.asarray(timestamps, dtype=np.float64)
        self.depth_timestamps = (
            self._timestamps.copy() if depth_timestamps is None else np.asarray(depth_timestamps, dtype=np.float64)
        )
        self.rgb_files = list(rgb_files)
        self.depth_files = list(depth_files)
        if depth_scale <= 0:
            raise InputError(f"dataset.depth_scale must be positive (got {depth_scale}); TUM uses 5000, PUT 1000")
        self.depth_scale = float(depth_scale)
        self.depth_correction = float(depth_correction)

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    def load(self, i: int) -> Frame:
        rgb_path, depth_path = self.rgb_files[i], self.depth_files[i]
        rgb = read_rgb(rgb_path, self.camera)
        depth = read_depth(depth_path, self.camera, self.depth_correction / self.depth_scale)
        try:
            name = str(rgb_path.relative_to(self.root))
        except ValueError:
            name = str(rgb_path)
        return Frame(i, float(self._timestamps[i]), rgb, depth, self.camera, name)


# ------------------------------------------------------------------ TUM lists and camera


def data_lines(path: Path):
    """Yield ``(line_number, fields)`` of the data lines of a text list ('#' comments and
    blank lines skipped; fields split on white space or commas)."""
    for lineno, line in enumerate(read_lines(path, "list file"), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield lineno, s.replace(",", " ").split()


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read 'timestamp filename' lines; '#' comments and blank lines skipped."""
    if not path.is_file():
        raise InputError(f"{path} is missing; a TUM sequence needs rgb.txt and depth.txt")
    stamps, names = [], []
    for lineno, parts in data_lines(path):
        try:
            t = float(parts[0])
            ok = len(parts) == 2 and np.isfinite(t)
        except ValueError:
            ok = False
        if not ok:
            raise InputError(
                f"{path}:{lineno}: expected 'timestamp filename'; got {' '.join(parts)[:60]!r}; fix or delete the line"
            )
        stamps.append(t)
        names.append(parts[1])
    if not stamps:
        raise InputError(f"{path} lists no images; it needs 'timestamp filename' lines")
    return np.array(stamps, dtype=np.float64), names


def _stamp(name: str) -> float | None:
    try:
        t = float(Path(name).stem)
    except ValueError:
        return None
    return t if np.isfinite(t) else None


def list_from_folder(folder: Path) -> tuple[np.ndarray, list[str]]:
    """'timestamp filename' pairs of the PNGs in ``folder`` named by their time stamps, in time
    order (what rgb.txt / depth.txt would list); file names relative to the folder's parent."""
    files = sorted(folder.glob("*.png"))
    bad = [f.name for f in files if _stamp(f.name) is None]
    if bad or not files:
        what = f"{bad[0]} is not named by its time stamp" if bad else "there are no PNG images"
        raise InputError(f"{folder}: {what}; without {folder.name}.txt the images must be named like "
                         f"1305031102.175304.png, or write {folder.name}.txt ('timestamp filename' lines)")
    stamps = np.array([_stamp(f.name) for f in files])
    order = np.argsort(stamps, kind="stable")
    return stamps[order], [f"{folder.name}/{files[k].name}" for k in order]


def _image_list(root: Path, kind: str) -> tuple[np.ndarray, list[str]]:
    """``kind``.txt if present, else the time-stamp-named PNGs of the folder ``kind``/.
    A time stamp listed twice is an error: association would silently keep only one image."""
    if (root / f"{kind}.txt").is_file() or not (root / kind).is_dir():
        source = root / f"{kind}.txt"
        ts, files = read_file_list(source)
    else:
        source = root / kind
        ts, files = list_from_folder(source)
    uniq, counts = np.unique(ts, return_counts=True)
    if len(uniq) < len(ts):
        t = uniq[np.argmax(counts > 1)]
        raise InputError(f"{source}: {len(ts) - len(uniq)} time stamp(s) are listed more than once (e.g. {t:.6f}); "
                         f"give every image its own time stamp")
    return ts, files


def read_associations(path: Path) -> tuple[np.ndarray, list[str], np.ndarray, list[str]]:
    """Read 'rgb_ts rgb_file depth_ts depth_file' lines (the output of TUM associate.py)."""
    if not path.is_file():
        raise InputError(f"associations file {path} does not exist; fix dataset.associations or leave it null")
    ts_rgb, f_rgb, ts_d, f_d = [], [], [], []
    for lineno, parts in data_lines(path):
        try:
            a, b = float(parts[0]), float(parts[2])
            ok = len(parts) == 4
        except (ValueError, IndexError):
            ok = False
        if not ok:
            raise InputError(
                f"{path}:{lineno}: expected 'rgb_ts rgb_file depth_ts depth_file'; "
                f"got {' '.join(parts)[:60]!r}; fix or delete the line"
            )
        ts_rgb.append(a)
        f_rgb.append(parts[1])
        ts_d.append(b)
        f_d.append(parts[3])
    if not ts_rgb:
        raise InputError(f"associations file {path} holds no pairs; it needs 'rgb_ts rgb_file depth_ts depth_file' lines")
    return np.array(ts_rgb), f_rgb, np.array(ts_d), f_d


def camera_from_yaml(path: Path) -> Camera:
    """A camera from ``camera.yaml``: ``camera: <known name>`` and/or explicit intrinsics
    ``fx fy cx cy width height dist`` (explicit values override the named camera's)."""
    try:
        data = yaml.safe_load(read_text(path, "camera file"))
    except yaml.YAMLError:
        raise InputError(f"{path} is not valid YAML; fix it or delete it to use the default camera") from None
    if not isinstance(data, dict):
        raise InputError(f"{path} must be a mapping with 'camera: <name>' or fx, fy, cx, cy, width, height, dist")
    known = {"camera", "fx", "fy", "cx", "cy", "width", "height", "dist"}
    unknown = set(data) - known
    if unknown:
        raise InputError(f"{path}: unknown key(s) {', '.join(sorted(map(str, unknown)))}; allowed: {', '.join(sorted(known))}")
    name = data.get("camera")
    base: dict = {}
    if name is not None:
        if name not in CAMERAS:
            raise InputError(f"{path}: unknown camera '{name}'; choose one of {', '.join(CAMERAS)} or give fx, fy, cx, cy")
        c = CAMERAS[name]
        base = dict(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width=c.width, height=c.height, dist=c.dist)
    for k in ("fx", "fy", "cx", "cy", "width", "height", "dist"):
        if k in data:
            base[k] = data[k]
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in base]
    if missing:
        raise InputError(f"{path}: missing {', '.join(missing)}; give 'camera: <name>' or all of fx, fy, cx, cy")
    try:
        dist = tuple(float(x) for x in base.get("dist", (0.0,) * 5))
        cam = Camera(
            float(base["fx"]), float(base["fy"]), float(base["cx"]), float(base["cy"]),
            int(base.get("width", 640)), int(base.get("height", 480)), dist, str(name or "custom"),
        )
    except (TypeError, ValueError):
        raise InputError(f"{path}: intrinsics must be numbers (dist a list of 5 numbers)") from None
    if len(dist) not in (4, 5, 8):
        raise InputError(f"{path}: dist must have 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 ...]); got {len(dist)}")
    if not (np.isfinite([cam.fx, cam.fy, cam.cx, cam.cy, *dist]).all() and cam.fx > 0 and cam.fy > 0
            and cam.width > 0 and cam.height > 0):
        raise InputError(f"{path}: fx and fy must be positive, width and height at least 1, and every value "
                         f"finite; got fx {cam.fx}, fy {cam.fy}, cx {cam.cx}, cy {cam.cy}, "
                         f"{cam.width}x{cam.height}")
    return cam


def choose_camera(root: Path, camera: str = "auto") -> Camera:
    """The camera for a TUM-layout folder (see the module docstring for the order)."""
    if camera != "auto":
        if camera not in CAMERAS:
            raise InputError(f"unknown camera '{camera}'; choose one of {', '.join(CAMERAS)}")
        return CAMERAS[camera]
    if (root / CAMERA_FILE).is_file():
        return camera_from_yaml(root / CAMERA_FILE)
    name = root.resolve().name.lower()
    for k in ("1", "2", "3"):
        if f"freiburg{k}" in name or f"fr{k}_" in name:
            return CAMERAS[f"fr{k}"]
    return CAMERAS["ros_default"]


def _is_tum(path: Path) -> bool:
    def listed(kind: str) -> bool:
        if (path / f"{kind}.txt").is_file():
            return True
        folder = path / kind
        return folder.is_dir() and any(_stamp(f.name) is not None for f in folder.glob("*.png"))

    return listed("rgb") and listed("depth")


@reader("tum", _is_tum)
class TumSequence(RgbdFileSequence):
    """A TUM RGB-D folder; see the module docstring."""

    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.config import DatasetConfig
        from rgbdslam.evaluation.associate import associate

        cfg = cfg or DatasetConfig()
        root = Path(root)
        if not root.is_dir():
            raise InputError(f"sequence folder {root} does not exist; check the path")
        if cfg.associations:
            assoc = Path(cfg.associations)
            if not assoc.is_absolute() and (root / assoc).is_file():
                assoc = root / assoc  # relative to the sequence folder first, then to the working dir
            ts_rgb, f_rgb, ts_d, f_d = read_associations(assoc)
            order = np.argsort(ts_rgb, kind="stable")
            ia = ib = order
        else:
            ts_rgb, f_rgb = _image_list(root, "rgb")
            ts_d, f_d = _image_list(root, "depth")
            ia, ib = associate(ts_rgb, ts_d, cfg.max_difference, cfg.offset)
            if len(ia) == 0:
                raise InputError(
                    f"no colour/depth pair in {root} has time stamps within {cfg.max_difference} s "
                    f"(offset {cfg.offset} s); check rgb.txt/depth.txt or raise dataset.max_difference"
                )
        keep = select_frames(len(ia), cfg, root)
        ia, ib = ia[keep], ib[keep]
        super().__init__(
            root=root,
            name=root.resolve().name,
            camera=choose_camera(root, cfg.camera),
            timestamps=ts_rgb[ia],
            rgb_files=[root / f_rgb[i] for i in ia],
            depth_files=[root / f_d[j] for j in ib],
            depth_scale=cfg.depth_scale if cfg.depth_scale is not None else TUM_DEPTH_SCALE,
            depth_correction=cfg.depth_correction,
            depth_timestamps=ts_d[ib],
        )

    def groundtruth(self) -> Trajectory | None:
        p = self.root / "groundtruth.txt"
        return read_tum(p) if p.is_file() else None
