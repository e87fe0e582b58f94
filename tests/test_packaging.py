"""rgbdslam as a real package: a wheel built from the sources, installed into a new virtual
environment and run from a folder far from the repository, has its presets and cameras and runs
the demo, a TUM folder, a ROS bag and 7-Scenes (with the shipped camera), also as ``python -m rgbdslam``.

To stay quick and offline the new environment gets the wheel with ``--no-deps`` and finds the
already installed dependencies (numpy, open3d, ...) through a ``.pth`` line naming the test
environment's site-packages; that folder's own ``.pth`` files (the editable install of the
checkout) are not processed from there, and the test checks that ``rgbdslam`` is imported from
the new environment, not from the checkout. The dependency resolution itself (``pip install .``
with the pinned versions) is what ``scripts/setup.sh`` does on every fresh machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from rgbdslam.datasets.testing import write_bag
from tests.conftest import DATA, TUM_DESK9, need

pytestmark = pytest.mark.data  # runs a TUM folder from the installed wheel


REPO = Path(__file__).resolve().parent.parent


def _run(cmd, cwd, env, timeout=600):
    res = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{' '.join(map(str, cmd))}\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}"
    return res


@pytest.mark.slow
def test_wheel_installs_and_runs_from_any_folder(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(REPO / "rgbdslam", src / "rgbdslam", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "RGBDSLAM_DATA", "VIRTUAL_ENV")}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    # build: the backend pinned in pyproject (setuptools >= 77 for the SPDX licence string)
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", tmp_path / "dist",
          src], cwd=tmp_path, env=env)
    wheel = next((tmp_path / "dist").glob("rgbdslam-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    presets = sorted(n for n in names if n.startswith("rgbdslam/presets/") and n.endswith(".yaml"))
    assert {"rgbdslam/presets/tum_fr1.yaml", "rgbdslam/presets/default.yaml"} <= set(presets)
    assert not any(n.startswith(("configs/", "tests/")) for n in names)
    assert {"rgbdslam/cameras/7scenes.yaml", "rgbdslam/__main__.py"} <= set(names)
    # a new environment that sees the installed dependencies but not the checkout
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=tmp_path, env=env)
    py = venv / "bin" / "python"
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path, env).stdout.strip())
    (site / "_rgbdslam_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    # the outer pip installs into the new environment (pip --python): no ensurepip needed
    _run([sys.executable, "-m", "pip", "--python", py, "install", "-q", "--no-deps", "--no-index", wheel],
         cwd=tmp_path, env=env)
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = _run([py, "-c", "import rgbdslam; print(rgbdslam.__file__)"], work, env).stdout.strip()
    assert where.startswith(str(site)), where
    exe = venv / "bin" / "rgbdslam"
    out = _run([exe, "config", "-c", "tum_fr1"], work, env).stdout
    assert "camera: fr1" in out
    demo = _run([exe, "demo", "--frames", "40", "-o", "demo", "--set", "mapping.mesh=false"], work, env)
    assert (work / "demo" / "run" / "trajectory.tum").is_file(), demo.stderr[-2000:]
    assert "ATE RMSE" in demo.stderr + demo.stdout
    # a TUM folder and a ROS 1 bag in one call (one config: the bag holds TUM's raw depth units)
    bag = write_bag(TUM_DESK9, work / "desk.bag", "ros1", frames=5)
    res = _run([exe, "run", need(TUM_DESK9), bag, "-o", "runs", "--no-map", "-q", "--set", "dataset.depth_scale=5000"],
               work, env)
    assert "from 'freiburg1' in the folder name" in " ".join(res.stderr.split())
    assert "from CameraInfo on /camera/color/camera_info" in " ".join(res.stderr.split())
    assert len((work / "runs" / TUM_DESK9.name / "trajectory.tum").read_text().splitlines()) >= 9
    assert len((work / "runs" / "desk.bag" / "trajectory.tum").read_text().splitlines()) >= 5
    # `python -m rgbdslam`, and 7-Scenes with the camera shipped in the package, no flags
    assert _run([py, "-m", "rgbdslam", "--help"], work, env).stdout.startswith("Usage: python -m rgbdslam")
    seven = need(DATA / "7scenes" / "frames_0000_0299")
    info = _run([exe, "info", seven], work, env).stdout
    assert "camera      7scenes: fx 530.0 fy 530.0" in info and "shipped with rgbdslam" in info, info
    _run([exe, "run", seven, "-o", "seven", "--max-frames", "20", "--no-map", "-q"], work, env)
    run = json.loads((work / "seven" / "run.json").read_text())
    assert run["tracked"] == 20 and run["camera_source"].startswith("the 7-Scenes camera shipped with rgbdslam")
    # no data folder outside the package: the pose-graph benchmark asks for one
    res = subprocess.run([exe, "posegraph", "bench", "--dataset", "m3500", "--instances", "1", "-q"], cwd=work,
                         env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "set RGBDSLAM_DATA" in res.stderr
