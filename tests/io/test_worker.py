"""Helper processes' priority: the work while tracking in a niced thread, the rest at the run's."""

from __future__ import annotations

import os
import sys
import threading

import pytest

from rgbdslam.io.worker import in_niced_thread


def _own_nice() -> int:
    """The calling thread's niceness as the kernel schedules it (/proc/self/task/TID/stat, field 19)."""
    tid = threading.get_native_id()
    with open(f"/proc/self/task/{tid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[16])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="threads have a niceness of their own on Linux")
def test_the_niced_thread_runs_at_a_lower_priority_and_the_caller_keeps_its_own():
    before = _own_nice()
    assert in_niced_thread(7, _own_nice) == min(before + 7, 19)
    assert _own_nice() == before and os.getpriority(os.PRIO_PROCESS, 0) == before
    assert in_niced_thread(0, _own_nice) == before


def test_an_error_in_the_niced_thread_is_raised_in_the_caller():
    def fail():
        raise ValueError("boom")

    with pytest.raises(ValueError, match="boom"):
        in_niced_thread(3, fail)


def test_a_process_that_ends_at_once_leaves_no_resource_tracker_warning(tmp_path):
    """An interrupted run ends with ``os._exit`` while its queues' semaphores still exist: the
    resource tracker unlinks them without printing anything after the run's last line. Without
    the quiet start (plain ``mp.get_context("spawn")``) the same script prints the tracker's
    "leaked semaphore" warning."""
    import subprocess
    import sys

    script = tmp_path / "leak.py"
    script.write_text(
        "import os, sys\n"
        "import multiprocessing as mp\n"
        "from rgbdslam.io.worker import spawn_context\n"
        "if __name__ == '__main__':\n"
        "    ctx = spawn_context() if sys.argv[1] == 'quiet' else mp.get_context('spawn')\n"
        "    q = ctx.Queue()\n"
        "    q.put(1)\n"
        "    print('last line', file=sys.stderr, flush=True)\n"
        "    os._exit(0)\n")
    for mode, warned in (("quiet", False), ("plain", True)):
        p = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr
        lines = p.stderr.strip().splitlines()
        assert lines[0] == "last line"
        assert any("resource_tracker" in line for line in lines) is warned, (mode, p.stderr)


_WARM_NICE: list[int] = []  # in the helper process: the niceness its warm-up ran at


def _warm_up_here() -> None:
    _WARM_NICE.append(_own_nice())


def _job_here(a, b):
    return a + b, _WARM_NICE[0], _own_nice(), os.getpid()


def _failing_job(path):
    from rgbdslam.errors import InputError

    raise InputError(f"{path} is bad")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="threads have a niceness of their own on Linux")
def test_a_helper_process_warms_up_niced_and_does_its_job_at_the_run_priority():
    """:class:`rgbdslam.io.worker.Helper`: a real spawned process; its warm-up ran in a thread niced
    by 5, the job in its main thread at the niceness the run had; the job's value comes back."""
    from rgbdslam.io.worker import Helper

    base = os.getpriority(os.PRIO_PROCESS, 0)
    helper = Helper("test helper", "tests.io.test_worker:_warm_up_here", 5)
    try:
        helper.submit("tests.io.test_worker:_job_here", 2, 3)
        total, warm_nice, job_nice, pid = helper.result()
    finally:
        helper.close()
    assert total == 5 and pid != os.getpid()
    assert warm_nice == min(base + 5, 19) and job_nice == base


def test_a_helper_process_raises_its_jobs_error_in_the_run_and_ends_without_a_job():
    from rgbdslam.errors import InputError
    from rgbdslam.io.worker import Helper

    helper = Helper("test helper", "tests.io.test_worker:_warm_up_here", 0)
    helper.submit("tests.io.test_worker:_failing_job", "cloud.ply")
    with pytest.raises(InputError, match="cloud.ply is bad"):
        helper.result()
    helper.close()
    idle = Helper("idle helper", "tests.io.test_worker:_warm_up_here", 0)
    idle.close()  # no job: it ends anyway
    assert not idle._proc.is_alive() and not helper._proc.is_alive()
