"""What commands print: status and progress on stderr, what was written where on stdout."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

console = Console(stderr=True, soft_wrap=True)  # status and progress
out = Console(soft_wrap=True)  # what a command wrote where

Advance = Callable[..., None]


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Advance]:
    """A rich progress bar on stderr (hidden when stderr is not a terminal); yields
    `advance(n, description=None)` (a new description replaces the bar's)."""
    with Progress(TextColumn("  {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True,
                  disable=not console.is_terminal) as progress:
        task = progress.add_task(description, total=total)

        def advance(n: int = 1, description: str | None = None) -> None:
            progress.update(task, advance=n, description=description)

        yield advance
