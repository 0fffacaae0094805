"""The mesh method on a point set of known geometry: the simulated room's true box."""

from __future__ import annotations

import json

import numpy as np
from export_helpers import distance_to_box, room_box

from export.mesh import OrientedPoints, reconstruct


def _box_points(box: dict, spacing: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points on the six faces of the box (with ±5 mm noise), normals into the room."""
    (x0, x1), (y0, y1), (z0, z1) = box["x"], box["y"], box["z"]
    pts, nrm = [], []
    for axis, (lo, hi) in enumerate([(x0, x1), (y0, y1), (z0, z1)]):
        a, b = [i for i in range(3) if i != axis]
        ra, rb = [(x0, x1), (y0, y1), (z0, z1)][a], [(x0, x1), (y0, y1), (z0, z1)][b]
        n = int((ra[1] - ra[0]) * (rb[1] - rb[0]) / spacing ** 2)
        for value, sign in ((lo, 1.0), (hi, -1.0)):
            p = np.zeros((n, 3))
            p[:, a] = rng.uniform(*ra, n)
            p[:, b] = rng.uniform(*rb, n)
            p[:, axis] = value + rng.normal(0, 0.005, n)
            q = np.zeros((n, 3))
            q[:, axis] = sign
            pts.append(p)
            nrm.append(q)
    return np.concatenate(pts), np.concatenate(nrm)


def test_poisson_mesh_of_the_true_room_lies_on_its_walls(trained_run):
    scene = trained_run / "S"
    box = room_box(scene)
    cams = np.array([np.asarray(v["pose"])[:3, 3] for v in json.loads((scene / "scene.json").read_text())["views"]])
    rng = np.random.default_rng(0)
    pts, nrm = _box_points(box, 0.05, rng)
    nearest = cams[np.argmin(((pts[:, None] - cams[None]) ** 2).sum(-1), 1)]
    # the production path: normals estimated by pymeshlab, turned towards the cameras
    mesh = reconstruct(OrientedPoints(pts, rng.uniform(0, 1, (len(pts), 3)), viewpoints=nearest), depth=7)
    d = distance_to_box(mesh.vertices, box)
    print(f"box mesh: {len(mesh.vertices)} vertices, median {100 * np.median(d):.2f} cm, "
          f"90th percentile {100 * np.percentile(d, 90):.2f} cm, max {100 * d.max():.2f} cm")
    assert np.median(d) < 0.03
    assert np.percentile(d, 90) < 0.05
    # faces look into the room: their normals point towards the room's centre
    centre = np.array([np.mean(box[a]) for a in "xyz"])
    tri = mesh.vertices[mesh.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = ((centre - tri.mean(1)) * fn).sum(1) > 0
    assert inward.mean() > 0.9 or inward.mean() < 0.1  # consistently oriented
    # colours came from the input points
    assert mesh.colors.shape == mesh.vertices.shape and 0 <= mesh.colors.min() and mesh.colors.max() <= 1
