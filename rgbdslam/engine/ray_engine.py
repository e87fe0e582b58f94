"""The Ray engine (optional extra ``rgbdslam[distributed]``): jobs as Ray tasks.

Without ``address`` a local Ray cluster with ``workers`` CPUs is started for the command and
stopped after it; with ``address`` (``auto``, ``HOST:6379`` or ``ray://HOST:10001``) the jobs
go to that running cluster. When Ray is already initialised in this process (a test, a notebook)
that session is used and left running.

What travels: the job's arguments and the ``shared`` object (put once into Ray's object store),
and the results, which come back to the driver. What does not: files. Sequences, data folders
and output folders are read and written by the workers at the paths the driver gives, so on a
cluster of several machines they must be on storage every node mounts at the same path, and
rgbdslam must be installed on every node (the same version).

Ray re-runs a task whose worker process died (``max_retries``); an exception raised by the
job itself is not retried and is raised again here with its own type.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Iterator

from rgbdslam.engine.base import DEFAULT_RETRIES, Engine, EngineError
from rgbdslam.errors import InputError


def _import_ray():
    try:
        import ray
    except ImportError:
        raise InputError("--engine ray needs Ray: pip install 'rgbdslam[distributed]' (or pip install ray)") from None
    return ray


def _token_auth_for_address() -> None:
    """Ray (2.60) turns token authentication on for a cluster that ``ray start --head`` starts
    while a token exists (``~/.ray/auth_token``, ``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH``), and
    a driver that finds the cluster by itself (``auto``) turns it on too; a driver given the
    address explicitly does not, and the cluster refuses it ("Authentication token is missing or
    incorrect"). Here the explicit address is treated like ``auto``: with RAY_AUTH_MODE unset and a
    token available, the driver uses it. Older Ray (no token authentication): nothing to do."""
    import os

    if os.environ.get("RAY_AUTH_MODE") is not None:
        return  # the user's choice
    try:
        from ray._private.authentication.authentication_token_setup import (
            maybe_enable_token_auth_if_token_available,
        )
    except ImportError:
        return
    import logging

    log = logging.getLogger("ray._private.authentication.authentication_token_setup")
    level = log.level
    log.setLevel(logging.ERROR)  # its warning says what the user did not ask about: token auth is on
    try:
        maybe_enable_token_auth_if_token_available(warn_if_disabled=False)
    finally:
        log.setLevel(level)


def _refused_for_token(e: BaseException) -> bool:
    """Whether Ray's connection error came from the cluster's token authentication."""
    while e is not None:
        if type(e).__name__ == "AuthenticationError" or "InvalidAuthToken" in str(e):
            return True
        e = e.__cause__ or e.__context__
    return False


CONNECT_TIMEOUT_S = 3.0  # seconds to reach the cluster's port before Ray is asked to (it waits ~60 s)


def check_address(address: str) -> None:
    """A cluster address Ray can use, checked before ``ray.init``: ``auto`` (Ray looks it up), or
    ``HOST:PORT`` / ``ray://HOST:PORT`` where HOST resolves and something accepts a connection at
    PORT within :data:`CONNECT_TIMEOUT_S` s. EngineError with one line otherwise — Ray itself
    waits a minute printing its C++ log lines for a closed port or an unknown host, and raises a
    traceback for an empty or ``http://`` address."""
    import socket

    from rgbdslam.errors import cut

    fix = "give auto, HOST:6379 or ray://HOST:10001 (a cluster started with `ray start --head`)"
    if address == "auto":
        return
    text = address.strip()
    scheme, _, rest = text.rpartition("://")
    if not text or scheme not in ("", "ray"):
        raise EngineError(f"--address '{cut(address)}' is not a Ray cluster address; {fix}")
    host, _, port = rest.rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise EngineError(f"--address '{cut(address)}' has no HOST:PORT; {fix}")
    try:
        socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        raise EngineError(f"--address '{cut(address)}': the host {cut(host)} is unknown; {fix}") from None
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as e:
        why = "nothing answered" if isinstance(e, TimeoutError) else (e.strerror or type(e).__name__).lower()
        raise EngineError(f"no Ray cluster at {cut(address)} ({why} within {CONNECT_TIMEOUT_S:g} s); start one "
                          f"with `ray start --head` or leave out --address for a local cluster") from None


def _call(fn: Callable, shared: Any, args: tuple) -> Any:
    return fn(shared, *args) if shared is not None else fn(*args)


class RayEngine(Engine):
    name = "ray"

    def __init__(self, workers: int = 1, address: str | None = None, retries: int = DEFAULT_RETRIES):
        ray = _import_ray()
        self.ray = ray
        self.workers = workers
        self.retries = retries
        self.address = address
        self._owner = False
        if not ray.is_initialized():
            kw = dict(include_dashboard=False, log_to_driver=False, logging_level="ERROR",
                      configure_logging=True)
            try:
                if address is None:
                    ray.init(num_cpus=workers, **kw)
                else:
                    check_address(address)
                    _token_auth_for_address()
                    ray.init(address=address, **kw)
            except ValueError as e:  # Ray's own refusal of the address, e.g. ray:// without `ray[client]`
                text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise EngineError(f"Ray cannot use the address {address}: {text[:200]}") from None
            except ConnectionError as e:
                if _refused_for_token(e):
                    raise EngineError(
                        f"the Ray cluster at {address} refused this driver: it uses token authentication and the "
                        f"token here is missing or another one; give the cluster's token (`ray get-auth-token` on "
                        f"its head node) as RAY_AUTH_TOKEN or in ~/.ray/auth_token") from None
                raise EngineError(f"no Ray cluster at {address}: {e}; start one with `ray start --head` "
                                  f"or leave out --address for a local cluster") from None
            self._owner = True
        self._remote = ray.remote(num_cpus=1, max_retries=retries)(_call)
        self.workers = int(ray.cluster_resources().get("CPU", workers))

    def describe(self) -> str:
        where = self.address or "local cluster"
        return f"ray ({where}), {self.workers} CPU(s)"

    def map(self, fn: Callable, jobs: Iterable[tuple], shared: Any = None) -> Iterator[tuple[int, Any]]:
        ray = self.ray
        shared_ref = ray.put(shared) if shared is not None else None
        refs = {self._remote.remote(fn, shared_ref, tuple(args)): k for k, args in enumerate(jobs)}
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayTaskError as e:  # the job's own exception, as it was raised
                        cause = getattr(e, "cause", None)
                        raise (cause if isinstance(cause, Exception) else e.as_instanceof_cause()) from None
                    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                            ray.exceptions.OutOfMemoryError) as e:
                        raise EngineError(f"job {refs[ref]} was lost with its worker {self.retries + 1} times "
                                          f"({type(e).__name__}); giving up") from None
                    yield refs[ref], result
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._owner and self.ray.is_initialized():
            self.ray.shutdown()
        self._owner = False
