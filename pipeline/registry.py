"""The stage DAG, declared in one place.

Each entry names the stage's inputs (upstream artifacts; True = required),
the scene files it reads (only those enter its cache key) and when a scene
does not call for it; its code version is the import closure of its module
(runtime/code_closure.py).
"""

from __future__ import annotations

from functools import cache

from pydantic import BaseModel

from runtime.stage import StageSpec
from schemas.scene import Scene, View


def train_views(scene: Scene, params) -> list[View]:
    return scene.manifest.train_views()


def torch_resources(params) -> dict[str, float]:
    """A torch stage: its `threads` CPUs (1 when unset: a batch runs stages side by side), and a
    GPU when its `device` setting names CUDA."""
    cpus = float(getattr(params, "threads", None) or 1)
    device = str(getattr(params, "device", None) or "cpu")
    return {"CPU": cpus, **({"GPU": 1.0} if device.startswith("cuda") else {})}


@cache
def build_registry() -> dict[str, StageSpec]:
    from stages import align, depth, evaluate, layout, poses, sampling, train, union

    specs = [
        StageSpec(
            "poses", poses.Params, poses.Output, poses.run, scene_inputs=("images", "masks"),
            skip_reason=poses.skip_reason, run_reason=poses.run_reason, completes_scene=poses.complete_scene,
            description="camera poses from the panoramas (structure from motion), upright and metric",
        ),
        StageSpec(
            "layout", layout.Params, layout.Output, layout.run, reads_views=layout.selected_views,
            # poses: the camera heights it recovers complete the views scene.json gives none
            inputs={"poses": False}, scene_inputs=("images", "layout"), skip_reason=layout.skip_reason, run_reason=layout.run_reason,
            resolve_params=layout.resolve_params, hint=layout.hint,
            # poses kept up to scale (poses scale_source none) are made metric by the rooms
            completes_scene=layout.complete_scene,
            description="room layout per view (supplied boundaries, or a HorizonNet model on the aligned panorama)",
        ),
        StageSpec(
            "depth", depth.Params, depth.Output, depth.run, reads_views=train_views,
            scene_inputs=("images", "depth"), skip_reason=depth.skip_reason, run_reason=depth.run_reason,
            resolve_params=depth.resolve_params, hint=depth.hint,
            description="depth per view (supplied files, or a depth model on cube faces of the panorama)",
        ),
        StageSpec(
            "union", union.Params, union.Output, union.run, reads_views=train_views,
            inputs={"poses": False, "layout": True}, scene_inputs=(),
            description="union of the per-view floor plans in the world frame",
        ),
        StageSpec(
            "sampling", sampling.Params, sampling.Output, sampling.run, reads_views=train_views,
            inputs={"poses": False, "union": True, "layout": True}, scene_inputs=("images",),
            description="box sampling of the floor plan into a layout point cloud",
        ),
        StageSpec(
            "align", align.Params, align.Output, align.run, reads_views=train_views,
            inputs={"poses": False, "depth": True, "layout": False, "sampling": False},
            scene_inputs=("images", "masks"),
            description="depth clouds scaled to the layout and merged with it (open3d)",
        ),
        StageSpec(
            "train", train.Params, train.Output, train.run, reads_views=train_views,
            inputs={"poses": False, "align": False, "sampling": False, "union": False},
            scene_inputs=("images", "masks"),
            description="360° Gaussian splatting optimisation", resources=torch_resources,
        ),
        StageSpec(
            "evaluate", evaluate.Params, evaluate.Output, evaluate.run,
            inputs={"poses": False, "train": True, "union": False}, scene_inputs=("images", "gt", "masks"),
            description="metrics on the held-out views", resources=torch_resources,
        ),
    ]
    return {s.name: s for s in specs}


def all_schemas() -> dict[str, type[BaseModel]]:
    """Name -> model, for `pano-pipe schema DIR` (artifacts wrapped in their envelope)."""
    from schemas.artifact import Artifact
    from schemas.scene import SceneManifest

    out: dict[str, type[BaseModel]] = {"scene": SceneManifest}
    for name, spec in build_registry().items():
        out[f"{name}.artifact"] = Artifact[spec.output]
    return out
