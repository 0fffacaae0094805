"""Issue 24's render probe (docs/training.md, "The sampling grid and the dilation"): re-render the
trained models of run folders at the scene's test views, with several screen-space dilations and
supersampling factors, and print PSNR / SSIM over the valid pixels against the evaluate stage's
ground truth. A model whose score collapses when it is drawn finer (a smaller dilation, or k times
the pixels averaged back) holds its surfaces together only through the training renders' dilation:
it shows holes from any camera that sees it finer, as a nearer test camera does.

    PYTHONPATH=$PWD .venv/bin/python scripts/render_probe.py SCENE RUN_DIR [RUN_DIR ...] \
        [--height 128] [--eps2d 0.3,0.1,0] [--supersample 1,2,4]

Each line: the run, the dilation the model was fitted with (Gaussians.eps2d), then
"eps2d x k": [PSNR, SSIM] for every combination.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    import cv2

    import splatting
    from evaluation import metrics
    from evaluation.model_io import load_model
    from gaussians.model import render
    from panogeom.images import read_rgb
    from schemas.scene_loader import load_scene, valid_mask

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--height", type=int, default=128)
    ap.add_argument("--eps2d", default="0.3,0.1,0", help="dilations to draw with (squared pixels), comma separated")
    ap.add_argument("--supersample", default="1", help="factors k: render k·H × k·W, average k×k blocks back")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    h, w = args.height, 2 * args.height
    dilations = [float(x) for x in args.eps2d.split(",")]
    factors = [int(x) for x in args.supersample.split(",")]
    views = scene.manifest.test_views()
    for run in args.runs:
        g = load_model(run / "train" / "point_cloud.ply")
        gts = {}
        for v in views:
            gt = read_rgb(run / "evaluate" / "gt" / f"{v.name}.png").astype(np.float32)
            gts[v.name] = gt / 255.0 if gt.max() > 1.5 else gt
        res = {}
        for eps in dilations:
            for k in factors:
                ps, ss = [], []
                for v in views:
                    vm = torch.as_tensor(np.asarray(v.viewmat), dtype=g.means.dtype)
                    with torch.no_grad():
                        img = render(g, vm, splatting.EquirectCamera(k * h, k * w), background=torch.zeros(3),
                                     eps2d=eps).image.numpy()
                    if k > 1:
                        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                    img = np.clip(img, 0.0, 1.0)
                    m = valid_mask(scene, v, h, w)
                    ps.append(metrics.psnr(img, gts[v.name], mask=m))
                    ss.append(metrics.ssim(img, gts[v.name], mask=m))
                res[f"{eps:g} x{k}"] = [round(float(np.mean(ps)), 2), round(float(np.mean(ss)), 3)]
        print(json.dumps({"run": run.name, "fitted_eps2d": g.eps2d, **res}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
