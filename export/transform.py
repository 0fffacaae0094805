"""The y-down -> y-up conversion: a proper rotation of the world by 180° about x.

pano-pipe's world frame is OpenCV-like (x right, y down, z forward). Most viewers and
file formats (glTF, three.js, SPZ's RUB) are y up. Rotating by R = diag(1, -1, -1)
maps (x, y, z) -> (x, -y, -z): a rotation, not a mirror, so handedness, triangle
winding and every rendered image are preserved.

Per Gaussian:
  * means, normals, u0:   p -> R p
  * quaternion (w,x,y,z): q -> q_R q q_R⁻¹ = (w, x, -y, -z). This is R·Rot·Rᵀ rather than
    R·Rot; both give the same covariance R Σ Rᵀ because Rᵀ S² R = S² for the diagonal
    R and S, and this choice makes the conversion an exact involution (applied twice
    it returns the same numbers).
  * SH coefficients: exact, no degree is dropped. Every real SH basis function of the
    3DGS order is a polynomial in (x, y, z) with a definite parity in (y, z), so
    Y_k(R d) = s_k Y_k(d) with s_k = ±1 and the new coefficients are s_k c_k.
"""

from __future__ import annotations

import numpy as np
import torch

from gaussians.model import Gaussians

__all__ = ["Y_UP", "SH_SIGNS", "to_y_up", "y_up_points", "y_up_pose"]

#: The rotation (x, y, z) -> (x, -y, -z) as a 4×4 homogeneous matrix.
Y_UP = np.diag([1.0, -1.0, -1.0, 1.0])

#: Sign of each SH basis (3DGS order, bands 0..3) under (x, y, z) -> (x, -y, -z).
#: band 1: y, z, x; band 2: xy, yz, 3z²-1, xz, x²-y²;
#: band 3: y(3x²-y²), xyz, y(5z²-1), z(5z²-3), x(5z²-1), z(x²-y²), x(x²-3y²).
SH_SIGNS = (1,
            -1, -1, 1,
            -1, 1, 1, -1, 1,
            -1, 1, -1, -1, 1, -1, 1)


def y_up_points(p: np.ndarray) -> np.ndarray:
    """Points or vectors [..., 3] rotated into the y-up frame."""
    p = np.asarray(p)
    return p * np.array([1.0, -1.0, -1.0], dtype=p.dtype if p.dtype.kind == "f" else np.float64)


def y_up_pose(c2w: np.ndarray) -> np.ndarray:
    """A camera-to-world pose of the y-down world expressed in the y-up world (the camera
    moves with the world, so it sees exactly the same image)."""
    return Y_UP @ np.asarray(c2w, dtype=np.float64)


def to_y_up(g: Gaussians) -> Gaussians:
    """`g` rotated 180° about x (see the module doc). Returns a detached copy."""
    out = g.detach()
    flip = torch.tensor([1.0, -1.0, -1.0], dtype=g.means.dtype, device=g.means.device)
    out.means = out.means * flip
    out.normals = out.normals * flip
    out.u0 = out.u0 * flip
    out.quats = out.quats * torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=g.quats.dtype, device=g.quats.device)
    k = out.sh_rest.shape[1]
    if k:
        signs = torch.tensor(SH_SIGNS[1:k + 1], dtype=g.sh_rest.dtype, device=g.sh_rest.device)
        out.sh_rest = out.sh_rest * signs[None, :, None]
    return out
