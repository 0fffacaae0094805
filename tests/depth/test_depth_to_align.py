"""depth -> align with the real union and sampling stages: ONNX models and scaled files, end to end."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from runfs.errors import PanoError
from stages.cloud_io import read_cloud


@pytest.fixture(scope="module")
def scene(dk, tmp_path_factory):
    return dk.make_encoded_scene(
        tmp_path_factory.mktemp("chain") / "s", "cuboid", views=2, height=64, seed=8, with_depth=True
    )


def test_scaled_depth_files_are_rescaled_and_merged(dk, chain, scene, tmp_path):
    k = 0.43
    for v in scene.manifest.train_views():  # the supplied files are off by a factor k
        mm = np.round(dk.gt_depth(scene, v) * 1000 * k).astype(np.uint16)
        cv2.imwrite(str(scene.depth_path(v)), mm)
    out, folder = chain.run(scene, tmp_path, {})
    print(
        f"files x{k}: scale error {abs(out.scale * k - 1):.4%}, ICP factor {out.fits[0].icp_factor:.5f}, "
        f"fitness {out.fits[0].icp_fitness:.3f}"
    )
    assert abs(out.scale * k - 1) < 0.01 and out.aligned_to_layout
    cloud = read_cloud(folder / "cloud.npz")
    dp = cloud["points"][~cloud["is_layout"]]
    d = chain.surface_distance(scene, dp)
    print(f"merged: {len(dp)} depth points, {np.mean(d < 0.02):.1%} within 2 cm")
    assert np.mean(d < 0.02) >= 0.95
    assert cloud["is_layout"].sum() > 1000 and np.allclose(
        np.linalg.norm(cloud["normals"][cloud["is_layout"]], axis=1), 1
    )


def test_depth_anything_like_model_end_to_end(dk, chain, scene, tmp_path):
    model = dk.export(dk.DepthAnythingLike(), tmp_path / "da.onnx", (1, 3, 28, 56), dynamic=True)
    params = dict(
        model=str(model), prefer="model", output="disparity", normalization="imagenet", multiple_of=14
    )
    out, folder = chain.run(scene, tmp_path, params)
    assert len(out.fits) == 2 and all(f.kind == "disparity" and len(f.views) == 1 for f in out.fits)
    cloud = read_cloud(folder / "cloud.npz")
    d = chain.surface_distance(scene, cloud["points"][~cloud["is_layout"]])
    print(
        f"Depth-Anything-like end to end: inliers {[round(f.inlier_share, 3) for f in out.fits]}, "
        f"{np.mean(d < 0.02):.1%} of merged points within 2 cm"
    )
    assert np.mean(d < 0.05) >= 0.95


def test_disparity_model_without_layout_is_refused(dk, chain, scene, tmp_path):
    model = dk.export(dk.DepthAnythingLike(), tmp_path / "da.onnx", (1, 3, 28, 56), dynamic=True)
    params = dict(
        model=str(model), prefer="model", output="disparity", normalization="imagenet", multiple_of=14
    )
    with pytest.raises(PanoError, match="needs a layout") as e:
        chain.run(scene, tmp_path, params, with_layout=False)
    assert "\n" not in str(e.value)
