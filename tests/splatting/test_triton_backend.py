"""The `cuda` backend (Triton kernels) against the `cpp` kernel: images to 1e-5, gradients of
every input to 1e-4 (relative), in float64, on the hard cases.

Without CUDA the kernels run in the Triton interpreter on CPU tensors (tests/conftest.py
sets TRITON_INTERPRET=1 before triton is imported); on a GPU the same tests run the
compiled kernels on CUDA tensors (`make gpu-check` runs every `cuda`-marked test).
"""

import math

import pytest
import torch

pytest.importorskip("triton")

import splatting  # noqa: E402
from splatting import raster_triton  # noqa: E402
from splat_helpers import (HARD_KINDS, dir_from_angles, equal_distance_cluster, eye, hard_case_scene,  # noqa: E402
                           random_scene, yaw_matrix)

pytestmark = pytest.mark.cuda
DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")
IMG_TOL = 1e-5
GRAD_RTOL = 1e-4


def test_kernels_can_run_here():
    """Not a skip: without CUDA the interpreter must be on, or every check below would be void."""
    assert raster_triton.unavailable_reason(DEVICE) is None, raster_triton.unavailable_reason(DEVICE)


def _view(dtype):
    """A camera that is neither at the origin nor axis-aligned (exercises the viewmat gradient)."""
    v = yaw_matrix(0.4, dtype)
    v[:3, 3] = torch.tensor([0.1, -0.05, 0.2], dtype=dtype)
    return v


def _run(params, viewmat, backend, device, render=splatting.render, **kw):
    """Render, then backpropagate a loss that weights every output; returns outputs and all gradients."""
    leaves = [p.detach().to(device).requires_grad_(True) for p in params]
    vm = viewmat.detach().to(device).requires_grad_(True)
    out = render(*leaves, vm, backend=backend, **kw)
    gen = torch.Generator().manual_seed(7)
    wimg = torch.rand(out.image.shape, generator=gen, dtype=torch.float64).to(out.image)
    wdep = torch.rand(out.depth.shape, generator=gen, dtype=torch.float64).to(out.image)
    wa = torch.rand(out.alpha.shape, generator=gen, dtype=torch.float64).to(out.image)
    loss = (out.image * wimg).sum() + 0.1 * (out.depth * wdep).sum() + (out.alpha * wa).sum()
    loss.backward()
    grads = [p.grad for p in leaves] + [vm.grad]
    return out, [torch.zeros_like(p) if g is None else g.cpu() for p, g in zip(leaves + [vm], grads)]


def _compare(params, viewmat, *, render=splatting.render, img_tol=IMG_TOL, grad_rtol=GRAD_RTOL, reference="cpp",
             **kw):
    """`cuda` on DEVICE against `reference` on the CPU: image, alpha, depth and the gradient of every input."""
    ref, gref = _run(params, viewmat, reference, "cpu", render=render, **kw)
    out, gout = _run(params, viewmat, "cuda", DEVICE, render=render, **kw)
    assert out.backend == "cuda"
    for name in ("image", "alpha", "depth"):
        a, r = getattr(out, name).detach().cpu(), getattr(ref, name).detach()
        err = float((a - r).abs().max())
        assert err <= img_tol, f"{name}: max error {err:.3g}"
    names = ("means", "quats", "scales", "opacities", "colors", "viewmat")
    for name, a, r in zip(names, gout, gref):
        scale = float(r.abs().max())
        err = float((a - r).abs().max())
        assert err <= grad_rtol * scale + 1e-12, f"d/d{name}: max error {err:.3g} vs max |grad| {scale:.3g}"
    if out.means2d.grad is not None and out.means2d.dim() == 2:
        r = ref.means2d.grad
        assert float((out.means2d.grad.cpu() - r).abs().max()) <= grad_rtol * float(r.abs().max()) + 1e-12
    return ref


@pytest.mark.parametrize("hw", [(16, 32), (32, 64)])
def test_random_scene_equirect(hw):
    params = random_scene(300, seed=3)
    ref = _compare(params, _view(torch.float64), camera=splatting.EquirectCamera(*hw))
    assert float(ref.alpha.detach().max()) > 0.9  # the scene covers the image: the check is not vacuous


