"""Right by default on other people's data: the preset chosen from the sequence's layout and
camera when no --config is given (printed with its reason; --config and --set win), a run that
loses most of its frames ending with one error line and exit 3, `python -m rgbdslam`, and the
preset list taken from the package rather than from hand-kept comments."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from tests.conftest import DATA, REPO, TUM_DESK9, cli, need
from rgbdslam.cli import sequence_config
from rgbdslam.config import preset_files
from rgbdslam.datasets.preset_choice import AUTOMATIC
from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

KITTI = DATA / "kitti" / "odometry_06_head51"
SEVEN = DATA / "7scenes" / "frames_0000_0299"


def _choice(path, config=None, overrides=()):
    cfg, choice = sequence_config(path, config, tuple(overrides))
    return cfg, (choice.name if choice is not None else None)


@pytest.mark.data
def test_the_layout_and_camera_choose_the_preset_and_config_and_set_win(tmp_path):
    cfg, name = _choice(need(KITTI))
    assert name == "kitti" and cfg.features.grid_cols == 12 and cfg.matching.max_depth == 40.0  # the kitti preset
    # --set wins over the chosen preset, --config over the choice
    cfg, name = _choice(KITTI, overrides=["features.n_features=1500"])
    assert name == "kitti" and cfg.features.n_features == 1500 and cfg.features.grid_cols == 12
    cfg, name = _choice(KITTI, config="default")
    assert name is None and cfg.features.grid_cols == 1
    # TUM: the camera the folder name says; a copy under another name has none (the default)
    assert _choice(need(TUM_DESK9))[1] == "tum_fr1"
    mine = tmp_path / "my_desk"
    shutil.copytree(TUM_DESK9, mine)
    assert _choice(mine)[1] == "default"
    assert _choice(mine, overrides=["dataset.camera=fr3"])[1] == "tum_fr3"
    assert _choice(need(SEVEN))[1] == "default"  # 7-Scenes: indoor Kinect, its camera shipped with rgbdslam
    # a KITTI-layout folder of a 640x480 indoor camera (rgbdslam synth --stereo) is not KITTI's car
    synth = tmp_path / "synth_kitti"
    generate_stereo_sequence(synth, 0.1, "kitti", frames=2, seed=0, width=64, height=48)
    assert _choice(synth)[1] == "default"
    assert _choice(tmp_path / "missing")[1] is None  # opening it says what is wrong, not the choice
    res = cli(["info", KITTI])
    assert res.exit_code == 0 and "\npreset      kitti: KITTI odometry layout" in res.output, res.output


def test_every_automatic_choice_is_a_shipped_preset_and_the_list_comes_from_the_package():
    shipped = set(preset_files())
    assert set(AUTOMATIC) <= shipped
    res = cli(["config", "--list-presets"])
    assert res.exit_code == 0, res.output
    listed = {ln.split()[0] for ln in res.output.splitlines() if ln and not ln.startswith(" ")}
    assert listed == shipped
    assert "kitti        KITTI odometry" in res.output
    # the hand-kept lists that went stale are gone: default.yaml names no reader kinds
    assert "auto | tum | put" not in (REPO / "rgbdslam" / "presets" / "default.yaml").read_text()


def test_python_dash_m_rgbdslam():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-m", "rgbdslam", "--help"], capture_output=True, text=True, env=env,
                         cwd=REPO.parent, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("Usage: python -m rgbdslam [OPTIONS] COMMAND") and " run " in res.stdout


@pytest.mark.data
@pytest.mark.slow
def test_the_kitti_folder_is_tracked_without_flags(tmp_path):
    """KITTI 06 frames 0-50 in KITTI's own layout, no --config: the kitti preset is chosen and
    every frame tracked (the indoor default tracked 3 of 51, ATE 19 m)."""
    res = cli(["run", need(KITTI), "--out", tmp_path / "run", "--no-map", "-q"])
    assert res.exit_code == 0, res.output
    assert "preset kitti: KITTI odometry layout with KITTI's 1226x370 car-mounted stereo camera" in res.output
    s = json.loads((tmp_path / "run" / "run.json").read_text())
    ev = json.loads((tmp_path / "run" / "evaluation.json").read_text())
    assert s["tracked"] == 51 and s["lost"] == 0 and s["status"] == "finished"
    assert ev["ate"]["rmse"] < 0.045, ev["ate"]  # 0.0432 m


@pytest.mark.data
@pytest.mark.slow
def test_a_run_that_loses_most_frames_is_one_error_line_with_the_fix(tmp_path):
    """The indoor default on KITTI loses 48 of 51 frames: not a 19 m ATE and exit 0, but exit 3,
    one line naming the likely fix, and run.json saying failed (the outputs stay for a look)."""
    res = cli(["run", need(KITTI), "--out", tmp_path / "run", "--no-map", "-q", "-c", "default"])
    assert res.exit_code == 3, res.output
    err = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and res.stderr.strip().splitlines()[-1] == err[0], res.stderr  # the closing line
    assert err[0].startswith("error: 48 of 51 frames of kitti_06 could not be tracked"), err
    assert "--config kitti" in err[0]
    s = json.loads((tmp_path / "run" / "run.json").read_text())
    assert s["status"] == "failed" and s["error"] in err[0] and (tmp_path / "run" / "trajectory.tum").is_file()
