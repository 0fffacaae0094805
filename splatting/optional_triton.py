"""Triton where it is installed: the one optional import the kernel modules share. Without it the
rest of the package works (the `cpp` and `torch` backends, the trainer's torch paths); the kernel
modules define their kernels under `if triton is not None` and their callers ask `available()`."""

from __future__ import annotations

import struct

try:
    import triton
    import triton.language as tl
except ImportError:
    triton = tl = None


def available() -> bool:
    """Whether triton imports here."""
    return triton is not None


def launch_float(x: float) -> float:
    """`x` as a compiled kernel receives it: Triton types a Python float argument float32 (its
    binder's signature, `scripts/gpu_check.sh` prints it on the GPU), where its interpreter keeps
    float64. On an H200 the float64 Adam test failed by float32's rounding of β₁, which the
    interpreter did not show: a launch rounds such arguments here, so that CI computes what the
    GPU does. A value a float64 kernel needs exactly goes in a tensor (splatting/layout_triton.py)."""
    return struct.unpack("f", struct.pack("f", float(x)))[0]
