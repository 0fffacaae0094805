"""poses: camera-to-world poses recovered from the panoramas themselves (structure from motion).

A scene calls for it when some view has no pose in scene.json. By default
(method auto) the upright N-view solver (sfm.upright_global) places levelled
panoramas, and pycolmap (sfm.reconstruct) is run where it leaves views out;
the artifact says which method was taken and why. The reconstruction is turned
upright and metric (sfm.frame): gravity from the cameras' mean down axis, scale
from the camera heights over the floor plane under them, or the frame of the
views that have poses. Downstream stages see the scene with the recovered
poses filled in (StageSpec.completes_scene); views SfM could not place are left
out of it. See docs/poses.md.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from panogeom.images import read_rgb
from runtime.console import console, make_progress
from runfs.errors import PanoError
from runfs.limits import image_size
from schemas.scene_loader import valid_mask
from runtime.stage import Loaded, StageContext
from schemas.poses import Attempt, PairRecord, PairSearch, PosesOutput, UprightPairReport, ViewPose
from schemas.scene import MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT, Scene
from schemas.stage_params import StageParams
from sfm.floor_boundary import floor_cue
from sfm.frame import FLOOR_WALL_BOUNDARY, NO_SCALE, Alignment, align_to_floor, align_to_known
from sfm.records import STEPS as SFM_STEPS
from sfm.records import Panorama, Reconstruction, SfmOptions
from sfm.upright_global import GlobalResult, UprightGlobalOptions
from sfm.upright_global import solve as solve_upright
from sfm.upright_pair import CAMERA_FIXED_MIN, PairResult, SearchLog, UprightPairOptions, relative_pose
from stages.cloud_io import write_ply

Output = PosesOutput

PLY_NAME = "points.ply"
#: The sparse points (world frame) and which view observes which: what a later stage needs to
#: measure the scale the poses stage could not (the layout stage, stages/layout.py).
OBSERVATIONS_NAME = "observations.npz"
DRAWING_NAME = "cameras.png"


Method = Literal["auto", "upright", "equirect", "rig", "upright-pair"]

#: Working heights when poses.working_height is not set: the upright solver needs the detail of
#: 1024 rows on real pairs metres apart (docs/poses.md); COLMAP's methods are tuned at 512.
DEFAULT_HEIGHT = {"upright": 1024, "upright-pair": 1024, "equirect": 512, "rig": 512}


class Params(StageParams):
    method: Method = Field(
        default="auto", description="auto: the upright solver, COLMAP (equirect) where it places fewer views; "
                                    "upright: N levelled panoramas, pairs solved with the camera's gravity; "
                                    "equirect: COLMAP on the panoramas (EQUIRECTANGULAR camera); rig: COLMAP on "
                                    "perspective views of each (more points, 8x slower); upright-pair: exactly "
                                    "two levelled panoramas; docs/poses.md.")
    working_height: int | None = Field(
        default=None, ge=64, le=4096, json_schema_extra={"pixels": "panorama_height"},
        description="Panoramas are resampled to this height (never up); default 1024 for the upright solvers, "
                    "512 for COLMAP.")
    max_features: int = Field(default=SfmOptions.max_features, ge=100,
                              description="SIFT features per image at most (COLMAP).")
    min_matches: int = Field(default=SfmOptions.min_matches, ge=5,
                             description="Verified matches a pair of images needs to count (COLMAP).")
    default_camera_height: float = Field(
        default=1.6, ge=MIN_CAMERA_HEIGHT, le=MAX_CAMERA_HEIGHT,
        description="Camera height (m) for views without camera_height in scene.json: it sets the metric scale "
                    "when no view has a pose.")
    threads: int | None = Field(default=None, ge=1,
                                description="CPU threads for COLMAP and the upright solver (default: all).")
    seed: int = Field(default=0, ge=0, le=2**31 - 1,
                      description="Random seed of COLMAP (RANSAC, mapping), the upright solver and the floor fit.")


def skip_reason(scene: Scene, params: Params) -> str | None:
    if not scene.manifest.unposed_views():
        return "every view has a pose in scene.json"
    return None


def run_reason(scene: Scene, params: Params) -> str:
    """Why a scene calls for the stage (skip_reason says when it does not)."""
    n = len(scene.manifest.unposed_views())
    return f"{n} of {len(scene.views)} views have no pose in scene.json"


def complete_scene(scene: Scene, artifact: Loaded) -> Scene:
    """The scene with the recovered poses filled in, unregistered views left out, and the camera
    heights over the fitted floor given to the views scene.json gives none (one source of truth:
    the layout stage then uses the heights the poses were made metric with, issue 36)."""
    placed = [v for v in artifact.data.views if v.registered and v.pose is not None]
    return scene.with_poses({v.view: v.pose for v in placed},
                            {v.view: v.camera_height for v in placed if v.camera_height is not None})


def _panoramas(ctx: StageContext, height: int) -> list[Panorama]:
    scene = ctx.scene
    out = []
    for view in ctx.track(scene.views, f"loading panoramas ({height}x{2 * height})"):
        rgb = read_rgb(scene.image_path(view), (height, 2 * height))
        out.append(Panorama(view.name, (rgb * 255.0 + 0.5).astype(np.uint8),
                            valid_mask(scene, view, height, 2 * height)))
    return out


def _working_height(scene: Scene, params: Params, method: str) -> int:
    heights = []
    wanted = params.working_height or DEFAULT_HEIGHT[method]
    for view in scene.views:
        size = image_size(scene.image_path(view))
        heights.append(size[0] if size else wanted)
    return min(wanted, *heights)


@dataclass
class _Solved:
    """One method's result, made upright and metric."""

    method: str
    height: int
    result: Reconstruction
    alignment: Alignment | None = None
    failure: str | None = None
    seconds: float = 0.0
    pair: PairResult | None = None
    solve: GlobalResult | None = None
    #: the upright solvers: which pair searches ran (the fast one, the exhaustive fallback)
    search: SearchLog | None = None

    @property
    def placed(self) -> int:
        return len(self.result.cam_from_world) if self.failure is None else 0


