"""`generate_scene`: write a complete simulated scene folder (DESIGN.md "A scene folder")."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runfs.fsutil import atomic_folder  # a leaf module: no pipeline machinery comes along
from schemas.scene import SceneManifest, View
from simulate import effects as fxmod
from simulate.geometry import PRESET_NAMES, Box, Camera, World, build_world, place_cameras
from simulate.layout import view_layout
from simulate.render import render_view

PRESETS = PRESET_NAMES
EFFECTS = fxmod.EFFECTS
# What "all" means for each preset: the demo is noise-free and capture-effect-free (it must be
# learnable, and its figures stay as they are); the others get every effect.
PRESET_ALL_EFFECTS = {p: frozenset(EFFECTS) - frozenset(fxmod.OPT_IN_EFFECTS) for p in PRESETS}
PRESET_ALL_EFFECTS["demo"] = frozenset({"texture", "furniture", "shading", "aa"})

MAX_HEIGHT = 4096


@dataclass
class SimulationResult:
    out_dir: Path
    manifest_path: Path
    preset: str
    effects: list[str]
    views: list[str]
    timings: dict[str, float] = field(default_factory=dict)


def parse_effects(
    effects: set[str] | frozenset[str] | list[str] | str | None, preset: str = "cuboid"
) -> set[str]:
    """'all' | 'none' | 'texture,shading' | an iterable of names -> a validated set."""
    if effects is None:
        return set(PRESET_ALL_EFFECTS.get(preset, EFFECTS))
    if isinstance(effects, str):
        s = effects.strip().lower()
        if s == "all":
            return set(PRESET_ALL_EFFECTS.get(preset, EFFECTS))
        if s in ("none", ""):
            return set()
        names = [p.strip() for p in s.split(",") if p.strip()]
    else:
        names = [str(p).strip().lower() for p in effects]
    if "all" in names:
        return set(PRESET_ALL_EFFECTS.get(preset, EFFECTS))
    names = [n for n in names if n != "none"]
    bad = sorted(set(names) - set(EFFECTS))
    if bad:
        raise ValueError(
            f"unknown effect(s) {', '.join(bad)}; choose from {', '.join(EFFECTS)}, 'all' or 'none'"
        )
    return set(names)


def _check_args(preset: str, views: int, test_views: int, height: int, seed: int, aa_samples: int) -> None:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if int(views) != views or views < 1 or views > 64:
        raise ValueError(f"--views must be an integer in 1..64, got {views}")
    if int(test_views) != test_views or test_views < 0 or test_views > 64:
        raise ValueError(f"--test-views must be an integer in 0..64, got {test_views}")
    if int(height) != height or height < 16 or height > MAX_HEIGHT or height % 2:
        raise ValueError(
            f"--height must be an even integer in 16..{MAX_HEIGHT} (width = 2 x height), got {height}"
        )
    if int(seed) != seed or seed < 0:
        raise ValueError(f"--seed must be a non-negative integer, got {seed}")
    if int(aa_samples) != aa_samples or aa_samples < 1 or aa_samples > 8:
        raise ValueError(f"--aa-samples must be an integer in 1..8, got {aa_samples}")


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    # Independent streams, so toggling an effect never changes the room, the cameras or the other effects.
    ss = np.random.SeedSequence(int(seed))
    # New streams go at the end: spawn keys are positional, so the earlier streams never change.
    names = ("room", "cameras", "furniture", "noise", "exposure", "tripod")
    return {n: np.random.default_rng(s) for n, s in zip(names, ss.spawn(len(names)))}


def _floor_plan(world: World, boxes: list[Box], cams: list[Camera]) -> dict:
    return {
        "frame": "world (x, z); y down, floor y = 0; polygons counter-clockwise in (x, z) (seen from above)",
        "rooms": [
            {
                "name": r.name,
                "polygon": np.round(r.polygon, 6).tolist(),
                "floor_y": 0.0,
                "ceiling_y": world.ceiling_y,
            }
            for r in world.rooms
        ],
        "outline": np.round(world.outline, 6).tolist(),
        "doorways": [
            {"a": d.a.tolist(), "b": d.b.tolist(), "rooms": list(d.rooms), "top_y": d.top_y}
            for d in world.doorways
        ],
        "furniture": [{"kind": b.kind, "min": b.lo.tolist(), "max": b.hi.tolist()} for b in boxes],
        "lights": [{"position": li.position.tolist(), "room": li.room} for li in world.lights],
        "cameras": {
            c.name: {"position": c.position.tolist(), "height": c.height, "split": c.split} for c in cams
        },
    }


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


#: Marks a scene folder the simulator wrote: only such a folder (or an empty one) is replaced.
SIMULATED_MARKER = ".pano-pipe-simulated"


def is_simulated_scene(folder: Path) -> bool:
    """Written by the simulator: the marker (or, from before the marker, scene.json beside gt/)."""
    folder = Path(folder)
    return (folder / SIMULATED_MARKER).is_file() or (
        (folder / "scene.json").is_file() and (folder / "gt" / "floor_plan.json").is_file()
    )


def _write_scene(
    tmp: Path, *, name, world, boxes, cams, height, fx, aa_samples, rngs, with_layout, with_depth, timings
) -> None:
    import cv2  # here, not at the top: `pano-pipe --help` lists the simulate command without OpenCV

    for sub in ("images", "gt/depth", "gt/layout"):
        (tmp / sub).mkdir(parents=True, exist_ok=True)
    if "tripod" in fx or "exposure" in fx:
        (tmp / "gt" / "clean").mkdir()
    if "tripod" in fx:
        (tmp / "gt" / "masks").mkdir()
    exposures: dict[str, dict] = {}
    if with_layout:
        (tmp / "layout").mkdir()
    if with_depth:
        (tmp / "depth").mkdir()
    views: list[View] = []
    for cam in cams:
        r = render_view(world, boxes, cam, height, fx, aa_samples, rngs, timings)
        t0 = time.perf_counter()
        lay = view_layout(world, cam, height)
        timings["layout"] = timings.get("layout", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        n = cam.name
        cv2.imwrite(str(tmp / "images" / f"{n}.png"), cv2.cvtColor(_to_u8(r.image), cv2.COLOR_RGB2BGR))
        if r.clean is not None:
            clean_bgr = cv2.cvtColor(_to_u8(r.clean), cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(tmp / "gt" / "clean" / f"{n}.png"), clean_bgr)
        if r.mask is not None:
            cv2.imwrite(str(tmp / "gt" / "masks" / f"{n}.png"), r.mask)
        if r.exposure is not None:
            exposures[n] = r.exposure
        depth32 = r.depth.astype(np.float32)
        np.save(tmp / "gt" / "depth" / f"{n}.npy", depth32)
        mm = np.clip(np.round(r.depth * 1000.0), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(tmp / "gt" / "depth" / f"{n}.png"), mm)
        np.save(tmp / "gt" / "layout" / f"{n}.npy", lay.boundary)
        (tmp / "gt" / "layout" / f"{n}.json").write_text(json.dumps(lay.horizonnet, indent=1))
        layout_rel = depth_rel = None
        if cam.split == "train" and with_layout:
            if lay.representable:
                layout_rel = f"layout/{n}.json"
                shutil.copyfile(tmp / "gt" / "layout" / f"{n}.json", tmp / layout_rel)
            else:
                layout_rel = f"layout/{n}.npy"
                shutil.copyfile(tmp / "gt" / "layout" / f"{n}.npy", tmp / layout_rel)
        if cam.split == "train" and with_depth:
            depth_rel = f"depth/{n}.png"
            shutil.copyfile(tmp / "gt" / "depth" / f"{n}.png", tmp / depth_rel)
        views.append(
            View(
                name=n,
                image=f"images/{n}.png",
                pose=cam.pose.tolist(),
                split=cam.split,
                camera_height=cam.height,
                layout=layout_rel,
                depth=depth_rel,
                gt_depth=f"gt/depth/{n}.npy",
            )
        )
        timings["write"] = timings.get("write", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    if "exposure" in fx:
        (tmp / "gt" / "exposure.json").write_text(json.dumps({
            "model": "images/<view>.png = clip(gt/clean/<view>.png x channel_gains) (+ sensor noise with "
                     "`noise`; the tripod, with `tripod`, is drawn before the exposure); RGB order; "
                     "channel_gains = gain x white_balance, white_balance green = 1",
            "views": exposures,
        }, indent=1))
    (tmp / "gt" / "floor_plan.json").write_text(json.dumps(_floor_plan(world, boxes, cams), indent=1))
    manifest = SceneManifest(name=name, views=views, floor_plan="gt/floor_plan.json")
    (tmp / "scene.json").write_text(manifest.model_dump_json(indent=2, exclude_none=True))
    timings["write"] = timings.get("write", 0.0) + time.perf_counter() - t0


def generate_scene(
    out_dir: Path,
    preset: str = "cuboid",
    views: int = 4,
    test_views: int = 2,
    height: int = 256,
    seed: int = 0,
    effects: set[str] | str = "all",
    aa_samples: int = 2,
    with_layout: bool = False,
    with_depth: bool = False,
    walk: bool = False,
    tripod_height: float | None = None,
    test_placement: str = "near",
) -> SimulationResult:
    """Simulate a scene and write its folder atomically (a sibling temp folder, renamed on success).

    `views` train and `test_views` test panoramas of `height` x 2`height` pixels. `effects`:
    'all', 'none', a comma-separated list or a set of names from EFFECTS ('all' for the demo
    preset means its noise-free set). `walk`: train cameras along a walk through the rooms (a
    chain); `tripod_height`: every camera at that height (m); `test_placement`: "near" the
    train cameras (default) or "away" from them (simulate.geometry.TEST_PLACEMENTS). Raises ValueError
    on bad arguments.
    """
    t_start = time.perf_counter()
    _check_args(preset, views, test_views, height, seed, aa_samples)
    fx = parse_effects(effects, preset)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"output {out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not is_simulated_scene(out_dir):
        # replacing it would delete the user's files
        raise ValueError(f"output {out_dir} is a folder the simulator did not write (no {SIMULATED_MARKER}); "
                         "choose a new or empty folder")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    rngs = _rngs(seed)
    world = build_world(preset, rngs["room"])
    if tripod_height is not None and not 0.3 <= tripod_height <= 0.9 * world.ceiling_height:
        raise ValueError(f"tripod height must be 0.3 m to 90 % of the ceiling height, got {tripod_height}")
    cams = place_cameras(world, int(views), int(test_views), rngs["cameras"], walk=walk,
                         tripod_height=tripod_height, test_placement=test_placement)
    timings["scene"] = time.perf_counter() - t0
    boxes: list[Box] = []
    if "furniture" in fx:
        t0 = time.perf_counter()
        boxes = fxmod.furniture(world, cams, rngs["furniture"])
        timings["furniture"] = time.perf_counter() - t0
    if "fixtures" in fx:
        t0 = time.perf_counter()
        boxes = boxes + fxmod.fixtures(world)
        timings["fixtures"] = time.perf_counter() - t0
    world.boxes = boxes
    if "plain-floor" in fx:
        fxmod.plain_floor(world)

    with atomic_folder(out_dir) as tmp:
        (tmp / SIMULATED_MARKER).write_text(f"preset={preset} seed={seed}\n")
        _write_scene(
            tmp,
            name=out_dir.name,
            world=world,
            boxes=boxes,
            cams=cams,
            height=int(height),
            fx=fx,
            aa_samples=int(aa_samples),
            rngs=rngs,
            with_layout=with_layout,
            with_depth=with_depth,
            timings=timings,
        )
    timings["total"] = time.perf_counter() - t_start
    return SimulationResult(
        out_dir=out_dir,
        manifest_path=out_dir / "scene.json",
        preset=preset,
        effects=sorted(fx),
        views=[c.name for c in cams],
        timings=timings,
    )
