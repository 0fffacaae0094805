"""Load and validate a scene folder: every problem is a one-line PanoError."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from pydantic import ValidationError

from runfs.errors import PanoError, describe_validation_error, read_json
from runfs.limits import MIN_IMAGE_HEIGHT, check_image_size, image_size, load_npy, max_megapixels, read_image
from schemas.scene import Scene, SceneManifest, View


def load_scene(root: str | Path, check_images: bool = True) -> Scene:
    root = Path(root)
    if not root.exists():
        raise PanoError(root, "scene folder does not exist")
    if not root.is_dir():
        raise PanoError(root, "not a folder (expected a scene folder holding scene.json)")
    manifest_path = root / "scene.json"
    if not manifest_path.is_file():
        raise PanoError(manifest_path, "missing (a scene folder needs a scene.json manifest)")
    raw = read_json(manifest_path)
    try:
        manifest = SceneManifest.model_validate(raw)
    except ValidationError as e:
        raise describe_validation_error(manifest_path, e) from None
    scene = Scene(root=root, manifest=manifest)
    limit = max_megapixels()
    for i, view in enumerate(manifest.views):
        files = {"layout": scene.layout_path(view), "depth": scene.depth_path(view),
                 "gt_depth": scene.gt_depth_path(view), "mask": scene.mask_path(view)}
        for field, path in files.items():
            if getattr(view, field) and not path.is_file():
                raise PanoError(path, f"missing (named by scene.json views.{i}.{field})")
            if path is not None and path.suffix.lower() == ".png":
                check_image_size(path, limit, min_height=1)
        if check_images:
            size = check_panorama(scene.image_path(view), f"scene.json views.{i}.image", limit)
            if files["mask"] is not None:
                read_mask(files["mask"], size)  # a bad mask fails now, before any stage runs
    if manifest.floor_plan:
        scene.path(manifest.floor_plan, "scene.json floor_plan")
    return scene


def check_panorama(path: Path, named_by: str, limit_mp: float | None = None) -> tuple[int, int]:
    """Return (H, W) of an equirectangular image, or raise naming the problem."""
    if not path.is_file():
        raise PanoError(path, f"image missing (named by {named_by})")
    img = read_image(path, min_height=MIN_IMAGE_HEIGHT, limit_mp=limit_mp)
    if img is None:
        raise PanoError(path, "unreadable image (not a format OpenCV can decode)")
    h, w = img.shape[:2]
    if w != 2 * h:
        raise PanoError(path, f"not an equirectangular 2:1 image: {w}x{h}")
    if h < MIN_IMAGE_HEIGHT:
        raise PanoError(path, f"image is {w}x{h}; panoramas need at least {MIN_IMAGE_HEIGHT} rows")
    if img.ndim == 3 and img.shape[2] not in (3, 4):
        raise PanoError(path, f"image has {img.shape[2]} channels; expected grey, RGB or RGBA")
    return h, w


def read_mask(path: Path, image_size: tuple[int, int]) -> np.ndarray:
    """A mask file as [H,W] bool (non-zero = valid) at its image's size `image_size` (H, W);
    unreadable, of another size, or masking out everything: a one-line PanoError."""
    m = read_image(path, what="mask")
    if m is None:
        raise PanoError(path, "unreadable mask (not a format OpenCV can decode)")
    if m.shape[:2] != tuple(image_size):
        raise PanoError(path, f"mask is {m.shape[1]}x{m.shape[0]}, its panorama {image_size[1]}x{image_size[0]}; "
                              "a mask has its image's size")
    valid = (m if m.ndim == 2 else m[..., :3].max(axis=2)) > 0
    if not valid.any():
        raise PanoError(path, "the mask leaves no valid pixel (non-zero = valid)")
    return valid


def valid_mask(scene: Scene, view: View, height: int, width: int) -> np.ndarray | None:
    """The pixels of `view` at (height, width) that training, depth back-projection and metrics
    use: its mask file (resized, nearest) and the scene's nadir cap. None when every pixel is."""
    from panogeom.equirect import nadir_cap

    mask = None
    path = scene.mask_path(view)
    if path is not None:
        native = image_size(scene.image_path(view))
        full = read_mask(path, native if native is not None else _decoded_size(scene.image_path(view)))
        mask = cv2.resize(full.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0
    if scene.manifest.nadir_mask_deg > 0:
        cap = nadir_cap(height, width, scene.manifest.nadir_mask_deg)
        mask = cap if mask is None else mask & cap
    if mask is not None and not mask.any():
        raise PanoError(path or scene.root / "scene.json", f"view {view.name!r}: no valid pixel left at "
                                                          f"{width}x{height} (mask and nadir_mask_deg)")
    return mask


def _decoded_size(path: Path) -> tuple[int, int]:
    img = read_image(path)
    if img is None:
        raise PanoError(path, "unreadable image (not a format OpenCV can decode)")
    return img.shape[:2]


def read_depth_file(path: str | Path) -> np.ndarray:
    """A supplied depth map in metres along the ray, float32 [H,W]; NaN where the file says invalid."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        raw = read_image(path, what="depth map")
        if raw is None:
            raise PanoError(path, "unreadable depth PNG")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            ch = 1 if raw.ndim == 2 else raw.shape[2]
            raise PanoError(
                path, f"depth PNG must be 16-bit single-channel millimetres, got {raw.dtype} x{ch}"
            )
        depth = raw.astype(np.float32) / 1000.0
        depth[raw == 0] = np.nan
    elif path.suffix.lower() == ".npy":
        depth = load_npy(path, pixels=True)
        if depth.ndim == 3 and depth.shape[-1] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
            raise PanoError(
                path, f"depth .npy must be a numeric [H,W] array, got {depth.dtype} {list(depth.shape)}"
            )
        depth = depth.astype(np.float32)
    else:
        raise PanoError(path, "depth file must be .png (uint16 mm) or .npy (float metres)")
    h, w = depth.shape
    if w != 2 * h:
        raise PanoError(path, f"depth map is {w}x{h} (width x height); expected a 2:1 equirectangular map, "
                              f"e.g. {2 * h}x{h}")
    if h < 4:
        raise PanoError(path, f"depth map is {w}x{h}; too small (at least 8x4)")
    return depth
