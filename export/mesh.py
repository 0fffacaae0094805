"""A coloured surface mesh of the room from a trained Gaussian model.

1. Oriented points. `source="depth"` (default when the run's scene folder is readable):
   the model is rendered (splatting.render, equirectangular) at every training pose;
   each pixel with alpha > 0.5 is back-projected along its ray to the alpha-normalised
   expected depth, keeping the rendered colour. `source="centres"`: the centres of the
   Gaussians with opacity ≥ 0.1, coloured by their degree-0 SH. In both cases normals
   are estimated by pymeshlab (PCA over the k nearest points) and turned to face the
   nearest training camera (or, with no cameras, the cloud's centroid), i.e. into the room.
2. Screened Poisson reconstruction (pymeshlab, octree depth `depth`).
3. Cleaning: vertices farther than `max_gap` from every input point (Poisson's closing
   membranes over unseen regions) are removed, then connected components smaller than
   `min_component` of the bounding-box diagonal, duplicate/unreferenced elements.
4. Colour: each vertex takes the colour of its nearest input point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["OrientedPoints", "MeshResult", "points_from_depth", "points_from_centres", "reconstruct",
           "write_mesh"]


@dataclass
class OrientedPoints:
    points: np.ndarray  # [N,3] float64
    colors: np.ndarray  # [N,3] float in [0,1]
    normals: np.ndarray | None = None  # [N,3] unit, or None (estimated by reconstruct)
    viewpoints: np.ndarray | None = None  # [N,3] camera a point was seen from (orients normals)


@dataclass
class MeshResult:
    vertices: np.ndarray  # [V,3]
    faces: np.ndarray  # [F,3] int
    colors: np.ndarray  # [V,3] float in [0,1]
    stats: dict = field(default_factory=dict)


def points_from_depth(g, poses: list[np.ndarray], height: int = 64, min_alpha: float = 0.5,
                      backend: str | None = None) -> OrientedPoints:
    """Back-project the model's rendered depth at each camera-to-world pose."""
    from evaluation.model_io import equirect_camera, render_pose
    from panogeom.equirect import ray_directions

    width = 2 * int(height)
    cam = equirect_camera(height, width)
    dirs = ray_directions(int(height), width).reshape(-1, 3)
    pts, cols, vps = [], [], []
    for c2w in poses:
        c2w = np.asarray(c2w, dtype=np.float64)
        r = render_pose(g, c2w, cam, backend=backend)
        ok = (r.alpha.reshape(-1) > min_alpha) & (r.depth.reshape(-1) > 0)
        d_world = dirs[ok] @ c2w[:3, :3].T
        p = c2w[:3, 3] + d_world * r.depth.reshape(-1)[ok, None]
        pts.append(p)
        cols.append(r.image.reshape(-1, 3)[ok])
        vps.append(np.broadcast_to(c2w[:3, 3], p.shape))
    if not pts:
        return OrientedPoints(np.zeros((0, 3)), np.zeros((0, 3)))
    return OrientedPoints(np.concatenate(pts), np.clip(np.concatenate(cols), 0, 1).astype(np.float64),
                          viewpoints=np.concatenate(vps))


def points_from_centres(g, cameras: np.ndarray | None = None, min_opacity: float = 0.1) -> OrientedPoints:
    """Centres of the (sufficiently opaque) Gaussians; normals face the nearest camera if given."""
    from gaussians.model import sh_to_rgb

    keep = (g.opacities.detach().cpu().numpy() >= min_opacity)
    p = g.means.detach().cpu().double().numpy()[keep]
    c = np.clip(sh_to_rgb(g.sh_dc.detach().cpu().double()).numpy().reshape(-1, 3)[keep], 0, 1)
    vps = None
    if cameras is not None and len(cameras) and len(p):
        cams = np.asarray(cameras, dtype=np.float64).reshape(-1, 3)
        nearest = np.argmin(((p[:, None, :] - cams[None]) ** 2).sum(-1), axis=1)
        vps = cams[nearest]
    return OrientedPoints(p, c, viewpoints=vps)


def _estimate_normals(ms, op: OrientedPoints, k: int) -> np.ndarray:
    ms.compute_normal_for_point_clouds(k=k, smoothiter=1, flipflag=False)
    n = ms.current_mesh().vertex_normal_matrix().astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    towards = (op.viewpoints if op.viewpoints is not None else op.points.mean(0)) - op.points
    flip = (n * towards).sum(1) < 0
    n[flip] *= -1
    return n


def reconstruct(op: OrientedPoints, depth: int = 8, max_gap: float | None = None, min_component: float = 10.0,
                k: int = 12) -> MeshResult:
    """Screened Poisson surface of the oriented points, cleaned and coloured (see the module doc).
    `max_gap` (metres) defaults to 4× the median spacing of the points (at least 3 cm)."""
    import pymeshlab
    from scipy.spatial import cKDTree

    if len(op.points) < 20:
        raise ValueError(f"only {len(op.points)} points to reconstruct a surface from (need at least 20)")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=op.points))
    normals = op.normals if op.normals is not None else _estimate_normals(ms, op, k)
    ms.clear()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=op.points, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(depth=int(depth), preclean=True, threads=2)
    m = ms.current_mesh()
    verts = m.vertex_matrix()
    tree = cKDTree(op.points)
    if max_gap is None:
        spacing = tree.query(op.points[:: max(1, len(op.points) // 5000)], k=2)[0][:, 1]
        max_gap = max(4.0 * float(np.median(spacing)), 0.03)
    gap = tree.query(verts, k=1)[0]
    stats = {"points": int(len(op.points)), "poisson_vertices": int(len(verts)), "max_gap_m": float(max_gap)}
    # quality > 0 marks the vertices to delete; pymeshlab selects them by condition
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=m.face_matrix(),
                               v_scalar_array=(gap > max_gap).astype(np.float64)))
    ms.compute_selection_by_condition_per_vertex(condselect="q > 0.5")
    ms.meshing_remove_selected_vertices()
    ms.meshing_remove_connected_component_by_diameter(
        mincomponentdiag=pymeshlab.PercentageValue(float(min_component)), removeunref=True)
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    verts, faces = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    if len(faces) == 0:
        raise ValueError("the reconstructed surface is empty after cleaning")
    _, idx = tree.query(verts, k=1)
    stats.update(vertices=int(len(verts)), faces=int(len(faces)))
    return MeshResult(verts, faces, op.colors[idx], stats)


def write_mesh(path: Path, mesh: MeshResult) -> None:
    """Write the mesh with per-vertex colours; the format follows the suffix (.ply, .glb)."""
    import trimesh

    rgba = np.concatenate([np.clip(np.rint(mesh.colors * 255), 0, 255), np.full((len(mesh.colors), 1), 255)], 1)
    tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, vertex_colors=rgba.astype(np.uint8),
                         process=False)
    file_type = Path(path).suffix.lower().lstrip(".")
    data = tm.export(file_type=file_type)
    Path(path).write_bytes(data if isinstance(data, bytes) else data.encode())
