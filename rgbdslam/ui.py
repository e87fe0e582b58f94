"""Terminal output shared by the library's long-running functions: one console, one progress style.

On a terminal the progress is a rich bar whose count, rate and time left keep their width in an
80-column window (the description and the status text give way first, then the bar). When
stderr is not a terminal (nohup, CI, batch schedulers) a plain line is printed every
:data:`PLAIN_EVERY` seconds instead, so a log shows that the work advances.
"""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeRemainingColumn
from rich.table import Column
from rich.text import Text

# soft_wrap: a warning is one line however long its path (rich would break it at 80 columns in a log)
console = Console(stderr=True, soft_wrap=True)
PLAIN_EVERY = 5.0  # seconds between progress lines when stderr is not a terminal


class _RateColumn(ProgressColumn):
    """Frames per second over rich's recent window."""

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("" if not speed else f"{speed:5.1f} frames/s", style="progress.data.speed")


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def progress_line(description: str, done: int, total: int, elapsed: float, status: str = "") -> str:
    """``SLAM seq: 120/798 frames (15 %), 25.3 frames/s, 0:00:27 left; 2 loops, 0 lost``."""
    rate = done / elapsed if elapsed > 0 else 0.0
    line = f"{description}: {done}/{total} ({100 * done / max(total, 1):.0f} %)"
    if rate > 0:
        line += f", {rate:.1f}/s, {_clock((total - done) / rate)} left"
    return line + (f"; {status}" if status else "")


@contextlib.contextmanager
def frame_progress(total: int | None, description: str, enabled: bool = True,
                   every: float | None = None) -> Iterator[Callable[..., None]]:
    """Yield ``advance(status="")``; shows a bar with frames/s, the time left and the last status
    text (e.g. "24 loops, 0 lost") when enabled and stderr is a terminal, else a plain progress
    line every ``every`` (default :data:`PLAIN_EVERY`) seconds."""
    if not enabled:
        yield lambda status="": None
        return
    if not console.is_terminal:
        every = PLAIN_EVERY if every is None else every
        t0 = last = time.monotonic()
        count = 0

        def plain(status: str = "") -> None:
            nonlocal count, last
            count += 1
            now = time.monotonic()
            if now - last >= every and count < total:
                last = now
                console.print(progress_line(description, count, total, now - t0, status), soft_wrap=True,
                              highlight=False, markup=False)

        yield plain
        return
    with Progress(
        TextColumn("[bold]{task.description}", table_column=Column(no_wrap=True, overflow="ellipsis", ratio=1,
                                                                   min_width=8)),
        BarColumn(bar_width=None, table_column=Column(ratio=1, min_width=5)),
        MofNCompleteColumn(table_column=Column(no_wrap=True, min_width=2 * len(str(total)) + 1)),
        _RateColumn(table_column=Column(no_wrap=True, min_width=14)),
        TimeRemainingColumn(table_column=Column(no_wrap=True, min_width=7)),
        TextColumn("{task.fields[status]}", table_column=Column(no_wrap=True, overflow="ellipsis", ratio=1,
                                                                 min_width=0)),
        console=console,
        transient=False,
        expand=True,
    ) as prog:
        task = prog.add_task(description, total=total, status="")

        def advance(status: str = "") -> None:
            if status:
                prog.update(task, advance=1, status=status)
            else:
                prog.advance(task)

        yield advance

