"""sampling stage: the extruded floor plan sampled into the layout cloud (simulator ground truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely
from pydantic import ValidationError
from shapely.geometry import LineString, Polygon

from floorplan import box_sampling as B
from panogeom.equirect import sample_bilinear
from panogeom.surfaces import CEILING, FLOOR, SURFACE_NAMES, WALL
from runfs.errors import PanoError
from runtime.stage import Loaded, StageContext
from schemas.layout import LayoutOutput
from schemas.scene_loader import load_scene
from schemas.union import Room
from stages import sampling as S
from stages.cloud_io import read_cloud


def _run(scene_dir, union, tmp_path, layout=None, **params):
    scene = load_scene(scene_dir)
    out = tmp_path / "sampling"
    out.mkdir(parents=True)
    ctx = StageContext(
        scene=scene,
        params=S.Params(**params),
        out_dir=out,
        inputs={
            "union": Loaded(union, tmp_path),
            "layout": Loaded(layout or LayoutOutput(views=[]), tmp_path),
        },
    )
    return S.run(ctx), out, ctx


def _distance_to_true_shell(
    points: np.ndarray, outline: Polygon, floor_y: float, ceiling_y: float
) -> np.ndarray:
    """Exact distance of each point to the true room shell (walls on the outline, floor and ceiling)."""
    xz = shapely.points(points[:, 0], points[:, 2])
    d_edge = shapely.distance(outline.boundary, xz)
    outside = np.where(shapely.contains_xy(outline, points[:, 0], points[:, 2]), 0.0, d_edge)
    y = points[:, 1]
    d_wall = np.hypot(d_edge, np.maximum(0.0, np.maximum(ceiling_y - y, y - floor_y)))
    d_floor = np.hypot(np.abs(y - floor_y), outside)
    d_ceil = np.hypot(np.abs(y - ceiling_y), outside)
    return np.minimum(d_wall, np.minimum(d_floor, d_ceil))


# ----------------------------------------------------------------------------- pure sampling


@pytest.mark.parametrize("density", [100.0, 400.0, 1000.0])
def test_stratified_samplers_match_density(density):
    rng = np.random.default_rng(0)
    st = B.stratified_rect(3.7, 2.65, density, rng)
    assert len(st) == pytest.approx(3.7 * 2.65 * density, rel=0.02)
    assert st[:, 0].min() >= 0 and st[:, 0].max() <= 3.7 and st[:, 1].min() >= 0 and st[:, 1].max() <= 2.65
    poly = Polygon(
        [(0, 0), (5, 0), (5, 2), (2, 2), (2, 4), (0, 4)], [[(0.5, 0.5), (1, 0.5), (1, 1), (0.5, 1)]]
    )
    xz = B.stratified_polygon(poly, density, rng)
    assert len(xz) == pytest.approx(poly.area * density, rel=0.03)
    assert shapely.contains_xy(poly, xz[:, 0], xz[:, 1]).all()
    # Uniform: each quarter of the big arm gets a quarter of its points.
    arm = xz[(xz[:, 1] < 2) & (xz[:, 0] > 1)]
    counts = np.histogram(arm[:, 0], bins=4, range=(1, 5))[0]
    assert counts.min() / counts.max() > 0.9


def test_room_walls_normals_point_inwards_including_holes():
    poly = Polygon(
        [(0, 0), (0, 4), (4, 4), (4, 0)], [[(1, 1), (2, 1), (2, 2), (1, 2)]]
    )  # clockwise outer ring
    walls = B.room_walls(poly)
    assert len(walls) == 8
    for a, b, n in walls:
        mid = (a + b) / 2
        assert poly.contains(shapely.Point(*(mid + 0.01 * n)))
        assert not poly.contains(shapely.Point(*(mid - 0.01 * n)))


def test_line_of_sight_blocked_by_walls():
    a = np.array([[2.0, 2.0], [2.0, 2.0]])
    b = np.array([[6.0, 2.0], [2.0, 6.0]])  # the two walls meeting at the L's reflex corner
    cam = np.array([1.0, 5.5])
    targets = np.array([[5.0, 1.0], [1.0, 0.5], [1.5, 3.0], [5.9, 1.99]])
    np.testing.assert_array_equal(B.line_of_sight(cam, targets, a, b), [False, True, True, False])


def test_bilinear_wraps_at_the_seam():
    img = np.zeros((4, 8, 1))
    img[:, 0, 0] = 1.0  # first column bright, last column dark
    v = sample_bilinear(img, np.array([7.5, -0.5, -0.25, 0.0, 3.0]), np.array([1.0, 1.0, 1.0, -0.5, 10.0]))
    np.testing.assert_allclose(v[:, 0], [0.5, 0.5, 0.75, 1.0, 0.0])


# ----------------------------------------------------------------------------- simulator scene


def test_points_on_true_surfaces_with_inward_normals(two_rooms, gt_union, tmp_path):
    union = gt_union(two_rooms)
    out, folder, _ = _run(two_rooms, union, tmp_path, density=300.0)
    cloud = read_cloud(folder / out.cloud.npz)
    labels = np.load(folder / out.labels)
    gt = json.loads((two_rooms / "gt" / "floor_plan.json").read_text())
    outline = Polygon(gt["outline"])
    floor_y, ceiling_y = gt["rooms"][0]["floor_y"], gt["rooms"][0]["ceiling_y"]
    p = cloud["points"].astype(np.float64)
    dist = _distance_to_true_shell(p, outline, floor_y, ceiling_y)
    print(f"max distance to the true surfaces: {dist.max() * 1000:.4f} mm over {len(p)} points")
    assert dist.max() < 1e-3
    n = cloud["normals"].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    surf = labels["surface"]
    wall = surf == WALL
    inside_in = shapely.contains_xy(outline, p[wall, 0] + 1e-3 * n[wall, 0], p[wall, 2] + 1e-3 * n[wall, 2])
    inside_out = shapely.contains_xy(outline, p[wall, 0] - 1e-3 * n[wall, 0], p[wall, 2] - 1e-3 * n[wall, 2])
    assert inside_in.all() and not inside_out.any()
    assert np.all(n[wall, 1] == 0)
    # Floor normals point up (-y: the room is above the floor), ceiling normals down (+y).
    np.testing.assert_array_equal(n[surf == FLOOR], np.tile([0, -1, 0], ((surf == FLOOR).sum(), 1)))
    np.testing.assert_array_equal(n[surf == CEILING], np.tile([0, 1, 0], ((surf == CEILING).sum(), 1)))
    np.testing.assert_allclose(p[surf == FLOOR, 1], floor_y, atol=1e-6)
    np.testing.assert_allclose(p[surf == CEILING, 1], ceiling_y, atol=1e-6)
    # u0 is the initial position; every point is a layout point.
    np.testing.assert_array_equal(cloud["u0"], cloud["points"])
    assert cloud["is_layout"].all() and out.cloud.num_layout_points == len(p)
    assert (folder / out.cloud.ply).stat().st_size > 0


def test_doorway_wall_is_not_sampled(two_rooms, gt_union, tmp_path):
    out, folder, _ = _run(two_rooms, gt_union(two_rooms), tmp_path, density=300.0)
    p = read_cloud(folder / out.cloud.npz)["points"]
    surf = np.load(folder / out.labels)["surface"]
    gt = json.loads((two_rooms / "gt" / "floor_plan.json").read_text())
    door = gt["doorways"][0]
    xw = door["a"][0]
    ra, rb = (np.asarray(r["polygon"]) for r in gt["rooms"])
    z0, z1 = max(ra[:, 1].min(), rb[:, 1].min()), min(ra[:, 1].max(), rb[:, 1].max())  # the shared wall
    on_plane = (surf == WALL) & (np.abs(p[:, 0] - xw) < 1e-4)
    assert on_plane.any()  # room A's own walls beside room B stay
    assert not ((p[on_plane, 2] > z0 + 1e-4) & (p[on_plane, 2] < z1 - 1e-4)).any()


@pytest.mark.parametrize("density", [150.0, 400.0])
def test_density_matches_parameter(two_rooms, gt_union, tmp_path, density):
    union = gt_union(two_rooms)
    out, _, _ = _run(two_rooms, union, tmp_path, density=density, export_mesh=False)
    areas = B.surface_areas(union.rooms)
    for name in ("wall", "floor", "ceiling"):
        got = out.points_per_surface[name] / areas[name]
        assert got == pytest.approx(density, rel=0.03), name
    assert out.cloud.num_points == sum(out.points_per_surface.values())


def test_room_glb_is_the_extruded_plan(two_rooms, gt_union, tmp_path):
    import trimesh

    union = gt_union(two_rooms)
    out, folder, _ = _run(two_rooms, union, tmp_path, density=50.0)
    mesh = trimesh.load(folder / out.mesh_glb, force="mesh")
    mesh.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))  # the file is y up (glTF); back to the y-down world
    room = union.rooms[0]
    outline = Polygon(room.polygon)
    assert mesh.is_watertight
    assert abs(mesh.volume) == pytest.approx(outline.area * (room.floor_y - room.ceiling_y), rel=1e-6)
    np.testing.assert_allclose(mesh.bounds[:, 1], [room.ceiling_y, room.floor_y], atol=1e-6)
    # Face normals point into the room, like the cloud's.
    c = mesh.triangles_center + 1e-3 * mesh.face_normals
    assert shapely.contains_xy(outline, c[:, 0], c[:, 2]).all()
    assert ((c[:, 1] > room.ceiling_y) & (c[:, 1] < room.floor_y)).all()


def test_simulator_colours_are_the_surface_colours(two_rooms, gt_union, gt_view_layouts, tmp_path):
    # Without effects the simulator paints each material one flat colour: a point's colour must be
    # that of the surface it lies on. Room B's floor seen from room A would show the shared wall
    # (interior to the union): each view's own layout keeps it from colouring through that wall.
    from simulate.effects import MATERIAL_RGB

    union = gt_union(two_rooms)
    out, folder, _ = _run(two_rooms, union, tmp_path, layout=gt_view_layouts(two_rooms), density=200.0)
    cloud = read_cloud(folder / out.cloud.npz)
    lab = np.load(folder / out.labels)
    assert lab["seen"].all() and out.unseen_points == 0
    col = cloud["colors"].astype(np.float64)
    surf = lab["surface"]

    def share(sel, names):
        ref = np.stack([np.round(MATERIAL_RGB[n] * 255) / 255 for n in names])
        d = np.abs(col[sel][:, None, :] - ref[None]).max(axis=2).min(axis=1)
        return float((d < 0.6 / 255).mean())

    floors = [n for n in MATERIAL_RGB if n.startswith("floor_")]
    shares = (
        share(surf == FLOOR, floors),
        share(surf == CEILING, ["ceiling"]),
        share(surf == WALL, ["paint", "wallpaper"]),
    )
    print(f"points with their surface's colour (floor, ceiling, walls): {shares}")
    assert min(shares) > 0.85  # the rest lie within a pixel of an edge and blend two surfaces
    # Away from every wall (the shared one included) no blending: every floor/ceiling point exact.
    gt = json.loads((two_rooms / "gt" / "floor_plan.json").read_text())
    p = cloud["points"].astype(np.float64)
    pts2 = shapely.points(p[:, 0], p[:, 2])
    walls = shapely.union_all([Polygon(r["polygon"]).boundary for r in gt["rooms"]])
    far = shapely.distance(walls, pts2) > 0.5
    assert (far & (surf == FLOOR)).sum() > 500
    assert (
        share(far & (surf == FLOOR), floors) == 1.0 and share(far & (surf == CEILING), ["ceiling"]) == 1.0
    )
    # Points of room B are coloured from room B's camera.
    room_b = Polygon(gt["rooms"][1]["polygon"]).buffer(-0.15)
    in_b = shapely.contains_xy(room_b, p[:, 0], p[:, 2])
    names = [str(v) for v in lab["views"]]
    cams_b = {
        i
        for i, n in enumerate(names)
        if Polygon(gt["rooms"][1]["polygon"]).contains(
            shapely.Point(np.asarray(gt["cameras"][n]["position"])[[0, 2]])
        )
    }
    assert cams_b and in_b.sum() > 100
    assert set(np.unique(lab["view"][in_b]).tolist()) <= cams_b


def test_colours_stored_match_own_lookup(two_rooms, gt_union, tmp_path):
    union = gt_union(two_rooms)
    out, folder, _ = _run(two_rooms, union, tmp_path, density=50.0)
    cloud = read_cloud(folder / out.cloud.npz)
    lab = np.load(folder / out.labels)
    scene = load_scene(two_rooms)
    train = scene.manifest.train_views()
    from panogeom.images import read_rgb

    imgs = [read_rgb(scene.image_path(v)) for v in train]
    own = B.colour_points(
        cloud["points"].astype(np.float64), lab["view"].astype(int), [v.pose_matrix for v in train], imgs
    )
    np.testing.assert_allclose(cloud["colors"], own, atol=1e-6)


# ----------------------------------------------------------------------------- colour, exactly


def _expected_pixel(p, pose, h, w):
    """DESIGN.md's mapping, written out independently of panogeom."""
    pose = np.asarray(pose)
    d = np.linalg.inv(pose) @ np.c_[p, np.ones(len(p))].T
    x, y, z = d[:3]
    phi = np.arctan2(x, z)
    theta = np.arctan2(-y, np.hypot(x, z))
    return (phi / (2 * np.pi) + 0.5) * w - 0.5, (0.5 - theta / np.pi) * h - 0.5


