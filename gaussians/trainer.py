"""The 360-GS optimisation loop, independent of the pipeline (stages/train.py is its glue).

One iteration (iteration numbers start at 1, as in 3DGS):
  1. position learning rate from the exponential schedule; every
     `sh_degree_every` iterations one more SH band (up to `sh_degree`);
  2. next view from a shuffled stack (refilled when empty);
  3. render, loss = λ1·L1 + λ2·D-SSIM + λ3·L_layout, backward;
  4. Adam step (non-finite gradients are zeroed and counted);
  5. densification statistics; on the schedule clone/split/prune and opacity reset.
All randomness comes from one torch.Generator whose state the checkpoint keeps,
so a resumed run continues exactly as an uninterrupted one would.

A checkpoint holds only tensors and plain data (dict/list/tuple/str/int/float/
bool/None) and is read with torch.load(weights_only=True): a file in the run
folder is data, never code. load_state_dict validates the whole checkpoint
before it changes anything, so a bad one leaves the trainer as it was.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pickle
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

import splatting
from gaussians.appearance import Appearance
from gaussians.crop_loss import CropResampler, crop_photometric_loss
from gaussians.densify import DensifyStats, densify_and_prune, gradient_scale, reset_opacity
from gaussians.losses import layout_loss, photometric_loss, psnr, psnr_tensor, solid_angle_weight
from gaussians.mip_filter import DEFAULT_VARIANCE, filter_variance, filtered, reset_cap_logits, sampling_rate
from gaussians.model import DEFAULT_EPS2D, PARAM_NAMES, Gaussians, render
from gaussians.optim import Adam, expon_lr
from gaussians.view_jitter import TurnGrid, random_turn, turn_panorama

__all__ = ["TrainConfig", "TrainView", "Trainer", "scene_extent", "CHECKPOINT_NAME"]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_VERSION = 3  # 2: numpy RNG state as plain data (weights_only loading); 3: appearance


@dataclass
class TrainConfig:
    iterations: int = 3000
    # loss
    lambda_l1: float = 0.8
    lambda_dssim: float = 0.2
    lambda_layout: float = 0.1
    layout_reg: bool = True
    #: weigh each panorama pixel's L1 and SSIM by its solid angle (cos latitude), so the loss counts
    #: every steradian alike (perspective views are unweighted)
    solid_angle_weighting: bool = False
    #: λ · mean Gaussian scale / extent (the official 360-GS code's mean-scale penalty on floaters)
    lambda_scale: float = 0.0
    #: largest ratio of a Gaussian's longest axis to its second longest, enforced after every step
    #: (None = free): keeps needles from forming (a flat disc, ratio ~1, is unaffected)
    max_anisotropy: float | None = None
    #: measure a panorama's L1 and D-SSIM on its eight 120° perspective crops (resampled from the
    #: render, gaussians/crop_loss.py) instead of on the equirectangular image
    crop_loss: bool = False
    #: weight of the novel-view coverage loss: mean(1 − alpha) of a panorama rendered from a random
    #: position between the training cameras (`coverage_height` rows). Indoors every ray from
    #: inside the room ends on a surface, so a hole there is an error no training view shows
    #: (the sparse-capture study in docs/training.md)
    lambda_coverage: float = 0.0
    coverage_height: int = 64
    #: horizontal jitter of those positions (× extent) around the segment between two cameras
    coverage_jitter: float = 0.05
    #: Mip-Splatting's 3D smoothing filter (gaussians/mip_filter.py): every render draws each Gaussian
    #: convolved with an isotropic low-pass of variance `mip_filter_variance` / ν², ν the finest rate
    #: (pixels per metre) at which a training camera samples it, opacity scaled to keep its integral;
    #: the exported model holds the filtered scales and opacities
    mip_filter: bool = False
    mip_filter_variance: float = DEFAULT_VARIANCE
    #: scale the filtered opacity by sqrt(det Σ / det Σ') (Mip-Splatting); False widens only (ablation)
    mip_filter_keep_integral: bool = True
    #: turn each training panorama's camera by a random rotation every time it is drawn, its ground
    #: truth and mask resampled to match (gaussians/view_jitter.py): supervision between the pixel
    #: centres, as the crops get
    random_turns: bool = False
    #: largest tilt of those turns (degrees; the yaw is free)
    random_turn_tilt_deg: float = 1.0
    #: how the turned ground truth is interpolated: "bilinear" or "bicubic"
    random_turn_interp: str = "bicubic"
    #: the renderer's screen-space dilation (squared pixels) the model is fitted with; the exported
    #: model keeps it (Gaussians.eps2d), so every later render uses it too
    eps2d: float = DEFAULT_EPS2D
    # learning rates (3DGS); the position rates are multiplied by the scene extent
    lr_position_init: float = 1.6e-4
    lr_position_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scaling: float = 5e-3
    lr_rotation: float = 1e-3
    extent: float = 1.0
    # spherical harmonics
    sh_degree: int = 3
    sh_degree_every: int = 1000
    # density control (3DGS schedule)
    densify_from: int = 500
    densify_until: int = 15000
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    opacity_reset_every: int = 3000
    max_world_scale: float | None = 0.1  # × extent; prunes after the first opacity reset, as 3DGS
    max_screen_radius: float | None = None  # radians; None = off
    #: iteration from which max_world_scale / max_screen_radius prune; None = after the first opacity reset
    size_prune_from: int | None = None
    max_gaussians: int | None = 200_000
    # misc
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: train against a random background colour each iteration (drawn from the trainer's generator):
    #: a pixel left partly transparent then cannot match its ground truth, so surfaces become opaque
    #: (every ray of an indoor panorama ends on one); renders for evaluation use `background`
    random_background: bool = False
    seed: int = 0
    backend: str | None = None
    #: torch device of the model, images, optimiser and losses; not in the fingerprint, so a
    #: checkpoint resumes on another device (checkpoints hold CPU tensors)
    device: str = "cpu"
    log_every: int = 10
    checkpoint_every: int = 500
    # per-panorama appearance (gaussians/appearance.py)
    appearance: bool = False
    lambda_appearance: float = 0.01
    #: weight of the penalty on the mean transform's distance from the identity (Appearance.gauge)
    lambda_appearance_gauge: float = 0.0
    lr_appearance: float = 1e-3

    def fingerprint(self) -> str:
        """What a checkpoint must match to be resumed (everything but logging/checkpoint cadence)."""
        import hashlib

        d = asdict(self)
        for k in ("log_every", "checkpoint_every", "device"):
            d.pop(k)
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class TrainView:
    """One training image: a panorama (EquirectCamera) or a perspective crop (PinholeCamera)."""

    name: str
    image: torch.Tensor  # [H,W,3] float in [0,1]
    viewmat: torch.Tensor  # [4,4] world-to-camera
    camera: object
    #: [H,W] bool, the pixels the losses use (a tripod or hand masked out); None = every pixel
    mask: torch.Tensor | None = None

    def to(self, device) -> TrainView:
        return TrainView(self.name, self.image.to(device), self.viewmat.to(device), self.camera,
                         None if self.mask is None else self.mask.to(device))


def scene_extent(points: np.ndarray | torch.Tensor, low: float = 1.0, high: float = 99.0) -> float:
    """Half the diagonal of the (1st–99th percentile) bounding box of `points`, at least 0.1 m:
    the scene size 3DGS scales position learning rates and size thresholds by."""
    p = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points, dtype=np.float64)
    if p.shape[0] == 0:
        return 1.0
    lo, hi = np.percentile(p, low, axis=0), np.percentile(p, high, axis=0)
    return float(max(0.5 * np.linalg.norm(hi - lo), 0.1))


def _all_finite(tensors: list[torch.Tensor]) -> torch.Tensor:
    """0-dim bool: every value of every tensor finite. One read pass per tensor (min and max
    are finite exactly when all values are: both propagate NaN), no host sync."""
    if not tensors:
        return torch.ones((), dtype=torch.bool)
    ends = torch.stack([torch.stack(torch.aminmax(t)) for t in tensors])
    return torch.isfinite(ends).all()


class _Laps:
    """Adds the seconds since the previous lap to `parts[name]`; does nothing when `parts` is None."""

    def __init__(self, parts: dict[str, float] | None, device: torch.device):
        self.parts = parts
        self.cuda = device.type == "cuda"
        self.t = time.perf_counter() if parts is not None else 0.0

    def __call__(self, name: str) -> None:
        if self.parts is None:
            return
        if self.cuda:
            torch.cuda.synchronize()
        now = time.perf_counter()
        self.parts[name] = self.parts.get(name, 0.0) + now - self.t
        self.t = now


@dataclass
class _Ema:
    loss: float | None = None
    psnr: float | None = None

    def update(self, loss: float, p: float, a: float = 0.4) -> None:
        self.loss = loss if self.loss is None else a * loss + (1 - a) * self.loss
        self.psnr = p if self.psnr is None else a * p + (1 - a) * self.psnr


class Trainer:
    def __init__(self, g: Gaussians, views: list[TrainView], cfg: TrainConfig,
                 log_path: Path | None = None):
        if not views:
            raise ValueError("no training views")
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        self.views = [v.to(self.device) for v in views]
        self.g = g.detach().to(device=self.device)
        self.g.requires_grad_(True)
        lr_means = cfg.lr_position_init * cfg.extent
        self.opt = Adam({
            "means": lr_means, "quats": cfg.lr_rotation, "log_scales": cfg.lr_scaling,
            "opacity_logits": cfg.lr_opacity, "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest,
        })
        self.stats = DensifyStats.zeros(len(self.g), dtype=self.g.means.dtype, device=self.device)
        self.gen = torch.Generator().manual_seed(int(cfg.seed))
        self.iteration = 0
        self.active_sh = 0
        self.stack: list[int] = []
        self.ema = _Ema()
        self.records: list[dict] = []
        self.train_seconds = 0.0
        self.nonfinite_steps = 0
        self.log_path = log_path
        self._bg = torch.tensor(cfg.background, dtype=self.g.means.dtype, device=self.device)
        self._has_layout: bool | None = None  # cached: asking the device every iteration would sync
        self._layout_rows: tuple[torch.Tensor, ...] = ()
        self.last_loss: float | None = None
        #: Per-panorama colour transforms (None: off); applied to training renders only.
        self.appearance = self._new_appearance()
        #: Extra identity a checkpoint must match (e.g. a hash of the initial model and images).
        self.extra_fingerprint = ""
        self._in_step = False
        #: Seconds spent in each part of the step, summed over steps (`pano-pipe bench train`);
        #: timed on the CPU (free there), None = not timed (a CUDA step would wait for the
        #: device at every part; set it to {} to time one anyway).
        self.part_seconds: dict[str, float] | None = {} if self.device.type == "cpu" else None
        self._weights: dict[tuple[int, int], torch.Tensor] = {}
        self._resamplers: dict = {}
        self._crops: dict = {}
        self._centres: torch.Tensor | None = None
        self._turn_grids: dict[tuple[int, int], TurnGrid] = {}

    def _new_appearance(self) -> Appearance | None:
        if not self.cfg.appearance:
            return None
        names = list(dict.fromkeys(Appearance.panorama_of(v.name) for v in self.views))
        return Appearance(names, self.cfg.lr_appearance, self.g.means.dtype, device=self.device)

    def _as_trained(self, view: TrainView, image: torch.Tensor) -> torch.Tensor:
        """A render as the loss sees it: through the view's appearance transform, when on."""
        return image if self.appearance is None else self.appearance.apply(view.name, image)

    def _crop_targets(self, view: TrainView):
        """(resampler, ground-truth crops, crop masks) of a panorama view when crop_loss is on, else None."""
        if not self.cfg.crop_loss or getattr(view.camera, "kind", None) != "equirect":
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

    def _camera_centres(self) -> torch.Tensor:
        """[P,3] distinct camera centres of the training views (a panorama's crops share one)."""
        if self._centres is None:
            c = torch.stack([-(v.viewmat[:3, :3].T @ v.viewmat[:3, 3]) for v in self.views])
            self._centres = torch.unique(torch.round(c, decimals=6), dim=0)
        return self._centres

    def _drawn(self) -> Gaussians:
        """The Gaussians every render draws: the model, through the 3D smoothing filter when on.
        The sampling rates are recomputed from the current centres at every call (Mip-Splatting
        recomputes them every 100 iterations; here it costs little, and a function of the model
        alone keeps a resumed run identical to an uninterrupted one)."""
        g = self.g
        if self.cfg.mip_filter:
            rate = sampling_rate(g.means.detach(), [v.viewmat for v in self.views], [v.camera for v in self.views])
            g = filtered(g, filter_variance(rate, self.cfg.mip_filter_variance), self.cfg.mip_filter_keep_integral)
        # drawn with the training dilation, which the exported model keeps (Gaussians.eps2d)
        return g if g.eps2d == self.cfg.eps2d else replace(g, eps2d=self.cfg.eps2d)

    def _coverage_loss(self, g: Gaussians) -> torch.Tensor:
        """mean(1 − alpha) of a coverage_height × 2·coverage_height panorama from a random point of
        the segment between two training cameras (horizontally jittered): pushes holes between
        splats, which only a new viewpoint shows, to close."""
        cfg = self.cfg
        c = self._camera_centres()
        i, j = torch.randint(len(c), (2,), generator=self.gen).tolist()
        u, jx, jz = torch.rand(3, generator=self.gen, dtype=torch.float64).tolist()
        pos = c[i] + u * (c[j] - c[i])
        pos = pos + pos.new_tensor([2 * jx - 1, 0.0, 2 * jz - 1]) * cfg.coverage_jitter * cfg.extent
        viewmat = torch.eye(4, dtype=self.g.means.dtype, device=self.device)
        viewmat[:3, 3] = -pos.to(viewmat.dtype)
        h = int(cfg.coverage_height)
        out = render(g, viewmat, splatting.EquirectCamera(h, 2 * h), backend=cfg.backend,
                     background=self._bg, sh_degree=0)
        return (1.0 - out.alpha).mean()

    def _pixel_weight(self, view: TrainView) -> torch.Tensor | None:
        """The per-pixel loss weight of `view`: its pixels' solid angle for a panorama when
        solid_angle_weighting is on, else None (a plain mean)."""
        cam = view.camera
        if not self.cfg.solid_angle_weighting or getattr(cam, "kind", None) != "equirect":
            return None
        key = (int(cam.height), int(cam.width))
        w = self._weights.get(key)
        if w is None:
            w = self._weights[key] = solid_angle_weight(*key, dtype=view.image.dtype, device=self.device)
        return w

    def _turned(self, view: TrainView) -> TrainView:
        """`view` with its camera frame turned by a random rotation R, the ground truth and mask
        resampled so that each pixel still shows what the panorama saw along that ray."""
        key = (int(view.camera.height), int(view.camera.width))
        grids = self._turn_grids.get(key)
        if grids is None:
            grids = self._turn_grids[key] = TurnGrid(*key, device=self.device)
        rot = random_turn(self.cfg.random_turn_tilt_deg, self.gen)
        grid = grids.grid(rot, view.image.dtype)
        with torch.no_grad():
            image = turn_panorama(view.image, grid, self.cfg.random_turn_interp)
            if self.cfg.random_turn_interp != "bilinear":
                image = image.clamp(0.0, 1.0)
            mask = None
            if view.mask is not None:
                mask = turn_panorama(view.mask[..., None].to(view.image.dtype), grid)[..., 0] > 0.999
        viewmat = view.viewmat.clone()
        viewmat[:3] = rot.to(viewmat) @ view.viewmat[:3]
        return TrainView(view.name, image, viewmat, view.camera, mask)

    # -- one iteration -------------------------------------------------------
    def _next_view(self) -> TrainView:
        if not self.stack:
            self.stack = torch.randperm(len(self.views), generator=self.gen).tolist()
        return self.views[self.stack.pop()]

    def step(self) -> dict:
        self._in_step = True  # cleared only when the whole iteration is done (see _consistent)
        cfg = self.cfg
        self.iteration += 1
        it = self.iteration
        self.opt.lrs["means"] = expon_lr(it, cfg.lr_position_init * cfg.extent, cfg.lr_position_final * cfg.extent,
                                         cfg.iterations)
        if cfg.sh_degree_every > 0 and it % cfg.sh_degree_every == 0:
            self.active_sh = min(self.active_sh + 1, cfg.sh_degree, self.g.sh_degree)
        view = self._next_view()
        if cfg.random_turns and getattr(view.camera, "kind", None) == "equirect":
            view = self._turned(view)
        g = self.g
        lap = _Laps(self.part_seconds, self.device)
        bg = self._bg
        if cfg.random_background:
            bg = torch.rand(3, generator=self.gen, dtype=self._bg.dtype).to(self.device)
        drawn = self._drawn()
        out = render(drawn, view.viewmat, view.camera, backend=cfg.backend, background=bg,
                     sh_degree=self.active_sh)
        lap("render")
        pred = self._as_trained(view, out.image)
        crops = self._crop_targets(view)
        if crops is not None:
            photo, l1, s = crop_photometric_loss(pred, crops[1], crops[0], cfg.lambda_l1, cfg.lambda_dssim, crops[2])
        else:
            photo, l1, s = photometric_loss(pred, view.image, cfg.lambda_l1, cfg.lambda_dssim, mask=view.mask,
                                            weight=self._pixel_weight(view))
        loss = photo
        if cfg.lambda_scale > 0:
            loss = loss + cfg.lambda_scale * torch.exp(g.log_scales).mean() / cfg.extent
        if self.appearance is not None and cfg.lambda_appearance > 0:
            loss = loss + cfg.lambda_appearance * self.appearance.regulariser()
        if self.appearance is not None and cfg.lambda_appearance_gauge > 0:
            loss = loss + cfg.lambda_appearance_gauge * self.appearance.gauge()
        cov = None
        if cfg.lambda_coverage > 0:
            cov = self._coverage_loss(drawn)
            loss = loss + cfg.lambda_coverage * cov
        lay = None
        if self._has_layout is None:
            self._has_layout = bool(g.is_layout.any())
            # the layout Gaussians' rows, anchors and normals change only with densification:
            # selected once, not by the mask at every step
            idx = torch.nonzero(g.is_layout).squeeze(1)
            self._layout_rows = (idx, g.u0[idx], g.normals[idx])
        if cfg.layout_reg and cfg.lambda_layout > 0 and self._has_layout:
            idx, u0, normals = self._layout_rows
            lay = layout_loss(g.means[idx], u0, normals)
            loss = loss + cfg.lambda_layout * lay
        if out.means2d.requires_grad:
            out.means2d.retain_grad()
        lap("losses")
        loss.backward()
        lap("backward")

        with torch.no_grad():
            # on the device, without a host sync: counted here, read by the log
            grads = [p.grad for p in (getattr(g, k) for k in PARAM_NAMES) if p.grad is not None and p.grad.numel()]
            finite = _all_finite(grads)
            self.nonfinite_steps = self.nonfinite_steps + (~finite).long()
            # on the CPU reading the flag costs nothing, and saves a pass over every gradient
            if self.device.type != "cpu" or not bool(finite):
                for gr in grads:
                    torch.nan_to_num_(gr, nan=0.0, posinf=0.0, neginf=0.0)
            self.opt.step(g)
            if self.appearance is not None:
                self.appearance.step()
            Adam.zero_grad(g)
            # quaternions: keep them away from zero (the renderer copes, Adam's steps would not)
            qn = torch.linalg.vector_norm(g.quats, dim=-1, keepdim=True)
            g.quats.copy_(torch.where(qn > 1e-8, g.quats, g.quats.new_tensor([1.0, 0, 0, 0])))
            if cfg.max_anisotropy is not None:
                clamp_anisotropy_(g.log_scales, cfg.max_anisotropy)
            lap("optimiser")

            if it < cfg.densify_until:
                self.stats.add(out.means2d.grad if out.means2d.requires_grad else None, out.visible, out.radii,
                               view.camera.pixel_scale[0], gradient_scale(view.camera))
                if it >= cfg.densify_from and it % cfg.densify_every == 0:
                    after_reset = (it >= cfg.size_prune_from if cfg.size_prune_from is not None
                                   else cfg.opacity_reset_every > 0 and it > cfg.opacity_reset_every)
                    res = densify_and_prune(
                        g, self.opt, self.stats,
                        grad_threshold=cfg.densify_grad_threshold, percent_dense=cfg.percent_dense,
                        extent=cfg.extent, min_opacity=cfg.min_opacity,
                        max_world_scale=(cfg.max_world_scale * cfg.extent
                                         if after_reset and cfg.max_world_scale else None),
                        max_screen_radius=cfg.max_screen_radius if after_reset else None,
                        max_gaussians=cfg.max_gaussians, generator=self.gen,
                    )
                    self.g = res.gaussians
                    self._has_layout = None
                    self.stats = DensifyStats.zeros(len(self.g), dtype=self.g.means.dtype, device=self.device)
                if cfg.opacity_reset_every > 0 and it % cfg.opacity_reset_every == 0:
                    if cfg.mip_filter:  # clamp the opacity as drawn (Mip-Splatting's reset)
                        rate = sampling_rate(self.g.means, [v.viewmat for v in self.views],
                                             [v.camera for v in self.views])
                        cap = reset_cap_logits(self.g.log_scales, filter_variance(rate, cfg.mip_filter_variance))
                        if not cfg.mip_filter_keep_integral:
                            cap = torch.full_like(cap, math.log(0.01 / 0.99))
                        self.g.opacity_logits.copy_(torch.minimum(self.g.opacity_logits, cap))
                        self.opt.reset("opacity_logits")
                    else:
                        reset_opacity(self.g, self.opt)
            lap("densify")

        # 0-dim tensors, not floats: reading them would wait for the device every iteration;
        # the log (every log_every iterations) converts them
        lv = loss.detach()
        p = psnr_tensor(pred, view.image, view.mask)
        self.ema.update(lv, p)
        self.last_loss = lv
        lap("log")
        self._in_step = False
        return {
            "iteration": it, "loss": lv, "l1": l1.detach(), "ssim": s.detach(),
            "layout": None if lay is None else lay.detach(), "psnr": p, "view": view.name,
            "coverage": None if cov is None else cov.detach(),
        }

    # -- the loop --------------------------------------------------------------
    def train(self, until: int | None = None,
              on_step: Callable[[Trainer, dict], None] | None = None,
              checkpoint_path: Path | None = None) -> None:
        """Iterate up to `until` (default cfg.iterations). Checkpoints every
        cfg.checkpoint_every iterations into `checkpoint_path`, and on
        KeyboardInterrupt (saved at the last completed iteration, then re-raised)."""
        until = self.cfg.iterations if until is None else min(until, self.cfg.iterations)
        t_last = time.perf_counter()
        try:
            while self.iteration < until:
                info = self.step()
                now = time.perf_counter()
                self.train_seconds += now - t_last
                t_last = now
                it = self.iteration
                if it % max(self.cfg.log_every, 1) == 0 or it == until or it == 1:
                    self._log(info)
                if checkpoint_path is not None and self.cfg.checkpoint_every > 0 and \
                        it % self.cfg.checkpoint_every == 0 and it < self.cfg.iterations:
                    self.save_checkpoint(checkpoint_path)
                if on_step is not None:
                    on_step(self, info)
        except KeyboardInterrupt:
            # An interrupt inside step() leaves a half-updated state, which is never saved
            # (the last periodic checkpoint stays); between iterations the state is whole.
            if checkpoint_path is not None and self._consistent():
                self.save_checkpoint(checkpoint_path)
            raise

    def _consistent(self) -> bool:
        return not self._in_step

    def _log(self, info: dict) -> None:
        """One record of plain numbers (the host syncs with the device here, every log_every steps)."""
        rec = {
            "iteration": info["iteration"], "loss": _num(info["loss"]), "l1": _num(info["l1"]),
            "ssim": _num(info["ssim"]), "layout": _num(info["layout"]), "psnr": _num(info["psnr"]),
            "ema_loss": _num(self.ema.loss), "ema_psnr": _num(self.ema.psnr),
            "num_gaussians": len(self.g), "sh_degree": self.active_sh, "lr_means": self.opt.lrs["means"],
            "seconds": round(self.train_seconds, 3), "nonfinite_steps": int(self.nonfinite_steps),
        }
        if info.get("coverage") is not None:
            rec["coverage"] = _num(info["coverage"])
        self.records.append(rec)
        if self.log_path is not None:
            with open(self.log_path, "a") as f:
                f.write(json.dumps(rec) + "\n")

    # -- evaluation helpers ------------------------------------------------------
    @torch.no_grad()
    def mean_psnr(self, views: list[TrainView] | None = None) -> float:
        vals = []
        drawn = self._drawn()
        for v in views or self.views:
            out = render(drawn, v.viewmat, v.camera, backend=self.cfg.backend, background=self._bg,
                         sh_degree=self.active_sh)
            vals.append(psnr(self._as_trained(v, out.image), v.image, v.mask))
        return float(np.mean(vals))

    @torch.no_grad()
    def final_gaussians(self) -> Gaussians:
        """The trained model as it renders, detached (with mip_filter, the filtered scales and
        opacities baked in, so a held-out render draws what training drew); it keeps all its SH
        bands (those never activated are zero)."""
        return self._drawn().detach()

    # -- checkpoints ------------------------------------------------------------
    def state_dict(self) -> dict:
        """Tensors and plain data only (what torch.load(weights_only=True) accepts); every tensor
        on the CPU, so a checkpoint written on one device resumes on another."""
        return _to_cpu({
            "version": CHECKPOINT_VERSION,
            "fingerprint": self.cfg.fingerprint() + self.extra_fingerprint,
            "iteration": self.iteration,
            "gaussians": {k: v.detach().clone() for k, v in self.g.tensors().items()},
            "opt": self.opt.state_dict(),
            "stats": self.stats.state_dict(),
            "gen": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "np_rng": _np_rng_to_plain(np.random.get_state()),
            "active_sh": self.active_sh,
            "stack": list(self.stack),
            "ema": {k: _num(v) for k, v in asdict(self.ema).items()},
            "appearance": None if self.appearance is None else self.appearance.state_dict(),
            "records": list(self.records),
            "train_seconds": self.train_seconds,
            "nonfinite_steps": int(self.nonfinite_steps),
        })

    def save_checkpoint(self, path: Path) -> None:
        """Write atomically (temporary file, then rename). On failure the temporary file is
        removed; an OSError is re-raised naming `path` (a full disk would otherwise read as
        an anonymous "[Errno 28] No space left on device")."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.save(self.state_dict(), tmp)
            os.replace(tmp, path)
        except BaseException as e:  # also Ctrl-C mid-write: never leave a half file behind
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            if isinstance(e, OSError):
                reason = e.strerror or str(e) or type(e).__name__
                raise OSError(e.errno, f"cannot write the training checkpoint: {reason}", str(path)) from e
            raise

    def load_state_dict(self, s: dict) -> None:
        """Restore a checkpoint. Raises ValueError (saying what is wrong) and changes nothing
        unless the whole checkpoint is valid for this trainer."""
        new = self._checked_state(s)
        # everything below is validated; none of it can fail half-way
        self.iteration = new["iteration"]
        self.g = new["g"].to(device=self.device)
        self.g.requires_grad_(True)
        self._has_layout = None
        self.opt = new["opt"].to(self.device)
        self.stats = new["stats"].to(self.device)
        self.gen.set_state(new["gen"])
        torch.set_rng_state(new["torch_rng"])
        np.random.set_state(new["np_rng"])
        self.active_sh = new["active_sh"]
        self.stack = new["stack"]
        self.ema = new["ema"]
        self.records = new["records"]
        self.train_seconds = new["train_seconds"]
        self.nonfinite_steps = new["nonfinite_steps"]
        self.appearance = new["appearance"]

    def _checked_state(self, s: object) -> dict:
        """The trainer state a checkpoint describes, every field checked (type, shape, range)
        so that a crafted or damaged file cannot leave a trainer that fails later."""
        if not isinstance(s, dict):
            raise ValueError(f"checkpoint is a {type(s).__name__}, not a dict")
        # plain comparisons only: `tensor != value` would be a tensor, not a bool
        version = s.get("version")
        if not _is_int(version) or version != CHECKPOINT_VERSION:
            raise ValueError(f"checkpoint version {_short(version, 40)} is not {CHECKPOINT_VERSION}")
        missing = sorted(_STATE_KEYS - set(s))
        if missing:
            raise ValueError(f"checkpoint lacks {', '.join(missing)}")
        fp = s["fingerprint"]
        if not isinstance(fp, str) or fp != self.cfg.fingerprint() + self.extra_fingerprint:
            raise ValueError("checkpoint was made with different training settings")
        out: dict = {}
        out["iteration"] = _int_in(s["iteration"], "iteration", 0, self.cfg.iterations)

        # the model: the fields, dtypes and SH bands of this trainer's; Gaussians checks the shapes
        ref = self.g.tensors()
        gs = s["gaussians"]
        if not isinstance(gs, dict) or set(gs) != set(ref):
            raise ValueError(f"checkpoint gaussians must hold exactly {', '.join(ref)}")
        for k, v in gs.items():
            if not _is_dense(v, ref[k].dtype) or v.ndim == 0:
                raise ValueError(f"checkpoint gaussians.{k} is not a {ref[k].dtype} tensor")
            if v.is_floating_point() and not bool(torch.isfinite(v).all()):
                raise ValueError(f"checkpoint gaussians.{k} has non-finite values")
        g = Gaussians(**{k: v.detach().clone() for k, v in gs.items()})  # raises ValueError on bad shapes
        if g.sh_rest.shape[1] != self.g.sh_rest.shape[1]:
            raise ValueError(f"checkpoint model has SH degree {g.sh_degree}, not {self.g.sh_degree}")
        n = len(g)

        # a fresh optimiser: validating into it leaves self.opt untouched
        opt = Adam(dict(self.opt.lrs), self.opt.betas, self.opt.eps)
        opt.load_state_dict(s["opt"])
        if set(opt.lrs) != set(self.opt.lrs):
            raise ValueError("checkpoint optimiser covers other parameters")
        for k, m in opt.exp_avg.items():
            p = getattr(g, k)
            if m.shape != p.shape or m.dtype != p.dtype:
                raise ValueError(f"checkpoint optimiser moments of {k} do not match the model")
        out["g"], out["opt"] = g, opt

        st = s["stats"]
        names = ("grad_accum", "count", "max_radius")
        if not isinstance(st, dict) or any(
                not _is_dense(st.get(k), g.means.dtype) or tuple(st[k].shape) != (n,) for k in names):
            raise ValueError(f"checkpoint stats must be {', '.join(names)}: "
                             f"{g.means.dtype} tensors of length {n}")
        out["stats"] = DensifyStats.from_state(st)

        # RNG states: tried on throw-away generators first
        for k in ("gen", "torch_rng"):
            try:  # torch checks the size and the MT19937 fields
                torch.Generator().set_state(s[k])
            except (TypeError, RuntimeError) as e:
                raise ValueError(f"checkpoint {k} is not a torch generator state ({_short(e)})") from None
            out[k] = s[k]
        out["np_rng"] = _np_rng_from_plain(s["np_rng"])

        out["active_sh"] = _int_in(s["active_sh"], "active_sh", 0, g.sh_degree)
        stack = s["stack"]
        if not isinstance(stack, list | tuple):
            raise ValueError("checkpoint stack is not a list")
        out["stack"] = [_int_in(i, "stack entry", 0, len(self.views) - 1) for i in stack]
        ema = s["ema"]
        if not isinstance(ema, dict) or set(ema) != {"loss", "psnr"} or \
                any(v is not None and not _is_real(v) for v in ema.values()):
            raise ValueError("checkpoint ema must be {loss, psnr} numbers or None")
        out["ema"] = _Ema(**{k: None if v is None else float(v) for k, v in ema.items()})
        recs = s["records"]
        if not isinstance(recs, list | tuple) or not all(isinstance(r, dict) for r in recs):
            raise ValueError("checkpoint records must be a list of dicts")
        try:  # they are written back to the JSON lines log
            json.dumps(recs)
        except (TypeError, ValueError):
            raise ValueError("checkpoint records are not JSON data") from None
        out["records"] = [dict(r) for r in recs]
        if not _is_real(s["train_seconds"]) or not s["train_seconds"] >= 0:
            raise ValueError("checkpoint train_seconds must be a number >= 0")
        out["train_seconds"] = float(s["train_seconds"])
        out["nonfinite_steps"] = _int_in(s["nonfinite_steps"], "nonfinite_steps", 0, None)
        out["appearance"] = self._new_appearance()
        if out["appearance"] is None:
            if s["appearance"] is not None:
                raise ValueError("checkpoint has appearance transforms, this run has appearance off")
        else:
            out["appearance"].load_state_dict(s["appearance"])
        return out

    def load_checkpoint(self, path: Path) -> None:
        """Load a checkpoint written by save_checkpoint. A file that cannot be read, holds anything
        but tensors and plain data, or does not fit this trainer raises ValueError; the trainer is
        then unchanged."""
        path = Path(path)
        try:
            # weights_only: the unpickler builds tensors and plain containers, never calls code
            s = torch.load(path, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError:
            # torch's message suggests weights_only=False: the one thing not to do with such a file
            raise ValueError("not a checkpoint: damaged, or holds objects other than tensors and plain data"
                             ) from None
        except OSError:
            raise
        except Exception as e:  # noqa: BLE001 (zip, EOF, storage errors of a damaged file)
            raise ValueError(f"not a readable checkpoint ({_short(e) or type(e).__name__})") from None
        self.load_state_dict(s)
        if self.log_path is not None:  # the log restarts from the checkpoint's records
            with open(self.log_path, "w") as f:
                for rec in self.records:
                    f.write(json.dumps(rec) + "\n")


def clamp_anisotropy_(log_scales: torch.Tensor, max_ratio: float) -> None:
    """In place: shorten every Gaussian's longest axis to at most `max_ratio` × its second longest
    (log scales [N,3]); the two shorter axes are untouched."""
    top2 = torch.topk(log_scales, 2, dim=1)
    limit = top2.values[:, 1] + math.log(max_ratio)
    over = top2.values[:, 0] > limit
    if bool(over.any()):
        rows = torch.nonzero(over, as_tuple=False).squeeze(1)
        log_scales[rows, top2.indices[rows, 0]] = limit[rows]


def _num(x):
    """A logged value as a plain number (None stays None); reading a device tensor waits for it."""
    return None if x is None else float(x)


def _to_cpu(x):
    """`x` with every tensor in it (nested dicts, lists, tuples) moved to the CPU."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu()
    if isinstance(x, dict):
        return {k: _to_cpu(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return type(x)(_to_cpu(v) for v in x)
    return x


_STATE_KEYS = frozenset({
    "fingerprint", "iteration", "gaussians", "opt", "stats", "gen", "torch_rng", "np_rng", "active_sh",
    "stack", "ema", "records", "train_seconds", "nonfinite_steps", "appearance",
})


def _short(x: object, limit: int = 120) -> str:
    """One line of an error message or value: its first sentence, at most `limit` characters."""
    text = str(x).strip().splitlines()[0] if str(x).strip() else ""
    text = text.split(". ")[0]
    return text if len(text) <= limit else text[: limit - 3] + "..."


_MT_N = 624  # words of MT19937 state


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_real(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _is_dense(t: object, dtype: torch.dtype) -> bool:
    """A plain (strided, CPU) tensor of `dtype`: what save_checkpoint writes."""
    return (isinstance(t, torch.Tensor) and t.layout == torch.strided and t.device.type == "cpu"
            and t.dtype == dtype)


def _int_in(x: object, what: str, lo: int, hi: int | None) -> int:
    if not _is_int(x) or x < lo or (hi is not None and x > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"checkpoint {what} must be an integer {bound}, got {_short(repr(x), 40)}")
    return int(x)


def _np_rng_to_plain(state: tuple) -> dict:
    """np.random.get_state() (a tuple holding a uint32 array) as plain data and a tensor."""
    name, keys, pos, has_gauss, cached = state
    return {"name": str(name), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
            "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}


def _np_rng_from_plain(d: object) -> tuple:
    """The inverse of _np_rng_to_plain, every field checked first (numpy trusts `pos`:
    an out-of-range one crashes the interpreter on the next draw)."""
    ok = (isinstance(d, dict) and isinstance(d.get("name"), str) and d["name"] == "MT19937"
          and _is_dense(d.get("keys"), torch.int64) and tuple(d["keys"].shape) == (_MT_N,)
          and _is_int(d.get("pos")) and 0 <= d["pos"] <= _MT_N
          and _is_int(d.get("has_gauss")) and d["has_gauss"] in (0, 1) and _is_real(d.get("cached_gaussian")))
    keys = d["keys"].numpy() if ok else None
    if keys is None or keys.min() < 0 or keys.max() > np.iinfo(np.uint32).max:
        raise ValueError("checkpoint np_rng is not a numpy MT19937 state")
    return ("MT19937", keys.astype(np.uint32), int(d["pos"]), int(d["has_gauss"]), float(d["cached_gaussian"]))
