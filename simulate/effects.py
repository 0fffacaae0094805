"""The optional effects. Each is called only when the scene lists it.

The renderer calls these functions through this module (`effects.texture(...)`),
so a test can replace them and count calls. Without an effect, nothing in this
module runs for it: `texture` off gives flat per-material albedo (a table
look-up in render.py), `shading` off gives the albedo unlit, `tripod`,
`exposure` and `noise` off write the rendered image as is, `aa` off casts one
ray per pixel centre, and `furniture` off leaves the room empty.

The capture effects (`tripod`, `exposure`, `noise`) act on the rendered image,
in that order: the tripod is an object in front of the lens (so it is exposed
and gets sensor noise like the rest), then the camera's exposure and white
balance, then its sensor noise.
"""

from __future__ import annotations

import time

import numpy as np
from shapely.geometry import Point, Polygon, box
from shapely.prepared import prep

from panogeom.equirect import column_longitudes, row_latitudes
from simulate.geometry import FURNITURE_CAMERA_CLEARANCE, Box, Camera, World

EFFECTS = ("texture", "furniture", "shading", "noise", "exposure", "tripod", "aa", "detail", "plain-floor",
           "fixtures")
#: Effects that `all` leaves out, with what each draws: they change what every existing scene looks
#: like, so a scene gets them only by naming them.
OPT_IN_EFFECTS = {
    "detail": "the fine non-repeating surface detail structure from motion needs",
    "plain-floor": "a floor without features",
    "fixtures": "the lamps hanging under the ceiling",
}

# Mean albedo of each material: also the flat colour used when `texture` is off.
MATERIAL_RGB = {
    "floor_wood": np.array([0.62, 0.45, 0.30]),
    "floor_carpet": np.array([0.45, 0.50, 0.58]),
    "ceiling": np.array([0.92, 0.91, 0.88]),
    "paint": np.array([0.80, 0.76, 0.68]),
    "bare": np.array([0.84, 0.82, 0.78]),  # paint without the `detail` effect's blotches: low texture
    "wallpaper": np.array([0.70, 0.74, 0.66]),
}

# ----------------------------------------------------------------------------- helpers


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _hash(i: np.ndarray, j: np.ndarray, seed: int | np.ndarray = 0) -> np.ndarray:
    """Deterministic pseudo-random value in [0,1) per integer cell (i, j)."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) ^ (seed * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / np.float32(65536.0)


# ----------------------------------------------------------------------------- texture


# Texture kinds: which procedural pattern a surface gets (index into TEXTURE_KINDS).
TEXTURE_KINDS = ("plain", "floor_wood", "floor_carpet", "wallpaper", "wood", "fabric")


def _wood_floor(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Planks 0.18 m wide, 1.2 m long, staggered; smooth grain; dark joints. Returns a gain [N]."""
    pw, pl = 0.18, 1.2
    row = np.floor(v / pw)
    shift = _hash(row, row * 0 + 7) * pl
    uu = u + shift
    col = np.floor(uu / pl)
    tone = 0.82 + 0.36 * _hash(row, col, 1)
    fu = uu / pl - col
    fv = v / pw - row
    grain = 0.93 + 0.07 * np.sin(2 * np.pi * (fu * 2.0 + 0.8 * fv + 3.0 * _hash(col, row, 2)))
    joint = 1.0 - 0.35 * (1.0 - _smoothstep(0.0, 0.06, np.minimum(fv, 1 - fv))) - 0.3 * (
        1.0 - _smoothstep(0.0, 0.015, np.minimum(fu, 1 - fu))
    )
    return tone * grain * joint


