"""Closing the room mesh: small holes filled, large ones left open, degenerate faces removed
without opening the surface."""

from __future__ import annotations

import numpy as np
import pymeshlab
import pytest
import trimesh

from export.mesh import boundary_loops, close_holes, mesh_topology, split_degenerate


def _sphere(radius: float = 2.0) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)


def _without(mesh: trimesh.Trimesh, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)[keep]


def _closed(v: np.ndarray, f: np.ndarray, max_hole_m: float) -> tuple[np.ndarray, np.ndarray]:
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f))
    close_holes(ms, max_hole_m)
    m = ms.current_mesh()
    return split_degenerate(m.vertex_matrix(), m.face_matrix())


def test_a_small_hole_is_closed_and_a_large_one_left_open():
    s = _sphere()
    centres = s.triangles_center
    small = np.linalg.norm(centres - [0, 0, 2], axis=1) < 0.3  # ~0.6 m across
    large = centres[:, 2] < -1.2  # a cap: a circle 3.2 m wide, its bounding box 4.6 m across
    v, f = _without(s, ~(small | large))
    before = mesh_topology(v, f)
    assert before["boundary_loops"] == 2 and not before["watertight"]
    v2, f2 = _closed(v, f, max_hole_m=1.0)
    after = mesh_topology(v2, f2)
    assert after["boundary_loops"] == 1 and after["holes_across_m"][0] == pytest.approx(4.6, abs=0.1)
    v3, f3 = _closed(v, f, max_hole_m=5.0)
    closed = mesh_topology(v3, f3)
    assert closed["watertight"] and closed["euler_number"] == 2 and closed["degenerate_faces"] == 0
    assert trimesh.Trimesh(v3, f3, process=False).is_winding_consistent


def test_no_hole_closed_when_asked_for_none():
    s = _sphere()
    v, f = _without(s, np.linalg.norm(s.triangles_center - [0, 0, 2], axis=1) >= 0.3)
    v2, f2 = _closed(v, f, max_hole_m=0.0)
    assert len(boundary_loops(f2)) == 1


def test_a_sliver_on_an_edge_is_split_away_and_the_surface_stays_closed():
    s = _sphere()
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    a, b, d = f[0]
    other = next(i for i, t in enumerate(f.tolist()) if i and a in t and b in t)
    c = len(v)
    v = np.vstack([v, (v[a] + v[b]) / 2])  # c on the edge ab: a T-junction closed by a zero-height face
    f = np.vstack([np.delete(f, 0, axis=0), [[a, c, d], [c, b, d], [a, b, c]]])
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh_topology(v, f)["degenerate_faces"] == 1
    v2, f2 = split_degenerate(v, f)
    out = trimesh.Trimesh(v2, f2, process=False)
    assert out.is_watertight and out.is_winding_consistent and mesh_topology(v2, f2)["degenerate_faces"] == 0
    assert len(f2) == len(f)  # the sliver and its neighbour out, the neighbour's two halves in
    assert out.volume == pytest.approx(mesh.volume, rel=1e-12)
    assert other is not None


def test_a_needle_on_a_collapsed_edge_is_merged_away():
    s = _sphere()
    v, f = np.asarray(s.vertices), np.asarray(s.faces).copy()
    a, b, _ = f[0]
    v = v.copy()
    v[b] = v[a] + 1e-8  # an edge of (almost) zero length: both faces on it are needles
    assert mesh_topology(v, f)["degenerate_faces"] == 2
    v2, f2 = split_degenerate(v, f)
    out = trimesh.Trimesh(v2, f2, process=False)
    assert out.is_watertight and mesh_topology(v2, f2)["degenerate_faces"] == 0 and len(f2) == len(f) - 2
