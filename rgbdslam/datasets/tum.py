"""TUM RGB-D sequence reader (also reads what ``rgbdslam synth`` writes).

Layout: ``rgb.txt`` and ``depth.txt`` ('timestamp filename' lines, '#' comments), the
images they name (colour 8-bit, depth 16-bit PNG with 5000 units per metre, 0 = no
measurement) and an optional ``groundtruth.txt`` (TUM trajectory). Without the two lists,
folders ``rgb/`` and ``depth/`` of PNGs named by their time stamps (``1305031102.175304.png``,
as TUM's and many bag-extraction tools write them) are read in time order. Colour and depth are
paired with TUM ``associate.py`` semantics, or read from an associations file
('rgb_ts rgb_file depth_ts depth_file').

Camera choice, first match wins (:func:`rgbdslam.datasets.camera_file.resolve_camera`):
``--camera FILE`` / ``dataset.camera_file``; ``dataset.camera`` if not ``auto``; a ``camera.yaml``
in the folder; what the folder says (ETH3D SLAM's ``calibration.txt``, ``freiburg1/2/3`` in the
folder name); else ``ros_default`` (TUM's default), with a warning.

Also read here: ETH3D SLAM data sets (TUM layout plus ``calibration.txt``, depth 5000 per metre).
ICL-NUIM's TUM variant has a reader of its own (``datasets/icl.py``: frame numbers, a y-up world).

The image loading here is shared with the PUT reader (:class:`RgbdFileSequence`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rgbdslam.io import validate
from rgbdslam.io.images import read_image
from rgbdslam.io.text import optional_file, read_lines, read_text, require_file
from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.datasets.camera_file import CAMERA_FILE, CameraSetup, read_camera_file, resolve_camera
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import CAMERAS, Camera
from rgbdslam.geometry.depth_registration import DepthRegistration
from rgbdslam.io.trajectory import Trajectory, read_tum
from rgbdslam.io.numbers import MAX_STAMP, check_stamps

TUM_DEPTH_SCALE = 5000.0


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
    img, why = read_image(path)
    if img is None:
        raise InputError(f"colour image {path} cannot be decoded ({why}); replace it with a valid PNG/JPEG")
    if img.dtype != np.uint8:
        raise InputError(f"colour image {path} is {img.dtype}, expected 8-bit; convert it to 8-bit RGB")
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        ch = 1 if img.ndim == 2 else img.shape[2]
        raise InputError(f"colour image {path} has {ch} channel(s), expected 3 (RGB); convert it to colour")
    _check_size(path, img, camera)
    code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
    return cv2.cvtColor(img, code)


def read_depth(path: Path, camera: Camera, metres_per_unit: float, invalid: int | None = None) -> np.ndarray:
    """A 16-bit depth image as (H, W) float32 metres (0 = no measurement; so is the raw value
    ``invalid``, e.g. 7-Scenes' 65535)."""
    if not path.is_file():
        raise InputError(f"depth image {path} is missing; restore it or remove its line from the list")
    img, why = read_image(path)
    if img is None:
        raise InputError(f"depth image {path} cannot be decoded ({why}); replace it with a valid 16-bit PNG")
    if img.ndim != 2:
        raise InputError(f"depth image {path} has {img.shape[2]} channels, expected one 16-bit channel")
    if img.dtype != np.uint16:
        raise InputError(f"depth image {path} is {img.dtype}, expected 16-bit unsigned; save depth as 16-bit PNG")
    _check_size(path, img, camera)
    out = img.astype(np.float32) * np.float32(metres_per_unit)
    if invalid is not None:
        out[img == invalid] = 0.0
    return out


def pick_depth_scale(cfg, setup: CameraSetup, default: float) -> float:
    """Raw depth units per metre: ``dataset.depth_scale`` if set, else the camera file's, else ``default``."""
    if cfg.depth_scale is not None:
        return cfg.depth_scale
    return setup.depth_scale if setup.depth_scale is not None else default


def _check_size(path: Path, img: np.ndarray, camera: Camera) -> None:
    h, w = img.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(
            f"image {path} is {w}x{h} but camera '{camera.name}' is {camera.width}x{camera.height}; "
            f"pass --camera FILE (or a {CAMERA_FILE} in the folder) with the intrinsics of these images"
        )


class RgbdFileSequence(Sequence):
    """Frames stored as one colour and one depth image file each."""

    def __init__(
        self,
        root: Path,
        name: str,
        camera: Camera | CameraSetup,
        timestamps: np.ndarray,
        rgb_files: list[Path],
        depth_files: list[Path],
        depth_scale: float,
        depth_correction: float = 1.0,
        depth_timestamps: np.ndarray | None = None,
        invalid_depth: int | None = None,
        depth_offset: float = 0.0,
    ) -> None:
        self.root = Path(root)
        self.name = name
        self.camera_setup = camera if isinstance(camera, CameraSetup) else CameraSetup(camera, "the reader")
        self.camera = self.camera_setup.camera
        setup = self.camera_setup
        self.registration = (DepthRegistration(setup.depth_camera, setup.camera, setup.depth_to_color)
                             if setup.depth_camera is not None else None)
        self._depth_size_camera = setup.depth_camera or setup.camera
        self._timestamps = np.asarray(timestamps, dtype=np.float64)
        self.depth_timestamps = (
            self._timestamps.copy() if depth_timestamps is None else np.asarray(depth_timestamps, dtype=np.float64)
        )
        self.depth_offset = float(depth_offset)  # dataset.offset: added to the depth stamps (their clock's offset)
        self.rgb_files = list(rgb_files)
        self.depth_files = list(depth_files)
        if depth_scale <= 0:
            raise InputError(f"dataset.depth_scale must be positive (got {depth_scale}); TUM uses 5000, PUT 1000")
        self.depth_scale = float(depth_scale)
        self.depth_correction = float(depth_correction)
        self.invalid_depth = invalid_depth
        self._check_first_image()

    def _check_first_image(self) -> None:
        """Intrinsics for another image size are a mistake of the whole run, not of one frame:
        say so before it starts (a first image that cannot be read is left to the frame loop)."""
        if not self.rgb_files or not self.rgb_files[0].is_file():
            return
        img, _ = read_image(self.rgb_files[0])  # no decoder noise for a damaged file (the frame loop names it)
        if img is not None:
            _check_size(self.rgb_files[0], img, self.camera)

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    def load(self, i: int) -> Frame:
        rgb_path, depth_path = self.rgb_files[i], self.depth_files[i]
        rgb = read_rgb(rgb_path, self.camera)
        depth = read_depth(depth_path, self._depth_size_camera, self.depth_correction / self.depth_scale,
                           self.invalid_depth)
        if self.registration is not None:
            depth = self.registration(depth)
        try:
            name = str(rgb_path.relative_to(self.root))
        except ValueError:
            name = str(rgb_path)
        return Frame(i, float(self._timestamps[i]), rgb, depth, self.camera, name,
                     depth_delay=float(self.depth_timestamps[i] + self.depth_offset - self._timestamps[i]))


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
            if ok:
                check_stamps([t], path, [lineno])
        except (ValueError, IndexError):  # IndexError: a line of commas only
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
    return t if np.isfinite(t) and abs(t) <= MAX_STAMP else None


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
    require_file(path, "associations file", "fix dataset.associations or leave it null")
    ts_rgb, f_rgb, ts_d, f_d = [], [], [], []
    for lineno, parts in data_lines(path):
        try:
            a, b = float(parts[0]), float(parts[2])
            ok = len(parts) == 4 and np.isfinite([a, b]).all()
            if ok:
                check_stamps([[a, b]], path, [lineno])
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
    """The colour camera of a camera file (``camera.yaml``; :mod:`rgbdslam.datasets.camera_file`)."""
    return read_camera_file(path).camera


def _eth3d_camera(root: Path) -> CameraSetup | None:
    """ETH3D SLAM: ``calibration.txt`` holds 'fx fy cx cy'; the size is the first colour image's."""
    p = root / "calibration.txt"
    if not p.is_file():
        return None
    rows = [f for _, f in data_lines(p)]
    try:
        fx, fy, cx, cy = (float(x) for x in rows[0])
    except (IndexError, ValueError):
        raise InputError(f"{p}: expected one line 'fx fy cx cy' (ETH3D SLAM calibration)") from None
    w, h = 640, 480
    try:
        first = root / _image_list(root, "rgb")[1][0]
        img, _ = read_image(first)
        if img is not None:
            h, w = img.shape[:2]
    except InputError:
        pass
    return CameraSetup(validate.camera(fx, fy, cx, cy, w, h, name="eth3d", where=str(p)), f"{p.name} (ETH3D SLAM)",
                       depth_scale=TUM_DEPTH_SCALE)


def _own_camera(root: Path) -> CameraSetup | None:
    """What a TUM-like folder says about its camera: ETH3D's calibration.txt or freiburg1/2/3 in
    the folder name (TUM)."""
    eth = _eth3d_camera(root)
    if eth is not None:
        return eth
    name = root.resolve().name.lower()
    for k in ("1", "2", "3"):
        if f"freiburg{k}" in name or f"fr{k}_" in name:
            return CameraSetup(CAMERAS[f"fr{k}"], f"'freiburg{k}' in the folder name")
    return None


def tum_camera_setup(root: Path, cfg) -> CameraSetup:
    """The camera for a TUM-layout folder (see the module docstring for the order)."""
    return resolve_camera(cfg, root, _own_camera(root))


def choose_camera(root: Path, camera: str = "auto") -> Camera:
    """The camera for a TUM-layout folder chosen by name (``camera``) or found in the folder."""
    from rgbdslam.datasets.config import DatasetConfig

    return tum_camera_setup(Path(root), DatasetConfig(camera=camera)).camera


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
        from rgbdslam.datasets.config import DatasetConfig
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
        setup = tum_camera_setup(root, cfg)
        super().__init__(
            root=root,
            name=root.resolve().name,
            camera=setup,
            timestamps=ts_rgb[ia],
            rgb_files=[root / f_rgb[i] for i in ia],
            depth_files=[root / f_d[j] for j in ib],
            depth_scale=pick_depth_scale(cfg, setup, TUM_DEPTH_SCALE),
            depth_correction=cfg.depth_correction,
            depth_timestamps=ts_d[ib],
            depth_offset=cfg.offset,
        )

    def groundtruth(self) -> Trajectory | None:
        p = optional_file(self.root / "groundtruth.txt", "ground-truth file")
        return read_tum(p) if p is not None else None
