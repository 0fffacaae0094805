"""A panorama seen as a rig of perspective virtual cameras sharing its centre.

SIFT was made for perspective images: on an equirectangular image the
distortion away from the horizon changes a feature's shape from one panorama
to the next, and its descriptors stop matching. COLMAP's own panorama example
therefore resamples each panorama into pinhole views with known rotations and
reconstructs them as a rig; this module does that resampling in pano-pipe's
pixel convention (DESIGN.md: pixel centres at +0.5, image centre along +z).

Each panorama pixel is assigned to exactly one virtual camera (the one whose
axis is closest to it): the views overlap, but a feature is extracted once.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from panogeom.equirect import angles_to_pixel, dirs_to_angles

#: Pitches of the rings of virtual cameras (degrees, up positive); the first camera of the
#: first ring looks along the panorama's +z, so the rig's reference camera IS the panorama.
RING_PITCHES_DEG = (0.0, -35.0, 35.0)
YAW_STEPS = 4
FOV_DEG = 90.0


def rotation_about_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_about_y(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass(frozen=True)
class VirtualRig:
    """Virtual pinhole cameras for panoramas of `pano_height` x 2`pano_height` pixels."""

    pano_height: int
    yaw_steps: int = YAW_STEPS
    pitches_deg: tuple[float, ...] = RING_PITCHES_DEG
    fov_deg: float = FOV_DEG

    @property
    def pano_width(self) -> int:
        return 2 * self.pano_height

    @cached_property
    def pano_from_cams(self) -> list[np.ndarray]:
        """Rotation of each virtual camera into the panorama frame; index 0 is the identity.
        Rings above and below the horizon are offset by half a yaw step, so their axes fill the
        gaps between the horizon ring's."""
        out = []
        for ring, pitch in enumerate(self.pitches_deg):
            offset = 0.5 if ring > 0 else 0.0
            for k in range(self.yaw_steps):
                yaw = 360.0 * (k + offset) / self.yaw_steps
                # rotation_about_x(pitch) tilts +z towards -y: a positive pitch looks up
                out.append(rotation_about_y(yaw) @ rotation_about_x(pitch))
        return out

    @property
    def focal(self) -> float:
        """Pixels per radian at a virtual image's centre equal the panorama's (W / 2 pi): the
        views neither blur nor invent detail there."""
        return self.pano_width / (2.0 * np.pi)

    @property
    def size(self) -> int:
        return int(round(2.0 * self.focal * np.tan(np.radians(self.fov_deg) / 2.0)))

    @cached_property
    def _camera_rays(self) -> np.ndarray:
        """[S,S,3] rays of the virtual pixels (centres at +0.5, COLMAP's and OpenCV's convention)."""
        s = self.size
        c = (np.arange(s) + 0.5 - s / 2.0) / self.focal
        x, y = np.meshgrid(c, c)
        return np.stack([x, y, np.ones_like(x)], axis=-1)

    @cached_property
    def _maps(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per virtual camera: the panorama pixel each of its pixels samples (x, y maps for
        cv2.remap) and which of its pixels it owns (closest axis)."""
        axes = np.stack([r[:, 2] for r in self.pano_from_cams])  # [K,3] camera axes in the panorama
        maps = []
        for k, rot in enumerate(self.pano_from_cams):
            rays = self._camera_rays @ rot.T
            phi, theta = dirs_to_angles(rays)
            col, row = angles_to_pixel(phi, theta, self.pano_height, self.pano_width)
            unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
            owned = np.argmax(unit @ axes.T, axis=-1) == k
            maps.append((col.astype(np.float32), row.astype(np.float32), owned))
        return maps

    def render(self, pano: np.ndarray, valid: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """The virtual views of `pano` [H,W,C] as (image, mask uint8 255 = use) pairs; `valid`
        [H,W] bool leaves masked panorama pixels (tripod, per-view masks) out of every mask."""
        if pano.shape[:2] != (self.pano_height, self.pano_width):
            raise ValueError(f"panorama is {pano.shape[1]}x{pano.shape[0]}, rig made for "
                             f"{self.pano_width}x{self.pano_height}")
        views = []
        for col, row, owned in self._maps:
            image = cv2.remap(pano, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            keep = owned
            if valid is not None:
                keep = owned & (cv2.remap(valid.astype(np.uint8), col, row, cv2.INTER_NEAREST,
                                          borderMode=cv2.BORDER_WRAP) > 0)
            views.append((image, keep.astype(np.uint8) * 255))
        return views
