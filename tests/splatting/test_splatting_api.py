"""Public API, cameras, SH, cubemap faces, backend selection."""

import math

import pytest
import torch

import splatting
from splat_helpers import BACKENDS, eye, random_scene


def test_exports():
    for name in ("render", "render_cubemap", "EquirectCamera", "PinholeCamera", "cubemap_faces", "eval_sh", "num_sh_bases"):
        assert hasattr(splatting, name)
    assert [splatting.num_sh_bases(d) for d in range(4)] == [1, 4, 9, 16]
    with pytest.raises(ValueError):
        splatting.num_sh_bases(4)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_output_shapes_and_ranges(backend, dtype):
    scene = random_scene(20, seed=1, dtype=dtype)
    for p in scene:
        p.requires_grad_(True)
    out = splatting.render(*scene, eye(dtype), splatting.EquirectCamera(16, 32), backend=backend)
    assert out.image.shape == (16, 32, 3) and out.alpha.shape == (16, 32) and out.depth.shape == (16, 32)
    assert out.image.dtype == dtype and out.alpha.dtype == dtype
    assert out.radii.shape == (20,) and out.visible.shape == (20,) and out.visible.dtype == torch.bool
    assert out.means2d.shape == (20, 2)
    assert float(out.alpha.detach().min()) >= 0 and float(out.alpha.detach().max()) <= 1
    assert bool(((out.radii > 0) == out.visible).all())
    (out.image.sum() + out.depth.sum()).backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (20, 2)
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in scene)


def test_cpp_kernel_builds_where_a_compiler_exists():
    """Guards against the silent fallback: with a compiler and ninja the kernel must build."""
    import shutil

    from splatting import raster_cpp

    try:
        import ninja  # noqa: F401
    except ImportError:
        pytest.skip("ninja not installed")
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler")
    assert raster_cpp.available()
    out = splatting.render(*random_scene(3), eye(), splatting.EquirectCamera(8, 16), backend="cpp")
    assert out.backend == "cpp"


def test_default_backend_is_cpp_on_cpu():
    scene = random_scene(3)
    out = splatting.render(*scene, eye(), splatting.EquirectCamera(8, 16))
    from splatting import raster_cpp

    assert out.backend == ("cpp" if raster_cpp.available() else "torch")
    with pytest.raises(ValueError):
        splatting.render(*scene, eye(), splatting.EquirectCamera(8, 16), backend="cuda-magic")


@pytest.mark.parametrize("backend", BACKENDS)
def test_background_and_sh(backend):
    means, quats, scales, op, col = random_scene(12, seed=2)
    cam = splatting.EquirectCamera(12, 24)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
    out = splatting.render(means, quats, scales, op, col, eye(), cam, background=bg, backend=backend)
    ref = splatting.render(means, quats, scales, op, col, eye(), cam, backend=backend)
    torch.testing.assert_close(out.image, ref.image + (1 - ref.alpha)[..., None] * bg.detach())
    out.image.sum().backward()
    torch.testing.assert_close(bg.grad, (1 - ref.alpha).sum().expand(3))
    # degree-0 SH with the 3DGS offset reproduces RGB colours
    sh = ((col - 0.5) / 0.28209479177387814)[:, None, :]
    out_sh = splatting.render(means, quats, scales, op, sh, eye(), cam, sh_degree=0, backend=backend)
    torch.testing.assert_close(out_sh.image, ref.image)
    # degree 3 runs and differentiates
    coeffs = torch.randn(12, 16, 3, dtype=torch.float64, requires_grad=True)
    o3 = splatting.render(means, quats, scales, op, coeffs, eye(), cam, sh_degree=3, backend=backend)
    o3.image.sum().backward()
    assert torch.isfinite(coeffs.grad).all() and coeffs.grad.abs().sum() > 0


def test_eval_sh_matches_known_values():
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=torch.float64)
    coeffs = torch.zeros(3, 4, 1, dtype=torch.float64)
    coeffs[:, 2, 0] = 1.0  # the z band
    v = splatting.eval_sh(1, coeffs, dirs)[:, 0]
    torch.testing.assert_close(v, torch.tensor([0.4886025119029199, 0.0, 0.0], dtype=torch.float64))
    coeffs = torch.zeros(1, 16, 1, dtype=torch.float64)
    coeffs[0, 0, 0] = 1.0
    assert float(splatting.eval_sh(3, coeffs, torch.randn(1, 3, dtype=torch.float64))) == pytest.approx(0.28209479177387814)


def test_cubemap_faces_are_rotations_covering_the_sphere():
    faces = splatting.cubemap_faces(8)
    assert len(faces) == 6
    axes = []
    for vm, cam in faces:
        R = vm[:3, :3]
        torch.testing.assert_close(R @ R.T, torch.eye(3))
        assert abs(float(torch.det(R)) - 1) < 1e-6
        assert isinstance(cam, splatting.PinholeCamera) and cam.width == 8 and cam.fx == 4.0
        axes.append(R[2])
    axes = torch.stack(axes)
    expected = torch.tensor([[0, 0, 1], [1, 0, 0], [0, 0, -1], [-1, 0, 0], [0, -1, 0], [0, 1, 0]], dtype=torch.float32)
    torch.testing.assert_close(axes, expected)


