"""The preset a sequence's layout and camera call for, when the user names none (``--config``).

``rgbdslam run`` and ``rgbdslam info`` without ``--config`` print the choice and its reason;
``--config`` (and ``--set`` over either) wins. A library caller passes its own config: nothing is
chosen for it. The rules, by the reader that recognises the folder:

* ``kitti`` with KITTI's wide car-mounted camera (width at least 2.5x the height: 1226x370 to
  1242x376) -> ``kitti`` (outdoor distances, ~1 m per frame); a KITTI-layout folder of another
  camera (``rgbdslam synth --stereo`` writes 640x480) keeps the default;
* ``tum`` whose camera is TUM's freiburg1/2/3 (from the folder name or ``dataset.camera``) ->
  ``tum_fr1`` / ``tum_fr2`` / ``tum_fr3``;
* ``put`` -> ``put_kinect1``;
* everything else (ICL-NUIM, 7-Scenes with its shipped camera, ETH3D, EuRoC, stereo folders, bags,
  TUM-layout folders of other cameras) -> ``default``: indoor hand-held RGB-D or stereo, what the
  defaults were tuned on.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rgbdslam.errors import InputError

WIDE = 2.5  # KITTI's cameras: 1226x370 .. 1242x376 (aspect 3.3); indoor cameras 4:3 or 16:9


@dataclass(frozen=True)
class PresetChoice:
    name: str  # a preset shipped in rgbdslam/presets/
    reason: str  # why, one clause

    def describe(self) -> str:
        return f"preset {self.name}: {self.reason} (--config NAME or FILE chooses another)"


# when a preset is chosen without --config (`rgbdslam config --list-presets` prints this beside each)
AUTOMATIC = {
    "kitti": "KITTI layout with KITTI's wide camera",
    "tum_fr1": "TUM layout, camera fr1 (freiburg1 in the folder name)",
    "tum_fr2": "TUM layout, camera fr2 (freiburg2 in the folder name)",
    "tum_fr3": "TUM layout, camera fr3 (freiburg3 in the folder name)",
    "put_kinect1": "PUT layout",
    "default": "every other layout (ICL-NUIM, 7-Scenes, ETH3D, EuRoC, stereo folders, bags, other cameras)",
}

OTHER = {
    "put": ("put_kinect1", "PUT layout ('matched'): a Kinect v1, depth in millimetres"),
    "icl": ("default", "ICL-NUIM layout: rendered indoor RGB-D, what the default is for"),
    "7scenes": ("default", "7-Scenes layout: a hand-held Kinect indoors"),
    "euroc": ("default", "EuRoC layout: an indoor stereo rig, within the default's indoor distances"),
    "stereo": ("default", "stereo folder: the default's indoor distances (use -c kitti for a car-mounted rig)"),
    "rosbag": ("default", "a recording: the camera from its CameraInfo, the indoor default"),
}


def choose_preset(path: str | Path, cfg) -> PresetChoice | None:
    """The preset for the sequence at ``path`` given ``cfg`` (the whole config without a preset:
    defaults, ``--set``, ``--camera``); None when no reader recognises it (opening it then says why)."""
    from rgbdslam.datasets import detect_kind, open_sequence

    path = Path(path)
    try:
        kind = detect_kind(path, cfg.dataset)
        if kind == "kitti":
            cam = open_sequence(path, cfg.dataset).camera
            if cam.width >= WIDE * cam.height:
                return PresetChoice("kitti", f"KITTI odometry layout with KITTI's {cam.width}x{cam.height} "
                                             f"car-mounted stereo camera (outdoor distances)")
            return PresetChoice("default", f"KITTI layout but a {cam.width}x{cam.height} camera, not KITTI's "
                                           f"car-mounted one")
        if kind == "tum":
            from rgbdslam.datasets.tum import tum_camera_setup

            setup = tum_camera_setup(path, cfg.dataset)
            if setup.camera.name in ("fr1", "fr2", "fr3"):
                return PresetChoice(f"tum_{setup.camera.name}", f"TUM layout, camera {setup.camera.name} "
                                                                f"(from {setup.source})")
            return PresetChoice("default", f"TUM layout, camera {setup.camera.name} (from {setup.source})")
    except InputError:
        return None  # opening the sequence for the run says what is wrong, in its own words
    if kind in OTHER:
        return PresetChoice(*OTHER[kind])
    return None
