"""Structure from motion on a set of panoramas with pycolmap (COLMAP 4).

Two ways to feed panoramas to COLMAP (docs/poses.md compares them):

- ``rig``: each panorama resampled into perspective views (sfm.rig) that COLMAP
  reconstructs as a rig with fixed, known relative rotations; the rig's pose
  is the panorama's.
- ``equirect``: the panoramas themselves, with COLMAP's EQUIRECTANGULAR camera.

Either way the result is one camera-from-world pose per registered panorama in
COLMAP's arbitrary frame (scale, rotation and origin are fixed later by
sfm.frame) and the sparse points with their tracks counted in panoramas.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from runfs.fsutil import native_write
from sfm.records import Panorama, Reconstruction, SfmOptions
from sfm.rig import VirtualRig


def quiet_colmap() -> None:
    """Keep COLMAP's log (glog) off stderr: it logs every step, and errors such as "Stopping
    thread..." when interrupted; pano-pipe reports progress and failures itself, in one line."""
    pycolmap.logging.minloglevel = pycolmap.logging.Level.FATAL.value
    pycolmap.logging.stderrthreshold = pycolmap.logging.Level.FATAL.value
    pycolmap.logging.alsologtostderr = False


def reconstruct(panoramas: Sequence[Panorama], work_dir: Path, options: SfmOptions,
                progress: Callable[[str], None] = lambda step: None) -> Reconstruction:
    """Run SfM on `panoramas` (all of one size) with its files in `work_dir`. Fewer than two
    registered panoramas come back as an empty Reconstruction that still counts the verified pairs."""
    quiet_colmap()
    pycolmap.set_random_seed(options.seed)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    database.unlink(missing_ok=True)
    timings: dict[str, float] = {}
    feed = _RigFeed(panoramas) if options.method == "rig" else _EquirectFeed(panoramas)

    t0 = time.perf_counter()
    feed.write(work_dir / "images", work_dir / "masks")
    timings["views"] = time.perf_counter() - t0
    progress("views")

    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions(num_threads=options.threads)
    extraction.sift.max_num_features = options.max_features
    extraction.sift.peak_threshold = options.peak_threshold
    pycolmap.extract_features(database, work_dir / "images", image_names=feed.image_names,
                              camera_mode=feed.camera_mode, reader_options=feed.reader_options(work_dir / "masks"),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    feed.configure_database(database)
    timings["features"] = time.perf_counter() - t0
    progress("features")

    t0 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions(num_threads=options.threads)
    feed.configure_matching(matching)
    pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(database) as db:
        verified_pairs = feed.count_verified_pairs(db, options.min_matches)
    timings["matching"] = time.perf_counter() - t0
    progress("matching")

    t0 = time.perf_counter()
    mapping = pycolmap.IncrementalPipelineOptions(
        min_num_matches=options.min_matches, min_model_size=2, num_threads=options.threads,
        random_seed=options.seed, extract_colors=True)
    # a point two panoramas see is as good as any: with a handful of panoramas most are such
    mapping.triangulation.ignore_two_view_tracks = False
    feed.configure_mapping(mapping)
    (work_dir / "sparse").mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(database, work_dir / "images", work_dir / "sparse", mapping)
    timings["mapping"] = time.perf_counter() - t0
    progress("mapping")
    if not models:
        return _empty(verified_pairs, timings)
    # the model registering the most panoramas; views only other models hold are unregistered
    best = max(models.values(), key=lambda m: (m.num_reg_frames(), m.num_points3D()))
    result = feed.read(best)
    if len(result.cam_from_world) < 2:
        return _empty(verified_pairs, timings)
    result.verified_pairs = verified_pairs
    result.models = len(models)
    result.timings = timings
    return result


def _empty(verified_pairs: int, timings: dict[str, float]) -> Reconstruction:
    return Reconstruction({}, {}, {}, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, int),
                          verified_pairs, 0, timings)


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    native_write(path, lambda: cv2.imwrite(str(path), image), "image")


