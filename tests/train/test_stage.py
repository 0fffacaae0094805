"""The train stage's glue: init choice, outputs, cube faces, Ctrl-C checkpoint and --resume."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch

import splatting
import stages.train as T
from gaussians import load_ply
from panogeom.resample import perspective_crop
from runfs.errors import PanoError
from runtime.stage import Loaded, StageContext
from schemas.sampling import SamplingOutput
from schemas.scene_loader import load_scene, valid_mask
from schemas.train import TrainOutput
from schemas.union import Room, UnionOutput
from stages.cloud_io import write_cloud


def ctx_for(root, tmp_path, params: dict, inputs=None, resume=False, name="out") -> StageContext:
    out = tmp_path / name
    out.mkdir(parents=True, exist_ok=True)
    base = dict(height=16, iterations=12, random_points=300, max_gaussians=2000, densify_from=4,
                densify_every=4, log_every=2, threads=1)
    base.update(params)
    return StageContext(
        scene=load_scene(root), params=T.Params(**base),
        inputs=inputs or {"align": None, "sampling": None, "union": None},
        out_dir=out, scratch_dir=tmp_path / "scratch", resume=resume,
    )


def test_resolve_init_table():
    r = T.resolve_init
    assert r("auto", True, True, True, True) == "layout+depth"
    assert r("auto", True, False, True, False) == "depth"
    assert r("auto", False, False, False, True) == "layout"
    assert r("auto", False, False, False, False) == "random"
    assert r("layout", True, True, True, False) == "layout"
    assert r("random", True, True, True, True) == "random"
    for req, args in [("layout+depth", (False, False, False, True)), ("depth", (False, False, False, True)),
                      ("layout", (False, False, False, False)), ("layout+depth", (True, False, True, False))]:
        with pytest.raises(ValueError, match=re.escape(f"init {req!r}")):
            r(req, *args)
    assert T.default_lambda_layout(4) == 0.1 and T.default_lambda_layout(8) == 0.1
    assert T.default_lambda_layout(9) == 0.01


def test_params_presets_and_validation():
    p = T.Params()
    assert (p.resolved("height"), p.resolved("iterations")) == (T.PRESETS["fast"]["height"],
                                                               T.PRESETS["fast"]["iterations"])
    assert T.Params(preset="paper").resolved("height") == 512
    assert T.Params(preset="quality").resolved("iterations") == 30_000
    assert T.Params(layout_reg="off").layout_reg is False  # the ablation switch reads on/off
    with pytest.raises(Exception):
        T.Params(projection="fisheye")
    with pytest.raises(Exception):
        T.Params(unknown=1)
    with pytest.raises(ValueError, match="'grey' is neither 'mean' nor an RGB triple"):
        T.Params(background="grey")
    assert T.Params(background=[0, 0.5, 1]).background == (0.0, 0.5, 1.0)


def test_random_init_run_writes_ply_log_and_artifact(tiny_room, tmp_path):
    ctx = ctx_for(tiny_room, tmp_path, {})
    out = T.run(ctx)
    assert isinstance(out, TrainOutput)
    assert out.init == "random" and out.projection == "360" and out.iterations == 12
    assert out.resolution == (16, 32) and out.sh_degree == 3 and out.lambda_layout == 0.1
    g = load_ply(ctx.out_dir / out.ply)
    assert len(g) == out.num_gaussians and g.sh_degree == 3
    lines = [json.loads(s) for s in (ctx.out_dir / out.log).read_text().splitlines()]
    assert [r["iteration"] for r in lines] == [1, 2, 4, 6, 8, 10, 12]
    assert out.final_train_psnr is not None and math.isfinite(out.final_train_psnr)
    assert not (tmp_path / "scratch" / T.CHECKPOINT_NAME).exists()  # removed once finished


def test_mean_colour_counts_each_valid_pixel_once():
    from gaussians.trainer import TrainView, mean_colour

    a = torch.zeros(2, 4, 3)
    a[0] = torch.tensor([0.2, 0.4, 0.6])  # the valid top row; the bottom row is masked out
    mask_a = torch.zeros(2, 4, dtype=torch.bool)
    mask_a[0] = True
    cam = splatting.EquirectCamera(2, 4)
    views = [TrainView("a", a, torch.eye(4), cam, mask_a), TrainView("b", torch.full((1, 2, 3), 0.8), torch.eye(4), cam)]
    expected = ((4 * 0.2 + 1.6) / 6, (1.6 + 1.6) / 6, (2.4 + 1.6) / 6)
    assert mean_colour((v.image, v.mask) for v in views) == pytest.approx(expected)
    # numpy pairs (evaluate's flat image) count the same
    assert mean_colour([(a.numpy(), mask_a.numpy()), (np.full((1, 2, 3), 0.8), None)]) == pytest.approx(expected)
    with pytest.raises(ValueError, match="no valid pixel"):
        mean_colour([(a, torch.zeros(2, 4, dtype=torch.bool))])


def test_mean_background_is_the_default_recorded_and_rendered_by_evaluate(tiny_room, tmp_path):
    """background 'mean' (the default): the trainer renders against the training images' mean
    colour over their masks, the artifact records that colour, and evaluate renders with it."""
    from gaussians.trainer import mean_colour
    from stages.evaluate import train_background

    ctx = ctx_for(tiny_room, tmp_path, {"iterations": 2})
    assert ctx.params.background == "mean"
    views = ctx.scene.manifest.train_views()
    images = T.load_images(ctx.scene, views, 16)
    masks = {v.name: valid_mask(ctx.scene, v, 16, 32) for v in views}
    built = T.build_views(images, {v.name: v.viewmat for v in views}, "360", masks, None)
    expected = mean_colour((v.image, v.mask) for v in built)
    assert min(expected) > 0.01  # not black
    out = T.run(ctx)
    assert out.settings["background"] == pytest.approx(list(expected))
    # evaluate reads the settled colour, not the parameter ("mean")
    assert train_background(Loaded(out, ctx.out_dir)) == pytest.approx(expected)
    assert T.make_config(T.Params(background=(0.1, 0.2, 0.3)), 4, 1.0).render.background == (0.1, 0.2, 0.3)
    assert T.make_config(T.Params(), 4, 1.0).render.background == "mean"


def test_requested_init_must_be_available(tiny_room, tmp_path):
    with pytest.raises(PanoError, match="layout"):
        T.run(ctx_for(tiny_room, tmp_path, {"init": "layout"}))


def test_layout_init_from_the_sampling_cloud(tiny_room, tmp_path):
    # a floor patch under the cameras, as the sampling stage would write it
    ax = np.linspace(-1.0, 1.0, 15)
    xx, zz = np.meshgrid(ax, ax)
    pts = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], 1)
    sdir = tmp_path / "sampling"
    files = write_cloud(sdir, pts, np.full_like(pts, 0.4), normals=np.tile([0, -1.0, 0], (len(pts), 1)),
                        is_layout=np.ones(len(pts), bool))
    sampling = Loaded(SamplingOutput(cloud=files, density_per_m2=50.0, points_per_surface={"floor": len(pts)}),
                      sdir)
    room = Room(polygon=[(-2, -2), (2, -2), (2, 2), (-2, 2)], floor_y=0.0, ceiling_y=-2.5, views=["v"])
    union = Loaded(UnionOutput(rooms=[room], floor_plan="f.json", drawing="d.png", area_m2=16.0), tmp_path)
    out = T.run(ctx_for(tiny_room, tmp_path, {"iterations": 4, "densify_from": 100},
                        inputs={"align": None, "sampling": sampling, "union": union}))
    assert out.init == "layout"
    assert out.num_gaussians == len(pts)
    # random init uses the union's room as its bounds
    out2 = T.run(ctx_for(tiny_room, tmp_path, {"iterations": 2, "init": "random", "layout_reg": False},
                         inputs={"align": None, "sampling": sampling, "union": union}, name="r"))
    g = load_ply(tmp_path / "r" / out2.ply)
    assert out2.init == "random" and out2.lambda_layout == 0.0
    assert g.means[:, 0].abs().max() <= 2.01 and g.means[:, 1].min() >= -2.51


def test_cube_face_resampling_matches_the_panorama():
    # a smooth panorama: colour = a function of the viewing direction
    h, w = 64, 128
    phi = ((np.arange(w) + 0.5) / w - 0.5) * 2 * np.pi
    theta = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    P, TH = np.meshgrid(phi, theta)
    d = np.stack([np.cos(TH) * np.sin(P), -np.sin(TH), np.cos(TH) * np.cos(P)], -1)
    pano = (0.5 + 0.5 * d * np.array([0.9, 0.8, 0.7])).astype(np.float32)
    for fv, cam in splatting.cubemap_faces(32):
        face = perspective_crop(pano, fv.numpy(), cam)
        dirs = cam.pixel_dirs(dtype=torch.float64).numpy()
        dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
        expect = 0.5 + 0.5 * (dirs @ fv.numpy()[:3, :3]) * np.array([0.9, 0.8, 0.7])
        assert np.abs(face - expect).max() < 0.03


def test_cubemap_projection_trains_on_six_faces(tiny_room, tmp_path):
    ctx = ctx_for(tiny_room, tmp_path, {"projection": "cubemap", "iterations": 6, "height": 32})
    out = T.run(ctx)
    assert out.projection == "cubemap"
    lines = [json.loads(s) for s in (ctx.out_dir / out.log).read_text().splitlines()]
    assert all(math.isfinite(r["loss"]) for r in lines)
    images = T.load_images(ctx.scene, ctx.scene.manifest.train_views(), 32)
    views = T.build_views(images, {v.name: v.viewmat for v in ctx.scene.manifest.train_views()}, "cubemap")
    assert len(views) == 6 * 3 and views[0].image.shape == (16, 16, 3)
    assert views[1].name.endswith("/right")


class _InterruptAfter:
    """Stands in for the Ctrl-C handler: 'pressed' once `n` iterations have completed."""

    n = 7

    def __init__(self):
        self.calls = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    @property
    def requested(self):
        self.calls += 1
        return self.calls >= self.n


def test_ctrl_c_saves_a_checkpoint_and_resume_finishes_identically(tiny_room, tmp_path, monkeypatch):
    params = {"iterations": 14, "checkpoint_every": 0, "seed": 5}
    ref = T.run(ctx_for(tiny_room, tmp_path / "a", params))
    ref_bytes = (tmp_path / "a" / "out" / ref.ply).read_bytes()

    monkeypatch.setattr(T, "_DeferredInterrupt", _InterruptAfter)
    with pytest.raises(KeyboardInterrupt):
        T.run(ctx_for(tiny_room, tmp_path / "b", params))
    ckpt = tmp_path / "b" / "scratch" / T.CHECKPOINT_NAME
    assert torch.load(ckpt, weights_only=False)["iteration"] == 7
    monkeypatch.undo()

    out = T.run(ctx_for(tiny_room, tmp_path / "b", params, resume=True, name="out2"))
    assert out.resumed_from == 7 and out.iterations == 14
    assert (tmp_path / "b" / "out2" / out.ply).read_bytes() == ref_bytes
    log = [json.loads(s) for s in (tmp_path / "b" / "out2" / out.log).read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2, 4, 6, 8, 10, 12, 14]

    # --resume with a changed setting: warned, trained from the start
    ctx = ctx_for(tiny_room, tmp_path / "b", {**params, "seed": 6}, resume=True, name="out3")
    T.run(ctx)
    assert any("resume" in w for w in ctx.warnings)


def test_mip_filter_is_baked_into_the_exported_model(tiny_room, tmp_path):
    """With mip_filter the PLY holds the filtered Gaussians: every axis at least the low-pass's
    σ = sqrt(0.2) / ν at its centre (ν from the training panoramas), and its renders at the training
    views score the PSNR the stage reported from the trainer's own (filtered) renders. Without
    the filter thinner axes survive, so the floor is not an accident of training."""
    from gaussians.losses import psnr
    from gaussians.mip_filter import filter_variance, sampling_rate
    from gaussians.model import render

    params = {"iterations": 12, "seed": 3}
    views = ctx_for(tiny_room, tmp_path, {}).scene.manifest.train_views()
    images = T.load_images(load_scene(tiny_room), views, 16)
    tv = T.build_views(images, {v.name: v.viewmat for v in views}, "360")
    floor_ok = {}
    for mip in (False, True):
        ctx = ctx_for(tiny_room, tmp_path, {**params, "mip_filter": mip}, name=f"mip{mip}")
        out = T.run(ctx)
        g = load_ply(ctx.out_dir / out.ply)
        sigma = filter_variance(sampling_rate(g.means, [v.viewmat for v in tv], [v.camera for v in tv])).sqrt()
        floor_ok[mip] = bool((g.scales.min(dim=1).values >= sigma * (1 - 1e-4)).all())
        with torch.no_grad():
            bg = torch.tensor(out.settings["background"])  # the colour it trained against
            p = float(np.mean([psnr(render(g, v.viewmat, v.camera, background=bg).image, v.image) for v in tv]))
        assert p == pytest.approx(out.final_train_psnr, abs=1e-3)
    assert floor_ok == {False: False, True: True}
    assert T.make_config(T.Params(), 4, 1.0).render.mip_filter is False  # off by default
    assert T.make_config(T.Params(mip_filter=True, mip_filter_variance=0.1), 4, 1.0).render.mip_filter_variance == 0.1


def test_mip_filter_run_resumes_identically(tiny_room, tmp_path, monkeypatch):
    """The filter is a function of the model and the cameras: a resumed run ends on the same bytes."""
    params = {"iterations": 10, "checkpoint_every": 0, "seed": 2, "mip_filter": True}
    ref = T.run(ctx_for(tiny_room, tmp_path / "a", params))
    monkeypatch.setattr(T, "_DeferredInterrupt", _InterruptAfter)
    with pytest.raises(KeyboardInterrupt):
        T.run(ctx_for(tiny_room, tmp_path / "b", params))
    monkeypatch.undo()
    out = T.run(ctx_for(tiny_room, tmp_path / "b", params, resume=True, name="out2"))
    assert out.resumed_from == 7
    assert (tmp_path / "b" / "out2" / out.ply).read_bytes() == (tmp_path / "a" / "out" / ref.ply).read_bytes()


def test_training_dilation_travels_with_the_exported_model(tiny_room, tmp_path):
    """A model fitted with eps2d 0.1 (and random turns) is saved with it (a PLY comment) and loaded
    with it, so the evaluate stage's renders use it: the loaded model's renders at the training views
    score the stage's reported training PSNR, and the same Gaussians drawn with 0.3 do not."""
    from gaussians.losses import psnr
    from gaussians.model import render

    ctx = ctx_for(tiny_room, tmp_path, {"iterations": 12, "seed": 3, "eps2d": 0.1, "random_turns": True})
    out = T.run(ctx)
    assert b"comment eps2d 0.1\n" in (ctx.out_dir / out.ply).read_bytes()[:400]
    g = load_ply(ctx.out_dir / out.ply)
    assert g.eps2d == 0.1
    views = ctx.scene.manifest.train_views()
    tv = T.build_views(T.load_images(load_scene(tiny_room), views, 16), {v.name: v.viewmat for v in views}, "360")

    def score(**kw):
        with torch.no_grad():
            bg = torch.tensor(out.settings["background"])
            return float(np.mean([psnr(render(g, v.viewmat, v.camera, background=bg, **kw).image, v.image)
                                  for v in tv]))

    assert score() == pytest.approx(out.final_train_psnr, abs=1e-3)
    assert abs(score(eps2d=0.3) - out.final_train_psnr) > 0.01
    # the 360 default is 0.05; a model at 3DGS's 0.3 is written as a plain 3DGS PLY
    default = ctx_for(tiny_room, tmp_path, {"iterations": 2, "seed": 3}, name="default")
    assert b"comment eps2d 0.05\n" in (default.out_dir / T.run(default).ply).read_bytes()[:400]
    plain = ctx_for(tiny_room, tmp_path, {"iterations": 2, "seed": 3, "eps2d": 0.3}, name="plain")
    assert b"comment eps2d" not in (plain.out_dir / T.run(plain).ply).read_bytes()[:400]
