"""Tile binning for the ``cuda`` backend without host synchronisation.

:func:`splatting.raster_torch.bin_gaussians_torch` sizes its pair list from the data
(``repeat_interleave``, ``bincount``), so the host waits for the device on every render.
Here the pair list has a preallocated capacity instead, and every shape is known on the
host before the device runs:

1. the Gaussians are ordered by their depth keys (splatting.project.depth_key; one ``sort``);
2. the projection kernel has counted each Gaussian's tiles (splatting/project_triton.py);
   one ``cumsum`` in depth order gives each Gaussian its slice of the pair list;
3. a kernel writes, per pair, the tile index (the sort key) and the Gaussian; a tile of the
   box that the footprint cannot reach (the tile test below) and the slots past the last pair
   keep the key ``ntiles`` (after every tile), so the rasteriser never walks them;
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

**The tile test.** A splat's pixel box is the bounding box of its ellipse, so many of the box's
tiles hold no pixel the splat reaches: 10 % of the pairs of `bench render`'s 300k Gaussians at
512×1024, 20 % of a trained model's, twice that with 8×8 tiles (docs/gpu.md, "The tile test").
Each pair costs the rasteriser a full trip of its loop all the same. The test keeps a tile unless
the splat's footprint (½ pᵀQp ≤ τ on its tangent plane) misses a convex region that holds every
pixel centre of the tile:
* equirectangular: the region between the tile's two meridians and the great circles through
  its corners; the edge nearer the equator moves equatorwards until its great circle clears the
  parallel it replaces (a great circle through two points of a parallel bulges towards the
  pole). Corners are made of a per-row and a per-column table (:func:`tile_corners`);
* pinhole: the tile's pixel rectangle.
On the splat's tangent plane that region is a convex quadrilateral (great circles project to
lines); with Q = LLᵀ the footprint is a disc of radius √(2τ), so the test is a disc against a
convex quadrilateral: the centre inside, or an edge within the radius. A corner behind the
tangent plane, a degenerate Q or tiles wider than 90° keep the tile. The region is widened by
``CULL_MARGIN_PX`` of a pixel and τ by ``CULL_SLACK``, far beyond rounding, so the image is
exactly the one without the test (tests/splatting/test_tile_culling.py checks every pixel).
"""

from __future__ import annotations

import math
import warnings

import torch

from .cameras import EquirectCamera
from .devices import cdiv, device_key
from .optional_triton import tl, triton  # raster_triton reports a missing triton
from .project import PACK
from .project_triton import INTS

#: the tile test's widening of a tile (a share of a pixel) and of the cutoff τ (relative)
CULL_MARGIN_PX = 1e-2
CULL_SLACK = 1e-3

