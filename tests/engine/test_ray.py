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


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_head(tmp_path_factory):
    """A running 2-CPU cluster as a user starts it (`ray start --head`), with token authentication
    (a token in RAY_AUTH_TOKEN_PATH, RAY_AUTH_MODE unset: Ray 2.60 turns it on) on a free port and
    a private temporary folder (no other `ray.init()` on this machine finds it). Stopped by ending
    `ray start --block` (never `ray stop`: that ends every Ray on the machine)."""
    import shutil
    import subprocess
    import sys
    import time

    work = tmp_path_factory.mktemp("head")
    token = work / "token"
    token.write_text("5e1f" * 16)
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["RAY_AUTH_TOKEN_PATH"] = str(token)
    tmp = Path("/tmp") / f"rgbdslam_test_ray_{os.getpid()}"  # short: Ray's socket paths must fit
    port = _free_port()
    log = work / "head.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([str(Path(sys.executable).parent / "ray"), "start", "--head", "--block", "--port",
                                 str(port), "--num-cpus", "2", "--include-dashboard", "false",
                                 "--disable-usage-stats", "--temp-dir", str(tmp)], env=env, stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        t0 = time.monotonic()
        while "Ray runtime started" not in log.read_text():
            assert proc.poll() is None and time.monotonic() - t0 < 180, log.read_text()[-2000:]
            time.sleep(0.5)
        assert "Token authentication is enabled" in log.read_text()
        yield f"127.0.0.1:{port}", env
    finally:
        proc.terminate()
        proc.wait(timeout=120)
        shutil.rmtree(tmp, ignore_errors=True)


@pytest.mark.data
def test_sweep_on_a_running_cluster_with_token_authentication(ray_head, tmp_path, desk9):
    """`--address` of a cluster `ray start --head` made: Ray 2.60 refused an explicit address
    ("Authentication token is missing or incorrect") until the driver turned token auth on; a
    wrong token is one clear error."""
    import subprocess
    import sys

    address, env = ray_head
    rgbdslam = str(Path(sys.executable).parent / "rgbdslam")
    args = [rgbdslam, "sweep", str(desk9), "--grid", "loop.enabled=true,false", "-c", "tum_fr1", "-q"]
    res = subprocess.run([*args, "--out", str(tmp_path / "ray"), "--engine", "ray", "--address", address],
                         env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    res = subprocess.run([*args, "--out", str(tmp_path / "local")], env=env, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert _without_timing(tmp_path / "ray" / "results.csv") == _without_timing(tmp_path / "local" / "results.csv")
    bad = dict(env, RAY_AUTH_TOKEN="0" * 64, RAY_AUTH_MODE="token")
    res = subprocess.run([*args, "--out", str(tmp_path / "bad"), "--engine", "ray", "--address", address],
                         env=bad, capture_output=True, text=True, timeout=600)
    assert res.returncode != 0
    assert f"error: the Ray cluster at {address} refused this driver: it uses token authentication" in res.stderr + res.stdout
