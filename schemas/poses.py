"""Artifact of the `poses` stage: camera-to-world poses recovered from the panoramas (SfM)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

Matrix4 = list[list[float]]


class ViewPose(BaseModel):
    view: str
    registered: bool = Field(description="False when SfM could not place the view; it is then left out downstream.")
    pose: Matrix4 | None = Field(default=None, description="Camera-to-world 4x4 in the world of DESIGN.md (metres).")
    given: bool = Field(default=False, description="True when scene.json gave the pose (it is kept as given).")
    reprojection_error_px: float | None = Field(
        default=None, description="Mean reprojection error of the view's observations, pixels of the working panorama.")
    observations: int = Field(default=0, description="Sparse points the view observes.")
    residual_m: float | None = Field(
        default=None, description="Given poses: distance between the fitted and the given camera centre (m).")
    residual_deg: float | None = Field(
        default=None, description="Given poses: angle between the fitted and the given orientation (degrees).")
    camera_height: float | None = Field(
        default=None, description="The camera's height over the floor the stage fitted (m; None: no floor was "
                                  "fitted). Views without camera_height in scene.json take it downstream.")


class UprightPairReport(BaseModel):
    """The upright-prior two-view solver (sfm.upright_pair), when it placed the views."""

    yaw_deg: float = Field(description="Second view's yaw relative to the first about gravity.")
    direction_deg: float = Field(description="Azimuth of the second view's centre seen from the first.")
    putative_matches: int = Field(description="SIFT matches after the ratio test, one per 2° cell.")
    guided_matches: int = Field(description="Matches found near the epipolar planes of the coarse pose.")
    inliers: int = Field(description="Guided matches within the fine tolerance (0.3°) of the pose.")
    residual_median_deg: float = Field(description="Median angular epipolar error of the inliers.")
    residual_rms_deg: float = Field(description="RMS angular epipolar error of the inliers.")
    score: float = Field(description="Coarse search score of the pose (truncated inlier count).")
    runner_up: float = Field(description="Best coarse score at least 5° away: how distinct the pose is.")
    search: Literal["peaks", "exhaustive", "exhaustive fallback"] = Field(
        default="peaks", description="The coarse search whose pose this is: the fast peak search, the exhaustive "
                                     "one, or the exhaustive one after the fast one found nothing convincing.")


class PairRecord(BaseModel):
    """A pair of panoramas the upright solver tried (sfm.upright_global)."""

    a: str
    b: str
    inliers: int = Field(description="Inlier matches of the verified pair pose; 0: not verified.")
    used: bool = Field(description="Kept by the global solve (its yaw and direction agree with the others).")


class PairSearch(BaseModel):
    """The upright solvers' (yaw, baseline direction) searches over their pairs (sfm.upright_pair)."""

    pairs: int = Field(description="Pairs searched.")
    fast: bool = Field(description="The fast peak search ran first (False: only the exhaustive one).")
    exhaustive: int = Field(description="Pairs the exhaustive search ran on after the fast one found nothing "
                                        "convincing (issue 36).")
    recovered: int = Field(description="Of those, pairs whose exhaustive pose was verified.")
    exhaustive_seconds: float = Field(description="Time spent in those exhaustive searches and their verification.")
    camera_fixed_matches: int = Field(
        description="Most matches of one pair at the same bearing in both panoramas, well below the horizon: "
                    "something travelling with the camera (tripod, hand) that no mask removed.")
    text: str = Field(description="The same in words.")


class Attempt(BaseModel):
    """One method the stage ran (method auto may run several)."""

    method: Literal["rig", "equirect", "upright", "upright-pair"]
    placed: int = Field(description="Views the method placed (0 when it failed).")
    seconds: float
    failure: str | None = Field(default=None, description="Why it failed or was not taken.")
    pair_search: PairSearch | None = Field(default=None, description="Upright solvers: which pair searches ran.")


class PosesOutput(BaseModel):
    method: Literal["rig", "equirect", "upright", "upright-pair"] = Field(
        description="What placed the views: COLMAP fed perspective views (rig) or panoramas (equirect), the "
                    "upright N-view solver (upright) or two-view solver (upright-pair) (docs/poses.md).")
    requested_method: Literal["auto", "rig", "equirect", "upright", "upright-pair"] = Field(
        default="auto", description="poses.method as set; auto lets the stage choose.")
    method_reason: str = Field(default="", description="Why this method's result was taken.")
    attempts: list[Attempt] = Field(default_factory=list, description="Every method run, in order.")
    pairs: list[PairRecord] = Field(
        default_factory=list, description="Upright solver: the pairs tried, their inliers, which were kept.")
    left_out: dict[str, str] = Field(default_factory=dict, description="Views not placed -> why.")
    residual_deg: float | None = Field(
        default=None, description="Median angular error of the sparse points' observations (degrees).")
    upright_pair: UprightPairReport | None = Field(default=None, description="The upright-pair solver's figures.")
    working_height: int = Field(description="Panorama height (pixels) features were extracted at.")
    views: list[ViewPose]
    frame: Literal["floor", "known poses", "known pose and floor", "known pose", "gravity"] = Field(
        description="What fixed the world frame: the floor and camera heights, views with given poses (one "
                    "given view: its pose, and the floor for the scale), or only the cameras' gravity and the "
                    "first view (no metric scale: 'gravity', or 'known pose' with one given view).")
    scale_source: Literal["floor_plane", "floor_wall_boundary", "known_poses", "none"] = Field(
        default="floor_plane",
        description="Where the metric scale came from: a plane fitted to the sparse points under the cameras "
                    "(floor_plane), the floor level at which the floor–wall boundaries show in the panoramas "
                    "(floor_wall_boundary; a plain floor gives SfM no point), the views with given poses "
                    "(known_poses), or nothing (none: the poses are kept up to scale, in the SfM frame's unit; "
                    "docs/poses.md).")
    scale: float = Field(description="Metres per SfM unit (1 when scale_source is none: the SfM frame's unit).")
    scale_uncertainty: float | None = Field(
        description="Relative standard uncertainty of the scale (0.01 = 1 %); None when there is no scale.")
    floor_tilt_deg: float | None = Field(
        default=None, description="Angle between the fitted floor's normal and gravity (the cameras' mean down axis).")
    points: int = Field(description="Sparse points.")
    mean_track_length: float = Field(description="Mean number of panoramas observing a sparse point.")
    verified_pairs: int = Field(description="Pairs of panoramas with geometrically verified matches.")
    sparse_points: str = Field(description="points.ply: the sparse points in the world frame (metres), coloured.")
    observations: str | None = Field(
        default=None, description="observations.npz: the sparse points (world frame) and which view observes "
                                  "which (stages.poses.read_observations).")
    drawing: str = Field(description="cameras.png: cameras over the sparse points, seen from above.")
    timings_s: dict[str, float] = Field(default_factory=dict)

    def scale_text(self) -> str:
        """The scale in words, for the summary line and the report."""
        if self.scale_source == "none" or self.scale_uncertainty is None:
            return "no metric scale (scale_source none: the poses are up to scale)"
        return (f"scale {self.scale:.4g} m/unit ± {100 * self.scale_uncertainty:.2g} % "
                f"(scale_source {self.scale_source})")
