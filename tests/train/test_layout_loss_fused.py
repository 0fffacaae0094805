"""The layout loss with its closed-form gradient (gaussians/layout_loss_fn.py) is
gaussians.losses.layout_loss of the selected rows, value and gradient, in few device operations."""

from __future__ import annotations

import pytest
import torch

from gaussians.layout_loss_fn import LayoutRows, layout_loss_rows
from gaussians.losses import layout_loss
from splatting.dispatch_count import DispatchCounter


def _case(n: int, k: int, seed: int, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype)
    idx = torch.randperm(n, generator=gen)[:k]
    u0 = means[idx] + 0.3 * torch.randn(k, 3, generator=gen, dtype=dtype)
    normals = torch.randn(k, 3, generator=gen, dtype=dtype)
    if k >= 8:
        u0[0] = means[idx[0]]  # μ = u0 exactly: 0/0, value 0 and a zero gradient
        u0[1] = means[idx[1]]
        normals[1] = 0.0  # a degenerate normal at μ = u0 too
        normals[2] = 0.0  # a degenerate normal
        normals[3] *= 1e150  # huge
        normals[4] *= 1e-150  # tiny: the norm clamped to 1e-12 as in layout_loss
        normals[5] *= 1e100  # huge too
        u0[6] = means[idx[6]] + 1e-14 * torch.randn(3, generator=gen, dtype=dtype)  # inside eps's reach
        # d ⟂ n exactly: the cosine 0 (the kink of |·|)
        means[idx[7]] = torch.tensor([2.0, 0.5, 0.25], dtype=dtype)
        u0[7] = torch.tensor([1.0, 0.5, 0.25], dtype=dtype)
        normals[7] = torch.tensor([0.0, 3.0, -1.0], dtype=dtype)
    return means, idx, u0, normals


def _reference(means, idx, u0, normals):
    m = means.detach().clone().requires_grad_(True)
    val = layout_loss(m[idx], u0, normals)
    (grad,) = torch.autograd.grad(val, m, allow_unused=True)
    return val.detach(), torch.zeros_like(m) if grad is None else grad


def _fused(means, idx, u0, normals):
    m = means.detach().clone().requires_grad_(True)
    val = layout_loss_rows(m, idx, u0, normals)
    (grad,) = torch.autograd.grad(val, m)
    return val.detach(), grad


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("k", [1, 3, 17, 200])
def test_value_and_gradient_are_layout_loss(seed, k):
    means, idx, u0, normals = _case(300, k, seed)
    want_v, want_g = _reference(means, idx, u0, normals)
    got_v, got_g = _fused(means, idx, u0, normals)
    assert torch.isfinite(got_v) and torch.all(torch.isfinite(got_g))
    assert abs(float(got_v - want_v)) <= 1e-12 * abs(float(want_v))
    # per row, relative to the row's gradient (components of one row may cancel)
    err = torch.linalg.vector_norm(got_g - want_g, dim=-1)
    scale = torch.linalg.vector_norm(want_g, dim=-1)
    assert torch.all(err <= 1e-12 * scale + 1e-300), (err / scale.clamp_min(1e-300)).max()
    outside = torch.ones(len(means), dtype=torch.bool)
    outside[idx] = False
    assert torch.all(got_g[outside] == 0)


def test_special_rows_value_and_gradient():
    means, idx, u0, normals = _case(50, 8, 3)
    for i in range(8):
        args = (means, idx[i : i + 1], u0[i : i + 1], normals[i : i + 1])
        (want_v, want_g), (got_v, got_g) = _reference(*args), _fused(*args)
        assert torch.isfinite(got_v) and torch.all(torch.isfinite(got_g))
        assert abs(float(got_v - want_v)) <= 1e-12 * abs(float(want_v)), i
        assert torch.allclose(got_g, want_g, rtol=1e-12, atol=1e-300), i
    # μ = u0, a degenerate normal, d ⟂ n: value 0, a zero gradient
    for i in (0, 1, 2, 7):
        v, g = _fused(means, idx[i : i + 1], u0[i : i + 1], normals[i : i + 1])
        assert float(v) == 0.0 and torch.all(g == 0), i


