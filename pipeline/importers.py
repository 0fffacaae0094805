"""Bring other capture conventions into a pano-pipe scene folder.

nerfstudio `transforms.json` (camera_model EQUIRECTANGULAR): `transform_matrix`
is camera-to-world with OpenGL camera axes (x right, y up, z back) and its
image centre looks along -z, so flipping the camera's y and z axes gives our
OpenCV camera with the same pixel-to-direction mapping. nerfstudio worlds are
usually z-up; ours is y-down, so the world is rotated by `WORLD_TO_YDOWN`.
Depth files are kept as metres along the ray. COLMAP models with EQUIRECTANGULAR cameras
(`import_colmap`) are made upright and metric with sfm.frame, as the poses stage does; the
scale rules of both importers are in docs/poses.md ("Importers").

The import follows the path rules of `runfs.paths` (docs/security.md):

- Every frame's `file_path` must resolve inside the folder holding
  transforms.json, after symlinks; an absolute path, '..' or a symlink leading
  out is refused (one-line error naming `frames.<i>.file_path`).
- The whole transforms.json is checked before anything is written, and the
  scene is written into a temporary sibling of OUT that is renamed into place
  only at the end: a failure leaves no OUT (or the empty OUT there was).
  OUT must be new or an empty folder, and may not overlap the source folder.
- A view's name is its image's file stem, made into a safe stem
  (`runfs.paths.safe_stem`) where it is not one: characters a file name may
  not hold become '_', leading dots, dashes and spaces are dropped, and long
  stems are cut. Names that then collide (`a/frame.png` and `b/frame.png`,
  `frame.png` and `frame.jpg`, or names differing only in case) are made unique
  in frame order: the first keeps the name, later ones get `_2`, `_3`, ...
  (skipping any name another frame already has). The image is copied to
  `images/<view name><suffix>`.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import unicodedata
from pathlib import Path, PurePosixPath

from collections.abc import Callable

import cv2
import numpy as np
from pydantic import ValidationError

from runfs.errors import PanoError, describe_validation_error, read_json
from runfs.fsutil import atomic_folder
from runfs.limits import check_colmap_binary, load_npy, read_image
from runfs.paths import (
    MAX_STEM_BYTES,
    is_inside,
    overlap_problem,
    relative_problem,
    safe_stem,
    stem_problem,
)
from panogeom import angles_to_dirs
from panogeom.equirect import pixel_to_angles
from schemas.scene import MAX_CAMERA_HEIGHT, REAL_CAPTURE_NADIR_DEG, SceneManifest, View
from sfm.frame import MAX_FLOOR_TILT_DEG, Similarity, align_to_floor, fit_floor, metric_scale
from stages.cloud_io import write_ply

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

#: Rotations taking a world with the given up axis to our y-down world.
WORLD_TO_YDOWN = {
    "+z": np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64),
    "+y": np.diag([1.0, -1.0, -1.0, 1.0]),
    "-y": np.eye(4),
}

#: nerfstudio's default depth_unit_scale_factor: depth PNGs in millimetres.
NERFSTUDIO_DEPTH_UNIT = 1e-3
#: Same tolerance as the scene schema's pose check (schemas/scene.py View).
RIGID_TOLERANCE = 1e-4
#: Room left in a stem for a `_<n>` suffix that makes it unique.
_STEM_BUDGET = MAX_STEM_BYTES - 12
_UNSAFE_CHARS = re.compile(r'[/\\:*?"<>|]')
_SUFFIX = re.compile(r"\.[A-Za-z0-9]{1,10}")


def nerfstudio_to_pose(transform_matrix, world_up: str = "+z") -> np.ndarray:
    """A nerfstudio camera-to-world matrix as our camera-to-world (OpenCV camera, y-down world)."""
    m = np.asarray(transform_matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    return WORLD_TO_YDOWN[world_up] @ m @ GL_TO_CV


def pose_to_nerfstudio(pose, world_up: str = "+z") -> np.ndarray:
    """The inverse of `nerfstudio_to_pose` (for exporting and for tests)."""
    return np.linalg.inv(WORLD_TO_YDOWN[world_up]) @ np.asarray(pose, dtype=np.float64) @ GL_TO_CV


def sanitize_stem(name: str, fallback: str = "view") -> str:
    """`name` made into a safe file-name stem (see the module docstring); deterministic."""
    s = "".join("_" if _UNSAFE_CHARS.match(c) or _is_control(c) else c for c in name)
    s = _trim(s)
    while len(s.encode("utf-8", "surrogatepass")) > _STEM_BUDGET:
        s = _trim(s[:-1])
    if stem_problem(s):
        s = fallback
    return safe_stem(s)


def _trim(s: str) -> str:
    """`s` without leading dots, dashes and spaces, or trailing dots and spaces."""
    start, end = 0, len(s)
    while start < end and (s[start] in ".-" or s[start].isspace()):
        start += 1
    while end > start and (s[end - 1] == "." or s[end - 1].isspace()):
        end -= 1
    return s[start:end]


def _is_control(c: str) -> bool:
    return unicodedata.category(c)[0] == "C"


def _image_suffix(src: Path) -> str:
    """The image's suffix if it is a plain one (`.png`, `.JPG`), else its letters and digits."""
    suffix = src.suffix
    if _SUFFIX.fullmatch(suffix):
        return suffix
    kept = "".join(c for c in suffix if c.isascii() and c.isalnum())[:10]
    return f".{kept}" if kept else ""


