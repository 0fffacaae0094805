"""The faster training step computes what the plain one did: fused Adam, the one-pass finite
check, SSIM's closed-form gradient, the skipped black background; and it reports its parts."""

from __future__ import annotations

import os

import pytest
import torch
import torch.nn.functional as F
from train_helpers import load_views, rooms, small_config

import splatting
from gaussians.init import random_points
from gaussians.losses import ssim
from gaussians.model import PARAM_NAMES
from gaussians.optim import Adam
from gaussians.trainer import Trainer, _Ema, scene_extent
from splatting.dispatch_count import DispatchCounter


class _Params:
    """The one attribute Adam reads from a Gaussians."""

    def __init__(self, means):
        self.means = means


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_adam_step_is_the_textbook_update(dtype):
    torch.manual_seed(0)
    p = _Params(torch.randn(500, 3, dtype=dtype, requires_grad=True))
    ref = p.means.detach().clone()
    m, v = torch.zeros_like(ref), torch.zeros_like(ref)
    opt, lr, (b1, b2), eps = Adam({"means": 1e-2}), 1e-2, (0.9, 0.999), 1e-15
    for t in range(1, 6):
        g = torch.randn_like(ref)
        p.means.grad = g.clone()
        opt.step(p)
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        ref = ref - lr / (1 - b1**t) * m / ((v / (1 - b2**t)).sqrt() + eps)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(p.means.detach(), ref, rtol=0, atol=tol)
    assert torch.allclose(opt.exp_avg["means"], m, atol=tol) and torch.allclose(opt.exp_avg_sq["means"], v, atol=tol)


class _Many:
    """Several tensors with gradients, as Adam reads them from a Gaussians."""

    def __init__(self, shapes, dtype=torch.float32, device="cpu"):
        for k, shape in shapes.items():
            setattr(self, k, torch.randn(*shape, dtype=dtype).to(device).requires_grad_(True))


# Adam's one Triton launch (splatting/adam_triton.py): what a GPU runs; here through the
# interpreter. `cuda`: `make gpu-check` runs these with the compiled kernel
_KERNEL_DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _kernel_path(monkeypatch) -> torch.device:
    from splatting import adam_triton, devices

    if not adam_triton.available():
        pytest.skip("triton is not installed")
    monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
    return _KERNEL_DEVICE


def test_adam_step_dispatches_one_kernel_per_tensor():
    """Issue 35's op budget, on CPU tensors: torch's fused kernel called directly, once per tensor,
    one shared step-count tensor set once per step (not a tensor made, and a _foreach_add_, per
    tensor), and the finite check: one multi-tensor pass, its flag read (free on the CPU)."""
    shapes = {"means": (50, 3), "quats": (50, 4), "log_scales": (50, 3), "opacity_logits": (50,), "sh_dc": (50, 3)}
    g = _Many(shapes)
    opt = Adam({k: 1e-3 for k in shapes})
    for step in range(3):
        for k in shapes:
            getattr(g, k).grad = torch.randn_like(getattr(g, k))
        with DispatchCounter() as c:
            opt.step(g)
        if step == 0:
            continue  # the first step makes the moments and the step tensor
        assert dict(c.ops) == {"_fused_adam_": len(shapes), "fill_": 1, "zeros": 1,
                               "_amp_foreach_non_finite_check_and_unscale_": 1, "_local_scalar_dense": 1}, c.summary()
    assert opt.step_count == 3 and opt.state_dict()["step_count"] == 3
    # the step tensor follows step_count through a checkpoint and a move
    opt2 = Adam({k: 1e-3 for k in shapes})
    opt2.load_state_dict(opt.state_dict())
    ref = _Many(shapes)
    for k in shapes:
        getattr(ref, k).data.copy_(getattr(g, k).detach())
        getattr(ref, k).grad = getattr(g, k).grad.clone()
    opt.step(g)
    opt2.to("cpu").step(ref)
    for k in shapes:
        assert torch.equal(getattr(g, k), getattr(ref, k)), k


