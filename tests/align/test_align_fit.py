"""Layout depth by ray casting, and the robust scale fit, against the simulator's exact depth."""

from __future__ import annotations

import numpy as np
import pytest

from depthalign.clouds import refine_scale_icp, view_rays
from depthalign.scale_fit import fit_scale, values_to_depth
from floorplan.layout_depth import layout_depth, layout_depth_map
from panogeom.equirect import ray_directions
from panogeom.surfaces import CEILING, FLOOR, WALL
from runfs.errors import PanoError
from stages.align import Params, fit_settings

#: the align stage's settings of the fit
DEFAULTS = fit_settings(Params())

H, W = 64, 128


@pytest.fixture(scope="module")
def sims(kit, sim_tmp):
    return {
        "cuboid": kit.make_sim(sim_tmp, "cuboid", views=3, height=H, seed=1),
        "l-shape": kit.make_sim(sim_tmp, "l-shape", views=3, height=H, seed=2),
        "furnished": kit.make_sim(sim_tmp, "cuboid", views=3, height=H, seed=3, furniture=True),
    }


def _layout_maps(sim, kit, tmp):
    lay = kit.layout_from_gt(sim, tmp)
    out = {}
    for lv in lay.data.views:
        out[lv.view] = layout_depth_map(lv.floor_polygon, lv.camera_height, lv.ceiling_distance, H, W)
    return out


@pytest.mark.parametrize("preset", ["cuboid", "l-shape"])
def test_layout_depth_equals_simulator_depth_of_an_empty_room(sims, kit, tmp_path, preset):
    sim = sims[preset]
    maps = _layout_maps(sim, kit, tmp_path)
    for v in sim.train():
        depth, label = maps[v.name]
        gt = sim.gt(v)
        assert np.abs(depth - gt).max() < 1e-4
        # Labels agree with the height of the hit point: floor at camera y = +h, ceiling at y = -d.
        y = -np.sin(np.linspace(np.pi / 2, -np.pi / 2, H, endpoint=False) - np.pi / (2 * H))[:, None] * depth
        h = -v.position[1]
        assert np.allclose(y[label == FLOOR], h, atol=1e-6)
        assert np.all(y[label == WALL] < h + 1e-6)
        assert np.all(label[y < h - 1e-3] != FLOOR)
        assert (label == CEILING).any() and (label == WALL).any()
        # The per-pixel caster and the per-column map agree.
        lv = kit.layout_from_gt(sim, tmp_path / "l2").data.view(v.name)
        d2, l2 = layout_depth(lv.floor_polygon, lv.camera_height, lv.ceiling_distance, ray_directions(H, W))
        assert np.allclose(d2, depth) and np.array_equal(l2, label)


