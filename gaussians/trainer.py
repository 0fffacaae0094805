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

import json
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from gaussians import checkpoint
from gaussians.appearance import Appearance
from gaussians.checkpoint import CHECKPOINT_NAME, plain_number
from gaussians.config import TrainConfig
from gaussians.densify import DensifyStats
from gaussians.losses import psnr, psnr_tensor
from gaussians.mip_filter import filter_variance, filtered, sampling_rate
from gaussians.model import Gaussians, render
from gaussians.objective import TrainingObjective
from gaussians.optim import Adam, expon_lr
from gaussians.strategy import DensifyStrategy
from gaussians.view_jitter import TurnMaps, random_turn, turn_view_images
from splatting import compile_ahead

__all__ = ["TrainConfig", "TrainView", "Trainer", "scene_extent", "CHECKPOINT_NAME"]

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


def mean_colour(images: Iterable[tuple]) -> tuple[float, float, float]:
    """The mean RGB of the valid pixels of (image [H,W,3], mask [H,W] bool or None) pairs (torch or
    numpy), every pixel counted once: the least-squares constant for what no training view covers,
    the background `background: "mean"` trains and renders with, and the flat image evaluate
    scores as the floor a model must beat."""
    total, count = np.zeros(3), 0
    for image, mask in images:
        px = torch.as_tensor(image).detach().to("cpu", torch.float64).reshape(-1, 3).numpy()
        if mask is not None:
            px = px[torch.as_tensor(mask).detach().cpu().reshape(-1).numpy()]
        total += px.sum(axis=0)
        count += px.shape[0]
    if count == 0:
        raise ValueError("mean_colour: no valid pixel in any training image")
    return tuple(float(c) for c in total / count)


def scene_extent(points: np.ndarray | torch.Tensor, low: float = 1.0, high: float = 99.0) -> float:
    """Half the diagonal of the (1st–99th percentile) bounding box of `points`, at least 0.1 m:
    the scene size 3DGS scales position learning rates and size thresholds by."""
    p = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points, dtype=np.float64)
    if p.shape[0] == 0:
        return 1.0
    lo, hi = np.percentile(p, low, axis=0), np.percentile(p, high, axis=0)
    return float(max(0.5 * np.linalg.norm(hi - lo), 0.1))


class _Laps:
    """Adds the seconds since the previous lap to `parts[name]`; does nothing when `parts` is None.

    On a GPU the laps are CUDA events on the current stream (no host sync): the seconds are the
    device timeline's, which is also where launch overhead shows (a device waiting for the host),
    and they are added to `parts` when `PendingLaps.settle` runs (at the log, which syncs anyway)."""

    def __init__(self, parts: dict[str, float] | None, device: torch.device, pending: PendingLaps):
        self.parts = parts
        self.pending = pending if device.type == "cuda" and parts is not None else None
        self.t = 0.0
        if parts is None:
            return
        if self.pending is not None:
            self.t = self.pending.event()
        else:
            self.t = time.perf_counter()

    def __call__(self, name: str) -> None:
        if self.parts is None:
            return
        if self.pending is not None:
            now = self.pending.event()
            self.pending.laps.append((name, self.t, now))
        else:
            now = time.perf_counter()
            self.parts[name] = self.parts.get(name, 0.0) + now - self.t
        self.t = now


class PendingLaps:
    """CUDA-event laps not yet read (reading one waits for the device)."""

    def __init__(self):
        self.laps: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []

    @staticmethod
    def event():
        e = torch.cuda.Event(enable_timing=True)
        e.record()
        return e

    def settle(self, parts: dict[str, float] | None) -> None:
        if not self.laps or parts is None:
            self.laps.clear()
            return
        self.laps[-1][2].synchronize()
        for name, start, end in self.laps:
            parts[name] = parts.get(name, 0.0) + start.elapsed_time(end) / 1000.0
        self.laps.clear()


