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
