"""``splatting.render``: 360° (and pinhole) Gaussian splatting, one function for all devices."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Optional, Union

import torch

from .cameras import EquirectCamera, PinholeCamera
from .devices import device_key
from .project import project
from .raster_torch import TorchRaster, bin_gaussians_torch
from .sh import eval_sh, num_sh_bases

__all__ = ["render", "RenderOutput"]

DEFAULT_TILE = 16
MAX_TILE = 32  # the C++ kernel's MAX_TILE (splatting/csrc): tile sizes are 1..MAX_TILE
#: 3DGS's screen-space dilation of every footprint, in squared pixels
DEFAULT_EPS2D = 0.3


@dataclass
class RenderOutput:
    image: torch.Tensor  # [H,W,3]
    alpha: torch.Tensor  # [H,W]
    depth: torch.Tensor  # [H,W] Σ T_i α_i ‖t_i‖ (divide by alpha for the expected distance)
    means2d: torch.Tensor  # [N,2] leaf; .grad = tangent-plane position gradient (pixels)
    radii: torch.Tensor  # [N] int32 pixels, 0 = not visible
    visible: torch.Tensor  # [N] bool
    backend: str = "torch"  # what actually ran: "cpp", "cuda" or "torch"


def _pick_backend(backend, device):
    if backend is None:
        backend = "cpp" if device.type == "cpu" else "cuda"
    if backend not in ("cpp", "cuda", "torch"):
        raise ValueError(f"backend must be 'cpp', 'cuda', 'torch' or None, got {backend!r}")
    if backend == "cpp":
        if device.type != "cpu":
            raise ValueError("backend='cpp' needs CPU tensors; use backend='cuda' (or 'torch') on CUDA")
        from . import raster_cpp

        if raster_cpp.load() is None:
            backend = "torch"
    elif backend == "cuda":
        from . import raster_triton

        reason = raster_triton.unavailable_reason(device)
        if reason is not None:
            if device.type != "cuda":
                raise ValueError(reason)
            _warn_once(f"splatting: the cuda backend cannot run ({reason}); falling back to the torch backend.")
            backend = "torch"
    return backend


_WARNED: set = set()


def _warn_once(message):
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def _color_fn(colors, sh_degree, N):
    if colors.dim() == 2:
        if sh_degree not in (None, 0) and colors.shape[-1] != 3:
            raise ValueError("colors must be [N,3] RGB or [N,K,3] SH coefficients")
        if colors.shape != (N, 3):
            raise ValueError(f"colors must be [N,3], got {tuple(colors.shape)}")
        return lambda dirs, idx: colors[idx]
    if colors.dim() != 3 or colors.shape[0] != N or colors.shape[2] != 3:
        raise ValueError(f"SH colors must be [N,K,3], got {tuple(colors.shape)}")
    K = colors.shape[1]
    if sh_degree is None:
        sh_degree = int(round(math.sqrt(K))) - 1
    if num_sh_bases(sh_degree) > K:
        raise ValueError(f"sh_degree={sh_degree} needs {num_sh_bases(sh_degree)} coefficients, got {K}")

    def fn(dirs, idx):
        return torch.clamp_min(eval_sh(sh_degree, colors[idx], dirs) + 0.5, 0.0)

    return fn


def render(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    camera: Union[EquirectCamera, PinholeCamera],
    sh_degree: Optional[int] = None,
    background: Optional[torch.Tensor] = None,
    eps2d: float = DEFAULT_EPS2D,
    near: float = 0.05,
    backend: Optional[str] = None,
    tile_size: int = DEFAULT_TILE,
) -> RenderOutput:
    """Render N Gaussians seen from ``viewmat`` (4×4 world-to-camera) with ``camera``.

    Differentiable in every tensor argument; runs in the dtype of ``means``
    (float32 or float64). ``backend``: "cpp" (CPU kernel, default for CPU tensors),
    "cuda" (Triton kernels, default for CUDA tensors; CPU tensors too when
    ``TRITON_INTERPRET=1``), "torch" (pure torch reference). See docs/splatting.md.
    """
    if not isinstance(camera, (EquirectCamera, PinholeCamera)):
        raise TypeError("camera must be splatting.EquirectCamera or splatting.PinholeCamera")
    dtype, device = means.dtype, means.device
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"means must be float32 or float64, got {dtype}")
    N = means.shape[0]
    if means.shape != (N, 3) or quats.shape != (N, 4) or scales.shape != (N, 3) or opacities.shape[0] != N:
        raise ValueError("shapes must be means [N,3], quats [N,4], scales [N,3], opacities [N]")
    opacities = opacities.reshape(N)
    backend = _pick_backend(backend, device)
    H, W = int(camera.height), int(camera.width)
    viewmat = viewmat.to(device=device, dtype=dtype)
    extra = (colors,) + ((background,) if isinstance(background, torch.Tensor) else ())
    bg = None if background is None else torch.as_tensor(background, dtype=dtype, device=device).reshape(3)
    if backend == "cpp":
        image, alpha, depth, means2d, radii, visible = _render_cpp(
            means, quats.to(dtype), scales.to(dtype), opacities.to(dtype), colors.to(dtype), sh_degree, viewmat,
            camera, eps2d, near, int(tile_size), extra)
        if bg is not None:
            # a black background that needs no gradient adds nothing: skip three image-sized
            # operations and their backward (reading bg costs nothing on the CPU)
            if bg.requires_grad or bool(bg.any()):
                image = image + (1.0 - alpha)[..., None] * bg
        return RenderOutput(image=image, alpha=alpha, depth=depth, means2d=means2d, radii=radii, visible=visible,
                            backend=backend)
    dirs = _pixel_dirs(camera, dtype, device)
    ts = int(tile_size)
    if backend == "cuda":
        # projection and binning in Triton kernels: a fixed handful of launches, no host sync
        from .bin_triton import bin_gaussians
        from .project_triton import project_gaussians
        from .raster_triton import TritonRaster

        colors = colors.to(dtype)
        _color_fn(colors, sh_degree, N)  # shape checks
        if colors.dim() == 3 and sh_degree is None:
            sh_degree = int(round(math.sqrt(colors.shape[1]))) - 1
        packed, ints, visible, means2d = project_gaussians(
            means, quats.to(dtype), scales.to(dtype), opacities.to(dtype), colors, viewmat, camera, eps2d, near,
            sh_degree, ts, _color_fn)
        toff, tlist, _ = bin_gaussians(ints, H, W, ts, packed=packed.detach(), camera=camera)
        if bg is not None and not bg.requires_grad:  # composited in the kernel (a blend outside costs 6 passes)
            color, depth, alpha = TritonRaster.apply(packed, dirs, toff, tlist, H, W, ts, bg)
            bg = None
        else:
            color, depth, alpha = TritonRaster.apply(packed, dirs, toff, tlist, H, W, ts)
        radii = ints[:, 5]
    else:
        proj = project(
            means, quats.to(dtype), scales.to(dtype), opacities.to(dtype), _color_fn(colors.to(dtype), sh_degree, N),
            viewmat, camera, eps2d, near, extra_grad=extra,
        )
        toff, tlist = bin_gaussians_torch(proj.bbox, proj.packed[:, 18].detach(), H, W, ts)
        color, depth, alpha = TorchRaster.apply(proj.packed, dirs, toff, tlist, H, W, ts)
        means2d, radii, visible = proj.means2d, proj.radii, proj.visible
    image = color if bg is None else color + (1.0 - alpha)[..., None] * bg
    return RenderOutput(image=image, alpha=alpha, depth=depth, means2d=means2d, radii=radii, visible=visible,
                        backend=backend)


_DIRS_CACHE: dict = {}


def _pixel_dirs(camera, dtype, device):
    """The camera's pixel ray directions, computed once per (camera, dtype, device): a render
    then dispatches no per-frame work for them."""
    key = (camera, dtype, device_key(device))
    dirs = _DIRS_CACHE.get(key)
    if dirs is None:
        if len(_DIRS_CACHE) >= 16:
            _DIRS_CACHE.clear()
        dirs = _DIRS_CACHE[key] = camera.pixel_dirs(dtype=dtype, device=device)
    return dirs


def _render_cpp(means, quats, scales, opacities, colors, sh_degree, viewmat, camera, eps2d, near, ts, extra):
    from . import raster_cpp

    N = means.shape[0]
    dtype = means.dtype
    if colors.dim() == 2:
        _color_fn(colors, sh_degree, N)  # shape checks
        rgb = colors
    else:
        # SH: view direction of each Gaussian in the world frame (from the camera centre)
        fn = _color_fn(colors, sh_degree, N)
        R, t = viewmat[:3, :3], viewmat[:3, 3]
        campos = -(R.T @ t)
        rgb = fn(means - campos, slice(None))
    need_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (means, quats, scales, opacities, viewmat, *extra))
    means2d = torch.zeros(N, 2, dtype=dtype, requires_grad=need_grad)
    camv = raster_cpp.camera_vector(camera, eps2d, near)
    dirs = raster_cpp.pixel_planes(camera, dtype)
    color, depth, alpha, visible, radii, m2d = raster_cpp.CppRender.apply(
        means, quats, scales, opacities, rgb, viewmat, means2d, dirs, camv, ts)
    with torch.no_grad():
        means2d.copy_(m2d)  # values: pixel position of the centre (the gradient ignores them)
    return color, alpha, depth, means2d, radii, visible
