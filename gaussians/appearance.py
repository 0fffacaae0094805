"""Per-panorama appearance: a learned colour transform for each training panorama.

Real captures differ in exposure and white balance from panorama to panorama. Without a
transform the model explains those differences with geometry and colour (floaters, smudges).
Each training panorama gets a per-channel gain and bias, applied to its render during training
only (test views are rendered without), regularised toward the identity so that the model, not
the transform, carries the scene's colours.
"""

from __future__ import annotations

import math

import torch

from gaussians.config import AppearanceConfig, OptimConfig

__all__ = ["Appearance"]


class Appearance:
    """out = gain[view] * rgb + bias[view], per channel; `names` are the panoramas (cube faces
    share their panorama's transform: a face "pano/px" uses "pano")."""

    # the defaults are the trainer's (gaussians/config.py), written there once
    def __init__(self, names: list[str], lr: float = OptimConfig.lr_appearance, dtype: torch.dtype = torch.float32,
                 device="cpu", pin_mean: bool = AppearanceConfig.pin_appearance_mean):
        if len(set(names)) != len(names) or not names:
            raise ValueError("appearance needs distinct panorama names")
        self.names = list(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.lr = float(lr)
        self.gain = torch.ones(len(names), 3, dtype=dtype, device=device, requires_grad=True)
        self.bias = torch.zeros(len(names), 3, dtype=dtype, device=device, requires_grad=True)
        self.opt = torch.optim.Adam([self.gain, self.bias], lr=self.lr)
        #: keep the mean transform at the identity exactly (see pin_mean_)
        self.pin_mean = bool(pin_mean)

    @staticmethod
    def panorama_of(view_name: str) -> str:
        return view_name.split("/", 1)[0]

    def apply(self, view_name: str, image: torch.Tensor) -> torch.Tensor:
        """[H,W,3] image of the view, transformed."""
        i = self.index[self.panorama_of(view_name)]
        return image * self.gain[i] + self.bias[i]

    def regulariser(self) -> torch.Tensor:
        """Mean squared distance of the transforms from the identity."""
        return ((self.gain - 1.0) ** 2).mean() + (self.bias**2).mean()

    def gauge(self) -> torch.Tensor:
        """Squared distance of the *mean* transform (over the panoramas, per channel) from the
        identity. The model's colours and the transforms share a free gauge (a common gain and
        offset moves from one to the other without changing any training render); test views are
        rendered without a transform, so they see that drift. Pinning the mean (pin_mean_) makes
        the model's colours those of the training panoramas' mean exposure."""
        return ((self.gain.mean(0) - 1.0) ** 2).sum() + (self.bias.mean(0) ** 2).sum()

    def step(self) -> None:
        for p in (self.gain, self.bias):
            if p.grad is not None:
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        if self.pin_mean:
            self.pin_mean_()

    @torch.no_grad()
    def pin_mean_(self) -> None:
        """Project the transforms onto {mean gain = 1, mean bias = 0} (per channel, over the
        panoramas): the gauge they share with the model's colours, fixed exactly. A penalty on the
        same distance (gauge(), × 10 until issue 39's fourth round) had to be stiff to hold it, and
        its gradient, common to every panorama, then dominated Adam's normalisation of the small
        per-panorama one: the relative exposures were learned several times slower."""
        self.gain.sub_(self.gain.mean(0) - 1.0)
        self.bias.sub_(self.bias.mean(0))

    def as_dict(self) -> dict[str, dict[str, list[float]]]:
        g, b = self.gain.detach(), self.bias.detach()
        return {n: {"gain": [round(float(x), 6) for x in g[i]], "bias": [round(float(x), 6) for x in b[i]]}
                for n, i in self.index.items()}

    # -- checkpoints: tensors and plain data only ---------------------------------
    def state_dict(self) -> dict:
        return {"names": list(self.names), "gain": self.gain.detach().clone(), "bias": self.bias.detach().clone(),
                "opt": self.opt.state_dict()}

    def load_state_dict(self, state: object) -> None:
        """Restore state_dict()'s output; ValueError (and nothing changed) when it is not one."""
        if not isinstance(state, dict) or set(state) != {"names", "gain", "bias", "opt"}:
            raise ValueError("checkpoint appearance must hold names, gain, bias, opt")
        if state["names"] != self.names:
            raise ValueError("checkpoint appearance covers other panoramas")
        for k in ("gain", "bias"):
            t = state[k]
            if not (isinstance(t, torch.Tensor) and t.shape == self.gain.shape and t.dtype == self.gain.dtype
                    and bool(torch.isfinite(t).all())):
                raise ValueError(f"checkpoint appearance {k} must be finite {self.gain.dtype} [{len(self.names)}, 3]")
        # checkpoints hold CPU tensors: back onto this model's device
        gain = state["gain"].to(self.gain.device, copy=True).requires_grad_(True)
        bias = state["bias"].to(self.gain.device, copy=True).requires_grad_(True)
        opt = torch.optim.Adam([gain, bias], lr=self.lr)
        try:
            opt.load_state_dict(state["opt"])
        except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as e:
            raise ValueError(f"checkpoint appearance optimiser state unusable ({type(e).__name__})") from None
        for group_state in opt.state.values():
            for v in group_state.values():
                if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all()):
                    raise ValueError("checkpoint appearance optimiser state is not finite")
                if isinstance(v, float) and not math.isfinite(v):
                    raise ValueError("checkpoint appearance optimiser state is not finite")
        self.gain, self.bias, self.opt = gain, bias, opt