def test_colours_are_the_image_at_the_projection(coded_l_scene, coded_l_union, tmp_path):
    out, folder, _ = _run(coded_l_scene, coded_l_union, tmp_path, density=200.0)
    cloud = read_cloud(folder / out.cloud.npz)
    lab = np.load(folder / out.labels)
    assert list(lab["views"]) == ["a", "b"]  # the test view colours nothing
    scene = load_scene(coded_l_scene)
    p = cloud["points"].astype(np.float64)
    col255 = cloud["colors"].astype(np.float64) * 255.0
    view = lab["view"].astype(int)
    np.testing.assert_allclose(col255[:, 2], 100 * view, atol=1e-3)  # B encodes the colouring view
    for j, name in enumerate(["a", "b"]):
        sel = view == j
        c, r = _expected_pixel(p[sel], scene.manifest.view(name).pose, 128, 256)
        r = np.clip(r, 0, 127)
        # Across the seam (c in (255, 255.5] or [-0.5, 0)) the lookup blends column 255 with column 0.
        cw = np.mod(c, 256)
        seam = cw > 255
        exp_r = np.where(seam, 255.0 * (256 - cw), cw)
        np.testing.assert_allclose(col255[sel, 0], exp_r, atol=1e-2)  # float32 points: ~1e-3 px
        np.testing.assert_allclose(col255[sel, 1], r, atol=1e-2)


