"""Loading a trained model and rendering it from a pose: the one place evaluation
touches gaussians/ and splatting/, so the rest stays pure numpy."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


def load_model(path: str | Path, device: str = "cpu"):
    try:
        from gaussians import load_ply
    except ImportError:  # the package may not re-export it
        from gaussians.ply import load_ply
    from runfs.errors import PanoError

    try:
        g = load_ply(path)
    except (ValueError, OSError) as e:  # a malformed, truncated or boastful PLY: bad input, one line
        raise PanoError(path, str(e).removeprefix(f"{path}: ")) from None
    return g.to(device=device) if device != "cpu" else g


def _render_fn():
    try:
        from gaussians import render
    except ImportError:
        from gaussians.model import render
    return render


def equirect_camera(height: int, width: int):
    import splatting

    return splatting.EquirectCamera(int(height), int(width))


def pinhole_camera(height: int, width: int, fov_deg: float = 90.0):
    """A pinhole camera with horizontal field of view `fov_deg`, principal point centred."""
    import math

    import splatting

    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    return splatting.PinholeCamera(f, f, width / 2.0, height / 2.0, int(width), int(height))


@dataclass
class Rendered:
    image: np.ndarray  # [H,W,3] float32 in [0,1]
    alpha: np.ndarray  # [H,W]
    depth: np.ndarray  # [H,W] expected distance along the ray (metres); 0 where nothing was hit
    seconds: float
    backend: str


def recorded_background(settings: dict | None, params: dict | None) -> tuple[float, float, float] | None:
    """The background a model was trained against, from its train artifact: the colour the train
    stage settled (`settings`, where "mean" is resolved), else its parameter (artifacts written
    before); None when neither holds an RGB triple."""
    bg = (settings or {}).get("background")
    if bg is None:
        bg = (params or {}).get("background")
    return tuple(float(x) for x in bg) if isinstance(bg, list | tuple) and len(bg) == 3 else None


def render_on_device(g, pose_c2w: np.ndarray, camera, backend: str | None = None, background=None, rig=None,
                     tile_size: int | None = None):
    """The render of `g` from a camera-to-world pose as the renderer returns it, on the model's
    device (what an interactive viewer shows; `render_pose` downloads and normalises it).
    `tile_size` None: the renderer's default."""
    from gaussians.model import render_stitched

    render = _render_fn()
    dtype, device = g.means.dtype, g.means.device
    viewmat = torch.linalg.inv(torch.as_tensor(np.asarray(pose_c2w), dtype=torch.float64)).to(dtype=dtype, device=device)
    tiles = {} if tile_size is None else {"tile_size": int(tile_size)}
    with torch.no_grad():
        if rig is None:
            return render(g, viewmat, camera, backend=backend, background=background, **tiles)
        return render_stitched(g, viewmat, camera.height, camera.width, rig, backend=backend, background=background,
                               **tiles)


def render_pose(g, pose_c2w: np.ndarray, camera, backend: str | None = None, background=None,
                rig=None, tile_size: int | None = None) -> Rendered:
    """Render `g` from a camera-to-world pose; depth is normalised by alpha (the renderer
    returns Σ T·α·‖t‖, whose ratio to alpha is the expected distance). With `rig` (a
    splatting.PerspectiveRig; `camera` then an EquirectCamera) the panorama is stitched from the
    rig's rendered crops, as the perspective baseline produces its test panoramas."""
    t0 = time.perf_counter()
    out = render_on_device(g, pose_c2w, camera, backend=backend, background=background, rig=rig, tile_size=tile_size)
    if g.means.device.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    alpha = out.alpha.detach().float().cpu().numpy()
    depth = out.depth.detach().float().cpu().numpy()
    exp_depth = np.where(alpha > 1e-4, depth / np.maximum(alpha, 1e-4), 0.0).astype(np.float32)
    image = np.clip(out.image.detach().float().cpu().numpy(), 0.0, 1.0)
    return Rendered(image, alpha, exp_depth, seconds, str(getattr(out, "backend", backend or "?")))
