"""The ``rgbdslam`` console script. Ctrl-C at any moment after start-up is exit 130 with one
line, never a traceback: our SIGINT handler is installed before anything heavy is imported, and
it records that the user interrupted, so an exception a library raises because its import or
its work was cut short (NumPy's "ImportError: initialization failed", ...) is reported as the
interruption it is (:func:`rgbdslam.errors.was_interrupted`)."""

from __future__ import annotations

import signal
import sys

from rgbdslam import errors


def main() -> None:
    signal.signal(signal.SIGINT, errors.on_sigint)
    signal.signal(signal.SIGTERM, errors.on_sigint)  # kill, timeout, docker stop: handled as Ctrl-C
    code: int | str | None = 0
    try:
        _command()
    except SystemExit as e:  # every ending of a command (click exits with the code; Ctrl-C with 130)
        code = e.code
    finally:
        # The command is over (finished, failed or interrupted; run.json says which). What is left
        # is the shutdown (_exit_now): multiprocessing's atexit finalizers (the live map's queue
        # feeder threads); Python's own would then tear the modules down with SIGINT reset to its default. A
        # Ctrl-C there used to raise KeyboardInterrupt inside those finalizers (a hang or a wrong
        # exit code) or kill the process by the signal (exit -2, after a finished run). There is
        # nothing left to stop: it is ignored, and the process exits with the command's code.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _exit_now(code)


def _exit_now(code: int | str | None) -> None:
    """End the process the way Python would, minus its finalisation: the threads' shutdown (a
    thread pool's workers are joined) and the atexit handlers (multiprocessing's queue feeders,
    Rerun) run, stdout/stderr are flushed, then ``os._exit``. Freeing every module's objects and
    the C++ static destructors of Open3D, GTSAM and OpenCV cost 0.6-0.8 s after every command on
    the 2-core machine (0.03 s this way); every file the command wrote is closed by then."""
    import atexit
    import os
    import threading

    if code is None:
        code = 0
    elif not isinstance(code, int):  # SystemExit("message"): Python prints it and exits with 1
        sys.stderr.write(f"{code}\n")
        code = 1
    if "rgbdslam.io.worker" in sys.modules:  # no helper left half-launched by another thread
        sys.modules["rgbdslam.io.worker"].settle()
    shutdown = getattr(threading, "_shutdown", None)
    if shutdown is not None:
        shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def _command() -> None:
    try:
        # a Ctrl-C that arrived while the interpreter started, with SIGINT blocked, is taken now
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
        from rgbdslam.cli import main as cli_main

        cli_main()
    except KeyboardInterrupt:
        errors.exit_interrupted()
    except SystemExit:
        raise
    except BaseException:
        if errors.was_interrupted():
            errors.exit_interrupted()
        raise


if __name__ == "__main__":  # pragma: no cover
    main()
