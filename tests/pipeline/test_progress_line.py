"""The progress line: the current rate (not an average from the start), and at 80 columns the
step count and ETA kept, decorations dropped first."""

from __future__ import annotations

import io

import pytest
from rich.console import Console
from rich.progress import TextColumn

import runtime.console as pc


def test_the_rate_is_the_recent_one():
    rate = pc.RecentRate(window_s=10.0)
    assert rate.update(0, 0.0) is None
    assert rate.update(1, 60.0) == pytest.approx(1 / 60)  # a first step of a minute (a warm-up)
    for i in range(1, 11):  # then 8 steps per second
        got = rate.update(1 + 8 * 5 * i, 60.0 + 5 * i)
    assert got == pytest.approx(8.0)  # the minute is out of the window; from the start: 2.1


def _line(monkeypatch, width: int) -> str:
    monkeypatch.setattr(pc, "console", Console(file=io.StringIO(), width=width, force_terminal=True,
                                               color_system=None))
    progress = pc.make_progress(TextColumn("loss {task.fields[loss]}"), TextColumn("PSNR {task.fields[psnr]}"),
                                TextColumn("{task.fields[count]} G"),
                                (TextColumn("{task.fields[rate]} it/s"), pc.KEEP_FIELD + 1))
    task = progress.add_task("train (layout, 360, cpu)", total=2000, loss="0.0123", psnr="31.52", count=40000,
                             rate="7.9")
    progress.update(task, completed=500)
    pc.console.print(progress.make_tasks_table(progress.tasks))
    return pc.console.file.getvalue()


@pytest.mark.parametrize("width", [80, 60, 200])
def test_the_line_fits_and_keeps_the_step_count_and_eta(monkeypatch, width):
    text = _line(monkeypatch, width)
    lines = text.rstrip("\n").splitlines()
    assert len(lines) == 1 and len(lines[0]) <= width
    assert "500/2000" in text and "ETA" in text and "it/s" in text
    assert ("━" in text) == (width == 200)  # the bar goes first


def test_at_80_columns_the_fields_stay_and_the_decorations_go(monkeypatch):
    text = _line(monkeypatch, 80)
    assert "loss 0.0123" in text and "PSNR 31.52" in text and "7.9 it/s" in text
    assert "25%" not in text and "━" not in text
