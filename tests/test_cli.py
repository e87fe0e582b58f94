"""The command line in scripts and small terminals: progress without a terminal, 80 columns,
frame-selection flags, a run folder's config.yaml that can be given back without harm."""

from __future__ import annotations

import io
import json
import re

import pytest
import yaml
from rich.console import Console

from tests.conftest import assert_cli_error, cli
from rgbdslam import ui
from rgbdslam.runfolder.folder import summary_lines


def test_plain_progress_lines_when_not_a_terminal(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(ui, "console", Console(file=buf, force_terminal=False, width=80))
    with ui.frame_progress(10, "SLAM seq", every=0.0) as advance:
        for _ in range(10):
            advance("2 loops, 0 lost")
    lines = buf.getvalue().splitlines()
    assert len(lines) == 9  # every frame but the last (the summary follows it)
    assert lines[0].startswith("SLAM seq: 1/10 (10 %), ") and lines[0].endswith(" left; 2 loops, 0 lost")
    assert re.search(r"\d+\.\d/s, \d+:\d\d:\d\d left", lines[-1])
    # default: one line every few seconds, not one per frame
    buf.truncate(0)
    with ui.frame_progress(1000, "SLAM seq") as advance:
        for _ in range(1000):
            advance()
    assert buf.getvalue() == ""


def test_eighty_column_bar_keeps_count_rate_and_time_left(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(ui, "console", Console(file=buf, force_terminal=True, width=80, color_system=None))
    with ui.frame_progress(798, "SLAM rgbd_dataset_freiburg1_rpy_head200_and_more") as advance:
        for _ in range(798):
            advance("24 loops, 3 lost, 2 restarts")
    last = [ln for ln in re.split(r"[\r\n]", buf.getvalue()) if "798" in ln][-1]
    last = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", last)
    assert len(last.rstrip()) <= 80
    assert "798/798" in last and "frames/s" in last and re.search(r"\d:\d\d:\d\d", last), last


def test_closing_summary_fits_eighty_columns():
    s = {"frames": 12345, "tracked": 12000, "lost": 300, "skipped": 45, "keyframes": list(range(2500)),
         "loops": [[1, 2]] * 310, "fps": 123.4, "processing_fps": 234.5, "restarts": [1000, 5000, 9000],
         "relocalized": 0, "segments": [{"first": 1000, "last": 4999, "frames": 3999, "map": False},
                                        {"first": 9000, "last": 12344, "frames": 3300, "map": False}],
         "evaluation": {"ate": {"rmse": 0.01234, "n_pairs": 12000}}}
    lines = [text for _, text in summary_lines(s)]
    assert all(len(t) <= 80 for t in lines), [t for t in lines if len(t) > 80]
    assert "without waiting for images" in " ".join(lines)


@pytest.fixture(scope="module")
def desk_run(tmp_path_factory):
    from tests.conftest import TUM_DESK9, need

    seq = need(TUM_DESK9)
    out = tmp_path_factory.mktemp("cli") / "run"
    rrd = out.parent / "first.rrd"
    res = cli(["run", seq, "--out", out, "--no-map", "-q", "--rerun-save", rrd, "--max-frames", 6, "--stride", 1])
    assert res.exit_code == 0, res.output
    return seq, out, rrd


@pytest.mark.data
def test_frame_flags_select_frames(desk_run):
    _, out, _ = desk_run
    assert json.loads((out / "run.json").read_text())["frames"] == 6
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["dataset"]["max_frames"] == 6  # the selection is part of the run: repeated from config.yaml


@pytest.mark.data
def test_rerun_from_config_yaml_keeps_the_earlier_recording(desk_run, tmp_path):
    seq, out, rrd = desk_run
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["output"]["rerun_save"] is None and saved["output"]["rerun"] is False
    before = rrd.stat().st_mtime_ns, rrd.stat().st_size
    res = cli(["run", seq, "--config", out / "config.yaml", "--out", tmp_path / "again", "-q", "--no-map"])
    assert res.exit_code == 0, res.output
    assert (rrd.stat().st_mtime_ns, rrd.stat().st_size) == before
    assert json.loads((tmp_path / "again" / "run.json").read_text())["frames"] == 6


@pytest.mark.data
def test_frame_flags_are_checked_like_set(desk9):
    assert_cli_error(cli(["run", desk9, "--stride", 0, "-q"]), "config key 'dataset.stride' must be at least 1; got 0")


@pytest.mark.data
def test_fuse_set_outside_mapping_is_an_error(desk_run):
    _, out, _ = desk_run
    before = sorted(p.name for p in (out / "map").iterdir())  # a --no-map run: the landmark map's top view only
    res = cli(["fuse", out, "--set", "registration.mp=3", "-q"])
    assert_cli_error(res, "fuse --set changes map settings only (mapping.KEY=VALUE); 'registration.mp' is not one; "
                          "re-run `rgbdslam run` to change it")
    assert sorted(p.name for p in (out / "map").iterdir()) == before == ["landmarks_topview.png"]
