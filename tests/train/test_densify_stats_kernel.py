"""A view's densification statistics through the Triton kernel (gaussians/densify_triton.py, what a
GPU runs) against the torch update: non-finite gradients, invisible and zero-radius Gaussians,
a strided radius column as the renderer returns it. Without CUDA: the Triton interpreter."""

from __future__ import annotations

import pytest
import torch

from gaussians.densify import DensifyStats
from splatting import densify_triton, devices
from splatting.dispatch_count import DispatchCounter

# `cuda`: `make gpu-check` runs these with the compiled kernels
pytestmark = [pytest.mark.skipif(not densify_triton.available(), reason="triton is not installed"),
              pytest.mark.cuda]
DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _views(n, seed):
    g = torch.Generator().manual_seed(seed)
    grad2d = torch.randn(n, 2, generator=g) * 3
    grad2d[0] = float("nan")
    grad2d[1, 0] = float("inf")
    ints = torch.randint(-2, 9, (n, 6), generator=g, dtype=torch.int32)  # radii: column 5, some <= 0
    visible = torch.rand(n, generator=g) > 0.3
    return grad2d, visible, ints[:, 5]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_statistics_equal_the_torch_update(dtype, monkeypatch):
    n = 1500  # two programs of 1024
    ref = DensifyStats.zeros(n, dtype=dtype)
    for seed in range(3):
        ref.add(*_views(n, seed), pixel_scale=163.0, grad_scale=81.5)
    monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
    out = DensifyStats.zeros(n, dtype=dtype, device=DEVICE)
    for seed in range(3):
        grad2d, visible, radii = _views(n, seed)
        out.add(grad2d.to(DEVICE), visible.to(DEVICE), radii.to(DEVICE), pixel_scale=163.0, grad_scale=81.5)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.allclose(out.grad_accum.cpu(), ref.grad_accum, rtol=tol, atol=tol)
    assert torch.equal(out.count.cpu(), ref.count)
    assert torch.equal(out.max_radius.cpu(), ref.max_radius)
    assert float(out.grad_accum[0]) == 0.0 and float(out.grad_accum[1]) == 0.0  # nan, inf -> 0


def test_kernel_statistics_are_one_launch(monkeypatch):
    monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
    stats = DensifyStats.zeros(100, device=DEVICE)
    grad2d, visible, radii = _views(100, 0)
    args = (grad2d.to(DEVICE), visible.to(DEVICE), radii.to(DEVICE))
    with DispatchCounter() as counter:
        stats.add(*args, pixel_scale=10.0)
    assert counter.device_ops == 1 and sum(counter.kernels.values()) == 1, counter.summary()
