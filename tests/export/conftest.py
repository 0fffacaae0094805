"""Fixtures of the export tests: a small random model, a tiny trained run, the CLI."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from gaussians.model import Gaussians
from tests.clitools import run_main
from export_helpers import random_gaussians


@pytest.fixture
def model() -> Gaussians:
    return random_gaussians()


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory) -> Path:
    """A tiny simulated room trained for 5 iterations (runs once per session): root/S, root/R."""
    from simulate.generate import generate_scene

    root = tmp_path_factory.mktemp("export_run")
    generate_scene(root / "S", views=3, test_views=1, height=32, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R", "--until", "train",
                     "--set", "train.iterations=5", "--set", "train.height=8"]) == 0
    assert (root / "R" / "train" / "point_cloud.ply").is_file()
    return root


@pytest.fixture
def run_copy(tmp_path, trained_run) -> Path:
    """A private copy of the trained run folder (tests may break it); its scene stays shared."""
    shutil.copytree(trained_run / "R", tmp_path / "R")
    return tmp_path / "R"
