"""Device memory of one ``cuda``-backend render, from its allocations (docs/gpu.md).

Every buffer the render allocates is listed here with its size; tests/splatting/test_cuda_pipeline.py
checks the forward's sum against the allocations actually made (splatting.dispatch_count.AllocationTracker,
on CPU tensors with the Triton interpreter).
"""

from __future__ import annotations

from .project import PACK
from .project_triton import INTS

# The backward's peak, float32, per Gaussian and per pixel: measured with the allocation tracker
# on small scenes with RGB colours (docs/gpu.md), not derived: the packed rows' gradient and the
# projection backward kernel's outputs (means, quaternions, scales, opacities, colours, means2d).
BACKWARD_BYTES_PER_GAUSSIAN_F32 = 174
BACKWARD_BYTES_PER_PIXEL_F32 = 24


def forward_bytes(n: int, height: int, width: int, capacity: int, element: int = 4, tile: int = 16) -> dict:
    """Peak bytes of a forward render by part: the larger of the binning peak and the raster peak,
    on top of the projection's buffers; plus the cached pixel directions."""
    ntiles = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
    px = height * width
    projection = n * (PACK * element + INTS * 4 + 1 + 2 * element)  # packed rows, box/counts/radius, visible, means2d
    # binning: depth order (int64), per-Gaussian offsets (int32; the pair count is a view of them);
    # pair slots: keys, Gaussians, sorted keys, permutation (int64), tile lists
    binning = n * (8 + 4) + capacity * (4 + 4 + 4 + 8 + 4)
    lists = capacity * 4 + (ntiles + 1) * 4 + n * 4
    raster = px * (3 * element + element + 2 * element + 4)  # colour, depth, T and alpha, last index
    dirs = px * 3 * element
    peak = projection + max(binning, lists + raster)
    return {"projection": projection, "binning": binning, "lists": lists, "raster": raster, "dirs": dirs,
            "peak": peak}


def training_step_bytes(n: int, height: int, width: int, capacity: int) -> int:
    """Peak of forward + backward in float32: the larger of the forward's peak and the backward's
    (measured coefficients, see above: when the projection is recomputed, plus the tile lists)."""
    backward = n * BACKWARD_BYTES_PER_GAUSSIAN_F32 + height * width * BACKWARD_BYTES_PER_PIXEL_F32 + capacity * 4
    return max(forward_bytes(n, height, width, capacity)["peak"], backward)
