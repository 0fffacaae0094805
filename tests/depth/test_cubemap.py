"""Cube faces: sampling conventions, and face-scale alignment before stitching (exact simulator depth)."""

from __future__ import annotations

import numpy as np
import pytest

from depthnet.cubemap import FACE_NAMES, face_cos, sample_face, stitch
from panogeom.equirect import ray_directions

H = 64


@pytest.fixture(scope="module")
def gt(dk, tmp_path_factory):
    scene = dk.make_encoded_scene(tmp_path_factory.mktemp("cube") / "s", "cuboid", views=1, height=H, seed=5)
    return dk.gt_depth(scene, scene.manifest.train_views()[0])


def test_faces_look_along_their_axes():
    # An equirect image of the camera-frame direction: each face's centre sees its own axis.
    dirs = ray_directions(H, 2 * H).astype(np.float32)
    axes = {
        "front": (0, 0, 1),
        "right": (1, 0, 0),
        "back": (0, 0, -1),
        "left": (-1, 0, 0),
        "up": (0, -1, 0),
        "down": (0, 1, 0),
    }
    for name in FACE_NAMES:
        face = sample_face(dirs, name, 16, 90.0)
        centre = face[7:9, 7:9].mean((0, 1))
        assert np.allclose(centre / np.linalg.norm(centre), axes[name], atol=0.03), name
        # Right of the image is the face's +x, down its +y: the right face's right edge looks back (-z).
    right = sample_face(dirs, "right", 16, 90.0)
    assert right[8, -1, 2] < -0.5 and right[-1, 8, 1] > 0.5


@pytest.mark.parametrize("kind", ["metric", "disparity", "relative"])
def test_face_alignment_undoes_per_face_scales(gt, kind):
    rng = np.random.default_rng(0)
    size, fov = 32, 100.0
    cos = face_cos(size, fov)
    faces = []
    for i, name in enumerate(FACE_NAMES):
        z = sample_face(gt.astype(np.float32), name, size, fov) * cos  # depth along the face axis
        s = 1.0 if i == 0 else rng.uniform(0.7, 1.4)
        if kind == "metric":
            faces.append(z * s)
        elif kind == "relative":
            faces.append(z * s + rng.uniform(-0.3, 0.3))
        else:
            faces.append(s / z + rng.uniform(-0.05, 0.2))
    faces = np.stack(faces)
    out, info = stitch(faces, kind, fov, (H, 2 * H))
    raw, _ = stitch(faces, kind, fov, (H, 2 * H), align=False)

    def err(m):
        d = m if kind != "disparity" else 1.0 / m
        # Up to one global scale (and, for affine kinds, the shift fixed through the overlaps).
        k = np.nanmedian(gt / d)
        return np.nanmedian(np.abs(k * d / gt - 1))

    print(
        f"{kind}: stitched error {err(out):.3%} aligned vs {err(raw):.3%} unaligned; "
        f"face scales {np.round(info['face_scales'], 3)}"
    )
    assert err(out) < 0.01 and err(raw) > 3 * err(out)
