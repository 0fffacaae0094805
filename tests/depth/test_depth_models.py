"""ONNX depth models of each contract, exported from tiny torch modules, through the depth stage.

The scenes' images encode their exact depth (conftest), so each model's
answer is known; scales are then fitted to the layout the way `align` does.
"""

from __future__ import annotations

import numpy as np
import pytest

from depthalign.scale_fit import fit_scale, values_to_depth
from floorplan.layout_depth import layout_depth_map
from runfs.errors import PanoError
from stages.align import Params, fit_settings

H = 64


@pytest.fixture(scope="module")
def scene(dk, tmp_path_factory):
    return dk.make_encoded_scene(
        tmp_path_factory.mktemp("models") / "s", "l-shape", views=2, height=H, seed=3
    )


@pytest.fixture(scope="module")
def models(dk, tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx")
    return {
        "metric": dk.export(dk.Metric360(scale=1.7), d / "metric360.onnx", (1, 3, 32, 64)),
        "da": dk.export(dk.DepthAnythingLike(), d / "da.onnx", (1, 3, 28, 56), dynamic=True),
        "face_metric": dk.export(dk.PerspectiveFace(32, 100.0, "metric"), d / "face.onnx", (1, 3, 32, 32)),
        "face_disp": dk.export(
            dk.PerspectiveFace(32, 100.0, "disparity"), d / "face_disp.onnx", (1, 3, 32, 32)
        ),
        "channels": dk.export(dk.WrongChannels(), d / "channels.onnx", (1, 3, 32, 64)),
        "aspect": dk.export(dk.WrongAspect(), d / "aspect.onnx", (1, 3, 32, 64)),
    }


def _fit(dk, scene, maps, kind, views=None):
    """One fit over `views` (default all train views), as align does for a group."""
    vals, lays, gts = [], [], []
    for v in views or scene.manifest.train_views():
        m = maps[v.name]
        poly, h, c = dk.floor_polygon_cam(scene, v)
        lay, _ = layout_depth_map(poly, h, c, *m.shape)
        vals.append(m.reshape(-1))
        lays.append(lay.reshape(-1))
        gts.append(dk.gt_depth(scene, v).reshape(-1))
    vals, lays, gts = map(np.concatenate, (vals, lays, gts))
    fit = fit_scale(vals, lays, kind, **fit_settings(Params()))
    err = np.nanmedian(np.abs(values_to_depth(vals, kind, fit.scale, fit.shift) / gts - 1))
    return fit, err


def test_metric_360_model_at_its_own_size(dk, scene, models, tmp_path):
    result, maps, _ = dk.run_depth(scene, tmp_path, model=str(models["metric"]), output="metric")
    for r in result.views:
        assert r.source == "model" and r.kind == "metric" and r.model_input == (32, 64)
        assert maps[r.view].shape == (H, 2 * H)
    fit, err = _fit(dk, scene, maps, "metric")
    print(f"metric 360 model (x1.7): scale error {abs(fit.scale * 1.7 - 1):.4%}, depth error {err:.4%}")
    assert abs(fit.scale * 1.7 - 1) < 0.01 and err < 0.01


def test_depth_anything_like_model_multiple_of_14_imagenet_disparity(dk, scene, models, tmp_path):
    result, maps, _ = dk.run_depth(
        scene, tmp_path, model=str(models["da"]), output="disparity", normalization="imagenet", multiple_of=14
    )
    assert all(r.model_input == (70, 140) for r in result.views)  # 64 rounded to a multiple of 14, 2:1
    for v in scene.manifest.train_views():  # each image is normalised on its own: one fit per view
        fit, err = _fit(dk, scene, maps, "disparity", [v])
        print(f"Depth-Anything-like disparity, {v.name}: depth error after scale+shift fit {err:.4%}")
        assert err < 0.01 and fit.inlier_share > 0.8


def test_depth_anything_like_model_refuses_sides_off_the_multiple(dk, scene, models, tmp_path):
    # Without multiple_of=14 the export's patchify reshape fails: a one-line error naming the model.
    with pytest.raises(PanoError) as e:
        dk.run_depth(scene, tmp_path, model=str(models["da"]), output="disparity", normalization="imagenet")
    assert "inference failed" in str(e.value) and "\n" not in str(e.value)


def test_perspective_metric_model_on_cube_faces(dk, scene, models, tmp_path):
    result, maps, _ = dk.run_depth(
        scene,
        tmp_path,
        model=str(models["face_metric"]),
        output="metric",
        projection="cubemap",
        face_fov_deg=100.0,
    )
    r = result.views[0]
    assert r.model_input == (32, 32) and len(r.face_scales) == 6 and r.face_scales[0] == 1.0
    assert np.ptp(r.face_scales) > 0.01  # the faces really had different scales
    # The faces' scales differed by several %; after alignment one scale per view fits (this
    # test model's front-face scale differs per view too, so views are fitted one by one).
    for v in scene.manifest.train_views():
        fit, err = _fit(dk, scene, maps, "metric", [v])
        print(
            f"cube faces, metric, {v.name}: face scales {np.round(r.face_scales, 3)}, "
            f"error after one scale {err:.4%}"
        )
        assert err < 0.015 and fit.inlier_share > 0.9


def test_perspective_disparity_model_on_cube_faces(dk, scene, models, tmp_path):
    result, maps, _ = dk.run_depth(
        scene,
        tmp_path,
        model=str(models["face_disp"]),
        output="disparity",
        projection="cubemap",
    )
    for v in scene.manifest.train_views():
        fit, err = _fit(dk, scene, maps, "disparity", [v])
        print(f"cube faces, disparity, {v.name}: depth error after scale+shift fit {err:.4%}")
        assert err < 0.03 and fit.inlier_share > 0.8


def test_model_with_image_output_is_refused_at_load(dk, scene, models, tmp_path):
    with pytest.raises(PanoError, match=r"output must be a depth map") as e:
        dk.run_depth(scene, tmp_path, model=str(models["channels"]))
    assert "channels.onnx" in str(e.value) and "\n" not in str(e.value)


def test_model_with_wrong_output_shape_is_refused(dk, scene, models, tmp_path):
    with pytest.raises(PanoError, match=r"output has shape \[1, 1, 32, 16\]") as e:
        dk.run_depth(scene, tmp_path, model=str(models["aspect"]))
    assert "\n" not in str(e.value)


def test_contract_mismatches_are_refused_at_load(dk, scene, models, tmp_path):
    with pytest.raises(PanoError, match="not 2:1"):
        dk.run_depth(scene, tmp_path, model=str(models["face_metric"]))  # a perspective model without cubemap
    with pytest.raises(PanoError, match="input_size"):
        dk.run_depth(scene, tmp_path, model=str(models["metric"]), input_size=(64, 128))
    with pytest.raises(PanoError, match="not a multiple of 14"):
        dk.run_depth(scene, tmp_path, model=str(models["metric"]), multiple_of=14)
    with pytest.raises(PanoError, match="depth model file does not exist"):
        dk.run_depth(scene, tmp_path, model=str(tmp_path / "none.onnx"))
    with pytest.raises(PanoError, match="unknown model; known depth models: depth-anything-v2-small"):
        dk.run_depth(scene, tmp_path, model="depth-anything-v3")
    with pytest.raises(PanoError, match="not available"):
        dk.run_depth(scene, tmp_path, model=str(models["metric"]), providers=["NoSuchExecutionProvider"])
    (tmp_path / "junk.onnx").write_bytes(b"junk")
    with pytest.raises(PanoError, match="not a loadable ONNX model") as e:
        dk.run_depth(scene, tmp_path, model=str(tmp_path / "junk.onnx"))
    assert "\n" not in str(e.value)
