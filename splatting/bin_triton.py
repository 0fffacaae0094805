"""Tile binning for the ``cuda`` backend without host synchronisation.

:func:`splatting.raster_torch.bin_gaussians_torch` sizes its pair list from the data
(``repeat_interleave``, ``bincount``), so the host waits for the device on every render.
Here the pair list has a preallocated capacity instead, and every shape is known on the
host before the device runs:

1. the visible Gaussians are ordered by distance (one ``sort``);
2. a Triton kernel counts each Gaussian's tiles (in depth order), one ``cumsum`` gives
   each Gaussian its slice of the pair list;
3. a second kernel writes, per pair, the tile index (the sort key) and the Gaussian;
   slots past the last pair keep the key ``ntiles`` (after every tile);
4. one stable ``sort`` of the keys groups the pairs by tile and keeps the depth order
   inside each tile; ``searchsorted`` gives the tile offsets.

Pairs beyond the capacity are dropped by the kernel, and the render would then miss
them; :class:`PairCapacity` prevents that without waiting: each render copies its pair
count to pinned host memory asynchronously, and the next render reads it only once its
event has completed, growing the capacity before anything is lost in steady state. A
render that finds an earlier one overflowed warns (once) and says by how much.
Everything is int32 (the kernels index with 32-bit integers: up to 2³¹ pairs).
"""

from __future__ import annotations

import warnings

import torch

try:
    import triton
    import triton.language as tl
except ImportError:  # raster_triton reports it
    triton = None

if triton is not None:

    @triton.jit
    def _tile_range(bbox, g, W, TS, NTX):
        """First tile row, tile rows, first tile column and tile columns of Gaussian ``g``'s
        box (columns wrap modulo W: one circular run starting at tile c0 // TS)."""
        r0 = tl.load(bbox + g * 4)
        r1 = tl.load(bbox + g * 4 + 1)
        c0 = tl.load(bbox + g * 4 + 2)
        nc = tl.load(bbox + g * 4 + 3)
        tr0 = r0 // TS
        tc0 = c0 // TS
        end = c0 + nc
        ntc = tl.where(end > W, NTX - tc0 + (end - W - 1) // TS + 1, (end - 1) // TS - tc0 + 1)
        ntc = tl.minimum(ntc, NTX)
        ntr = tl.where(r1 >= r0, r1 // TS - tr0 + 1, 0)
        return tr0, ntr, tc0, ntc

    @triton.jit
    def _count_tiles(bbox, order, counts, N, W, TS, NTX, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < N
        g = tl.load(order + i, mask=ok, other=0)
        tr0, ntr, tc0, ntc = _tile_range(bbox, g, W, TS, NTX)
        tl.store(counts + i, tl.where(ok, ntr * ntc, 0), mask=ok)

    @triton.jit
    def _emit_pairs(bbox, order, offsets, keys, gids, CAP, W, TS, NTX):
        """One program per Gaussian (in depth order): its pairs (tile, Gaussian) at its slice."""
        i = tl.program_id(0)
        g = tl.load(order + i)
        tr0, ntr, tc0, ntc = _tile_range(bbox, g, W, TS, NTX)
        n = ntr * ntc
        base = tl.load(offsets + i) - n
        for j in range(0, n):
            slot = base + j
            if slot < CAP:
                tile = (tr0 + j // ntc) * NTX + (tc0 + j % ntc) % NTX
                tl.store(keys + slot, tile)
                tl.store(gids + slot, g)


class PairCapacity:
    """The pair list's capacity on one device, grown from the counts of earlier renders
    without waiting for them (see the module docstring)."""

    def __init__(self, initial: int = 1 << 16, growth: float = 1.5):
        self.capacity = int(initial)
        self.growth = float(growth)
        self._pending = []  # (event or None, pinned host count, capacity used)
        self.largest_seen = 0

    def _observe(self, count: int, used: int):
        self.largest_seen = max(self.largest_seen, count)
        if count > used:
            warnings.warn(f"splatting: a render had {count} tile-Gaussian pairs, more than the pair capacity {used}; "
                          f"it missed the rest. The capacity grows to {int(count * self.growth)} (set it ahead with "
                          "splatting.bin_triton.PairCapacity.reserve).", RuntimeWarning, stacklevel=4)
        if count * self.growth > self.capacity:
            self.capacity = int(count * self.growth) + 1

    def poll(self):
        """Read the counts of finished renders (never waits for the device)."""
        still = []
        for event, host, used in self._pending:
            if event is None or event.query():
                self._observe(int(host[0]), used)
            else:
                still.append((event, host, used))
        self._pending = still

    def record(self, total: torch.Tensor, used: int):
        """Remember this render's pair count, copied to the host asynchronously."""
        if total.device.type == "cuda":
            host = torch.empty(1, dtype=total.dtype, pin_memory=True)
            host.copy_(total.reshape(1), non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self._pending.append((event, host, used))
        else:  # on the CPU (the interpreter) the value is already there
            self._pending.append((None, total.reshape(1), used))

    def reserve(self, pairs: int):
        """Make room for ``pairs`` pairs from the next render on."""
        self.capacity = max(self.capacity, int(pairs))


_CAPACITIES: dict = {}


def capacity_for(device: torch.device) -> PairCapacity:
    key = (device.type, device.index)
    if key not in _CAPACITIES:
        _CAPACITIES[key] = PairCapacity()
    return _CAPACITIES[key]


def bin_gaussians(bbox: torch.Tensor, dist: torch.Tensor, H: int, W: int, ts: int, capacity: PairCapacity = None):
    """Tile lists (offsets [ntiles+1] int32, Gaussian indices [capacity] int32, sorted front to
    back by ``dist`` within each tile) and the pair count (a device scalar); the same lists as
    ``bin_gaussians_torch`` (ties in index order) while the count fits the capacity."""
    device = bbox.device
    cap = capacity if capacity is not None else capacity_for(device)
    cap.poll()
    CAP = cap.capacity
    ntx, nty = (W + ts - 1) // ts, (H + ts - 1) // ts
    ntiles = ntx * nty
    nv = bbox.shape[0]
    bbox = bbox.to(torch.int32).contiguous()
    order = torch.sort(dist.detach(), stable=True).indices.to(torch.int32)
    counts = torch.empty(nv, dtype=torch.int32, device=device)
    BLOCK = 256
    if nv:
        _count_tiles[(triton.cdiv(nv, BLOCK),)](bbox, order, counts, nv, W, ts, ntx, BLOCK=BLOCK)
    offsets = torch.cumsum(counts, 0, dtype=torch.int32)
    keys = torch.full((CAP,), ntiles, dtype=torch.int32, device=device)
    gids = torch.empty(CAP, dtype=torch.int32, device=device)
    if nv:
        _emit_pairs[(nv,)](bbox, order, offsets, keys, gids, CAP, W, ts, ntx)
    skeys, perm = torch.sort(keys, stable=True)
    tlist = gids[perm]
    toff = torch.searchsorted(skeys, torch.arange(ntiles + 1, dtype=torch.int32, device=device), out_int32=True)
    total = offsets[-1:] if nv else torch.zeros(1, dtype=torch.int32, device=device)
    cap.record(total, CAP)
    return toff, tlist, total
