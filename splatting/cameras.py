"""Cameras of the 360° splatting renderer.

Both cameras reduce to the same description used by the rasteriser:
  * a ray direction per pixel (``pixel_dirs``), in the OpenCV camera frame;
  * how a Gaussian's tangent plane is chosen (``equirect``: the plane touching the
    unit sphere at the Gaussian's own direction; ``pinhole``: the plane z = 1);
  * how tangent-plane units map to pixels (``pixel_scale``).

Conventions are those of DESIGN.md: x right, y down, z forward; longitude
phi = atan2(x, z), latitude theta = atan2(-y, hypot(x, z)); pixel centres at +0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["EquirectCamera", "PinholeCamera", "cubemap_faces", "CUBEMAP_FACE_NAMES", "CUBEMAP_FACE_AXES"]


@dataclass(frozen=True)
class EquirectCamera:
    """A full-sphere equirectangular camera, ``height`` × ``width`` pixels (usually W = 2H)."""

    height: int
    width: int

    kind = "equirect"

    def __post_init__(self):
        if int(self.height) < 1 or int(self.width) < 1:
            raise ValueError(f"EquirectCamera needs positive size, got {self.height}x{self.width}")

    @property
    def pixel_scale(self) -> tuple[float, float]:
        """Pixels per tangent-plane unit (one pixel = 2π/W radians), along e1 and e2."""
        s = self.width / (2.0 * math.pi)
        return (s, s)

    def pixel_dirs(self, dtype=torch.float32, device="cpu") -> torch.Tensor:
        """[H, W, 3] unit ray directions of the pixel centres."""
        H, W = int(self.height), int(self.width)
        phi = ((torch.arange(W, dtype=torch.float64) + 0.5) / W - 0.5) * (2.0 * math.pi)
        theta = (0.5 - (torch.arange(H, dtype=torch.float64) + 0.5) / H) * math.pi
        ct, st = torch.cos(theta)[:, None], torch.sin(theta)[:, None]
        sp, cp = torch.sin(phi)[None, :], torch.cos(phi)[None, :]
        d = torch.stack([ct * sp, (-st).expand(H, W), ct * cp], dim=-1)
        return d.to(dtype=dtype, device=device).contiguous()

    def dirs_to_pixels(self, dirs: torch.Tensor) -> torch.Tensor:
        """Continuous (col, row) [..., 2] of directions [..., 3] (DESIGN.md mapping)."""
        x, y, z = dirs.unbind(-1)
        phi = torch.atan2(x, z)
        theta = torch.atan2(-y, torch.sqrt(x * x + z * z))
        col = (phi / (2.0 * math.pi) + 0.5) * self.width - 0.5
        row = (0.5 - theta / math.pi) * self.height - 0.5
        return torch.stack([col, row], dim=-1)


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera (OpenCV intrinsics; the pixel with index (c, r) has its centre
    at image coordinates (c + 0.5, r + 0.5), as in gsplat / nerfstudio)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    kind = "pinhole"

    def __post_init__(self):
        if int(self.height) < 1 or int(self.width) < 1:
            raise ValueError(f"PinholeCamera needs positive size, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError("PinholeCamera needs positive focal lengths")

    @property
    def pixel_scale(self) -> tuple[float, float]:
        return (float(self.fx), float(self.fy))

    def pixel_dirs(self, dtype=torch.float32, device="cpu") -> torch.Tensor:
        """[H, W, 3] ray directions (x/z, y/z, 1) of the pixel centres (not unit length)."""
        H, W = int(self.height), int(self.width)
        xs = (torch.arange(W, dtype=torch.float64) + 0.5 - self.cx) / self.fx
        ys = (torch.arange(H, dtype=torch.float64) + 0.5 - self.cy) / self.fy
        d = torch.stack(
            [xs[None, :].expand(H, W), ys[:, None].expand(H, W), torch.ones(H, W, dtype=torch.float64)], dim=-1
        )
        return d.to(dtype=dtype, device=device).contiguous()


CUBEMAP_FACE_NAMES = ("front", "right", "back", "left", "up", "down")

# Rows are the face camera's x, y, z axes expressed in the panorama camera frame,
# so each 3x3 block is the camera-from-panorama rotation of that face.
CUBEMAP_FACE_AXES = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "right": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    "back": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
    "left": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),
    "up": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "down": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
}


def cubemap_faces(face_size: int, dtype=torch.float32, device="cpu"):
    """The six 90° cube faces: list of ``(viewmat, PinholeCamera)`` in the order
    front (+z), right (+x), back (−z), left (−x), up (−y), down (+y).

    ``viewmat`` is a 4×4 camera-from-panorama rotation: render a face of a panorama
    whose world-to-camera matrix is ``V`` with ``viewmat @ V``.
    """
    face_size = int(face_size)
    f = face_size / 2.0
    cam = PinholeCamera(fx=f, fy=f, cx=face_size / 2.0, cy=face_size / 2.0, width=face_size, height=face_size)
    out = []
    for name in CUBEMAP_FACE_NAMES:
        m = torch.eye(4, dtype=dtype, device=device)
        m[:3, :3] = torch.tensor(CUBEMAP_FACE_AXES[name], dtype=dtype, device=device)
        out.append((m, cam))
    return out
