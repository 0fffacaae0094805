"""The stage DAG, declared in one place.

Each entry names the stage's inputs (upstream artifacts; True = required),
the scene files it reads (only those enter its cache key), the code it depends
on (its version), and when a scene does not call for it.
"""

from __future__ import annotations

from functools import cache

from pipeline.stage import StageSpec
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
            code=("stages.poses", "sfm", "panogeom"),
            description="camera poses from the panoramas (structure from motion), upright and metric",
        ),
        StageSpec(
            "layout", layout.Params, layout.Output, layout.run, reads_views=layout.selected_views,
            scene_inputs=("images", "layout"), skip_reason=layout.skip_reason, run_reason=layout.run_reason,
            resolve_params=layout.resolve_params, hint=layout.hint,
            code=("stages.layout", "layoutnet", "panogeom"),
            description="room layout per view (supplied boundaries, or a HorizonNet model on the aligned panorama)",
        ),
        StageSpec(
            "depth", depth.Params, depth.Output, depth.run, reads_views=train_views,
            scene_inputs=("images", "depth"), skip_reason=depth.skip_reason, run_reason=depth.run_reason,
            resolve_params=depth.resolve_params, hint=depth.hint,
            code=("stages.depth", "depthnet", "panogeom"),
            description="depth per view (supplied files, or a depth model on cube faces of the panorama)",
        ),
        StageSpec(
            "union", union.Params, union.Output, union.run, reads_views=train_views,
            inputs={"poses": False, "layout": True}, scene_inputs=(),
            code=("stages.union",),
            description="union of the per-view floor plans in the world frame",
        ),
        StageSpec(
            "sampling", sampling.Params, sampling.Output, sampling.run, reads_views=train_views,
            inputs={"poses": False, "union": True, "layout": True}, scene_inputs=("images",),
            code=("stages.sampling", "stages.union", "stages.cloud_io", "panogeom"),
            description="box sampling of the floor plan into a layout point cloud",
        ),
        StageSpec(
            "align", align.Params, align.Output, align.run, reads_views=train_views,
            inputs={"poses": False, "depth": True, "layout": False, "sampling": False},
            scene_inputs=("images", "masks"),
            code=("stages.align", "stages.cloud_io", "panogeom"),
            description="depth clouds scaled to the layout and merged with it (open3d)",
        ),
        StageSpec(
            "train", train.Params, train.Output, train.run, reads_views=train_views,
            inputs={"poses": False, "align": False, "sampling": False, "union": False},
            scene_inputs=("images", "masks"),
            code=("stages.train", "stages.cloud_io", "gaussians", "splatting"),
            description="360° Gaussian splatting optimisation", resources=torch_resources,
        ),
        StageSpec(
            "evaluate", evaluate.Params, evaluate.Output, evaluate.run,
            inputs={"poses": False, "train": True, "union": False}, scene_inputs=("images", "gt", "masks"),
            code=("stages.evaluate", "evaluation", "gaussians", "splatting"),
            description="metrics on the held-out views", resources=torch_resources,
        ),
    ]
    return {s.name: s for s in specs}
