"""The one rich console and progress-bar factory the pipeline prints through."""

from __future__ import annotations


from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

#: What pano-pipe reports (progress, tables, warnings, results) goes to stdout, so it can be
#: piped or saved; stderr holds only the one-line error of a failed command (err_console).
console = Console(highlight=False)
err_console = Console(stderr=True, highlight=False)


def make_progress(*extra_columns) -> Progress:
    """A progress bar with count, rate (via extra columns) and ETA; quiet when not a terminal."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TaskProgressColumn(),
        *extra_columns,
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
        disable=not console.is_terminal,
    )


def track(iterable, description: str = "", total: int | None = None):
    """Iterate with a progress bar (count, %, elapsed, ETA)."""
    if total is None and hasattr(iterable, "__len__"):
        total = len(iterable)
    with make_progress() as progress:
        task = progress.add_task(description, total=total)
        for item in iterable:
            yield item
            progress.advance(task)