def test_optimiser_part_of_a_training_step_stays_small(tiny_room):
    """Trainer._optimiser_step between densifications: the finite check one multi-tensor op, one
    Adam kernel per tensor; on the CPU the flag is read (one sync), on a GPU never."""
    views = load_views(tiny_room)
    g = random_points(300, 0, rooms=rooms(tiny_room))
    tr = Trainer(g, views, small_config(iterations=10, extent=scene_extent(g.means), densify_from=100,
                                        densify_until=100, sh_degree_every=0))
    tr.step()
    tr.step()
    for k in PARAM_NAMES:
        p = getattr(tr.g, k)
        p.grad = torch.randn_like(p)
    with torch.no_grad(), DispatchCounter() as c:
        tr._optimiser_step()
    n = len(PARAM_NAMES)
    assert c.ops["_fused_adam_"] == n and c.sync_ops == {"_local_scalar_dense": 1}, c.summary()
    for gone in ("full", "_foreach_add_", "aminmax", "stack", "isfinite", "nan_to_num_", "_to_copy", "copy_"):
        assert gone not in c.ops, c.summary()
    # the check, its counting, the step tensor, the quaternions' fix-up (norm, compare, where)
    assert c.device_ops <= n + 8, c.summary()


@pytest.mark.parametrize("path", ["torch", "kernel"])
def test_a_nonfinite_gradient_is_zeroed_and_counted(tiny_room, path, monkeypatch):
    """Both paths of Adam.step (CPU tensors; "kernel": the one Triton launch a GPU takes, which
    never reads the flag): the non-finite entries count as 0, the other entries still update."""
    views = load_views(tiny_room)
    g = random_points(300, 0, rooms=rooms(tiny_room))
    tr = Trainer(g, views, small_config(iterations=10, extent=scene_extent(g.means), densify_from=100,
                                        densify_until=100, sh_degree_every=0))
    tr.step()
    assert int(tr.nonfinite_steps) == 0
    if path == "kernel":
        if os.environ.get("TRITON_INTERPRET") != "1":  # the trainer's tensors are on the CPU
            pytest.skip("the kernel path on CPU tensors runs in the interpreter (the cuda tests below: on a GPU)")
        _kernel_path(monkeypatch)
    before = tr.g.means.detach().clone()
    for k in PARAM_NAMES:
        p = getattr(tr.g, k)
        p.grad = torch.randn_like(p)
    tr.g.means.grad[7, 1] = float("nan")
    tr.g.sh_dc.grad[3, 0] = float("inf")
    moment = tr.opt.exp_avg["means"][7, 1].clone()
    with torch.no_grad(), DispatchCounter() as c:
        tr._optimiser_step()
    assert c.syncs == (1 if path == "torch" else 0), c.summary()
    assert (sum(c.kernels.values()) == 1) == (path == "kernel"), c.summary()
    assert int(tr.nonfinite_steps) == 1
    assert all(torch.isfinite(getattr(tr.g, k)).all() for k in PARAM_NAMES)
    assert torch.allclose(tr.opt.exp_avg["means"][7, 1], 0.9 * moment, rtol=1e-6, atol=0)  # its gradient taken as 0
    assert bool((tr.g.means.detach() != before).all(dim=1)[torch.arange(300) != 7].all())
    for k in PARAM_NAMES:
        p = getattr(tr.g, k)
        p.grad = torch.randn_like(p)
    with torch.no_grad():
        tr._optimiser_step()
    assert int(tr.nonfinite_steps) == 1  # a finite step counts nothing


def test_ema_is_the_same_average_in_one_operation():
    ema, ref = _Ema(), None
    g = torch.Generator().manual_seed(3)
    firsts = []
    for t in range(6):
        loss, p = torch.rand((), generator=g), 20 + 10 * torch.rand((), generator=g)
        firsts.append((loss, loss.clone()))
        with DispatchCounter() as c:
            ema.update(loss, p)
        if t:
            assert c.device_ops == 1, c.summary()
        ref = (float(loss), float(p)) if ref is None else \
            (0.4 * float(loss) + 0.6 * ref[0], 0.4 * float(p) + 0.6 * ref[1])
        assert float(ema.loss) == pytest.approx(ref[0], rel=1e-6) and float(ema.psnr) == pytest.approx(ref[1], rel=1e-6)
    assert all(torch.equal(a, b) for a, b in firsts)  # the values given are never changed
    # a checkpoint's plain numbers: they continue as tensors
    ema2 = _Ema(loss=0.5, psnr=21.0)
    ema2.update(torch.tensor(1.0), torch.tensor(11.0))
    assert float(ema2.loss) == pytest.approx(0.7) and float(ema2.psnr) == pytest.approx(17.0)
    ema3 = _Ema()
    ema3.update(0.5, 21.0)
    ema3.update(1.0, 11.0)
    assert ema3.loss == pytest.approx(0.7) and ema3.psnr == pytest.approx(17.0)


