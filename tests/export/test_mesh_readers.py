"""The exported mesh is watertight for the common readers, as the CLI says: trimesh's default
load (which merges coincident vertices) and open3d (which does not), with no duplicate vertices."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from export.mesh import MeshResult, weld_coincident, write_mesh
from tests.clitools import invoke

# a tetrahedron whose last face names a second copy (index 4) of vertex 0
TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]], dtype=np.float64)
FACES = np.array([[0, 2, 1], [0, 1, 3], [4, 3, 2], [1, 2, 3]])


def _readers(path):
    """(trimesh's default load, open3d's) watertight verdicts and open3d's vertex positions."""
    mesh = o3d.io.read_triangle_mesh(str(path))
    return trimesh.load(path, force="mesh").is_watertight, mesh.is_watertight(), np.asarray(mesh.vertices)


def test_coincident_vertices_are_welded_so_both_readers_see_a_closed_surface(tmp_path):
    raw = tmp_path / "raw.ply"
    write_mesh(raw, MeshResult(TETRA, FACES, np.full((5, 3), 0.5), {}))
    assert not _readers(raw)[1]  # open3d: the copy leaves two edges with one face each
    v, f = weld_coincident(TETRA, FACES)
    assert len(v) == 4 and np.array_equal(v, TETRA[:4]) and f.max() == 3
    welded = tmp_path / "welded.ply"
    write_mesh(welded, MeshResult(v, f, np.full((4, 3), 0.5), {}))
    trimesh_says, open3d_says, vertices = _readers(welded)
    assert trimesh_says and open3d_says and len(np.unique(vertices, axis=0)) == len(vertices)


def test_the_exported_mesh_is_what_the_cli_says_for_both_readers(run_copy, capsys):
    code, out, err = invoke(["export", run_copy, "--format", "mesh", "--mesh-height", "32", "--mesh-depth", "7"],
                            capsys)
    assert code == 0, err
    claimed = "watertight" in out.split("mesh:")[1].split(";")[1]
    for path in (run_copy / "export" / "mesh.ply", run_copy / "export" / "mesh.glb"):
        trimesh_says, open3d_says, vertices = _readers(path)
        assert trimesh_says == open3d_says == claimed, path
        assert len(np.unique(vertices, axis=0)) == len(vertices), path  # no duplicate vertices
