"""The scene manifest, `scene.json` (DESIGN.md, "A scene folder")."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, field_validator, model_validator

from runfs.paths import safe_relative, safe_stem, scene_file

#: A number in scene.json: an int or a float, finite (the models refuse NaN and Inf), never a
#: boolean (pydantic would read `true` as 1.0) or a string.
Real = Annotated[float, Strict()]
Matrix4 = list[list[Real]]

#: Bounds that catch unit mistakes (millimetres for metres, kilometres for metres) and overflow
#: or underflow before any geometry runs.
MAX_CAMERA_HEIGHT = 100.0
MIN_CAMERA_HEIGHT = 0.05
MAX_TRANSLATION = 1e5

LAYOUT_SUFFIXES = (".json", ".txt", ".npy")
DEPTH_SUFFIXES = (".png", ".npy")


class View(BaseModel):
    """One panorama: its image, camera-to-world pose and split."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = Field(min_length=1, description="Unique view name, also the stem of its files.")
    image: str = Field(description="Equirectangular image (2:1), relative to the scene folder.")
    pose: Matrix4 | None = Field(
        default=None, description="Camera-to-world 4x4, row-major, metres; OpenCV axes, y down. Left out, "
                                  "the poses stage recovers it from the panoramas.")
    split: Literal["train", "test"] = "train"
    camera_height: Real | None = Field(
        default=None, ge=MIN_CAMERA_HEIGHT, le=MAX_CAMERA_HEIGHT, description="Camera height above the floor in metres, where known."
    )
    layout: str | None = Field(
        default=None, description="Supplied layout boundaries (.json HorizonNet, .txt corners, .npy [2,W])."
    )
    depth: str | None = Field(
        default=None, description="Supplied depth (distance along the ray): .png uint16 mm or .npy metres."
    )
    gt_depth: str | None = Field(
        default=None, description="Ground-truth depth (.png uint16 mm or .npy metres, as `depth`) for evaluation only; "
                                  "never used to train."
    )
    mask: str | None = Field(
        default=None, description="Valid-pixel mask (.png, non-zero = valid; resized to any working size); "
                                  "found as masks/<view>.png when not named.")

    @field_validator("name")
    @classmethod
    def _safe_name(cls, name: str) -> str:
        return safe_stem(name)

    @field_validator("image", "layout", "depth", "gt_depth", "mask")
    @classmethod
    def _inside_scene(cls, rel: str | None) -> str | None:
        return None if rel is None else safe_relative(rel)

    @field_validator("pose")
    @classmethod
    def _rigid(cls, pose: Matrix4 | None) -> Matrix4 | None:
        if pose is None:
            return None
        m = np.asarray(pose, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"must be 4x4, got shape {list(m.shape)}")
        if not np.all(np.isfinite(m)):
            raise ValueError("contains NaN or Inf")
        if np.abs(m[:3, 3]).max() > MAX_TRANSLATION:
            raise ValueError(f"translation {m[:3, 3].tolist()} is over {MAX_TRANSLATION:g} m; poses are in metres")
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError(f"last row must be [0, 0, 0, 1], got {m[3].tolist()}")
        r = m[:3, :3]
        err = float(np.abs(r.T @ r - np.eye(3)).max())
        if err > 1e-4 or np.linalg.det(r) < 0:
            raise ValueError(f"not a rigid transform (|R^T R - I| = {err:.2g}, det R = {np.linalg.det(r):.3g})")
        return pose

    @property
    def pose_matrix(self) -> np.ndarray:
        if self.pose is None:
            raise ValueError(f"view {self.name!r} has no pose: the poses stage recovers it (pano-pipe run poses)")
        return np.asarray(self.pose, dtype=np.float64)

    @property
    def viewmat(self) -> np.ndarray:
        """World-to-camera 4x4."""
        return np.linalg.inv(self.pose_matrix)

    @property
    def position(self) -> np.ndarray:
        return self.pose_matrix[:3, 3].copy()


#: The nadir cap for real captures: a tripod with a levelling base (ZInD's) reaches ~32° from the
#: nadir, a hand-held pole or a bare tripod less. Checked on ../shared/data/zind_pair by
#: tests/masks/test_real_captures.py; the importers write it, synthetic scenes keep 0.
REAL_CAPTURE_NADIR_DEG = 35.0


