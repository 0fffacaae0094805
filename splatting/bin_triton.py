"""Tile binning for the ``cuda`` backend without host synchronisation.

:func:`splatting.raster_torch.bin_gaussians_torch` sizes its pair list from the data
(``repeat_interleave``, ``bincount``), so the host waits for the device on every render.
Here the pair list has a preallocated capacity instead, and every shape is known on the
host before the device runs:

1. the Gaussians are ordered by their depth keys (splatting.project.depth_key; one ``sort``);
2. the projection kernel has counted each Gaussian's tiles (splatting/project_triton.py);
   one ``cumsum`` in depth order gives each Gaussian its slice of the pair list;
3. a kernel writes, per pair, the tile index (the sort key) and the Gaussian;
   slots past the last pair keep the key ``ntiles`` (after every tile);
4. one stable ``sort`` of the keys groups the pairs by tile and keeps the depth order
   inside each tile; ``searchsorted`` gives the tile offsets.

Pairs beyond the capacity are dropped by the kernel, and the render would then miss
them. :class:`PairCapacity` sizes the list once by reading the pair count (the first render
on a device, and again when the scene has grown by a quarter, as densification does), with a
50 % margin; after that each render copies its pair count to pinned host memory
asynchronously, and a later render reads it once its event has completed, growing the
capacity before the margin is used up. A render that finds an earlier one overflowed warns
and says by how much.
Everything is int32 (the kernels index with 32-bit integers: up to 2³¹ pairs).
"""

from __future__ import annotations

import warnings

import torch

from .devices import cdiv, device_key
from .optional_triton import tl, triton  # raster_triton reports a missing triton
from .project_triton import INTS

