"""Finite but absurd numbers are refused where they are read (issue 16, class 6): one error line
naming file:line, exit 2, and no NumPy warning on the way (rgbdslam.io.numbers)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from rgbdslam.cli import main
from rgbdslam.errors import InputError

GOOD = "".join(f"{1000 + 0.1 * i:.1f} {0.1 * i:.3f} {0.05 * i * i:.3f} 0 0 0 {np.sin(0.1 * i):.6f} "
               f"{np.cos(0.1 * i):.6f}\n" for i in range(12))


def _one_line(res) -> str:
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, (res.exception, res.output)
    lines = res.output.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    return lines[0]


def _with(text: str, line: int, row: str) -> str:
    rows = text.splitlines()
    rows[line - 1] = row
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("row, message", [
    ("1000.4 0.4 0.8 0 1e200 1e200 1e200 1e200", "est.tum:5: the quaternion (qx qy qz qw) has length 2e+200, not 1"),
    ("1000.4 0.4 0.8 0 0 0 0 2", "est.tum:5: the quaternion (qx qy qz qw) has length 2, not 1"),
    ("1000.4 0.4 1e300 0 0 0 0 1", "est.tum:5: position 1e+300 is beyond ±1e+09; positions must be metres"),
    ("1e300 0.4 0.8 0 0 0 0 1", "est.tum:5: time stamp 1e+300 is beyond ±1e+12; time stamps must be seconds"),
])
def test_absurd_trajectory_values_are_one_line_naming_the_line(tmp_path, row, message):
    gt, est = tmp_path / "gt.tum", tmp_path / "est.tum"
    gt.write_text(GOOD)
    est.write_text(_with(GOOD, 5, row))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not a single NumPy warning on the way to the error
        res = CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--no-plots"])
    assert message in _one_line(res)


def test_ground_truth_scaled_by_1e300_and_absurd_options(tmp_path):
    gt, est = tmp_path / "gt.tum", tmp_path / "est.tum"
    est.write_text(GOOD)
    gt.write_text("".join(" ".join([p[0], *(f"{float(x) * 1e300:g}" for x in p[1:4]), *p[4:]]) + "\n"
                          for p in (ln.split() for ln in GOOD.splitlines())))
    assert "gt.tum:2: position 1e+299 is beyond ±1e+09" in _one_line(
        CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--no-plots"]))
    gt.write_text(GOOD)
    for opt, value in (("--offset", "1e300"), ("--max-difference", "1e300")):
        assert opt in _one_line(CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--no-plots", opt, value]))


def test_one_rule_for_repeated_time_stamps(tmp_path):
    """Ground truth with two poses at one time is refused like an estimate (and image lists)."""
    gt, est = tmp_path / "gt.tum", tmp_path / "est.tum"
    est.write_text(GOOD)
    gt.write_text(GOOD + GOOD.splitlines()[3] + "\n")
    line = _one_line(CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--no-plots"]))
    assert "the ground truth has more than one pose at time stamp 1000.300000" in line


def test_other_readers_refuse_absurd_numbers(tmp_path):
    from rgbdslam.posegraph.graph_io import read_graph
    from rgbdslam.datasets.put import read_initial_position, read_matched
    from rgbdslam.datasets.tum import read_associations, read_file_list
    from rgbdslam.mapping.map2d import read_accelerometer

    cases = [
        (read_file_list, "rgb.txt", "1.0 rgb/a.png\n1e300 rgb/b.png\n", "rgb.txt:2: time stamp 1e+300 is beyond"),
        (read_associations, "assoc.txt", "1.0 a.png 1e300 b.png\n", "assoc.txt:1: time stamp 1e+300 is beyond"),
        (read_associations, "assoc.txt", "1.0 a.png nan b.png\n", "assoc.txt:1: expected 'rgb_ts rgb_file"),
        (read_matched, "matched", "1.0 1.0\n2.0 2e300\n", "matched:2: time stamp 2e+300 is beyond"),
        (read_initial_position, "initialPosition", "0 0 0 1e200 1e200 1e200 1e200",
         "initialPosition:1: the quaternion (qx qy qz qw) has length 2e+200, not 1"),
        (read_accelerometer, "accelerometer.txt", "1.0 0 -9.8 1e300\n", "accelerometer.txt:1: acceleration 1e+300"),
        (read_graph, "g.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1e300 0 0 1 0 1\n",
         "g.g2o:3: EDGE_SE2 number 1e+300 is beyond ±1e+16; fix the line"),
    ]
    for reader, name, text, message in cases:
        p = tmp_path / name
        p.write_text(text)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(InputError) as e:
                reader(p)
        assert message in str(e.value), (name, str(e.value))


@pytest.mark.data
def test_depth_scale_1e_300_is_bad_input_not_lost_tracking(desk9, tmp_path):
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(tmp_path / "r"), "-q",
                                    "--set", "dataset.depth_scale=1e-300"])
    assert "config key 'dataset.depth_scale' must be between 0.001 and 1000000" in _one_line(res)
    assert not (tmp_path / "r").exists()
