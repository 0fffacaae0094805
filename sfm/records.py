"""What structure from motion takes and gives: panoramas in, poses and points out.

Apart from sfm/reconstruct.py, which runs pycolmap, so that the upright solvers and the poses
stage use these without importing pycolmap (a scene with every pose given never loads it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Method = Literal["rig", "equirect"]
METHODS: tuple[Method, ...] = ("rig", "equirect")


@dataclass
class Panorama:
    """One input: a name, its RGB pixels [H,W,3] uint8 at the working size, and where they may
    be used ([H,W] bool, or None for everywhere)."""

    name: str
    rgb: np.ndarray
    valid: np.ndarray | None = None


@dataclass
class SfmOptions:
    method: Method = "equirect"
    max_features: int = 4096
    #: Verified two-view matches needed for an image pair to count (COLMAP's default 15).
    min_matches: int = 15
    #: SIFT's contrast threshold; below COLMAP's 0.0067: indoor walls are low-contrast
    peak_threshold: float = 0.004
    threads: int = -1
    seed: int = 0


@dataclass
class Reconstruction:
    """What SfM found, in its own frame."""

    #: view name -> camera-from-world 4x4 (OpenCV axes), only for registered views
    cam_from_world: dict[str, np.ndarray]
    #: view name -> mean reprojection error (pixels of the working panorama) and observations
    reprojection_error: dict[str, float]
    observations: dict[str, int]
    points: np.ndarray  # [N,3]
    colors: np.ndarray  # [N,3] uint8
    #: [N] number of distinct panoramas observing each point
    track_length: np.ndarray
    #: image pairs with verified matches (virtual views of a rig counted per panorama pair)
    verified_pairs: int
    models: int = 1
    timings: dict[str, float] = field(default_factory=dict)
    #: view name -> indices of the points it observes; empty when not recorded (then every
    #: registered view is taken to see every point, as for a two-view solve)
    seen_by: dict[str, np.ndarray] = field(default_factory=dict)


#: The steps `reconstruct` reports to its `progress` callback as each one ends.
STEPS = ("views", "features", "matching", "mapping")
