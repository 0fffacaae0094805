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
