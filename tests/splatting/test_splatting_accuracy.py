"""The math: analytic alpha, dense reference, tile independence, seam, poles, convergence, means2d."""

import math

import pytest
import torch

import splatting
from splat_helpers import BACKENDS, dense_render, dir_from_angles, eye, random_scene, yaw_matrix


def _one(mean, scale=(0.1, 0.1, 0.1), quat=(1.0, 0.0, 0.0, 0.0), op=0.9, dtype=torch.float64):
    return (
        torch.as_tensor(mean, dtype=dtype).reshape(1, 3),
        torch.tensor([quat], dtype=dtype),
        torch.tensor([scale], dtype=dtype),
        torch.tensor([op], dtype=dtype),
        torch.tensor([[0.2, 0.6, 1.0]], dtype=dtype),
    )


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("eps2d", [0.0, 0.3])
def test_isotropic_gaussian_matches_analytic_alpha(backend, eps2d):
    """Isotropic σ at distance D: Σ2 = (sσ/D)² I + ε I on the tangent plane, so a pixel at
    angle γ from the centre has alpha = o·exp(-½ (s tanγ)² / ((sσ/D)² + ε))."""
    H, W = 32, 64
    s = W / (2 * math.pi)
    D, sig, o = 2.0, 0.25, 0.7
    n = dir_from_angles(0.4, 0.3)
    out = splatting.render(*_one(n * D, (sig, sig, sig), op=o), eye(), splatting.EquirectCamera(H, W), eps2d=eps2d, backend=backend)
    dirs = splatting.EquirectCamera(H, W).pixel_dirs(torch.float64)
    var = (s * sig / D) ** 2 + eps2d
    tau = min(math.log(255 * o), 4.5)
    cosg = (dirs @ n).clamp(max=1.0)
    tan2 = (1 - cosg**2) / cosg**2
    power = 0.5 * s * s * tan2 / var
    expect = torch.where((cosg > 0) & (power <= tau), o * torch.exp(-power), torch.zeros_like(power))
    assert int((expect > 0).sum()) >= 10
    torch.testing.assert_close(out.alpha, expect, atol=1e-12, rtol=1e-9)
    for r, c in [(12, 36), (11, 35), (13, 38)]:  # a few pixels spelled out
        g = math.acos(min(1.0, float(dirs[r, c] @ n)))
        p = 0.5 * (s * math.tan(g)) ** 2 / var
        assert float(out.alpha[r, c]) == pytest.approx(o * math.exp(-p), rel=1e-9)
    # depth of a lone Gaussian is alpha · distance
    torch.testing.assert_close(out.depth, out.alpha * D)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_dense_reference(backend, seed):
    """Tiles and pixel boxes change nothing: equal to evaluating every pixel against every Gaussian."""
    scene = random_scene(25, seed=seed, spread=1.5, scale=(0.02, 0.6))
    # put some on the poles and the seam
    scene[0][0] = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    scene[0][1] = torch.tensor([0.0, 1.3, 0.0], dtype=torch.float64)
    scene[0][2] = torch.tensor([0.01, 0.2, -1.0], dtype=torch.float64)
    scene[0][3] = torch.tensor([-0.02, 0.5, -0.8], dtype=torch.float64)
    cam = splatting.EquirectCamera(16, 32)
    out = splatting.render(*scene, eye(), cam, backend=backend)
    color, depth, alpha = dense_render(*scene, eye(), cam)
    torch.testing.assert_close(out.image, color, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.depth, depth, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.alpha, alpha, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_pinhole_matches_dense_reference(backend):
    scene = random_scene(20, seed=3, spread=1.0)
    scene[0][:, 2] += 3.0
    cam = splatting.PinholeCamera(20.0, 22.0, 12.0, 9.0, 24, 18)
    out = splatting.render(*scene, eye(), cam, backend=backend)
    color, depth, alpha = dense_render(*scene, eye(), cam)
    torch.testing.assert_close(out.image, color, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.alpha, alpha, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("width", [48, 40])  # 40: a narrow last tile column
def test_image_independent_of_tile_size(backend, dtype, width):
    """Tile size, and the lane windows the CPU kernel picks per tile row (8 or 16 lanes,
    or any width), change the work, not the image; nor do the gradients change."""
    scene = random_scene(60, seed=4, scale=(0.005, 0.4), dtype=dtype)
    for x in scene:
        x.requires_grad_(True)
    cam = splatting.EquirectCamera(width // 2, width)
    tol = 1e-12 if dtype == torch.float64 else 2e-6

    def run(ts):
        out = splatting.render(*scene, eye(dtype), cam, backend=backend, tile_size=ts)
        grads = torch.autograd.grad((out.image * out.image.detach()).sum() + out.depth.sum(), scene)
        return out.image.detach(), grads

    ref, ref_grads = run(16)
    for ts in (4, 8, 12, 32):
        img, grads = run(ts)
        torch.testing.assert_close(img, ref, atol=tol, rtol=0)
        for g, rg in zip(grads, ref_grads):
            torch.testing.assert_close(g, rg, atol=tol * 100, rtol=1e-4 if dtype == torch.float32 else 1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("phi", [math.pi, math.pi - 0.03, -math.pi + 0.05])
def test_seam_is_invisible(backend, dtype, phi):
    """A Gaussian straddling phi = ±pi renders like the same Gaussian turned 180° about the
    vertical axis, shifted by W/2 columns."""
    H, W = 16, 32
    g = torch.Generator().manual_seed(5)
    mean = dir_from_angles(phi, 0.2) * 1.5
    quat = torch.randn(1, 4, generator=g, dtype=torch.float64)
    scales = torch.tensor([[0.25, 0.1, 0.05]], dtype=torch.float64)
    op = torch.tensor([0.8], dtype=torch.float64)
    col = torch.tensor([[0.3, 0.7, 0.1]], dtype=torch.float64)
    R = yaw_matrix(math.pi)[:3, :3]
    qy = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)  # 180° about y
    w1, v1 = qy[:, :1], qy[:, 1:]
    w2, v2 = quat[:, :1], quat[:, 1:]
    quat_r = torch.cat([w1 * w2 - (v1 * v2).sum(-1, keepdim=True), w1 * v2 + w2 * v1 + torch.cross(v1, v2, dim=-1)], -1)
    cam = splatting.EquirectCamera(H, W)
    a = splatting.render(*(x.to(dtype) for x in (mean[None], quat, scales, op, col)), eye(dtype), cam, backend=backend)
    b = splatting.render(*(x.to(dtype) for x in ((R @ mean)[None], quat_r, scales, op, col)), eye(dtype), cam, backend=backend)
    assert float(a.alpha[:, 0].max()) > 0.05 and float(a.alpha[:, -1].max()) > 0.05  # really on both edges
    torch.testing.assert_close(a.image, torch.roll(b.image, W // 2, dims=1), atol=1e-5, rtol=0)
    torch.testing.assert_close(a.alpha, torch.roll(b.alpha, W // 2, dims=1), atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("sign", [-1.0, 1.0])
def test_gaussian_on_a_pole_covers_every_column(backend, sign):
    H, W = 16, 32
    out = splatting.render(*_one((0.0, sign * 2.0, 0.0), (0.3, 0.3, 0.3)), eye(), splatting.EquirectCamera(H, W), backend=backend)
    rows = out.alpha[:2] if sign < 0 else out.alpha[-2:]
    assert float(rows.min()) > 0.1 and float((out.alpha[0] if sign < 0 else out.alpha[-1]).min()) > 0.5
    # rotational symmetry about the vertical axis: constant along each row
    assert float((out.alpha - out.alpha.mean(1, keepdim=True)).abs().max()) < 1e-9
    far = out.alpha[-2:] if sign < 0 else out.alpha[:2]
    assert float(far.max()) == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_resolution_convergence(backend):
    """Point samples of a resolution-independent function: rendering at 2R and averaging
    2×2 blocks approaches the render at R as R grows (error ~ 1/R²)."""
    scene = random_scene(6, seed=6, spread=1.0, scale=(0.15, 0.4), opacity=(0.3, 0.8))
    scene[0] = scene[0] / scene[0].norm(dim=-1, keepdim=True) * 2.0

    def r(H):
        return splatting.render(*scene, eye(), splatting.EquirectCamera(H, 2 * H), eps2d=0.0, backend=backend).image

    def pool(img):
        return torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)

    i16, i32, i64 = r(16), r(32), r(64)
    e1 = float((pool(i32) - i16).abs().mean())
    e2 = float((pool(i64) - i32).abs().mean())
    assert e2 < 0.6 * e1
    assert e2 < 0.02


@pytest.mark.parametrize("backend", BACKENDS)
def test_means2d_gradient_is_the_tangent_plane_position_gradient(backend):
    """For a small Gaussian on the equator, turning the camera by a yaw ε moves the splat
    ε·s pixels east on its tangent plane (s = W/2π): dL/dε ≈ s·means2d.grad[:, 0]."""
    H, W = 32, 64
    s = W / (2 * math.pi)
    params = _one(dir_from_angles(0.3, 0.0) * 2.0, (0.05, 0.04, 0.03), quat=(0.9, 0.1, 0.3, -0.2), op=0.8)
    target = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    eps = torch.zeros((), dtype=torch.float64, requires_grad=True)

    def loss_for(e):
        c, sn = torch.cos(e), torch.sin(e)
        z, o = torch.zeros_like(e), torch.ones_like(e)
        R = torch.stack([torch.stack([c, z, -sn]), torch.stack([z, o, z]), torch.stack([sn, z, c])])
        vm = torch.eye(4, dtype=torch.float64).index_put((torch.arange(3)[:, None], torch.arange(3)[None, :]), R)
        out = splatting.render(*params, vm, splatting.EquirectCamera(H, W), backend=backend)
        return ((out.image - target) ** 2).sum(), out

    loss, out = loss_for(eps)
    loss.backward()
    # turning the camera by -ε (R above maps phi to phi - ε) moves the splat ε·s pixels west... sign:
    g_yaw = float(eps.grad)
    g2d = out.means2d.grad[0]
    assert torch.isfinite(g2d).all()
    assert g_yaw == pytest.approx(-s * float(g2d[0]), rel=0.02)
