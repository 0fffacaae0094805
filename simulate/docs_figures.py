"""Regenerate the figures and the profile table of docs/simulator.md.

    .venv/bin/python -m simulate.docs_figures [docs/images]

Writes sim_<preset>.png (train view 0 of each preset, 256x512, all effects but noise),
sim_gt_<preset>.png (that view's gt depth, with the gt layout boundaries drawn
over the image) and prints the profile table of a 4-view 512x1024 scene.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from simulate.generate import PRESETS, generate_scene


def _depth_vis(depth: np.ndarray) -> np.ndarray:
    d = np.clip(depth / 8.0, 0, 1)
    return cv2.applyColorMap((255 * (1 - d)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)


def _overlay(img: np.ndarray, bnd: np.ndarray) -> np.ndarray:
    out = img.copy()
    h, w = img.shape[:2]
    for k, colour in ((0, (0, 0, 255)), (1, (0, 255, 0))):
        rows = (0.5 - bnd[k] / np.pi) * h - 0.5
        pts = np.stack([np.arange(w), rows], -1)
        for c in range(w - 1):
            if abs(rows[c + 1] - rows[c]) < h / 8:
                p0 = tuple(np.round(pts[c]).astype(int))
                p1 = tuple(np.round(pts[c + 1]).astype(int))
                cv2.line(out, p0, p1, colour, 1, cv2.LINE_AA)
    return out


def main(dest: Path = Path("docs/images")) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for preset in PRESETS:
            out = Path(tmp) / preset
            fx = "texture,furniture,shading,aa"
            generate_scene(out, preset=preset, views=4, test_views=2, height=256, seed=0, effects=fx)
            img = cv2.imread(str(out / "images" / "train_00.png"))
            cv2.imwrite(str(dest / f"sim_{preset}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            depth = np.load(out / "gt" / "depth" / "train_00.npy")
            bnd = np.load(out / "gt" / "layout" / "train_00.npy")
            gt = np.concatenate([_depth_vis(depth), _overlay(img, bnd)], axis=0)
            gt = cv2.resize(gt, (gt.shape[1] // 2, gt.shape[0] // 2), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(dest / f"sim_gt_{preset}.png"), gt, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            print("wrote", dest / f"sim_{preset}.png", dest / f"sim_gt_{preset}.png")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/images"))
