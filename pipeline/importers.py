"""Bring other capture conventions into a pano-pipe scene folder.

nerfstudio `transforms.json` (camera_model EQUIRECTANGULAR): `transform_matrix`
is camera-to-world with OpenGL camera axes (x right, y up, z back) and its
image centre looks along -z, so flipping the camera's y and z axes gives our
OpenCV camera with the same pixel-to-direction mapping. nerfstudio worlds are
usually z-up; ours is y-down, so the world is rotated by `WORLD_TO_YDOWN`.

The import follows the path rules of `pipeline.paths` (docs/security.md):

- Every frame's `file_path` must resolve inside the folder holding
  transforms.json, after symlinks; an absolute path, '..' or a symlink leading
  out is refused (one-line error naming `frames.<i>.file_path`).
- The whole transforms.json is checked before anything is written, and the
  scene is written into a temporary sibling of OUT that is renamed into place
  only at the end: a failure leaves no OUT (or the empty OUT there was).
  OUT must be new or an empty folder, and may not overlap the source folder.
- A view's name is its image's file stem, made into a safe stem
  (`pipeline.paths.safe_stem`) where it is not one: characters a file name may
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

import numpy as np
from pydantic import ValidationError

from pipeline.errors import PanoError, describe_validation_error, read_json
from pipeline.fsutil import atomic_folder
from pipeline.paths import (
    MAX_STEM_BYTES,
    is_inside,
    overlap_problem,
    relative_problem,
    safe_stem,
    stem_problem,
)
from schemas.scene import SceneManifest, View

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

#: Rotations taking a world with the given up axis to our y-down world.
WORLD_TO_YDOWN = {
    "+z": np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64),
    "+y": np.diag([1.0, -1.0, -1.0, 1.0]),
    "-y": np.eye(4),
}

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


def _check_out(out: Path, base: Path) -> None:
    """Refuse an OUT that overlaps the source folder, is a file, or is a non-empty folder."""
    problem = overlap_problem(out, base)
    if problem:
        raise PanoError(out, f"output folder {problem} the source folder {base} (holding transforms.json); "
                             "choose an OUT outside it")
    if overlap_problem(out, Path.cwd()) in ("is the same folder", "contains"):
        raise PanoError(out, "output folder is (or contains) the working folder; "
                             "choose a new or empty folder")
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise PanoError(out, "exists and is not a folder; choose a new or empty folder for the scene")
        if any(out.iterdir()):
            raise PanoError(out, "exists and is not empty; choose a new or empty folder for the scene")


def import_nerfstudio(
    transforms: Path, out: Path, world_up: str = "+z", test_every: int = 8, name: str | None = None
) -> Path:
    """Write a scene folder at `out` from a nerfstudio `transforms.json`; returns its scene.json.

    Every problem is a one-line PanoError; problems with the input are found before anything is
    written, and a failure while writing (a disk full) leaves OUT as it was.
    """
    check_world_up(world_up)
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 0:
        raise PanoError("--test-every",
                        f"must be 0 (no test views) or a positive whole number, got {test_every!r}")
    transforms = Path(transforms)
    out = Path(os.path.abspath(out))  # '.' and '..' resolved lexically
    if out.is_symlink():  # write into the folder it names, keeping the link
        out = out.resolve()
    if name is not None:
        problem = stem_problem(name)
        if problem:
            raise PanoError("name", f"{name!r} is not a safe scene name: it {problem}")
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

    # Check every frame before writing anything.
    sources, suffixes, stems, poses, splits = [], [], [], [], []
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
            split = "test" if test_every > 0 and i % test_every == test_every - 1 else "train"
        sources.append(src)
        suffixes.append(_image_suffix(named))
        stems.append(sanitize_stem(named.stem))
        poses.append(nerfstudio_to_pose(m, world_up))
        splits.append(split)
    if "train" not in splits:
        why = ("every frame is in test_filenames" if test_names
               else f"--test-every {test_every} makes every frame a test view")
        raise PanoError(transforms, f"no train views: {why}")

    views = []
    for i, (src, view_name, pose, split) in enumerate(zip(sources, unique_names(stems), poses, splits)):
        image = f"images/{view_name}{suffixes[i]}"
        try:
            views.append(View(name=view_name, image=image, pose=pose.tolist(), split=split))
        except ValidationError as e:
            problem = describe_validation_error(transforms, e).problem
            problem = problem.replace("pose:", "transform_matrix:", 1)
            raise PanoError(transforms, f"frames.{i}.{problem}") from None
    scene_name = name if name is not None else sanitize_stem(out.name, fallback="scene")
    try:
        manifest = SceneManifest(name=scene_name, views=views)
    except ValidationError as e:
        raise describe_validation_error(transforms, e) from None

    try:
        _check_out(out, base)
    except (OSError, RuntimeError) as e:
        why = getattr(e, "strerror", None) or str(e)
        raise PanoError(out, f"cannot use as the output folder: {why}") from None
    try:
        with atomic_folder(out) as tmp:
            (tmp / "images").mkdir()
            for src, view in zip(sources, views):
                try:
                    shutil.copy2(src, tmp / view.image)
                except OSError as e:
                    raise PanoError(src, f"cannot copy image: {e.strerror or e}") from None
            (tmp / "scene.json").write_text(manifest.model_dump_json(indent=2, exclude_none=True))
            # OUT was checked above; refuse to replace it if something was written there meanwhile.
            if out.is_dir() and any(out.iterdir()):
                raise PanoError(out, "was written to during the import; choose a new or empty folder")
    except OSError as e:
        raise PanoError(out, f"cannot write the scene: {e.strerror or e}") from None
    return out / "scene.json"


def _frame_image(frame: dict, i: int, base: Path, transforms: Path) -> tuple[Path, Path]:
    """The frame's image as named (for its view name) and resolved (symlinks followed, to copy),
    checked to lie inside `base`."""
    field = f"frames.{i}.file_path"
    rel = frame.get("file_path")
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
            raise PanoError(src, f"image missing (named by {field})")
        if not src.is_file():
            raise PanoError(src, f"not a regular file (named by {field})")
        return src, src.resolve(strict=True)
    except (OSError, RuntimeError) as e:  # name too long, symlink loop, no permission
        why = getattr(e, "strerror", None) or str(e)
        raise PanoError(transforms, f"{field}: cannot open {rel[:80]!r}: {why}") from None
