"""What rgbdslam wrote into an output folder, and so what it may replace there (docs/outputs.md).

Every folder rgbdslam writes into — a run folder, its ``previous/``, an export's ``--out``, a
sweep's or a batch's ``--out`` — keeps a manifest, ``FOLDER/.rgbdslam-manifest.json``::

    {"written_by": "rgbdslam 0.9", "complete": true,
     "entries": {"map": "run", "map/cloud.ply": "run", "colmap": "export", ...}}

one entry per file and folder (paths relative to FOLDER, ``/``-separated) naming the kind of
command that wrote it (:data:`RUN`, :data:`EXPORT`, :data:`TABLE`, :data:`SEQUENCE`). A command replaces, moves or
removes only what the manifest lists with a kind that command may replace; anything else where it
would write — a user's file or folder, a link the manifest does not list, another run's outputs
— stops it with one line naming that path (:meth:`Manifest.check_way`, an InputError: exit 2).
Paths are judged as they are: a link is a link (never followed out of the folder) and is moved or
replaced as the link.

A run first claims the top-level names it is going to write (``"complete": false``) and lists
every file when it ends, however it ends; a run killed where it could not write that list
(SIGKILL, power loss) leaves its claims, and everything below a claimed name counts as its own.
The manifest is written atomically: never half a manifest, and a damaged one (not this JSON) is an
error naming it, never read as "nothing here is ours".
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable, Iterator

from rgbdslam import __version__
from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_write_text

MANIFEST = ".rgbdslam-manifest.json"
RUN = "run"  # a run (and its map fusion): the run folder's own files
EXPORT = "export"  # `rgbdslam export`
TABLE = "table"  # the results tables of a sweep, a batch or the pose-graph benchmark
SEQUENCE = "sequence"  # a synthetic sequence (`rgbdslam synth`, the demo)
KINDS = (RUN, EXPORT, TABLE, SEQUENCE)


def walk(root: Path, rel: str) -> Iterator[str]:
    """``rel`` (when it exists) and every path below it, relative to ``root``; links are not followed."""
    p = root / rel
    if not os.path.lexists(p):
        return
    yield rel
    if p.is_dir() and not p.is_symlink():
        for dirpath, dirnames, filenames in os.walk(p):  # os.walk does not follow links by default
            base = Path(dirpath).relative_to(root).as_posix()
            for name in sorted(dirnames) + sorted(filenames):
                yield f"{base}/{name}"


class Manifest:
    """The manifest of ``folder`` (empty when the folder has none)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / MANIFEST
        self.exists = os.path.lexists(self.path)
        self.entries: dict[str, str] = {}
        self.complete = True
        if self.exists:
            self._read()

    def _read(self) -> None:
        why = None
        data = None
        if self.path.is_symlink() or not self.path.is_file():
            why = "it is not a regular file"
        else:
            try:
                data = json.loads(self.path.read_text(encoding="utf-8"))
            except OSError as e:
                why = f"it cannot be read: {e.strerror or e}"
            except (UnicodeDecodeError, ValueError, RecursionError):
                why = "it is empty" if self.path.stat().st_size == 0 else "it is not valid JSON"
        if why is None:
            entries = data.get("entries") if isinstance(data, dict) else None
            if not (isinstance(entries, dict) and all(isinstance(k, str) and v in KINDS for k, v in entries.items())
                    and isinstance(data.get("complete", True), bool)):
                why = "it does not hold rgbdslam's list of the files it wrote"
            else:
                self.entries, self.complete = dict(entries), data.get("complete", True)
                return
        raise InputError(f"{self.path} is damaged ({why}), so rgbdslam cannot tell the files it wrote in "
                         f"{self.folder} from yours; move them away (or restore the file) and try again")

    # ------------------------------------------------------------------ what is ours

    def kind(self, rel: str) -> str | None:
        """The kind of command that wrote ``rel``, or None when this manifest does not list it. In an
        incomplete manifest (its run was killed) everything below a listed name counts as listed."""
        if rel in self.entries:
            return self.entries[rel]
        if not self.complete:
            parts = rel.split("/")
            for k in range(len(parts) - 1, 0, -1):
                owner = self.entries.get("/".join(parts[:k]))
                if owner is not None:
                    return owner
        return None

    def foreign(self, names: Iterable[str], kinds: Iterable[str], below: bool = True) -> Path | None:
        """The first path among ``names`` (relative to the folder) and, with ``below``, everything
        below them that the manifest does not list with one of ``kinds``; None when there is none."""
        kinds = set(kinds)
        for rel in names:
            for sub in walk(self.folder, rel) if below else [rel] * os.path.lexists(self.folder / rel):
                if self.kind(sub) not in kinds:
                    return self.folder / sub
        return None

    def check_way(self, names: Iterable[str], kinds: Iterable[str], fix: str, below: bool = True) -> None:
        """An InputError naming the first path in the way (:meth:`foreign`); ``fix`` ends the line."""
        bad = self.foreign(names, kinds, below)
        if bad is None:
            return
        owner = self.kind(bad.relative_to(self.folder).as_posix())
        why = (f"it holds the outputs of `rgbdslam {owner}`, which this command does not replace"
               if owner in (RUN, EXPORT) else "rgbdslam did not write it")
        raise InputError(f"{bad} is in the way: {why}; {fix}")

    def unlink_links(self, names: Iterable[str]) -> None:
        """Remove the links among ``names`` (checked to be ours): a write there then makes a new
        file in this folder instead of following the link out of it."""
        for rel in names:
            if (self.folder / rel).is_symlink():
                (self.folder / rel).unlink()

    # ------------------------------------------------------------------ writing

    def claim(self, names: Iterable[str], kind: str) -> None:
        """List ``names`` (top-level names about to be written) as ``kind``'s and mark the manifest
        incomplete until :meth:`record` with ``complete=True``."""
        for rel in names:
            self.entries[rel] = kind
        self.complete = False
        self.save()

    def record(self, names: Iterable[str], kind: str, complete: bool | None = None, below: bool = True) -> None:
        """List as ``kind``'s every path now at (and, with ``below``, below) ``names``, replacing what
        was listed there; a name that does not exist is dropped, unless it was claimed and the
        manifest stays incomplete. ``complete``: mark the manifest complete (True) or not (False);
        None keeps it."""
        if complete is not None:
            self.complete = complete
        for rel in names:
            claimed = self.entries.get(rel) == kind and not self.complete
            present = list(walk(self.folder, rel)) if below else [rel] * os.path.lexists(self.folder / rel)
            if below:
                self.entries = {k: v for k, v in self.entries.items() if k != rel and not k.startswith(rel + "/")}
            else:
                self.entries.pop(rel, None)
            self.entries.update((p, kind) for p in present)
            if claimed and not present:
                self.entries[rel] = kind
        self.save()

    def forget(self, names: Iterable[str]) -> None:
        """Drop ``names`` and everything below them (no longer in the folder) and save, when listed."""
        names = list(names)
        keep = {k: v for k, v in self.entries.items()
                if not any(k == n or k.startswith(n + "/") for n in names)}
        if keep != self.entries:
            self.entries = keep
            self.save()

    def save(self) -> None:
        atomic_write_text(self.path, json.dumps({"written_by": f"rgbdslam {__version__}", "complete": self.complete,
                                                 "entries": dict(sorted(self.entries.items()))}, indent=1) + "\n")
        self.exists = True


def tables_ready(folder: Path, names: Iterable[str]) -> None:
    """Nothing at ``names`` in ``folder`` (the results tables a sweep, a batch or the pose-graph
    benchmark writes there) that its manifest does not list as earlier tables: an InputError
    names it otherwise."""
    m = Manifest(folder)
    m.check_way(names, [TABLE], "move it away or choose another --out (the results tables replace only "
                                "earlier results tables)")
    m.unlink_links(names)


def record_tables(folder: Path, names: Iterable[str]) -> None:
    """List the results tables ``names`` now in ``folder`` in its manifest."""
    Manifest(folder).record(names, TABLE)


def remove_path(path: Path) -> None:
    """Remove ``path``: a link as a link (never what it points to), a folder with its contents."""
    import shutil

    if path.is_symlink() or not path.is_dir():
        path.unlink()
    else:
        shutil.rmtree(path)
