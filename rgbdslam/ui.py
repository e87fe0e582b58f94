"""Terminal output shared by the library's long-running functions: one console, one progress style."""

from __future__ import annotations

import contextlib
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

console = Console(stderr=True)


@contextlib.contextmanager
def frame_progress(total: int, description: str, enabled: bool = True) -> Iterator[Callable[[], None]]:
    """Yield ``advance()``; shows a bar with a rate column when enabled and stderr is a terminal."""
    if not enabled or not console.is_terminal:
        yield lambda: None
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as prog:
        task = prog.add_task(description, total=total)
        yield lambda: prog.advance(task)
