"""gradcheck in float64, cpp vs torch agreement, hypothesis property tests."""

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import splatting
from splat_helpers import BACKENDS, all_finite, dense_render, eye, random_scene


def _render_fn(backend, camera, with_viewmat=False, sh=False):
    def f(means, quats, scales, op, col, *rest):
        vm = rest[0] if with_viewmat else eye()
        bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)
        out = splatting.render(means, quats, scales, op, col, vm, camera, backend=backend, background=bg,
                               sh_degree=1 if sh else None)
        return out.image, out.depth, out.alpha

    return f


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_gradcheck_equirect(backend, seed):
    scene = random_scene(6, seed=seed, spread=1.2, scale=(0.15, 0.5), opacity=(0.2, 0.9))
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, 3] = torch.tensor([0.1, -0.05, 0.2])
    inputs = [x.clone().requires_grad_(True) for x in scene] + [vm.requires_grad_(True)]
    assert torch.autograd.gradcheck(_render_fn(backend, splatting.EquirectCamera(12, 24), with_viewmat=True), inputs,
                                    eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_sh_and_pinhole(backend):
    means, quats, scales, op, _ = random_scene(5, seed=2, spread=0.6, scale=(0.1, 0.3), opacity=(0.2, 0.9))
    means = means + torch.tensor([0.0, 0.0, 2.5], dtype=torch.float64)
    sh = torch.randn(5, 4, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.3
    inputs = [x.clone().requires_grad_(True) for x in (means, quats, scales, op, sh)]
    cam = splatting.PinholeCamera(10.0, 11.0, 8.0, 6.0, 16, 12)
    assert torch.autograd.gradcheck(_render_fn(backend, cam, sh=True), inputs, eps=1e-6, atol=1e-5, rtol=1e-4,
                                    fast_mode=True)


def test_gradients_match_dense_autograd_reference():
    """The hand-written backward equals plain autograd through the dense reference."""
    scene = [x.clone().requires_grad_(True) for x in random_scene(15, seed=3, scale=(0.05, 0.5))]
    cam = splatting.EquirectCamera(12, 24)
    w = torch.rand(12, 24, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    color, depth, alpha = dense_render(*scene, eye(), cam)
    ref = torch.autograd.grad((color * w).sum() + depth.sum() + alpha.sum(), scene)
    for backend in BACKENDS:
        out = splatting.render(*scene, eye(), cam, backend=backend)
        got = torch.autograd.grad((out.image * w).sum() + out.depth.sum() + out.alpha.sum(), scene)
        for a, b in zip(got, ref):
            torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-8)


def _agree(scene, cam, dtype, img_tol=1e-5, grad_rel=1e-4, depth_alpha=True):
    outs, grads = {}, {}
    w = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(dtype)
    for backend in BACKENDS:
        params = [x.clone().to(dtype).requires_grad_(True) for x in scene]
        out = splatting.render(*params, eye(dtype), cam, backend=backend)
        loss = (out.image * w).sum()
        if depth_alpha:
            loss = loss + 0.3 * out.depth.sum() + out.alpha.sum()
        loss.backward()
        outs[backend] = out
        grads[backend] = [p.grad for p in params] + [out.means2d.grad]
    a, b = outs["torch"], outs["cpp"]
    for x, y in ((a.image, b.image), (a.alpha, b.alpha)):
        assert float((x - y).detach().abs().max()) <= img_tol
    assert float((a.depth - b.depth).detach().abs().max()) <= img_tol * max(1.0, float(a.depth.detach().abs().max()))
    for ga, gb in zip(grads["torch"], grads["cpp"]):
        scale = float(ga.abs().max())
        assert float((ga - gb).abs().max()) <= grad_rel * max(scale, 1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cpp_and_torch_agree(dtype, seed):
    scene = random_scene(60, seed=seed, spread=1.5, scale=(0.02, 0.4))
    _agree(scene, splatting.EquirectCamera(24, 48), dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_and_torch_agree_on_an_image_only_loss(dtype):
    """No gradient into depth and alpha (as in training): the CPU kernel's backward leaves
    their terms out, and must still agree with the torch backend."""
    scene = random_scene(60, seed=5, spread=1.5, scale=(0.02, 0.4))
    _agree(scene, splatting.EquirectCamera(24, 48), dtype, depth_alpha=False)


finite = dict(allow_nan=False, allow_infinity=False)


@st.composite
def gaussians(draw, max_n=6):
    n = draw(st.integers(1, max_n))
    rows = []
    for _ in range(n):
        phi = draw(st.sampled_from([math.pi, -math.pi, 0.0]) | st.floats(-math.pi, math.pi, **finite))
        theta = draw(st.sampled_from([math.pi / 2, -math.pi / 2]) | st.floats(-math.pi / 2, math.pi / 2, **finite))
        # (not exactly at near = 0.05: there the cull depends on the rounding of ‖t‖, per backend)
        dist = draw(st.floats(0.0, 20.0, **finite).filter(lambda d: abs(d - 0.05) > 1e-9) | st.sampled_from([1e-6, 0.0499, 0.0501, 1e4]))
        mean = [dist * math.cos(theta) * math.sin(phi), -dist * math.sin(theta), dist * math.cos(theta) * math.cos(phi)]
        quat = draw(st.lists(st.floats(-1, 1, **finite), min_size=4, max_size=4))
        scales = [10 ** draw(st.floats(-9, 3, **finite)) for _ in range(3)]
        op = draw(st.floats(0.0, 1.0, **finite))
        col = draw(st.lists(st.floats(0, 1, **finite), min_size=3, max_size=3))
        rows.append((mean, quat, scales, op, col))
    t = lambda i: torch.tensor([r[i] for r in rows], dtype=torch.float64)
    return [t(0), t(1), t(2), t(3), t(4)]


# derandomize: the same examples on every run, so CI never meets a new one by chance
@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(scene=gaussians(), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_property_finite_and_backends_agree(scene, dtype):
    cam = splatting.EquirectCamera(8, 16)
    res = {}
    for backend in BACKENDS:
        params = [x.to(dtype).requires_grad_(True) for x in scene]
        out = splatting.render(*params, eye(dtype), cam, backend=backend)
        assert all_finite(out.image, out.alpha, out.depth)
        assert float(out.alpha.detach().min()) >= 0 and float(out.alpha.detach().max()) <= 1
        # colours are convex combinations: never above the brightest Gaussian
        assert float(out.image.detach().max()) <= float(params[4].detach().max()) + 1e-5
        (out.image.sum() + out.alpha.sum() + 1e-3 * out.depth.sum()).backward()
        for p in params:
            assert all_finite(p.grad)
        assert all_finite(out.means2d.grad)
        res[backend] = out
    # float32: a 100 m-wide splat's conic sums terms ~1e4 apart; the two kernels' operation
    # order then differs by a few ulps of the power (seen: 1.4e-5 in an image value)
    tol = 1e-5 if dtype == torch.float64 else 5e-5
    assert float((res["cpp"].image - res["torch"].image).detach().abs().max()) <= tol


@settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(scene=gaussians(max_n=5))
def test_property_boxes_are_conservative(scene):
    """The pixel boxes used for binning never drop a pixel the exact test would keep:
    the binned render equals the dense every-pixel render (float64)."""
    cam = splatting.EquirectCamera(8, 16)
    color, depth, alpha = dense_render(*scene, eye(), cam)
    for backend in BACKENDS:
        out = splatting.render(*scene, eye(), cam, backend=backend)
        torch.testing.assert_close(out.alpha, alpha, atol=1e-9, rtol=1e-7)
        torch.testing.assert_close(out.image, color, atol=1e-9, rtol=1e-7)