def test_spherical_harmonics_and_background():
    m, q, s, o, _ = random_scene(200, seed=4)
    sh = torch.randn(200, 9, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 0.3
    kw = dict(camera=splatting.EquirectCamera(16, 32), sh_degree=2,
              background=torch.tensor([0.2, 0.5, 0.1], dtype=torch.float64))
    # Against `torch`, which shares the projection: `cpp` takes the SH view direction as
    # means − camera centre, the projection as Rᵀ·(R·means + t)/‖·‖. Equal for a rotation R,
    # so images agree (checked against `cpp` with the viewmat gradient left out), but the raw
    # gradient with respect to the 16 entries of viewmat differs off the rotations.
    _compare([m, q, s, o, sh], _view(torch.float64), reference="torch", **kw)
    ref, gref = _run([m, q, s, o, sh], _view(torch.float64), "cpp", "cpu", **kw)
    out, gout = _run([m, q, s, o, sh], _view(torch.float64), "cuda", DEVICE, **kw)
    assert float((out.image.detach().cpu() - ref.image.detach()).abs().max()) <= IMG_TOL
    for a, r in zip(gout[:5], gref[:5]):
        assert float((a - r).abs().max()) <= GRAD_RTOL * float(r.abs().max())


@pytest.mark.parametrize("with_alpha", [False, True])
def test_background_composited_in_the_kernel(with_alpha):
    """The kernel composites the background (training's render): colour, and the gradients of a
    colour loss (with an alpha term or without, the kernel's two paths), equal to `cpp`'s blend
    outside, across the seam; a background that needs a gradient is blended outside and gets it."""
    params = _seam_scene(12, seed=5)
    bg = torch.tensor([0.7, 0.2, 0.4], dtype=torch.float64)
    cam = splatting.EquirectCamera(16, 32)
    gen = torch.Generator().manual_seed(3)
    w = torch.rand(16, 32, 3, generator=gen, dtype=torch.float64)
    wa = torch.rand(16, 32, generator=gen, dtype=torch.float64)

    def grads(backend, device, background):
        leaves = [p.detach().to(device).requires_grad_(True) for p in params]
        out = splatting.render(*leaves, eye().to(device), cam, backend=backend, background=background)
        loss = (out.image * w.to(device)).sum() + ((out.alpha * wa.to(device)).sum() if with_alpha else 0.0)
        loss.backward()
        return out.image.detach().cpu(), [p.grad.cpu() for p in leaves]

    ref_img, ref_grads = grads("cpp", "cpu", bg)
    img, got = grads("cuda", DEVICE, bg.to(DEVICE))
    assert float(ref_img.std()) > 0.05  # the background shows and Gaussians cover part of the image
    assert float((img - ref_img).abs().max()) <= IMG_TOL
    for a, r in zip(got, ref_grads):
        assert float((a - r).abs().max()) <= GRAD_RTOL * float(r.abs().max()) + 1e-12
    learnt = [bg.clone().requires_grad_(True), bg.clone().to(DEVICE).requires_grad_(True)]
    for background, backend in zip(learnt, ("cpp", "cuda")):
        out = splatting.render(*[p.to(background.device) for p in params], eye().to(background.device), cam,
                               backend=backend, background=background)
        (out.image * w.to(background.device)).sum().backward()
    assert float(learnt[0].grad.abs().min()) > 0
    assert float((learnt[1].grad.cpu() - learnt[0].grad).abs().max()) <= 1e-8 * float(learnt[0].grad.abs().max())


def _seam_scene(n, seed):
    """n Gaussians of mixed sizes around the ±180° seam (the back of the panorama), in front of the camera too."""
    gen = torch.Generator().manual_seed(seed)
    phi = math.pi + (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5) * 0.8
    phi[: n // 2] -= math.pi  # half in front
    th = (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5) * 1.6
    means = torch.stack([torch.cos(th) * torch.sin(phi), -torch.sin(th), torch.cos(th) * torch.cos(phi)], 1) * 2.0
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(math.log(0.05), math.log(0.4), generator=gen))
    op = torch.empty(n, dtype=torch.float64).uniform_(0.2, 0.95, generator=gen)
    col = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    return [means, quats, scales, op, col]


def test_saturated_pixels_stop_early():
    """Many opaque Gaussians: most pixels saturate (T < 1e-4) well inside long tile lists."""
    params = random_scene(400, seed=6, spread=1.5, scale=(0.2, 0.6), opacity=(0.8, 1.0))
    ref = _compare(params, eye(), camera=splatting.EquirectCamera(16, 32))
    saturated = ref.alpha.detach() > 1 - 2e-4  # T_final below about T_MIN = 1e-4
    assert float(saturated.double().mean()) > 0.5


@pytest.mark.parametrize("tile_size", [8, 13])
def test_other_tile_sizes(tile_size):
    """Tiles of 64 and of 169 (not a power of two) pixels, partial tiles at the image border."""
    params = random_scene(150, seed=8)
    _compare(params, _view(torch.float64), camera=splatting.EquirectCamera(16, 32), tile_size=tile_size)


def test_seam_and_poles_scene():
    """Large splats straddling the ±180° seam and covering both poles, seen from a tilted camera."""
    means = torch.stack([dir_from_angles(math.pi - 0.05 * i, 0.3 * (i - 3)) * (1.2 + 0.2 * i) for i in range(7)]
                        + [torch.tensor([0.0, -1.5, 0.1]), torch.tensor([0.1, 1.8, 0.0])]).double()
    n = means.shape[0]
    gen = torch.Generator().manual_seed(9)
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.5 + 0.2
    ops = torch.rand(n, generator=gen, dtype=torch.float64) * 0.5 + 0.4
    cols = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    vm = eye()
    vm[:3, :3] = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(0.3), -math.sin(0.3)],
                               [0.0, math.sin(0.3), math.cos(0.3)]], dtype=torch.float64)
    _compare([means, quats, scales, ops, cols], vm, camera=splatting.EquirectCamera(32, 64))


