"""`pano-pipe new SCENE PANORAMA...`: a scene folder from a handful of panoramas.

The panoramas go to `SCENE/images/` (copied, or hard-linked with `--link`: a symbolic link
would lead out of the scene folder, which scenes refuse, docs/security.md), each view named
after its file (made a safe, unique stem as the importers do, pipeline/importers.py). No
poses: the poses stage recovers them, except for a single panorama, which has nothing to be placed
against: its camera is the world frame (the identity pose: at the origin and level, as the upright
solvers take every panorama to be). Every panorama is checked (a file, decodable,
2:1) before anything is written, and the folder is written whole or not at all
(runfs.fsutil.atomic_folder), as the importers write theirs.
"""

from __future__ import annotations

import os
import shlex
from pathlib import Path
from typing import Annotated, Optional

import typer

from runtime.console import console
from runfs.errors import PanoError
from schemas.scene import REAL_CAPTURE_NADIR_DEG


def new_scene(out: Path, panoramas: list[Path], *, link: bool = False, test_every: int = 8,
              camera_height: float | None = None, nadir_mask_deg: float = REAL_CAPTURE_NADIR_DEG,
              name: str | None = None) -> Path:
    """Write the scene folder `out` holding `panoramas` (in the order given); returns its scene.json.
    Every problem is a one-line PanoError naming the file or option, raised before anything is written."""
    from pydantic import ValidationError

    from pipeline.importers import (
        _check_common, _check_out, _image_suffix, _manifest, _output_folder, _split, _write_scene,
        sanitize_stem, unique_names,
    )
    from runfs.errors import describe_validation_error
    from runfs.paths import overlap_problem
    from schemas.scene import View
    from schemas.scene_loader import check_panorama

    _check_common(test_every, name, camera_height, None, nadir_mask_deg)
    if not panoramas:
        raise PanoError("new", "give one or more panoramas (e.g. photos/*.jpg)")
    out = _output_folder(out)
    sources = [Path(p) for p in panoramas]
    for src in sources:
        if src.is_dir():
            raise PanoError(src, "is a folder; give the panoramas themselves (e.g. photos/*.jpg)")
        if not src.is_file():
            raise PanoError(src, "no such file")
        check_panorama(src, "the command line")  # unreadable or not 2:1: one line naming it
    seen: dict[Path, Path] = {}
    for src in sources:
        if (first := seen.setdefault(src.resolve(), src)) is not src:
            raise PanoError(src, f"given twice (also as {first})")
    splits = [_split(i, test_every) for i in range(len(sources))]
    if "train" not in splits:
        raise PanoError("--test-every", f"{test_every} makes every panorama a test view")
    names = unique_names([sanitize_stem(src.stem) for src in sources])
    # one panorama is the world frame; several are placed relative to each other by the poses stage
    pose = [[float(i == j) for j in range(4)] for i in range(4)] if len(sources) == 1 else None
    views = []
    for view_name, src, split in zip(names, sources, splits):
        try:
            views.append(View(name=view_name, image=f"images/{view_name}{_image_suffix(src)}", split=split,
                              camera_height=camera_height, pose=pose))
        except ValidationError as e:
            raise describe_validation_error(src, e) from None
    manifest = _manifest(views, out, name if name is not None else sanitize_stem(out.name, fallback="scene"),
                         nadir_mask_deg)
    # OUT may lie inside the panoramas' folder (`new scene photos/*.jpg` run in photos/), but may
    # not be or hold it: the final rename would replace the panoramas
    for folder in {src.parent.resolve() for src in sources}:
        if overlap_problem(out, folder) in ("is", "contains"):
            raise PanoError(out, f"is or holds {folder}, the folder of the panoramas; choose a new folder")
    _check_out(out, {})
    if not link:
        _write_scene(out, manifest, [(src, view.image) for src, view in zip(sources, views)], {}, "new")
        return out / "scene.json"

    def hard_links(tmp: Path) -> None:
        (tmp / "images").mkdir()
        for src, view in zip(sources, views):
            try:
                os.link(src, tmp / view.image)
            except OSError as e:
                raise PanoError(src, f"cannot hard-link into {out} ({e.strerror or e}; another file "
                                     "system?); leave out --link to copy the panoramas") from None

    _write_scene(out, manifest, [], {}, "new", extra=hard_links)
    return out / "scene.json"


def new_command(
    scene: Annotated[Path, typer.Argument(help="Scene folder to write (new or empty).", show_default=False)],
    panoramas: Annotated[list[Path], typer.Argument(
        help="Equirectangular panoramas (2:1), e.g. photos/*.jpg; view names come from the file names.",
        show_default=False)],
    link: Annotated[bool, typer.Option(
        "--link", help="Hard-link the panoramas into SCENE/images instead of copying them (same file system).")]
    = False,
    test_every: Annotated[int, typer.Option(
        "--test-every", help="Hold out every Nth panorama as a test view (0: none; evaluate then "
                             "measures the training views).")] = 8,
    camera_height: Annotated[Optional[float], typer.Option(
        "--camera-height", help="Camera height over the floor (m), for every view: makes the recovered "
                                "poses metric (docs/poses.md).")] = None,
    nadir_mask_deg: Annotated[float, typer.Option(
        "--nadir-mask-deg", help="Degrees around the nadir left out of training (tripod, hand; 0: off).")]
    = REAL_CAPTURE_NADIR_DEG,
    name: Annotated[Optional[str], typer.Option(
        "--name", help="Scene name (default: the folder's name); names the run folder runs/<name>/.")] = None,
) -> None:
    """Make a scene folder from panoramas without poses (the poses stage recovers them)."""
    from rich.markup import escape

    from pipeline.settings import SCENE_CONFIG

    path = new_scene(scene, panoramas, link=link, test_every=test_every, camera_height=camera_height,
                     nadir_mask_deg=nadir_mask_deg, name=name)
    import json

    n_test = sum(v["split"] == "test" for v in json.loads(path.read_text())["views"])
    console.print(escape(f"wrote {path} ({len(panoramas)} views: {len(panoramas) - n_test} train, {n_test} test; "
                         f"images {'linked' if link else 'copied'}; nadir_mask_deg {nadir_mask_deg:g}; "
                         f"the settings for captured panoramas in {path.parent / SCENE_CONFIG})"),
                  soft_wrap=True)
    if len(panoramas) == 1:
        console.print("one panorama: its camera is the world frame (the identity pose, level as captured); "
                      "add more panoramas to recover poses between them", soft_wrap=True, highlight=False)
    console.print(escape(f"next: pano-pipe run all {shlex.quote(str(scene))}"), soft_wrap=True)
