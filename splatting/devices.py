"""One name per device for the per-device caches (pixel directions, tile ids, pair capacity).

``torch.device("cuda")`` and a tensor's ``cuda:0`` are the same GPU but different keys: a cache
filled under one is missed under the other (issue 35: the pair capacity reserved for "cuda" was
never read by renders on "cuda:0", and every render rebuilt the pixel directions).
"""

from __future__ import annotations

import torch


def device_key(device) -> tuple[str, int | None]:
    """(type, index) with the current CUDA device filled in for an index-less ``cuda``."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return ("cuda", torch.cuda.current_device())
    return (device.type, device.index)


#: Run the training step's Triton kernels (the photometric loss, the random turn, the
#: densification statistics) on CPU tensors too, in the Triton interpreter: the tests set it
#: to check and count what a GPU runs. One switch for all of them.
KERNELS_ON_CPU = False


def takes_kernels(t: torch.Tensor) -> bool:
    """Whether the training step's Triton kernels take tensor `t`: on a GPU (or on the CPU with
    KERNELS_ON_CPU), with triton importable; otherwise the callers' torch/CPU path runs."""
    if not (t.device.type == "cuda" or (KERNELS_ON_CPU and t.device.type == "cpu")):
        return False
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


def cdiv(a: int, b: int) -> int:
    """⌈a/b⌉ for launch grids, in plain Python ints: `triton.cdiv` is a ConstexprFunction in
    Triton 3.8 and costs microseconds a call on the host, a dozen calls every training step."""
    return -(-a // b)