@pytest.mark.parametrize("path", ["torch", pytest.param("kernel", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf"), None])
def test_adam_flags_any_nonfinite_gradient_value(bad, path, monkeypatch):
    device = _kernel_path(monkeypatch) if path == "kernel" else "cpu"
    shapes = {"means": (100, 3), "opacity_logits": (7,), "sh_rest": (4, 15, 3)}
    g = _Many(shapes, device=device)
    for k in shapes:
        getattr(g, k).grad = torch.randn_like(getattr(g, k))
    if bad is not None:
        g.sh_rest.grad[3, 11, 1] = bad  # the last element of the last program's block
    found = Adam({k: 1e-3 for k in shapes}).step(g)
    assert float(found) == (0.0 if bad is None else 1.0)
    assert all(bool(torch.isfinite(getattr(g, k)).all()) for k in shapes)


@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_adam_in_one_launch_is_torchs_fused_adam(dtype, monkeypatch):
    """The one Triton launch over every tensor against torch's fused kernel on the CPU: each
    tensor with its own lr, one without a gradient (no update), one empty, tensors of several
    programs, five steps (the bias corrections), a checkpoint's round trip between them."""
    from splatting import devices

    dev = _kernel_path(monkeypatch)
    shapes = {"means": (700, 3), "quats": (700, 4), "log_scales": (700, 3), "opacity_logits": (700,),
              "sh_dc": (700, 3), "sh_rest": (700, 0, 3)}
    lrs = {k: 1e-3 * (i + 1) for i, k in enumerate(shapes)}
    torch.manual_seed(1)
    ref = _Many(shapes, dtype)  # on the CPU, with torch's fused Adam
    ours = _Many(shapes, dtype, dev)
    for k in shapes:
        getattr(ours, k).data.copy_(getattr(ref, k).detach())
    opt, ref_opt = Adam(lrs), Adam(lrs)
    for step in range(5):
        for k in shapes:
            grad = None if k == "quats" and step % 2 else torch.randn_like(getattr(ref, k))
            getattr(ref, k).grad, getattr(ours, k).grad = grad, None if grad is None else grad.to(dev, copy=True)
        with DispatchCounter() as c:
            found = opt.step(ours)
        monkeypatch.setattr(devices, "KERNELS_ON_CPU", False)  # the reference: torch's path
        ref_opt.step(ref)
        monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
        assert sum(c.kernels.values()) == 1 and c.syncs == 0, c.summary()
        if step:  # the first step also makes the moments
            assert c.device_ops == 2, c.summary()  # the flag's zeros, the launch
        assert float(found) == 0.0
        if step == 2:
            opt = Adam(lrs)
            opt.load_state_dict(ref_opt.state_dict())
            opt.to(dev)
    # float32 scalars in the kernel, on a GPU and (launch_float) in the interpreter alike: a float64
    # step carries float32's rounding of its size (2^-24 of lr ≤ 6e-3 times |m̂/√v̂| ≤ 3.2, over 5
    # steps: ≤ 1.2e-8), its first moment that of β₁ (float32(0.9) = 0.9 − 2.4e-8: ~1e-8 a step)
    tol = dict(rtol=0, atol=1e-6) if dtype == torch.float32 else dict(rtol=0, atol=2e-8)
    moment_tol = tol if dtype == torch.float32 else dict(rtol=0, atol=1e-7)
    for k in shapes:
        assert torch.allclose(getattr(ours, k).cpu(), getattr(ref, k), **tol), k
        assert torch.allclose(opt.exp_avg[k].cpu(), ref_opt.exp_avg[k], **moment_tol), k
        assert torch.allclose(opt.exp_avg_sq[k].cpu(), ref_opt.exp_avg_sq[k], rtol=1e-6, atol=0), k
    assert opt.step_count == ref_opt.step_count == 5


def _ssim_autograd(pred, gt, mask=None, window=11, sigma=1.5):
    """3DGS's SSIM written with plain autograd ops (the full 2D window), the reference."""
    if mask is not None:
        m = mask[..., None].to(pred.dtype)
        pred, gt = pred * m, gt * m
    pred, gt = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    x = torch.arange(window, dtype=pred.dtype) - window // 2
    g1 = torch.exp(-x * x / (2 * sigma * sigma))
    g1 = g1 / g1.sum()
    w = (g1[:, None] * g1[None, :]).expand(3, 1, window, window)

    def blur(t):
        return F.conv2d(t, w, padding=window // 2, groups=3)

    mu1, mu2 = blur(pred), blur(gt)
    s1, s2, s12 = blur(pred * pred) - mu1**2, blur(gt * gt) - mu2**2, blur(pred * gt) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    smap = (2 * mu1 * mu2 + c1) * (2 * s12 + c2) / ((mu1**2 + mu2**2 + c1) * (s1 + s2 + c2))
    if mask is None:
        return smap.mean()
    return (smap.mean(1)[0] * mask).sum() / mask.sum()


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("compiled", [True, False], ids=["cpu-kernel", "torch"])
def test_ssim_value_and_gradient_match_autograd(masked, compiled, monkeypatch):
    """Both implementations: the compiled CPU kernel's fused SSIM and the torch one (GPU, or no compiler)."""
    import gaussians.losses as losses

    if compiled and losses._cpu_kernels(torch.zeros(1)) is None:
        pytest.skip("the C++ CPU kernel could not be built here")
    if not compiled:
        monkeypatch.setattr(losses, "_cpu_kernels", lambda x: None)
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(24, 40, 3, generator=g, dtype=torch.float64)
    pred = (gt + 0.2 * torch.randn(24, 40, 3, generator=g, dtype=torch.float64)).clamp(0, 1).requires_grad_(True)
    mask = torch.rand(24, 40, generator=g) > 0.3 if masked else None
    a = ssim(pred, gt, mask=mask)
    b = _ssim_autograd(pred, gt, mask)
    (ga,) = torch.autograd.grad(a, pred)
    (gb,) = torch.autograd.grad(b, pred)
    assert abs(float((a - b).detach())) < 1e-12
    assert torch.allclose(ga, gb, rtol=1e-9, atol=1e-13)
    assert torch.autograd.gradcheck(lambda p: ssim(p, gt[:10, :12], mask=None if mask is None else mask[:10, :12]),
                                    (pred.detach()[:10, :12].clone().requires_grad_(True),))


def test_black_background_changes_nothing_and_a_learned_one_gets_its_gradient():
    torch.manual_seed(0)
    n = 40
    means = torch.randn(n, 3) * 0.3 + torch.tensor([0.0, 0.0, 2.0])
    quats, scales = torch.randn(n, 4), torch.full((n, 3), 0.1)
    op, col = torch.full((n,), 0.6), torch.rand(n, 3)
    cam = splatting.EquirectCamera(16, 32)
    eye = torch.eye(4)
    plain = splatting.render(means, quats, scales, op, col, eye, cam, backend="cpp")
    black = splatting.render(means, quats, scales, op, col, eye, cam, backend="cpp", background=torch.zeros(3))
    assert torch.equal(plain.image, black.image)
    bg = torch.zeros(3, requires_grad=True)
    out = splatting.render(means, quats, scales, op, col, eye, cam, backend="cpp", background=bg)
    out.image.sum().backward()
    # d(sum)/d(bg_c) = Σ (1 − alpha): the uncovered part of the panorama
    assert torch.allclose(bg.grad, (1 - plain.alpha).sum().expand(3), rtol=1e-5)
    assert float(bg.grad[0]) > 0


def test_trainer_reports_the_seconds_of_each_part_of_the_step(tiny_room):
    views = load_views(tiny_room)
    g = random_points(300, 0, rooms=rooms(tiny_room))
    tr = Trainer(g, views, small_config(iterations=4, extent=scene_extent(g.means)))
    tr.train()
    parts = tr.part_seconds
    assert list(parts) == ["render", "losses", "backward", "optimiser", "densify", "log"]
    assert all(v > 0 for v in parts.values())
    assert sum(parts.values()) <= tr.train_seconds  # the parts lie inside the timed iterations


def test_every_training_render_uses_the_configured_tile_size(tiny_room, monkeypatch):
    """`train.tile_size` (speed only) reaches each render the trainer makes: the steps', the
    coverage term's and the PSNR's."""
    seen = []
    real = splatting.render

    def spy(*args, **kw):
        seen.append(kw.get("tile_size"))
        return real(*args, **kw)

    monkeypatch.setattr(splatting, "render", spy)  # what gaussians.model.render calls
    views = load_views(tiny_room)
    g = random_points(300, 0, rooms=rooms(tiny_room))
    tr = Trainer(g, views, small_config(iterations=3, extent=scene_extent(g.means), tile_size=8, lambda_coverage=0.1))
    tr.train()
    tr.mean_psnr()
    assert len(seen) >= 3 + 1 + len(views) and set(seen) == {8}
