"""ICL-NUIM reader, for the data set's TUM-compatible archives (``living_room_traj2_frei_png``,
``traj0_frei_png``, ...).

Layout: ``rgb/N.png`` and ``depth/N.png`` named by the frame number N (living room from 0,
office from 1), ``associations.txt`` ('N depth/N.png N rgb/N.png': depth first) and the ground
truth ``*.gt.freiburg`` (``livingRoom2.gt.freiburg``, ``traj0.gt.freiburg``) in TUM's line format.
Depth: 16-bit PNG, 5000 units per metre. Camera: the published fx 481.20, fy 480.00, cx 319.5,
cy 239.5 (the page gives fy as -480: that is for the renderer's bottom-up rows; the PNGs are stored
top-down, so fy is positive here), no distortion.

Two conventions differ from TUM's and are converted where they are read, so that ``run``,
``evaluate``, ``info``, the plots, the exports and the batch tables all see the same thing:

* **Frame numbers, not times.** The first column of ``associations.txt`` and of the ground truth
  is the frame number (image ``N.png`` <-> the pose whose first column is N). The data set was
  rendered at 30 Hz, so frame N is given the time stamp N / 30 s (RPE per second, speeds and the
  time options then mean what they say).
* **A y-up world.** The poses are the renderer's (y up) while the images are stored top-down:
  every pose is reflected about the XZ plane, T -> F T F with F = diag(1, -1, 1) (rotation and
  translation; the result is a rotation again). Without it no rigid alignment fits a correct
  trajectory (docs/formats.md "ICL-NUIM" gives the measured effect).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.datasets.camera_file import CameraSetup, resolve_camera
from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.tum import RgbdFileSequence, data_lines, pick_depth_scale, select_frames
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.io.text import require_file
from rgbdslam.io.trajectory import Trajectory, read_tum

RATE_HZ = 30.0
DEPTH_SCALE = 5000.0
ASSOCIATIONS = "associations.txt"
CAMERA = Camera(481.20, 480.00, 319.5, 239.5, 640, 480, (0.0,) * 5, "icl_nuim")
# the reflection about the XZ plane that takes the renderer's y-up world to the images' y-down one
FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])


def groundtruth_file(root: Path) -> Path | None:
    found = sorted(Path(root).glob("*.gt.freiburg"))
    return found[0] if found else None


def _number(name: str) -> int | None:
    stem = Path(name).stem
    return int(stem) if Path(name).suffix == ".png" and stem.isdigit() else None


def _numbered(folder: Path) -> dict[int, str]:
    """Frame number -> file name (relative to the sequence) of the frame-numbered PNGs in ``folder``."""
    if not folder.is_dir():
        return {}
    return {n: f"{folder.name}/{p.name}" for p in folder.glob("*.png") if (n := _number(p.name)) is not None}


def _is_icl(path: Path) -> bool:
    return (path.is_dir() and groundtruth_file(path) is not None
            and bool(_numbered(path / "rgb")) and bool(_numbered(path / "depth")))


def read_associations(path: Path) -> tuple[list[int], list[str], list[str]]:
    """Frame numbers, colour and depth files of ICL-NUIM's ``associations.txt`` ('N depth/N.png N
    rgb/N.png'; a 'N rgb/.. N depth/..' order is recognised by the folder names too)."""
    require_file(path, "associations file", "fix dataset.associations or leave it null")
    numbers, rgb, depth = [], [], []
    for lineno, parts in data_lines(path):
        ok = len(parts) == 4 and parts[0].isdigit() and parts[0] == parts[2]
        if ok:
            first_is_depth = parts[1].startswith("depth")
            ok = first_is_depth != parts[3].startswith("depth")
        if not ok:
            raise InputError(f"{path}:{lineno}: expected 'N depth/N.png N rgb/N.png' (ICL-NUIM: frame number, "
                             f"depth file, the same number, colour file); got {' '.join(parts)[:60]!r}")
        numbers.append(int(parts[0]))
        depth.append(parts[1] if first_is_depth else parts[3])
        rgb.append(parts[3] if first_is_depth else parts[1])
    if not numbers:
        raise InputError(f"{path} pairs no frames; it needs 'N depth/N.png N rgb/N.png' lines")
    order = np.argsort(numbers, kind="stable")
    return [numbers[k] for k in order], [rgb[k] for k in order], [depth[k] for k in order]


