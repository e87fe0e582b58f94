"""Terminal output shared by the library's long-running functions: one console, one progress style."""

from __future__ import annotations

import contextlib
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeRemainingColumn
from rich.text import Text

console = Console(stderr=True)


class _RateColumn(ProgressColumn):
    """Frames per second over rich's recent window."""

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("" if not speed else f"{speed:5.1f} frames/s", style="progress.data.speed")


@contextlib.contextmanager
def frame_progress(total: int | None, description: str, enabled: bool = True) -> Iterator[Callable[..., None]]:
    """Yield ``advance(status="")``; shows a bar with frames/s, the time left and the last status
    text (e.g. "24 loops, 0 lost") when enabled and stderr is a terminal."""
    if not enabled or not console.is_terminal:
        yield lambda status="": None
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        _RateColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[status]}"),
        console=console,
        transient=False,
    ) as prog:
        task = prog.add_task(description, total=total, status="")

        def advance(status: str = "") -> None:
            if status:
                prog.update(task, advance=1, status=status)
            else:
                prog.advance(task)

        yield advance