class PosesFailure(Exception):
    """A method could not place the scene (the message says why, without the file)."""


def run(ctx: StageContext) -> PosesOutput:
    scene, p = ctx.scene, ctx.params
    views = scene.views
    if len(views) < 2:  # structure from motion places panoramas relative to each other
        raise PanoError(scene.root / "scene.json", f"the scene has {len(views)} panorama and no pose for it; "
                                                   "recovering poses needs at least two overlapping panoramas "
                                                   "(or give the pose in scene.json)")
    if p.method == "upright-pair" and len(views) != 2:
        raise PanoError(scene.root, f"poses.method=upright-pair places two panoramas, the scene has {len(views)}; "
                                    "poses.method=upright places any number")
    loaded: dict[int, list[Panorama]] = {}

    def attempt(method: str) -> _Solved:
        height = _working_height(scene, p, method)
        if height not in loaded:
            loaded[height] = _panoramas(ctx, height)
        t0 = time.perf_counter()
        solved = _solve(method, loaded[height], p, height)
        if solved.search is not None and solved.search.exhaustive:  # say which pair search ran (issue 36)
            from rich.markup import escape

            console.print(escape(f"{method}: {solved.search.describe()}"), soft_wrap=True, highlight=False)
        if solved.failure is None:
            try:
                solved.alignment = _align(ctx, solved.result, p, method, loaded[height])
            except PosesFailure as e:
                solved.failure = str(e)
        solved.seconds = time.perf_counter() - t0
        return solved

    if p.method == "auto":
        chosen, attempts, reason = _auto(attempt, len(views))
    else:
        chosen = attempt(p.method)
        attempts, reason = [chosen], "asked for (poses.method)"
    if chosen.failure is not None:
        raise PanoError(scene.root,
                        _camera_fixed_hint(scene, attempts) + _failure_message(attempts, p.method, len(views)))
    return _output(ctx, chosen, attempts, reason)


def _auto(attempt: Callable[[str], _Solved], n: int) -> tuple[_Solved, list[_Solved], str]:
    """The upright solver first (levelled 360° cameras, wide baselines); COLMAP's incremental
    mapper where the upright solver left views out, failed or found no metric scale; the result
    placing more views, and on a tie the one with a metric scale, then the upright one (its
    residual is the smaller on levelled cameras). An upright result without a metric scale needs
    a pair COLMAP can verify: between panoramas of different rooms the upright pair search can
    return a confident pose, which the missing floor used to give away (docs/poses.md)."""
    upright = attempt("upright")
    scaled = upright.alignment is not None and upright.alignment.scale_source != NO_SCALE
    if upright.failure is None and upright.placed == n and scaled:
        return upright, [upright], f"the upright solver placed all {n} views"
    colmap = attempt("equirect")
    attempts = [upright, colmap]
    if upright.failure is None and not scaled and colmap.result.verified_pairs == 0:
        upright.failure = "no metric scale, and no pair of panoramas that COLMAP verifies confirms its pairs"
    ok = [s for s in attempts if s.failure is None]
    if not ok:
        return upright, attempts, ""
    best = max(ok, key=lambda s: (s.placed, s.alignment.scale_source != NO_SCALE, s.method == "upright"))
    other = colmap if best is upright else upright
    why = other.failure or f"it placed {other.placed} of {n}"
    return best, attempts, (f"{best.method} placed {best.placed} of {n} views; {other.method}: {why}")