class SceneManifest(BaseModel):
    """`scene.json`: the list of views. Paths are relative to the scene folder."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str | None = Field(default=None, description="Scene name; defaults to the folder name.")
    views: list[View] = Field(min_length=1)
    floor_plan: str | None = Field(
        default=None, description="Ground-truth floor plan JSON (simulator), for evaluation only."
    )
    nadir_mask_deg: Real = Field(
        default=0.0, ge=0.0, le=90.0,  # REAL_CAPTURE_NADIR_DEG is the value for captured panoramas
        description="A cap of this angular radius around every view's nadir (tripod, hand) is left out of "
                    "training, depth back-projection and metrics; 0 = off.")

    @field_validator("name")
    @classmethod
    def _safe_name(cls, name: str | None) -> str | None:
        return None if name is None else safe_stem(name)

    @field_validator("floor_plan")
    @classmethod
    def _inside_scene(cls, rel: str | None) -> str | None:
        return None if rel is None else safe_relative(rel)

    @model_validator(mode="after")
    def _unique_and_trainable(self) -> SceneManifest:
        seen: set[str] = set()
        for v in self.views:
            if v.name in seen:
                raise ValueError(f"duplicate view name {v.name!r}")
            seen.add(v.name)
        if not any(v.split == "train" for v in self.views):
            raise ValueError("the train split is empty: at least one view needs split 'train'")
        return self

    def train_views(self) -> list[View]:
        return [v for v in self.views if v.split == "train"]

    def test_views(self) -> list[View]:
        return [v for v in self.views if v.split == "test"]

    def unposed_views(self) -> list[View]:
        return [v for v in self.views if v.pose is None]

    def view(self, name: str) -> View:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(name)


class Scene(BaseModel):
    """A validated scene: its folder and manifest, with supplied files resolved."""

    model_config = ConfigDict(arbitrary_types_allowed=True)

    root: Path
    manifest: SceneManifest

    @property
    def name(self) -> str:
        return self.manifest.name or self.root.resolve().name

    @property
    def views(self) -> list[View]:
        return self.manifest.views

    # Every path below goes through runfs.paths.scene_file: it refuses what resolves
    # outside the scene folder ('..', absolute paths, symlinks pointing out).
    def path(self, rel: str, named_by: str | None = None) -> Path:
        return scene_file(self.root, rel, named_by)

    def with_poses(self, poses: dict[str, Matrix4], heights: dict[str, float] | None = None) -> Scene:
        """This scene with the missing poses filled in from `poses` (view name -> camera-to-world)
        and the missing camera heights from `heights`; a pose or height the manifest gives is kept,
        and a view left without a pose is left out."""
        heights = heights or {}

        def completed(v):
            update = {}
            if v.pose is None and v.name in poses:
                update["pose"] = poses[v.name]
            if v.camera_height is None and v.name in heights:
                update["camera_height"] = heights[v.name]
            return v.model_copy(update=update) if update else v

        views = [completed(v) for v in self.manifest.views]
        manifest = self.manifest.model_copy(update={"views": [v for v in views if v.pose is not None]})
        return Scene(root=self.root, manifest=manifest)

    def with_scaled_positions(self, views: list[str], scale: float, anchor: list[float]) -> Scene:
        """This scene with the camera positions of `views` moved `scale` times as far from `anchor`:
        poses recovered up to scale, made metric by a later stage (stages/layout.py)."""
        names, centre = set(views), np.asarray(anchor, dtype=np.float64)

        def scaled(v):
            if v.name not in names or v.pose is None:
                return v
            pose = np.array(v.pose, dtype=np.float64)
            pose[:3, 3] = centre + scale * (pose[:3, 3] - centre)
            return v.model_copy(update={"pose": pose.tolist()})

        manifest = self.manifest.model_copy(update={"views": [scaled(v) for v in self.manifest.views]})
        return Scene(root=self.root, manifest=manifest)

    def image_path(self, view: View) -> Path:
        return self.path(view.image, f"view {view.name!r} image")

    def layout_path(self, view: View) -> Path | None:
        """The supplied layout file: named in the manifest, else found as layout/<view>.{json,txt,npy}."""
        if view.layout:
            return self.path(view.layout, f"view {view.name!r} layout")
        return self._first_existing("layout", view.name, LAYOUT_SUFFIXES)

    def depth_path(self, view: View) -> Path | None:
        if view.depth:
            return self.path(view.depth, f"view {view.name!r} depth")
        return self._first_existing("depth", view.name, DEPTH_SUFFIXES)

    def mask_path(self, view: View) -> Path | None:
        """The view's mask file: named in the manifest, else found as masks/<view>.png."""
        if view.mask:
            return self.path(view.mask, f"view {view.name!r} mask")
        return self._first_existing("masks", view.name, (".png",))

    def gt_depth_path(self, view: View) -> Path | None:
        return self.path(view.gt_depth, f"view {view.name!r} gt_depth") if view.gt_depth else None

    def _first_existing(self, folder: str, stem: str, suffixes: tuple[str, ...]) -> Path | None:
        for s in suffixes:
            p = self.root / folder / f"{stem}{s}"
            if p.is_file():
                return self.path(f"{folder}/{stem}{s}")
        return None
