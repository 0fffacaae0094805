"""Small simulated scenes for the batch tests, made once per session and copied per test."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

#: The fastest settings that still run every stage.
FAST = {"train": {"iterations": 5, "height": 8}, "evaluate": {"fps_repeats": 1}}
FAST_SET = ["--set", "train.iterations=5", "--set", "train.height=8", "--set", "evaluate.fps_repeats=1"]


@pytest.fixture(scope="session")
def scene_pool(tmp_path_factory) -> Path:
    from simulate.generate import generate_scene

    root = tmp_path_factory.mktemp("batch-scenes")
    for i in range(4):
        generate_scene(root / f"room{i}", views=3, test_views=1, height=16, seed=i, effects="none",
                       with_layout=True, with_depth=True)
    return root


@pytest.fixture
def scenes(scene_pool, tmp_path, monkeypatch) -> Path:
    """A fresh copy of the four scenes in tmp/scenes; the working folder is tmp/cwd."""
    shutil.copytree(scene_pool, tmp_path / "scenes")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    return tmp_path / "scenes"
