"""The local engine: in-process, a real process pool, a worker that dies has its job re-run."""

from __future__ import annotations

import os

import pytest

import tests.engine.jobs as jobs
from rgbdslam.engine import EngineError, build_engine
from rgbdslam.errors import InputError


def test_in_process_engine_keeps_order_and_passes_shared():
    with build_engine("local", 1) as eng:
        assert list(eng.map(jobs.square, [(k,) for k in range(5)])) == [(k, k * k) for k in range(5)]
        out = dict(eng.map(jobs.scaled, [(1,), (2,)], shared={"factor": 3}))
    assert [v[0] for v in out.values()] == [3, 6]
    assert {v[1] for v in out.values()} == {os.getpid()}  # really in this process


def test_process_pool_gives_the_same_results_in_other_processes():
    with build_engine("local", 2) as eng:
        out = dict(eng.map(jobs.scaled, [(k,) for k in range(6)], shared={"factor": 2}))
    assert sorted(out) == list(range(6))
    assert [out[k][0] for k in range(6)] == [2 * k for k in range(6)]
    assert os.getpid() not in {v[1] for v in out.values()}


def test_a_worker_that_dies_has_its_job_run_again(tmp_path):
    marker = tmp_path / "died"
    with build_engine("local", 2) as eng:
        out = dict(eng.map(jobs.die_once, [(str(marker), k) for k in range(4)]))
    assert marker.read_text() == "died"  # one worker really died
    assert out == {k: k + 100 for k in range(4)}


def test_a_job_that_always_kills_its_worker_gives_up_with_an_error():
    eng = build_engine("local", 2, retries=1)
    with pytest.raises(EngineError, match="lost 2 times with its worker"):
        list(eng.map(jobs.die_always, [(1,), (2,)]))


def test_job_errors_come_back_with_their_type():
    with build_engine("local", 2) as eng, pytest.raises(InputError, match=r"bad input [34]"):
        list(eng.map(jobs.refuse, [(3,), (4,)]))


def test_unknown_engine_and_stray_address_are_input_errors():
    with pytest.raises(InputError, match="unknown engine 'spark'"):
        build_engine("spark")
    with pytest.raises(InputError, match="--address is the address of a Ray cluster"):
        build_engine("local", 1, address="auto")
    with pytest.raises(InputError, match="--workers must be a whole number >= 1"):
        build_engine("local", 0)


@pytest.mark.data
def test_engine_options_need_several_sequences(tmp_path, desk9):
    from tests.conftest import cli

    res = cli(["run", desk9, "--workers", "2", "--out", tmp_path / "r"])
    assert res.exit_code == 2 and "give more than one SEQUENCE" in res.stderr
    assert not (tmp_path / "r").exists()