def test_a_normal_whose_squared_norm_overflows():
    """‖n‖ = inf: the cosine 0 in both; layout_loss's autograd gradient is NaN there (inf/inf in
    its backward), the closed form's a finite 0 (the trainer would have zeroed the NaN)."""
    means, idx, u0, normals = _case(20, 2, 5)
    normals = normals * 1e200
    want_v, want_g = _reference(means, idx, u0, normals)
    got_v, got_g = _fused(means, idx, u0, normals)
    assert float(want_v) == float(got_v) == 0.0
    assert torch.isnan(want_g[idx]).all()
    assert torch.all(got_g == 0)


def test_no_row_gives_zero_attached_to_the_graph():
    means = torch.randn(10, 3, dtype=torch.float64, requires_grad=True)
    idx = torch.zeros(0, dtype=torch.long)
    val = layout_loss_rows(means, idx, torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64))
    assert float(val.detach()) == 0.0 and val.requires_grad
    (g,) = torch.autograd.grad(val, means)
    assert torch.all(g == 0)
    assert len(LayoutRows(idx, torch.zeros(0, 3), torch.zeros(0, 3))) == 0


def test_float32_at_u0_is_finite():
    means, idx, u0, normals = _case(40, 5, 1, dtype=torch.float32)
    u0[0] = means[idx[0]]
    m = means.clone().requires_grad_(True)
    val = layout_loss_rows(m, idx, u0, normals)
    (g,) = torch.autograd.grad(val, m)
    assert torch.isfinite(val) and torch.all(torch.isfinite(g))
    assert torch.all(g[idx[0]] == 0)


def test_gradcheck():
    means, idx, u0, normals = _case(12, 5, 4)
    m = means.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: layout_loss_rows(x, idx, u0, normals), (m,))
    # the gradient scales with the incoming one (the loss times λ_layout in the objective)
    assert torch.autograd.gradcheck(lambda x: 0.37 * layout_loss_rows(x, idx, u0, normals), (m,))


def test_few_device_operations():
    """Between densifications (rows cached): forward and backward together a handful of
    operations, none of them a host sync (the unfused loss was ~15 forward + ~20 backward)."""
    means, idx, u0, normals = _case(300, 40, 2, dtype=torch.float32)
    rows = LayoutRows(idx, u0, normals)
    m = means.clone().requires_grad_(True)
    with DispatchCounter() as c:
        (0.1 * rows.loss(m)).backward()
    assert c.syncs == 0, c.summary()
    # 14 forward (rows, d, ‖d‖, r, d/r, c, Σ|c|, n̂ − c·d/r, sign(c), /r, the rows of the
    # gradient, the [N,3] zeros and the scatter) + 1 backward; the test's 0.1·L: 1 + 2 backward
    assert c.device_ops <= 18, c.summary()
    assert c.ops.get("index_put_", 0) == 0 and c.ops.get("index_put", 0) == 0, c.summary()


