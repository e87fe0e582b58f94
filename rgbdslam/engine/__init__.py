"""Where independent jobs run: in this process, a local process pool, or a Ray cluster.

The commands that run many independent cells (``rgbdslam run A B C``, ``rgbdslam sweep``,
``rgbdslam posegraph bench``) hand them to an :class:`~rgbdslam.engine.base.Engine`, built by
:func:`build_engine` from ``--engine local|ray``, ``--workers`` and ``--address``:

* ``local`` (default): ``workers == 1`` runs the jobs one after the other in this process;
  more workers use a process pool (:mod:`rgbdslam.engine.local`);
* ``ray``: Ray tasks on a new local cluster of ``workers`` CPUs, or on the running cluster at
  ``--address`` (:mod:`rgbdslam.engine.ray_engine`; the optional extra ``rgbdslam[distributed]``).

Every engine calls the same module-level function with the same arguments and returns its
results to the driver, so the numbers are the ones of a local run. A worker process that dies
(killed, out of memory) has its job run again (``retries`` times); an exception raised by the
job itself is not retried, it comes back to the driver.
"""

from rgbdslam.engine.base import DEFAULT_RETRIES, ENGINES, Engine, EngineError, check_workers
from rgbdslam.errors import InputError

__all__ = ["ENGINES", "Engine", "EngineError", "build_engine"]


def build_engine(name: str = "local", workers: int = 1, address: str | None = None,
                 retries: int = DEFAULT_RETRIES) -> Engine:
    """The engine called ``name`` (``local`` or ``ray``); ``address`` only for ``ray`` (a running
    cluster, e.g. ``ray://head:10001`` or ``auto``; without it a local cluster of ``workers`` CPUs)."""
    workers = check_workers(workers)
    if name == "local":
        if address is not None:
            raise InputError("--address is the address of a Ray cluster; give it with --engine ray")
        from rgbdslam.engine.local import LocalEngine

        return LocalEngine(workers, retries=retries)
    if name == "ray":
        from rgbdslam.engine.ray_engine import RayEngine

        return RayEngine(workers, address=address, retries=retries)
    raise InputError(f"unknown engine {name!r}; use {' or '.join(ENGINES)}")
