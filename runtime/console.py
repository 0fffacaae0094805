"""The one rich console and progress-bar factory the pipeline prints through."""

from __future__ import annotations


import time
from collections import deque

from rich.console import Console
from rich.markup import escape
from rich.measure import Measurement
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text

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


class RecentRate:
    """Steps per second over about the last `window_s` seconds: the current rate. An average from
    the start stays low long after a slow start (a first iteration's warm-up, a slow phase)."""

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        self._samples: deque[tuple[float, float]] = deque()

    def update(self, count: float, now: float) -> float | None:
        """Record `count` steps done at time `now` (seconds); the rate, None before two samples."""
        self._samples.append((now, count))
        while len(self._samples) > 2 and now - self._samples[1][0] >= self.window_s:
            self._samples.popleft()  # the oldest kept still starts a window of at least window_s
        t0, c0 = self._samples[0]
        return (count - c0) / (now - t0) if now > t0 else None


class EtaColumn(TimeRemainingColumn):
    """'ETA 0:01:23': the label and the time, kept or dropped together."""

    def render(self, task) -> Text:
        return Text.assemble("ETA ", super().render(task))


#: Column priorities of a progress line (FittingProgress): what an 80-column terminal keeps.
KEEP_ALWAYS, KEEP_DESCRIPTION, KEEP_FIELD, KEEP_ELAPSED, KEEP_DECORATION = 10, 6, 3, 2, 0


class FittingProgress(Progress):
    """rich's Progress with each task on one line that fits the console: columns are dropped,
    lowest priority first (the bar and percentage, then elapsed time, then the extra fields; among
    equals the rightmost), never the step count and ETA."""

    def __init__(self, *columns: tuple[ProgressColumn, int], **kwargs):
        self.priorities = [priority for _, priority in columns]
        super().__init__(*(c for c, _ in columns), **kwargs)

    def make_tasks_table(self, tasks) -> Table:
        tasks = [t for t in tasks if t.visible]
        if not tasks:  # nothing to fit (also while Progress is being made: no console yet)
            return Table.grid()
        options = self.console.options
        widths = [max((Measurement.get(self.console, options, column(t)).maximum for t in tasks), default=0)
                  for column in self.columns]
        keep = list(range(len(self.columns)))
        while len(keep) > 1 and sum(widths[i] for i in keep) + len(keep) - 1 > self.console.width:
            keep.remove(min(keep, key=lambda i: (self.priorities[i], -i)))
        table = Table.grid(*(self.columns[i].get_table_column().copy() for i in keep), padding=(0, 1),
                           expand=self.expand)
        for task in tasks:
            table.add_row(*(self.columns[i](task) for i in keep))
        return table


def make_progress(*extra_columns) -> Progress | PlainProgress:
    """A progress bar with count, rate (via extra columns: a column, or (column, priority) to
    outrank the others) and ETA on a terminal, fitted to its width; plain periodic lines
    otherwise (a pipe, a log file, CI)."""
    if not console.is_terminal:
        return PlainProgress()
    extra = [c if isinstance(c, tuple) else (c, KEEP_FIELD) for c in extra_columns]
    return FittingProgress(
        (TextColumn("[bold]{task.description}"), KEEP_DESCRIPTION),
        (BarColumn(), KEEP_DECORATION),
        (MofNCompleteColumn(), KEEP_ALWAYS),
        (TaskProgressColumn(), KEEP_DECORATION),
        *extra,
        (TimeElapsedColumn(), KEEP_ELAPSED),
        (EtaColumn(), KEEP_ALWAYS),
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
