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


def test_run_uses_a_cached_depth_model_and_fits_affine_inverse_depth_per_view(
    dk, chain, tmp_path, monkeypatch
):
    """`run` on a scene with layout files and no depth files: with no depth model the plan says how
    to get one; with the known depth model in the cache, depth runs it (contract from its
    metadata) and align fits scale and shift in inverse depth per view."""
    from depthnet.runner import write_metadata
    from models.registry import get_model
    from models.store import onnx_path, write_record
    from pipeline.engine import Engine, load_artifact
    from pipeline.registry import build_registry
    from stages import align

    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(tmp_path / "cache"))
    scene = dk.make_encoded_scene(tmp_path / "s", "l-shape", views=2, height=64, seed=5, with_layout=True)
    config = {"sampling": {"density": 100.0}}
    engine = Engine(scene, tmp_path / "run", build_registry(), config)
    plan = engine.plan()
    assert plan["depth"].state == "skipped"
    assert "pano-pipe models fetch depth-anything-v2-small" in plan["depth"].reason
    assert any(h.startswith("depth:") and "models fetch depth-anything-v2-small" in h for h in engine.hints())

    # A stand-in for the fetched model, in its place in the cache: a perspective disparity network
    # (per-face min-max normalised, so each face has its own scale and shift), its contract recorded.
    cached = onnx_path(get_model("depth-anything-v2-small"))
    cached.parent.mkdir(parents=True)
    dk.export(dk.PerspectiveFace(32, 100.0, "disparity"), cached, (1, 3, 32, 32))
    write_metadata(cached, {"output": "disparity", "projection": "cubemap", "face_fov_deg": 100.0},
                   {"architecture": "stand-in"})
    write_record(get_model("depth-anything-v2-small"), "stand-in")  # as `models fetch` leaves it: trusted
    off = Engine(scene, tmp_path / "run", build_registry(), {**config, "depth": {"model": "none"}}).plan()
    assert off["depth"].state == "skipped"  # `none`: files only, the cached model is not used
    engine = Engine(scene, tmp_path / "run", build_registry(), config)
    assert not any(h.startswith("depth:") for h in engine.hints())
    assert "depth-anything-v2-small" in engine.plan()["depth"].reason  # says which model will run
    outcomes = {r.name: r.outcome for r in engine.run(target="align")}
    assert outcomes["depth"] == "ran" and outcomes["align"] == "ran"
    out = load_artifact(tmp_path / "run" / "align", align.Output).data
    assert len(out.fits) == 2 and all(len(f.views) == 1 for f in out.fits)
    assert all(f.kind == "disparity" for f in out.fits)
    assert all(f.depth_model == "affine inverse depth (1/d = s*v + t)" for f in out.fits)
    assert len({round(f.scale, 6) for f in out.fits}) == 2  # each view its own scale and shift
    from stages.cloud_io import read_cloud

    cloud = read_cloud(tmp_path / "run" / "align" / "cloud.npz")
    d = chain.surface_distance(scene, cloud["points"][~cloud["is_layout"]])
    print(f"cached affine depth model, run to align: {np.mean(d < 0.02):.1%} of merged points within 2 cm, "
          f"scales {[round(f.scale, 4) for f in out.fits]}, shifts {[round(f.shift, 4) for f in out.fits]}")
    assert np.mean(d < 0.05) >= 0.95
