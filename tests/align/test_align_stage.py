"""The align stage end to end on simulator scenes: fitted scale, merged cloud accuracy, layout points kept."""

from __future__ import annotations

import numpy as np
import pytest

from runfs.errors import PanoError
from stages.cloud_io import read_cloud

H = 64


@pytest.fixture(scope="module")
def empty_room(kit, sim_tmp):
    return kit.make_sim(sim_tmp, "l-shape", views=3, height=H, seed=4)


def _scaled_depth(sim, k, nan_share=0.0, seed=0):
    rng = np.random.default_rng(seed)
    maps = {}
    for v in sim.train():
        d = sim.gt(v) * k
        if nan_share:
            m = rng.random(d.shape)
            d[m < nan_share] = np.nan
            d[(m >= nan_share) & (m < 2 * nan_share)] = 0.0
        maps[v.name] = d
    return maps


@pytest.fixture(scope="module")
def furnished_room(kit, sim_tmp):
    return kit.make_sim(sim_tmp, "demo", views=3, height=H, seed=0, furniture=True)


@pytest.mark.parametrize("room", ["empty_room", "furnished_room"])
def test_scaled_depth_is_aligned_and_merged_within_2cm(kit, room, request, tmp_path):
    sim = request.getfixturevalue(room)
    k = float(np.random.default_rng(7).uniform(0.3, 3.0))
    depth = kit.depth_loaded(tmp_path / "depth", _scaled_depth(sim, k, nan_share=0.05))
    layout = kit.layout_from_gt(sim, tmp_path / "layout")
    sampling = kit.sampling_from_gt(sim, tmp_path / "sampling", spacing=0.05)
    out, folder = kit.run_align(sim, tmp_path, depth, layout, sampling)
    print(
        f"align stage: k={k:.3f} scale error {abs(out.scale * k - 1):.4%}, "
        f"ICP factor {out.fits[0].icp_factor:.5f}"
    )
    assert abs(out.scale * k - 1) < 0.01
    assert out.aligned_to_layout and out.inlier_share > 0.9 and out.residual_m < 0.01

    cloud = read_cloud(folder / out.cloud.npz)
    assert (folder / out.cloud.ply).is_file()
    lay = cloud["is_layout"]
    ref = read_cloud(sampling.path(sampling.data.cloud.npz))
    assert lay.sum() == len(ref["points"]) == out.cloud.num_layout_points
    assert np.array_equal(cloud["normals"][lay], ref["normals"]) and np.array_equal(
        cloud["u0"][lay], ref["u0"]
    )
    dp = cloud["points"][~lay]
    assert len(dp) > 1000
    assert np.all(cloud["normals"][~lay] == 0) and np.array_equal(cloud["u0"][~lay], dp)
    dist = sim.surface_distance(dp)
    print(
        f"merged depth cloud: {len(dp)} points, "
        f"95th percentile distance {np.percentile(dist, 95) * 100:.2f} cm"
    )
    assert np.mean(dist < 0.02) >= 0.95
    # NaN / zero pixels were masked: nothing lands at a camera centre.
    cams = np.array([v.position for v in sim.train()])
    assert np.min(np.linalg.norm(dp[:, None] - cams[None], axis=2)) > 0.3
    # Colours come from the images.
    assert cloud["colors"][~lay].std() > 0.01


def test_without_layout_depth_is_used_as_is(kit, empty_room, tmp_path):
    sim = empty_room
    depth = kit.depth_loaded(tmp_path / "depth", _scaled_depth(sim, 1.0))
    out, folder = kit.run_align(sim, tmp_path, depth, None, None)
    assert out.scale == 1.0 and not out.aligned_to_layout and out.inlier_share is None
    cloud = read_cloud(folder / out.cloud.npz)
    assert cloud["is_layout"].sum() == 0
    assert np.mean(sim.surface_distance(cloud["points"]) < 0.02) >= 0.95


def test_disparity_without_layout_is_refused(kit, empty_room, tmp_path):
    maps = {n: 1.0 / d for n, d in _scaled_depth(empty_room, 1.0).items()}
    depth = kit.depth_loaded(tmp_path / "depth", maps, kind="disparity")
    with pytest.raises(PanoError, match="needs a layout"):
        kit.run_align(empty_room, tmp_path, depth, None, None)


def test_disparity_stage_with_layout(kit, empty_room, tmp_path):
    sim = empty_room
    a, b = 1.7, 0.3
    maps = {n: a / d + b for n, d in _scaled_depth(sim, 1.0).items()}
    depth = kit.depth_loaded(tmp_path / "depth", maps, kind="disparity")
    layout = kit.layout_from_gt(sim, tmp_path / "layout")
    sampling = kit.sampling_from_gt(sim, tmp_path / "sampling", spacing=0.05)
    out, folder = kit.run_align(sim, tmp_path, depth, layout, sampling)
    assert abs(out.scale * a - 1) < 0.01 and abs(out.shift + b / a) < 0.01
    cloud = read_cloud(folder / out.cloud.npz)
    assert np.mean(sim.surface_distance(cloud["points"][~cloud["is_layout"]]) < 0.02) >= 0.95


