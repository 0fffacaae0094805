"""The sparse-capture study's model diagnostics (docs/training.md, issue 24): for each run folder,
the trained model's mean accumulated alpha over the test panoramas' valid pixels (rendered as a
panorama at the training height; holes between splats show as alpha < 1) and the needle
statistics of its Gaussians (longest / second-longest axis: median, 90th, 99th percentile) and the
fraction of them whose middle axis is thinner than Mip-Splatting's 3D filter (σ = sqrt(0.2) / ν, ν the
finest training panorama's sampling rate at the centre, gaussians/mip_filter.py): the needles that
filter would widen.

    PYTHONPATH=$PWD .venv/bin/python scripts/model_stats.py SCENE RUN_DIR [RUN_DIR ...] [--height 128]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    from evaluation.model_io import equirect_camera, load_model, render_pose
    from gaussians.mip_filter import filter_variance, sampling_rate
    from schemas.scene_loader import load_scene, valid_mask

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--height", type=int, default=128)
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    h, w = args.height, 2 * args.height
    views = scene.manifest.test_views()
    train = scene.manifest.train_views()
    train_viewmats = [torch.as_tensor(np.asarray(v.viewmat), dtype=torch.float32) for v in train]
    for run in args.runs:
        g = load_model(run / "train" / "point_cloud.ply")
        alphas = []
        for v in views:
            pose = np.linalg.inv(np.asarray(v.viewmat, dtype=np.float64))
            a = render_pose(g, pose, equirect_camera(h, w), background=torch.zeros(3)).alpha
            m = valid_mask(scene, v, h, w)
            alphas.append(float(a[m].mean()) if m is not None else float(a.mean()))
        s = torch.sort(g.scales, dim=1, descending=True).values
        ratio = (s[:, 0] / s[:, 1]).numpy()
        cams = [equirect_camera(h, w)] * len(train)
        sigma = filter_variance(sampling_rate(g.means, train_viewmats, cams)).sqrt()
        print(json.dumps({
            "run": str(run), "test_alpha": round(float(np.mean(alphas)), 3),
            "needle_p50_p90_p99": [round(float(np.percentile(ratio, q)), 1) for q in (50, 90, 99)],
            "median_opacity": round(float(g.opacities.median()), 3), "gaussians": len(g),
            "middle_axis_below_filter": round(float((s[:, 1] < sigma).float().mean()), 3),
        }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
