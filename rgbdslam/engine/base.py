"""The engine interface and its factory (see :mod:`rgbdslam.engine`)."""

from __future__ import annotations

from typing import Any, Callable, Iterable, Iterator

from rgbdslam.errors import InputError, RgbdslamError

ENGINES = ("local", "ray")
DEFAULT_RETRIES = 2  # re-runs of a job whose worker process died


class EngineError(RgbdslamError):
    """The engine could not run a job (its worker died more often than allowed, no cluster at the address)."""


class Engine:
    """Runs ``fn(*args)`` (or ``fn(shared, *args)`` when ``shared`` is given) for every ``args`` of
    ``jobs`` and yields ``(position in jobs, result)`` as the jobs finish (in any order).

    ``fn`` must be a module-level function (it travels to the workers by reference); ``shared``
    is one object every job needs (a pose graph): it is sent to each worker once, not per job.
    Use as a context manager: leaving it stops the workers the engine started."""

    name = "engine"
    workers = 1

    def map(self, fn: Callable, jobs: Iterable[tuple], shared: Any = None) -> Iterator[tuple[int, Any]]:
        raise NotImplementedError

    def describe(self) -> str:
        return f"{self.name}, {self.workers} worker(s)"

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_workers(workers) -> int:
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"--workers must be a whole number >= 1, not {workers!r}")
    return workers
