"""Shared test helpers: tiny valid scenes to break in specific ways."""

from __future__ import annotations

import json
import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads; see pipeline/cli.py
# Tests never download LPIPS weights (CI is offline); subprocesses inherit this.
os.environ["PANO_PIPE_OFFLINE"] = "1"
# Tests never see the user's model cache: a cached layout model changes what the layout stage does.
# Tests that fetch models point PANO_PIPE_MODELS_DIR at their own folder.
os.environ["PANO_PIPE_MODELS_DIR"] = os.path.join(
    __import__("tempfile").mkdtemp(prefix="pano-pipe-test-models-"), "models")
os.environ.pop("PANO_PIPE_MODELS_REGISTRY", None)
# Without CUDA, the `cuda` splatting backend's Triton kernels run in the Triton interpreter.
# Triton reads this when it is first imported (its library functions are decorated then),
# so it is set here, before any test module can import triton (splatting/raster_triton.py).
import torch  # noqa: E402  (after OMP_WAIT_POLICY)

if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def yaw_pose(yaw: float, position=(0.0, -1.5, 0.0)) -> list[list[float]]:
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[:3, 3] = position
    return m.tolist()


def write_tiny_scene(root: Path, n_train: int = 2, n_test: int = 1, height: int = 8, seed: int = 0) -> Path:
    """A valid scene folder with random 2:1 images and level poses."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    views = []
    for i in range(n_train + n_test):
        name = f"v{i}"
        img = rng.integers(0, 255, size=(height, 2 * height, 3), dtype=np.uint8)
        cv2.imwrite(str(root / "images" / f"{name}.png"), img)
        views.append(
            {
                "name": name,
                "image": f"images/{name}.png",
                "pose": yaw_pose(0.3 * i, (0.5 * i, -1.5, 0.2 * i)),
                "split": "train" if i < n_train else "test",
                "camera_height": 1.5,
            }
        )
    (root / "scene.json").write_text(json.dumps({"name": root.name, "views": views}, indent=2))
    return root


@pytest.fixture
def tiny_scene(tmp_path: Path) -> Path:
    return write_tiny_scene(tmp_path / "tiny")

