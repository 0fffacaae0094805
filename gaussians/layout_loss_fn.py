"""The layout loss (gaussians.losses.layout_loss) of some rows of the model's means, with its
gradient in closed form: few device operations per training step.

For the selected rows i (K of them), with d = μ − u0, n̂ = n / max(‖n‖, 1e-12) and
r = sqrt(‖d‖² + eps²) (eps as in layout_loss: 0/0 at μ = u0 becomes 0 with a zero gradient):

    L = (1/K) Σ |c_i|,  c = n̂·d / r  (c = 0 where ‖d‖ ≤ the dead zone),
    ∂L/∂μ_i = sign(c_i) / (K r_i) · (n̂_i − c_i · d_i / r_i)

(computed with n̂/K in place of n̂, so that the mean and the 1/K come for free).

The forward computes both and scatters the gradient into a full-size [N,3] tensor, zero outside
the rows (where the training kernels run, one Triton launch: splatting/layout_triton.py); the
backward is one multiplication by the incoming gradient (no index backward, no chain of
elementwise backward operations). The rows, their anchors and unit normals change only
with densification: :class:`LayoutRows` keeps them (and eps as a tensor on their device).
"""

from __future__ import annotations

import torch

from gaussians.losses import LAYOUT_EPS
from splatting import layout_triton

__all__ = ["LayoutRows", "layout_loss_rows"]


class _LayoutLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means: torch.Tensor, idx: torch.Tensor, u0: torch.Tensor, nhat_k: torch.Tensor,
                eps_deadzone: torch.Tensor, deadzone: float) -> torch.Tensor:
        """`nhat_k`: the unit normals divided by K (the mean's 1/K folded in once); `eps_deadzone`:
        (eps, deadzone) as a tensor on the means' device (no host read), `deadzone` also as a number
        (the torch path's branch)."""
        if idx.shape[0] and _on_kernel(means, u0, nhat_k):
            value, full = layout_triton.layout_value_and_gradient(means, idx, u0, nhat_k, eps_deadzone)
            ctx.save_for_backward(full)
            return value
        full = torch.zeros_like(means, memory_format=torch.contiguous_format)
        if idx.shape[0] == 0:  # no row: 0, still attached to the graph, a zero gradient
            ctx.save_for_backward(full)
            return means.new_zeros(())
        d = means.index_select(0, idx) - u0
        length = torch.linalg.vector_norm(d, dim=-1, keepdim=True)
        r = torch.hypot(length, eps_deadzone[0])  # [K,1]
        e = d / r
        c = (e * nhat_k).sum(-1, keepdim=True)  # the cosines / K, [K,1]
        if deadzone > 0:  # a Python float: no branch on device values
            c = c * (length > deadzone)
        value = torch.linalg.vector_norm(c, ord=1)  # Σ|c|: the mean of the |cosines|
        # (n̂ − cos·e)/K, times sign/r; sign(0) = 0: the zero gradient where d ⟂ n̂ (and at μ = u0)
        rows = torch.addcmul(nhat_k, c, e, value=-1.0).mul_(torch.sign(c).div_(r))
        full.index_add_(0, idx, rows)  # (a repeated row gets the sum of its terms, as with autograd)
        ctx.save_for_backward(full)
        return value

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        (full,) = ctx.saved_tensors
        return full * grad, None, None, None, None, None


def _on_kernel(means: torch.Tensor, u0: torch.Tensor, nhat_k: torch.Tensor) -> bool:
    """One Triton launch instead of ~20 operations: where the training kernels run
    (splatting.devices.takes_kernels), with the layouts the kernel reads."""
    from splatting.devices import takes_kernels

    return takes_kernels(means) and means.stride(1) == 1 and u0.is_contiguous() and nhat_k.is_contiguous()


def layout_loss_rows(means: torch.Tensor, idx: torch.Tensor, u0: torch.Tensor, normals: torch.Tensor,
                     eps: float = LAYOUT_EPS, deadzone: float = 0.0) -> torch.Tensor:
    """layout_loss(means[idx], u0, normals, eps=eps, deadzone=deadzone) with the closed-form
    gradient (w.r.t. all of `means`, zero outside `idx`'s rows); no row -> 0, attached to the graph."""
    return LayoutRows(idx, u0, normals, eps, deadzone).loss(means)


class LayoutRows:
    """The layout Gaussians' rows `idx` with their anchors `u0` and plane normals `normals`
    ([K], [K,3], [K,3]; fixed between densifications), and the loss of a model's means."""

    def __init__(self, idx: torch.Tensor, u0: torch.Tensor, normals: torch.Tensor, eps: float = LAYOUT_EPS,
                 deadzone: float = 0.0):
        self.idx = idx
        self.deadzone = float(deadzone)
        self.u0 = u0
        nn = torch.linalg.vector_norm(normals, dim=-1, keepdim=True).clamp_min(1e-12)
        self.nhat_k = normals / (nn * max(int(idx.shape[0]), 1))
        self.eps_deadzone = torch.tensor([float(eps), self.deadzone], dtype=u0.dtype, device=u0.device)

    def __len__(self) -> int:
        return int(self.idx.shape[0])

    def loss(self, means: torch.Tensor) -> torch.Tensor:
        """L_layout of means[idx] (a 0-dim tensor; its gradient reaches `means` directly)."""
        return _LayoutLoss.apply(means, self.idx, self.u0, self.nhat_k, self.eps_deadzone, self.deadzone)
