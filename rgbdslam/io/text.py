"""Reading the project's text inputs (lists, trajectories, configs, graph files) with one clear
error when a file is not text: a binary or wrongly encoded file names itself and the fix."""

from __future__ import annotations

from pathlib import Path

from rgbdslam.errors import InputError


def read_lines(path: str | Path, what: str = "text file") -> list[str]:
    """The lines of ``path`` split at newlines only (``str.splitlines`` also breaks at form feeds
    and Unicode separators, which would shift the line numbers that error messages name)."""
    return read_text(path, what).replace("\r\n", "\n").split("\n")


def read_text(path: str | Path, what: str = "text file") -> str:
    """The UTF-8 text of ``path`` (a path, or a package resource from ``importlib.resources``);
    an :class:`InputError` naming the file when it is not text."""
    path = Path(path) if isinstance(path, str) else path
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{what} {path} is not UTF-8 text (byte {e.start}); give the text file "
                         f"itself, not a binary or compressed copy") from None
