"""A view's metric room, from a supplied layout or from the layout model: the room (floor polygon
in the view's camera frame, camera height, ceiling distance), its boundaries as the view's image
sees them, the source's own boundaries and a per-column confidence. The layout stage is glue over
this module; the walls are fitted by `postprocess.layout_from_boundaries` with the stage's
`mode`, `wall_source`, `peak_r` and `peak_min` (required keywords here: their defaults are the
stage's)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from layoutnet import postprocess as pp
from layoutnet.alignment import Alignment
from layoutnet.formats import SuppliedLayout
from layoutnet.inference import INPUT_SHAPE

MODEL_HEIGHT, MODEL_WIDTH = INPUT_SHAPE[2:]  # the layout model's contract (HorizonNet's size)


@dataclass
class ViewRoom:
    """A room in the view's own frame, with what the layout stage writes beside it."""

    room: pp.RoomLayout
    boundaries: np.ndarray  # [2,width] the fitted room in the view's image
    raw: np.ndarray | None  # the source's own boundaries in the view's image; None for corner files
    confidence: np.ndarray  # [width]
    alignment: Alignment | None = None


def _confidence(room: pp.RoomLayout, raw: np.ndarray | None, width: int) -> np.ndarray:
    """Per column, how well the fitted room follows the source's boundaries (1 without them)."""
    if raw is None:
        return np.ones(width)
    conf = pp.column_confidence(raw, pp.polygon_to_boundaries(
        room.polygon, room.camera_height, room.ceiling_distance, raw.shape[1]))
    return pp.resample_boundaries(conf[None].astype(np.float64), width)[0]


def room_from_supplied(sup: SuppliedLayout, camera_height: float, width: int, **wall_fit) -> ViewRoom:
    """A supplied layout: [2,W] boundaries are fitted with walls; corner files are used as given (the
    ceiling from the file, else from each corner's floor and ceiling points)."""
    if sup.boundaries is not None:
        room = pp.layout_from_boundaries(sup.boundaries, camera_height, **wall_fit)
    else:
        c = sup.corners
        if sup.ceiling_ratio is not None:
            ceiling = sup.ceiling_ratio * camera_height
        else:  # each corner's floor point fixes its distance, its ceiling point then the ceiling
            ceiling = pp.mean_percentile(camera_height * np.tan(c[:, 1]) / np.tan(-c[:, 2]))
        poly = pp.corners_to_polygon(c[:, 0], c[:, 1], c[:, 2], camera_height, ceiling)
        room = pp.RoomLayout(poly, camera_height, float(ceiling), "corners")
    fitted = pp.polygon_to_boundaries(room.polygon, room.camera_height, room.ceiling_distance, width)
    return ViewRoom(room, fitted, sup.boundaries, _confidence(room, sup.boundaries, width))


def _model_input(rgb: np.ndarray) -> np.ndarray:
    interpolation = cv2.INTER_AREA if rgb.shape[0] > MODEL_HEIGHT else cv2.INTER_LINEAR
    return cv2.resize(rgb, (MODEL_WIDTH, MODEL_HEIGHT), interpolation=interpolation)


def _predict(model, small: np.ndarray, camera_height: float, tta: bool, wall_fit: dict):
    bounds, cor = model.predict(small, tta=tta)
    return pp.layout_from_boundaries(bounds, camera_height, cor=cor, **wall_fit), bounds


def room_from_model(model, rgb: np.ndarray, camera_height: float, width: int, *, align: str,
                    max_tilt_deg: float, tta: bool, down: np.ndarray | None = None, **wall_fit) -> ViewRoom:
    """The model on the panorama ([H,W,3] in [0,1], 2:1) turned into its room's Manhattan frame
    (`align`: auto, lines or off; layoutnet.alignment), the room turned back into the view's frame
    (`alignment.room_in_view`). `down`: gravity in the view's frame when the pose gives it
    (align=auto)."""
    from layoutnet.alignment import MIN_APPLIED_DEG, estimate_alignment, room_in_view
    from panogeom.rotate import rotate_equirect

    small = _model_input(rgb)
    alignment = None
    if align != "off":
        alignment = estimate_alignment(small, down=down if align == "auto" else None, max_tilt_deg=max_tilt_deg)
        if alignment.angle_deg < MIN_APPLIED_DEG:
            alignment.rotation = np.eye(3)
    if alignment is None or alignment.angle_deg == 0.0:
        room, raw = _predict(model, small, camera_height, tta, wall_fit)
        fitted = pp.polygon_to_boundaries(room.polygon, room.camera_height, room.ceiling_distance, width)
        room.notes += alignment.notes if alignment else []
        return ViewRoom(room, fitted, raw, _confidence(room, raw, width), alignment)
    room, raw = _predict(model, rotate_equirect(small, alignment.rotation), camera_height, tta, wall_fit)
    view_room, fitted, raw_view, conf = room_in_view(room, raw, alignment.rotation, width)
    view_room.notes += alignment.notes
    return ViewRoom(view_room, fitted, raw_view, conf, alignment)
