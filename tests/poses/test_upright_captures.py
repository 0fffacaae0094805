"""The default pose solver (`poses.method=auto`: the upright N-view solver) on simulated
captures with the hard parts of real ones. Apart from tests/poses/test_poses.py so that the
suite's two workers (`make test`: pytest-xdist, one module per worker at a time) share them out."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.engine import Engine
from pipeline.registry import build_registry
from schemas.scene_loader import load_scene
from sfm.bench import similarity_errors, simulate_capture


def _run_poses(scene: Path, run: Path, **params) -> dict:
    Engine(load_scene(scene), run, build_registry(), {"poses": params}).run(target="poses")
    return json.loads((run / "poses" / "artifact.json").read_text())["data"]


@pytest.mark.slow
# 13 views over the same rooms: tests/poses/test_plain_floor.py's capture (plain floor, the harder
# case) covers that count; the textured 13 are the bench's (`pano-pipe bench poses`)
@pytest.mark.parametrize("views,walk", [(8, False), (8, True)], ids=["8-views", "chain-8"])
def test_capture_over_three_rooms_placed_by_default_within_5cm_and_1_degree(tmp_path, views, walk):
    """Simulated captures with the hard parts of real ones (sfm.bench): three rooms seen from one
    another only through openings, bare walls, noise, exposure, a tripod, neighbours 1-6 m apart;
    the chain: cameras along a walk. Every view placed by the default, within 5 cm and 1°."""
    scene = tmp_path / "scene"
    truth = simulate_capture(scene, views, height=512, walk=walk)
    data = _run_poses(scene, tmp_path / "run")
    assert data["requested_method"] == "auto" and data["method"] == "upright", data["attempts"]
    posed = {v["view"]: np.asarray(v["pose"]) for v in data["views"] if v["registered"]}
    assert sorted(posed) == sorted(truth) and data["left_out"] == {}
    errors, scale = similarity_errors(posed, truth)
    assert max(e[0] for e in errors.values()) < 0.05, errors
    assert max(e[1] for e in errors.values()) < 1.0, errors
    assert data["frame"] == "floor" and abs(scale - 1.0) < 0.05, scale  # the metric scale from the floor
    assert data["residual_deg"] < 0.2
