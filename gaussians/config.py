"""The trainer's configuration, nested by concern: what the loss weighs, how Adam steps, when
densification runs, how each view is drawn and turned, the per-panorama appearance.

Every setting has one name, unique across the groups: `TrainConfig.of(**settings)` builds a
config from those names (the train stage's flat parameters, `train.lr_opacity`, are exactly
them), `flat()` gives them back. The numbers below are the defaults the train stage's
parameters take as theirs (stages/train.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field

from gaussians.mip_filter import DEFAULT_VARIANCE
from splatting.render import DEFAULT_EPS2D, DEFAULT_TILE

__all__ = ["TrainConfig", "LossConfig", "OptimConfig", "DensifyConfig", "RenderConfig", "TurnConfig",
           "AppearanceConfig"]


@dataclass
class LossConfig:
    lambda_l1: float = 0.8
    lambda_dssim: float = 0.2
    lambda_layout: float = 0.1
    layout_reg: bool = True
    #: displacements from the anchor up to this length (scene units: 5 cm in a metric scene) are
    #: free of L_layout: the official 360-GS code's `normal_threshold` (0 there: the paper's term,
    #: which locks a layout Gaussian at its anchor and cost every scene measured, docs/training.md)
    layout_deadzone: float = 0.05
    #: weigh each panorama pixel's L1 and SSIM by its solid angle (cos latitude), so the loss counts
    #: every steradian alike (perspective views are unweighted)
    solid_angle_weighting: bool = False
    #: λ · mean Gaussian scale / extent (the official 360-GS code's mean-scale penalty on floaters)
    lambda_scale: float = 0.0
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
    #: weight pulling the appearance transforms to the identity
    lambda_appearance: float = 0.01


@dataclass
class OptimConfig:
    # learning rates (3DGS); the position rates are multiplied by the scene extent
    lr_position_init: float = 1.6e-4
    lr_position_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scaling: float = 5e-3
    lr_rotation: float = 1e-3
    lr_appearance: float = 1e-3
    # spherical harmonics: one more band every `sh_degree_every` iterations up to `sh_degree`
    sh_degree: int = 3
    sh_degree_every: int = 1000
    #: largest ratio of a Gaussian's longest axis to its second longest, enforced after every step
    #: (None = free): keeps needles from forming (a flat disc, ratio ~1, is unaffected)
    max_anisotropy: float | None = None


@dataclass
class DensifyConfig:
    """3DGS's density control and its schedule (gaussians/strategy.py)."""

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


@dataclass
class RenderConfig:
    """How every training render draws the model."""

    #: the renderer's screen-space dilation (squared pixels) the model is fitted with; the exported
    #: model keeps it (Gaussians.eps2d), so every later render uses it too
    eps2d: float = DEFAULT_EPS2D
    #: Mip-Splatting's 3D smoothing filter (gaussians/mip_filter.py): every render draws each Gaussian
    #: convolved with an isotropic low-pass of variance `mip_filter_variance` / ν², ν the finest rate
    #: (pixels per metre) at which a training camera samples it, opacity scaled to keep its integral;
    #: the exported model holds the filtered scales and opacities
    mip_filter: bool = False
    mip_filter_variance: float = DEFAULT_VARIANCE
    #: scale the filtered opacity by sqrt(det Σ / det Σ') (Mip-Splatting); False widens only (ablation)
    mip_filter_keep_integral: bool = True
    #: RGB in [0, 1] behind the Gaussians, or "mean": the training images' mean colour over their
    #: masks (Trainer.background), so what no training view covers shows the colour that costs least
    background: tuple[float, float, float] | str = (0.0, 0.0, 0.0)
    #: train against a random background colour each iteration (drawn from the trainer's generator):
    #: a pixel left partly transparent then cannot match its ground truth, so surfaces become opaque
    #: (every ray of an indoor panorama ends on one); renders for evaluation use `background`
    random_background: bool = False
    backend: str | None = None
    #: the rasteriser's square tile (pixels); the image does not depend on it, only the speed
    tile_size: int = DEFAULT_TILE


