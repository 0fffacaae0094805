"""Supplied layouts: HorizonNet JSON, PanoContext/Stanford corner text files and
[2,W] latitude arrays, read into one form (docs/layout.md, "Formats").

Angles follow DESIGN.md: longitude phi, latitude theta (up positive). Bad files
raise PanoError naming the file and the problem, in one line.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from runfs.errors import PanoError
from runfs.limits import load_npy

#: HorizonNet's JSON stores corners normalised by the size it infers at.
HORIZONNET_W, HORIZONNET_H = 1024, 512

__all__ = [
    "SuppliedLayout",
    "read_layout",
    "read_horizonnet_json",
    "read_corner_txt",
    "read_boundaries_npy",
    "horizonnet_json",
    "pixel_to_angles",
]


@dataclass
class SuppliedLayout:
    kind: Literal["json", "txt", "npy"]
    #: [2,W] latitudes (ceiling, floor) for .npy; None for corner formats.
    boundaries: np.ndarray | None = None
    #: [K,3] corners (phi, ceiling latitude, floor latitude), in the file's order.
    corners: np.ndarray | None = None
    #: Ceiling distance / camera height where the file fixes it (JSON z0 / -z1).
    ceiling_ratio: float | None = None


def pixel_to_angles(x, y, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (centres at integers) → (phi, theta): DESIGN.md's mapping,
    which is also HorizonNet's coorx2u / coory2v."""
    phi = ((np.asarray(x, dtype=np.float64) + 0.5) / width - 0.5) * 2 * np.pi
    theta = -((np.asarray(y, dtype=np.float64) + 0.5) / height - 0.5) * np.pi
    return phi, theta