@pytest.mark.parametrize("hw", [(24, 48), (64, 128)])
@pytest.mark.parametrize("phi", [math.pi, 0.0], ids=["seam", "front"])
@pytest.mark.parametrize("seed", [0, 3])  # the failing seeds (1 and 2 are in the cpp/torch test)
def test_gaussians_at_one_distance_across_the_seam(seed, phi, hw):
    """issue 35: ten Gaussians at one distance straddling ±180° (and the same straight ahead);
    image and every gradient as `cpp`, in float32 as training renders them."""
    _compare(equal_distance_cluster(seed, phi), eye(torch.float32), camera=splatting.EquirectCamera(*hw), eps2d=0.0)


@pytest.mark.skipif(DEVICE.type == "cpu", reason="about a minute in the interpreter; the kernels and cases of "
                    "test_gaussians_at_one_distance_across_the_seam, on a larger image")
@pytest.mark.parametrize("seed", range(4))
def test_gaussians_at_one_distance_across_the_seam_full_size(seed):
    _compare(equal_distance_cluster(seed), eye(torch.float32), camera=splatting.EquirectCamera(512, 1024), eps2d=0.0)


@pytest.mark.parametrize("kind", HARD_KINDS)
def test_hard_case_equirect(kind):
    _compare(hard_case_scene(kind, torch.float64), eye(), camera=splatting.EquirectCamera(16, 32))


@pytest.mark.parametrize("kind", ["behind_pinhole", "at_camera", "huge", "disc_edge_on", "mixed_scales", "far"])
def test_hard_case_pinhole(kind):
    _compare(hard_case_scene(kind, torch.float64), eye(), camera=splatting.PinholeCamera(12.0, 12.0, 10.0, 8.0, 20, 16))


def test_random_scene_pinhole():
    params = random_scene(300, seed=10)
    _compare(params, _view(torch.float64), camera=splatting.PinholeCamera(20.0, 20.0, 31.0, 17.0, 64, 32))