def _failure_message(attempts: list[_Solved], method: str, n: int) -> str:
    """One line: why no method placed the views, and which method might."""
    # COLMAP's verification is the stricter (the upright pair search can return a confident pose for
    # panoramas of different rooms, docs/poses.md): where it ran, it says whether anything is shared
    judges = [s for s in attempts if s.method in ("equirect", "rig")] or attempts
    verified = max(s.result.verified_pairs for s in judges)
    if verified == 0:
        text = (f"no two of the {n} panoramas share content that structure from motion can match; poses need "
                "overlapping panoramas (docs/poses.md)")
    elif len(attempts) == 1:
        text = f"poses.method={method} could not place the panoramas: {attempts[0].failure}"
    else:
        text = "; ".join(f"{s.method}: {s.failure}" for s in attempts)
        text = f"no method placed the panoramas ({text})"
    # the method not tried that likely works: COLMAP finds nothing between levelled panoramas metres
    # apart (zind_pair), the upright solver nothing between tilted ones
    hint = {"equirect": "upright (levelled panoramas far apart)", "rig": "upright (levelled panoramas far apart)",
            "upright": "equirect (panoramas not levelled)", "upright-pair": "equirect (panoramas not levelled)"}
    if method in hint:
        text += f"; try --set poses.method={hint[method]}"
    if verified > 0:
        text += ("; or " if method in hint else "; ") + "give poses in scene.json"
    return text


def _solve(method: str, panoramas: list[Panorama], p: Params, height: int) -> _Solved:
    threads = p.threads or os.cpu_count() or 1
    log = SearchLog()
    if method == "upright-pair":
        pair = relative_pose(*panoramas, UprightPairOptions(log=log))
        if pair is None:
            return _Solved(method, height, _empty(0), failure="no distinct upright pose between the two panoramas",
                           search=log)
        return _Solved(method, height, pair.reconstruction, pair=pair, search=log)
    if method == "upright":
        options = UprightGlobalOptions(seed=p.seed, threads=threads, pair=UprightPairOptions(log=log))
        with make_progress() as bar:
            tasks: dict[str, int] = {}

            def progress(step: str, done: int, total: int) -> None:
                if step not in tasks:
                    tasks[step] = bar.add_task(f"upright solver: {step}", total=total)
                bar.update(tasks[step], completed=done)

            try:
                solved = solve_upright(panoramas, options, progress=progress)
            except np.linalg.LinAlgError as e:  # a degenerate graph: a failure of the method, not of the run
                return _Solved(method, height, _empty(0), failure=f"the global solve is degenerate ({e})", search=log)
        out = _Solved(method, height, solved.reconstruction, solve=solved, search=log)
        if len(solved.reconstruction.cam_from_world) < 2:
            out.failure = ("no verified pair of panoramas" if solved.reconstruction.verified_pairs == 0 else
                           "its pairs do not agree on one placement")
        return out
    result = _colmap(panoramas, p, method)
    out = _Solved(method, height, result)
    if len(result.cam_from_world) < 2:
        out.failure = (f"COLMAP placed fewer than two panoramas ({result.verified_pairs} matched pairs)"
                       if result.verified_pairs else "no matched pair of panoramas")
    return out


#: The upright solver's cloud is dense at the cameras' height (the rig's horizon views): its floor
#: is looked for only among points seen this far below the horizon (sfm.frame.fit_floor).
FLOOR_DEPRESSION_DEG = {"upright": 15.0, "upright-pair": 0.0, "equirect": 0.0, "rig": 0.0}


