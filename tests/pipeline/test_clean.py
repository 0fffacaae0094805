"""`pano-pipe clean`: asks before deleting a run, refuses without a terminal unless --yes, --dry-run lists."""

from __future__ import annotations

import io
import sys

import pytest

from simulate.generate import generate_scene
from tests.clitools import invoke, run_main


class _Terminal(io.StringIO):
    """stdin as a terminal on which the user types `answer`."""

    def isatty(self) -> bool:
        return True


@pytest.fixture()
def run(tmp_path):
    generate_scene(tmp_path / "S", views=2, test_views=0, height=16, effects="none", with_layout=True)
    assert run_main(["run", "layout", tmp_path / "S", "--out", tmp_path / "R"]) == 0
    return tmp_path


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def test_without_a_terminal_clean_refuses_unless_yes(run, capsys):
    before = _files(run / "R")
    code, out, err = invoke(["clean", run / "S", "--out", run / "R"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--yes" in err and str(run / "R") in err
    assert _files(run / "R") == before
    code, out, err = invoke(["clean", run / "S", "--out", run / "R", "--yes"], capsys)
    assert code == 0, err
    assert not (run / "R").exists()


def test_dry_run_lists_and_deletes_nothing(run, capsys):
    before = _files(run / "R")
    code, out, err = invoke(["clean", run / "S", "--out", run / "R", "--dry-run"], capsys)
    assert code == 0, err
    assert f"would delete {run / 'R'}" in " ".join(out.split()) and "layout/" in out
    assert _files(run / "R") == before


@pytest.mark.parametrize("answer, deleted", [("y\n", True), ("n\n", False), ("\n", False)])
def test_on_a_terminal_clean_asks(run, capsys, monkeypatch, answer, deleted):
    monkeypatch.setattr(sys, "stdin", _Terminal(answer))
    code, out, err = invoke(["clean", run / "S", "--out", run / "R"], capsys)
    assert code == 0, err
    assert f"delete {run / 'R'}" in " ".join(out.split())  # the question names what goes
    assert (run / "R").exists() != deleted
