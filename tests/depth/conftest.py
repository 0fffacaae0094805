"""Fixtures for the depth tests: simulator scenes whose images encode their exact depth, and tiny
ONNX depth models of each kind that decode it.

The images' RGB channels hold depth / DMAX quantised with 0, 1/3 and 2/3 of a
level of dither, so a model that averages them reads depth at 3x the 8-bit
resolution; the models then behave like the networks of each contract (metric
360°, Depth-Anything-like relative disparity, perspective cube faces) with the
exact answer known.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from schemas.scene_loader import load_scene
from runtime.stage import StageContext
from simulate import generate_scene

DMAX = 10.0
LEVEL = 1.0 / 255.0
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)


def encode_depth(depth: np.ndarray) -> np.ndarray:
    """uint8 RGB image encoding depth (metres) with a 3-level dither."""
    x = np.clip(depth / DMAX, 0, 1 - LEVEL)
    chans = [np.round((x + k * LEVEL / 3) * 255.0) for k in range(3)]
    return np.clip(np.stack(chans, -1), 0, 255).astype(np.uint8)


def _decode(x: torch.Tensor) -> torch.Tensor:
    """[1,3,H,W] in [0,1] -> [1,1,H,W] metres."""
    return DMAX * (x.mean(1, keepdim=True) - LEVEL / 3)


class Metric360(torch.nn.Module):
    def __init__(self, scale: float = 1.0):
        super().__init__()
        self.scale = scale

    def forward(self, x):
        return self.scale * _decode(x)


class DepthAnythingLike(torch.nn.Module):
    """ImageNet input, sides a multiple of 14 (patchified), min-max normalised disparity [1,H,W]."""

    def forward(self, x):
        mean = torch.tensor(MEAN).view(1, 3, 1, 1)
        std = torch.tensor(STD).view(1, 3, 1, 1)
        x = x * std + mean
        b, c, h, w = x.shape
        p = x.reshape(b, c, h // 14, 14, w // 14, 14)  # fails unless the sides are multiples of 14
        x = p.reshape(b, c, h, w)
        disp = 1.0 / _decode(x).clamp(min=0.05)
        lo, hi = disp.amin(dim=(2, 3), keepdim=True), disp.amax(dim=(2, 3), keepdim=True)
        return ((disp - lo) / (hi - lo))[:, 0]


class PerspectiveFace(torch.nn.Module):
    """A perspective model on an S x S face of field of view `fov_deg`: depth along its axis (z).

    metric: z times a per-image scale (1 + mean intensity, so each face differs);
    disparity: min-max normalised 1/z (per-face scale and shift).
    """

    def __init__(self, size: int, fov_deg: float, kind: str = "metric"):
        super().__init__()
        f = (size / 2) / np.tan(np.radians(fov_deg) / 2)
        c = (np.arange(size) + 0.5 - size / 2) / f
        x, y = np.meshgrid(c, c)
        self.register_buffer(
            "cos", torch.tensor(1 / np.sqrt(x**2 + y**2 + 1), dtype=torch.float32)[None, None]
        )
        self.kind = kind

    def forward(self, x):
        z = _decode(x) * self.cos
        if self.kind == "metric":
            return z * (1.0 + x.mean())
        disp = 1.0 / z.clamp(min=0.05)
        lo, hi = disp.amin(dim=(2, 3), keepdim=True), disp.amax(dim=(2, 3), keepdim=True)
        return 0.5 + 2.0 * (disp - lo) / (hi - lo)


class WrongChannels(torch.nn.Module):
    def forward(self, x):
        return x * 2.0  # [1,3,H,W]: an image, not a depth map


class WrongAspect(torch.nn.Module):
    def forward(self, x):
        return _decode(x)[:, :, :, : x.shape[3] // 4]  # a quarter of the width


def export(module: torch.nn.Module, path: Path, shape, dynamic: bool = False) -> Path:
    torch.set_num_threads(1)
    module.eval()
    kwargs = {}
    if dynamic:
        kwargs["dynamic_axes"] = {"image": {2: "height", 3: "width"}, "depth": {1: "h", 2: "w"}}
    torch.onnx.export(
        module,
        (torch.rand(*shape),),
        str(path),
        input_names=["image"],
        output_names=["depth"],
        opset_version=17,
        dynamo=False,
        **kwargs,
    )
    return path


def make_encoded_scene(
    root: Path, preset="cuboid", views=2, height=64, seed=0, with_depth=False, with_layout=False
):
    """A simulator scene (empty room) whose train images encode the exact depth."""
    res = generate_scene(
        root,
        preset,
        views=views,
        test_views=1,
        height=height,
        seed=seed,
        effects="texture",
        aa_samples=1,
        with_depth=with_depth,
        with_layout=with_layout,
    )
    scene = load_scene(res.out_dir)
    for v in scene.manifest.views:
        gt = np.load(res.out_dir / "gt" / "depth" / f"{v.name}.npy")
        cv2.imwrite(str(scene.image_path(v)), cv2.cvtColor(encode_depth(gt), cv2.COLOR_RGB2BGR))
    return scene


def gt_depth(scene, view) -> np.ndarray:
    return np.load(scene.root / "gt" / "depth" / f"{view.name}.npy").astype(np.float64)


def run_depth(scene, tmp: Path, **params):
    from stages import depth

    out = tmp / f"depth-out-{len(list(tmp.glob('depth-out-*')))}"
    out.mkdir(parents=True)
    ctx = StageContext(scene=scene, params=depth.Params(**params), inputs={}, out_dir=out)
    result = depth.run(ctx)
    maps = {v.view: np.load(out / v.depth) for v in result.views}
    return result, maps, ctx


def floor_polygon_cam(scene, view):
    fp = json.loads((scene.root / "gt" / "floor_plan.json").read_text())
    room = fp["rooms"][0]
    pose = view.pose_matrix
    poly = np.asarray(room["polygon"], dtype=np.float64)
    world = np.stack([poly[:, 0], np.zeros(len(poly)), poly[:, 1]], 1)
    cam = (world - pose[:3, 3]) @ pose[:3, :3]
    return cam[:, [0, 2]], float(-pose[1, 3]), float(pose[1, 3] - room["ceiling_y"])


@pytest.fixture(scope="session")
def dk():
    return SimpleNamespace(
        Metric360=Metric360,
        DepthAnythingLike=DepthAnythingLike,
        PerspectiveFace=PerspectiveFace,
        WrongChannels=WrongChannels,
        WrongAspect=WrongAspect,
        export=export,
        encode_depth=encode_depth,
        make_encoded_scene=make_encoded_scene,
        gt_depth=gt_depth,
        run_depth=run_depth,
        floor_polygon_cam=floor_polygon_cam,
        DMAX=DMAX,
    )


def run_chain(scene, tmp: Path, depth_params: dict, align_params: dict | None = None, with_layout=True):
    """depth (stage) -> exact layout (simulator) -> union -> sampling -> align, in folders under tmp."""
    from runtime.stage import Loaded
    from schemas.layout import LayoutOutput, ViewLayout
    from stages import align, sampling, union

    result, _, ctx = run_depth(scene, tmp, **depth_params)
    depth_in = Loaded(data=result, dir=ctx.out_dir)
    layout_in = samp_in = None
    if with_layout:
        views = []
        for v in scene.manifest.views:
            poly, h, c = floor_polygon_cam(scene, v)
            views.append(
                ViewLayout(
                    view=v.name,
                    source="npy",
                    boundaries="none.npy",
                    floor_polygon=[tuple(p) for p in poly.tolist()],
                    camera_height=h,
                    ceiling_distance=c,
                    camera_height_assumed=False,
                )
            )
        layout_in = Loaded(data=LayoutOutput(views=views), dir=tmp)
        loaded = {"layout": layout_in}
        for name, mod, inputs in (("union", union, ("layout",)), ("sampling", sampling, ("union", "layout"))):
            out = tmp / name
            out.mkdir()
            c2 = StageContext(
                scene=scene, params=mod.Params(), inputs={k: loaded[k] for k in inputs}, out_dir=out
            )
            loaded[name] = Loaded(data=mod.run(c2), dir=out)
        samp_in = loaded["sampling"]
    out = tmp / "align"
    out.mkdir()
    c3 = StageContext(
        scene=scene,
        params=align.Params(**(align_params or {})),
        inputs={"depth": depth_in, "layout": layout_in, "sampling": samp_in},
        out_dir=out,
    )
    return align.run(c3), out


def surface_distance(scene, pts: np.ndarray) -> np.ndarray:
    """Distance of world points to the nearest floor, ceiling or wall of the (empty) simulated room."""
    fp = json.loads((scene.root / "gt" / "floor_plan.json").read_text())
    ceil = min(r["ceiling_y"] for r in fp["rooms"])
    best = np.minimum(np.abs(pts[:, 1]), np.abs(pts[:, 1] - ceil))
    xz = pts[:, [0, 2]].astype(np.float64)
    for room in fp["rooms"]:
        poly = np.asarray(room["polygon"], dtype=np.float64)
        for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            e = b - a
            t = np.clip(((xz - a) @ e) / (e @ e), 0, 1)
            best = np.minimum(best, np.linalg.norm(xz - (a + t[:, None] * e), axis=1))
    return best


@pytest.fixture(scope="session")
def chain():
    return SimpleNamespace(run=run_chain, surface_distance=surface_distance)