def test_nearest_view_with_clear_line_of_sight(coded_l_scene, coded_l_union, tmp_path):
    out, folder, _ = _run(coded_l_scene, coded_l_union, tmp_path, density=100.0)
    cloud = read_cloud(folder / out.cloud.npz)
    view = np.load(folder / out.labels)["view"].astype(int)
    scene = load_scene(coded_l_scene)
    cams = [scene.manifest.view(n).position for n in ("a", "b")]
    room = Polygon(coded_l_union.rooms[0].polygon)
    p = cloud["points"].astype(np.float64)
    n = cloud["normals"].astype(np.float64)
    rng = np.random.default_rng(0)
    occluded_nearest = 0
    for i in rng.choice(len(p), 400, replace=False):
        q = p[i, [0, 2]] + 1e-3 * n[i, [0, 2]]
        d = [np.linalg.norm(p[i] - c) for c in cams]
        clear = [room.covers(LineString([c[[0, 2]], q])) for c in cams]
        expected = min((k for k in range(2) if clear[k]), key=lambda k: d[k], default=int(np.argmin(d)))
        assert view[i] == expected
        occluded_nearest += int(not clear[int(np.argmin(d))])
    assert occluded_nearest > 10  # the occlusion test mattered for some points


# ----------------------------------------------------------------------------- failure modes


