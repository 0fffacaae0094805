"""`make demo` installs what the pipeline needs, `make test` adds the test extras (checked with make -n)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _dry_run(folder: Path, target: str) -> list[str]:
    """The pip commands `make -n TARGET` would run in `folder`."""
    out = subprocess.run(["make", "-n", target], cwd=folder, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return [line.strip() for line in out.stdout.splitlines() if "pip install" in line]


@pytest.fixture()
def checkout(tmp_path):
    if shutil.which("make") is None:
        pytest.skip("no make")
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(ROOT / name, tmp_path / name)
    return tmp_path


def test_demo_installs_no_test_extras_and_test_adds_them(checkout):
    demo = _dry_run(checkout, "demo")
    assert any(line.endswith("install -q -e .") for line in demo)
    assert not any("[test" in line for line in demo)
    test = _dry_run(checkout, "test")
    assert any("[test" in line for line in test) and any(line.endswith("install -q -e .") for line in test)


def test_test_extras_are_added_to_a_demo_install_once(checkout):
    (checkout / ".venv").mkdir()
    (checkout / ".venv" / ".installed").touch()  # `make demo` ran: only the extras are missing
    assert [("[test" in line) for line in _dry_run(checkout, "test")] == [True]
    (checkout / ".venv" / ".installed-test").touch()
    assert _dry_run(checkout, "test") == []