def _align(ctx: StageContext, result: Reconstruction, p: Params, method: str,
           panoramas: list[Panorama]) -> Alignment:
    """Upright and metric: the frame of the given poses, else the floor and camera heights: the
    floor plane among the sparse points, else the floor level the floor–wall boundaries show in
    the panoramas (sfm.floor_boundary), else none: the poses are kept up to scale."""
    views = ctx.scene.views
    registered = [v for v in views if v.name in result.cam_from_world]
    if sum(v.split == "train" for v in registered) < 2:
        missing = [v.name for v in views if v.name not in result.cam_from_world]
        raise PosesFailure(f"placed {len(registered)} panoramas, fewer than two of them train views "
                           f"(unplaced: {', '.join(missing)})")
    cam_to_world = {name: np.linalg.inv(m) for name, m in result.cam_from_world.items()}
    known = {v.name: v.pose_matrix for v in registered if v.pose is not None}
    heights = {v.name: v.camera_height or p.default_camera_height for v in views}
    order = [v.name for v in views]
    cues = [(FLOOR_WALL_BOUNDARY, floor_cue(panoramas, result.seen_by))]
    try:
        return (align_to_known(cam_to_world, known, result.points, heights, order, cues=cues, unscaled=True)
                if known else
                align_to_floor(cam_to_world, result.points, heights, order,
                               min_depression_deg=FLOOR_DEPRESSION_DEG[method], cues=cues, unscaled=True))
    except ValueError as e:
        raise PosesFailure(f"cannot make the poses metric: {e}") from None


def _output(ctx: StageContext, chosen: _Solved, attempts: list[_Solved], reason: str) -> PosesOutput:
    scene, p = ctx.scene, ctx.params
    views = scene.views
    result, alignment = chosen.result, chosen.alignment
    cam_to_world = {name: np.linalg.inv(m) for name, m in result.cam_from_world.items()}
    left_out = dict(chosen.solve.left_out) if chosen.solve is not None else {}
    for v in views:
        if v.name not in cam_to_world:
            left_out.setdefault(v.name, "not registered by COLMAP")
    if left_out:
        ctx.warn("could not place " + "; ".join(f"{k} ({why})" for k, why in left_out.items())
                 + ": left out of the later stages")
    if alignment.scale_source == NO_SCALE:
        ctx.warn("no metric scale: no floor plane among the sparse points and no floor–wall boundary in the "
                 "panoramas; the poses are kept up to scale (scale_source none; give camera poses or a scale "
                 "in scene.json, docs/poses.md)")
    elif alignment.source == "floor" and not any(v.camera_height for v in views):
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
            residual_m=alignment.residual_m.get(view.name), residual_deg=alignment.residual_deg.get(view.name),
            camera_height=_rounded(alignment.camera_heights.get(view.name))))

    points = transform.points(result.points)
    write_ply(ctx.out_dir / PLY_NAME, points, result.colors / 255.0, np.zeros_like(points))
    _write_observations(ctx.out_dir / OBSERVATIONS_NAME, points, result, [v.view for v in out_views if v.registered])
    draw_cameras(ctx.out_dir / DRAWING_NAME, points, {v.view: np.asarray(v.pose) for v in out_views if v.registered})
    report = residual = None
    pair = chosen.pair
    if pair is not None:
        r = pair.residual_deg
        residual = float(np.median(r))
        report = UprightPairReport(
            yaw_deg=float(np.degrees(pair.pose.theta)), direction_deg=float(np.degrees(pair.pose.phi)),
            putative_matches=pair.putative, guided_matches=pair.guided, inliers=pair.inliers,
            residual_median_deg=float(np.median(r)), residual_rms_deg=float(np.sqrt(np.mean(r**2))),
            score=pair.pose.score, runner_up=pair.pose.runner_up, search=pair.search)
    pairs = []
    if chosen.solve is not None:
        residual = chosen.solve.residual_deg
        pairs = [PairRecord(a=a, b=b, inliers=n, used=used) for a, b, n, used in chosen.solve.pairs]
    elif result.reprojection_error:  # COLMAP: pixels of the working panorama to degrees
        residual = float(np.median(list(result.reprojection_error.values()))) * 360.0 / (2 * chosen.height)
    return PosesOutput(
        method=chosen.method, requested_method=p.method, method_reason=reason,
        attempts=[Attempt(method=s.method, placed=s.placed, seconds=s.seconds, failure=s.failure,
                          pair_search=_pair_search(s.search)) for s in attempts],
        pairs=pairs, left_out=left_out, residual_deg=residual,
        upright_pair=report, working_height=chosen.height, views=out_views, frame=alignment.source,
        scale_source=alignment.scale_source, scale=transform.scale, scale_uncertainty=alignment.scale_uncertainty,
        floor_tilt_deg=alignment.floor_tilt_deg, points=len(points),
        mean_track_length=float(result.track_length.mean()) if len(points) else 0.0,
        verified_pairs=result.verified_pairs, sparse_points=PLY_NAME, observations=OBSERVATIONS_NAME,
        drawing=DRAWING_NAME,
        timings_s={**result.timings, "total": chosen.seconds})