@dataclass
class _Ema:
    """Exponential moving averages of the loss and the PSNR: the first value as it is, then
    a·new + (1 − a)·old. 0-dim tensors (updated in place, one multi-tensor lerp for both,
    no host sync) or plain numbers (a checkpoint's; plain numbers updated by plain ones)."""

    loss: float | torch.Tensor | None = None
    psnr: float | torch.Tensor | None = None

    def update(self, loss, p, a: float = 0.4) -> None:
        if not (isinstance(loss, torch.Tensor) and isinstance(p, torch.Tensor)):
            self.loss = loss if self.loss is None else a * loss + (1 - a) * self.loss
            self.psnr = p if self.psnr is None else a * p + (1 - a) * self.psnr
            return
        if self.loss is None or self.psnr is None:
            # copies: the averages are updated in place, the step's values are returned as they are
            self.loss, self.psnr = loss.detach().clone(), p.detach().clone()
            return
        if not (isinstance(self.loss, torch.Tensor) and isinstance(self.psnr, torch.Tensor)):
            # a checkpoint's plain numbers: on the device once, then updated in place
            self.loss = torch.tensor(float(self.loss), dtype=loss.dtype, device=loss.device)
            self.psnr = torch.tensor(float(self.psnr), dtype=p.dtype, device=p.device)
        # old + a·(new − old): a·new + (1 − a)·old to rounding
        torch._foreach_lerp_([self.loss, self.psnr], [loss.detach(), p.detach()], a)


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
        lr_means = cfg.optim.lr_position_init * cfg.extent
        self.opt = Adam({
            "means": lr_means, "quats": cfg.optim.lr_rotation, "log_scales": cfg.optim.lr_scaling,
            "opacity_logits": cfg.optim.lr_opacity, "sh_dc": cfg.optim.lr_sh_dc, "sh_rest": cfg.optim.lr_sh_rest,
        })
        self.strategy = DensifyStrategy.from_config(cfg, self.g)
        self.objective = TrainingObjective(cfg, self.views, self.device)
        self.gen = torch.Generator().manual_seed(int(cfg.seed))
        self.iteration = 0
        self.active_sh = 0
        self.stack: list[int] = []
        self.ema = _Ema()
        self.records: list[dict] = []
        self.train_seconds = 0.0
        self.nonfinite_steps = 0
        self.log_path = log_path
        bg = mean_colour((v.image, v.mask) for v in views) if cfg.render.background == "mean" else cfg.render.background
        self._bg = torch.tensor(bg, dtype=self.g.means.dtype, device=self.device)
        self.last_loss: float | None = None
        #: Per-panorama colour transforms (None: off); applied to training renders only.
        self.appearance = self.new_appearance()
        #: Extra identity a checkpoint must match (e.g. a hash of the initial model and images).
        self.extra_fingerprint = ""
        self._in_step = False
        #: Seconds spent in each part of the step, summed over steps (`pano-pipe bench train`):
        #: the CPU's clock, or CUDA events on a GPU (read at each log); None = not timed.
        self.part_seconds: dict[str, float] | None = {}
        self._pending_laps = PendingLaps()
        self._turn_maps: dict[tuple[int, int], TurnMaps] = {}
        self._const_cache: dict[tuple[str, torch.dtype], torch.Tensor] = {}

    def new_appearance(self) -> Appearance | None:
        if not self.cfg.appearance.enabled:
            return None
        names = list(dict.fromkeys(Appearance.panorama_of(v.name) for v in self.views))
        return Appearance(names, self.cfg.optim.lr_appearance, self.g.means.dtype, device=self.device,
                          pin_mean=self.cfg.appearance.pin_appearance_mean)

    def _as_trained(self, view: TrainView, image: torch.Tensor) -> torch.Tensor:
        """A render as the loss sees it: through the view's appearance transform, when on."""
        return image if self.appearance is None else self.appearance.apply(view.name, image)

    def _drawn(self) -> Gaussians:
        """The Gaussians every render draws: the model, through the 3D smoothing filter when on.
        The sampling rates are recomputed from the current centres at every call (Mip-Splatting
        recomputes them every 100 iterations; here it costs little, and a function of the model
        alone keeps a resumed run identical to an uninterrupted one)."""
        g = self.g
        if self.cfg.render.mip_filter:
            rate = sampling_rate(g.means.detach(), [v.viewmat for v in self.views], [v.camera for v in self.views])
            g = filtered(g, filter_variance(rate, self.cfg.render.mip_filter_variance), self.cfg.render.mip_filter_keep_integral)
        # drawn with the training dilation, which the exported model keeps (Gaussians.eps2d)
        return g if g.eps2d == self.cfg.render.eps2d else replace(g, eps2d=self.cfg.render.eps2d)

    def _turned(self, view: TrainView) -> TrainView:
        """`view` with its camera frame turned by a random rotation R, the ground truth and mask
        resampled so that each pixel still shows what the panorama saw along that ray."""
        key = (int(view.camera.height), int(view.camera.width))
        turn_maps = self._turn_maps.get(key)
        if turn_maps is None:
            turn_maps = self._turn_maps[key] = TurnMaps(*key, device=self.device)
        rot = random_turn(self.cfg.turns.random_turn_tilt_deg, self.gen).numpy()
        # one copy to the device carries R (3x3, the turn kernel's) and diag(R, 1) (4x4, the view
        # matrix's), made on the host in the view's dtype: no cast, clone or concatenation there
        turn4 = np.eye(4)
        turn4[:3, :3] = rot
        both = np.concatenate([rot.ravel(), turn4.ravel()])
        dtype = np.dtype(str(view.viewmat.dtype).removeprefix("torch."))
        both = self._to_device(torch.from_numpy(both.astype(dtype)))
        with torch.no_grad():
            image, mask = turn_view_images(turn_maps, both[:9].view(3, 3), view.image, view.mask,
                                           self.cfg.turns.random_turn_interp)
        viewmat = both[9:].view(4, 4) @ view.viewmat
        return TrainView(view.name, image, viewmat, view.camera, mask)

    # -- one iteration -------------------------------------------------------
    def _next_view(self) -> TrainView:
        if not self.stack:
            self.stack = torch.randperm(len(self.views), generator=self.gen).tolist()
        return self.views[self.stack.pop()]

    @property
    def background(self) -> tuple[float, float, float]:
        """The background colour this trainer renders with ("mean" resolved)."""
        return tuple(float(c) for c in self._bg.detach().cpu())

    @property
    def stats(self) -> DensifyStats:
        """The densification statistics (the strategy's state)."""
        return self.strategy.stats

    def step(self) -> dict:
        """One iteration (the module docstring's steps 1-5)."""
        self._in_step = True  # cleared only when the whole iteration is done (see _consistent)
        cfg, it = self.cfg, self.iteration + 1
        self.iteration = it
        self._schedule(it)
        view = self._next_view()
        if cfg.turns.random_turns and getattr(view.camera, "kind", None) == "equirect":
            view = self._turned(view)
        lap = _Laps(self.part_seconds, self.device, self._pending_laps)
        bg = self._bg
        if cfg.render.random_background:
            bg = self._to_device(torch.rand(3, generator=self.gen, dtype=self._bg.dtype))
        drawn = self._drawn()
        out = render(drawn, view.viewmat, view.camera, backend=cfg.render.backend, background=bg, sh_degree=self.active_sh,
                     tile_size=cfg.render.tile_size)
        lap("render")
        pred = self._as_trained(view, out.image)
        terms = self.objective(self.g, drawn, pred, view, self.appearance, self._bg, self.gen)
        if out.means2d.requires_grad:
            out.means2d.retain_grad()
        lap("losses")
        # the seed gradient made once (autograd would fill a new one every step)
        terms.loss.backward(self._consts("one", 1.0, terms.loss.dtype))
        lap("backward")
        with torch.no_grad():
            self._optimiser_step()
            lap("optimiser")
            g = self.strategy.step_post_backward(self.g, self.opt, out, view.camera, it, self.views, self.gen)
            if g is not self.g:
                self.g = g
                self.objective.model_changed()
            lap("densify")
        # 0-dim tensors, not floats: reading them would wait for the device every iteration;
        # the log (every log_every iterations) converts them
        lv = terms.loss.detach()
        p = terms.psnr if terms.psnr is not None else psnr_tensor(pred, view.image, view.mask)
        self.ema.update(lv, p)
        self.last_loss = lv
        lap("log")
        self._in_step = False
        detached = lambda t: None if t is None else t.detach()  # noqa: E731
        return {"iteration": it, "loss": lv, "l1": terms.l1.detach(), "ssim": terms.ssim.detach(),
                "layout": detached(terms.layout), "psnr": p, "view": view.name,
                "coverage": detached(terms.coverage)}

    def _schedule(self, it: int) -> None:
        """Iteration `it`'s position learning rate and SH bands."""
        cfg = self.cfg
        self.opt.lrs["means"] = expon_lr(it, cfg.optim.lr_position_init * cfg.extent, cfg.optim.lr_position_final * cfg.extent,
                                         cfg.iterations)
        if cfg.optim.sh_degree_every > 0 and it % cfg.optim.sh_degree_every == 0:
            self.active_sh = min(self.active_sh + 1, cfg.optim.sh_degree, self.g.sh_degree)

    def _optimiser_step(self) -> None:
        """Adam on every parameter (non-finite gradients zeroed and counted, without a host sync
        on a GPU), the appearance transforms' step, then the parameters kept valid."""
        g = self.g
        # the flag (1.0: some gradient value was not finite, and taken as 0) is counted as a 0-dim
        # tensor, read only when the log or a checkpoint wants the number
        self.nonfinite_steps = self.nonfinite_steps + self.opt.step(g)
        if self.appearance is not None:
            self.appearance.step()
        Adam.zero_grad(g)
        # quaternions: keep them away from zero (the renderer copes, Adam's steps would not)
        qn = torch.linalg.vector_norm(g.quats, dim=-1, keepdim=True)
        torch.where(qn > 1e-8, g.quats, self._consts("unit_quat", (1.0, 0.0, 0.0, 0.0), g.quats.dtype), out=g.quats)
        if self.cfg.optim.max_anisotropy is not None:
            clamp_anisotropy_(g.log_scales, self.cfg.optim.max_anisotropy)

    def _to_device(self, t: torch.Tensor) -> torch.Tensor:
        """A small tensor drawn on the host (the CPU generator's numbers), on the trainer's device
        without waiting for it: a copy from pageable memory to a GPU synchronises the stream (the
        host would wait for the queued iteration: one cudaStreamSynchronize a step on the H200), a
        pinned one does not (torch's caching host allocator keeps the block until the copy is done)."""
        if self.device.type != "cuda":
            return t.to(self.device)
        return t.pin_memory().to(self.device, non_blocking=True)

    def _consts(self, name: str, value, dtype=torch.float32) -> torch.Tensor:
        """A constant tensor on the trainer's device, made once (not copied there at every step)."""
        key = (name, dtype)
        t = self._const_cache.get(key)
        if t is None:
            t = self._const_cache[key] = torch.tensor(value, dtype=dtype, device=self.device)
        return t

    # -- the loop --------------------------------------------------------------
    def train(self, until: int | None = None,
              on_step: Callable[[Trainer, dict], None] | None = None,
              checkpoint_path: Path | None = None) -> None:
        """Iterate up to `until` (default cfg.iterations). Checkpoints every
        cfg.checkpoint_every iterations into `checkpoint_path`, and on
        KeyboardInterrupt (saved at the last completed iteration, then re-raised)."""
        until = self.cfg.iterations if until is None else min(until, self.cfg.iterations)
        t_last = time.perf_counter()
        compile_ahead.sh_degrees(*self.sh_degrees_ahead())
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
        finally:
            compile_ahead.sh_degrees()

    def sh_degrees_ahead(self) -> tuple[int, ...]:
        """The SH degrees this run will still raise to, on a GPU: each needs new projection
        kernels, which splatting.compile_ahead compiles beside the first iterations (none on the
        CPU, whose kernel is compiled once)."""
        if self.device.type != "cuda" or self.cfg.optim.sh_degree_every <= 0:
            return ()
        return tuple(range(self.active_sh + 1, min(self.cfg.optim.sh_degree, self.g.sh_degree) + 1))

    def _consistent(self) -> bool:
        return not self._in_step

    def _log(self, info: dict) -> None:
        """One record of plain numbers (the host syncs with the device here, every log_every steps)."""
        self._pending_laps.settle(self.part_seconds)
        rec = {
            "iteration": info["iteration"], "loss": plain_number(info["loss"]), "l1": plain_number(info["l1"]),
            "ssim": plain_number(info["ssim"]), "layout": plain_number(info["layout"]), "psnr": plain_number(info["psnr"]),
            "ema_loss": plain_number(self.ema.loss), "ema_psnr": plain_number(self.ema.psnr),
            "num_gaussians": len(self.g), "sh_degree": self.active_sh, "lr_means": self.opt.lrs["means"],
            "seconds": round(self.train_seconds, 3), "nonfinite_steps": int(self.nonfinite_steps),
        }
        if info.get("coverage") is not None:
            rec["coverage"] = plain_number(info["coverage"])
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
            out = render(drawn, v.viewmat, v.camera, backend=self.cfg.render.backend, background=self._bg,
                         sh_degree=self.active_sh, tile_size=self.cfg.render.tile_size)
            vals.append(psnr(self._as_trained(v, out.image), v.image, v.mask))
        return float(np.mean(vals))

    @torch.no_grad()
    def final_gaussians(self) -> Gaussians:
        """The trained model as it renders, detached (with mip_filter, the filtered scales and
        opacities baked in, so a held-out render draws what training drew); it keeps all its SH
        bands (those never activated are zero)."""
        return self._drawn().detach()

    # -- checkpoints (gaussians/checkpoint.py) -------------------------------------
    def state_dict(self) -> dict:
        return checkpoint.trainer_state(self)

    def save_checkpoint(self, path: Path) -> None:
        checkpoint.write(self.state_dict(), path)

    def load_state_dict(self, s: dict) -> None:
        """Restore a checkpoint. Raises ValueError (saying what is wrong) and changes nothing
        unless the whole checkpoint is valid for this trainer."""
        new = checkpoint.checked_state(s, self)
        # everything below is validated; none of it can fail half-way
        self.iteration = new["iteration"]
        self.g = new["g"].to(device=self.device)
        self.g.requires_grad_(True)
        self.objective.model_changed()
        self.opt = new["opt"].to(self.device)
        self.strategy.stats = new["stats"].to(self.device)
        self.gen.set_state(new["gen"])
        torch.set_rng_state(new["torch_rng"])
        np.random.set_state(new["np_rng"])
        self.active_sh = new["active_sh"]
        self.stack = new["stack"]
        self.ema = _Ema(**new["ema"])
        self.records = new["records"]
        self.train_seconds = new["train_seconds"]
        self.nonfinite_steps = new["nonfinite_steps"]
        self.appearance = new["appearance"]

    def load_checkpoint(self, path: Path) -> None:
        """Load a checkpoint written by save_checkpoint. A file that cannot be read, holds anything
        but tensors and plain data, or does not fit this trainer raises ValueError; the trainer is
        then unchanged."""
        self.load_state_dict(checkpoint.read(path))
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