def _pairs_to_corners(path: Path, xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """Consecutive (ceiling, floor) pixel pairs → [K,3] corners sorted by phi."""
    if len(xy) % 2:
        raise PanoError(path, f"expected (ceiling, floor) pairs of points, got an odd count ({len(xy)})")
    if len(xy) < 6:
        raise PanoError(path, f"a room needs at least 3 corners (6 points), got {len(xy)} points")
    pairs = xy.reshape(-1, 2, 2)
    # Within a pair the ceiling point is the upper one (smaller row).
    top = np.where(pairs[:, 0, 1] <= pairs[:, 1, 1], 0, 1)
    ceil = pairs[np.arange(len(pairs)), top]
    floor = pairs[np.arange(len(pairs)), 1 - top]
    phi_c, th_c = pixel_to_angles(ceil[:, 0], ceil[:, 1], width, height)
    phi_f, th_f = pixel_to_angles(floor[:, 0], floor[:, 1], width, height)
    bad = np.flatnonzero((th_c <= 0) | (th_f >= 0))
    if bad.size:
        j = int(bad[0])
        raise PanoError(
            path,
            f"corner {j + 1}: the ceiling point must lie above the horizon and the floor point below it "
            f"(rows {ceil[j, 1]:.4g} and {floor[j, 1]:.4g} of {height})",
        )
    # A corner's ceiling and floor points share a column up to labelling noise:
    # their circular mean (written so that equal columns give exactly phi_c).
    phi = phi_c + 0.5 * np.angle(np.exp(1j * (phi_f - phi_c)))
    # Kept in file order: HorizonNet and the simulator write corners in wall order.
    return np.stack([phi, th_c, th_f], axis=1)


def read_horizonnet_json(path: Path, width: int = HORIZONNET_W, height: int = HORIZONNET_H) -> SuppliedLayout:
    """HorizonNet's inference output: {"z0": ceiling z, "z1": floor z, "uv": [[u, v], ...]}
    with u, v the corners' pixel coordinates (centres at integers) divided by the
    panorama's width and height (1024 x 512 where HorizonNet made it), in
    (ceiling, floor) pairs. z0/-z1 is the ceiling distance over the camera height."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise PanoError(path, f"not valid JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except RecursionError:
        raise PanoError(path, "JSON nested too deeply") from None
    except (OSError, UnicodeDecodeError) as e:
        raise PanoError(path, f"cannot read: {e}") from None
    if not isinstance(data, dict) or "uv" not in data:
        raise PanoError(path, 'expected HorizonNet layout JSON {"z0", "z1", "uv": [[u, v], ...]}')
    try:
        uv = np.asarray(data["uv"], dtype=np.float64)
    except (TypeError, ValueError):
        raise PanoError(path, '"uv" must be a list of [u, v] number pairs') from None
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise PanoError(path, f'"uv" must be a list of [u, v] pairs, got shape {list(uv.shape)}')
    if not np.all(np.isfinite(uv)) or uv.min() < 0 or uv.max() > 1:
        raise PanoError(path, '"uv" values must be finite and normalised to [0, 1]')
    ratio = None
    if "z0" in data or "z1" in data:
        try:
            z0, z1 = float(data["z0"]), float(data["z1"])
        except (KeyError, TypeError, ValueError):
            raise PanoError(path, '"z0" and "z1" must both be numbers') from None
        if not (z0 > 0 > z1) or not np.isfinite(z0 + z1):
            raise PanoError(
                path, f'expected "z0" > 0 (ceiling) and "z1" < 0 (floor), got z0={z0:g}, z1={z1:g}'
            )
        ratio = z0 / -z1
    xy = uv * np.array([width, height])
    corners = _pairs_to_corners(path, xy, width, height)
    return SuppliedLayout("json", corners=corners, ceiling_ratio=ratio)


def read_corner_txt(path: Path, width: int, height: int) -> SuppliedLayout:
    """PanoContext / Stanford 2D-3D-S corner labels (HorizonNet's `label_cor`):
    one "x y" pixel coordinate per line, (ceiling, floor) pairs per wall-wall
    corner, in the pixel frame of the panorama they label (width x height)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise PanoError(path, f"cannot read: {e}") from None
    rows = []
    for no, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            vals = []
        if len(vals) != 2 or not np.all(np.isfinite(vals)):
            raise PanoError(path, f'line {no}: expected two numbers "x y", got {line[:40]!r}')
        rows.append(vals)
    xy = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
    if xy.size and (
        xy[:, 0].min() < -0.5
        or xy[:, 0].max() > width - 0.5
        or xy[:, 1].min() < -0.5
        or xy[:, 1].max() > height - 0.5
    ):
        raise PanoError(path, f"corner coordinates fall outside the {width}x{height} panorama")
    return SuppliedLayout("txt", corners=_pairs_to_corners(path, xy, width, height))


def read_boundaries_npy(path: Path) -> SuppliedLayout:
    """[2,W] float latitudes in radians: ceiling boundary (> 0), floor boundary (< 0)."""
    path = Path(path)
    b = load_npy(path)
    if b.ndim != 2 or b.shape[0] != 2 or b.shape[1] < 8:
        raise PanoError(path, f"expected [2,W] boundary latitudes (W >= 8), got shape {list(b.shape)}")
    if not np.issubdtype(b.dtype, np.floating):
        raise PanoError(path, f"expected float latitudes in radians, got dtype {b.dtype}")
    b = b.astype(np.float64)
    if not np.all(np.isfinite(b)):
        raise PanoError(path, "boundaries contain NaN or Inf")
    if np.median(b[0]) < 0 < np.median(b[1]):
        raise PanoError(
            path,
            "row 0 lies below the horizon and row 1 above: this looks like HorizonNet's "
            "`bon` (= -latitude); store latitudes (ceiling > 0, floor < 0)",
        )
    if np.abs(b).max() > np.pi / 2:
        raise PanoError(path, "latitudes must be radians in [-pi/2, pi/2]")
    if b[0].min() <= 0 or b[1].max() >= 0:
        raise PanoError(
            path,
            "the ceiling boundary (row 0) must be above the horizon (> 0) and the floor "
            "boundary (row 1) below it (< 0) in every column",
        )
    return SuppliedLayout("npy", boundaries=b)


def read_layout(path: Path, width: int = HORIZONNET_W, height: int = HORIZONNET_H) -> SuppliedLayout:
    """Any supplied layout file, by suffix; width/height: the panorama's size
    (the pixel frame of .txt corners and of the JSON's normalised uv)."""
    path = Path(path)
    if not path.is_file():
        raise PanoError(path, "layout file does not exist")
    suffix = path.suffix.lower()
    if suffix == ".json":
        return read_horizonnet_json(path, width, height)
    if suffix == ".txt":
        return read_corner_txt(path, width, height)
    if suffix == ".npy":
        return read_boundaries_npy(path)
    raise PanoError(path, f"unknown layout format {suffix!r}: use .json (HorizonNet), .txt (corners) or .npy")


def horizonnet_json(
    polygon: np.ndarray,
    camera_height: float,
    ceiling_distance: float,
    width: int = HORIZONNET_W,
    height: int = HORIZONNET_H,
) -> dict:
    """A metric room (camera-frame floor polygon) as HorizonNet's JSON, with its
    z0 = 50 convention: corners sorted by u, each a (ceiling, floor) pair, uv
    normalised by the panorama's width and height."""
    poly = np.asarray(polygon, dtype=np.float64)
    phi = np.arctan2(poly[:, 0], poly[:, 1])
    d = np.hypot(poly[:, 0], poly[:, 1])
    order = np.argsort(phi)
    z0 = 50.0
    z1 = -z0 * camera_height / ceiling_distance
    uv = []
    for j in order:
        u = ((phi[j] / (2 * np.pi) + 0.5) * width - 0.5) / width
        for th in (np.arctan2(ceiling_distance, d[j]), -np.arctan2(camera_height, d[j])):
            v = ((0.5 - th / np.pi) * height - 0.5) / height
            uv.append([float(u % 1.0), float(v)])
    return {"z0": z0, "z1": float(z1), "uv": uv}
