"""Fixtures of the export tests: a small random model, a tiny trained run, the CLI."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gaussians.model import Gaussians


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


@pytest.fixture
def model() -> Gaussians:
    return random_gaussians()


def ensure_export_registered():
    """Register `export` on the CLI app if pipeline/cli.py does not (yet) do it itself."""
    from pipeline import cli

    names = {c.name for c in cli.app.registered_commands}
    if "export" not in names:
        from export.command import export_command

        cli.app.command("export")(export_command)
    return cli


def run_cli(args: list, capsys) -> tuple[int, str]:
    """Run `pano-pipe ARGS` in-process: (exit code, stdout + stderr)."""
    cli = ensure_export_registered()
    old = sys.argv
    sys.argv = ["pano-pipe", *[str(a) for a in args]]
    capsys.readouterr()
    try:
        cli.main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    finally:
        sys.argv = old
    cap = capsys.readouterr()
    return code, cap.out + cap.err


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory) -> Path:
    """A tiny simulated room trained for 5 iterations (runs once per session): root/S, root/R."""
    from simulate.generate import generate_scene

    cli = ensure_export_registered()
    root = tmp_path_factory.mktemp("export_run")
    generate_scene(root / "S", views=3, test_views=1, height=32, effects="none", with_layout=True, with_depth=True)
    old = sys.argv
    sys.argv = ["pano-pipe", "run", "all", str(root / "S"), "--out", str(root / "R"), "--until", "train",
                "--set", "train.iterations=5", "--set", "train.height=8"]
    try:
        cli.main()
    except SystemExit as e:
        assert e.code in (0, None), f"training run failed with exit {e.code}"
    finally:
        sys.argv = old
    assert (root / "R" / "train" / "point_cloud.ply").is_file()
    return root


@pytest.fixture
def run_copy(tmp_path, trained_run) -> Path:
    """A private copy of the trained run folder (tests may break it); its scene stays shared."""
    shutil.copytree(trained_run / "R", tmp_path / "R")
    return tmp_path / "R"


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