def unique_names(stems: list[str]) -> list[str]:
    """Each stem, later repeats (compared ignoring case) suffixed `_2`, `_3`, ... in order."""
    taken = {s.casefold() for s in stems}
    seen: set[str] = set()
    out = []
    for stem in stems:
        name = stem
        if name.casefold() in seen:
            k = 2
            while f"{stem}_{k}".casefold() in taken or f"{stem}_{k}".casefold() in seen:
                k += 1
            name = f"{stem}_{k}"
        seen.add(name.casefold())
        out.append(name)
    return out


def check_world_up(world_up: str) -> None:
    """A nerfstudio world's up axis as --world-up names it, or a one-line PanoError."""
    if world_up not in WORLD_TO_YDOWN:
        raise PanoError("--world-up", f"must be one of {', '.join(sorted(WORLD_TO_YDOWN))}, got {world_up!r}")


def rigid_matrix(value, where: Path, field: str) -> np.ndarray:
    """A frame's transform_matrix as a checked 4x4 rigid float matrix; else a PanoError naming the field."""
    if not isinstance(value, list) or len(value) not in (3, 4):
        got = f"{len(value)} rows" if isinstance(value, list) else type(value).__name__
        raise PanoError(where, f"{field}: must be a 4x4 (or 3x4) list of rows of numbers, got {got}")
    rows = []
    for r, row in enumerate(value):
        if not isinstance(row, list) or len(row) != 4:
            got = f"{len(row)} entries" if isinstance(row, list) else type(row).__name__
            raise PanoError(where, f"{field}.{r}: each row must hold 4 numbers, got {got}")
        for c, x in enumerate(row):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                raise PanoError(where, f"{field}.{r}.{c}: must be a number, got {type(x).__name__}")
            try:
                fx = float(x)
            except OverflowError:
                fx = math.inf
            if not math.isfinite(fx):
                raise PanoError(where, f"{field}.{r}.{c}: must be finite, got {x!r}"[:200])
        rows.append([float(x) for x in row])
    m = np.asarray(rows, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise PanoError(where, f"{field}.3: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if not err <= RIGID_TOLERANCE or not det > 0:
        raise PanoError(where, f"{field}: not a rigid transform (|R^T R - I| = {err:.2g}, "
                               f"det R = {det:.3g}); pano-pipe needs rotation + translation "
                               "without scale or mirroring")
    return m


def _check_out(out: Path, sources: dict[str, Path]) -> None:
    """Refuse an OUT that overlaps a source folder (`sources`: what it holds -> folder), is a
    file, or is a non-empty folder."""
    for what, base in sources.items():
        problem = overlap_problem(out, base)
        if problem:
            raise PanoError(out, f"output folder {problem} the source folder {base} (holding {what}); "
                                 "choose an OUT outside it")
    if overlap_problem(out, Path.cwd()) in ("is", "contains"):
        raise PanoError(out, "output folder is (or contains) the working folder; "
                             "choose a new or empty folder")
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise PanoError(out, "exists and is not a folder; choose a new or empty folder for the scene")
        if any(out.iterdir()):
            raise PanoError(out, "exists and is not empty; choose a new or empty folder for the scene")


def _output_folder(out: Path) -> Path:
    out = Path(os.path.abspath(out))  # '.' and '..' resolved lexically
    return out.resolve() if out.is_symlink() else out  # write into the folder a link names, keeping it


def _check_common(test_every, name: str | None, camera_height: float | None, scale: float | None,
                  nadir_mask_deg: float) -> None:
    """The options both importers share, or a one-line PanoError naming the option."""
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 0:
        raise PanoError("--test-every",
                        f"must be 0 (no test views) or a positive whole number, got {test_every!r}")
    if name is not None:
        problem = stem_problem(name)
        if problem:
            raise PanoError("name", f"{name!r} is not a safe scene name: it {problem}")
    if camera_height is not None and scale is not None:
        raise PanoError("--camera-height", "give --camera-height or --scale, not both")
    if camera_height is not None and not 0 < camera_height <= MAX_CAMERA_HEIGHT:
        raise PanoError("--camera-height", f"must be in (0, {MAX_CAMERA_HEIGHT:g}] metres, got {camera_height!r}")
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise PanoError("--scale", f"must be a positive number, got {scale!r}")
    if not 0 <= nadir_mask_deg <= 90:
        raise PanoError("--nadir-mask-deg", f"must be in [0, 90] degrees, got {nadir_mask_deg!r}")


def _split(i: int, test_every: int) -> str:
    return "test" if test_every > 0 and i % test_every == test_every - 1 else "train"


def _measured_heights(heights: np.ndarray) -> list[float | None]:
    """Camera heights (m) worth writing to scene.json: those the schema accepts, else None."""
    return [float(h) if 0 < h <= MAX_CAMERA_HEIGHT else None for h in heights]


def _write_scene(out: Path, manifest: SceneManifest, copies: list[tuple[Path, str]],
                 arrays: dict[str, np.ndarray], command: str, extra: Callable[[Path], None] | None = None) -> None:
    """The scene folder at `out`, written whole or not at all (runfs.fsutil.atomic_folder):
    `copies` are (source file, path in the scene), `arrays` .npy files by path in the scene,
    `extra` writes anything else into the temporary folder. The scene's pano-pipe.yaml starts with
    the settings for captured panoramas, saying which `command` wrote it."""
    from pipeline.settings import SCENE_CONFIG, real_capture_settings_text

    try:
        with atomic_folder(out) as tmp:
            for src, rel in copies:
                (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                try:
                    shutil.copy2(src, tmp / rel)
                except OSError as e:
                    raise PanoError(src, f"cannot copy: {e.strerror or e}") from None
            for rel, values in arrays.items():
                (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                np.save(tmp / rel, values)
            if extra is not None:
                extra(tmp)
            (tmp / SCENE_CONFIG).write_text(real_capture_settings_text(command))
            (tmp / "scene.json").write_text(manifest.model_dump_json(indent=2, exclude_none=True))
            # OUT was checked before; refuse to replace it if something was written there meanwhile.
            if out.is_dir() and any(out.iterdir()):
                raise PanoError(out, "was written to during the import; choose a new or empty folder")
    except OSError as e:
        raise PanoError(out, f"cannot write the scene: {e.strerror or e}") from None


def _manifest(views: list[View], where: Path, scene_name: str, nadir_mask_deg: float) -> SceneManifest:
    try:
        return SceneManifest(name=scene_name, views=views, nadir_mask_deg=nadir_mask_deg)
    except ValidationError as e:
        raise describe_validation_error(where, e) from None


def import_nerfstudio(
    transforms: Path, out: Path, world_up: str = "+z", test_every: int = 8, name: str | None = None,
    camera_height: float | None = None, scale: float | None = None,
    nadir_mask_deg: float = REAL_CAPTURE_NADIR_DEG,
) -> Path:
    """Write a scene folder at `out` from a nerfstudio `transforms.json`; returns its scene.json.

    Translations (and depth) are multiplied by `scale`, or by the scale that puts the cameras
    `camera_height` metres over the floor seen in the depth maps (docs/poses.md, "Importers").
    Every problem is a one-line PanoError; problems with the input are found before anything is
    written, and a failure while writing (a disk full) leaves OUT as it was.
    """
    check_world_up(world_up)
    _check_common(test_every, name, camera_height, scale, nadir_mask_deg)
    transforms = Path(transforms)
    out = _output_folder(out)
    try:
        if not transforms.exists():
            raise PanoError(transforms, "file does not exist")
        if transforms.is_dir():
            raise PanoError(transforms, "is a folder; give the path of transforms.json itself")
    except OSError as e:
        raise PanoError(transforms, f"cannot open: {e.strerror or e}") from None
    meta = read_json(transforms)
    if not isinstance(meta, dict):
        raise PanoError(transforms, f"top level must be a JSON object, got {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise PanoError(transforms, "frames: must be a non-empty list of frames")
    model = meta.get("camera_model", "EQUIRECTANGULAR")
    base = transforms.parent
    test_list = meta.get("test_filenames", [])
    if not isinstance(test_list, list) or not all(isinstance(p, str) for p in test_list):
        raise PanoError(transforms, "test_filenames: must be a list of file paths")
    test_names = {PurePosixPath(p.replace("\\", "/")).name for p in test_list}
    depth_unit = meta.get("depth_unit_scale_factor", NERFSTUDIO_DEPTH_UNIT)
    if isinstance(depth_unit, bool) or not isinstance(depth_unit, (int, float)) or not (
            math.isfinite(depth_unit) and depth_unit > 0):
        raise PanoError(transforms, f"depth_unit_scale_factor: must be a positive number, got {depth_unit!r}")

    # Check every frame before writing anything.
    sources, suffixes, stems, poses, splits, depths = [], [], [], [], [], []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise PanoError(transforms, f"frames.{i}: must be an object, got {type(frame).__name__}")
        if frame.get("camera_model", model) != "EQUIRECTANGULAR":
            raise PanoError(transforms, f"frames.{i}: camera_model must be EQUIRECTANGULAR")
        named, src = _frame_image(frame, i, base, transforms)
        if "transform_matrix" not in frame:
            raise PanoError(transforms, f"frames.{i}.transform_matrix: missing")
        m = rigid_matrix(frame["transform_matrix"], transforms, f"frames.{i}.transform_matrix")
        if test_names:
            split = "test" if named.name in test_names else "train"
        else:
            split = _split(i, test_every)
        sources.append(src)
        suffixes.append(_image_suffix(named))
        stems.append(sanitize_stem(named.stem))
        poses.append(nerfstudio_to_pose(m, world_up))
        splits.append(split)
        depth = None
        if frame.get("depth_file_path") is not None:
            depth = _nerfstudio_depth(_frame_image(frame, i, base, transforms, "depth_file_path")[1],
                                      depth_unit, f"frames.{i}.depth_file_path")
        depths.append(depth)
    if "train" not in splits:
        why = ("every frame is in test_filenames" if test_names
               else f"--test-every {test_every} makes every frame a test view")
        raise PanoError(transforms, f"no train views: {why}")

    heights: list[float | None] = [None] * len(poses)
    if camera_height is not None:
        scale, measured = _scale_from_depth_floor(poses, depths, camera_height, transforms)
        heights = _measured_heights(measured)
    scale = 1.0 if scale is None else scale
    for pose in poses:
        pose[:3, 3] *= scale

    views, arrays = [], {}
    for i, (view_name, pose, split) in enumerate(zip(unique_names(stems), poses, splits)):
        image = f"images/{view_name}{suffixes[i]}"
        depth_rel = None
        if depths[i] is not None:
            depth_rel = f"depth/{view_name}.npy"
            arrays[depth_rel] = (depths[i] * scale).astype(np.float32)
        try:
            views.append(View(name=view_name, image=image, pose=pose.tolist(), split=split,
                              camera_height=heights[i], depth=depth_rel))
        except ValidationError as e:
            problem = describe_validation_error(transforms, e).problem
            problem = problem.replace("pose:", "transform_matrix:", 1)
            raise PanoError(transforms, f"frames.{i}.{problem}") from None
    scene_name = name if name is not None else sanitize_stem(out.name, fallback="scene")
    manifest = _manifest(views, transforms, scene_name, nadir_mask_deg)

    try:
        _check_out(out, {"transforms.json": base})
    except (OSError, RuntimeError) as e:
        why = getattr(e, "strerror", None) or str(e)
        raise PanoError(out, f"cannot use as the output folder: {why}") from None
    _write_scene(out, manifest, [(src, view.image) for src, view in zip(sources, views)], arrays, "import-nerfstudio")
    return out / "scene.json"


def _nerfstudio_depth(path: Path, unit: float, field: str) -> np.ndarray:
    """A nerfstudio depth file in metres, float64 [H,W], 0 where invalid.

    nerfstudio reads .npy as is and images with any bit depth, then multiplies by
    depth_unit_scale_factor (dataparsers/base and utils/data_utils.get_depth_image_from_path).
    For EQUIRECTANGULAR cameras its ray directions are unit vectors, so its depth is the distance
    along the ray, as ours is: only the unit changes."""
    try:
        if path.suffix.lower() == ".npy":
            raw = load_npy(path, pixels=True)
        else:
            raw = read_image(path, cv2.IMREAD_ANYDEPTH, what=f"depth map (named by {field})")
            if raw is None:
                raise PanoError(path, f"unreadable depth image (named by {field})")
    except (OSError, ValueError) as e:
        raise PanoError(path, f"unreadable depth file (named by {field}): {e}") from None
    if raw.ndim == 3 and raw.shape[-1] == 1:
        raw = raw[..., 0]
    if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.number):
        raise PanoError(path, f"depth must be a single-channel [H,W] map (named by {field}), "
                              f"got {raw.dtype} {list(raw.shape)}")
    h, w = raw.shape
    if w != 2 * h:
        raise PanoError(path, f"depth map is {w}x{h} (width x height); expected 2:1 equirectangular "
                              f"(named by {field})")
    metres = raw.astype(np.float64) * unit
    metres[~np.isfinite(metres) | (metres < 0)] = 0.0
    return metres


#: Depth pixels back-projected per view to find the floor (a 64x128 grid is plenty for a plane).
FLOOR_GRID_HEIGHT = 64


def _scale_from_depth_floor(poses: list[np.ndarray], depths: list[np.ndarray | None], camera_height: float,
                            transforms: Path) -> tuple[float, np.ndarray]:
    """The scale putting the cameras `camera_height` over the floor plane fitted to the depth maps
    back-projected into the (upright) world, and each camera's height over it in metres after
    scaling. The depth is taken in the units of the poses, as nerfstudio's depth supervision does."""
    if any(d is None for d in depths):
        missing = sum(d is None for d in depths)
        raise PanoError(transforms, f"--camera-height needs every frame's depth_file_path to find the floor "
                                    f"({missing} frames have none); give --scale instead")
    points = []
    for pose, depth in zip(poses, depths):
        step = max(1, depth.shape[0] // FLOOR_GRID_HEIGHT)
        d = depth[step // 2::step, step // 2::step]
        phi, theta = pixel_to_angles(*np.meshgrid(np.arange(d.shape[1]) * step + step // 2,
                                                  np.arange(d.shape[0]) * step + step // 2),
                                     depth.shape[0], depth.shape[1])
        rays = angles_to_dirs(phi, theta)[d > 0] * d[d > 0, None]
        points.append(rays @ pose[:3, :3].T + pose[:3, 3])
    centres = np.array([p[:3, 3] for p in poses])
    floor = fit_floor(np.concatenate(points), centres)
    if floor is None:
        raise PanoError(transforms, "--camera-height: no floor plane (within "
                                    f"{MAX_FLOOR_TILT_DEG:g} deg of level) below the cameras in the depth maps; "
                                    "check --world-up or give --scale")
    d = floor.height_above(centres)
    if np.any(d <= 0):
        raise PanoError(transforms, "--camera-height: the floor found in the depth maps is not below every camera; "
                                    "give --scale")
    scale, _ = metric_scale(d, np.full(len(d), camera_height), floor)
    return scale, scale * d


def _frame_image(frame: dict, i: int, base: Path, transforms: Path, key: str = "file_path") -> tuple[Path, Path]:
    """The frame's image (or the file its `key` names) as named (for its view name) and resolved
    (symlinks followed, to copy), checked to lie inside `base`."""
    field = f"frames.{i}.{key}"
    rel = frame.get(key)
    if rel is None:
        raise PanoError(transforms, f"{field}: missing")
    if not isinstance(rel, str):
        raise PanoError(transforms, f"{field}: must be a string, got {type(rel).__name__}")
    problem = relative_problem(rel)
    if problem:
        why = problem.split(";")[0].replace("scene folder", "folder of transforms.json")
        raise PanoError(transforms, f"{field}: {rel!r} {why}; "
                                    "images must lie inside the folder holding transforms.json")
    src = base / rel
    try:
        inside = is_inside(src, base)
    except PanoError:  # a symlink loop: say so about the field that names it
        raise PanoError(transforms, f"{field}: cannot open {rel[:80]!r}: a symlink loop") from None
    try:
        if not inside:
            raise PanoError(transforms, f"{field}: {rel!r} resolves outside the folder of transforms.json "
                                        "(a symlink?); images must lie inside it")
        if not src.exists():
            raise PanoError(src, f"{'image' if key == 'file_path' else 'file'} missing (named by {field})")
        if not src.is_file():
            raise PanoError(src, f"not a regular file (named by {field})")
        return src, src.resolve(strict=True)
    except (OSError, RuntimeError) as e:  # name too long, symlink loop, no permission
        why = getattr(e, "strerror", None) or str(e)
        raise PanoError(transforms, f"{field}: cannot open {rel[:80]!r}: {why}") from None


# -- COLMAP --------------------------------------------------------------------------------------

SPARSE_POINTS = "sparse/points.ply"
_MODEL_FILES = ("cameras", "images", "points3D")


def import_colmap(
    model_dir: Path, images_dir: Path, out: Path, camera_height: float | None = None,
    scale: float | None = None, test_every: int = 0, name: str | None = None,
    nadir_mask_deg: float = REAL_CAPTURE_NADIR_DEG, warn: Callable[[str], None] | None = None,
) -> Path:
    """Write a scene folder at `out` from a COLMAP sparse model with EQUIRECTANGULAR cameras;
    returns its scene.json.

    COLMAP's equirectangular camera has OpenCV axes and maps pixels to rays as DESIGN.md does
    (image centre along +z, top row at the zenith, longitude growing to the right), so a registered
    image's pose is the inverse of its cam_from_world. The SfM frame is made upright and metric
    as the poses stage does (sfm.frame): gravity from the cameras' mean down axis; the scale from
    the camera heights over the floor plane fitted to the sparse points (`camera_height`, default
    the poses stage's default_camera_height), or `scale` times COLMAP's units. The first image (by name) sits at the
    origin. Unregistered images are left out.
    """
    _check_common(test_every, name, camera_height, scale, nadir_mask_deg)
    model_dir, images_dir, out = Path(model_dir), Path(images_dir), _output_folder(out)
    model = _read_colmap(model_dir)
    images = sorted((im for im in model.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise PanoError(model_dir, "the COLMAP model has no registered images")
    for camera_id, camera in model.cameras.items():
        if camera.model.name != "EQUIRECTANGULAR":
            raise PanoError(model_dir, f"camera {camera_id} is {camera.model.name}: only EQUIRECTANGULAR cameras "
                                       "are supported (not perspective rigs); see docs/poses.md")
        if camera.width != 2 * camera.height:
            raise PanoError(model_dir, f"camera {camera_id} is {camera.width}x{camera.height}; "
                                       "equirectangular images must be 2:1")
    if not images_dir.is_dir():
        raise PanoError(images_dir, "images folder does not exist" if not images_dir.exists() else "not a folder")
    sources = [_colmap_image(images_dir, im.name) for im in images]

    cam_to_world = {im.name: np.linalg.inv(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]))
                    for im in images}
    order = [im.name for im in images]
    points = np.array([p.xyz for p in model.points3D.values()], dtype=np.float64).reshape(-1, 3)
    colors = np.array([p.color for p in model.points3D.values()], dtype=np.float64).reshape(-1, 3) / 255.0
    transform, heights = _colmap_alignment(cam_to_world, points, order, camera_height, scale, model_dir, warn)

    stems = unique_names([sanitize_stem(PurePosixPath(n).stem) for n in order])
    views = []
    for i, (image_name, stem, src) in enumerate(zip(order, stems, sources)):
        pose = transform.pose(cam_to_world[image_name])
        try:
            views.append(View(name=stem, image=f"images/{stem}{_image_suffix(src)}", pose=pose.tolist(),
                              split=_split(i, test_every), camera_height=heights[i]))
        except ValidationError as e:  # a --scale that puts cameras 100 km apart
            problem = describe_validation_error(model_dir, e).problem
            raise PanoError(model_dir, f"image {image_name!r}: {problem}") from None
    if not any(v.split == "train" for v in views):
        raise PanoError("--test-every", f"{test_every} makes every image a test view")
    manifest = _manifest(views, model_dir, name if name is not None else sanitize_stem(out.name, fallback="scene"),
                         nadir_mask_deg)

    try:
        _check_out(out, {"the COLMAP model": model_dir, "the images": images_dir})
    except (OSError, RuntimeError) as e:
        why = getattr(e, "strerror", None) or str(e)
        raise PanoError(out, f"cannot use as the output folder: {why}") from None
    world_points = transform.points(points)

    def write_points(tmp: Path) -> None:
        (tmp / SPARSE_POINTS).parent.mkdir()
        write_ply(tmp / SPARSE_POINTS, world_points, colors, np.zeros_like(world_points))

    _write_scene(out, manifest, [(src, view.image) for src, view in zip(sources, views)], {}, "import-colmap",
                 write_points)
    return out / "scene.json"


def _read_colmap(model_dir: Path):
    """The pycolmap.Reconstruction in `model_dir` (binary or text), or a one-line PanoError."""
    import pycolmap

    from sfm.reconstruct import quiet_colmap

    quiet_colmap()  # its own log of a corrupt file would precede our one line
    if not model_dir.is_dir():
        raise PanoError(model_dir, "COLMAP model folder does not exist" if not model_dir.exists() else
                                   "not a folder; give the folder holding cameras/images/points3D .bin or .txt")
    for stem in _MODEL_FILES:
        if not any((model_dir / f"{stem}{ext}").is_file() for ext in (".bin", ".txt")):
            raise PanoError(model_dir / f"{stem}.bin", "missing (neither .bin nor .txt): not a COLMAP sparse model")
    if any((model_dir / f"{stem}.bin").is_file() for stem in _MODEL_FILES):
        check_colmap_binary(model_dir)  # pycolmap allocates what the counts claim before reading
    try:
        return pycolmap.Reconstruction(model_dir)
    except Exception as e:  # pycolmap raises bare RuntimeErrors / ValueErrors on corrupt files
        first = str(e).strip().splitlines()[-1:] or [type(e).__name__]
        raise PanoError(model_dir, f"cannot read the COLMAP model: {first[0][:200]}") from None


def _colmap_image(images_dir: Path, image_name: str) -> Path:
    """The image file a COLMAP image name refers to, checked to lie inside `images_dir`."""
    problem = relative_problem(image_name)
    if problem:
        raise PanoError(images_dir, f"COLMAP image name {image_name!r} {problem.split(';')[0]}")
    src = images_dir / image_name
    try:
        if not is_inside(src, images_dir):
            raise PanoError(src, "resolves outside the images folder (a symlink?)")
        if not src.is_file():
            raise PanoError(src, "image missing (named by the COLMAP model)")
        return src.resolve(strict=True)
    except (OSError, RuntimeError) as e:
        raise PanoError(src, f"cannot open: {getattr(e, 'strerror', None) or e}") from None


def _colmap_alignment(cam_to_world: dict[str, np.ndarray], points: np.ndarray, order: list[str],
                      camera_height: float | None, scale: float | None, model_dir: Path,
                      warn: Callable[[str], None] | None) -> tuple[Similarity, list[float | None]]:
    """SfM frame -> world, and each camera's height over the floor in metres (None where no
    floor was found)."""
    if scale is None and camera_height is None:  # as the poses stage does without camera_height in scene.json
        from stages.poses import Params

        camera_height = Params.model_fields["default_camera_height"].default
        if warn is not None:
            warn(f"no --camera-height or --scale: the scale assumes cameras {camera_height:g} m over the floor")
    try:
        alignment = align_to_floor(cam_to_world, points, dict.fromkeys(order, camera_height), order, scale=scale)
    except ValueError as e:
        raise PanoError(model_dir, f"cannot make the poses metric: {e}; give --scale") from None
    transform, floor = alignment.transform, alignment.floor
    if floor is None:
        return transform, [None] * len(order)
    centres = np.array([transform.rotation @ cam_to_world[v][:3, 3] for v in order])
    return transform, _measured_heights(transform.scale * floor.height_above(centres))
