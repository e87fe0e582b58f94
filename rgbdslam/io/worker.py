"""A helper process of a run (the map process, the plot process): started with ``spawn``, it
takes jobs from one queue and puts ``(status, value)`` on another. The pieces both use."""

from __future__ import annotations

import os
import queue


def receive(results, proc, what: str) -> tuple[str, object]:
    """The next ``(status, value)`` from ``results``; an RgbdslamError naming ``what`` when the
    process ``proc`` ended without sending one."""
    from rgbdslam.errors import RgbdslamError

    while True:
        try:
            return results.get(timeout=1.0)
        except queue.Empty:
            if not proc.is_alive():
                raise RgbdslamError(f"the {what} ended unexpectedly (exit code {proc.exitcode})") from None


def end(proc, jobs, timeout: float = 5.0) -> None:
    """Ask the process to end (``None`` as its next job), wait ``timeout`` s, then terminate it."""
    if proc.is_alive():
        jobs.put(None)
        proc.join(timeout=timeout)
        if proc.is_alive():
            proc.terminate()
            proc.join()
    jobs.cancel_join_thread()  # its reader is gone: exit must not wait to flush the queue


def exit_now(results) -> None:
    """In the helper process, after its last result: wait until that is in the pipe, then end
    without the interpreter's teardown (freeing Open3D's or matplotlib's modules takes longer than
    the last job; the run waits for the process to end)."""
    results.close()
    results.join_thread()
    os._exit(0)


def lower_priority(nice: int) -> None:
    """In the helper process: yield the CPU to tracking (``os.nice``; as it is where that is not possible)."""
    if nice > 0:
        try:
            os.nice(nice)
        except (AttributeError, OSError):  # pragma: no cover - no nice() (Windows) or not allowed
            pass