def test_too_many_points_and_bad_surface_fail_cleanly(coded_l_scene, coded_l_union, tmp_path):
    with pytest.raises(PanoError, match="max_points"):
        _run(coded_l_scene, coded_l_union, tmp_path, density=1000.0, max_points=1000)
    with pytest.raises(ValidationError, match="surfaces"):
        S.Params(surfaces=["walls"])
    with pytest.raises(ValidationError):
        S.Params(density=0)


def test_surfaces_subset(coded_l_scene, coded_l_union, tmp_path):
    out, _, _ = _run(coded_l_scene, coded_l_union, tmp_path, density=100.0, surfaces=["wall"])
    assert out.points_per_surface["floor"] == 0 and out.points_per_surface["ceiling"] == 0
    assert out.points_per_surface["wall"] > 0


def test_two_rooms_of_different_heights():
    rooms = [
        Room(polygon=[(0, 0), (3, 0), (3, 3), (0, 3)], floor_y=0.0, ceiling_y=-2.5, views=["a"]),
        Room(polygon=[(5, 0), (8, 0), (8, 3), (5, 3)], floor_y=0.2, ceiling_y=-3.0, views=["b"]),
    ]
    s = B.sample_rooms(rooms, density=200.0, seed=1, jitter=True, surfaces=SURFACE_NAMES)
    for i, r in enumerate(rooms):
        sel = s.room == i
        assert s.points[sel, 1].min() == pytest.approx(r.ceiling_y) and s.points[
            sel, 1
        ].max() == pytest.approx(r.floor_y)
        w = sel & (s.surface == WALL)
        assert (s.points[w, 1] >= r.ceiling_y).all() and (s.points[w, 1] <= r.floor_y).all()


