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
    try:
        _command()
    finally:
        # The command is over (finished, failed or interrupted; run.json says which). What is left
        # is Python's shutdown: multiprocessing's atexit finalizers (the live map's queue feeder
        # threads), then module teardown with SIGINT reset to its default by Python itself. A
        # Ctrl-C there used to raise KeyboardInterrupt inside those finalizers (a hang or a wrong
        # exit code) or kill the process by the signal (exit -2, after a finished run). There is
        # nothing left to stop: it is ignored, and the process exits with the command's code.
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _command() -> None:
    try:
        # a Ctrl-C that arrived while the interpreter started, with SIGINT blocked, is taken now
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
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
