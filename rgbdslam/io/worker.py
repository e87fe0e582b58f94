"""A helper process of a run (the map process, the plot process): started with ``spawn``, it
takes jobs from one queue and puts ``(status, value)`` on another. The pieces both use."""

from __future__ import annotations

import os
import queue

_QUIET = "ignore:resource_tracker:UserWarning"


def spawn_context():
    """multiprocessing's ``spawn`` context, with its resource tracker (the process that unlinks
    the named semaphores of the queues) started without warnings.

    An interrupted run ends at once (``os._exit``, docs/robustness.md): the queues' semaphores are
    then unlinked by the tracker, which is what it is for, but it also warns about each one
    ("leaked semaphore", or an ``[Errno 2]`` when the other end had unlinked it) *after* the run's
    last line. The tracker is a separate interpreter started with the ``-W`` options of
    ``sys.warnoptions``: it is started here, once, with its own warnings ignored."""
    import multiprocessing as mp
    import sys
    from multiprocessing import resource_tracker

    added = _QUIET not in sys.warnoptions
    if added:
        sys.warnoptions.append(_QUIET)
    try:
        resource_tracker.ensure_running()
    finally:
        if added:
            sys.warnoptions.remove(_QUIET)
    return mp.get_context("spawn")


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


def lower_thread_priority(nice: int) -> None:
    """Yield the CPU to tracking in the calling *thread* only (Linux schedules threads: a thread's
    niceness is its own). A process cannot take back a lower priority without privileges, but
    its other threads keep theirs: the helper's work while tracking runs in a niced thread and
    the work the user waits for after the last frame in the process's main thread, at the
    priority of the run. Where threads have no niceness of their own: the whole process (:func:`lower_priority`)."""
    if nice <= 0:
        return
    import sys
    import threading

    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + nice)
            return
        except (AttributeError, OSError):  # pragma: no cover - not allowed
            pass
    lower_priority(nice)  # pragma: no cover - elsewhere


def in_niced_thread(nice: int, work):
    """``work()`` in a thread of its own at niceness + ``nice`` (:func:`lower_thread_priority`);
    its result, or its exception raised here."""
    import threading

    out: dict = {}

    def body():
        try:
            lower_thread_priority(nice)
            out["value"] = work()
        except BaseException as e:  # noqa: BLE001 - raised again in the calling thread
            out["error"] = e

    t = threading.Thread(target=body, name="niced", daemon=True)
    t.start()
    t.join()
    if "error" in out:
        raise out["error"]
    return out.get("value")


class Helper:
    """A helper process for one job after the last frame: started with the run, it runs ``warm``
    (``"module:function"``: its imports, e.g. Open3D) in a thread niced by ``nice`` while the frames
    are tracked; then the :meth:`submit` ted jobs, one after another, each ``"module:function"``
    called with its arguments in its main thread at the run's priority; :meth:`result` gives the next
    job's value (its error raised here; the process ends after an error). Functions are named, not
    imported here: this module stays free of the package's stages."""

    def __init__(self, name: str, warm: str, nice: int):
        ctx = spawn_context()
        self.name = name
        self._jobs = ctx.Queue()
        self._results = ctx.Queue()
        self._warm = ctx.Event()
        self._proc = ctx.Process(target=_helper, name=name, daemon=True,
                                 args=(self._jobs, self._results, warm, nice, self._warm))
        self._proc.start()

    def ready(self) -> bool:
        """True when the warm-up is done (a job sent earlier would wait for its niced imports)."""
        return self._warm.is_set()

    def submit(self, func: str, *args) -> None:
        self._jobs.put((func, args))

    def result(self):
        status, value = receive(self._results, self._proc, self.name)
        if status == "error":
            raise value
        return value

    def close(self, wait: float = 5.0) -> None:
        """End the process (at once when its job is done; without a job when none was sent): asked
        to end, terminated after ``wait`` s."""
        end(self._proc, self._jobs, timeout=wait)


def _call(func: str, *args):
    import importlib

    module, name = func.split(":")
    return getattr(importlib.import_module(module), name)(*args)


def _helper(jobs, results, warm: str, nice: int, warmed) -> None:
    """The helper process's body (:class:`Helper`)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's to handle: it stops us
    try:
        in_niced_thread(nice, lambda: _call(warm))
        warmed.set()
        while (job := jobs.get()) is not None:  # until close()
            results.put(("ok", _call(job[0], *job[1])))
    except BaseException as e:  # noqa: BLE001 - the run reports it (OSError as itself: a full disk names its file)
        from rgbdslam.errors import RgbdslamError

        results.put(("error", e if isinstance(e, (RgbdslamError, OSError)) else RuntimeError(f"{type(e).__name__}: {e}")))
    exit_now(results)