def _frames(root: Path, cfg) -> tuple[list[int], list[str], list[str]]:
    """The paired frames: from the associations file if there is one, else every frame number
    that has both a colour and a depth PNG."""
    assoc = Path(cfg.associations) if cfg.associations else root / ASSOCIATIONS
    if cfg.associations and not assoc.is_absolute() and (root / assoc).is_file():
        assoc = root / assoc
    if cfg.associations or assoc.is_file():
        return read_associations(assoc)
    rgb, depth = _numbered(root / "rgb"), _numbered(root / "depth")
    numbers = sorted(set(rgb) & set(depth))
    if not numbers:
        raise InputError(f"{root}: no frame number has both rgb/N.png and depth/N.png (ICL-NUIM layout)")
    return numbers, [rgb[n] for n in numbers], [depth[n] for n in numbers]


def read_groundtruth(path: Path) -> Trajectory:
    """An ICL-NUIM ``*.gt.freiburg`` file in this project's conventions: time stamps N / 30 s from
    the frame numbers N of its first column, poses reflected about the XZ plane (F T F)."""
    raw = read_tum(path)
    numbers = np.round(raw.timestamps)
    if not np.allclose(raw.timestamps, numbers, rtol=0, atol=1e-6):
        raise InputError(f"{path}: the first column of an ICL-NUIM ground truth is the frame number; "
                         f"{raw.timestamps[~np.isclose(raw.timestamps, numbers, rtol=0, atol=1e-6)][0]} is not one")
    return Trajectory(numbers / RATE_HZ, FLIP_Y @ raw.poses @ FLIP_Y)


def convention(path: Path) -> str:
    """One line saying how the ground truth ``path`` was converted (printed by run, info, evaluate)."""
    return (f"{path.name} read as ICL-NUIM: frame N at N/{RATE_HZ:g} s, y-up poses reflected about the XZ "
            f"plane (T -> F T F, F = diag(1, -1, 1))")


@reader("icl", _is_icl, before="tum")
class IclSequence(RgbdFileSequence):
    """An ICL-NUIM TUM-compatible folder; see the module docstring."""

    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig

        cfg = cfg or DatasetConfig()
        root = Path(root)
        if not root.is_dir():
            raise InputError(f"sequence folder {root} does not exist; check the path")
        numbers, rgb, depth = _frames(root, cfg)
        keep = select_frames(len(numbers), cfg, root)
        own = CameraSetup(CAMERA, "ICL-NUIM's published intrinsics (fy positive: the PNGs are stored top-down)",
                          depth_scale=DEPTH_SCALE)
        setup = resolve_camera(cfg, root, own)
        self.frame_numbers = [numbers[k] for k in keep]
        super().__init__(
            root=root,
            name=root.resolve().name,
            camera=setup,
            timestamps=np.array(self.frame_numbers, dtype=np.float64) / RATE_HZ,
            rgb_files=[root / rgb[k] for k in keep],
            depth_files=[root / depth[k] for k in keep],
            depth_scale=pick_depth_scale(cfg, setup, DEPTH_SCALE),
            depth_correction=cfg.depth_correction,
        )
        gt = groundtruth_file(root)
        self.groundtruth_convention = convention(gt) if gt is not None else None

    def groundtruth_path(self) -> Path | None:
        return groundtruth_file(self.root)

    def groundtruth(self) -> Trajectory | None:
        p = groundtruth_file(self.root)
        return read_groundtruth(p) if p is not None else None