@dataclass
class TurnConfig:
    """Random turns of the training panoramas (gaussians/view_jitter.py): supervision between the
    pixel centres, as the crops get."""

    #: turn each training panorama's camera by a random rotation every time it is drawn, its ground
    #: truth and mask resampled to match
    random_turns: bool = False
    #: largest tilt of those turns (degrees; the yaw is free)
    random_turn_tilt_deg: float = 1.0
    #: how the turned ground truth is interpolated: "bilinear" or "bicubic"
    random_turn_interp: str = "bicubic"


@dataclass
class AppearanceConfig:
    """A learned colour gain and bias per training panorama (gaussians/appearance.py)."""

    enabled: bool = False
    #: hold the mean transform over the panoramas at the identity exactly (Appearance.pin_mean_):
    #: the transforms and the colours share a free gain and offset, and an unpinned mean drifts into
    #: a colour cast of the held-out renders (docs/training.md, issue 39: +0.5 to +1.3 dB on real
    #: captures, neutral on the simulated sparse case)
    pin_appearance_mean: bool = True


#: Flat names whose field in their group is named otherwise: flat name -> field
_RENAMED = {"appearance": "enabled"}


@dataclass
class TrainConfig:
    iterations: int = 3000
    #: the scene's size (m): the position learning rates and the size thresholds are relative to it
    extent: float = 1.0
    seed: int = 0
    #: torch device of the model, images, optimiser and losses; not in the fingerprint, so a
    #: checkpoint resumes on another device (checkpoints hold CPU tensors)
    device: str = "cpu"
    log_every: int = 10
    checkpoint_every: int = 500
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    turns: TurnConfig = field(default_factory=TurnConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)

    @classmethod
    def groups(cls) -> dict[str, type]:
        """Group name -> its dataclass."""
        return {f.name: f.default_factory for f in dataclasses.fields(cls) if f.default_factory is not dataclasses.MISSING}

    @classmethod
    def setting_names(cls) -> list[str]:
        """Every setting's flat name (the train stage's parameter of the same name)."""
        top = [f.name for f in dataclasses.fields(cls) if f.name not in cls.groups()]
        inverse = {v: k for k, v in _RENAMED.items()}
        return top + [inverse.get(f.name, f.name) for g in cls.groups().values() for f in dataclasses.fields(g)]

    @classmethod
    def of(cls, **settings) -> TrainConfig:
        """A config from flat setting names (any subset; the rest keep their defaults)."""
        groups = cls.groups()
        where = {}
        for group, kind in groups.items():
            for f in dataclasses.fields(kind):
                where[next((k for k, v in _RENAMED.items() if v == f.name), f.name)] = (group, f.name)
        top, nested = {}, {g: {} for g in groups}
        for name, value in settings.items():
            if name in where:
                group, field_name = where[name]
                nested[group][field_name] = value
            elif name in {f.name for f in dataclasses.fields(cls)} and name not in groups:
                top[name] = value
            else:
                raise TypeError(f"unknown training setting {name!r}")
        return cls(**top, **{g: kind(**nested[g]) for g, kind in groups.items()})

    def flat(self) -> dict:
        """Every setting by its flat name."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in self.groups()}
        inverse = {v: k for k, v in _RENAMED.items()}
        for group in self.groups():
            sub = getattr(self, group)
            out.update({inverse.get(f.name, f.name): getattr(sub, f.name) for f in dataclasses.fields(sub)})
        return out

    def with_settings(self, **settings) -> TrainConfig:
        """A copy with some settings (flat names) changed."""
        return type(self).of(**{**self.flat(), **settings})

    def fingerprint(self) -> str:
        """What a checkpoint must match to be resumed (everything but logging/checkpoint cadence)."""
        d = self.flat()
        for k in ("log_every", "checkpoint_every", "device"):
            d.pop(k)
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]