@pytest.mark.parametrize("backend", BACKENDS)
def test_pinhole_matches_3dgs_ewa_formula(backend):
    """A Gaussian in front of a pinhole camera: alpha = o·exp(-½ Δᵀ(JΣJᵀ+εI)⁻¹Δ) with the
    classic 3DGS Jacobian, at every covered pixel."""
    mean = torch.tensor([[0.3, -0.2, 3.0]], dtype=torch.float64)
    quat = torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=torch.float64)
    scale = torch.tensor([[0.2, 0.1, 0.05]], dtype=torch.float64)
    op = torch.tensor([0.8], dtype=torch.float64)
    col = torch.ones(1, 3, dtype=torch.float64)
    cam = splatting.PinholeCamera(fx=30.0, fy=25.0, cx=20.0, cy=14.0, width=40, height=30)
    out = splatting.render(mean, quat, scale, op, col, eye(), cam, backend=backend)
    from splatting.project import quat_to_rotmat

    R = quat_to_rotmat(quat)[0]
    S = R @ torch.diag(scale[0] ** 2) @ R.T
    x, y, z = mean[0]
    J = torch.tensor([[30.0 / z, 0, -30.0 * x / z**2], [0, 25.0 / z, -25.0 * y / z**2]], dtype=torch.float64)
    S2 = J @ S @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
    c = torch.tensor([30.0 * x / z + 20.0, 25.0 * y / z + 14.0], dtype=torch.float64)
    rr, cc = torch.meshgrid(torch.arange(30.0, dtype=torch.float64), torch.arange(40.0, dtype=torch.float64), indexing="ij")
    dx = torch.stack([cc + 0.5 - c[0], rr + 0.5 - c[1]], -1)
    power = 0.5 * torch.einsum("hwi,ij,hwj->hw", dx, torch.linalg.inv(S2), dx)
    alpha = torch.clamp(0.8 * torch.exp(-power), max=0.99)
    alpha = torch.where((power <= math.log(255 * 0.8)) & (power <= 4.5), alpha, torch.zeros_like(alpha))
    torch.testing.assert_close(out.alpha, alpha, atol=1e-10, rtol=1e-9)
    torch.testing.assert_close(out.means2d.detach()[0], c)


@pytest.mark.parametrize("backend", BACKENDS)
def test_cubemap_baseline_close_to_direct_render(backend):
    """Six 90° pinhole faces resampled to the panorama: close to the direct 360° render
    (they differ by the projection of each splat and by the bilinear resampling)."""
    means, quats, scales, op, col = random_scene(40, seed=7, spread=1.0, scale=(0.1, 0.3), opacity=(0.5, 0.9))
    means = means / means.norm(dim=-1, keepdim=True) * 2.5
    H, W = 32, 64
    direct = splatting.render(means, quats, scales, op, col, eye(), splatting.EquirectCamera(H, W), backend=backend)
    params = [x.clone().requires_grad_(True) for x in (means, quats, scales, op, col)]
    cube = splatting.render_cubemap(*params, eye(), H, W, backend=backend, face_size=32)
    assert cube.image.shape == (H, W, 3) and cube.alpha.shape == (H, W) and cube.depth.shape == (H, W)
    mse = float(((cube.image.detach() - direct.image) ** 2).mean())
    assert 10 * math.log10(1 / mse) > 25
    cube.image.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in params)
    assert bool(cube.visible.all()) and cube.means2d.shape == (6, 40, 2)


def test_fallback_to_torch_when_the_kernel_cannot_be_built(monkeypatch):
    from splatting import raster_cpp

    monkeypatch.setattr(raster_cpp, "_module", None)
    monkeypatch.setattr(raster_cpp, "_failed", True)
    out = splatting.render(*random_scene(3), eye(), splatting.EquirectCamera(8, 16))
    assert out.backend == "torch"


def test_build_failure_warns_and_falls_back(monkeypatch, tmp_path):
    from splatting import raster_cpp
    from torch.utils import cpp_extension

    def boom(*a, **k):
        raise RuntimeError("no compiler")

    monkeypatch.setattr(raster_cpp, "_module", None)
    monkeypatch.setattr(raster_cpp, "_failed", False)
    monkeypatch.setenv("PANO_PIPE_CACHE", str(tmp_path))
    monkeypatch.setattr(cpp_extension, "load", boom)
    with pytest.warns(RuntimeWarning, match="falling back"):
        out = splatting.render(*random_scene(3), eye(), splatting.EquirectCamera(8, 16))
    assert out.backend == "torch"


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene(backend):
    z = torch.zeros(0, 3, dtype=torch.float64)
    out = splatting.render(z, torch.zeros(0, 4, dtype=torch.float64), z.clone(), torch.zeros(0, dtype=torch.float64), z.clone(),
                           eye(), splatting.EquirectCamera(8, 16), backend=backend, background=torch.ones(3, dtype=torch.float64))
    assert float(out.alpha.abs().max()) == 0.0 and float((out.image - 1).abs().max()) == 0.0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_torch_backend_on_cuda_matches_cpu():
    scene = random_scene(40, seed=9, dtype=torch.float32)
    cam = splatting.EquirectCamera(32, 64)
    cpu = splatting.render(*scene, eye(torch.float32), cam, backend="torch")
    params = [x.cuda().requires_grad_(True) for x in scene]
    gpu = splatting.render(*params, eye(torch.float32).cuda(), cam, backend="torch")
    assert gpu.backend == "torch" and gpu.image.is_cuda
    torch.testing.assert_close(gpu.image.cpu(), cpu.image, atol=1e-5, rtol=1e-4)
    gpu.image.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in params)
