"""Adaptive density control of 3DGS: clone, split, prune, opacity reset, with a cap.

The view-space gradient that drives it is normalised to angle and to solid
angle (`gradient_scale`): the gradient of the loss with respect to the splat's
position in pixels (splatting's `means2d.grad`) times the camera's pixels per
radian (`camera.pixel_scale`), i.e. the gradient with respect to the splat's
angular position, then rescaled to the weight an equirectangular image's mean
loss gives one steradian near its equator. Doubling the resolution halves the
per-pixel gradient and doubles the pixels per radian, so a threshold means the
same at any resolution; and since a mean over a narrow crop weighs each
steradian more than a mean over the whole sphere (a 120° crop 1.6×, a 90° cube
face 4.9× at its centre), the second factor puts panoramas and perspective
crops on the same footing: the same splat with the same pixel errors gets the
same statistic in both. For an equirectangular camera the factor is exactly
the pixels per radian. Like the mean loss it is the gradient of, it weighs latitude θ by
1/cos θ per steradian (a per-steradian statistic was measured and lost: docs/training.md).

Layout Gaussians stay layout Gaussians: a split samples its children's
offsets in the plane (the offset's component along the plane normal is
removed), and children inherit `normals` and `u0`, so their displacement from
u0 starts in the plane and L_layout starts at 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gaussians.model import Gaussians
from gaussians.optim import Adam

__all__ = ["DensifyStats", "densify_and_prune", "reset_opacity", "quat_to_rotmat", "DensifyResult",
           "gradient_scale"]

#: The weight a mean loss over an equirectangular image gives one steradian near its equator:
#: 1 / (W·W/2 pixels) per pixel of (2π/W)² sr = 1 / (2π²), independent of W.
EQUIRECT_WEIGHT_PER_SR = 1.0 / (2.0 * math.pi**2)


def gradient_scale(camera) -> float:
    """Factor from ‖∂L/∂(splat centre in pixels)‖ of a view rendered with `camera` to the statistic
    the densification threshold applies to: × pixels per radian (an angular gradient) × the ratio of
    the equirectangular loss weight per steradian to this camera's at its image centre (a mean over
    H·W pixels of 1/s² sr each, s = pixels per radian). Equirectangular: exactly s."""
    s = float(camera.pixel_scale[0])
    weight_per_sr = s * s / (int(camera.width) * int(camera.height))
    return s * EQUIRECT_WEIGHT_PER_SR / weight_per_sr


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(w,x,y,z), any norm (zero -> identity) -> [N,3,3]."""
    n2 = (q * q).sum(-1, keepdim=True)
    q = q * torch.rsqrt(torch.clamp(n2, min=1e-24))
    q = torch.where(n2 > 1e-24, q, torch.tensor([1.0, 0, 0, 0], dtype=q.dtype, device=q.device))
    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
         2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
         2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return r.reshape(q.shape[:-1] + (3, 3))


@dataclass
class DensifyStats:
    """Per-Gaussian accumulators between densification steps (3DGS's xyz_gradient_accum, denom, max_radii2D)."""

    grad_accum: torch.Tensor  # [N] sum of normalised view-space gradient norms
    count: torch.Tensor  # [N] views in which the Gaussian was visible
    max_radius: torch.Tensor  # [N] largest screen radius seen, radians

    @classmethod
    def zeros(cls, n: int, dtype=torch.float32, device="cpu") -> DensifyStats:
        z = torch.zeros(n, dtype=dtype, device=device)
        return cls(z.clone(), z.clone(), z.clone())

    @torch.no_grad()
    def add(self, grad2d: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor, pixel_scale: float,
            grad_scale: float | None = None) -> None:
        """Accumulate one rendered view: `grad2d` = means2d.grad [N,2] (pixels), `radii` pixels,
        `pixel_scale` pixels per radian; `grad_scale` multiplies ‖grad2d‖ (default `pixel_scale`;
        the trainer passes `gradient_scale(camera)`)."""
        if grad2d is None:
            return
        scale = float(pixel_scale if grad_scale is None else grad_scale)
        if self._on_kernel():
            from splatting import densify_triton

            densify_triton.add_(grad2d, visible, radii, self.grad_accum, self.count, self.max_radius, scale,
                                float(pixel_scale))
            return
        g = torch.linalg.vector_norm(grad2d.to(self.grad_accum.dtype), dim=-1) * scale
        g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
        vis = visible & (radii > 0)
        self.grad_accum += torch.where(vis, g, torch.zeros_like(g))
        self.count += vis.to(self.count.dtype)
        r = radii.to(self.max_radius.dtype) / float(pixel_scale)
        self.max_radius = torch.where(vis, torch.maximum(self.max_radius, r), self.max_radius)

    def _on_kernel(self) -> bool:
        """One Triton launch instead of ~14 operations: where the training kernels run
        (splatting.devices.takes_kernels), with the accumulators contiguous."""
        from splatting.devices import takes_kernels

        return takes_kernels(self.grad_accum) and all(
            x.is_contiguous() for x in (self.grad_accum, self.count, self.max_radius))

    def mean_grad(self) -> torch.Tensor:
        return torch.where(self.count > 0, self.grad_accum / self.count.clamp_min(1), torch.zeros_like(self.count))

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum.clone(), "count": self.count.clone(),
                "max_radius": self.max_radius.clone()}

    @classmethod
    def from_state(cls, s: dict) -> DensifyStats:
        return cls(s["grad_accum"].clone(), s["count"].clone(), s["max_radius"].clone())

    def to(self, device) -> DensifyStats:
        return DensifyStats(self.grad_accum.to(device), self.count.to(device), self.max_radius.to(device))


