"""The evaluate stage end to end on a simulated scene with a model built from its exact depth."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from evalhelpers import backprojected_gaussians, make_scene, write_train_artifact
from pipeline.engine import load_artifact
from runtime.stage import StageContext
from schemas.train import TrainOutput
from stages import evaluate


def _run(scene, run_dir, **params):
    tdir = run_dir / "train"
    ctx = StageContext(scene=scene, params=evaluate.Params(**params),
                       inputs={"train": load_artifact(tdir, TrainOutput), "union": None},
                       out_dir=run_dir / "evaluate")
    return evaluate.run(ctx), ctx


def test_evaluate_matches_ground_truth(sim_scene, sim_model, tmp_path, monkeypatch):
    monkeypatch.setenv("PANO_PIPE_LPIPS_WEIGHTS", str(tmp_path / "no-weights"))
    write_train_artifact(tmp_path, sim_model, resolution=(32, 64))
    out, ctx = _run(sim_scene, tmp_path, fps_repeats=2, threads=1)
    assert out.split == "test" and not out.on_train_views
    assert [v.view for v in out.views] == ["test_00"]
    v = out.views[0]
    # A model made from the exact depth reproduces the view: high PSNR, small depth error.
    assert v.psnr > 20 and v.ssim > 0.6 and v.ws_psnr > 20
    # A few % nearer: the renderer's 2D dilation lets nearer neighbours bleed in front-to-back.
    assert v.depth_abs_rel is not None and v.depth_abs_rel < 0.08
    assert v.depth_rmse < 0.3 and v.depth_valid_pixels == 32 * 64
    assert out.mean["psnr"] == pytest.approx(v.psnr)
    assert "lpips" not in out.mean and v.lpips is None
    assert not out.lpips_available and "no-weights" in out.lpips_reason
    assert any("LPIPS unavailable" in w for w in ctx.warnings)
    assert out.fps > 0 and out.threads == 1 and out.backend in ("cpp", "torch")
    assert out.resolution == (32, 64) and out.num_gaussians == len(sim_model)
    d = tmp_path / "evaluate"
    for rel in (v.gt, v.render, v.error, v.depth, v.depth_npy, out.csv):
        assert (d / rel).is_file(), rel
    depth = np.load(d / v.depth_npy)
    assert depth.shape == (32, 64) and depth.dtype == np.float32
    rows = list(csv.DictReader(open(d / out.csv)))
    assert [r["view"] for r in rows] == ["test_00", "mean"]
    assert float(rows[0]["psnr"]) == pytest.approx(v.psnr, rel=1e-5)
    assert rows[0]["lpips"] == ""
    # The metric is reproducible from the written PNGs (8-bit rounding aside).
    from evaluation.metrics import psnr
    from panogeom.images import read_rgb

    assert psnr(read_rgb(d / v.render), read_rgb(d / v.gt)) == pytest.approx(v.psnr, abs=0.3)


def test_evaluate_without_test_views_flags_train(tmp_path, monkeypatch):
    monkeypatch.setenv("PANO_PIPE_LPIPS_WEIGHTS", str(tmp_path / "none"))
    scene = make_scene(tmp_path / "s", views=1, test_views=0, height=16)
    write_train_artifact(tmp_path / "run", backprojected_gaussians(scene), resolution=(16, 32))
    out, ctx = _run(scene, tmp_path / "run", fps_repeats=1, resolution=(16, 32), lpips=False)
    assert out.split == "train" and out.on_train_views
    assert [v.split for v in out.views] == ["train"]
    assert any("TRAINING views" in w for w in ctx.warnings)
    assert out.lpips_reason.startswith("disabled")


def test_the_tile_size_reaches_every_render_and_changes_no_metric(tmp_path, monkeypatch):
    """`evaluate.tile_size` is the renderer's (speed only): each render of the stage, the timed ones
    too, gets it, and the metrics equal those at the default tile."""
    import splatting

    monkeypatch.setenv("PANO_PIPE_LPIPS_WEIGHTS", str(tmp_path / "none"))
    scene = make_scene(tmp_path / "s", views=1, test_views=1, height=16)
    write_train_artifact(tmp_path / "run", backprojected_gaussians(scene), resolution=(16, 32))
    default, _ = _run(scene, tmp_path / "run", fps_repeats=1, lpips=False)
    seen, real = [], splatting.render

    def spy(*args, **kw):
        seen.append(kw.get("tile_size"))
        return real(*args, **kw)

    monkeypatch.setattr(splatting, "render", spy)
    small, _ = _run(scene, tmp_path / "run", fps_repeats=2, lpips=False, tile_size=5)
    assert len(seen) == 1 + 2 and set(seen) == {5}
    assert small.views[0].psnr == pytest.approx(default.views[0].psnr, abs=1e-4)
    with pytest.raises(Exception):
        evaluate.Params(tile_size=64)


def test_params_reject_unknown_and_bad_values():
    with pytest.raises(Exception):
        evaluate.Params(bogus=1)
    with pytest.raises(Exception):
        evaluate.Params(resolution="huge")
    with pytest.raises(Exception, match="both >= 2"):
        evaluate.Params(resolution=[0, 16])
    assert evaluate.Params(resolution=[8, 16]).resolution == (8, 16)


def test_mean_metrics_leaves_out_missing():
    rows = [{"psnr": 10.0, "lpips": None, "depth_rmse": float("nan")}, {"psnr": 20.0, "lpips": None}]
    assert evaluate.mean_metrics(rows) == {"psnr": 15.0}


def test_a_flat_image_is_the_floor_and_a_model_below_it_is_named(tmp_path, monkeypatch):
    """Each view is also scored as a flat image of the posed training panoramas' mean colour over
    their valid pixels (`flat_psnr`, `flat_ssim`): a model that reconstructs the view beats it, one
    that does not is named in a warning (its raw metrics then measure exposure and smoothness)."""
    from evaluation import metrics as M
    from panogeom.images import read_rgb
    from schemas.scene_loader import valid_mask

    monkeypatch.setenv("PANO_PIPE_LPIPS_WEIGHTS", str(tmp_path / "none"))
    scene = make_scene(tmp_path / "s", views=2, test_views=1, height=16)
    size = (16, 32)
    pixels = []
    for t in scene.manifest.train_views():
        image, mask = read_rgb(scene.image_path(t), size=size), valid_mask(scene, t, *size)
        pixels.append(image.reshape(-1, 3) if mask is None else image[mask])
    colour = np.concatenate(pixels).astype(np.float64).mean(axis=0)
    test = scene.manifest.test_views()[0]
    gt, mask = read_rgb(scene.image_path(test), size=size), valid_mask(scene, test, *size)
    flat = np.broadcast_to(colour.astype(np.float32), gt.shape)

    good = backprojected_gaussians(scene)
    write_train_artifact(tmp_path / "good", good, resolution=size)
    out, ctx = _run(scene, tmp_path / "good", fps_repeats=1, lpips=False)
    v = out.views[0]
    assert v.flat_psnr == pytest.approx(M.psnr(flat, gt, mask=mask), abs=1e-4)
    assert v.flat_ssim == pytest.approx(M.ssim(flat, gt, mask=mask), abs=1e-4)
    assert v.psnr > v.flat_psnr + 3 and v.ssim > v.flat_ssim
    assert out.mean["flat_psnr"] == pytest.approx(v.flat_psnr)
    assert not any("flat image" in w for w in ctx.warnings)

    good.sh_dc = -good.sh_dc  # every colour inverted about grey: the geometry right, the view not predicted
    write_train_artifact(tmp_path / "bad", good, resolution=size)
    out, ctx = _run(scene, tmp_path / "bad", fps_repeats=1, lpips=False)
    v = out.views[0]
    assert v.flat_psnr == pytest.approx(M.psnr(flat, gt, mask=mask), abs=1e-4)
    assert v.psnr < v.flat_psnr
    assert [w for w in ctx.warnings if "flat image" in w and "test_00" in w and "1 of 1" in w]
