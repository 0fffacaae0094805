"""Shared fixtures for the simulator tests: small scenes, generated once per session."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from schemas.scene import SceneManifest
from simulate import generate_scene

H = 64  # small: the suite must stay fast on a shared 2-core machine


class LoadedScene:
    def __init__(self, root: Path):
        self.root = root
        self.manifest = SceneManifest.model_validate_json((root / "scene.json").read_text())
        self.floor_plan = json.loads((root / "gt" / "floor_plan.json").read_text())

    def depth(self, name: str) -> np.ndarray:
        return np.load(self.root / "gt" / "depth" / f"{name}.npy")

    def layout(self, name: str) -> np.ndarray:
        return np.load(self.root / "gt" / "layout" / f"{name}.npy")

    def layout_json(self, name: str) -> dict:
        return json.loads((self.root / "gt" / "layout" / f"{name}.json").read_text())

    def image(self, name: str) -> np.ndarray:
        return cv2.imread(str(self.root / "images" / f"{name}.png"), cv2.IMREAD_UNCHANGED)

    @property
    def ceiling_height(self) -> float:
        return -self.floor_plan["rooms"][0]["ceiling_y"]


@pytest.fixture(scope="session")
def scenes(tmp_path_factory) -> dict[tuple[str, str], LoadedScene]:
    """(preset, effects) -> scene, generated lazily."""
    base = tmp_path_factory.mktemp("sim")
    cache: dict[tuple[str, str], LoadedScene] = {}

    class _Lazy(dict):
        def __missing__(self, key):
            preset, fx = key
            out = base / f"{preset}-{fx.replace(',', '_')}"
            generate_scene(out, preset=preset, views=3, test_views=2, height=H, seed=1, effects=fx,
                           with_layout=True, with_depth=True)
            self[key] = LoadedScene(out)
            return self[key]

    return _Lazy(cache)