def test_affine_view_without_a_layout_is_left_out_with_a_warning(kit, empty_room, tmp_path):
    """A view the layout stage could not read: its affine inverse depth cannot be placed, the others can."""
    sim = empty_room
    maps = {n: 1.7 / d + 0.3 for n, d in _scaled_depth(sim, 1.0).items()}
    depth = kit.depth_loaded(tmp_path / "depth", maps, kind="disparity")
    layout = kit.layout_from_gt(sim, tmp_path / "layout")
    kept, dropped = layout.data.views[0].view, [lv.view for lv in layout.data.views[1:]]
    assert dropped  # the room has several train views
    layout.data.views = layout.data.views[:1]
    sampling = kit.sampling_from_gt(sim, tmp_path / "sampling", spacing=0.05)
    from runtime.stage import StageContext
    from stages import align

    folder = tmp_path / "align-out"
    folder.mkdir()
    ctx = StageContext(scene=sim.scene, params=align.Params(),
                       inputs={"depth": depth, "layout": layout, "sampling": sampling}, out_dir=folder)
    out = align.run(ctx)
    assert [f.views for f in out.fits] == [[kept]] and abs(out.scale * 1.7 - 1) < 0.01
    assert any(all(name in w for name in dropped) and "left out" in w for w in ctx.warnings)
    cloud = read_cloud(folder / out.cloud.npz)
    assert np.mean(sim.surface_distance(cloud["points"][~cloud["is_layout"]]) < 0.02) >= 0.95


def test_garbage_depth_is_refused_with_one_line(kit, empty_room, tmp_path):
    rng = np.random.default_rng(0)
    maps = {v.name: rng.uniform(0.5, 9.0, (H, 2 * H)) for v in empty_room.train()}
    depth = kit.depth_loaded(tmp_path / "depth", maps)
    layout = kit.layout_from_gt(empty_room, tmp_path / "layout")
    with pytest.raises(PanoError) as e:
        kit.run_align(empty_room, tmp_path, depth, layout, None, inlier_threshold=0.03, min_inlier_share=0.5)
    assert "agree with the layout" in str(e.value) and "\n" not in str(e.value)


def test_registry_pipeline_up_to_align_with_scaled_files(tmp_path):
    """The real DAG up to align: layout from the simulator's HorizonNet JSON, union, sampling, depth files."""
    import cv2

    from pipeline.engine import Engine
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene
    from simulate import generate_scene

    res = generate_scene(
        tmp_path / "scene",
        "l-shape",
        views=2,
        test_views=1,
        height=64,
        seed=3,
        effects="texture,furniture",
        aa_samples=1,
        with_layout=True,
        with_depth=True,
    )
    k = 2.3
    for p in (res.out_dir / "depth").glob("*.png"):
        mm = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64)
        cv2.imwrite(str(p), np.clip(mm * k, 0, 65535).astype(np.uint16))
    engine = Engine(
        load_scene(res.out_dir), tmp_path / "run", build_registry(), {"sampling": {"density": 100.0}}
    )
    results = {r.name: r.outcome for r in engine.run(target="align")}
    assert results == {"poses": "skipped", "layout": "ran", "depth": "ran", "union": "ran", "sampling": "ran",
                       "align": "ran"}
    from pipeline.engine import load_artifact
    from stages import align

    out = load_artifact(tmp_path / "run" / "align", align.Output).data
    print(f"registry pipeline: scale error {abs(out.scale * k - 1):.4%}")
    assert abs(out.scale * k - 1) < 0.01 and out.inlier_share > 0.5
    # Unchanged inputs: the second run is cached.
    again = {r.name: r.outcome for r in engine.run(until="align")}
    assert again["align"] == "cached" and again["depth"] == "cached"


def test_rescaling_metric_depth_to_an_assumed_camera_height_warns(kit, empty_room, tmp_path):
    from runtime.stage import StageContext
    from stages import align

    sim = empty_room
    depth = kit.depth_loaded(tmp_path / "depth", _scaled_depth(sim, 1.5))
    layout = kit.layout_from_gt(sim, tmp_path / "layout")
    for lv in layout.data.views:
        lv.camera_height_assumed = True
    ctx = StageContext(
        scene=sim.scene,
        params=align.Params(),
        inputs={"depth": depth, "layout": layout, "sampling": None},
        out_dir=tmp_path / "out",
    )
    out = align.run(ctx)
    assert abs(out.scale * 1.5 - 1) < 0.01
    assert any("assumed" in w for w in ctx.warnings)
