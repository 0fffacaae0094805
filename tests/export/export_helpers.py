"""Helpers of the export tests: random models, the CLI in-process, the simulated room's box."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from gaussians.model import Gaussians
from tests.clitools import invoke


def random_gaussians(n: int = 200, degree: int = 3, seed: int = 0, dtype=torch.float32, spread: float = 3.0
                     ) -> Gaussians:
    """N random Gaussians in a ±`spread` m cube, every field non-trivial."""
    gen = torch.Generator().manual_seed(seed)

    def u(*shape, lo=-1.0, hi=1.0):
        return lo + (hi - lo) * torch.rand(*shape, generator=gen, dtype=torch.float64)

    k = (degree + 1) ** 2
    means = u(n, 3, lo=-spread, hi=spread)
    g = Gaussians(
        means=means,
        quats=u(n, 4) * 2.0,
        log_scales=u(n, 3, lo=math.log(0.005), hi=math.log(0.3)),
        opacity_logits=u(n, lo=-4, hi=4),
        sh_dc=u(n, 1, 3, lo=-1.5, hi=1.5),
        sh_rest=u(n, k - 1, 3, lo=-0.9, hi=0.9),
        is_layout=torch.rand(n, generator=gen) > 0.5,
        normals=torch.nn.functional.normalize(u(n, 3), dim=1),
        u0=means + 0.01 * u(n, 3),
    )
    return g.to(dtype=dtype)


def run_cli(args: list, capsys) -> tuple[int, str]:
    """Run `pano-pipe ARGS` in-process: (exit code, stdout + stderr)."""
    capsys.readouterr()
    code, out, err = invoke(args, capsys)
    return code, out + err


def room_box(scene: Path) -> dict:
    """The simulated room's true planes from gt/floor_plan.json (one rectangular room)."""
    fp = json.loads((scene / "gt" / "floor_plan.json").read_text())["rooms"][0]
    poly = np.asarray(fp["polygon"], dtype=np.float64)
    return {"x": (poly[:, 0].min(), poly[:, 0].max()), "z": (poly[:, 1].min(), poly[:, 1].max()),
            "y": (fp["ceiling_y"], fp["floor_y"])}


def distance_to_box(points: np.ndarray, box: dict) -> np.ndarray:
    """Distance of each point to the nearest of the room's six planes."""
    d = [np.abs(points[:, i, None] - np.asarray(box[a])[None]) for i, a in enumerate("xyz")]
    return np.concatenate(d, 1).min(1)
