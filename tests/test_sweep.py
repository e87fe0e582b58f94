"""rgbdslam sweep: grid parsing, one table over every cell, resuming keeps finished cells."""

from __future__ import annotations

import csv
import json

import pytest

from rgbdslam.errors import ConfigError
from rgbdslam.sweep import TIMING_COLUMNS, parse_grid, run_sweep

from tests.conftest import assert_cli_error, cli


def test_parse_grid_and_its_errors():
    assert parse_grid(["loop.enabled=true,false", "registration.mp=2,4,6"]) == [
        ("loop.enabled", ["true", "false"]), ("registration.mp", ["2", "4", "6"])]
    for bad, msg in [("loop.enabled", "must look like section.key=value1"), ("enabled=1,2", "must look like"),
                     ("loop.enabled=true,,false", "has an empty value"), ("loop.enabled=true,true", "lists a value twice")]:
        with pytest.raises(ConfigError, match=msg):
            parse_grid([bad])
    with pytest.raises(ConfigError, match="loop.enabled is given twice"):
        parse_grid(["loop.enabled=true", "loop.enabled=false"])


def _table(out):
    rows = list(csv.DictReader(open(out / "results.csv")))
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows]


@pytest.mark.data
def test_sweep_runs_every_cell_once_and_resumes(tmp_path, desk9):
    out = tmp_path / "sw"
    res = run_sweep([desk9], ["loop.enabled=true,false", "depth_filter.enabled=true,false"], out,
                    config_path="tum_fr1", progress=False)
    assert res["ran"] == 4 and res["kept"] == 0
    rows = _table(out)
    assert [(r["loop.enabled"], r["depth_filter.enabled"]) for r in rows] == [
        ("true", "true"), ("true", "false"), ("false", "true"), ("false", "false")]
    assert all(r["status"] == "ok" and r["frames"] == "9" and float(r["ate_rmse"]) < 0.02 for r in rows)
    assert all(float(r["rpe_trans_rmse"]) > 0 for r in rows)
    # the cells really ran with their settings: the config each run saved says so
    cfg = (out / "cells" / desk9.name / "loop.enabled=false,depth_filter.enabled=false" / "config.yaml").read_text()
    assert "enabled: false" in cfg.split("loop:")[1].split("\n\n")[0].split("backend:")[0]
    assert (out / "results.md").read_text().count("\n") == 6 and (out / "results.png").stat().st_size > 1000
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("cells/*/*/cell.json")}
    assert len(stamps) == 4
    # the same sweep again keeps every finished cell
    res = run_sweep([desk9], ["loop.enabled=true,false", "depth_filter.enabled=true,false"], out,
                    config_path="tum_fr1", progress=False)
    assert res["ran"] == 0 and res["kept"] == 4 and _table(out) == rows
    assert {p: p.stat().st_mtime_ns for p in out.glob("cells/*/*/cell.json")} == stamps
    res = run_sweep([desk9], ["loop.enabled=false", "depth_filter.enabled=false", "keyframes.max_gap=5"], out,
                    config_path="tum_fr1", progress=False)
    assert res["ran"] == 1 and res["kept"] == 0  # another setting: another cell
    info = json.loads(next(iter(stamps)).read_text())
    assert info["row"]["status"] == "ok" and "config" in info["settings"]


@pytest.mark.data
def test_sweep_cli_prints_the_table_and_refuses_bad_grids(tmp_path, desk9):
    res = cli(["sweep", desk9, "--grid", "loop.enabled=true,false", "-c", "tum_fr1", "--out", tmp_path / "c", "-q"])
    assert res.exit_code == 0, res.output
    assert "| sequence | loop.enabled | status |" in res.stdout and "2 cell(s) run, 0 kept" in res.stdout
    res = cli(["sweep", desk9, "--grid", "loop.nonsense=1,2", "--out", tmp_path / "d"])
    assert res.exit_code == 2 and res.stderr.startswith("error:") and "nonsense" in res.stderr
    assert not (tmp_path / "d").exists()
    assert_cli_error(cli(["sweep", tmp_path / "missing", "--grid", "loop.enabled=true", "--out", tmp_path / "e"]),
                     f"sequence folder {tmp_path / 'missing'} does not exist; check the path (TUM data sets live "
                     f"under ../shared/data/tum)")


def test_cells_whose_names_would_collide_get_folders_of_their_own(tmp_path):
    """``a/b.txt`` and ``a_b.txt`` (and names equal but for case) would share one cell folder:
    each gets its own, the same whatever the order of the values."""
    from rgbdslam.sweep import plan_cells

    seq = tmp_path / "seq"
    for values in (["a/b.txt", "a_b.txt", "A_B.txt", "c.txt"], ["c.txt", "A_B.txt", "a_b.txt", "a/b.txt"]):
        cells = plan_cells([seq], parse_grid([f"dataset.groundtruth={','.join(values)}"]), tmp_path / "out")
        names = {c.assignment[0][1]: c.out_dir.name for c in cells}
        assert len({n.lower() for n in names.values()}) == 4, names
        assert names["c.txt"] == "dataset.groundtruth=c.txt"  # a name that collides with none stays as it was
        assert names["a/b.txt"].startswith("dataset.groundtruth=a_b.txt~") and "/" not in names["a/b.txt"]
        if values[0] == "a/b.txt":
            first = names
    assert names == first


def test_a_grid_beyond_the_bound_is_refused_before_any_cell_is_planned(tmp_path):
    from rgbdslam.sweep import plan_cells

    values = ",".join(f"{0.01 + k / 1000:.3f}" for k in range(40))
    grid = parse_grid([f"mapping.voxel_size={values}", f"mapping.tsdf_voxel={values}"])
    with pytest.raises(ConfigError, match=r"the sweep would run 1600 cells \(1 sequence\(s\) x 40 x 40 values\); at "
                                          r"most 1000 are allowed: split it into several sweeps"):
        plan_cells([tmp_path / "seq"], grid, tmp_path / "out")
    assert len(plan_cells([tmp_path / "seq"], grid[:1], tmp_path / "out")) == 40


@pytest.mark.data
def test_sweep_takes_the_recordings_run_takes(tmp_path, desk9):
    """`sweep` refused a ROS bag file ("sequence folder ... does not exist") that `run` reads."""
    from rgbdslam.datasets.testing import write_bag

    bag = write_bag(desk9, tmp_path / "desk.bag", "ros1", frames=4)
    res = cli(["sweep", bag, "--grid", "loop.enabled=true", "--set", "dataset.depth_scale=5000",
               "--out", tmp_path / "s", "-q"])
    assert res.exit_code == 0, res.output
    assert "1 cell(s) run, 0 kept" in res.stdout


def test_a_grid_over_a_retired_key_is_refused_before_any_cell_is_planned(tmp_path):
    """A removed key swept would run every cell with the same configuration."""
    from rgbdslam.sweep import plan_cells

    with pytest.raises(ConfigError, match=r"^config key 'registration.pregate' \(--set registration.pregate=0\) "
                                          r"was removed: it measured no gain \(docs/frontend.md"):
        plan_cells([tmp_path / "seq"], parse_grid(["registration.pregate=0,0.1"]), tmp_path / "out")
    assert not (tmp_path / "out").exists()
