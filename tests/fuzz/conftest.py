"""Fixtures of the fuzz suite: one tiny scene and one good run of it per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from fuzz_helpers import build_base, wait_for_cleanup


@pytest.fixture(scope="session")
def fuzz_base(tmp_path_factory) -> tuple[Path, Path]:
    """(scene folder, run folder): copied into a fresh sandbox by every example, never changed."""
    yield build_base(tmp_path_factory.mktemp("fuzz-base"))
    wait_for_cleanup()


@pytest.fixture(autouse=True)
def _join_cleanup():
    """Each test's sandboxes are gone before the next test starts."""
    yield
    wait_for_cleanup()
