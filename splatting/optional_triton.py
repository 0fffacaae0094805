"""Triton where it is installed: the one optional import the kernel modules share. Without it the
rest of the package works (the `cpp` and `torch` backends, the trainer's torch paths); the kernel
modules define their kernels under `if triton is not None` and their callers ask `available()`."""

from __future__ import annotations

try:
    import triton
    import triton.language as tl
except ImportError:
    triton = tl = None


def available() -> bool:
    """Whether triton imports here."""
    return triton is not None
