"""Tiny training fixtures: a 32×64 simulated room and its views."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

import splatting
from gaussians.config import TrainConfig
from gaussians.trainer import TrainView
from panogeom.images import read_rgb
from schemas.scene import SceneManifest

H = 32


def tiny_scene(root: Path, seed: int = 0) -> Path:
    from simulate import generate_scene

    if not (root / "scene.json").is_file():
        generate_scene(root, preset="cuboid", views=3, test_views=1, height=H, seed=seed, effects="shading",
                       aa_samples=1)
    return root


def load_views(root: Path, split: str = "train", height: int = H) -> list[TrainView]:
    m = SceneManifest.model_validate_json((root / "scene.json").read_text())
    views = m.train_views() if split == "train" else m.test_views()
    out = []
    for v in views:
        img = torch.from_numpy(read_rgb(root / v.image, size=(height, 2 * height)))
        out.append(TrainView(v.name, img, torch.tensor(v.viewmat, dtype=torch.float32),
                             splatting.EquirectCamera(height, 2 * height)))
    return out


def rooms(root: Path) -> list[dict]:
    return json.loads((root / "gt" / "floor_plan.json").read_text())["rooms"]


def camera_positions(root: Path) -> np.ndarray:
    m = SceneManifest.model_validate_json((root / "scene.json").read_text())
    return np.stack([v.position for v in m.views])


def small_config(**kw) -> TrainConfig:
    base = dict(iterations=40, extent=3.0, densify_from=10, densify_until=35, densify_every=10,
                opacity_reset_every=0, sh_degree_every=15, max_gaussians=3000, log_every=5,
                checkpoint_every=0, backend="cpp")
    base.update(kw)
    return TrainConfig.of(**base)
