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

__all__ = ["EquirectCamera", "PinholeCamera", "PerspectiveRig", "crop_rig", "cubemap_rig", "cubemap_faces",
           "CUBEMAP_FACE_NAMES", "CUBEMAP_FACE_AXES", "PAPER_CROPS"]


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


@dataclass(frozen=True)
class PerspectiveRig:
    """Square pinhole crops sharing the panorama's centre: the cameras of the perspective
    ("3D-GS") baseline, whose renders :func:`splatting.render_stitched` blends back into a panorama.

    ``axes[i]`` holds crop i's x, y, z axes in the panorama camera frame (the rows of its
    camera-from-panorama rotation); every crop is ``size`` × ``size`` pixels with a ``fov_deg``
    field of view across (and down) the image. Hashable, so stitch tables can be cached per rig.
    """

    size: int
    fov_deg: float
    axes: tuple[tuple[tuple[float, float, float], ...], ...]
    names: tuple[str, ...]

    def __post_init__(self):
        if int(self.size) < 2:
            raise ValueError(f"crops need at least 2x2 pixels, got {self.size}")
        if not 0.0 < float(self.fov_deg) < 180.0:
            raise ValueError(f"a pinhole crop's field of view must be in (0, 180) degrees, got {self.fov_deg}")
        if not self.axes or len(self.axes) != len(self.names):
            raise ValueError("a rig needs at least one crop and one name per crop")

    def __len__(self) -> int:
        return len(self.axes)

    @property
    def camera(self) -> PinholeCamera:
        """The crops' shared intrinsics (principal point at the image centre)."""
        s = int(self.size)
        f = s / (2.0 * self.tan_half_fov)
        return PinholeCamera(fx=f, fy=f, cx=s / 2.0, cy=s / 2.0, width=s, height=s)

    @property
    def tan_half_fov(self) -> float:
        """Half the image-plane extent of a crop (exactly 1 for the cube's 90°)."""
        return 1.0 if float(self.fov_deg) == 90.0 else math.tan(math.radians(self.fov_deg) / 2.0)

    def rotations(self, dtype=torch.float64, device="cpu") -> torch.Tensor:
        """[K, 3, 3] camera-from-panorama rotations."""
        return torch.tensor(self.axes, dtype=dtype, device=device)

    def crops(self, dtype=torch.float32, device="cpu") -> list[tuple[torch.Tensor, PinholeCamera]]:
        """``(viewmat, camera)`` per crop; ``viewmat`` is a 4×4 camera-from-panorama rotation: render a
        crop of a panorama whose world-to-camera matrix is ``V`` with ``viewmat @ V``."""
        cam = self.camera
        out = []
        for rot in self.rotations(dtype, device):
            m = torch.eye(4, dtype=dtype, device=device)
            m[:3, :3] = rot
            out.append((m, cam))
        return out


#: The paper's perspective baseline (Bai et al., §4): eight crops with a 120° field of view at
#: elevations −45°, 0° and 45°, read as 2 + 4 + 2 crops (docs/training.md says why).
PAPER_CROPS = {"fov_deg": 120.0, "elevations": (-45.0, 0.0, 45.0), "counts": (2, 4, 2)}


def _cos_sin_deg(deg: float) -> tuple[float, float]:
    """cos and sin of an angle in degrees, exact at multiples of 90° (so the cube faces come out
    as exact axis permutations)."""
    q, r = divmod(float(deg), 90.0)
    if r == 0.0:
        return ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))[int(q) % 4]
    a = math.radians(deg)
    return math.cos(a), math.sin(a)


def crop_rig(size: int, fov_deg: float = PAPER_CROPS["fov_deg"],
             elevations: tuple[float, ...] = PAPER_CROPS["elevations"],
             counts: tuple[int, ...] = PAPER_CROPS["counts"], names: tuple[str, ...] | None = None
             ) -> PerspectiveRig:
    """Rings of crops: ``counts[k]`` crops at elevation ``elevations[k]`` (degrees, up positive),
    their yaws evenly spread from 0 (0°, 360°/n, ...; yaw = longitude of the crop's centre), each
    crop level (its x axis horizontal). Ordered ring by ring, yaw increasing. The default is the
    paper's 2 + 4 + 2 crops of 120°; ``crop_rig(s, 90, (0, 90, -90), (4, 1, 1))`` is the cubemap."""
    if len(elevations) != len(counts) or not elevations:
        raise ValueError(f"one crop count per elevation, got elevations {list(elevations)}, counts {list(counts)}")
    axes, auto_names = [], []
    for elev, n in zip(elevations, counts):
        if not -90.0 <= float(elev) <= 90.0:
            raise ValueError(f"crop elevations must lie in [-90, 90] degrees, got {elev}")
        if int(n) < 1:
            raise ValueError(f"every elevation needs at least one crop, got {n}")
        ce, se = _cos_sin_deg(elev)
        for j in range(int(n)):
            yaw = 360.0 * j / int(n)
            cy, sy = _cos_sin_deg(yaw)
            z = (ce * sy, -se, ce * cy)  # the crop's viewing direction (DESIGN.md angles)
            x = (cy, 0.0, -sy)  # horizontal, to the right of z
            y = (z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0])  # z × x
            axes.append((x, y, z))
            auto_names.append(f"el{float(elev):+g}_yaw{yaw:g}")
    return PerspectiveRig(int(size), float(fov_deg), tuple(axes), tuple(names) if names else tuple(auto_names))


def cubemap_rig(face_size: int) -> PerspectiveRig:
    """The six 90° cube faces as a rig: front (+z), right (+x), back (−z), left (−x), up (−y), down (+y)."""
    return crop_rig(face_size, 90.0, (0.0, 90.0, -90.0), (4, 1, 1), names=CUBEMAP_FACE_NAMES)


def cubemap_faces(face_size: int, dtype=torch.float32, device="cpu"):
    """The six 90° cube faces: list of ``(viewmat, PinholeCamera)`` in the order
    front (+z), right (+x), back (−z), left (−x), up (−y), down (+y).

    ``viewmat`` is a 4×4 camera-from-panorama rotation: render a face of a panorama
    whose world-to-camera matrix is ``V`` with ``viewmat @ V``.
    """
    return cubemap_rig(int(face_size)).crops(dtype, device)
