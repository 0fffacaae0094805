"""The metric scale of poses that have none, from the rooms the layout stage found.

When the poses stage finds neither a floor plane nor a floor–wall boundary it keeps the poses up
to scale (PosesOutput.scale_source "none"). The layout stage then knows, for every view, its room
in metres (the layout's floor polygon, made metric by the camera height); the poses stage's sparse
points are in the poses' unit. Along the azimuth of a point a view observes, the room's wall lies
D metres away; the point lies d units away horizontally. For the points on the walls D / d is the
scale (metres per unit); points on furniture or seen through a doorway give other ratios, each
its own. The scale is the ratio most points agree on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: Points seen more than this far above or below the horizon are left out (ceiling, floor).
MAX_ELEVATION_DEG = 45.0
#: Ratios within this relative distance of each other agree.
AGREE = 0.02
#: The scale's relative uncertainty is at least this: a layout's walls are no better placed.
MIN_UNCERTAINTY = 0.005
#: The scale needs this many agreeing points, and this share of the points that voted.
MIN_VOTES = 30
MIN_SHARE = 0.1


@dataclass
class RoomScale:
    scale: float  # metres per unit of the poses
    uncertainty: float  # relative standard uncertainty
    votes: int  # points whose ratio agrees with the scale
    points: int  # points that voted


def wall_distance(polygon: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """[M] distance from the origin to the nearest edge of `polygon` [K,2] (x, z) along each
    azimuth (direction (sin a, cos a)); inf where a ray meets no edge."""
    a = np.asarray(polygon, float)
    b = np.roll(a, -1, axis=0)
    d = np.stack([np.sin(azimuth), np.cos(azimuth)], axis=1)  # [M,2]
    e = b - a  # [K,2]
    # origin + t d = a + u e: solve per ray and edge (2x2, Cramer)
    den = d[:, None, 0] * (-e[None, :, 1]) - d[:, None, 1] * (-e[None, :, 0])
    t = (a[None, :, 0] * (-e[None, :, 1]) - a[None, :, 1] * (-e[None, :, 0])) / np.where(den == 0, np.nan, den)
    u = (d[:, None, 0] * a[None, :, 1] - d[:, None, 1] * a[None, :, 0]) / np.where(den == 0, np.nan, den)
    hit = (t > 0) & (u >= 0) & (u <= 1)
    return np.where(hit, t, np.inf).min(axis=1)


def scale_from_rooms(views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> RoomScale | None:
    """The metres per unit of the poses from (camera-to-world pose in the poses' unit, room polygon
    [K,2] in metres in the camera frame, [M,3] world points the view observes) per view; None when
    too few points agree on one ratio."""
    logs = []
    for pose, polygon, points in views:
        pose = np.asarray(pose, float)
        rel = (np.asarray(points, float).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]  # camera frame
        horizontal = np.hypot(rel[:, 0], rel[:, 2])
        keep = (horizontal > 0) & (np.abs(np.degrees(np.arctan2(-rel[:, 1], horizontal))) < MAX_ELEVATION_DEG)
        if not keep.any() or len(polygon) < 3:
            continue
        walls = wall_distance(np.asarray(polygon, float), np.arctan2(rel[keep, 0], rel[keep, 2]))
        ok = np.isfinite(walls)
        logs.append(np.log(walls[ok] / horizontal[keep][ok]))
    if not logs:
        return None
    ratios = np.sort(np.concatenate(logs))
    if len(ratios) < MIN_VOTES:
        return None
    # the window of width 2 AGREE holding the most ratios, then the median inside it
    window = np.log1p(AGREE)
    ends = np.searchsorted(ratios, ratios + 2 * window)
    start = int(np.argmax(ends - np.arange(len(ratios))))
    inside = ratios[start:ends[start]]
    if len(inside) < max(MIN_VOTES, MIN_SHARE * len(ratios)):
        return None
    centre = float(np.median(inside))
    spread = 1.4826 * float(np.median(np.abs(inside - centre)))
    return RoomScale(float(np.exp(centre)), max(spread / np.sqrt(len(inside)), MIN_UNCERTAINTY), len(inside),
                     len(ratios))
