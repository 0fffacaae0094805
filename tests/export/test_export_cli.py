"""`pano-pipe export` end to end on a tiny trained run: outputs, refusals, one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from export_helpers import distance_to_box, room_box, run_cli

from export.spz import read_spz
from gaussians.ply import load_ply


@pytest.mark.parametrize("fmt,name", [("ply", "point_cloud.ply"), ("splat", "point_cloud.splat"),
                                      ("spz", "point_cloud.spz"), ("sog", "point_cloud.sog"),
                                      ("html", "point_cloud.html")])
def test_export_writes_the_default_file_and_refuses_to_overwrite(run_copy, capsys, fmt, name):
    code, out = run_cli(["export", run_copy, "--format", fmt], capsys)
    assert code == 0, out
    target = run_copy / "export" / name
    assert target.is_file() and target.stat().st_size > 0
    before = target.read_bytes()
    code, out = run_cli(["export", run_copy, "--format", fmt], capsys)
    assert code == 2
    lines = out.strip().splitlines()
    assert len(lines) == 1 and "already exists" in lines[0] and "--overwrite" in lines[0], out
    assert target.read_bytes() == before
    code, out = run_cli(["export", run_copy, "--format", fmt, "--overwrite"], capsys)
    assert code == 0, out
    assert sorted(p.name for p in target.parent.iterdir()) == [name], "temporary files left behind"


def test_ply_y_up_export_matches_the_model(run_copy, capsys, tmp_path):
    out_file = tmp_path / "up.ply"
    code, out = run_cli(["export", run_copy, "--format", "ply", "--y-up", "--out", out_file], capsys)
    assert code == 0, out
    g = load_ply(run_copy / "train" / "point_cloud.ply")
    up = load_ply(out_file)
    np.testing.assert_array_equal(up.means.numpy(), g.means.numpy() * [1, -1, -1])
    code, out = run_cli(["export", run_copy, "--format", "spz", "--out", tmp_path / "m.spz"], capsys)
    assert code == 0, out
    back = read_spz(tmp_path / "m.spz")
    assert np.abs(back.means.numpy() - g.means.numpy()).max() < 1e-3


def _one_line_error(code, out, *words):
    lines = out.strip().splitlines()
    assert code == 2, out
    assert len(lines) == 1 and lines[0].startswith("error:"), out
    for w in words:
        assert w in lines[0], out


def test_bad_run_folders_are_refused_in_one_line(tmp_path, run_copy, capsys):
    _one_line_error(*run_cli(["export", tmp_path / "nope", "--format", "ply"], capsys), "no such run folder")
    (tmp_path / "file").write_text("x")
    _one_line_error(*run_cli(["export", tmp_path / "file", "--format", "ply"], capsys), "not a folder")
    (tmp_path / "empty").mkdir()
    _one_line_error(*run_cli(["export", tmp_path / "empty", "--format", "splat"], capsys), "artifact.json")
    assert not (tmp_path / "empty" / "export").exists()
    # a truncated model
    ply = run_copy / "train" / "point_cloud.ply"
    ply.write_bytes(ply.read_bytes()[:5000])
    _one_line_error(*run_cli(["export", run_copy, "--format", "spz"], capsys), "truncated")
    # a broken artifact
    artifact = run_copy / "train" / "artifact.json"
    valid = json.loads(artifact.read_text())
    artifact.write_text("{not json")
    _one_line_error(*run_cli(["export", run_copy, "--format", "ply"], capsys), "invalid JSON")
    artifact.write_text(json.dumps({"data": {"ply": "point_cloud.ply"}}))
    _one_line_error(*run_cli(["export", run_copy, "--format", "ply"], capsys), "meta")
    artifact.write_text(json.dumps({**valid, "data": {**valid["data"], "ply": "../../etc/passwd"}}))
    _one_line_error(*run_cli(["export", run_copy, "--format", "ply"], capsys), "data.ply")
    assert not (run_copy / "export").exists()


def test_bad_options_are_refused_in_one_line(run_copy, capsys, tmp_path):
    _one_line_error(*run_cli(["export", run_copy, "--format", "splat", "--out", tmp_path / "x.ply"], capsys),
                    ".splat")
    _one_line_error(*run_cli(["export", run_copy, "--format", "mesh", "--out", tmp_path / "x.obj"], capsys),
                    ".glb")
    (tmp_path / "d.ply").mkdir()
    _one_line_error(*run_cli(["export", run_copy, "--format", "ply", "--out", tmp_path / "d.ply"], capsys),
                    "is a folder")
    code, out = run_cli(["export", run_copy, "--format", "obj"], capsys)
    assert code == 2 and len(out.strip().splitlines()) == 1, out


def _glb_vertices(scene) -> np.ndarray:
    """The vertices of a loaded .glb's one mesh (trimesh >= 4.5 names the call to_geometry)."""
    return np.asarray(scene.to_geometry().vertices if hasattr(scene, "to_geometry")
                      else scene.dump(concatenate=True).vertices)


def test_mesh_export_from_a_trained_run(run_copy, trained_run, capsys):
    code, out = run_cli(["export", run_copy, "--format", "mesh", "--mesh-height", "32", "--mesh-depth", "7"],
                        capsys)
    assert code == 0, out
    ply, glb = run_copy / "export" / "mesh.ply", run_copy / "export" / "mesh.glb"
    m = trimesh.load(ply, process=False)
    assert len(m.vertices) > 500 and len(m.faces) > 500
    assert m.visual.vertex_colors.shape == (len(m.vertices), 4)
    scene = trimesh.load(glb)
    assert sum(len(geo.faces) for geo in scene.geometry.values()) == len(m.faces)
    # the .glb is y up (glTF's axes), the .ply keeps the run's y-down world: the same vertices rotated
    np.testing.assert_allclose(_glb_vertices(scene), np.asarray(m.vertices) * [1, -1, -1], atol=1e-5)
    assert m.is_watertight and "watertight" in " ".join(out.split())
    assert len(m.faces) == len(m.faces[m.area_faces > 1e-12])  # no degenerate face
    # both files refused the second time, nothing replaced
    code, out = run_cli(["export", run_copy, "--format", "mesh", "--out", glb], capsys)
    assert code == 2 and "already exists" in out
    # --glb-axes pano-pipe: the .glb in the run's own axes, like the .ply
    code, out = run_cli(["export", run_copy, "--format", "mesh", "--mesh-height", "32", "--mesh-depth", "7",
                         "--glb-axes", "pano-pipe", "--out", run_copy / "export" / "raw.glb"], capsys)
    assert code == 0, out
    raw = trimesh.load(run_copy / "export" / "raw.glb")
    twin = trimesh.load(run_copy / "export" / "raw.ply", process=False)  # written beside it, y down too
    np.testing.assert_allclose(_glb_vertices(raw), np.asarray(twin.vertices), atol=1e-5)
    d = distance_to_box(np.asarray(m.vertices), room_box(trained_run / "S"))
    print(f"trained-run mesh: {len(m.vertices)} vertices, median distance to the true walls "
          f"{100 * np.median(d):.2f} cm, 90th percentile {100 * np.percentile(d, 90):.2f} cm")
    assert np.median(d) < 0.05
