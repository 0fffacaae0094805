"""Helpers for the evaluation tests: a tiny simulated scene and a 'trained' model made
by back-projecting the scene's exact ground-truth depth (so renders should match it)."""

from __future__ import annotations

import json
import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

torch.set_num_threads(1)


def make_scene(root: Path, views: int = 2, test_views: int = 1, height: int = 32, preset: str = "cuboid"):
    import simulate

    simulate.generate_scene(root, preset=preset, views=views, test_views=test_views, height=height, seed=0,
                            effects="none")
    from schemas.scene_loader import load_scene

    return load_scene(root)


def backprojected_gaussians(scene, stride: int = 1):
    """Gaussians on the surfaces seen by every view: one per ground-truth depth pixel,
    coloured by the image, sized by the pixel footprint."""
    from gaussians.model import Gaussians
    from panogeom.equirect import ray_directions
    from panogeom.images import read_rgb

    means, cols, scales = [], [], []
    for v in scene.views:
        depth = np.load(scene.gt_depth_path(v)).astype(np.float64)
        h, w = depth.shape
        rgb = read_rgb(scene.image_path(v), size=(h, w)).astype(np.float64)
        dirs = ray_directions(h, w)
        pose = v.pose_matrix
        pts_cam = dirs * depth[..., None]
        pts = pts_cam @ pose[:3, :3].T + pose[:3, 3]
        sl = (slice(None, None, stride), slice(None, None, stride))
        means.append(pts[sl].reshape(-1, 3))
        cols.append(rgb[sl].reshape(-1, 3))
        scales.append((depth[sl] * (2 * math.pi / w) * 0.35 * stride).reshape(-1))
    means, cols, s = np.concatenate(means), np.concatenate(cols), np.concatenate(scales)
    return Gaussians.create(
        torch.tensor(means, dtype=torch.float32),
        colors=torch.tensor(cols, dtype=torch.float32),
        log_scales=torch.tensor(np.log(np.repeat(s[:, None], 3, 1)), dtype=torch.float32),
        opacity_logits=torch.full((len(means),), math.log(0.97 / 0.03)),
        sh_degree=0,
    )


def write_train_artifact(run_dir: Path, g, resolution=(32, 64), log_records=None, train_seconds=1.0,
                         duration_s=1.0):
    """A train stage folder as the train stage writes it (ply + log + artifact.json)."""
    from gaussians.ply import save_ply
    from schemas.artifact import Artifact, ArtifactMeta
    from schemas.train import TrainOutput

    from runfs.paths import RUN_MARKER

    d = run_dir / "train"
    d.mkdir(parents=True, exist_ok=True)
    (run_dir / RUN_MARKER).write_text("{}\n")  # a run folder as the engine makes it
    save_ply(d / "point_cloud.ply", g)
    if log_records is None:
        log_records = [
            {"iteration": i, "loss": 0.5 / i, "psnr": 10 + 3 * math.log(i), "num_gaussians": 100 + i,
             "seconds": 0.1 * i}
            for i in range(1, 51)
        ]
    (d / "train_log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in log_records))
    data = TrainOutput(ply="point_cloud.ply", log="train_log.jsonl", num_gaussians=len(g), iterations=50,
                       train_seconds=train_seconds, resolution=tuple(resolution), sh_degree=0, init="layout",
                       projection="360", layout_reg=True, backend="cpp", final_train_psnr=25.0)
    meta = ArtifactMeta(stage="train", key="k", scene_hash="s", params={}, code_version="c", upstream={},
                        created=datetime.now(timezone.utc), duration_s=duration_s)
    (d / "artifact.json").write_text(Artifact[TrainOutput](meta=meta, data=data).model_dump_json(indent=1))
    return d


def run_evaluate(scene, run_dir: Path, write_artifact: bool = True, **params):
    """Run the evaluate stage on `run_dir`/train; optionally write its artifact.json as the engine would."""
    from pipeline.engine import load_artifact
    from runtime.stage import StageContext
    from schemas.artifact import Artifact, ArtifactMeta
    from schemas.evaluate import EvaluateOutput
    from schemas.train import TrainOutput
    from stages import evaluate

    ctx = StageContext(scene=scene, params=evaluate.Params(**params),
                       inputs={"train": load_artifact(run_dir / "train", TrainOutput), "union": None},
                       out_dir=run_dir / "evaluate")
    out = evaluate.run(ctx)
    if write_artifact:
        meta = ArtifactMeta(stage="evaluate", key="k", scene_hash="s", params={}, code_version="c", upstream={},
                            created=datetime.now(timezone.utc), duration_s=0.5, warnings=ctx.warnings)
        (run_dir / "evaluate" / "artifact.json").write_text(
            Artifact[EvaluateOutput](meta=meta, data=out).model_dump_json(indent=1))
    return out, ctx


def fake_lpips_state(net: str = "alex", seed: int = 0) -> tuple[dict, dict]:
    """Backbone and linear-head state dicts with the published keys and random values: they
    exercise finding and loading the files, not LPIPS's calibration."""
    from evaluation import metrics as M

    torch.manual_seed(seed)
    model = M.LPIPS(net)
    for p in model.parameters():
        p.data = torch.rand_like(p) * (0.05 if p.ndim == 4 and p.shape[2] > 1 else 1.0)
    backbone = {f"features.{k}": v for k, v in model.features.state_dict().items()}
    backbone["classifier.1.weight"] = torch.zeros(2, 2)  # torchvision's classifier: ignored
    lin = {f"lin{i}.model.1.weight": model.lins[i].weight.data for i in range(5)}
    return backbone, lin


def write_fake_lpips_folder(folder: Path, net: str = "alex", seed: int = 0) -> tuple[dict, dict]:
    """The two published files, random-valued, in one folder (the $PANO_PIPE_LPIPS_WEIGHTS layout)."""
    from evaluation import metrics as M

    backbone, lin = fake_lpips_state(net, seed)
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(backbone, folder / M._BACKBONE_FILES[net])
    torch.save(lin, folder / M._LIN_FILES[net])
    return backbone, lin
