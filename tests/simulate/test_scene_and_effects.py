"""The scene folder, cameras, effects bookkeeping, determinism, API and command."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import MultiPoint, Point, Polygon

import simulate
from schemas.scene import SceneManifest
from simulate import effects as fx
from simulate.generate import parse_effects

H = 64  # the conftest scenes' image height


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# ----------------------------------------------------------------------------- scene folder


@pytest.mark.parametrize("preset", ["cuboid", "l-shape", "two-rooms", "demo"])
def test_scene_folder_complete_and_valid(scenes, preset):
    scene = scenes[(preset, "furniture")]
    m = SceneManifest.model_validate_json((scene.root / "scene.json").read_text())
    assert m.floor_plan == "gt/floor_plan.json"
    assert [v.split for v in m.views] == ["train"] * 3 + ["test"] * 2
    for v in m.views:
        img = scene.image(v.name)
        assert img.dtype == np.uint8 and img.shape == (H, 2 * H, 3)  # 2:1 RGB
        assert (scene.root / v.gt_depth).is_file() and v.gt_depth == f"gt/depth/{v.name}.npy"
        d = scene.depth(v.name)
        assert d.dtype == np.float32 and d.shape == (H, 2 * H) and np.all(np.isfinite(d)) and d.min() > 0
        assert scene.layout(v.name).dtype == np.float32
        assert (scene.root / "gt" / "layout" / f"{v.name}.json").is_file()
        pose = v.pose_matrix
        r = pose[:3, :3]
        assert np.abs(r.T @ r - np.eye(3)).max() < 1e-12 and np.linalg.det(r) == pytest.approx(1.0)
        assert np.allclose(r[:, 1], [0, 1, 0]) and np.allclose(r[1], [0, 1, 0])  # level, yaw only
        assert 1.2 <= v.camera_height <= 1.7
        if v.split == "train":  # --with-layout / --with-depth inputs: train views only
            assert v.layout and (scene.root / v.layout).is_file()
            assert v.depth == f"depth/{v.name}.png" and (scene.root / v.depth).is_file()
        else:
            assert v.layout is None and v.depth is None
            assert not (scene.root / "layout" / f"{v.name}.json").exists()
            assert not (scene.root / "depth" / f"{v.name}.png").exists()
    # Yaws differ between views (pose handling is exercised).
    yaws = [np.arctan2(v.pose_matrix[0, 2], v.pose_matrix[0, 0]) for v in m.views]
    assert len(set(np.round(yaws, 6))) == len(yaws)


@pytest.mark.parametrize("preset", ["cuboid", "l-shape", "two-rooms", "demo"])
def test_floor_plan(scenes, preset):
    fp = scenes[(preset, "furniture")].floor_plan
    rooms = [Polygon(r["polygon"]) for r in fp["rooms"]]
    for r, poly in zip(fp["rooms"], rooms):
        x, z = np.asarray(r["polygon"]).T
        assert 0.5 * np.sum(x * np.roll(z, -1) - np.roll(x, -1) * z) > 0  # CCW in (x, z)
        assert r["floor_y"] == 0.0 and -3.2 <= r["ceiling_y"] <= -2.4
    union = rooms[0].union(rooms[1]) if len(rooms) > 1 else rooms[0]
    outline = Polygon(fp["outline"])
    assert outline.symmetric_difference(union).area < 1e-9
    if preset == "two-rooms":
        assert len(fp["doorways"]) == 1 and fp["doorways"][0]["rooms"] == [0, 1]
        assert -2.2 <= fp["doorways"][0]["top_y"] <= -2.0
    if preset in ("l-shape", "demo"):
        assert len(fp["rooms"][0]["polygon"]) == 6
    assert fp["furniture"], "furniture effect on: boxes expected"
    for b in fp["furniture"]:
        assert b["max"][1] == 0.0 and b["min"][1] < 0  # standing on the floor (y down)


@pytest.mark.parametrize("preset", ["cuboid", "l-shape", "two-rooms", "demo"])
def test_cameras_distinct_inside_and_never_in_furniture(scenes, preset):
    scene = scenes[(preset, "furniture")]
    fp = scene.floor_plan
    pos = {k: np.asarray(v["position"]) for k, v in fp["cameras"].items()}
    outline = Polygon(fp["outline"])
    names = list(pos)
    for i, a in enumerate(names):
        p = pos[a]
        assert outline.buffer(-0.45).contains(Point(p[0], p[2]))
        for b in fp["furniture"]:
            lo, hi = np.asarray(b["min"])[[0, 2]], np.asarray(b["max"])[[0, 2]]
            clearance = np.linalg.norm(np.clip(p[[0, 2]], lo, hi) - p[[0, 2]])
            assert clearance > 0.35, f"camera {a} in/at furniture {b['kind']} ({clearance:.3f} m)"
        for b_ in names[i + 1 :]:
            assert np.linalg.norm(p - pos[b_]) > 0.25, f"cameras {a} and {b_} coincide"
    train = [n for n in names if fp["cameras"][n]["split"] == "train"]
    test = [n for n in names if fp["cameras"][n]["split"] == "test"]
    assert set(train).isdisjoint(test) and len(test) == 2


def test_demo_preset_learnable_layout(tmp_path):
    """Demo: 4 train + 2 test at 256x512 by default, test cameras inside the train hull and
    within 1 m of a train camera, no noise in its 'all'."""
    res = simulate.generate_scene(tmp_path / "demo", preset="demo", views=4, test_views=2, height=32, seed=0)
    assert "noise" not in res.effects and set(res.effects) == {"texture", "furniture", "shading", "aa"}
    fp = json.loads((tmp_path / "demo" / "gt" / "floor_plan.json").read_text())
    cams = fp["cameras"]
    train = np.array([cams[k]["position"] for k in cams if cams[k]["split"] == "train"])[:, [0, 2]]
    test = np.array([cams[k]["position"] for k in cams if cams[k]["split"] == "test"])[:, [0, 2]]
    hull = MultiPoint([tuple(p) for p in train]).convex_hull
    for p in test:
        assert hull.buffer(1e-6).contains(Point(*p))
        assert np.linalg.norm(train - p, axis=1).min() <= 1.0
    assert len(fp["rooms"][0]["polygon"]) == 6  # L-shape


# ----------------------------------------------------------------------------- effects


class _Counter:
    def __init__(self, monkeypatch):
        names = ("texture", "furniture", "shading", "noise", "exposure", "tripod", "antialias", "plain_floor",
                 "fixtures")
        self.calls = {n: 0 for n in names}
        for name in self.calls:
            original = getattr(fx, name)
            monkeypatch.setattr(fx, name, self._wrap(name, original))

    def _wrap(self, name, original):
        def wrapper(*args, **kwargs):
            self.calls[name] += 1
            return original(*args, **kwargs)

        return wrapper


@pytest.mark.parametrize(
    "effects, expected",
    [
        ("none", set()),
        ("texture", {"texture"}),
        ("furniture", {"furniture"}),
        ("shading", {"shading"}),
        ("noise", {"noise"}),
        ("exposure", {"exposure"}),
        ("tripod", {"tripod"}),
        ("aa", {"antialias"}),
        ("plain-floor", {"plain_floor"}),
        ("fixtures", {"fixtures"}),
        ("all", {"texture", "furniture", "shading", "noise", "exposure", "tripod", "antialias"}),
    ],
)
def test_effects_off_are_never_evaluated(tmp_path, monkeypatch, effects, expected):
    counter = _Counter(monkeypatch)
    res = simulate.generate_scene(
        tmp_path / "s", preset="two-rooms", views=2, test_views=1, height=16, seed=0, effects=effects
    )
    called = {k for k, v in counter.calls.items() if v > 0}
    assert called == expected
    # Only the effects that ran show up in the profile.
    timed = set(res.timings) & {"texture", "furniture", "shading", "noise", "exposure", "tripod", "aa", "fixtures"}
    # (plain-floor only marks the floor plain: nothing to time)
    # (the lamps of `fixtures` are boxes: their ray-box tests are timed with the furniture's)
    assert timed == {("aa" if e == "antialias" else e) for e in expected if e != "plain_floor"} | (
        {"furniture"} if "fixtures" in expected else set())


def test_effects_do_change_the_image(tmp_path):
    base = simulate.generate_scene(tmp_path / "a", preset="cuboid", views=1, test_views=0, height=32, seed=2,
                                   effects="none")
    import cv2

    img0 = cv2.imread(str(base.out_dir / "images" / "train_00.png")).astype(int)
    for e in simulate.EFFECTS:
        if e == "plain-floor":  # it takes the floor's texture away: nothing to take without `texture`
            base_img = cv2.imread(str(simulate.generate_scene(
                tmp_path / "texture-only", preset="cuboid", views=1, test_views=0, height=32, seed=2,
                effects="texture").out_dir / "images" / "train_00.png")).astype(int)
            e, reference = "texture,plain-floor", base_img
        elif e == "fixtures":  # a disc a pixel wide at this size: test_fixtures_... checks it
            continue
        else:
            reference = img0
        r = simulate.generate_scene(
            tmp_path / e, preset="cuboid", views=1, test_views=0, height=32, seed=2, effects=e
        )
        img = cv2.imread(str(r.out_dir / "images" / "train_00.png")).astype(int)
        assert np.abs(img - reference).mean() > 0.2, f"effect {e} changed nothing"
        # Geometry and cameras do not depend on the effects (independent random streams).
        a = json.loads((base.out_dir / "scene.json").read_text())["views"][0]["pose"]
        b = json.loads((r.out_dir / "scene.json").read_text())["views"][0]["pose"]
        assert a == b


def test_fixtures_are_saturated_lamps_hanging_where_the_lights_are(tmp_path):
    import cv2

    def image(effects):
        r = simulate.generate_scene(tmp_path / effects, preset="cuboid", views=1, test_views=0, height=64, seed=2,
                                    effects=effects)
        return cv2.imread(str(r.out_dir / "images" / "train_00.png")).astype(int), r.out_dir

    shaded, _ = image("shading")
    lit, out = image("shading,fixtures")
    changed = np.abs(lit - shaded).max(-1) > 0
    rows, cols = np.nonzero(changed)
    assert changed.sum() >= 10 and rows.max() < 32  # above the horizon: on the ceiling
    assert (lit[changed] >= 250).all()  # saturated, as a lamp is
    # in the direction of the cuboid's one light (the lamp's underside)
    from panogeom.equirect import angles_to_pixel, dirs_to_angles

    lamp = np.array(json.loads((out / "gt" / "floor_plan.json").read_text())["lights"][0]["position"])
    pose = np.array(json.loads((out / "scene.json").read_text())["views"][0]["pose"])  # camera to world
    col, row = angles_to_pixel(*dirs_to_angles(pose[:3, :3].T @ (lamp - pose[:3, 3])), 64, 128)
    assert abs(((cols.mean() - col + 64) % 128) - 64) < 3 and abs(rows.mean() - row) < 4


def test_noise_free_scene_is_flat_per_material(tmp_path):
    """Without texture/shading/noise/aa each surface has one colour: exactly the material table."""
    import cv2

    r = simulate.generate_scene(tmp_path / "s", preset="cuboid", views=1, test_views=0, height=32, seed=0,
                                effects="none")
    img = cv2.imread(str(r.out_dir / "images" / "train_00.png"))
    assert len(np.unique(img.reshape(-1, 3), axis=0)) <= 4  # floor, ceiling, paint, wallpaper


def test_parse_effects():
    assert parse_effects("all") == set(simulate.EFFECTS) - {"detail", "plain-floor", "fixtures"}  # opt-in effects
    assert parse_effects("none") == set()
    assert parse_effects("texture, aa") == {"texture", "aa"}
    assert parse_effects({"noise"}) == {"noise"}
    assert {"exposure", "tripod"} <= parse_effects("all")
    assert parse_effects("all", "demo") == {"texture", "furniture", "shading", "aa"}
    with pytest.raises(ValueError, match="unknown effect"):
        parse_effects("texture,blur")


# ----------------------------------------------------------------------------- determinism, API


def test_deterministic_for_a_seed(tmp_path):
    kw = dict(preset="l-shape", views=2, test_views=1, height=16, effects="all")
    kw |= dict(with_layout=True, with_depth=True)
    simulate.generate_scene(tmp_path / "a", seed=5, **kw)
    simulate.generate_scene(tmp_path / "b", seed=5, **kw)
    simulate.generate_scene(tmp_path / "c", seed=6, **kw)
    da, db, dc = _digest(tmp_path / "a"), _digest(tmp_path / "b"), _digest(tmp_path / "c")
    # scene.json names the scene after its folder; compare it without the name.
    for d, root in ((da, "a"), (db, "b")):
        m = json.loads((tmp_path / root / "scene.json").read_text())
        m.pop("name")
        d["scene.json"] = json.dumps(m)
    assert da == db
    assert da["images/train_00.png"] != dc["images/train_00.png"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(preset="castle"), "unknown preset"),
        (dict(views=0), "--views"),
        (dict(test_views=-1), "--test-views"),
        (dict(height=15), "--height"),
        (dict(height=8), "--height"),
        (dict(aa_samples=0), "--aa-samples"),
        (dict(seed=-1), "--seed"),
        (dict(effects="sparkle"), "unknown effect"),
    ],
)
def test_bad_arguments_raise_value_error(tmp_path, kwargs, match):
    args = dict(preset="cuboid", views=1, test_views=0, height=16, seed=0, effects="none") | kwargs
    with pytest.raises(ValueError, match=match):
        simulate.generate_scene(tmp_path / "s", **args)
    assert not (tmp_path / "s").exists()


def test_output_replaced_atomically(tmp_path, monkeypatch):
    out = tmp_path / "scene"
    simulate.generate_scene(out, preset="cuboid", views=1, test_views=0, height=16, seed=0, effects="none")
    before = _digest(out)

    import simulate.generate as gen

    def boom(*a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(gen, "render_view", boom)
    with pytest.raises(RuntimeError):
        simulate.generate_scene(
            out, preset="cuboid", views=2, test_views=0, height=16, seed=1, effects="none"
        )
    assert _digest(out) == before  # untouched on failure
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temp folders left
    monkeypatch.undo()
    simulate.generate_scene(out, preset="cuboid", views=2, test_views=0, height=16, seed=1, effects="none")
    assert len(json.loads((out / "scene.json").read_text())["views"]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_fast_grid_cast_equals_generic_cast():
    """The separable equirectangular fast path gives the same hits as the plain ray caster."""
    from panogeom.equirect import column_longitudes, row_latitudes
    from simulate.geometry import build_world, place_cameras
    from simulate.raycast import cast, cast_grid

    rng = np.random.default_rng(0)
    world = build_world("two-rooms", rng)
    cams = place_cameras(world, 2, 1, rng)
    boxes = fx.furniture(world, cams, rng)
    assert boxes
    for cam in cams:
        lat, lon = row_latitudes(48), column_longitudes(96)
        hits, dirs = cast_grid(cam.position, cam.rotation, lat, lon, world, boxes)
        ref = cast(cam.position, dirs, world, boxes)
        np.testing.assert_allclose(hits.t, ref.t, rtol=1e-9)
        assert np.array_equal(hits.sid, ref.sid)
        assert np.array_equal(hits.box_axis, ref.box_axis)


def test_command_profile(tmp_path):
    typer = pytest.importorskip("typer")
    from typer.testing import CliRunner

    from simulate.command import simulate_command

    app = typer.Typer()
    app.command()(simulate_command)
    out = tmp_path / "s"
    r = CliRunner().invoke(
        app,
        [str(out), "--preset", "cuboid", "--views", "1", "--test-views", "1", "--height", "16", "--profile"],
    )
    assert r.exit_code == 0, r.output
    assert "total" in r.output and "texture" in r.output
    assert "tripod" in r.output and "exposure" in r.output  # 'all' includes the capture effects
    assert (out / "scene.json").is_file()
    r = CliRunner().invoke(app, [str(out), "--preset", "nope"])
    assert r.exit_code != 0 and isinstance(r.exception, ValueError)


def test_test_cameras_away_from_the_training_ones():
    """`test_placement="away"`: every test camera >= AWAY_MIN_DISTANCE from every train camera, spread
    over both rooms; the default ("near") placement is unchanged by the option."""
    from simulate.geometry import AWAY_MIN_DISTANCE, build_world, place_cameras

    def cams(placement):
        rng = np.random.default_rng(3)
        world = build_world("two-rooms", np.random.default_rng(4))
        return world, place_cameras(world, 4, 8, rng, test_placement=placement)

    world, away = cams("away")
    train = np.array([c.position[[0, 2]] for c in away if c.split == "train"])
    test = np.array([c.position[[0, 2]] for c in away if c.split == "test"])
    assert len(test) == 8
    d = np.linalg.norm(test[:, None] - train[None], axis=2).min(axis=1)
    assert d.min() >= AWAY_MIN_DISTANCE
    rooms = {next(i for i, r in enumerate(world.rooms) if r.shape.buffer(1e-6).contains(Point(*p))) for p in test}
    assert rooms == {0, 1}
    _, near = cams("near")
    near_test = np.array([c.position[[0, 2]] for c in near if c.split == "test"])
    assert np.linalg.norm(near_test[:, None] - train[None], axis=2).min(axis=1).max() <= 1.0 + 1e-9
    with pytest.raises(ValueError, match="test placement"):
        cams("far")
