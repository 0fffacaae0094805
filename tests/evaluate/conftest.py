"""Fixtures for the evaluation tests (helpers in evalhelpers.py)."""

from __future__ import annotations

import pytest

from evalhelpers import backprojected_gaussians, make_scene


@pytest.fixture(scope="session")
def sim_scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene") / "cub")


@pytest.fixture(scope="session")
def sim_model(sim_scene):
    return backprojected_gaussians(sim_scene)