def test_layout_depth_misses_outside_the_polygon():
    # A camera outside the room sees it only in some directions; the rest are misses.
    poly = [(1.0, 1.0), (2.0, 1.0), (2.0, 2.0), (1.0, 2.0)]
    d, lab = layout_depth(poly, 1.5, 1.0, np.array([[1.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    assert np.isclose(d[0], np.sqrt(2)) and lab[0] == WALL
    assert np.isinf(d[1]) and lab[1] == -1
    assert np.isclose(d[2], 1.5) and lab[2] == FLOOR


def _pool(sim, maps, fn, rng):
    vals, lays, gts = [], [], []
    for v in sim.train():
        gt = sim.gt(v)
        vals.append(fn(gt, rng).reshape(-1))
        lays.append(maps[v.name][0].reshape(-1))
        gts.append(gt.reshape(-1))
    return np.concatenate(vals), np.concatenate(lays), np.concatenate(gts)


def _noisy(gt, rng, noise, outliers):
    d = gt * (1 + noise * rng.standard_normal(gt.shape)) if noise else gt.copy()
    if outliers:
        m = rng.random(gt.shape) < outliers
        d[m] = rng.uniform(0.2, 10.0, m.sum())
    return d


@pytest.mark.parametrize("noise,outliers,tol", [(0.0, 0.0, 0.01), (0.05, 0.02, 0.03)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_metric_scale_recovered_despite_furniture(sims, kit, tmp_path, noise, outliers, tol, seed):
    sim = sims["furnished"]  # furniture hides part of the layout: outliers to the fit
    maps = _layout_maps(sim, kit, tmp_path)
    rng = np.random.default_rng(seed)
    k = rng.uniform(0.3, 3.0)
    vals, lays, _ = _pool(sim, maps, lambda gt, r: _noisy(gt, r, noise, outliers) * k, rng)
    fit = fit_scale(vals, lays, "metric", **fit_settings(Params(seed=seed)))
    err = abs(fit.scale * k - 1)
    print(
        f"metric k={k:.3f} noise={noise} outliers={outliers}: "
        f"scale error {err:.4%}, inliers {fit.inlier_share:.2f}"
    )
    assert err < tol
    assert 0.3 < fit.inlier_share <= 1 and fit.residual_m >= 0


@pytest.mark.parametrize("noise,outliers,tol", [(0.0, 0.0, 0.01), (0.05, 0.02, 0.03)])
@pytest.mark.parametrize("seed", [0, 1])
def test_disparity_scale_and_shift_recovered(sims, kit, tmp_path, noise, outliers, tol, seed):
    sim = sims["furnished"]
    maps = _layout_maps(sim, kit, tmp_path)
    rng = np.random.default_rng(10 + seed)
    a, b = rng.uniform(0.3, 3.0), rng.uniform(-0.1, 0.5)  # disparity = a / depth + b
    vals, lays, gts = _pool(sim, maps, lambda gt, r: a / _noisy(gt, r, noise, outliers) + b, rng)
    fit = fit_scale(vals, lays, "disparity", **fit_settings(Params(seed=seed)))
    assert abs(fit.scale * a - 1) < tol  # s = 1/a
    depth = values_to_depth(vals, "disparity", fit.scale, fit.shift)
    clean = values_to_depth(a / gts + b, "disparity", fit.scale, fit.shift)
    err = np.nanmedian(np.abs(clean / gts - 1))
    print(
        f"disparity a={a:.3f} b={b:.3f} noise={noise}: "
        f"scale error {abs(fit.scale * a - 1):.4%}, depth error {err:.4%}"
    )
    assert err < tol and np.isfinite(depth).mean() > 0.9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_affine_inverse_depth_fit_per_view_recovers_scale_and_shift_within_1_percent(
    sims, kit, tmp_path, seed
):
    """One view at a time, as align fits a Depth Anything view: v = a/D + b (a known affine map in
    inverse depth) with 2 % noise and 5 % gross outliers, in a furnished room (furniture is a further
    outlier to the layout). The fit 1/D = s*v + t must give s = 1/a and t = -b/a."""
    sim = sims["furnished"]
    maps = _layout_maps(sim, kit, tmp_path)
    rng = np.random.default_rng(100 + seed)
    for v in sim.train():
        a, b = rng.uniform(0.2, 5.0), rng.uniform(-0.3, 1.0)
        gt = sim.gt(v)
        vals = a / _noisy(gt, rng, 0.02, 0.05) + b
        fit = fit_scale(vals, maps[v.name][0], "disparity", **fit_settings(Params(seed=seed)))
        s_err = abs(fit.scale * a - 1)
        t_err = abs(fit.shift + b / a) / np.median(1 / gt)  # relative to the view's typical inverse depth
        print(
            f"per-view affine inverse depth a={a:.3f} b={b:.3f}: "
            f"scale error {s_err:.3%}, shift error {t_err:.3%}"
        )
        assert s_err < 0.01 and t_err < 0.01


def test_relative_depth_scale_and_shift_recovered(sims, kit, tmp_path):
    sim = sims["furnished"]
    maps = _layout_maps(sim, kit, tmp_path)
    rng = np.random.default_rng(5)
    a, b = 2.2, -0.7  # relative value = a * depth + b
    vals, lays, gts = _pool(sim, maps, lambda gt, r: a * gt + b, rng)
    fit = fit_scale(vals, lays, "relative", **DEFAULTS)
    assert abs(fit.scale * a - 1) < 0.01 and abs(fit.shift - (-b / a)) < 0.01
    assert fit.residual_m < 1e-3


def test_masked_pixels_are_ignored(sims, kit, tmp_path):
    sim = sims["cuboid"]
    maps = _layout_maps(sim, kit, tmp_path)
    rng = np.random.default_rng(3)

    def broken(gt, r):
        d = gt * 0.5
        m = r.random(gt.shape)
        d[m < 0.2] = np.nan
        d[(m >= 0.2) & (m < 0.4)] = 0.0
        d[(m >= 0.4) & (m < 0.45)] = np.inf
        return d

    vals, lays, _ = _pool(sim, maps, broken, rng)
    fit = fit_scale(vals, lays, "metric", **DEFAULTS)
    assert abs(fit.scale - 2.0) < 1e-3
    assert fit.num_pixels == np.isfinite(vals[vals > 0]).sum()


def test_refuses_depth_that_disagrees_with_the_layout(sims, kit, tmp_path):
    sim = sims["cuboid"]
    maps = _layout_maps(sim, kit, tmp_path)
    vals, lays, _ = _pool(sim, maps, lambda gt, r: r.uniform(0.5, 8.0, gt.shape), np.random.default_rng(0))
    with pytest.raises(PanoError) as e:
        fit_scale(vals, lays, "metric", **fit_settings(Params(inlier_threshold=0.05, min_inlier_share=0.5)))
    assert "agree" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(PanoError, match="only 5 valid"):
        fit_scale(np.ones(5), np.ones(5), "metric", **DEFAULTS)


def test_scale_only_icp_recovers_a_residual_scale(sims, kit, tmp_path):
    sim = sims["cuboid"]
    lc = kit.sampling_from_gt(sim, tmp_path / "samp", spacing=0.04)
    from stages.cloud_io import read_cloud

    cloud = read_cloud(lc.path(lc.data.cloud.npz))
    rays, cents = [], []
    for v in sim.train():
        r, _, c = view_rays(sim.gt(v) * 1.03, v.pose_matrix)
        rays.append(r)
        cents.append(np.broadcast_to(c, r.shape))
    lam, stats = refine_scale_icp(
        np.concatenate(cents), np.concatenate(rays), cloud["points"], cloud["normals"], max_distance=0.2,
        iterations=Params().icp_iterations
    )
    assert abs(lam * 1.03 - 1) < 2e-3
    assert stats["fitness"] > 0.9 and stats["rmse_m"] < 0.02
