"""The local engine: the jobs in this process (one worker) or in a pool of worker processes."""

from __future__ import annotations

from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterable, Iterator

from rgbdslam.engine.base import DEFAULT_RETRIES, Engine, EngineError
from rgbdslam.io.worker import follow_parent, spawn_context

_SHARED: dict[str, Any] = {}


def _init_worker(shared: Any = None) -> None:
    """A pool worker's start: it ends with the driver (:func:`follow_parent`); ``shared`` is kept
    for the jobs."""
    follow_parent()
    _SHARED["value"] = shared


def _call_shared(fn: Callable, args: tuple) -> Any:
    return fn(_SHARED["value"], *args)


class LocalEngine(Engine):
    """``workers == 1``: in this process, in order. More: a ``spawn`` process pool (fresh
    interpreters: no thread state of the driver is copied into them); a pool whose worker
    died is replaced and the jobs it had not finished run again (at most ``retries`` times each)."""

    name = "local"

    def __init__(self, workers: int = 1, retries: int = DEFAULT_RETRIES):
        self.workers = workers
        self.retries = retries

    def map(self, fn: Callable, jobs: Iterable[tuple], shared: Any = None) -> Iterator[tuple[int, Any]]:
        jobs = [tuple(a) for a in jobs]
        if self.workers == 1 or len(jobs) <= 1:
            for k, args in enumerate(jobs):
                yield k, (fn(shared, *args) if shared is not None else fn(*args))
            return
        yield from self._pool_map(fn, jobs, shared)

    def _pool_map(self, fn, jobs, shared) -> Iterator[tuple[int, Any]]:
        todo = dict(enumerate(jobs))
        attempts = {k: 0 for k in todo}
        ctx = spawn_context()
        while todo:
            pool = ProcessPoolExecutor(min(self.workers, len(todo)), mp_context=ctx,
                                       initializer=_init_worker, initargs=(shared,))
            try:
                futures = {}
                for k, args in todo.items():
                    attempts[k] += 1
                    futures[pool.submit(_call_shared, fn, args) if shared is not None
                            else pool.submit(fn, *args)] = k
                pending = set(futures)
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        k = futures[f]
                        try:
                            result = f.result()
                        except BrokenProcessPool:
                            continue  # a worker died: this job (and the pool's other unfinished ones) run again
                        del todo[k]
                        yield k, result
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
            dead = [k for k in todo if attempts[k] > self.retries]
            if dead:
                raise EngineError(f"job {dead[0]} was lost {attempts[dead[0]]} times with its worker process "
                                  f"(killed or out of memory?); giving up")