def test_cubemap():
    params = random_scene(200, seed=11)
    _compare(params, _view(torch.float64), render=splatting.render_cubemap, height=16, width=32, face_size=8)


def test_float32_agrees_loosely():
    params = [p.float() for p in random_scene(300, seed=12)]
    _compare(params, _view(torch.float32), camera=splatting.EquirectCamera(32, 64), img_tol=1e-4, grad_rtol=2e-3)


def test_default_backend_per_device():
    params = [p[:20] for p in random_scene(20, seed=13)]
    out = splatting.render(*params, eye(), splatting.EquirectCamera(8, 16))
    assert out.backend == "cpp"  # CPU tensors keep the C++ kernel unless `cuda` is asked for
    if torch.cuda.is_available():
        out = splatting.render(*[p.cuda() for p in params], eye().cuda(), splatting.EquirectCamera(8, 16))
        assert out.backend == "cuda"


def test_cpu_tensors_without_interpreter_are_refused(monkeypatch):
    monkeypatch.setattr(raster_triton, "_INTERPRETED", False)
    monkeypatch.setattr(raster_triton, "_LIBRARY_INTERPRETED", False)
    params = random_scene(5, seed=14)
    with pytest.raises(ValueError, match="TRITON_INTERPRET=1"):
        splatting.render(*params, eye(), splatting.EquirectCamera(8, 16), backend="cuda")


def _projection_grads(params, viewmat, camera, reference, monkeypatch):
    """Every input's gradient (and means2d's) through the `cuda` backend, with the projection's
    gradient from its kernel or from autograd through the torch reference."""
    from splatting.project_triton import TritonProject

    monkeypatch.setattr(TritonProject, "REFERENCE_BACKWARD", reference)
    _, grads = _run(params, viewmat, "cuda", DEVICE, camera=camera)
    return grads


@pytest.mark.parametrize("colours", ["rgb", "sh1", "sh3"])
@pytest.mark.parametrize("camera", [splatting.EquirectCamera(16, 32), splatting.PinholeCamera(12.0, 12.0, 10.0, 8.0, 20, 16)],
                         ids=["equirect", "pinhole"])
def test_projection_gradient_kernel_is_the_reference(colours, camera, monkeypatch):
    """issue 35: the projection's backward as one kernel (splatting/project_triton_backward.py)
    gives autograd's gradients through splatting.project to rounding, SH colours included (their
    coefficients and, through the view direction, the means and the view matrix)."""
    means, quats, scales, ops, rgb = random_scene(60, seed=2)
    gen = torch.Generator().manual_seed(4)
    cols = {"rgb": rgb, "sh1": torch.randn(60, 4, 3, generator=gen, dtype=torch.float64) * 0.3,
            "sh3": torch.randn(60, 16, 3, generator=gen, dtype=torch.float64) * 0.3}[colours]
    params = [means, quats, scales, ops, cols]
    kernel = _projection_grads(params, _view(torch.float64), camera, False, monkeypatch)
    reference = _projection_grads(params, _view(torch.float64), camera, True, monkeypatch)
    for name, a, r in zip(("means", "quats", "scales", "opacities", "colors", "viewmat"), kernel, reference):
        assert float((a - r).abs().max()) <= 1e-9 * float(r.abs().max()) + 1e-15, name


@pytest.mark.parametrize("kind", ["north_pole", "seam", "at_camera", "mixed_scales", "disc_edge_on", "tiny_quat"])
def test_projection_gradient_kernel_on_hard_cases(kind, monkeypatch):
    params = hard_case_scene(kind, torch.float64)
    kernel = _projection_grads(params, _view(torch.float64), splatting.EquirectCamera(16, 32), False, monkeypatch)
    reference = _projection_grads(params, _view(torch.float64), splatting.EquirectCamera(16, 32), True, monkeypatch)
    for a, r in zip(kernel, reference):
        assert torch.isfinite(a).all() and float((a - r).abs().max()) <= 1e-8 * float(r.abs().max()) + 1e-15
