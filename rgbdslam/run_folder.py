"""A run folder's housekeeping: one writer at a time (a lock), the earlier run kept in
``previous/`` with a manifest of what rgbdslam put there, and run.json's status.

* :func:`folder_lock`: an exclusive ``flock`` on ``FOLDER/.rgbdslam.lock`` while a run (or a
  fusion) writes into the folder. A second process gets one error line instead of mixing its
  outputs with the first one's; the kernel drops the lock when its process dies, so a killed
  run never blocks the next one.
* :func:`keep_previous_run`: a finished earlier run is moved to ``previous/`` with a manifest
  (``previous/.rgbdslam-previous.json``, every path moved there); an older ``previous/`` is only
  deleted when it holds nothing but what its manifest lists (a user's file beside it stops the
  run with one line instead).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
from pathlib import Path
from typing import Iterator

from rgbdslam import __version__
from rgbdslam.errors import InputError

# what a run writes into its folder; a new run into the same folder first moves these to previous/
RUN_ARTEFACTS = ("trajectory.tum", "odometry.tum", "posegraph.g2o", "config.yaml", "run.json", "evaluation.json",
                 "plots", "map", "keyframes", "recording.rrd")
PREVIOUS = "previous"
MANIFEST = ".rgbdslam-previous.json"
LOCK_NAME = ".rgbdslam.lock"


@contextlib.contextmanager
def folder_lock(folder: str | Path, what: str = "run") -> Iterator[None]:
    """Hold the folder's lock for the block; InputError (one line, exit 2) when another process
    holds it. ``what`` names the kind of work in the message."""
    folder = Path(folder)
    path = folder / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
            raise InputError(f"{folder} is in use by another rgbdslam process"
                             + (f" ({holder})" if holder else "")
                             + f"; wait for it to end or choose another folder for this {what}") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}, {what}\n".encode("ascii"), 0)
        yield
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with a waiting process)


def finished_run(run_json: Path) -> bool:
    """True when ``run_json`` records a run that ran to its end (``status`` "finished"; older
    run.json files without a status count as finished unless they say ``interrupted``)."""
    try:
        info = json.loads(run_json.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    if not isinstance(info, dict):
        return False
    return info.get("status", "interrupted" if info.get("interrupted") else "finished") == "finished"


def _tree(root: Path, names) -> list[str]:
    """Relative paths of ``names`` in ``root`` and of everything below them (links not followed)."""
    out = []
    for name in names:
        p = root / name
        if not os.path.lexists(p):
            continue
        out.append(name)
        if p.is_dir() and not p.is_symlink():
            out += [str(q.relative_to(root)) for q in sorted(p.rglob("*"))]
    return out


def _foreign_entry(prev: Path) -> str | None:
    """The first path in ``prev`` that rgbdslam did not put there, "" when ``prev`` is no run of
    rgbdslam at all, or None when everything in it is ours."""
    try:
        listed = set(json.loads((prev / MANIFEST).read_text(encoding="utf-8"))["entries"])
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        listed = None
    if listed is None:  # an earlier version's previous/ (no manifest): our top-level names only
        if not (prev / "run.json").is_file():
            return ""
        return next((p.name for p in sorted(prev.iterdir()) if p.name not in RUN_ARTEFACTS), None)
    present = _tree(prev, sorted(os.listdir(prev)))
    return next((p for p in present if p != MANIFEST and p not in listed), None)


def keep_previous_run(out_dir: Path) -> bool:
    """Move a finished earlier run's files in ``out_dir`` to ``out_dir/previous`` (replacing an
    older ``previous`` made by rgbdslam), so that a new run that fails or is interrupted part-way
    never overwrites a finished one. A failed or interrupted run in ``out_dir`` is not moved: the
    new run replaces it, and ``previous/`` keeps the last finished one. True when a run was moved.

    ``previous/`` is deleted only when everything in it is listed in its manifest (what rgbdslam
    moved there); anything else in it, or a ``previous`` that is not a folder, is an InputError."""
    if not finished_run(out_dir / "run.json"):
        return False
    prev = out_dir / PREVIOUS
    if os.path.lexists(prev):
        foreign = _foreign_entry(prev) if prev.is_dir() and not prev.is_symlink() else ""
        if foreign is not None:  # not ours: never delete it
            what = (f"{prev} holds {prev / foreign}, which rgbdslam did not write" if foreign else
                    f"{prev} exists and is not an earlier run of rgbdslam")
            raise InputError(f"{what}; move it away or choose another --out (a new run keeps the last finished one "
                             f"in {PREVIOUS}/ and replaces only what it wrote there)")
    from rgbdslam.io.atomic import interrupts_deferred

    with interrupts_deferred():  # Ctrl-C waits: never half an old run here, half in previous/
        if os.path.lexists(prev):
            shutil.rmtree(prev)
        entries = _tree(out_dir, RUN_ARTEFACTS)
        prev.mkdir()
        (prev / MANIFEST).write_text(json.dumps({"written_by": f"rgbdslam {__version__}", "entries": entries},
                                                indent=1))
        for name in RUN_ARTEFACTS:
            if os.path.lexists(out_dir / name):
                (out_dir / name).replace(prev / name)
    return True
