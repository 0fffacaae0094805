"""A real panorama (HorizonNet's demo, PanoContext) with HorizonNet's own layout JSON:
the stage's metric room must be the geometry the JSON implies at 1.6 m camera height."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from layout_helpers import match_corners, run_layout
from shapely.geometry import Point, Polygon

from layoutnet import postprocess as pp

DEMO = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "horizonnet_demo"
pytestmark = pytest.mark.skipif(
    not (DEMO / "demo_aligned_rgb.json").is_file(), reason="shared demo data absent"
)


def _horizonnet_room(data: dict, camera_height: float = 1.6) -> tuple[np.ndarray, float]:
    """HorizonNet's own formulas (misc/post_proc.py): coorx2u, coory2v, the ceiling corners
    on the plane z0 at distance z0 / tan(v); metres = units * camera_height / -z1."""
    uv = np.asarray(data["uv"], dtype=np.float64)
    ceil = uv[0::2] * [1024, 512]
    u = ((ceil[:, 0] + 0.5) / 1024 - 0.5) * 2 * np.pi
    v = -((ceil[:, 1] + 0.5) / 512 - 0.5) * np.pi
    scale = camera_height / -data["z1"]
    c = data["z0"] / np.tan(v) * scale
    return np.stack([c * np.sin(u), c * np.cos(u)], axis=1), data["z0"] * scale


@pytest.fixture
def demo_scene(tmp_path) -> Path:
    root = tmp_path / "demo"
    root.mkdir()
    for name in ("demo_aligned_rgb.png", "demo_aligned_rgb.json"):  # a scene names files inside itself
        shutil.copy(DEMO / name, root / name)
    view = {
        "name": "demo",
        "image": "demo_aligned_rgb.png",
        "pose": np.eye(4).tolist(),
        "camera_height": 1.6,
        "layout": "demo_aligned_rgb.json",
    }
    (root / "scene.json").write_text(json.dumps({"name": "demo", "views": [view]}))
    return root


def test_demo_panorama_to_metric_room(demo_scene, tmp_path):
    data = json.loads((DEMO / "demo_aligned_rgb.json").read_text())
    out, warnings = run_layout(demo_scene, tmp_path / "out")
    lay = out.view("demo")
    assert lay.source == "json" and lay.method == "corners" and not warnings
    ref, ceiling = _horizonnet_room(data)
    poly = np.asarray(lay.floor_polygon)
    assert len(poly) == len(ref) == 8
    assert match_corners(poly, ref) < 1e-3  # float32 rounding in HorizonNet's JSON
    assert lay.ceiling_distance == pytest.approx(ceiling, abs=1e-6)
    assert lay.camera_height + lay.ceiling_distance == pytest.approx(
        1.6 * (1 + 50 / 53.993988037109375), abs=1e-6
    )
    # HorizonNet's walls are Manhattan in the aligned panorama's frame: every edge axis-parallel.
    edges = np.roll(poly, -1, axis=0) - poly
    assert np.abs(edges).min(axis=1).max() < 0.01
    shape = Polygon(poly)
    assert shape.is_valid and shape.contains(Point(0, 0))
    assert 10 < shape.area < 40  # an ordinary room, in square metres
    fitted = np.load(tmp_path / "out" / lay.boundaries)
    assert fitted.shape == (2, 1024)
    # Corner latitudes the JSON states are those of the fitted room's boundaries, except
    # where a nearer wall hides the corner (HorizonNet's corner at u = 0.0073 lies behind
    # the wall ending at u = 0.0146): there the boundary is nearer (further from the horizon).
    uv = np.asarray(data["uv"]).reshape(-1, 2, 2)
    seen = 0
    for (uc, vc), (_, vf) in uv:
        col = int(round(uc * 1024))
        lats = [-((v * 512 + 0.5) / 512 - 0.5) * np.pi for v in (vc, vf)]
        near = fitted[:, [(col - 1) % 1024, col % 1024, (col + 1) % 1024]]
        err = np.abs(near - np.asarray(lats)[:, None]).min(axis=1)
        if err.max() < 0.02:
            seen += 1
        else:
            assert (np.abs(near).min(axis=1) > np.abs(lats)).all()
    assert seen == 7


def test_demo_boundaries_refit_to_the_same_room(tmp_path):
    """The room's [2,W] boundaries, fitted again as if a model had output them (Manhattan
    post-processing, corners found from the boundaries alone), give the same walls."""
    data = json.loads((DEMO / "demo_aligned_rgb.json").read_text())
    ref, ceiling = _horizonnet_room(data)
    b = pp.polygon_to_boundaries(ref, 1.6, ceiling, 1024)
    room = pp.layout_from_boundaries(b, 1.6, mode="manhattan")
    assert room.ceiling_distance == pytest.approx(ceiling, abs=1e-6)
    # All eight corners, the two of the wall seen from behind (7 columns, found as the
    # hidden wall on the occluding ray) within a column's width: 6.4 mm measured.
    assert room.method == "manhattan" and len(room.polygon) == 8
    assert match_corners(room.polygon, ref) < 0.01
    assert Polygon(room.polygon).symmetric_difference(Polygon(ref)).area < 0.05
