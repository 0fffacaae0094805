"""Issue #13's done-when: on a simulated scene with `exposure` and `tripod`, held-out PSNR on valid
pixels with masks and appearance on is within 1 dB of the same scene without those effects.

Both scenes are the same room, poses and textures (the simulator draws each effect from its own
random stream); both are trained alike from the same grey Gaussians on the exact depth (so the
colours are learned from the images, exposures and tripod included) and scored on the held-out
view's valid pixels (outside a 20° nadir cap, which holds the tripod) against the effect-free
image `gt/clean`. A gain common to every training panorama cannot be observed (a brighter room
looks like a longer exposure), so the scores are taken after the per-view colour fit that
evaluate reports as colour-fit PSNR; the raw PSNR is checked against the clean image at the
training panoramas' mean exposure. Small (32×64, 300 iterations) to stay well under a minute.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import simulate
import splatting
import stages.train as T
from evaluation import metrics as M
from gaussians.init import from_cloud
from gaussians.model import render
from gaussians.trainer import Trainer, scene_extent
from panogeom.equirect import ray_directions
from panogeom.images import read_rgb
from schemas.scene_loader import load_scene, valid_mask

H, ITERATIONS, SEED, NADIR_DEG = 32, 300, 1, 20.0


def make_scene(root, effects: str):
    simulate.generate_scene(root, preset="cuboid", views=3, test_views=1, height=H, seed=SEED, effects=effects,
                            aa_samples=1)
    manifest = json.loads((root / "scene.json").read_text())
    manifest["nadir_mask_deg"] = NADIR_DEG
    (root / "scene.json").write_text(json.dumps(manifest))
    return load_scene(root)


def grey_gaussians(scene):
    """Grey Gaussians on the training views' exact depth (every other pixel)."""
    pts = []
    for v in scene.manifest.train_views():
        depth = np.load(scene.gt_depth_path(v)).astype(np.float64)
        xyz = ray_directions(*depth.shape) * depth[..., None] @ v.pose_matrix[:3, :3].T + v.pose_matrix[:3, 3]
        pts.append(xyz[::2, ::2].reshape(-1, 3))
    return from_cloud({"points": np.concatenate(pts)}, sh_degree=1, init_opacity=0.5)


def trained_render(scene, appearance: bool) -> np.ndarray:
    """Train on the scene with its masks (and appearance when asked); the held-out view's render."""
    views = scene.manifest.train_views()
    images = T.load_images(scene, views, H)
    masks = {v.name: valid_mask(scene, v, H, 2 * H) for v in views}
    train_views = T.build_views(images, {v.name: v.viewmat for v in views}, "360", masks)
    g = grey_gaussians(scene)
    p = T.Params(iterations=ITERATIONS, height=H, densify_from=75, densify_until=225, densify_every=50,
                 max_gaussians=20_000, seed=SEED, sh_degree=1, appearance=appearance, checkpoint_every=0)
    trainer = Trainer(g, train_views, T.make_config(p, len(views), scene_extent(g.means)))
    trainer.train()
    test = scene.manifest.test_views()[0]
    viewmat = torch.linalg.inv(torch.as_tensor(test.pose_matrix, dtype=torch.float32))
    with torch.no_grad():  # test views are rendered without any appearance transform
        out = render(trainer.final_gaussians(), viewmat, splatting.EquirectCamera(H, 2 * H))
    return out.image.clamp(0, 1).numpy()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    base = tmp_path_factory.mktemp("effects")
    return make_scene(base / "plain", "texture,shading"), make_scene(base / "capture", "texture,shading,exposure,tripod")


def test_masks_and_appearance_bring_a_capture_within_1_db_of_the_effect_free_scene(scenes):
    plain, capture = scenes
    test = plain.manifest.test_views()[0]
    clean = read_rgb(capture.root / "gt" / "clean" / f"{test.name}.png", size=(H, 2 * H))
    # the same room: the capture's clean image is the plain scene's image
    assert np.abs(clean - read_rgb(plain.image_path(test), size=(H, 2 * H))).max() < 1.5 / 255
    mask = valid_mask(capture, capture.manifest.view(test.name), H, 2 * H)
    assert mask is not None and 0.85 < mask.mean() < 0.99  # the nadir cap is left out

    exposure = json.loads((capture.root / "gt" / "exposure.json").read_text())["views"]
    gains = np.array([exposure[v.name]["channel_gains"] for v in capture.manifest.train_views()])
    assert np.abs(np.log(gains)).max() > 0.05  # the training panoramas really differ in exposure

    def fitted_psnr(img):
        return M.psnr(M.colour_fit(img, clean, mask), clean, mask=mask)

    plain_render = trained_render(plain, appearance=False)
    capture_render = trained_render(capture, appearance=True)
    reference = fitted_psnr(plain_render)
    assert reference > 20  # a real reconstruction, not two equally failed ones
    assert fitted_psnr(capture_render) > reference - 1.0
    # raw PSNR, against the clean image at the training panoramas' mean exposure
    at_mean_exposure = np.clip(clean * np.exp(np.log(gains).mean(0)), 0, 1)
    assert M.psnr(capture_render, at_mean_exposure, mask=mask) > M.psnr(plain_render, clean, mask=mask) - 1.0
