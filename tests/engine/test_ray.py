"""The Ray engine on a real local Ray cluster (2 CPUs, started once for this module): the same
results as a local run, a worker that dies has its job re-run, job errors keep their type."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

import tests.engine.jobs as jobs
from rgbdslam.engine import build_engine
from rgbdslam.errors import InputError

REPO = Path(__file__).resolve().parents[2]  # workers import tests.engine.jobs from here


@pytest.fixture(scope="module")
def cluster():
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR",
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}})
    yield ray
    ray.shutdown()


def test_ray_jobs_run_in_other_processes_with_the_shared_object(cluster):
    with build_engine("ray", 2) as eng:
        assert eng.workers == 2
        out = dict(eng.map(jobs.scaled, [(k,) for k in range(5)], shared={"factor": 3}))
    assert [out[k][0] for k in range(5)] == [3 * k for k in range(5)]
    assert os.getpid() not in {v[1] for v in out.values()}
    assert cluster.is_initialized()  # a session the engine did not start is left running


def test_a_ray_worker_that_dies_has_its_job_run_again(cluster, tmp_path):
    marker = tmp_path / "died"
    with build_engine("ray", 2) as eng:
        out = dict(eng.map(jobs.die_once, [(str(marker), k) for k in range(3)]))
    assert marker.read_text() == "died"
    assert out == {k: k + 100 for k in range(3)}


def test_a_job_error_comes_back_as_itself(cluster):
    with build_engine("ray", 2) as eng, pytest.raises(InputError, match=r"^bad input 7$"):
        list(eng.map(jobs.refuse, [(7,)]))


def _without_timing(path):
    from rgbdslam.sweep import TIMING_COLUMNS

    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in csv.DictReader(open(path))]


@pytest.mark.data
def test_sweep_on_ray_gives_the_local_table(cluster, tmp_path, desk9):
    from rgbdslam.sweep import run_sweep

    grid = ["loop.enabled=true,false"]
    local = run_sweep([desk9], grid, tmp_path / "local", config_path="tum_fr1", progress=False)
    ray = run_sweep([desk9], grid, tmp_path / "ray", config_path="tum_fr1", engine="ray", workers=2,
                    progress=False)
    assert local["ran"] == ray["ran"] == 2 and ray["engine"].startswith("ray")
    assert _without_timing(tmp_path / "local" / "results.csv") == _without_timing(tmp_path / "ray" / "results.csv")
    assert (tmp_path / "ray" / "cells" / desk9.name / "loop.enabled=true" / "trajectory.tum").is_file()


@pytest.mark.data
def test_several_sequences_on_ray_match_the_local_batch(cluster, tmp_path, desk9):
    from rgbdslam.batch import run_sequences
    from rgbdslam.config import load_config

    cfg = load_config("tum_fr1", ["mapping.enabled=false"])
    seqs = [desk9, tmp_path / "missing"]
    local = run_sequences(seqs, tmp_path / "l", cfg, progress=False)
    ray = run_sequences(seqs, tmp_path / "r", cfg, progress=False, engine="ray", workers=2)
    key = lambda rows: [(Path(r["sequence"]).name, r["status"][:30], r.get("tracked"), r.get("ate_rmse")) for r in rows]  # noqa: E731
    assert key(local) == key(ray)
    assert local[0]["status"] == "ok" and "does not exist" in local[1]["status"] or "missing" in local[1]["status"]
    assert (tmp_path / "r" / desk9.name / "trajectory.tum").read_text() == \
        (tmp_path / "l" / desk9.name / "trajectory.tum").read_text()


def test_posegraph_bench_on_ray_matches_one_local_worker(cluster):
    from rgbdslam.posegraph.bench import run_benchmark
    from rgbdslam.posegraph.synthetic import manhattan_world

    ref, gt = manhattan_world(120, seed=4)
    kw = dict(instances=3, max_iter=30, seed=2, progress=False, reference=(ref, gt, "synthetic grid"),
              methods=("odometry", "masat"))
    a = run_benchmark("m3500", [(0.05, 0.05, 0.05)], workers=1, **kw)
    b = run_benchmark("m3500", [(0.05, 0.05, 0.05)], workers=2, engine="ray", **kw)
    k = lambda r: (r.instance, r.method, r.converged_rel, r.iterations_rel, r.reduced_chi2_rel)  # noqa: E731
    assert [k(r) for r in a["records"]] == [k(r) for r in b["records"]]
    assert "engine ray" in b["report"]