def test_a_repeated_row_counts_twice():
    means, idx, u0, normals = _case(30, 4, 6)
    idx2, u02, n2 = torch.cat([idx, idx[:2]]), torch.cat([u0, u0[:2] + 0.1]), torch.cat([normals, normals[:2]])
    (want_v, want_g), (got_v, got_g) = _reference(means, idx2, u02, n2), _fused(means, idx2, u02, n2)
    assert abs(float(got_v - want_v)) <= 1e-12 * abs(float(want_v))
    assert torch.allclose(got_g, want_g, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("seed", range(3))
def test_the_dead_zone_frees_small_displacements_only(seed):
    """`deadzone` (the official code's normal_threshold): rows within it of their anchor give 0 and
    no gradient, the others exactly what the term gives without it; the fused form agrees."""
    means, idx, u0, normals = _case(300, 200, seed)
    deadzone = 0.4  # the case's displacements are 0.3·N(0, 1) per axis: about half within
    length = torch.linalg.vector_norm(means[idx] - u0, dim=-1)
    inside = length <= deadzone
    assert 0.2 < float(inside.double().mean()) < 0.8
    m = means.detach().clone().requires_grad_(True)
    val = layout_loss(m[idx], u0, normals, deadzone=deadzone)
    (want,) = torch.autograd.grad(val, m)
    outside_rows = ~inside
    cos = layout_loss(means[idx][outside_rows], u0[outside_rows], normals[outside_rows])
    assert float(val) == pytest.approx(float(cos) * int(outside_rows.sum()) / len(idx), rel=1e-12)
    assert torch.all(want[idx[inside]] == 0)
    ordinary = outside_rows.clone()
    ordinary[:8] = False  # the case's special rows (degenerate normals, d ⟂ n) have no gradient anyway
    assert torch.all(torch.linalg.vector_norm(want[idx[ordinary]], dim=-1) > 0)
    m2 = means.detach().clone().requires_grad_(True)
    got_v = layout_loss_rows(m2, idx, u0, normals, deadzone=deadzone)
    (got,) = torch.autograd.grad(got_v, m2)
    assert abs(float(got_v - val)) <= 1e-12 * abs(float(val))
    err = torch.linalg.vector_norm(got - want, dim=-1)
    assert torch.all(err <= 1e-12 * torch.linalg.vector_norm(want, dim=-1) + 1e-300)


# the Triton kernel (splatting/layout_triton.py): what a GPU runs; here through the interpreter.
# `cuda`: `make gpu-check` runs these with the compiled kernel
_KERNEL_DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _kernel_case(dtype, deadzone, seed, monkeypatch):
    from splatting import devices, layout_triton

    if not layout_triton.available():
        pytest.skip("triton is not installed")
    means, idx, u0, normals = _case(1300, 1100, seed)  # three programs of 512
    normals[3] /= 1e120  # the case's huge and tiny normals, brought into float32's range
    normals[5] /= 1e70
    normals[4] *= 1e138
    idx = torch.cat([idx, idx[:5]])  # repeated rows: the sum of their terms
    u0 = torch.cat([u0, u0[:5]])
    normals = torch.cat([normals, normals[:5]])
    means, u0, normals = means.to(dtype), u0.to(dtype), normals.to(dtype)
    ref = LayoutRows(idx, u0, normals, deadzone=deadzone)
    m = means.clone().requires_grad_(True)
    want_v = ref.loss(m)
    (want_g,) = torch.autograd.grad(want_v, m)
    monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
    dev = _KERNEL_DEVICE
    rows = LayoutRows(idx.to(dev), u0.to(dev), normals.to(dev), deadzone=deadzone)
    m2 = means.to(dev).requires_grad_(True)
    return rows, m2, want_v, want_g


@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("deadzone", [0.0, 0.4])
def test_the_kernel_gives_the_torch_value_and_gradient(dtype, deadzone, monkeypatch):
    rows, m, want_v, want_g = _kernel_case(dtype, deadzone, 1, monkeypatch)
    got_v = rows.loss(m)
    (got_g,) = torch.autograd.grad(got_v, m)
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    assert abs(float(got_v) - float(want_v)) <= tol * abs(float(want_v))
    err = torch.linalg.vector_norm(got_g.cpu() - want_g, dim=-1)
    assert torch.all(err <= tol * 10 * torch.linalg.vector_norm(want_g, dim=-1) + 1e-30), err.max()
    assert torch.all(torch.isfinite(got_g))


@pytest.mark.cuda
def test_the_kernel_is_one_launch_and_no_sync(monkeypatch):
    rows, m, _, _ = _kernel_case(torch.float32, 0.05, 2, monkeypatch)
    seed = torch.full((), 0.1, device=m.device)  # λ3, the gradient the loss's sum hands it
    with DispatchCounter() as counter:
        value = rows.loss(m)
        value.backward(seed)
    kernels = sum(counter.kernels.values())
    assert kernels == 1 and not counter.sync_ops, counter.summary()
    # one zeroed buffer (the gradient and the value), the launch, the backward's multiplication:
    # against ~20 operations in torch
    assert counter.device_ops <= 3, counter.summary()
