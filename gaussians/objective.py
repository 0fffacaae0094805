"""The training objective: one call gives the loss of a render and its terms.

    loss = λ1·L1 + λ2·D-SSIM                   (on the panorama, or on its eight perspective crops)
         + λ_scale · mean scale / extent        (the official 360-GS code's floater penalty)
         + λ_app · appearance regulariser         (its mean held at the identity by projection)
         + λ_cov · mean(1 − alpha) from a point between two training cameras
         + λ3 · L_layout                         (layout Gaussians moving off their planes)

It keeps what the terms reuse between iterations (solid-angle weights, crop resamplers and
ground-truth crops, the layout Gaussians' rows); :meth:`TrainingObjective.model_changed` drops
what depends on the model's rows (after densification or a checkpoint load).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

import splatting
from gaussians.crop_loss import CropResampler, crop_photometric_loss
from gaussians.layout_loss_fn import LayoutRows
from gaussians.losses import photometric_loss, solid_angle_weight
from gaussians.model import Gaussians, render

__all__ = ["TrainingObjective", "LossTerms"]


@dataclass
class LossTerms:
    """The loss and its terms as 0-dim device tensors (None: the term is off)."""

    loss: torch.Tensor
    l1: torch.Tensor
    ssim: torch.Tensor
    layout: torch.Tensor | None = None
    coverage: torch.Tensor | None = None
    #: PSNR of the render against the view (unweighted, over its mask): the loss's kernels give it
    #: at no cost on a GPU; None where the loss does not (the crop loss)
    psnr: torch.Tensor | None = None


class TrainingObjective:
    def __init__(self, cfg, views, device: torch.device):
        self.cfg = cfg
        self.views = views
        self.device = device
        self._weights: dict[tuple[int, int], torch.Tensor] = {}
        self._resamplers: dict = {}
        self._crops: dict = {}
        self._centres: torch.Tensor | None = None
        self._layout_rows: LayoutRows | None = None  # cached: finding them syncs

    def model_changed(self) -> None:
        """The model's rows changed (densification, a checkpoint): find the layout rows again."""
        self._layout_rows = None

    def __call__(self, g: Gaussians, drawn: Gaussians, pred: torch.Tensor, view, appearance, background,
                 generator: torch.Generator) -> LossTerms:
        """The loss of `pred` (the render of `drawn`, through the view's appearance) against `view`;
        `g` is the model itself (its scales and layout rows)."""
        cfg = self.cfg
        crops = self._crop_targets(view)
        if crops is not None:
            photo, l1, s = crop_photometric_loss(pred, crops[1], crops[0], cfg.loss.lambda_l1, cfg.loss.lambda_dssim,
                                                 crops[2])
            terms = LossTerms(photo, l1, s)
        else:
            photo, l1, s, p = photometric_loss(pred, view.image, cfg.loss.lambda_l1, cfg.loss.lambda_dssim,
                                               mask=view.mask, weight=self._pixel_weight(view), with_psnr=True)
            terms = LossTerms(photo, l1, s, psnr=p)
        if cfg.loss.lambda_scale > 0:
            terms.loss = terms.loss + cfg.loss.lambda_scale * torch.exp(g.log_scales).mean() / cfg.extent
        if appearance is not None and cfg.loss.lambda_appearance > 0:
            terms.loss = terms.loss + cfg.loss.lambda_appearance * appearance.regulariser()
        if cfg.loss.lambda_coverage > 0:
            terms.coverage = self._coverage_loss(drawn, background, generator)
            terms.loss = terms.loss + cfg.loss.lambda_coverage * terms.coverage
        if cfg.loss.layout_reg and cfg.loss.lambda_layout > 0:
            if self._layout_rows is None:
                # the layout Gaussians' rows, anchors and normals change only with densification:
                # selected once, not by the mask at every step
                idx = torch.nonzero(g.is_layout).squeeze(1)
                self._layout_rows = LayoutRows(idx, g.u0[idx], g.normals[idx], deadzone=cfg.loss.layout_deadzone)
            rows = self._layout_rows
            if len(rows):
                # gaussians.losses.layout_loss(g.means[idx], u0, normals), its gradient in closed form
                terms.layout = rows.loss(g.means)
                terms.loss = terms.loss + cfg.loss.lambda_layout * terms.layout
        return terms

    def _crop_targets(self, view):
        """(resampler, ground-truth crops, crop masks) of a panorama view when crop_loss is on, else None."""
        if not self.cfg.loss.crop_loss or getattr(view.camera, "kind", None) != "equirect":
            return None
        hit = self._crops.get(view.name)
        if hit is None:
            key = (int(view.camera.height), int(view.camera.width))
            rs = self._resamplers.get(key)
            if rs is None:
                rs = self._resamplers[key] = CropResampler(*key, dtype=view.image.dtype, device=self.device)
            with torch.no_grad():
                gt = rs(view.image)
                m = None if view.mask is None else rs(view.mask[..., None].to(view.image.dtype))[:, 0] > 0.999
            hit = self._crops[view.name] = (rs, gt, m)
        return hit

    def camera_centres(self) -> torch.Tensor:
        """[P,3] distinct camera centres of the training views (a panorama's crops share one)."""
        if self._centres is None:
            c = torch.stack([-(v.viewmat[:3, :3].T @ v.viewmat[:3, 3]) for v in self.views])
            self._centres = torch.unique(torch.round(c, decimals=6), dim=0)
        return self._centres

    def _coverage_loss(self, g: Gaussians, background, generator) -> torch.Tensor:
        """mean(1 − alpha) of a coverage_height × 2·coverage_height panorama from a random point of
        the segment between two training cameras (horizontally jittered): pushes holes between
        splats, which only a new viewpoint shows, to close."""
        cfg = self.cfg
        c = self.camera_centres()
        i, j = torch.randint(len(c), (2,), generator=generator).tolist()
        u, jx, jz = torch.rand(3, generator=generator, dtype=torch.float64).tolist()
        pos = c[i] + u * (c[j] - c[i])
        pos = pos + pos.new_tensor([2 * jx - 1, 0.0, 2 * jz - 1]) * cfg.loss.coverage_jitter * cfg.extent
        viewmat = torch.eye(4, dtype=g.means.dtype, device=self.device)
        viewmat[:3, 3] = -pos.to(viewmat.dtype)
        h = int(cfg.loss.coverage_height)
        out = render(g, viewmat, splatting.EquirectCamera(h, 2 * h), backend=cfg.render.backend,
                     background=background, sh_degree=0, tile_size=cfg.render.tile_size)
        return (1.0 - out.alpha).mean()

    def _pixel_weight(self, view) -> torch.Tensor | None:
        """The per-pixel loss weight of `view`: its pixels' solid angle for a panorama when
        solid_angle_weighting is on, else None (a plain mean)."""
        cam = view.camera
        if not self.cfg.loss.solid_angle_weighting or getattr(cam, "kind", None) != "equirect":
            return None
        key = (int(cam.height), int(cam.width))
        w = self._weights.get(key)
        if w is None:
            w = self._weights[key] = solid_angle_weight(*key, dtype=view.image.dtype, device=self.device)
        return w
