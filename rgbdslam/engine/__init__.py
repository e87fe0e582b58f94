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

from rgbdslam.engine.base import ENGINES, Engine, EngineError, build_engine

__all__ = ["ENGINES", "Engine", "EngineError", "build_engine"]
