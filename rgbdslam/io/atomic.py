"""Atomic file writes: a reader never sees a half-written output."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import signal
import stat
import threading
import tempfile
from pathlib import Path
from typing import Iterator


def plain_permissions(path: str | Path) -> None:
    """Give a file or folder made by ``tempfile`` (owner-only) the permissions a plain ``open()``
    or ``mkdir()`` would give it under the current umask."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if Path(path).is_dir() else 0o666) & ~umask)


def make_dirs(path: str | Path) -> Path:
    """``mkdir -p path``, but an ancestor that exists and is not a folder is named as the problem
    (NotADirectoryError on it: Python's own error says "File exists" about the path asked for)."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.is_dir():
            break
        if os.path.lexists(p):  # a file, a dangling link, a link loop: not a folder to write into
            raise NotADirectoryError(errno.ENOTDIR, "is a file, not a folder", str(p))
    path.mkdir(parents=True, exist_ok=True)
    return path


def write_target(path: str | Path) -> tuple[Path, bool]:
    """Where a write to ``path`` must go and whether it can be atomic: ``(target, True)`` for a
    regular file or a new name (symbolic links followed to their end, so the link stays a link
    and the file it names is replaced), ``(path, False)`` for an existing file that is not
    regular (a device such as /dev/null or /dev/stdout, a FIFO): such a target is written into
    directly and never replaced by a plain file. A folder is an IsADirectoryError naming it."""
    path = Path(path)
    try:
        st = os.stat(path)  # follows links; a loop is OSError(ELOOP) naming the path
    except NotADirectoryError:  # a file where a folder of the path should be: name that file
        make_dirs(path.parent)
        raise
    except FileNotFoundError:
        # a new name, or a link to a name that does not exist yet: create the link's target
        return (Path(os.path.realpath(path)) if os.path.islink(path) else path), True
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(errno.EISDIR, "is a folder, not a file", str(path))
    if stat.S_ISREG(st.st_mode):
        return Path(os.path.realpath(path)), True
    return path, False


def commit(tmp: str | Path, path: str | Path) -> None:
    """Put the finished temporary file ``tmp`` in place of ``path`` (see :func:`write_target`):
    renamed over a regular file, copied into a device or FIFO; ``tmp`` is gone afterwards."""
    target, atomic = write_target(path)
    if atomic:
        plain_permissions(tmp)
        os.replace(tmp, target)
        return
    try:
        with open(tmp, "rb") as src, open(target, "wb") as dst:
            shutil.copyfileobj(src, dst)
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(path)) from None  # name the user's path, not a temporary
    finally:
        Path(tmp).unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside the target; on success it replaces ``path`` (a regular file,
    also through symbolic links) or is copied into it (a device, a FIFO: never replaced)."""
    target, atomic = write_target(path)
    if atomic:
        make_dirs(target.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=Path(path).suffix or ".tmp",
                               dir=target.parent if atomic else None)  # a device's folder: /tmp instead
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        commit(tmp_path, path)
    except OSError as e:  # a full disk, a lost folder: name the user's file, not our temporary one
        if e.filename is None or str(e.filename) == str(tmp_path):
            raise OSError(e.errno, e.strerror or str(e), str(path)) from None
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def in_final_place(e: OSError, stage: Path, final: Path) -> OSError:
    """``e`` naming the file in ``final`` when it names one in the temporary folder ``stage`` that
    is built to become ``final`` (a full disk part-way): a message never names our temporary folder."""
    if e.filename is not None and Path(e.filename).is_relative_to(stage):
        return OSError(e.errno, e.strerror, str(final / Path(e.filename).relative_to(stage)))
    return e


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


@contextlib.contextmanager
def interrupts_deferred():
    """Ctrl-C inside the block is raised at its end (main thread only), so the few renames that
    swap finished outputs into place (a synthetic sequence, a map) are never cut in the middle."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    hit: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda *_: hit.append(1))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
        if hit:
            raise KeyboardInterrupt