if triton is not None:
    _PACK = tl.constexpr(PACK)
    _CULL_SLACK = tl.constexpr(CULL_SLACK)

    @triton.jit
    def _corner(r0, r1, c0, c1, m00, m01, m02, m10, m11, m12, n0, n1, n2, uc, vc, l00, l10, l11):
        """A tile corner's direction (r0·c0, r1, r0·c1) on the splat's tangent plane, in the
        coordinates where the footprint is a disc (w = Lᵀ(p − centre)); and its c = n·d."""
        dx = r0 * c0
        dz = r0 * c1
        c = n0 * dx + n1 * r1 + n2 * dz
        ic = 1.0 / tl.where(c > 0, c, 1.0)
        u = (m00 * dx + m01 * r1 + m02 * dz) * ic - uc
        v = (m10 * dx + m11 * r1 + m12 * dz) * ic - vc
        return l00 * u + l10 * v, l11 * v, c

    @triton.jit
    def _edge(ax, ay, bx, by):
        """(squared distance from the origin to the segment a-b, the sign side of the origin)."""
        ex = bx - ax
        ey = by - ay
        t = tl.minimum(tl.maximum(-(ax * ex + ay * ey) / tl.maximum(ex * ex + ey * ey, 1e-30), 0.0), 1.0)
        px = ax + t * ex
        py = ay + t * ey
        return px * px + py * py, ay * ex - ax * ey

    @triton.jit
    def _emit_pairs(ints, order, offsets, keys, gids, P, rows, cols, CAP, N, TS, NTX, INTS: tl.constexpr,
                    BLOCK: tl.constexpr, CULL: tl.constexpr):
        """BLOCK Gaussians per program, taken in depth order: each writes its (tile, Gaussian) pairs
        at its slice of the list, a tile the footprint cannot reach with the key past every tile
        (CULL: the tile test of the module docstring). ``ints`` rows (splatting/project_triton.py):
        row0, row1, col0, ncols, tiles covered, radius, depth key; ``P`` the packed rows; ``rows``
        and ``cols`` the corner tables of :func:`tile_corners`."""
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < N
        g = tl.load(order + i, mask=ok, other=0).to(tl.int32)
        row = ints + g * INTS
        n = tl.load(row + 4, mask=ok, other=0)
        tr0 = tl.load(row, mask=ok, other=0) // TS
        tc0 = tl.load(row + 2, mask=ok, other=0) // TS
        ntc = tl.maximum(n // tl.maximum(tl.load(row + 1, mask=ok, other=0) // TS - tr0 + 1, 1), 1)
        base = tl.load(offsets + i, mask=ok, other=0) - n
        if CULL:
            pr = P + g * _PACK
            m00 = tl.load(pr, mask=ok, other=0)
            m01 = tl.load(pr + 1, mask=ok, other=0)
            m02 = tl.load(pr + 2, mask=ok, other=0)
            m10 = tl.load(pr + 3, mask=ok, other=0)
            m11 = tl.load(pr + 4, mask=ok, other=0)
            m12 = tl.load(pr + 5, mask=ok, other=0)
            n0 = tl.load(pr + 6, mask=ok, other=0)
            n1 = tl.load(pr + 7, mask=ok, other=0)
            n2 = tl.load(pr + 8, mask=ok, other=0)
            uc = tl.load(pr + 9, mask=ok, other=0)
            vc = tl.load(pr + 10, mask=ok, other=0)
            q00 = tl.load(pr + 11, mask=ok, other=0)
            q01 = tl.load(pr + 12, mask=ok, other=0)
            q11 = tl.load(pr + 13, mask=ok, other=0)
            cut = 2.0 * tl.load(pr + 19, mask=ok, other=0) * (1.0 + _CULL_SLACK) + 1e-4
            # Q = LLᵀ (Q = [[q00, q01], [q01, q11]], the footprint ½ pᵀQp ≤ τ)
            l00 = tl.sqrt(tl.maximum(q00, 1e-30))
            l10 = q01 / l00
            l11sq = q11 - l10 * l10
            l11 = tl.sqrt(tl.maximum(l11sq, 0.0))
            testable = (q00 > 0) & (l11sq > 0)
        for j in range(0, tl.max(n, axis=0)):
            slot = base + j
            m = (j < n) & (slot < CAP)
            tr = tr0 + j // ntc
            tc = (tc0 + j % ntc) % NTX
            if CULL:
                rt0 = tl.load(rows + tr * 4, mask=m, other=1)
                rt1 = tl.load(rows + tr * 4 + 1, mask=m, other=0)
                rb0 = tl.load(rows + tr * 4 + 2, mask=m, other=1)
                rb1 = tl.load(rows + tr * 4 + 3, mask=m, other=0)
                cl0 = tl.load(cols + tc * 4, mask=m, other=0)
                cl1 = tl.load(cols + tc * 4 + 1, mask=m, other=1)
                cr0 = tl.load(cols + tc * 4 + 2, mask=m, other=0)
                cr1 = tl.load(cols + tc * 4 + 3, mask=m, other=1)
                ax, ay, ca = _corner(rt0, rt1, cl0, cl1, m00, m01, m02, m10, m11, m12, n0, n1, n2, uc, vc, l00, l10, l11)
                bx, by, cb = _corner(rt0, rt1, cr0, cr1, m00, m01, m02, m10, m11, m12, n0, n1, n2, uc, vc, l00, l10, l11)
                cx, cy, cc = _corner(rb0, rb1, cr0, cr1, m00, m01, m02, m10, m11, m12, n0, n1, n2, uc, vc, l00, l10, l11)
                dx, dy, cd = _corner(rb0, rb1, cl0, cl1, m00, m01, m02, m10, m11, m12, n0, n1, n2, uc, vc, l00, l10, l11)
                dab, sab = _edge(ax, ay, bx, by)
                dbc, sbc = _edge(bx, by, cx, cy)
                dcd, scd = _edge(cx, cy, dx, dy)
                dda, sda = _edge(dx, dy, ax, ay)
                inside = ((sab >= 0) & (sbc >= 0) & (scd >= 0) & (sda >= 0)) | (
                    (sab <= 0) & (sbc <= 0) & (scd <= 0) & (sda <= 0))
                near = tl.minimum(tl.minimum(dab, dbc), tl.minimum(dcd, dda)) <= cut
                front = (ca > 0) & (cb > 0) & (cc > 0) & (cd > 0)
                keep = ~(front & testable) | inside | near
                tl.store(keys + slot, tr * NTX + tc, mask=m & keep)
            else:
                tl.store(keys + slot, tr * NTX + tc, mask=m)
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


_CORNERS: dict = {}


def tile_corners(camera, ts: int, dtype, device):
    """The tile test's corner tables of `camera` with `ts`-pixel tiles: (rows [nty, 4], cols
    [ntx, 4]) such that the four corners of tile (r, c) are (R0·C0, R1, R0·C1) for R = rows[r][0:2]
    (top) or [2:4] (bottom) and C = cols[c][0:2] (left) or [2:4] (right); None where the test does
    not hold (equirectangular tiles wider than 90°). Cached per camera, tile, dtype and device."""
    key = (camera, int(ts), dtype, device_key(device))
    if key in _CORNERS:
        return _CORNERS[key]
    H, W, m = int(camera.height), int(camera.width), CULL_MARGIN_PX
    r0 = torch.arange(0, H, ts, dtype=torch.float64)
    r1 = torch.clamp(r0 + ts, max=H) - 1
    c0 = torch.arange(0, W, ts, dtype=torch.float64)
    c1 = torch.clamp(c0 + ts, max=W) - 1
    if isinstance(camera, EquirectCamera):
        half = ((ts - 1) / 2 + m) * 2 * math.pi / W  # half a full tile's longitudes: narrower tiles are inside
        if half >= math.pi / 4:
            _CORNERS[key] = None
            return None
        top = torch.clamp(math.pi * (0.5 - (r0 + 0.5 - m) / H), max=math.pi / 2)
        bottom = torch.clamp(math.pi * (0.5 - (r1 + 0.5 + m) / H), min=-math.pi / 2)
        # the edge whose great circle would bulge into the tile: tan θ' = tan θ · cos(half)
        top = torch.where(top < 0, torch.atan(torch.tan(top) * math.cos(half)), top)
        bottom = torch.where(bottom > 0, torch.atan(torch.tan(bottom) * math.cos(half)), bottom)
        rows = torch.stack([torch.cos(top), -torch.sin(top), torch.cos(bottom), -torch.sin(bottom)], -1)
        left = 2 * math.pi * ((c0 + 0.5 - m) / W - 0.5)
        right = 2 * math.pi * ((c1 + 0.5 + m) / W - 0.5)
        cols = torch.stack([torch.sin(left), torch.cos(left), torch.sin(right), torch.cos(right)], -1)
    else:  # a pinhole's pixel (c, r) looks along ((c + 0.5 − cx)/fx, (r + 0.5 − cy)/fy, 1)
        one = torch.ones_like(r0)
        rows = torch.stack([one, (r0 + 0.5 - m - camera.cy) / camera.fy, one, (r1 + 0.5 + m - camera.cy) / camera.fy], -1)
        one = torch.ones_like(c0)
        cols = torch.stack([(c0 + 0.5 - m - camera.cx) / camera.fx, one, (c1 + 0.5 + m - camera.cx) / camera.fx, one], -1)
    if len(_CORNERS) >= 16:
        _CORNERS.clear()
    out = tuple(t.to(dtype=dtype, device=device).contiguous() for t in (rows, cols))
    _CORNERS[key] = out
    return out


def emit_launch(ints, order, offsets, keys, gids, CAP, ts, ntx, n, packed=None, corners=None):
    """(kernel, grid, args, options) of the pair writer, for the launch and the compile check;
    with `packed` and `corners` (:func:`tile_corners`) the tile test culls."""
    cull = packed is not None and corners is not None
    P, rows, cols = (packed, *corners) if cull else (ints, ints, ints)  # any pointer: never read without CULL
    return (_emit_pairs, (cdiv(n, EMIT_BLOCK),), (ints, order, offsets, keys, gids, P, rows, cols, CAP, n, ts, ntx),
            dict(INTS=INTS, BLOCK=EMIT_BLOCK, CULL=cull, num_warps=4))


EMIT_BLOCK = 128


def bin_gaussians(ints: torch.Tensor, H: int, W: int, ts: int, capacity: PairCapacity = None,
                  packed: torch.Tensor = None, camera=None):
    """Tile lists from the projection kernel's integer rows ``ints`` [N, INTS] (box, tiles covered,
    depth key): offsets [ntiles+1] int32, Gaussian indices [capacity] int32 (front to
    back within each tile, ties in index order, the lists of ``bin_gaussians_torch`` less the
    tiles the tile test culls, when ``packed`` and ``camera`` are given) and the pair count of the
    boxes (a device scalar: what the list's capacity must hold). Nine device operations; no host
    sync once the capacity is sized."""
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
        corners = None if packed is None or camera is None else tile_corners(camera, ts, packed.dtype, device)
        kernel, grid, args, options = emit_launch(ints, order, offsets, keys, gids, CAP, ts, ntx, n, packed, corners)
        kernel[grid](*args, **options)
    skeys, perm = torch.sort(keys, stable=True)
    tlist = gids[perm]
    toff = torch.searchsorted(skeys, _tile_ids(ntiles, device), out_int32=True)
    total = offsets[-1:] if n else torch.zeros(1, dtype=torch.int32, device=device)
    if not capturing:
        cap.record(total, CAP)
    return toff, tlist, total
