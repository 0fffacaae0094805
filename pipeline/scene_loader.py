"""Load and validate a scene folder: every problem is a one-line PanoError."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
from pydantic import ValidationError

from pipeline.errors import PanoError, describe_validation_error
from schemas.scene import Scene, SceneManifest


def load_scene(root: str | Path, check_images: bool = True) -> Scene:
    root = Path(root)
    if not root.exists():
        raise PanoError(root, "scene folder does not exist")
    if not root.is_dir():
        raise PanoError(root, "not a folder (expected a scene folder holding scene.json)")
    manifest_path = root / "scene.json"
    if not manifest_path.is_file():
        raise PanoError(manifest_path, "missing (a scene folder needs a scene.json manifest)")
    try:
        raw = json.loads(manifest_path.read_text())
    except json.JSONDecodeError as e:
        raise PanoError(manifest_path, f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    try:
        manifest = SceneManifest.model_validate(raw)
    except ValidationError as e:
        raise describe_validation_error(manifest_path, e) from None
    scene = Scene(root=root, manifest=manifest)
    for i, view in enumerate(manifest.views):
        for field in ("layout", "depth", "gt_depth"):
            rel = getattr(view, field)
            if rel and not (root / rel).is_file():
                raise PanoError(root / rel, f"missing (named by scene.json views.{i}.{field})")
        if check_images:
            check_panorama(scene.image_path(view), f"scene.json views.{i}.image")
    return scene


def check_panorama(path: Path, named_by: str) -> tuple[int, int]:
    """Return (H, W) of an equirectangular image, or raise naming the problem."""
    if not path.is_file():
        raise PanoError(path, f"image missing (named by {named_by})")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise PanoError(path, "unreadable image (not a format OpenCV can decode)")
    h, w = img.shape[:2]
    if w != 2 * h:
        raise PanoError(path, f"not an equirectangular 2:1 image: {w}x{h}")
    return h, w
