"""Adam over the Gaussians' tensors, with the row surgery densification needs,
and the 3DGS position learning-rate schedule.

A small hand-written Adam (the update of torch.optim.Adam, eps 1e-15 as in
3DGS) because densification appends and removes rows of every parameter and
its moments; keeping them in one plain dict also makes checkpoints trivial.
"""

from __future__ import annotations

import math

import torch

from gaussians.model import PARAM_NAMES, Gaussians

__all__ = ["Adam", "expon_lr"]


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """3DGS's log-linear decay from lr_init (step 0) to lr_final (step max_steps), then constant."""
    if lr_init == lr_final or max_steps <= 0:
        return lr_init
    t = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)


class Adam:
    """Adam over Gaussians' PARAM_NAMES tensors, one learning rate per tensor."""

    def __init__(self, lrs: dict[str, float], betas=(0.9, 0.999), eps: float = 1e-15):
        unknown = set(lrs) - set(PARAM_NAMES)
        if unknown:
            raise ValueError(f"unknown parameters {sorted(unknown)}")
        self.lrs = dict(lrs)
        self.betas = betas
        self.eps = eps
        self.step_count = 0
        self.exp_avg: dict[str, torch.Tensor] = {}
        self.exp_avg_sq: dict[str, torch.Tensor] = {}
        #: the fused kernel's step count, one float32 0-dim tensor per device, always equal to
        #: step_count (derived from it: rebuilt after a load or a move, refilled at each step)
        self._steps: dict[torch.device, torch.Tensor] = {}
        self._ones: dict[torch.device, torch.Tensor] = {}

    def _step_tensor(self, device: torch.device) -> torch.Tensor:
        t = self._steps.get(device)
        if t is None:
            t = self._steps[device] = torch.full((), float(self.step_count), dtype=torch.float32, device=device)
        return t

    def _init_state(self, g: Gaussians) -> None:
        for k in self.lrs:
            p = getattr(g, k)
            if k not in self.exp_avg or self.exp_avg[k].shape != p.shape:
                self.exp_avg[k] = torch.zeros_like(p.detach())
                self.exp_avg_sq[k] = torch.zeros_like(p.detach())

    @torch.no_grad()
    def step(self, g: Gaussians) -> torch.Tensor:
        """One update of every parameter of `g` that has a gradient. A gradient value that is not
        finite is taken as 0; returns a 0-dim float32 tensor on the parameters' device, 1.0 when
        some was (a tensor: reading it would wait for a GPU)."""
        self._init_state(g)
        self.step_count += 1
        items = []  # (parameter, gradient, moments, lr)
        for k, lr in self.lrs.items():
            p = getattr(g, k)
            if p.grad is not None:  # as torch.optim.Adam: no gradient, no update (SH bands not yet in use)
                items.append((p, p.grad, self.exp_avg[k], self.exp_avg_sq[k], lr))
        if not items:
            return torch.zeros((), dtype=torch.float32)
        found = torch.zeros((), dtype=torch.float32, device=items[0][0].device)
        if _one_launch_ok(items):
            # every tensor, the finite check and the zeroing in one launch (splatting/adam_triton.py)
            from splatting import adam_triton

            adam_triton.step_([(p.detach(), gr, m, v, lr) for p, gr, m, v, lr in items], self.step_count,
                              self.betas, self.eps, found)
            return found
        grads = [gr for _, gr, _, _, _ in items if gr.numel()]
        if grads:
            # one multi-tensor pass for the flag (AMP's check-and-unscale by 1.0: values unchanged)
            torch._amp_foreach_non_finite_check_and_unscale_(grads, found, self._one(found.device))
            # on the CPU reading the flag costs nothing, and saves a pass over every gradient
            if found.device.type != "cpu" or bool(found):
                for gr in grads:
                    torch.nan_to_num_(gr, nan=0.0, posinf=0.0, neginf=0.0)
        b1, b2 = self.betas
        refilled: set[torch.device] = set()
        for p, grad, m, v, lr in items:
            if _fused_ok(p, grad, m, v):
                # torch's fused Adam kernel, called directly: one pass over the parameter, its
                # gradient and both moments, one launch per tensor (each has its own lr). The
                # kernel reads the step (this update's t, bias corrections 1 − β^t) from a
                # tensor: one per device, set once per step, not one made per tensor.
                steps = self._step_tensor(p.device)
                if p.device not in refilled:
                    steps.fill_(float(self.step_count))
                    refilled.add(p.device)
                torch._fused_adam_([p], [grad], [m], [v], [], [steps], lr=lr, beta1=b1, beta2=b2,
                                   weight_decay=0.0, eps=self.eps, amsgrad=False, maximize=False,
                                   grad_scale=None, found_inf=None)
                continue
            bc1 = 1.0 - b1**self.step_count
            bc2 = 1.0 - b2**self.step_count
            m.mul_(b1).add_(grad, alpha=1.0 - b1)
            v.mul_(b2).addcmul_(grad, grad, value=1.0 - b2)
            denom = (v.sqrt() / math.sqrt(bc2)).add_(self.eps)
            p.addcdiv_(m, denom, value=-lr / bc1)
        return found

    def _one(self, device: torch.device) -> torch.Tensor:
        """A float32 1.0 on `device`, made once (the finite check's unscale factor)."""
        t = self._ones.get(device)
        if t is None:
            t = self._ones[device] = torch.ones((), dtype=torch.float32, device=device)
        return t

    @staticmethod
    def zero_grad(g: Gaussians) -> None:
        for k in PARAM_NAMES:
            getattr(g, k).grad = None

    # -- row surgery (densification) ---------------------------------------
    def keep_rows(self, keep: torch.Tensor) -> None:
        """Drop the moments of pruned Gaussians (`keep`: bool mask over the current rows)."""
        for d in (self.exp_avg, self.exp_avg_sq):
            for k in d:
                d[k] = d[k][keep].contiguous()

    def append_rows(self, count: int) -> None:
        """New Gaussians start with zero moments (as in 3DGS)."""
        for d in (self.exp_avg, self.exp_avg_sq):
            for k in d:
                z = d[k].new_zeros((count,) + tuple(d[k].shape[1:]))
                d[k] = torch.cat([d[k], z], 0)

    def reset(self, name: str) -> None:
        """Zero the moments of one tensor (3DGS does this when it resets opacities)."""
        if name in self.exp_avg:
            self.exp_avg[name].zero_()
            self.exp_avg_sq[name].zero_()

    def to(self, device) -> Adam:
        """Move the moments to `device` (a checkpoint's are on the CPU); returns self."""
        for d in (self.exp_avg, self.exp_avg_sq):
            for k in d:
                d[k] = d[k].to(device)
        self._steps = {}
        return self

    # -- checkpoints --------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "lrs": dict(self.lrs), "betas": self.betas, "eps": self.eps, "step_count": self.step_count,
            "exp_avg": {k: v.clone() for k, v in self.exp_avg.items()},
            "exp_avg_sq": {k: v.clone() for k, v in self.exp_avg_sq.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore state_dict()'s output. Raises ValueError, leaving the optimiser unchanged,
        when `state` is not one (a checkpoint file is untrusted input)."""
        keys = ("lrs", "betas", "eps", "step_count", "exp_avg", "exp_avg_sq")
        if not isinstance(state, dict) or not set(keys) <= set(state):
            raise ValueError(f"optimiser state must hold {', '.join(keys)}")
        lrs, betas, eps, steps = state["lrs"], state["betas"], state["eps"], state["step_count"]
        if not isinstance(lrs, dict) or not set(lrs) <= set(PARAM_NAMES) or \
                not all(_real(x) for x in lrs.values()):
            raise ValueError(f"optimiser lrs must map some of {', '.join(PARAM_NAMES)} to numbers")
        if not isinstance(betas, list | tuple) or len(betas) != 2 or not all(_real(b) for b in betas):
            raise ValueError("optimiser betas must be two numbers")
        if not _real(eps) or not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
            raise ValueError("optimiser eps must be a number and step_count an integer >= 0")
        m, v = state["exp_avg"], state["exp_avg_sq"]
        if not isinstance(m, dict) or not isinstance(v, dict) or set(m) != set(v) or not set(m) <= set(lrs):
            raise ValueError("optimiser moments must be two dicts over the same parameters")
        for k in m:
            if not (_tensor(m[k]) and _tensor(v[k]) and m[k].shape == v[k].shape
                    and m[k].dtype == v[k].dtype):
                raise ValueError(f"optimiser moments of {k} must be two floating tensors of one shape")
        self.lrs = {k: float(x) for k, x in lrs.items()}
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self.step_count = int(steps)
        self.exp_avg = {k: x.clone() for k, x in m.items()}
        self.exp_avg_sq = {k: x.clone() for k, x in v.items()}
        self._steps = {}


def _fused_ok(p: torch.Tensor, *others: torch.Tensor) -> bool:
    """Whether torch's fused Adam kernel takes `p` with its gradient and moments `others` (CPU
    and CUDA floating tensors, contiguous, all of one dtype and device)."""
    return p.device.type in ("cpu", "cuda") and p.dtype in (torch.float32, torch.float64) and p.is_contiguous() \
        and all(t.dtype == p.dtype and t.device == p.device and t.is_contiguous() for t in others)


def _one_launch_ok(items) -> bool:
    """Whether one Triton launch takes every (parameter, gradient, moments, lr) of `items`: where
    the training kernels run (splatting.devices.takes_kernels), all contiguous, of one floating
    dtype and device."""
    from splatting.devices import takes_kernels

    p0 = items[0][0]
    return takes_kernels(p0) and p0.dtype in (torch.float32, torch.float64) \
        and all(_fused_ok(p0, p, gr, m, v) for p, gr, m, v, _ in items)


def _real(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _tensor(x: object) -> bool:
    return isinstance(x, torch.Tensor) and x.layout == torch.strided and x.is_floating_point()
