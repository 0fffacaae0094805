"""The one rich console and progress-bar factory the pipeline prints through."""

from __future__ import annotations


import time

from rich.console import Console
from rich.markup import escape
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


class PlainProgress:
    """Progress for a pipe or a log file: a plain line per task every `every_s` seconds and at
    its end (description, count, percent, elapsed, ETA and the task's fields), through the
    same calls as rich's Progress (add_task, update, advance, with-block).

    The ETA's rate is measured from the task's first advance on, as rich measures it: the time
    before it (a kernel compile, a first iteration's warm-up) says nothing about the steps after."""

    def __init__(self, every_s: float = 10.0):
        self.every_s = every_s
        self._tasks: dict[int, dict] = {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            for task_id, t in self._tasks.items():
                if not t["printed_end"]:
                    self._line(task_id)
        return False

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields) -> int:
        task_id = len(self._tasks)
        now = time.monotonic()
        self._tasks[task_id] = {"description": description, "total": total, "completed": completed,
                                "start": completed, "fields": fields, "t0": now, "last": now,
                                "printed_end": False, "rate_from": None}
        return task_id

    def update(self, task_id: int, completed: float | None = None, advance: float | None = None, **fields) -> None:
        t = self._tasks[task_id]
        before = t["completed"]
        if completed is not None:
            t["completed"] = completed
        if advance is not None:
            t["completed"] += advance
        t["fields"].update(fields)
        now = time.monotonic()
        if t["rate_from"] is None and t["completed"] != before:
            t["rate_from"] = (now, t["completed"])  # the first step done: the rate is timed from here
        done = t["total"] is not None and t["completed"] >= t["total"]
        if now - t["last"] >= self.every_s or (done and not t["printed_end"]):
            t["last"] = now
            t["printed_end"] = done
            self._line(task_id)

    def advance(self, task_id: int, advance: float = 1) -> None:
        self.update(task_id, advance=advance)

    def _line(self, task_id: int) -> None:
        t = self._tasks[task_id]
        elapsed = time.monotonic() - t["t0"]
        parts = [f"{t['description']}: {t['completed']:g}"]
        if t["total"]:
            parts[0] += f"/{t['total']:g} ({100 * t['completed'] / t['total']:.0f}%)"
            rate = 0.0
            if t["rate_from"] is not None:
                since, at = t["rate_from"]
                seconds = time.monotonic() - since
                rate = (t["completed"] - at) / seconds if seconds > 0 else 0.0
            if 0 < rate and t["completed"] < t["total"]:
                parts.append(f"ETA {(t['total'] - t['completed']) / rate:.0f} s")
        parts.append(f"{elapsed:.0f} s")
        parts += [f"{k} {v}" for k, v in t["fields"].items() if v not in ("-", "", None)]
        console.print(escape(", ".join(parts)), soft_wrap=True, highlight=False)


def make_progress(*extra_columns) -> Progress | PlainProgress:
    """A progress bar with count, rate (via extra columns) and ETA on a terminal; plain periodic
    lines otherwise (a pipe, a log file, CI)."""
    if not console.is_terminal:
        return PlainProgress()
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
