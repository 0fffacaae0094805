"""Read and write the shared initial point cloud (schemas/cloud.py): cloud.npz + cloud.ply.

`sampling` writes the layout cloud, `align` the merged one, `train` reads it.
The npz is the source of truth (float32 points/colors/normals/u0, bool is_layout);
the PLY (open3d) carries positions, normals and colours for viewers only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from runfs.errors import PanoError
from runfs.fsutil import native_write
from schemas.cloud import CloudFiles

NPZ_NAME = "cloud.npz"
PLY_NAME = "cloud.ply"
_KEYS = ("points", "colors", "normals", "u0", "is_layout")


def _as_n3(name: str, arr, n: int | None) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float32)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and a.shape[0] != n):
        raise ValueError(f"{name}: expected shape [{n if n is not None else 'N'},3], got {list(a.shape)}")
    return np.ascontiguousarray(a)


def write_cloud(
    out_dir: str | Path,
    points,
    colors,
    normals=None,
    u0=None,
    is_layout=None,
) -> CloudFiles:
    """Write cloud.npz and cloud.ply into `out_dir`; returns CloudFiles with paths relative to it.

    normals default to zero (depth points have none), u0 to the points, is_layout to False.
    Colours are RGB in [0, 1] (uint8 input is scaled).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pts = _as_n3("points", points, None)
    n = pts.shape[0]
    col = np.asarray(colors)
    if col.dtype == np.uint8:
        col = col.astype(np.float32) / 255.0
    col = np.clip(_as_n3("colors", col, n), 0.0, 1.0)
    nrm = np.zeros((n, 3), np.float32) if normals is None else _as_n3("normals", normals, n)
    u0a = pts.copy() if u0 is None else _as_n3("u0", u0, n)
    lay = np.zeros(n, bool) if is_layout is None else np.asarray(is_layout, dtype=bool).reshape(-1)
    if lay.shape[0] != n:
        raise ValueError(f"is_layout: expected shape [{n}], got {list(lay.shape)}")
    for name, a in (("points", pts), ("colors", col), ("normals", nrm), ("u0", u0a)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: contains NaN or Inf")

    np.savez(out_dir / NPZ_NAME, points=pts, colors=col, normals=nrm, u0=u0a, is_layout=lay)
    write_ply(out_dir / PLY_NAME, pts, col, nrm)
    return CloudFiles(npz=NPZ_NAME, ply=PLY_NAME, num_points=int(n), num_layout_points=int(lay.sum()))


def write_ply(path: Path, pts: np.ndarray, col: np.ndarray, nrm: np.ndarray) -> None:
    """A binary PLY of points, colours (RGB in [0, 1]) and normals, for viewers."""
    if len(pts) == 0:  # open3d refuses to write an empty cloud; a header-only PLY is valid
        props = "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
        props += "".join(f"property uchar {k}\n" for k in ("red", "green", "blue"))
        path.write_text(f"ply\nformat ascii 1.0\nelement vertex 0\n{props}end_header\n")
        return
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(pts.astype(np.float64))
    pc.colors = o3d.utility.Vector3dVector(col.astype(np.float64))
    pc.normals = o3d.utility.Vector3dVector(nrm.astype(np.float64))
    native_write(path, lambda: o3d.io.write_point_cloud(str(path), pc, write_ascii=False), "point cloud")


def read_cloud(path: str | Path) -> dict[str, np.ndarray]:
    """Load a cloud: `path` is cloud.npz or the folder holding it.

    Returns float32 points/colors/normals/u0 [N,3] and bool is_layout [N].
    A missing or malformed file raises PanoError naming it.
    """
    path = Path(path)
    if path.is_dir():
        path = path / NPZ_NAME
    if not path.is_file():
        raise PanoError(path, "point cloud file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # zip/format errors: one line for the user
        raise PanoError(path, f"unreadable point cloud ({type(exc).__name__}: {exc})") from exc
    missing = [k for k in _KEYS if k not in data]
    if missing:
        raise PanoError(path, f"missing arrays {missing} (expected {list(_KEYS)})")
    n = data["points"].shape[0] if data["points"].ndim == 2 else -1
    out: dict[str, np.ndarray] = {}
    for k in _KEYS[:4]:
        a = data[k]
        if a.ndim != 2 or a.shape != (n, 3):
            raise PanoError(path, f"{k}: expected shape [N,3] with N={n}, got {list(a.shape)}")
        out[k] = a.astype(np.float32, copy=False)
    lay = data["is_layout"]
    if lay.shape != (n,):
        raise PanoError(path, f"is_layout: expected shape [{n}], got {list(lay.shape)}")
    out["is_layout"] = lay.astype(bool, copy=False)
    return out
