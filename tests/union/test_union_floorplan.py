"""union stage: per-view floor plans to one world floor plan (simulator ground truth)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from shapely.geometry import Polygon
from shapely.ops import unary_union

from floorplan import union as F
from runfs.errors import PanoError
from runtime.stage import Loaded, StageContext
from schemas.layout import LayoutOutput, ViewLayout
from schemas.scene_loader import load_scene
from stages import union as U

#: the union stage's settings
P = U.Params()


def _gt(scene_dir):
    return json.loads((scene_dir / "gt" / "floor_plan.json").read_text())


def _gt_shape(scene_dir):
    return unary_union([Polygon(r["polygon"]) for r in _gt(scene_dir)["rooms"]])


def _run(scene_dir, layout: LayoutOutput, tmp_path, **params):
    scene = load_scene(scene_dir)
    out = tmp_path / "union"
    out.mkdir()
    ctx = StageContext(
        scene=scene, params=U.Params(**params), inputs={"layout": Loaded(layout, tmp_path)}, out_dir=out
    )
    return U.run(ctx), out, ctx


def _poses(scene_dir):
    scene = load_scene(scene_dir)
    return {v.name: v.pose_matrix for v in scene.views}


# ----------------------------------------------------------------------------- pure geometry


def test_polygon_to_world_yaw_and_translation():
    yaw = np.deg2rad(90.0)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
    pose[:3, 3] = [1.0, -1.5, 2.0]
    # Camera forward (+z) turned 90 deg about +y points along world +x; camera +x along world -z.
    w = F.polygon_to_world([(0.0, 1.0), (1.0, 0.0)], pose, 1.5)
    np.testing.assert_allclose(w, [[2.0, 2.0], [1.0, 1.0]], atol=1e-12)
    assert F.camera_tilt_deg(pose) == pytest.approx(0.0, abs=1e-9)


def test_bowtie_polygon_is_repaired():
    bowtie = [(0, 0), (2, 2), (2, 0), (0, 2)]  # self-intersecting at (1, 1)
    assert not Polygon(bowtie).is_valid
    fixed, repaired = F.repair_polygon(bowtie)
    assert repaired and fixed.is_valid
    assert fixed.area == pytest.approx(2.0, abs=1e-9)  # the two unit triangles
    same, repaired2 = F.repair_polygon([(0, 0), (1, 0), (1, 1)])
    assert not repaired2 and same.area == pytest.approx(0.5)
    empty, rep3 = F.repair_polygon([(0, 0), (1, 1)])
    assert rep3 and empty.is_empty


def test_bowtie_view_in_stage_is_repaired_and_warned():
    layouts = [
        ViewLayout(
            view="a",
            source="npy",
            boundaries="a.npy",
            floor_polygon=[(-2, -2), (2, 2), (2, -2), (-2, 2)],
            camera_height=1.5,
            ceiling_distance=1.2,
            camera_height_assumed=False,
        ),
    ]
    warnings = []
    rooms, per_view = F.build_floor_plan(layouts, {"a": np.eye(4)}, **U.plan_settings(P), warn=warnings.append)
    assert per_view["a"]["repaired"] is True
    assert any("repaired" in w for w in warnings)
    # The two triangles touch at the camera: closing merges them into one valid room.
    assert len(rooms) == 1 and Polygon(rooms[0].polygon).is_valid
    assert Polygon(rooms[0].polygon).area == pytest.approx(8.0, rel=0.02)


def test_gaps_below_tolerance_close_and_wide_gaps_do_not():
    a = Polygon([(0, 0), (3, 0), (3, 3), (0, 3)])
    b_near = Polygon([(3.03, 0.5), (6, 0.5), (6, 2.5), (3.03, 2.5)])  # 3 cm gap < 2 tol
    b_far = Polygon([(3.5, 0.5), (6, 0.5), (6, 2.5), (3.5, 2.5)])  # 50 cm apart: another room
    merged = F.merge_floor_plans([a, b_near], tolerance=0.05, min_area=P.min_room_area, simplify=P.simplify)
    assert len(merged) == 1
    # The gap is filled only where both walls face each other (z in [0.5, 2.5]).
    assert merged[0].area == pytest.approx(9 + 2.97 * 2 + 0.03 * 2, abs=1e-6)
    assert len(F.merge_floor_plans([a, b_far], tolerance=0.05, min_area=P.min_room_area, simplify=P.simplify)) == 2
    # A 2 cm sliver sticking out of the room is removed; square corners stay exact.
    spike = Polygon([(3, 1.0), (4, 1.0), (4, 1.02), (3, 1.02)])
    clean = F.merge_floor_plans([a, spike], tolerance=0.05, min_area=P.min_room_area, simplify=P.simplify)
    assert len(clean) == 1 and clean[0].symmetric_difference(a).area < 1e-9


def test_robust_mean_ignores_outlier():
    assert F.robust_mean([2.80, 2.81, 2.79, 3.60]) == pytest.approx(2.80, abs=1e-9)
    assert F.robust_mean([1.0]) == 1.0


# ----------------------------------------------------------------------------- simulator scenes


def test_two_rooms_union_matches_true_floor_plan(two_rooms_scene, tmp_path, gt_layouts):
    gt = _gt(two_rooms_scene)
    out, folder, _ = _run(two_rooms_scene, gt_layouts(two_rooms_scene), tmp_path)
    true = _gt_shape(two_rooms_scene)
    # The doorway's wall is interior to the union: one room, the outline of both.
    assert len(out.rooms) == 1
    got = F.room_shape(out.rooms[0])
    iou = F.polygon_iou(got, true)
    print(f"two-rooms IoU (exact layouts): {iou:.6f}")
    assert iou >= 0.999
    assert out.area_m2 == pytest.approx(true.area, rel=1e-3)
    room = out.rooms[0]
    assert room.floor_y == pytest.approx(gt["rooms"][0]["floor_y"], abs=1e-6)
    assert room.ceiling_y == pytest.approx(gt["rooms"][0]["ceiling_y"], abs=1e-6)
    train = {n for n, c in gt["cameras"].items() if c["split"] == "train"}
    assert set(room.views) == train
    # Files: floor_plan.json holds rooms and per-view polygons; the PNG is an image.
    doc = json.loads((folder / out.floor_plan).read_text())
    assert len(doc["rooms"]) == 1 and set(doc["views"]) == train
    for rec in doc["views"].values():
        assert Polygon(rec["polygon_world"]).buffer(1e-6).within(true.buffer(1e-3))
    img = cv2.imread(str(folder / out.drawing))
    assert img is not None and img.shape[0] > 200 and img.std() > 5


def test_two_rooms_union_with_noisy_layouts(two_rooms_scene, tmp_path, gt_layouts):
    # Each view's room 1 cm short of every wall (so a 2 cm gap at the doorway wall) with 2 cm corner noise.
    layout = gt_layouts(two_rooms_scene, noise=0.02, shrink=0.01, seed=7)
    out, _, _ = _run(two_rooms_scene, layout, tmp_path)
    assert len(out.rooms) == 1
    iou = F.polygon_iou(F.room_shape(out.rooms[0]), _gt_shape(two_rooms_scene))
    print(f"two-rooms IoU (noisy layouts): {iou:.4f}")
    assert iou >= 0.98


def test_l_shape_union(l_shape_scene, tmp_path, gt_layouts):
    out, _, _ = _run(l_shape_scene, gt_layouts(l_shape_scene), tmp_path)
    assert len(out.rooms) == 1
    assert F.polygon_iou(F.room_shape(out.rooms[0]), _gt_shape(l_shape_scene)) >= 0.999


def test_rooms_with_different_heights_keep_their_own(tmp_path):
    # Two separate rooms (4 m apart) seen by two cameras each; room 2 is a step lower with a higher ceiling.
    def view(name, x, cam_y, floor_y, ceil_y, poly):
        pose = np.eye(4)
        pose[:3, 3] = [x, cam_y, 0.0]
        vl = ViewLayout(
            view=name,
            source="npy",
            boundaries="x.npy",
            floor_polygon=[(px - x, pz) for px, pz in poly],
            camera_height=floor_y - cam_y,
            ceiling_distance=cam_y - ceil_y,
            camera_height_assumed=False,
        )
        return vl, pose

    r1 = [(-2, -2), (2, -2), (2, 2), (-2, 2)]
    r2 = [(6, -2), (10, -2), (10, 2), (6, 2)]
    specs = [
        ("a0", -1, -1.5, 0.0, -2.6, r1),
        ("a1", 1, -1.6, 0.0, -2.6, r1),
        ("b0", 7, -1.2, 0.3, -2.9, r2),
        ("b1", 9, -1.3, 0.3, -2.9, r2),
    ]
    made = [view(*s) for s in specs]
    rooms, per_view = F.build_floor_plan(
        [m[0] for m in made], {s[0]: m[1] for s, m in zip(specs, made)}, **U.plan_settings(P)
    )
    assert len(rooms) == 2
    by_views = {tuple(r.views): r for r in rooms}
    assert by_views[("a0", "a1")].floor_y == pytest.approx(0.0) and by_views[
        ("a0", "a1")
    ].ceiling_y == pytest.approx(-2.6)
    assert by_views[("b0", "b1")].floor_y == pytest.approx(0.3) and by_views[
        ("b0", "b1")
    ].ceiling_y == pytest.approx(-2.9)
    assert per_view["b1"]["room"] != per_view["a0"]["room"]


def test_only_train_views_are_used(two_rooms_scene, tmp_path, gt_layouts):
    layout = gt_layouts(two_rooms_scene)
    test_name = next(v.name for v in load_scene(two_rooms_scene).views if v.split == "test")
    huge = ViewLayout(
        view=test_name,
        source="npy",
        boundaries="t.npy",
        floor_polygon=[(-50, -50), (50, -50), (50, 50), (-50, 50)],
        camera_height=1.5,
        ceiling_distance=1.0,
        camera_height_assumed=False,
    )
    out, _, _ = _run(two_rooms_scene, LayoutOutput(views=[*layout.views, huge]), tmp_path)
    assert out.area_m2 == pytest.approx(_gt_shape(two_rooms_scene).area, rel=1e-3)
    assert test_name not in out.rooms[0].views


def test_missing_layouts_fail_with_one_line_error(two_rooms_scene, tmp_path):
    with pytest.raises(PanoError) as exc:
        _run(two_rooms_scene, LayoutOutput(views=[]), tmp_path)
    assert "scene.json" in str(exc.value) and "\n" not in str(exc.value)


def test_partial_layouts_warn(two_rooms_scene, tmp_path, gt_layouts):
    layout = gt_layouts(two_rooms_scene)
    out, _, ctx = _run(two_rooms_scene, LayoutOutput(views=layout.views[:-1]), tmp_path)
    assert any("no layout" in w for w in ctx.warnings)
    assert out.rooms


def test_tilted_camera_and_polygon_not_around_camera_warn():
    tilt = np.deg2rad(10.0)
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]]
    vl = ViewLayout(
        view="a",
        source="npy",
        boundaries="a.npy",
        floor_polygon=[(1, 1), (3, 1), (3, 3), (1, 3)],  # does not surround the camera
        camera_height=1.5,
        ceiling_distance=1.2,
        camera_height_assumed=False,
    )
    warnings = []
    F.build_floor_plan([vl], {"a": pose}, **U.plan_settings(P), warn=warnings.append)
    assert any("tilted 10.0 deg" in w for w in warnings)
    assert any("outside its own floor polygon" in w for w in warnings)


def test_layout_stage_to_union_to_sampling(tmp_path):
    # The whole chain on the simulator's supplied layouts (HorizonNet JSON): conventions agree end to end.
    layout_stage = pytest.importorskip("stages.layout")
    from simulate import generate_scene
    from stages import sampling as S
    from stages.cloud_io import read_cloud

    scene_dir = tmp_path / "scene"
    generate_scene(
        scene_dir,
        preset="two-rooms",
        views=4,
        test_views=1,
        height=64,
        seed=0,
        effects="none",
        aa_samples=1,
        with_layout=True,
    )
    scene = load_scene(scene_dir)
    dirs = {k: tmp_path / k for k in ("layout", "union", "sampling")}
    for p in dirs.values():
        p.mkdir()
    lo = layout_stage.run(
        StageContext(scene=scene, params=layout_stage.Params(), inputs={}, out_dir=dirs["layout"])
    )
    uo = U.run(
        StageContext(
            scene=scene,
            params=U.Params(),
            inputs={"layout": Loaded(lo, dirs["layout"])},
            out_dir=dirs["union"],
        )
    )
    iou = F.polygon_iou(F.room_shape(uo.rooms[0]), _gt_shape(scene_dir))
    print(f"two-rooms IoU (layout stage on the simulator's JSON): {iou:.6f}")
    assert len(uo.rooms) == 1 and iou >= 0.98
    gt = _gt(scene_dir)
    assert uo.rooms[0].ceiling_y == pytest.approx(gt["rooms"][0]["ceiling_y"], abs=0.01)
    assert uo.rooms[0].floor_y == pytest.approx(gt["rooms"][0]["floor_y"], abs=0.01)
    so = S.run(
        StageContext(
            scene=scene,
            params=S.Params(density=100.0),
            inputs={"union": Loaded(uo, dirs["union"]), "layout": Loaded(lo, dirs["layout"])},
            out_dir=dirs["sampling"],
        )
    )
    cloud = read_cloud(dirs["sampling"] / so.cloud.npz)
    assert so.unseen_points == 0 and len(cloud["points"]) == so.cloud.num_points > 0