if triton is not None:

    @triton.jit
    def _emit_pairs(ints, order, offsets, keys, gids, CAP, N, TS, NTX, INTS: tl.constexpr, BLOCK: tl.constexpr):
        """BLOCK Gaussians per program, taken in depth order: each writes its (tile, Gaussian) pairs
        at its slice of the list. ``ints`` rows (splatting/project_triton.py): row0, row1, col0,
        ncols, tiles covered, radius, depth key."""
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < N
        g = tl.load(order + i, mask=ok, other=0).to(tl.int32)
        row = ints + g * INTS
        n = tl.load(row + 4, mask=ok, other=0)
        tr0 = tl.load(row, mask=ok, other=0) // TS
        tc0 = tl.load(row + 2, mask=ok, other=0) // TS
        ntc = tl.maximum(n // tl.maximum(tl.load(row + 1, mask=ok, other=0) // TS - tr0 + 1, 1), 1)
        base = tl.load(offsets + i, mask=ok, other=0) - n
        for j in range(0, tl.max(n, axis=0)):
            slot = base + j
            m = (j < n) & (slot < CAP)
            tl.store(keys + slot, (tr0 + j // ntc) * NTX + (tc0 + j % ntc) % NTX, mask=m)
            tl.store(gids + slot, g, mask=m)


class PairCapacity:
    """The pair list's capacity on one device, grown from the counts of earlier renders
    without waiting for them (see the module docstring)."""

    def __init__(self, initial: int = 1 << 16, growth: float = 1.5, regrow_n: float = 1.25, device=None):
        self.capacity = int(initial)
        self.growth = float(growth)
        self.regrow_n = float(regrow_n)
        self.sized_n = None  # Gaussian count of the last synchronous sizing (None: never sized)
        self._pending = None  # (event or None, host count, capacity used) of the render in flight
        # the pinned buffer the counts are copied into (allocated here, not during a render)
        cuda = device is not None and torch.device(device).type == "cuda"
        self._host = torch.empty(1, dtype=torch.int32, pin_memory=True) if cuda else None
        self.largest_seen = 0

    def needs_sizing(self, n: int) -> bool:
        """Whether this render must read its pair count before allocating: on the first render,
        and when the scene has grown past ``regrow_n`` × the count it was sized for (densification)."""
        return self.sized_n is None or n > self.regrow_n * self.sized_n

    def size(self, n: int, pairs: int):
        """Size for ``pairs`` pairs of a render of ``n`` Gaussians (with the growth margin)."""
        self.largest_seen = max(self.largest_seen, int(pairs))
        self.capacity = max(self.capacity, int(pairs * self.growth) + 1)
        self.sized_n = int(n)

    def _observe(self, count: int, used: int):
        self.largest_seen = max(self.largest_seen, count)
        if count > used:
            warnings.warn(f"splatting: a render had {count} tile-Gaussian pairs, more than the pair capacity {used}; "
                          f"it missed the rest. The capacity grows to {int(count * self.growth)} (set it ahead with "
                          "splatting.bin_triton.capacity_for(device).reserve).", RuntimeWarning, stacklevel=4)
        if count * self.growth > self.capacity:
            self.capacity = int(count * self.growth) + 1

    def poll(self):
        """Read the count of the render in flight if it has finished (never waits for the device)."""
        if self._pending is None:
            return
        event, host, used = self._pending
        if event is None or event.query():
            self._pending = None
            # a host buffer (pinned, filled by a finished copy; on the CPU the tensor itself):
            # reading it through numpy waits for nothing and dispatches nothing
            self._observe(int(host.numpy()[0]), used)

    def record(self, total: torch.Tensor, used: int):
        """Have this render's pair count copied to the host asynchronously, unless an earlier
        count is still in flight (one pinned buffer, reused)."""
        if self._pending is not None:
            return
        if total.device.type == "cuda":
            if self._host is None:
                self._host = torch.empty(1, dtype=total.dtype, pin_memory=True)
            self._host.copy_(total.reshape(1), non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self._pending = (event, self._host, used)
        else:  # on the CPU (the interpreter) the value is already there
            self._pending = (None, total.reshape(1), used)

    def reserve(self, pairs: int, n: int):
        """Make room for ``pairs`` pairs from the next render of about ``n`` Gaussians on (no sizing sync)."""
        self.capacity = max(self.capacity, int(pairs))
        self.sized_n = int(n)


_CAPACITIES: dict = {}
_TILE_IDS: dict = {}


def capacity_for(device: torch.device) -> PairCapacity:
    key = device_key(device)
    if key not in _CAPACITIES:
        _CAPACITIES[key] = PairCapacity(device=device)
    return _CAPACITIES[key]


def _tile_ids(ntiles, device):
    key = (ntiles, device_key(device))
    if key not in _TILE_IDS:
        if len(_TILE_IDS) >= 16:
            _TILE_IDS.clear()
        _TILE_IDS[key] = torch.arange(ntiles + 1, dtype=torch.int32, device=device)
    return _TILE_IDS[key]


def emit_launch(ints, order, offsets, keys, gids, CAP, ts, ntx, n):
    """(kernel, grid, args, options) of the pair writer, for the launch and the compile check."""
    return (_emit_pairs, (cdiv(n, EMIT_BLOCK),), (ints, order, offsets, keys, gids, CAP, n, ts, ntx),
            dict(INTS=INTS, BLOCK=EMIT_BLOCK, num_warps=4))


EMIT_BLOCK = 128


def bin_gaussians(ints: torch.Tensor, H: int, W: int, ts: int, capacity: PairCapacity = None):
    """Tile lists from the projection kernel's integer rows ``ints`` [N, INTS] (box, tiles covered,
    depth key): offsets [ntiles+1] int32, Gaussian indices [capacity] int32 (front to
    back within each tile, ties in index order, the lists of ``bin_gaussians_torch``) and the
    pair count (a device scalar). Nine device operations; no host sync once the capacity is sized."""
    device = ints.device
    cap = capacity if capacity is not None else capacity_for(device)
    # inside a CUDA graph capture the capacity is frozen into the graph: no event queries or copies
    capturing = device.type == "cuda" and torch.cuda.is_current_stream_capturing()
    if not capturing:
        cap.poll()
    ntx, nty = (W + ts - 1) // ts, (H + ts - 1) // ts
    ntiles = ntx * nty
    n = ints.shape[0]
    order = torch.sort(ints[:, 6], stable=True).indices
    offsets = torch.cumsum(ints[:, 4][order], 0, dtype=torch.int32)
    if n and not capturing and cap.needs_sizing(n):
        cap.size(n, int(offsets[-1]))  # the one host sync: first render, or after the scene grew
    CAP = cap.capacity
    keys = torch.full((CAP,), ntiles, dtype=torch.int32, device=device)
    gids = torch.empty(CAP, dtype=torch.int32, device=device)
    if n:
        kernel, grid, args, options = emit_launch(ints, order, offsets, keys, gids, CAP, ts, ntx, n)
        kernel[grid](*args, **options)
    skeys, perm = torch.sort(keys, stable=True)
    tlist = gids[perm]
    toff = torch.searchsorted(skeys, _tile_ids(ntiles, device), out_int32=True)
    total = offsets[-1:] if n else torch.zeros(1, dtype=torch.int32, device=device)
    if not capturing:
        cap.record(total, CAP)
    return toff, tlist, total
