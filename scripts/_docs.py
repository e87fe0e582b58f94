"""Shared by the benchmark scripts: replace one "## " section of docs/benchmarks.md."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "docs" / "benchmarks.md"


def replace_section(section: str, path: Path = BENCHMARKS) -> None:
    """Replace the section whose first line is ``section``'s first line ("## Title") up to the
    next "## " heading, or append it; written atomically. Other sections are left alone."""
    from rgbdslam.io.atomic import atomic_write_text

    heading = section.splitlines()[0]
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    start = text.find(heading + "\n")
    if start >= 0:
        end = text.find("\n## ", start + 1)
        text = text[:start] + section.rstrip("\n") + "\n" + ("" if end < 0 else text[end:])
    else:
        text = text.rstrip("\n") + "\n\n" + section.rstrip("\n") + "\n"
    atomic_write_text(path, text)


def publish(section: str, write_docs: bool) -> int:
    """Print a benchmark's markdown section; with ``write_docs`` also put it into benchmarks.md."""
    print(section)
    if write_docs:
        replace_section(section)
    return 0