def test_oblique_walls_and_holes_are_sampled_exactly():
    # A rotated, non-Manhattan room with a pillar (hole): points lie on its planes to float precision.
    ang = np.deg2rad(27.0)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    outer = np.array([(0, 0), (5, 0), (6, 2.5), (3, 4.5), (0, 3)]) @ rot.T + [10.0, -7.0]
    hole = np.array([(2, 1), (2, 2), (3, 2), (3, 1)]) @ rot.T + [10.0, -7.0]  # clockwise
    room = Room(
        polygon=[tuple(p) for p in outer],
        holes=[[tuple(p) for p in hole]],
        floor_y=0.1,
        ceiling_y=-2.7,
        views=["a"],
    )
    poly = Polygon(room.polygon, room.holes)
    s = B.sample_rooms([room], density=300.0, seed=2, jitter=True, surfaces=SURFACE_NAMES)
    p = s.points.astype(np.float32).astype(np.float64)  # as stored
    d = _distance_to_true_shell(p, poly, room.floor_y, room.ceiling_y)
    assert d.max() < 1e-5
    wall = s.surface == WALL
    q_in = p[wall][:, [0, 2]] + 1e-3 * s.normals[wall][:, [0, 2]]
    q_out = p[wall][:, [0, 2]] - 1e-3 * s.normals[wall][:, [0, 2]]
    assert shapely.contains_xy(poly, q_in[:, 0], q_in[:, 1]).all()
    assert not shapely.contains_xy(poly, q_out[:, 0], q_out[:, 1]).any()
    areas = B.surface_areas([room])
    assert wall.sum() == pytest.approx(300.0 * areas["wall"], rel=0.03)
    assert (s.surface == FLOOR).sum() == pytest.approx(300.0 * poly.area, rel=0.03)