def _carpet(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Checkerboard carpet, 0.5 m squares with soft (~3 cm) edges. Returns a gain [N]."""
    s = 0.5
    k = np.clip(np.sin(np.pi / s * u) * np.sin(np.pi / s * v) * 8.0, -1.0, 1.0)  # soft sign
    return 0.975 + 0.275 * k  # 1.25 light squares, 0.7 dark squares


_PAPER_INK = np.array([0.62, 0.42, 0.40], dtype=np.float32)


def _wallpaper(u: np.ndarray, v: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Vertical stripes (0.3 m period, smooth) with a diamond motif between them. Returns RGB [N,3]."""
    p = 0.3
    fu = u / p - np.floor(u / p)
    stripe = _smoothstep(0.05, 0.12, fu) * (1.0 - _smoothstep(0.38, 0.45, fu))
    du = np.abs(fu - 0.72) / 0.2
    fv = v / p - np.floor(v / p)
    dv = np.abs(fv - 0.5) / 0.5
    diamond = 0.45 * (1.0 - _smoothstep(0.7, 0.9, du + dv))
    gain = (1.12 - 0.34 * stripe) * (1.0 - diamond)
    return base * gain[:, None] + diamond[:, None] * _PAPER_INK[None, :]


def _furniture_wood(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return 0.9 + 0.1 * np.sin(2 * np.pi * (u * 3.0 + 0.4 * np.sin(2 * np.pi * 1.5 * v)))


def _fabric(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return 0.92 + 0.08 * np.sin(2 * np.pi / 0.4 * u)  # broad soft stripes on upholstery


_GAIN_PATTERNS = {"floor_wood": _wood_floor, "floor_carpet": _carpet, "wood": _furniture_wood, "fabric": _fabric}


def texture(kind: np.ndarray, uv: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """Procedural albedo [N,3]: `kind` [N] indexes TEXTURE_KINDS, `uv` [N,2] texture
    coordinates in metres, `albedo` [N,3] the flat (mean) colour of each hit."""
    out = albedo.copy()
    for k, name in enumerate(TEXTURE_KINDS):
        if name == "plain":
            continue  # paint, ceiling: the texture-less case
        sel = np.flatnonzero(kind == k)
        if len(sel) == 0:
            continue
        u, v = uv[sel, 0], uv[sel, 1]
        if name == "wallpaper":
            out[sel] = _wallpaper(u, v, albedo[sel])
            continue
        gain = _GAIN_PATTERNS[name](u, v)
        out[sel] = albedo[sel] * gain[:, None].astype(out.dtype)
    return np.clip(out, 0.0, 1.0, out=out)


DETAIL_CELLS_M = (0.12, 0.05, 0.02)  # octaves of the detail noise: blobs SIFT finds at 256..1024 px


def detail(surface: np.ndarray, uv: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """Albedo [N,3] with fine, non-repeating detail: multi-octave value noise in the surface's
    texture coordinates `uv` (metres), seeded per surface id `surface` [N] so no two surfaces
    look alike. Real rooms have such detail (scuffs, grain, clutter); plain paint and periodic
    wallpaper give structure from motion nothing to match, so scenes posed by SfM need it."""
    u = uv[:, 0].astype(np.float64)
    v = uv[:, 1].astype(np.float64)
    seed = surface.astype(np.int64)
    noise = sum(_value_noise(u, v, cell, seed + 101 * k) for k, cell in enumerate(DETAIL_CELLS_M))
    gain = 0.45 + 1.1 * _smoothstep(0.6, 2.4, noise)  # contrast stretched: dark and light blotches
    return np.clip(albedo * gain[:, None].astype(albedo.dtype), 0.0, 1.0)


def plain_floor(world: World) -> None:
    """A floor with few features, as a plain wooden or carpeted floor without rugs is: its
    material's flat colour (wood or carpet), neither `texture`'s planks or squares nor `detail`'s
    blotches; shading and sensor noise still reach it. Structure from motion then finds (almost)
    no point on the floor, only on the walls, the furniture and the ceiling."""
    world.floor_plain = True


# ----------------------------------------------------------------------------- shading

AMBIENT = 0.4
LIGHT_RADIUS = 2.0  # m: the soft falloff 1 / (1 + (d / r)^2)
LIGHT_GAIN = 0.75


def shading(points: np.ndarray, normals: np.ndarray, world: World) -> np.ndarray:
    """Irradiance factor [N] at `points` with `normals` (facing the viewer): ambient plus
    Lambertian ceiling lights with a soft 1 / (1 + (d/r)^2) falloff, each light lit only
    within its own room (no cast shadows)."""
    dt = points.dtype
    px, py, pz = points[:, 0], points[:, 1], points[:, 2]
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    e = np.full(len(points), AMBIENT, dtype=dt)
    multi = len(world.rooms) > 1
    if multi:
        qx = px + dt.type(1e-3) * nx
        qz = pz + dt.type(1e-3) * nz
    inv_r2 = dt.type(1.0 / LIGHT_RADIUS**2)
    for light in world.lights:
        lx, ly, lz = (dt.type(c) for c in light.position)
        dx, dy, dz = lx - px, ly - py, lz - pz
        dist2 = dx * dx + dy * dy + dz * dz
        ndl = nx * dx + ny * dy + nz * dz
        np.maximum(ndl, 0, out=ndl)
        contrib = dt.type(LIGHT_GAIN * light.intensity) * ndl / (np.sqrt(dist2) * (1 + dist2 * inv_r2))
        if multi:
            room = world.rooms[light.room]
            x0, z0 = room.polygon.min(axis=0)
            x1, z1 = room.polygon.max(axis=0)
            contrib *= (qx >= x0) & (qx <= x1) & (qz >= z0) & (qz <= z1)
        e += contrib
    return e


# ----------------------------------------------------------------------------- fixtures

FIXTURE_SIZE = (0.6, 0.08, 0.6)  # m: a lamp panel's width, thickness and depth
#: emitted, brighter than the sensor's white: it saturates, as real lamps do
FIXTURE_RGB = np.array([1.6, 1.55, 1.45])


def fixtures(world: World) -> list[Box]:
    """The lamps themselves, as boxes (kind "lamp"): a glowing panel of FIXTURE_SIZE hanging at
    each light, its underside at the light's height (LIGHT_DROP below the ceiling), which the
    renderer draws in emitted light (FIXTURE_RGB, `shading` does not reach it). Real rooms show
    their lamps, fans and chandeliers as saturated objects off the ceiling: from another view
    they land elsewhere on the ceiling, and a layout has no plane for them."""
    w, t, d = FIXTURE_SIZE
    out = []
    for light in world.lights:
        x, y, z = light.position
        out.append(Box("lamp", np.array([x - w / 2, y - t, z - d / 2]), np.array([x + w / 2, y, z + d / 2]),
                       np.array([0.9, 0.9, 0.9]), "plain"))
    return out


# ----------------------------------------------------------------------------- noise


def noise(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Sensor noise (shot + read), sigma = sqrt(0.004^2 + 0.012^2 I), image in [0,1].
    Exposure and white balance are the separate `exposure` effect."""
    sigma = np.sqrt(0.004**2 + (0.012**2) * np.clip(image, 0.0, None))
    img = image + sigma * rng.standard_normal(image.shape)
    return np.clip(img, 0.0, 1.0)


# ----------------------------------------------------------------------------- exposure

EXPOSURE_GAIN = (0.75, 1.25)  # per-view gain, log-uniform
WHITE_BALANCE = 0.08  # red and blue gains relative to green, uniform in [1 - x, 1 + x]


def exposure(image: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Per-view exposure and white balance: image x gain x (wb_r, 1, wb_b), clipped to [0,1].

    Returns the image and its parameters {"gain", "white_balance": [r, g, b] (g = 1),
    "channel_gains": gain x white_balance} (RGB order, the image's channel order)."""
    gain = float(np.exp(rng.uniform(np.log(EXPOSURE_GAIN[0]), np.log(EXPOSURE_GAIN[1]))))
    wr, wb = (float(v) for v in rng.uniform(1.0 - WHITE_BALANCE, 1.0 + WHITE_BALANCE, 2))
    white = [wr, 1.0, wb]
    channel = [gain * c for c in white]
    img = np.clip(image * np.asarray(channel, dtype=image.dtype), 0.0, 1.0)
    return img, {"gain": gain, "white_balance": white, "channel_gains": channel}


# ----------------------------------------------------------------------------- tripod

TRIPOD_RADIUS_DEG = (11.0, 16.0)  # mean angular radius of the blob around the nadir
# The boundary never leaves this band (19.5 deg from the nadir = the bottom 10.8 % of rows).
TRIPOD_CLIP_DEG = (8.0, 19.5)


def _value_noise(x: np.ndarray, y: np.ndarray, cell: float, seed: int | np.ndarray) -> np.ndarray:
    """Smooth value noise in [0,1): hashed lattice values, smoothstep-interpolated."""
    gx, gy = x / cell, y / cell
    i0, j0 = np.floor(gx), np.floor(gy)
    fx, fy = gx - i0, gy - j0
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    v00, v10 = _hash(i0, j0, seed), _hash(i0 + 1, j0, seed)
    v01, v11 = _hash(i0, j0 + 1, seed), _hash(i0 + 1, j0 + 1, seed)
    return (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy


def tripod(image: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A tripod / hand at the nadir: a dark, roughly textured blob, different per view.

    Its boundary, as an angle from the nadir per image column (longitude phi), is
    r(phi) = r0 (1 + offset, elongation, three legs and rough harmonics), r0 uniform in
    TRIPOD_RADIUS_DEG, clipped to TRIPOD_CLIP_DEG. Pixels whose centre lies within r(phi)
    of the nadir are covered (a one-row soft edge inside the boundary); nothing outside
    changes. Returns the image and the valid mask [H,W] uint8 (255 = valid, 0 = tripod)."""
    h, w = image.shape[:2]
    # Draw every parameter up front (a fixed number of draws per view).
    r0 = np.deg2rad(rng.uniform(*TRIPOD_RADIUS_DEG))
    offset, elong, legs = rng.uniform(0.0, 0.12), rng.uniform(0.0, 0.15), rng.uniform(0.03, 0.10)
    ph = rng.uniform(-np.pi, np.pi, 3)
    rough_k = np.arange(4, 10)
    rough_a = rng.normal(0.0, 0.015, len(rough_k))
    rough_p = rng.uniform(-np.pi, np.pi, len(rough_k))
    grey = rng.uniform(0.05, 0.12)
    tint = 1.0 + rng.uniform(-0.12, 0.12, 3)
    seed = int(rng.integers(0, 1 << 20))

    lon = column_longitudes(w)
    shape = (
        1.0
        + offset * np.cos(lon - ph[0])
        + elong * np.cos(2 * (lon - ph[1]))
        + legs * np.cos(3 * (lon - ph[2]))
        + (rough_a[:, None] * np.cos(rough_k[:, None] * lon[None, :] + rough_p[:, None])).sum(axis=0)
    )
    radius = np.clip(r0 * shape, *np.deg2rad(TRIPOD_CLIP_DEG))  # [W]
    pix = np.pi / h  # one row, in radians
    n = min(h, int(np.ceil(radius.max() / pix)) + 1)  # rows that can be covered
    rows = np.arange(h - n, h)
    alpha_nadir = (h - rows - 0.5) * pix  # angle of each row's pixel centres from the nadir
    cover = np.clip((radius[None, :] - alpha_nadir[:, None]) / pix, 0.0, 1.0)  # > 0 iff inside

    # Texture in the plane around the nadir (degrees): two octaves of value noise, darker legs.
    a_deg = np.rad2deg(alpha_nadir)[:, None]
    x, y = a_deg * np.sin(lon)[None, :], a_deg * np.cos(lon)[None, :]
    rough = 0.55 + 0.6 * _value_noise(x, y, 2.5, seed) + 0.3 * _value_noise(x, y, 0.8, seed + 1)
    leg = np.cos(1.5 * (lon - ph[2])) ** 2  # 1 along the three legs (period 2 pi / 3)
    rough *= 1.0 - 0.35 * (leg ** 8)[None, :]
    colour = grey * rough[..., None] * tint[None, None, :]

    out = image.copy()
    band = out[h - n :]
    out[h - n :] = band * (1.0 - cover[..., None]) + cover[..., None] * colour.astype(out.dtype)
    mask = np.full((h, w), 255, dtype=np.uint8)
    mask[h - n :][cover > 0] = 0
    return out, mask


# ----------------------------------------------------------------------------- aa


def subpixel_offsets(n: int) -> np.ndarray:
    """The n x n regular grid of sub-pixel offsets (pixel units, centred on 0)."""
    return (np.arange(n) + 0.5) / n - 0.5


def downsample(img: np.ndarray, n: int) -> np.ndarray:
    """Box-filter an [nH, nW, C] supersampled image to [H, W, C]."""
    h, w = img.shape[0] // n, img.shape[1] // n
    return img.reshape(h, n, w, n, -1).mean(axis=(1, 3))


AA_CHUNK_RAYS = 1 << 17


def antialias(render_block, h: int, w: int, n: int, timings: dict[str, float]) -> np.ndarray:
    """Supersampled anti-aliasing: render the n x n regular sub-pixel grid of every pixel
    (the pixel centres of an nH x nW panorama) in row blocks through
    `render_block(latitudes, longitudes) -> [rows, cols, 3]`, box-filtered to [H, W, 3]."""
    lat = row_latitudes(n * h)
    lon = column_longitudes(n * w)
    out = np.empty((h, w, 3), dtype=np.float64)
    rows = max(n, (AA_CHUNK_RAYS // (n * w)) // n * n)
    for r0 in range(0, n * h, rows):
        r1 = min(n * h, r0 + rows)
        block = render_block(lat[r0:r1], lon)
        t0 = time.perf_counter()
        out[r0 // n : r1 // n] = downsample(block, n)
        timings["aa"] = timings.get("aa", 0.0) + time.perf_counter() - t0
    return out


# ----------------------------------------------------------------------------- furniture

FURNITURE_KINDS = {
    # kind: (width along the wall, depth, height, material, colour)
    "bed": (2.0, 1.5, 0.55, "fabric", (0.55, 0.35, 0.40)),
    "cabinet": (1.0, 0.5, 2.0, "wood", (0.45, 0.30, 0.20)),
    "sofa": (1.9, 0.85, 0.8, "fabric", (0.30, 0.42, 0.55)),
    "shelf": (0.8, 0.4, 1.4, "wood", (0.70, 0.55, 0.35)),
    "table": (1.2, 0.8, 0.75, "wood", (0.55, 0.40, 0.25)),
}


def furniture(world: World, cameras: list[Camera], rng: np.random.Generator) -> list[Box]:
    """Place boxes: pieces against walls, a free-standing table per room. Never within
    FURNITURE_CAMERA_CLEARANCE of a camera, never in front of a doorway, never overlapping."""
    placed: list[Polygon] = []
    boxes: list[Box] = []
    cam_zone = [Point(c.position[0], c.position[2]).buffer(FURNITURE_CAMERA_CLEARANCE) for c in cameras]
    keep_out = list(cam_zone)
    for dw in world.doorways:
        x = dw.a[0]
        keep_out.append(box(x - 1.0, min(dw.a[1], dw.b[1]) - 0.2, x + 1.0, max(dw.a[1], dw.b[1]) + 0.2))
    for ri, room in enumerate(world.rooms):
        shape = prep(room.shape.buffer(-0.02))
        edges = [
            (room.polygon[i], room.polygon[(i + 1) % len(room.polygon)]) for i in range(len(room.polygon))
        ]
        kinds = ["bed", "cabinet", "sofa", "shelf"]
        order = rng.permutation(len(kinds))
        n_wall = int(rng.integers(2, 4))
        for k in order[:n_wall]:
            kind = kinds[k]
            w, d, h, mat, col = FURNITURE_KINDS[kind]
            for _ in range(30):
                a, b = edges[int(rng.integers(len(edges)))]
                e = b - a
                length = float(np.hypot(*e))
                if length < w + 0.2:
                    continue
                e = e / length
                inward = np.array([-e[1], e[0]])  # CCW polygon: interior on the left
                s = rng.uniform(0.1, length - w - 0.1)
                p0 = a + e * s + inward * 0.03
                corners = np.array([p0, p0 + e * w, p0 + e * w + inward * d, p0 + inward * d])
                poly = Polygon(corners)
                if not shape.contains(poly):
                    continue
                grown = poly.buffer(0.15)
                if any(poly.intersects(z) for z in keep_out) or any(grown.intersects(q) for q in placed):
                    continue
                placed.append(poly)
                lo2, hi2 = corners.min(axis=0), corners.max(axis=0)
                jitter = rng.uniform(0.9, 1.1, 3)
                boxes.append(
                    Box(kind, np.array([lo2[0], -h, lo2[1]]), np.array([hi2[0], 0.0, hi2[1]]),
                        np.clip(np.array(col) * jitter, 0, 1), mat)
                )
                break
        # One free-standing table per room.
        w, d, h, mat, col = FURNITURE_KINDS["table"]
        x0, z0 = room.polygon.min(axis=0)
        x1, z1 = room.polygon.max(axis=0)
        for _ in range(60):
            cx, cz = rng.uniform(x0 + 0.8, x1 - 0.8), rng.uniform(z0 + 0.8, z1 - 0.8)
            ww, dd = (w, d) if rng.uniform() < 0.5 else (d, w)
            poly = box(cx - ww / 2, cz - dd / 2, cx + ww / 2, cz + dd / 2)
            if not shape.contains(poly):
                continue
            grown = poly.buffer(0.4)
            if any(poly.intersects(z) for z in keep_out) or any(grown.intersects(q) for q in placed):
                continue
            placed.append(poly)
            boxes.append(
                Box(
                    "table",
                    np.array([cx - ww / 2, -h, cz - dd / 2]),
                    np.array([cx + ww / 2, 0.0, cz + dd / 2]),
                    np.array(col),
                    mat,
                )
            )
            break
    return boxes
