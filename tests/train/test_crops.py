"""The paper's 3D-GS baseline in training: perspective crops resampled from the panoramas,
densification on the same footing as 360° training, and test panoramas stitched from crops."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_stage import ctx_for

import splatting
import stages.train as T
from gaussians.densify import gradient_scale
from gaussians.losses import l1_loss
from panogeom.resample import perspective_crop
from runfs.errors import PanoError
from runtime.stage import Loaded, StageContext
from schemas.scene_loader import load_scene


def smooth_panorama(h: int, w: int) -> np.ndarray:
    """A panorama whose colour is a smooth function of the viewing direction."""
    d = splatting.EquirectCamera(h, w).pixel_dirs(dtype=torch.float64).numpy()
    return (0.5 + 0.4 * np.stack([d[..., 0], d[..., 1] * d[..., 2], np.sin(2 * d[..., 2])], -1)).astype(np.float32)


@pytest.mark.parametrize("projection", ["crops", "cubemap"])
def test_crops_resampled_from_a_panorama_stitch_back_to_it(projection):
    h, w = 64, 128
    pano = smooth_panorama(h, w)
    rig = T.Params(projection=projection).rig(h)
    crops = np.stack([perspective_crop(pano, cv.numpy(), cam) for cv, cam in rig.crops()])
    back = splatting.stitch(torch.from_numpy(crops), h, w, rig).numpy()
    err = np.abs(back - pano)
    # two bilinear resamplings of a smooth image: small everywhere
    assert err.max() < 0.02 and err.mean() < 2e-3


def test_crop_views_are_the_paper_rig_with_masks_resampled():
    h, w = 32, 64
    img = smooth_panorama(h, w)
    mask = np.ones((h, w), bool)
    mask[-4:] = False  # a tripod cap at the nadir
    rig = T.Params(projection="crops").rig(h)
    views = T.build_views({"a": img}, {"a": np.eye(4)}, "crops", {"a": mask}, rig)
    assert [v.name for v in views] == [f"a/{n}" for n in rig.names] and len(views) == 8
    assert all(v.image.shape == (32, 32, 3) and isinstance(v.camera, splatting.PinholeCamera) for v in views)
    down = [v for v in views if v.name.startswith("a/el-45")]
    level = [v for v in views if v.name.startswith("a/el+0")]
    assert all(not bool(v.mask.all()) for v in down)  # the downward crops see the cap
    assert all(bool(v.mask.all()) for v in level)  # the horizon crops reach 60° down only


def _one_splat_gradient(camera, viewmat):
    """The densification statistic of one Gaussian 3 m straight ahead whose target is the same
    Gaussian moved 0.5° sideways (L1 over the image, as the photometric loss)."""
    def scene(shift_deg):
        a = math.radians(shift_deg)
        means = torch.tensor([[3 * math.sin(a), 0.0, 3 * math.cos(a)]], dtype=torch.float64)
        return (means, torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                torch.full((1, 3), 0.15, dtype=torch.float64), torch.tensor([0.9], dtype=torch.float64),
                torch.tensor([[1.0, 0.8, 0.6]], dtype=torch.float64))

    target = splatting.render(*scene(0.5), viewmat, camera, backend="torch").image
    means, *rest = scene(0.0)
    out = splatting.render(means.requires_grad_(True), *rest, viewmat, camera, backend="torch")
    out.means2d.retain_grad()
    l1_loss(out.image, target).backward()
    return float(out.means2d.grad.norm()) * gradient_scale(camera)


def test_densification_gradient_is_on_the_same_footing_for_panoramas_and_crops():
    eye = torch.eye(4, dtype=torch.float64)
    # about the same pixels per radian at the image centre (40.7, 40.4, 41): the same dilation
    pano = _one_splat_gradient(splatting.EquirectCamera(128, 256), eye)
    crop = splatting.crop_rig(140)  # 120° crops; the first horizon crop looks along +z
    k = crop.names.index("el+0_yaw0")
    crop_stat = _one_splat_gradient(crop.camera, crop.crops(torch.float64)[k][0])
    face_vm, face_cam = splatting.cubemap_faces(82, dtype=torch.float64)[0]
    face_stat = _one_splat_gradient(face_cam, face_vm)
    assert pano > 1e-3
    # the same splat, the same error: the same statistic (with the pixels-per-radian factor alone a
    # 120° crop would read 1.6x and a cube face 4.9x the panorama's: a mean over a narrower image
    # weighs each steradian more)
    assert crop_stat == pytest.approx(pano, rel=0.05)
    assert face_stat == pytest.approx(pano, rel=0.05)
    # the panorama's factor is its pixels per radian, as before
    assert gradient_scale(splatting.EquirectCamera(128, 256)) == pytest.approx(256 / (2 * math.pi))


def test_training_on_crops_and_evaluating_a_stitched_panorama(tiny_room, tmp_path):
    from evaluation.model_io import load_model
    from gaussians.model import render_stitched
    from panogeom.images import read_rgb
    from stages import evaluate

    ctx = ctx_for(tiny_room, tmp_path, {"projection": "crops", "iterations": 8, "height": 16})
    out = T.run(ctx)
    assert out.projection == "crops" and out.train_images == 3 * 8 and out.crops is not None
    assert out.crops.size == 16 and out.crops.fov_deg == 120.0 and len(out.crops.names) == 8
    lines = [json.loads(s) for s in (ctx.out_dir / out.log).read_text().splitlines()]
    assert all(math.isfinite(r["loss"]) for r in lines) and lines[-1]["iteration"] == 8

    ev = evaluate.run(StageContext(
        scene=load_scene(tiny_room), params=evaluate.Params(resolution=(32, 64), lpips=False, fps_repeats=1),
        inputs={"train": Loaded(out, ctx.out_dir), "union": None}, out_dir=tmp_path / "ev"))
    assert ev.stitched == "8 crops of 120°, 32 px"  # crops scaled with the evaluation height
    # the written render is the stitched crops, not a direct 360° render
    scene = load_scene(tiny_room)
    view = scene.manifest.test_views()[0]
    g = load_model(ctx.out_dir / out.ply)
    vm = torch.linalg.inv(torch.as_tensor(view.pose_matrix, dtype=torch.float32))
    bg = torch.tensor(out.settings["background"])  # evaluate renders against the trained background
    with torch.no_grad():
        stitched = render_stitched(g, vm, 32, 64, out.crops.rig(32), background=bg).image.clamp(0, 1).numpy()
        direct = splatting.render(g.means, g.quats, g.log_scales.exp(), g.opacity_logits.sigmoid(),
                                  torch.cat([g.sh_dc, g.sh_rest], 1), vm, splatting.EquirectCamera(32, 64),
                                  sh_degree=g.sh_degree, background=bg).image.clamp(0, 1).numpy()
    written = read_rgb(tmp_path / "ev" / ev.views[0].render)
    assert np.abs(written - stitched).max() < 1.5 / 255
    assert np.abs(written - direct).max() > 4 / 255  # and it is not the direct render


def test_a_rig_that_leaves_gaps_is_a_one_line_error(tiny_room, tmp_path):
    ctx = ctx_for(tiny_room, tmp_path, {"projection": "crops", "crop_fov": 60.0, "iterations": 2})
    with pytest.raises(PanoError, match="unseen"):
        T.run(ctx)
