"""The fused Triton photometric loss (splatting/photometric_triton.py) against the torch one
(gaussians.losses): values and gradients, masks and weights, tile borders and the 0/0 cases.
Without CUDA the kernels run in the Triton interpreter (tests/conftest.py)."""

from __future__ import annotations

import pytest
import torch

from gaussians import losses
from splatting import devices, photometric_triton
from splatting.dispatch_count import DispatchCounter

# `cuda`: `make gpu-check` runs these with the compiled kernels
pytestmark = [pytest.mark.skipif(not photometric_triton.available(), reason="triton is not installed"),
              pytest.mark.cuda]
DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _both(pred, gt, mask=None, weight=None, lambdas=(0.8, 0.2), upstream=(1.0, 0.3, -0.7)):
    """(values, gradient) of the fused and the torch loss for one weighted sum of (loss, L1, SSIM)."""
    out = []
    for fn in (photometric_triton.photometric_loss, losses.photometric_loss):
        p = pred.detach().clone().requires_grad_(True)
        terms = fn(p, gt, *lambdas, mask=mask, weight=weight)[:3]
        sum(k * t for k, t in zip(upstream, terms)).backward()
        out.append((torch.stack([t.detach() for t in terms]), p.grad))
    return out


@pytest.mark.parametrize("dtype, shape, case", [
    (torch.float64, (9, 70), "mask+weight"),  # 3x2 tiles of 4x64: the borders between programs
    (torch.float64, (9, 70), "mask"),
    (torch.float32, (6, 27), "plain"),
    (torch.float32, (6, 27), "weight"),
])
def test_fused_loss_equals_the_torch_loss(dtype, shape, case):
    g = torch.Generator().manual_seed(hash(case) % 1000)
    h, w = shape
    pred = torch.rand(h, w, 3, dtype=dtype, generator=g).to(DEVICE)
    gt = torch.rand(h, w, 3, dtype=dtype, generator=g).to(DEVICE)
    pred[0, :5] = gt[0, :5]  # |p - g| at 0: the subgradient 0, as torch's abs
    mask = (torch.rand(h, w, generator=g) > 0.3).to(DEVICE) if "mask" in case else None
    weight = losses.solid_angle_weight(h, w, dtype, DEVICE) if "weight" in case else None
    (fused, g_fused), (ref, g_ref) = _both(pred, gt, mask, weight)
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    assert torch.allclose(fused, ref, rtol=tol, atol=tol), (fused, ref)
    assert float((g_fused - g_ref).abs().max()) <= tol * float(g_ref.abs().max())


@pytest.mark.parametrize("dtype, case", [(torch.float64, "mask+weight"), (torch.float64, "empty mask"),
                                         (torch.float32, "plain"), (torch.float64, "equal")])
def test_fused_loss_gives_the_training_logs_psnr(dtype, case):
    """The fourth value is psnr_tensor's PSNR of the same images: the render clamped to [0, 1]
    (values outside it here), over the mask and unweighted (the loss's weight does not enter),
    every pixel for an all-false mask, and a finite 120 dB (mse floored at 1e-12) for equal images."""
    g = torch.Generator().manual_seed(4)
    h, w = 9, 70  # 3x2 tiles of 4x64
    gt = torch.rand(h, w, 3, dtype=dtype, generator=g).to(DEVICE)
    pred = (gt + 0.3 * torch.randn(h, w, 3, dtype=dtype, generator=g).to(DEVICE)).requires_grad_(True)
    if case == "equal":
        pred = gt.clone().requires_grad_(True)
    mask = {"mask+weight": (torch.rand(h, w, generator=g) > 0.3).to(DEVICE),
            "empty mask": torch.zeros(h, w, dtype=torch.bool, device=DEVICE)}.get(case)
    weight = losses.solid_angle_weight(h, w, dtype, DEVICE) if "weight" in case else None
    fused = photometric_triton.photometric_loss(pred, gt, 0.8, 0.2, mask=mask, weight=weight)[3]
    ref = losses.psnr_tensor(pred, gt, mask)
    assert float((pred.detach() < 0).sum() + (pred.detach() > 1).sum()) > 0 or case == "equal"
    assert not fused.requires_grad and fused.dtype == dtype
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    if case == "equal":  # the kernel's 1e-12 floor is a float32 literal: 120 dB to 2e-8
        tol = 1e-6
    assert abs(float(fused) - float(ref)) <= tol, (float(fused), float(ref))
    if case == "equal":
        assert float(fused) == pytest.approx(120.0)


def test_fused_loss_of_an_empty_mask_and_flat_images_is_finite():
    """No valid pixel: L1 0 and SSIM 0 (as the torch loss: no 0/0), gradient 0; a constant image
    has zero variance everywhere (SSIM's denominators then rest on C1, C2 alone)."""
    h, w = 5, 12
    pred = torch.full((h, w, 3), 0.5, dtype=torch.float64, device=DEVICE)
    gt = torch.full((h, w, 3), 0.5, dtype=torch.float64, device=DEVICE)
    empty = torch.zeros(h, w, dtype=torch.bool, device=DEVICE)
    (fused, g_fused), (ref, g_ref) = _both(pred, gt, mask=empty)
    assert torch.isfinite(fused).all() and torch.equal(g_fused, torch.zeros_like(g_fused))
    assert torch.allclose(fused, ref, atol=1e-15)
    (fused, g_fused), (ref, g_ref) = _both(pred, gt)  # identical flat images: SSIM 1, L1 0
    assert torch.allclose(fused, ref, atol=1e-12) and abs(float(fused[2]) - 1.0) < 1e-12
    assert torch.allclose(g_fused, g_ref, atol=1e-12)


def test_fused_loss_reads_a_strided_render_and_only_the_loss_gradient_is_needed():
    """A render viewed as [H,W,3] from a channels-first buffer is read through its strides; with
    only the loss used, the backward is the loss's alone."""
    h, w = 6, 27
    g = torch.Generator().manual_seed(1)
    chw = torch.rand(3, h, w, dtype=torch.float64, generator=g).to(DEVICE)
    gt = torch.rand(h, w, 3, dtype=torch.float64, generator=g).to(DEVICE)
    pred = chw.permute(1, 2, 0)
    (fused, g_fused), (ref, g_ref) = _both(pred, gt, upstream=(1.0,))
    assert torch.allclose(fused, ref, atol=1e-12)
    assert float((g_fused - g_ref).abs().max()) <= 1e-12 * float(g_ref.abs().max())


def test_fused_loss_is_five_launches_and_a_few_allocations(monkeypatch):
    """The point of the fusion: the loss and its backward in a handful of device operations
    (the torch loss is ~90 on a GPU), and no host sync."""
    monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
    h, w = 6, 27
    pred = torch.rand(h, w, 3, device=DEVICE, requires_grad=True)
    gt = torch.rand(h, w, 3, device=DEVICE)
    mask = torch.rand(h, w, device=DEVICE) > 0.2
    losses.photometric_loss(pred, gt, 0.8, 0.2, mask=mask)  # the window, made once per dtype and device
    with DispatchCounter() as counter:
        loss, _, _, _ = losses.photometric_loss(pred, gt, 0.8, 0.2, mask=mask, with_psnr=True)
        loss.backward()
    assert sum(counter.kernels.values()) == 5, counter.summary()
    # + 5 allocations (no launch), the mask's conversion and backward()'s seed: 13
    assert counter.device_ops <= 13, counter.summary()
    assert not counter.sync_ops, counter.summary()
