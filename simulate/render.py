"""Equirectangular rendering of a simulated world from one camera.

Two passes:
  * the ground-truth pass, one float64 ray per pixel centre (DESIGN.md's
    mapping): distance along the ray and surface ids;
  * the colour pass: the same hits when `aa` is off, otherwise an n x n grid of
    float32 sub-pixel rays per pixel, box-filtered down.
Colour = albedo (flat per material, or procedural with `texture`) times the
irradiance (only with `shading`); then the capture effects, each only when
listed: the tripod at the nadir (`tripod`), the per-view exposure and white
balance (`exposure`), sensor noise (`noise`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from panogeom.equirect import column_longitudes, row_latitudes
from simulate import effects
from simulate.geometry import Box, Camera, World
from simulate.raycast import CEILING, FLOOR, WALL0, Hits, box_id0, cast_grid, normals

CHUNK_RAYS = 1 << 17


@dataclass
class ViewRender:
    image: np.ndarray  # [H,W,3] float in [0,1]
    depth: np.ndarray  # [H,W] float64 metres along the ray
    sid: np.ndarray  # [H,W] surface id at pixel centres
    clean: np.ndarray | None = None  # [H,W,3] before tripod / exposure / noise (with tripod or exposure)
    mask: np.ndarray | None = None  # [H,W] uint8, 255 = valid, 0 = tripod (when tripod is on)
    exposure: dict | None = None  # the view's exposure parameters (when exposure is on)


class _Materials:
    """Per-surface-id look-up tables: flat colour, texture kind, texture frame."""

    def __init__(self, world: World, boxes: list[Box]):
        nsurf = box_id0(world) + len(boxes)
        kinds = effects.TEXTURE_KINDS
        rgb = np.zeros((nsurf, 3))
        kind = np.zeros(nsurf, dtype=np.int64)
        # uv = coef[key] @ (x, y, z, 1), key = 3 * sid + box face axis (0 elsewhere).
        coef = np.zeros((3 * nsurf, 2, 4))
        fl = "floor_" + world.floor_material
        rgb[FLOOR], kind[FLOOR] = effects.MATERIAL_RGB[fl], kinds.index(fl)
        rgb[CEILING], kind[CEILING] = effects.MATERIAL_RGB["ceiling"], kinds.index("plain")
        for s in (FLOOR, CEILING):
            coef[3 * s, 0, 0] = 1.0  # u = x
            coef[3 * s, 1, 2] = 1.0  # v = z
        bare = np.zeros(nsurf, bool)
        if world.floor_plain:  # the `plain-floor` effect: no texture, no detail on the floor
            kind[FLOOR], bare[FLOOR] = kinds.index("plain"), True
        off = 0.0  # running arc length keeps the pattern continuous around corners
        for k, wall in enumerate(world.walls):
            s = WALL0 + k
            mat = wall.material
            rgb[s] = effects.MATERIAL_RGB[mat]
            bare[s] = mat == "bare"
            kind[s] = kinds.index("wallpaper" if mat == "wallpaper" else "plain")
            ex, ez = (wall.b - wall.a) / wall.length
            coef[3 * s, 0] = (ex, 0.0, ez, off - ex * wall.a[0] - ez * wall.a[1])
            coef[3 * s, 1, 1] = 1.0  # v = y
            off += wall.length
        for j, bx in enumerate(boxes):
            s = box_id0(world) + j
            rgb[s] = bx.color
            kind[s] = kinds.index(bx.material)
            for a, (i0, i1) in enumerate(((2, 1), (0, 2), (0, 1))):
                coef[3 * s + a, 0, i0] = 1.0
                coef[3 * s + a, 1, i1] = 1.0
        self.rgb = rgb
        self.bare = bare
        self.emits = np.zeros(nsurf, bool)  # surfaces drawn in emitted light: the lamps
        self.emits[box_id0(world):] = [bx.kind == "lamp" for bx in boxes]
        self.kind = kind
        self.coef = coef
        self.boxes = boxes


def _uv(hits: Hits, points: np.ndarray, m: _Materials) -> np.ndarray:
    """Texture coordinates [N,2] in metres: floor/ceiling (x, z); walls (arc length, y); box faces by axis."""
    key = 3 * hits.sid + np.maximum(hits.box_axis, 0)
    c = m.coef.astype(points.dtype)[key]  # [N,2,4]
    uv = c[:, :, 3] + c[:, :, 0] * points[:, None, 0]
    uv += c[:, :, 1] * points[:, None, 1]
    uv += c[:, :, 2] * points[:, None, 2]
    return uv


def _colour(
    hits: Hits, dirs: np.ndarray, origin: np.ndarray, world: World, m: _Materials, fx: set[str], timings: dict
) -> np.ndarray:
    albedo = m.rgb.astype(dirs.dtype)[hits.sid]
    need_points = bool({"texture", "shading", "detail"} & fx)
    if need_points:
        points = origin.astype(dirs.dtype)[None, :] + hits.t[:, None] * dirs
    if "texture" in fx:
        t0 = time.perf_counter()
        albedo = effects.texture(m.kind[hits.sid], _uv(hits, points, m), albedo)
        timings["texture"] = timings.get("texture", 0.0) + time.perf_counter() - t0
    if "detail" in fx:
        t0 = time.perf_counter()
        detailed = effects.detail(hits.sid, _uv(hits, points, m), albedo)
        albedo = np.where(m.bare[hits.sid][:, None], albedo, detailed)
        timings["detail"] = timings.get("detail", 0.0) + time.perf_counter() - t0
    if "shading" in fx:
        t0 = time.perf_counter()
        nrm = normals(hits, dirs, world, m.boxes, origin)
        albedo = albedo * effects.shading(points, nrm, world)[:, None]
        timings["shading"] = timings.get("shading", 0.0) + time.perf_counter() - t0
    if m.emits.any():  # the `fixtures` effect's lamps: emitted light, which the shading does not touch
        albedo = np.where(m.emits[hits.sid][:, None], effects.FIXTURE_RGB.astype(albedo.dtype), albedo)
    return albedo


def render_view(
    world: World,
    boxes: list[Box],
    cam: Camera,
    height: int,
    fx: set[str],
    aa_samples: int,
    rngs: dict[str, np.random.Generator] | np.random.Generator | None,
    timings: dict[str, float],
) -> ViewRender:
    """Render one view. `rngs`: the per-purpose random streams ("noise", "exposure", "tripod";
    a single Generator is used for every one of them); each is drawn from only when its
    effect is listed in `fx`."""
    if not isinstance(rngs, dict):
        rngs = {"noise": rngs, "exposure": rngs, "tripod": rngs}
    h, w = height, 2 * height
    rot = cam.rotation
    origin = cam.position.astype(np.float64)
    m = _Materials(world, boxes)
    lon = column_longitudes(w)
    lat = row_latitudes(h)
    depth = np.empty((h, w), dtype=np.float64)
    sid = np.empty((h, w), dtype=np.int32)
    use_aa = "aa" in fx and aa_samples > 1
    image = None if use_aa else np.empty((h, w, 3), dtype=np.float64)
    rows_per_chunk = max(1, CHUNK_RAYS // w)
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        hits, dirs = cast_grid(origin, rot, lat[r0:r1], lon, world, boxes, timings, dtype=np.float64)
        depth[r0:r1] = hits.t.reshape(r1 - r0, w)
        sid[r0:r1] = hits.sid.reshape(r1 - r0, w)
        if not use_aa:
            image[r0:r1] = _colour(hits, dirs, origin, world, m, fx, timings).reshape(r1 - r0, w, 3)
    if use_aa:
        image = effects.antialias(
            lambda lat_s, lon_s: _supersampled_block(lat_s, lon_s, rot, origin, world, boxes, m, fx, timings),
            h,
            w,
            aa_samples,
            timings,
        )
    image = np.clip(image, 0.0, 1.0)
    clean = mask = params = None
    if "tripod" in fx or "exposure" in fx:
        clean = image.copy()
    if "tripod" in fx:
        t0 = time.perf_counter()
        image, mask = effects.tripod(image, rngs["tripod"])
        timings["tripod"] = timings.get("tripod", 0.0) + time.perf_counter() - t0
    if "exposure" in fx:
        t0 = time.perf_counter()
        image, params = effects.exposure(image, rngs["exposure"])
        timings["exposure"] = timings.get("exposure", 0.0) + time.perf_counter() - t0
    if "noise" in fx:
        t0 = time.perf_counter()
        image = effects.noise(image, rngs["noise"])
        timings["noise"] = timings.get("noise", 0.0) + time.perf_counter() - t0
    return ViewRender(
        image=np.clip(image, 0.0, 1.0), depth=depth, sid=sid, clean=clean, mask=mask, exposure=params
    )


def _supersampled_block(lat_s, lon_s, rot, origin, world, boxes, m, fx, timings) -> np.ndarray:
    hits, dirs = cast_grid(origin, rot, lat_s, lon_s, world, boxes, timings, shell_key="aa", dtype=np.float32)
    return _colour(hits, dirs, origin, world, m, fx, timings).reshape(len(lat_s), len(lon_s), 3)