@dataclass
class DensifyResult:
    gaussians: Gaussians
    cloned: int
    split: int
    pruned: int


def _select_capped(cand: torch.Tensor, score: torch.Tensor, budget: int) -> torch.Tensor:
    """Keep at most `budget` candidates (those with the highest score; ties by index)."""
    n = int(cand.sum())
    if n <= budget:
        return cand
    out = torch.zeros_like(cand)
    if budget <= 0:
        return out
    idx = torch.nonzero(cand, as_tuple=False).squeeze(1)
    # stable: sort by -score, index breaks ties, so the choice is deterministic
    order = torch.argsort(-score[idx], stable=True)
    out[idx[order[:budget]]] = True
    return out


@torch.no_grad()
def densify_and_prune(
    g: Gaussians,
    opt: Adam | None,
    stats: DensifyStats,
    *,
    grad_threshold: float,
    percent_dense: float,
    extent: float,
    min_opacity: float,
    max_world_scale: float | None = None,
    max_screen_radius: float | None = None,
    max_gaussians: int | None = None,
    split_children: int = 2,
    generator: torch.Generator | None = None,
) -> DensifyResult:
    """One 3DGS densification step. Returns new leaf tensors (requires_grad set
    like the input) and updates `opt`'s moments row for row.

    Clone: mean gradient ≥ threshold and max scale ≤ percent_dense·extent
    (a copy in place). Split: the same gradient and larger (`split_children`
    children drawn from the Gaussian itself, scales / (0.8·children); layout
    children offset within their plane). Prune: opacity < min_opacity, and
    (when given) max scale > max_world_scale (metres) or a screen radius larger
    than max_screen_radius (radians). `max_gaussians` caps the count after
    densification (highest-gradient candidates first); pruning then frees room.
    """
    req = g.means.requires_grad
    n0 = len(g)
    grads = stats.mean_grad()
    scales = torch.exp(g.log_scales.detach())
    smax = scales.max(dim=1).values
    big = smax > percent_dense * extent
    hot = grads >= grad_threshold
    clone = hot & ~big
    split = hot & big
    if max_gaussians is not None:
        budget = max(int(max_gaussians) - n0, 0)
        # a clone adds one Gaussian, a split children-1 (one with the default two)
        both = _select_capped(clone | split, grads, budget // max(split_children - 1, 1))
        clone, split = clone & both, split & both

    T = {k: v.detach() for k, v in g.tensors().items()}
    parts = [T]
    # -- clone: an exact copy (the next gradient steps pull the pair apart)
    c_idx = torch.nonzero(clone, as_tuple=False).squeeze(1)
    parts.append({k: v[c_idx] for k, v in T.items()})
    # -- split
    s_idx = torch.nonzero(split, as_tuple=False).squeeze(1)
    ns = s_idx.numel()
    if ns:
        k = split_children
        std = scales[s_idx].repeat(k, 1)
        # drawn on the generator's device (the CPU), so the stream is the same on every device
        noise = torch.randn(std.shape, generator=generator, dtype=std.dtype).to(std.device)
        local = noise * std
        rot = quat_to_rotmat(T["quats"][s_idx]).repeat(k, 1, 1)
        offset = (rot @ local[:, :, None]).squeeze(-1)
        lay = T["is_layout"][s_idx].repeat(k)
        nrm = T["normals"][s_idx].repeat(k, 1)
        nrm_u = nrm / torch.linalg.vector_norm(nrm, dim=-1, keepdim=True).clamp_min(1e-12)
        in_plane = offset - (offset * nrm_u).sum(-1, keepdim=True) * nrm_u
        offset = torch.where(lay[:, None], in_plane, offset)
        child = {kk: v[s_idx].repeat((k,) + (1,) * (v.ndim - 1)) for kk, v in T.items()}
        child["means"] = T["means"][s_idx].repeat(k, 1) + offset
        child["log_scales"] = torch.log(std / (0.8 * k))
        parts.append(child)
    merged = {k: torch.cat([p[k] for p in parts], 0) for k in T}
    n_new = merged["means"].shape[0] - n0
    if opt is not None:
        opt.append_rows(n_new)

    # -- prune: the split parents, then the transparent / oversized ones
    keep = torch.ones(merged["means"].shape[0], dtype=torch.bool, device=g.means.device)
    keep[s_idx] = False
    op = torch.sigmoid(merged["opacity_logits"])
    prune = op < min_opacity
    if max_world_scale is not None:
        prune |= torch.exp(merged["log_scales"]).max(dim=1).values > max_world_scale
    if max_screen_radius is not None:
        radius = torch.cat([stats.max_radius, stats.max_radius.new_zeros(n_new)])
        prune |= radius > max_screen_radius
    # never prune everything: a degenerate model cannot recover
    if bool((keep & ~prune).any()):
        keep &= ~prune
    pruned = int((~keep).sum()) - ns
    merged = {k: v[keep].contiguous() for k, v in merged.items()}
    if opt is not None:
        opt.keep_rows(keep)
    out = Gaussians(**merged, eps2d=g.eps2d)
    if req:
        out.requires_grad_(True)
    return DensifyResult(out, cloned=int(c_idx.numel()), split=ns, pruned=pruned)


@torch.no_grad()
def reset_opacity(g: Gaussians, opt: Adam | None, max_opacity: float = 0.01) -> None:
    """3DGS's periodic reset: opacities clamped to ≤ 0.01, their Adam moments zeroed."""
    cap = math.log(max_opacity / (1.0 - max_opacity))
    g.opacity_logits.clamp_(max=cap)
    if opt is not None:
        opt.reset("opacity_logits")

