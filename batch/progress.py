"""What a batch shows while it runs, and the table it ends with.

On a terminal: a live table of scenes x stages (queued, running, ran, cached, skipped,
failed, blocked), redrawn as jobs start and finish. Elsewhere (a pipe, a log file, CI): one
plain line per finished job and a heartbeat line every `heartbeat_s` seconds.
"""

from __future__ import annotations

import time

from rich.console import Console
from rich.live import Live
from rich.markup import escape
from rich.table import Table

#: The batch's own console (stdout): while it runs, the stages' console is quiet, so the live
#: table is the one thing drawing on the terminal.
console = Console(highlight=False)

STYLES = {
    "queued": "dim", "running": "bold cyan", "ran": "green", "cached": "green", "skipped": "dim",
    "failed": "bold red", "blocked": "red", "": "dim",
}
SYMBOLS = {"queued": "·", "running": "▶", "ran": "✓", "cached": "=", "skipped": "–", "failed": "✗",
           "blocked": "∅", "": " "}


class Board:
    def __init__(self, scenes: list[str], stages: list[str], executor: str, heartbeat_s: float = 30.0):
        self.scenes, self.stages, self.executor = scenes, stages, executor
        self.cells: dict[tuple[str, str], str] = {(s, t): "" for s in scenes for t in stages}
        self.heartbeat_s = heartbeat_s
        self._live: Live | None = None
        self._last_beat = time.monotonic()
        self._t0 = time.monotonic()

    def __enter__(self):
        if console.is_terminal:
            self._live = Live(self.table(), console=console, refresh_per_second=4, transient=False)
            self._live.__enter__()
        else:
            console.print(f"batch: {len(self.scenes)} scenes x {len(self.stages)} stages, "
                          f"executor {self.executor}", soft_wrap=True)
        return self

    def __exit__(self, *exc):
        if self._live is not None:
            self._live.update(self.table())
            self._live.__exit__(*exc)
        return False

    def set(self, scene: str, stage: str, state: str, note: str = "") -> None:
        """A job's new state; `note`: its duration or its error, for the plain lines."""
        if self.cells.get((scene, stage)) == state:
            return
        self.cells[(scene, stage)] = state
        if self._live is not None:
            self._live.update(self.table())
        elif state not in ("queued", "running"):
            console.print(f"{escape(scene)}/{stage}: {state}" + (f" ({escape(note)})" if note else ""),
                          soft_wrap=True)

    def tick(self) -> None:
        """Called while waiting: a heartbeat line when not on a terminal."""
        now = time.monotonic()
        if self._live is None and now - self._last_beat >= self.heartbeat_s:
            self._last_beat = now
            counts = {}
            for state in self.cells.values():
                counts[state or "waiting"] = counts.get(state or "waiting", 0) + 1
            shown = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
            console.print(f"batch: {now - self._t0:.0f} s: {shown}", soft_wrap=True)

    def table(self) -> Table:
        table = Table(title=f"batch ({self.executor})", title_justify="left")
        table.add_column("scene")
        for stage in self.stages:
            table.add_column(stage, justify="center")
        for scene in self.scenes:
            row = []
            for stage in self.stages:
                state = self.cells[(scene, stage)]
                row.append(f"[{STYLES[state]}]{SYMBOLS[state]} {state}[/]" if state else "")
            table.add_row(escape(scene), *row)
        return table


def summary_table(rows: list[dict]) -> Table:
    """The end of a batch: one row per scene."""
    table = Table(title="batch summary", title_justify="left")
    for col, justify in (("scene", "left"), ("ran", "right"), ("cached", "right"), ("skipped", "right"),
                         ("failed", "right"), ("wall s", "right"), ("test PSNR", "right"), ("error", "left")):
        table.add_column(col, justify=justify)
    for r in rows:
        psnr = f"{r['psnr']:.2f}" if r.get("psnr") is not None else "—"
        table.add_row(escape(r["scene"]), str(r["ran"]), str(r["cached"]), str(r["skipped"]),
                      f"[red]{r['failed']}[/]" if r["failed"] else "0", f"{r['wall_s']:.1f}", psnr,
                      escape(r.get("error", "")))
    return table
