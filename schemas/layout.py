"""Artifact of the `layout` stage: a metric room per view, in that view's camera frame."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

Point2 = tuple[float, float]


class LayoutAlignment(BaseModel):
    """How the panorama was turned into its room's Manhattan frame before the model ran."""

    rotation: list[list[float]] = Field(
        description="3x3, row-major: d_aligned = R d_view (the view's directions in the room's frame).")
    yaw_deg: float = Field(description="Turn about gravity, degrees.")
    tilt_deg: float = Field(description="Angle between the camera's down axis and gravity, degrees.")
    gravity: Literal["pose", "lines", "none"] = Field(
        description="Where gravity came from: the scene.json pose, vertical line segments, or neither "
        "(too few lines: the image's vertical was kept).")
    segments: int = Field(description="Line segments detected.")
    inliers: int = Field(description="Segments that agree with one of the frame's three axes.")


class ViewLayout(BaseModel):
    view: str
    source: Literal["model", "json", "txt", "npy"] = Field(description="Where the boundaries came from.")
    boundaries: str = Field(
        description="[2,W] float32 .npy at the image's width: ceiling and floor boundary latitudes (radians) "
        "of the fitted room (consistent with floor_polygon and the heights)."
    )
    confidence: str | None = Field(default=None, description="[W] float32 .npy per-column confidence in [0,1].")
    floor_polygon: list[Point2] = Field(
        description="Floor outline in the camera frame, (x, z) metres, counter-clockwise seen from above."
    )
    camera_height: float = Field(gt=0, description="Camera above the floor (m): floor plane at camera y = +h.")
    ceiling_distance: float = Field(gt=0, description="Camera below the ceiling (m): ceiling at camera y = -d.")
    camera_height_assumed: bool = Field(description="True when 1.6 m was assumed (no height in scene.json).")
    # Added by the layout stage (optional for readers):
    split: Literal["train", "test"] = Field(default="train", description="The view's split in scene.json.")
    raw_boundaries: str | None = Field(
        default=None,
        description="[2,W'] float32 .npy: the boundaries as the source gave them (model: W'=1024; .npy: its "
        "width); None for corner formats (.json/.txt), whose room is exactly the given corners.",
    )
    alignment: LayoutAlignment | None = Field(
        default=None,
        description="Model views with layout.align on: the rotation into the room's frame. The model ran on "
        "the turned panorama; boundaries, raw_boundaries and confidence are turned back to the view's own "
        "image, floor_polygon holds the floor corners' (x, z) in the view's own frame (for a tilted camera "
        "the floor is then only approximately at y = +camera_height there).",
    )
    method: str = Field(
        default="corners",
        description="How the polygon was made: corners (given), manhattan, cuboid, atlanta, or raw "
        "(fallback: the per-column outline).",
    )


class PoseRescale(BaseModel):
    """The metric scale the layout stage measured for poses the poses stage left without one
    (its scale_source none): the later stages see those poses' positions scaled by it."""

    scale: float = Field(gt=0, description="Metres per unit of the poses (layoutnet.pose_scale).")
    uncertainty: float = Field(ge=0, description="Its relative standard uncertainty.")
    anchor: list[float] = Field(description="The point the positions are scaled about (world): the given "
                                            "view's centre, else the origin (the first view).")
    views: list[str] = Field(description="The views whose recovered poses are scaled.")
    votes: int = Field(description="Sparse points whose wall-distance ratio agrees with the scale.")
    points: int = Field(description="Sparse points that voted.")


class LayoutOutput(BaseModel):
    views: list[ViewLayout]
    poses_rescale: PoseRescale | None = Field(
        default=None, description="Set when the poses had no metric scale and the rooms measured it.")
    model: str | None = Field(default=None, description="The ONNX model used, if any.")
    model_name: str | None = Field(
        default=None, description="The known model (pano-pipe models list) that file is, if it is one.")

    def view(self, name: str) -> ViewLayout:
        return next(v for v in self.views if v.view == name)

    def train_views(self) -> list[ViewLayout]:
        """The layouts of training views: what the union of floor plans should use."""
        return [v for v in self.views if v.split == "train"]