class _Feed(ABC):
    """How panoramas enter COLMAP and how its model maps back to panoramas."""

    camera_mode: pycolmap.CameraMode
    image_names: list[str]

    def __init__(self, panoramas: Sequence[Panorama]):
        self.panoramas = list(panoramas)
        sizes = {p.rgb.shape[:2] for p in self.panoramas}
        if len(sizes) != 1:
            raise ValueError(f"panoramas of different sizes {sorted(sizes)}; resample them to one size first")
        self.height, self.width = sizes.pop()

    @abstractmethod
    def write(self, images: Path, masks: Path) -> None:
        """Write the images COLMAP reads (`image_names`) and their masks (`<image name>.png`)."""

    @abstractmethod
    def reader_options(self, masks: Path) -> pycolmap.ImageReaderOptions:
        """The camera model COLMAP gives the images."""

    def configure_database(self, database: Path) -> None:
        pass

    def configure_matching(self, matching: pycolmap.FeatureMatchingOptions) -> None:
        pass

    def configure_mapping(self, mapping: pycolmap.IncrementalPipelineOptions) -> None:
        pass

    @abstractmethod
    def view_of(self, image_name: str) -> str:
        """The panorama an image of `image_names` comes from."""

    def count_verified_pairs(self, db: pycolmap.Database, min_matches: int) -> int:
        """Pairs of panoramas with at least `min_matches` verified matches between their images."""
        ids = {img.image_id: self.view_of(img.name) for img in db.read_all_images()}
        inliers: dict[tuple[str, str], int] = {}
        for pair_id, n in zip(*db.read_two_view_geometry_num_inliers()):
            a, b = (ids[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
            if a != b:
                key = (min(a, b), max(a, b))
                inliers[key] = inliers.get(key, 0) + int(n)
        return sum(n >= min_matches for n in inliers.values())

    def pano_from_image(self, image: pycolmap.Image) -> np.ndarray:
        """Rotation taking the image's camera frame to its panorama's."""
        return np.eye(3)

    def read(self, model: pycolmap.Reconstruction) -> Reconstruction:
        poses: dict[str, np.ndarray] = {}
        err_sum: dict[str, float] = {}
        obs: dict[str, int] = {}
        for image in model.images.values():
            if not image.has_pose:
                continue
            view = self.view_of(image.name)
            cam_from_world = np.eye(4)
            cam_from_world[:3] = image.cam_from_world().matrix()
            if view not in poses:
                pano_from_world = np.eye(4)
                pano_from_world[:3, :3] = self.pano_from_image(image) @ cam_from_world[:3, :3]
                pano_from_world[:3, 3] = self.pano_from_image(image) @ cam_from_world[:3, 3]
                poses[view] = pano_from_world
            xy, xyz = [], []
            for p2d in image.points2D:
                if p2d.has_point3D():
                    xy.append(p2d.xy)
                    xyz.append(model.points3D[p2d.point3D_id].xyz)
            if xyz:
                cam = np.asarray(xyz) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
                projected = np.asarray(image.camera.img_from_cam(cam))
                err_sum[view] = err_sum.get(view, 0.0) + float(np.sum(np.linalg.norm(projected - np.asarray(xy), axis=1)))
                obs[view] = obs.get(view, 0) + len(xyz)
        names = {img.image_id: self.view_of(img.name) for img in model.images.values()}
        pts = list(model.points3D.values())
        seen: dict[str, set[int]] = {}
        for k, p in enumerate(pts):
            for e in p.track.elements:
                seen.setdefault(names[e.image_id], set()).add(k)
        points = np.array([p.xyz for p in pts]).reshape(-1, 3)
        colors = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
        tracks = np.array([len({names[e.image_id] for e in p.track.elements}) for p in pts], dtype=int)
        errors = {v: err_sum.get(v, 0.0) / max(obs.get(v, 0), 1) for v in poses}
        seen_by = {v: np.array(sorted(seen.get(v, ())), int) for v in poses}
        return Reconstruction(poses, errors, {v: obs.get(v, 0) for v in poses}, points, colors, tracks, 0,
                              seen_by=seen_by)


class _EquirectFeed(_Feed):
    camera_mode = pycolmap.CameraMode.SINGLE

    def __init__(self, panoramas: Sequence[Panorama]):
        super().__init__(panoramas)
        self.image_names = [f"{p.name}.png" for p in self.panoramas]

    def write(self, images: Path, masks: Path) -> None:
        for p, name in zip(self.panoramas, self.image_names):
            _write_png(images / name, cv2.cvtColor(p.rgb, cv2.COLOR_RGB2BGR))
            # every image gets a mask: COLMAP skips an image whose mask folder is missing
            valid = np.ones(p.rgb.shape[:2], bool) if p.valid is None else p.valid
            _write_png(masks / f"{name}.png", valid.astype(np.uint8) * 255)

    def reader_options(self, masks: Path) -> pycolmap.ImageReaderOptions:
        return pycolmap.ImageReaderOptions(camera_model="EQUIRECTANGULAR", mask_path=masks)

    def view_of(self, image_name: str) -> str:
        return image_name.removesuffix(".png")


class _RigFeed(_Feed):
    camera_mode = pycolmap.CameraMode.PER_FOLDER

    def __init__(self, panoramas: Sequence[Panorama]):
        super().__init__(panoramas)
        self.rig = VirtualRig(self.height)
        self.prefixes = [f"cam{k:02d}/" for k in range(len(self.rig.pano_from_cams))]
        self.image_names = [prefix + f"{p.name}.png" for p in self.panoramas for prefix in self.prefixes]

    def write(self, images: Path, masks: Path) -> None:
        for p in self.panoramas:
            bgr = cv2.cvtColor(p.rgb, cv2.COLOR_RGB2BGR)
            for prefix, (image, mask) in zip(self.prefixes, self.rig.render(bgr, p.valid)):
                _write_png(images / prefix / f"{p.name}.png", image)
                _write_png(masks / prefix / f"{p.name}.png.png", mask)

    def reader_options(self, masks: Path) -> pycolmap.ImageReaderOptions:
        s, f = self.rig.size, self.rig.focal
        return pycolmap.ImageReaderOptions(camera_model="PINHOLE", camera_params=f"{f},{f},{s / 2},{s / 2}",
                                           mask_path=masks)

    def configure_database(self, database: Path) -> None:
        cameras = []
        for k, (prefix, pano_from_cam) in enumerate(zip(self.prefixes, self.rig.pano_from_cams)):
            # camera 0 is the reference sensor and looks along the panorama's axes
            cam_from_rig = None if k == 0 else pycolmap.Rigid3d(
                pycolmap.Rotation3d(pano_from_cam.T), np.zeros((3, 1)))
            cameras.append(pycolmap.RigConfigCamera(ref_sensor=k == 0, image_prefix=prefix,
                                                    cam_from_rig=cam_from_rig))
        with pycolmap.Database.open(database) as db:
            pycolmap.apply_rig_config([pycolmap.RigConfig(cameras=cameras)], db)

    def configure_matching(self, matching: pycolmap.FeatureMatchingOptions) -> None:
        # the rig's relative poses are exact, and views of one panorama share no features (masks)
        matching.rig_verification = True
        matching.skip_image_pairs_in_same_frame = True

    def configure_mapping(self, mapping: pycolmap.IncrementalPipelineOptions) -> None:
        mapping.ba_refine_sensor_from_rig = False
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False

    def view_of(self, image_name: str) -> str:
        return image_name.split("/", 1)[1].removesuffix(".png")

    def pano_from_image(self, image: pycolmap.Image) -> np.ndarray:
        return self.rig.pano_from_cams[self.prefixes.index(image.name.split("/", 1)[0] + "/")]
