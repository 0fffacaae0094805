"""poses: camera-to-world poses recovered from the panoramas themselves (structure from motion).

A scene calls for it when some view has no pose in scene.json. pycolmap
reconstructs every panorama (sfm.reconstruct), or with method upright-pair two
levelled panoramas are posed by sfm.upright_pair; the reconstruction is turned
upright and metric (sfm.frame): gravity from the cameras' mean down axis, scale
from the camera heights over the floor plane under them, or the frame of the
views that have poses. Downstream stages see the scene with the recovered
poses filled in (StageSpec.completes_scene); views SfM could not place are left
out of it. See docs/poses.md.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from panogeom.images import read_rgb
from pipeline.console import make_progress
from runfs.errors import PanoError
from runfs.limits import image_size
from schemas.scene_loader import valid_mask
from pipeline.stage import Loaded, StageContext
from schemas.poses import PosesOutput, UprightPairReport, ViewPose
from schemas.scene import Scene
from sfm.frame import align_to_floor, align_to_known
from sfm.reconstruct import STEPS as SFM_STEPS
from sfm.reconstruct import Panorama, Reconstruction, SfmOptions, reconstruct
from sfm.upright_pair import PairResult, relative_pose
from stages.cloud_io import write_ply

Output = PosesOutput

PLY_NAME = "points.ply"
DRAWING_NAME = "cameras.png"


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    method: Literal["rig", "equirect", "upright-pair"] = Field(
        default="equirect", description="Feed COLMAP the panoramas with its EQUIRECTANGULAR camera (equirect), "
                                        "or perspective views of each as a rig (rig: more points, 8x slower); "
                                        "upright-pair: two levelled panoramas at one camera height, without "
                                        "COLMAP, for pairs too far apart for it; docs/poses.md.")
    working_height: int = Field(
        default=512, ge=64, le=4096, description="Panoramas are resampled to this height (never up) for SfM.")
    max_features: int = Field(default=4096, ge=100, description="SIFT features per image at most.")
    min_matches: int = Field(default=15, ge=5, description="Verified matches a pair of images needs to count.")
    default_camera_height: float = Field(
        default=1.6, gt=0, le=100, description="Camera height (m) for views without camera_height in scene.json: "
                                               "it sets the metric scale when no view has a pose.")
    threads: int | None = Field(default=None, ge=1, description="CPU threads for COLMAP (default: all).")
    seed: int = Field(default=0, ge=0, le=2**31 - 1,
                      description="Random seed of COLMAP (RANSAC, mapping) and of the floor fit.")


def skip_reason(scene: Scene, params: Params) -> str | None:
    if not scene.manifest.unposed_views():
        return "every view has a pose in scene.json"
    return None


def run_reason(scene: Scene, params: Params) -> str:
    """Why a scene calls for the stage (skip_reason says when it does not)."""
    n = len(scene.manifest.unposed_views())
    return f"{n} of {len(scene.views)} views have no pose in scene.json"


def complete_scene(scene: Scene, artifact: Loaded) -> Scene:
    """The scene with the recovered poses filled in, unregistered views left out."""
    return scene.with_poses({v.view: v.pose for v in artifact.data.views if v.registered and v.pose is not None})


def _panoramas(ctx: StageContext, height: int) -> list[Panorama]:
    scene = ctx.scene
    out = []
    for view in ctx.track(scene.views, "loading panoramas"):
        rgb = read_rgb(scene.image_path(view), (height, 2 * height))
        out.append(Panorama(view.name, (rgb * 255.0 + 0.5).astype(np.uint8),
                            valid_mask(scene, view, height, 2 * height)))
    return out


def _working_height(scene: Scene, params: Params) -> int:
    heights = []
    for view in scene.views:
        size = image_size(scene.image_path(view))
        heights.append(size[0] if size else params.working_height)
    return min(params.working_height, *heights)


def run(ctx: StageContext) -> PosesOutput:
    scene, p = ctx.scene, ctx.params
    height = _working_height(scene, p)
    panoramas = _panoramas(ctx, height)
    views = scene.views
    pair = None
    if p.method == "upright-pair":
        if len(panoramas) != 2:
            raise PanoError(scene.root, f"poses.method=upright-pair places two panoramas, "
                                        f"the scene has {len(panoramas)}")
        result, pair = _upright_pair(panoramas)
    else:
        result = _colmap(panoramas, p)
    if len(result.cam_from_world) < 2:
        if result.verified_pairs == 0:
            raise PanoError(scene.root, f"no two of the {len(views)} panoramas share content that structure from "
                                        "motion can match; poses need overlapping panoramas (docs/poses.md)")
        raise PanoError(scene.root, f"structure from motion placed fewer than two panoramas "
                                    f"({result.verified_pairs} matched pairs); give poses in scene.json")
    registered = [v for v in views if v.name in result.cam_from_world]
    missing = [v.name for v in views if v.name not in result.cam_from_world]
    if missing:
        ctx.warn(f"structure from motion could not place {', '.join(missing)}: left out of the later stages")
    if sum(v.split == "train" for v in registered) < 2:
        raise PanoError(scene.root, f"structure from motion placed {len(registered)} panoramas, fewer than two of "
                                    f"them train views (unplaced: {', '.join(missing)})")

    cam_to_world = {name: np.linalg.inv(m) for name, m in result.cam_from_world.items()}
    known = {v.name: v.pose_matrix for v in registered if v.pose is not None}
    heights = {v.name: v.camera_height or p.default_camera_height for v in views}
    order = [v.name for v in views]
    try:
        alignment = (align_to_known(cam_to_world, known, result.points, heights, order) if known
                     else align_to_floor(cam_to_world, result.points, heights, order))
    except ValueError as e:
        raise PanoError(scene.root, f"cannot make the poses metric: {e}; give camera poses in scene.json") from None
    if not known and not any(v.camera_height for v in views):
        ctx.warn(f"no camera_height in scene.json: the scale assumes {p.default_camera_height:g} m for every camera")
    transform = alignment.transform

    out_views = []
    for view in views:
        if view.name not in cam_to_world:
            out_views.append(ViewPose(view=view.name, registered=False))
            continue
        given = view.pose is not None
        pose = view.pose_matrix if given else transform.pose(cam_to_world[view.name])
        out_views.append(ViewPose(
            view=view.name, registered=True, pose=pose.tolist(), given=given,
            reprojection_error_px=result.reprojection_error[view.name],
            observations=result.observations[view.name],
            residual_m=alignment.residual_m.get(view.name), residual_deg=alignment.residual_deg.get(view.name)))

    points = transform.points(result.points)
    write_ply(ctx.out_dir / PLY_NAME, points, result.colors / 255.0, np.zeros_like(points))
    draw_cameras(ctx.out_dir / DRAWING_NAME, points, {v.view: np.asarray(v.pose) for v in out_views if v.registered})
    report = None
    if pair is not None:
        r = pair.residual_deg
        report = UprightPairReport(
            yaw_deg=float(np.degrees(pair.pose.theta)), direction_deg=float(np.degrees(pair.pose.phi)),
            putative_matches=pair.putative, guided_matches=pair.guided, inliers=pair.inliers,
            residual_median_deg=float(np.median(r)), residual_rms_deg=float(np.sqrt(np.mean(r**2))),
            score=pair.pose.score, runner_up=pair.pose.runner_up)
    return PosesOutput(
        method=p.method, upright_pair=report, working_height=height, views=out_views, frame=alignment.source,
        scale=transform.scale, scale_uncertainty=alignment.scale_uncertainty,
        floor_tilt_deg=alignment.floor_tilt_deg, points=len(points),
        mean_track_length=float(result.track_length.mean()) if len(points) else 0.0,
        verified_pairs=result.verified_pairs, sparse_points=PLY_NAME, drawing=DRAWING_NAME,
        timings_s=result.timings)


def _colmap(panoramas: list[Panorama], p: Params) -> Reconstruction:
    options = SfmOptions(method=p.method, max_features=p.max_features, min_matches=p.min_matches,
                         threads=p.threads or -1, seed=p.seed)
    with make_progress() as bar, tempfile.TemporaryDirectory(prefix="colmap-") as work:
        task = bar.add_task(f"structure from motion ({p.method})", total=len(SFM_STEPS))
        return reconstruct(panoramas, Path(work), options, progress=lambda step: bar.update(task, advance=1, step=step))


def _upright_pair(panoramas: list[Panorama]) -> tuple[Reconstruction, PairResult | None]:
    """The upright two-view solver's reconstruction, or an empty one (no verified pair) when it
    finds no distinct pose."""
    pair = relative_pose(*panoramas)
    if pair is None:
        return Reconstruction({}, {}, {}, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, int), 0), None
    return pair.reconstruction, pair


def draw_cameras(path: Path, points: np.ndarray, poses: dict[str, np.ndarray], dpi: int = 110) -> None:
    """cameras.png: the sparse points and the cameras (dot, forward arrow, name) seen from above
    (world x right, z up the page)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    if len(points):
        ax.scatter(points[:, 0], points[:, 2], s=1, c="0.55", linewidths=0)
    for name, pose in poses.items():
        x, z = pose[0, 3], pose[2, 3]
        forward = pose[[0, 2], 2]  # the panorama's centre column looks this way
        ax.plot(x, z, "o", color="tab:red", ms=5)
        ax.annotate("", (x + 0.4 * forward[0], z + 0.4 * forward[1]), (x, z),
                    arrowprops={"arrowstyle": "->", "lw": 0.8, "color": "tab:red"})
        ax.annotate(name, (x, z), textcoords="offset points", xytext=(4, 4), fontsize=8)
    centres = np.array([pose[[0, 2], 3] for pose in poses.values()])
    # frame the cameras with a margin, not the far outliers of the sparse cloud
    lo, hi = centres.min(axis=0) - 2.5, centres.max(axis=0) + 2.5
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world z (m)")
    ax.set_title(f"cameras over {len(points)} sparse points (from above)")
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
