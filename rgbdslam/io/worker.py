"""A helper process of a run (the map process, the plot process): started with ``spawn``, it
takes jobs from one queue and puts ``(status, value)`` on another. The pieces both use."""

from __future__ import annotations

import os
import queue
import threading

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

    import signal

    added = _QUIET not in sys.warnoptions
    if added:
        sys.warnoptions.append(_QUIET)
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})  # as start()
    try:
        resource_tracker.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        if added:
            sys.warnoptions.remove(_QUIET)
    return mp.get_context("spawn")


PARENT_POLL_S = 0.2  # how often a helper looks whether its parent is still there
_STARTING = threading.Lock()  # held while a helper is launched (see settle())


def start(proc) -> None:
    """``proc.start()`` with SIGINT and SIGTERM blocked in the calling thread: the new process
    inherits the block (fork and exec keep the thread's signal mask), so a Ctrl-C, which the
    terminal sends to every process of the run, or a SIGTERM sent to the whole process group (a
    batch scheduler, systemd) reaches only the run itself, from the helper's first instruction (a
    helper interrupted while it imports printed its own traceback; one killed by the group's
    SIGTERM made the run warn); the run then ends its helpers (:func:`end`, :func:`stop`). In the main thread, where
    Python runs its signal handlers, a Ctrl-C or SIGTERM that arrives during the launch is handled
    right after it (a launch cut short leaves the new interpreter without its instructions: an
    EOFError traceback after the run's last line)."""
    import signal

    _stop_at_exit()
    main = threading.current_thread() is threading.main_thread()
    caught: list = []
    previous = {}
    if main:
        for sig in (signal.SIGINT, signal.SIGTERM):
            handler = signal.getsignal(sig)
            if callable(handler):
                previous[sig] = handler
                signal.signal(sig, lambda signum, frame: caught.append((signum, frame)))
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        with _STARTING:
            proc._rgbdslam_helper = True  # noqa: SLF001 - our mark on multiprocessing's object
            proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if caught:
        previous[caught[0][0]](*caught[0])


_STARTED: list = []  # the helpers start() launched (weakly: ended ones are not kept alive)


def _stop_at_exit() -> None:
    """Once per process: at exit, :func:`stop` every helper still running, before multiprocessing's
    own exit handler would ``terminate`` it and wait — a SIGTERM the helper blocks (:func:`start`),
    so that wait would never end. Registered after multiprocessing's handler, so it runs first."""
    if _STARTED:
        return
    import atexit
    import multiprocessing.util  # noqa: F401 - its exit handler is registered first, runs last

    _STARTED.append(None)

    def stop_helpers() -> None:
        import multiprocessing

        for proc in multiprocessing.active_children():
            if proc.daemon and getattr(proc, "_rgbdslam_helper", False):
                stop(proc)

    atexit.register(stop_helpers)


def settle(timeout: float = 5.0) -> None:
    """Wait (at most ``timeout`` s) until no helper is being launched by another thread: a process
    that ends while it launches one leaves the new interpreter without its instructions, and that
    prints a traceback (EOFError) after the run's last line."""
    if _STARTING.acquire(timeout=timeout):
        _STARTING.release()


def follow_parent() -> None:
    """In a helper process, first: end it (``os._exit``) as soon as the process that started it is
    gone (killed with SIGKILL, crashed), so no helper — some hold hundreds of MB — outlives its run
    as an orphan. A daemon thread compares the parent's id every :data:`PARENT_POLL_S` s (a
    parent's death re-parents the helper; Linux's PR_SET_PDEATHSIG would fire when the *thread*
    that started it ends, which is not the run's end)."""
    import multiprocessing
    import time

    started_by = multiprocessing.parent_process()  # the run's id, also when the run is PID 1 (a container)
    parent = started_by.pid if started_by is not None else os.getppid()
    if os.getppid() != parent:  # the run ended before this helper got here
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="follow-parent", daemon=True).start()


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
    """Ask the process to end (``None`` as its next job), wait ``timeout`` s, then :func:`stop` it."""
    if proc.is_alive():
        jobs.put(None)
        proc.join(timeout=timeout)
        if proc.is_alive():
            stop(proc)
    jobs.cancel_join_thread()  # its reader is gone: exit must not wait to flush the queue


def stop(proc) -> None:
    """End the helper process at once (SIGKILL: it blocks SIGTERM, see :func:`start`; it has no
    cleanup of its own to do — the run removes what it leaves)."""
    proc.kill()
    proc.join()


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
        start(self._proc)

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

    follow_parent()
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