def _write_observations(path: Path, points: np.ndarray, result: Reconstruction, views: list[str]) -> None:
    """The observations file: `points` [N,3] (world), `views` [V] names, and per observation its
    `view` and `point` indices; where the solve records none (the two-view solver) every view sees
    every point."""
    every = np.arange(len(points))
    seen = [np.asarray(result.seen_by.get(v, every) if result.seen_by else every, int) for v in views]
    np.savez_compressed(path, points=points.astype(np.float32), views=np.array(views),
                        view=np.repeat(np.arange(len(views)), [len(s) for s in seen]).astype(np.int32),
                        point=(np.concatenate(seen) if seen else np.zeros(0, int)).astype(np.int32))


def read_observations(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The points of an observations file and, per view, the points it observes."""
    with np.load(path) as f:
        views, view, point = [str(v) for v in f["views"]], f["view"], f["point"]
        points = f["points"].astype(np.float64)
    return points, {name: points[point[view == k]] for k, name in enumerate(views)}


def _rounded(height: float | None) -> float | None:
    return None if height is None else round(float(height), 4)


def summary(data: PosesOutput) -> str:
    """What `run poses` prints: views placed, method (and why), scale, residual."""
    placed = sum(v.registered for v in data.views)
    text = (f"poses: {placed} of {len(data.views)} views placed by {data.method}"
            + (f" ({data.method_reason})" if data.requested_method == "auto" and data.method_reason else "")
            + f"; {data.scale_text()}")
    if data.residual_deg is not None:
        text += f"; median residual {data.residual_deg:.3f}°"
    if data.left_out:
        text += "; left out: " + ", ".join(f"{k} ({why})" for k, why in data.left_out.items())
    search = next((a.pair_search for a in data.attempts if a.method == data.method and a.pair_search), None)
    if search is not None and search.exhaustive:  # the fast pair search found nothing convincing somewhere
        text += f"; pair search: {search.text}"
    return text


def _pair_search(log: SearchLog | None) -> PairSearch | None:
    if log is None or not log.pairs:
        return None
    return PairSearch(pairs=log.pairs, fast=log.fast, exhaustive=log.exhaustive, recovered=log.recovered,
                      exhaustive_seconds=round(log.exhaustive_seconds, 2), camera_fixed_matches=log.camera_fixed,
                      text=log.describe())


def _camera_fixed_hint(scene: Scene, attempts: list[_Solved]) -> str:
    """Where the upright pair search matched something travelling with the camera (a tripod or hand
    no mask removes: it sits at one bearing in every panorama and outvotes the room), say so."""
    if not any(s.search is not None and s.search.camera_fixed >= CAMERA_FIXED_MIN for s in attempts):
        return ""
    nadir = scene.manifest.nadir_mask_deg
    what = f"a nadir_mask_deg larger than {nadir:g}" if nadir > 0 else "nadir_mask_deg (35 for a tripod)"
    return (f"something at the bottom of the panoramas moves with the camera (a tripod or a hand?) and matches "
            f"itself: set {what} in scene.json and run again; ")


def _empty(verified_pairs: int) -> Reconstruction:
    return Reconstruction({}, {}, {}, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, int), verified_pairs)


def _colmap(panoramas: list[Panorama], p: Params, method: str) -> Reconstruction:
    from sfm.reconstruct import reconstruct  # pycolmap: loaded only where structure from motion runs

    options = SfmOptions(method=method, max_features=p.max_features, min_matches=p.min_matches,
                         threads=p.threads or -1, seed=p.seed)
    with make_progress() as bar, tempfile.TemporaryDirectory(prefix="colmap-") as work:
        task = bar.add_task(f"structure from motion ({method})", total=len(SFM_STEPS))
        return reconstruct(panoramas, Path(work), options, progress=lambda step: bar.update(task, advance=1, step=step))


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
