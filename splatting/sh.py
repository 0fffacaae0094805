"""Real spherical harmonics, degrees 0-3, with the constants and sign
conventions of the original 3D Gaussian Splatting code (and gsplat/nerfstudio)."""

from __future__ import annotations

import torch

__all__ = ["eval_sh", "num_sh_bases"]

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (0..3): (degree + 1)²."""
    if not 0 <= int(degree) <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (int(degree) + 1) ** 2


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH: ``coeffs`` [..., K, C] (K ≥ (degree+1)²), ``dirs`` [..., 3]
    (normalised here; a zero direction gives the degree-0 term only) -> [..., C].

    No +0.5 offset is applied (the renderer adds 0.5 and clamps at 0, as 3DGS does).
    """
    n = num_sh_bases(degree)
    if coeffs.shape[-2] < n:
        raise ValueError(f"SH degree {degree} needs {n} coefficients, got {coeffs.shape[-2]}")
    result = C0 * coeffs[..., 0, :]
    if degree == 0:
        return result
    r2 = (dirs * dirs).sum(-1, keepdim=True)
    dirs = dirs * torch.rsqrt(torch.clamp(r2, min=1e-30))
    x, y, z = (dirs[..., i : i + 1] for i in range(3))
    result = result - C1 * y * coeffs[..., 1, :] + C1 * z * coeffs[..., 2, :] - C1 * x * coeffs[..., 3, :]
    if degree == 1:
        return result
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    result = (
        result
        + C2[0] * xy * coeffs[..., 4, :]
        + C2[1] * yz * coeffs[..., 5, :]
        + C2[2] * (2.0 * zz - xx - yy) * coeffs[..., 6, :]
        + C2[3] * xz * coeffs[..., 7, :]
        + C2[4] * (xx - yy) * coeffs[..., 8, :]
    )
    if degree == 2:
        return result
    result = (
        result
        + C3[0] * y * (3 * xx - yy) * coeffs[..., 9, :]
        + C3[1] * xy * z * coeffs[..., 10, :]
        + C3[2] * y * (4 * zz - xx - yy) * coeffs[..., 11, :]
        + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[..., 12, :]
        + C3[4] * x * (4 * zz - xx - yy) * coeffs[..., 13, :]
        + C3[5] * z * (xx - yy) * coeffs[..., 14, :]
        + C3[6] * x * (xx - 3 * yy) * coeffs[..., 15, :]
    )
    return result
