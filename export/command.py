"""CLI command `pano-pipe export RUN --format ply|splat|spz|mesh` (pipeline/cli.py registers it).

Reads RUN/train/point_cloud.ply (the file the train stage's artifact names) and writes one
export beside the run's stages, in RUN/export/, or where --out says. Never overwrites an
existing file unless --overwrite; every file is written to a temporary sibling and renamed
into place, so an interrupted export leaves nothing half-written. See docs/export.md.
"""

from __future__ import annotations

import json
from dataclasses import replace
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer
from rich.markup import escape

from pipeline.console import console
from runfs.errors import PanoError

EXTENSIONS = {"ply": ".ply", "splat": ".splat", "spz": ".spz", "mesh": ".ply"}


class ExportFormat(str, Enum):
    ply = "ply"
    splat = "splat"
    spz = "spz"
    mesh = "mesh"


class GlbAxes(str, Enum):
    y_up = "y-up"
    pano_pipe = "pano-pipe"


class MeshSource(str, Enum):
    auto = "auto"
    depth = "depth"
    centres = "centres"


RunArg = Annotated[Path, typer.Argument(help="Run folder (holding train/point_cloud.ply).", show_default=False)]


def load_run_model(run: Path):
    """The trained Gaussians of a run folder; every problem a one-line PanoError."""
    from gaussians.ply import load_ply
    from pipeline.engine import read_output

    run = Path(run)
    if not run.exists():
        raise PanoError(run, "no such run folder")
    if not run.is_dir():
        raise PanoError(run, "not a folder (expected a run folder holding train/)")
    train = read_output(run, "train")
    art_path = run / "train" / "artifact.json"
    if train is None:
        raise PanoError(art_path, "missing: this run has no trained model (run `pano-pipe run train SCENE` first)")
    if not train.ply or Path(train.ply).name != train.ply:
        raise PanoError(art_path, "data.ply must name the model file inside train/")
    ply = run / "train" / train.ply
    if not ply.is_file():
        raise PanoError(ply, "missing (named by train/artifact.json)")
    try:
        g = load_ply(ply)
    except (ValueError, OSError) as e:
        msg = str(e)
        raise PanoError(ply, msg.removeprefix(f"{ply}: ")) from None
    if len(g) == 0:
        raise PanoError(ply, "holds no Gaussians")
    return g  # load_ply refuses non-finite parameters


def default_output(run: Path, fmt: str, y_up: bool) -> Path:
    from runfs.paths import run_path

    stem = "mesh" if fmt == "mesh" else "point_cloud"
    return run_path(run, f"export/{stem}{'_yup' if y_up else ''}{EXTENSIONS[fmt]}")


def output_paths(run: Path, fmt: str, y_up: bool, out: Path | None) -> list[Path]:
    """The file(s) this export writes: one, or for a mesh its .ply and its .glb twin."""
    path = default_output(run, fmt, y_up) if out is None else Path(out)
    suffix = path.suffix.lower()
    if fmt == "mesh":
        if suffix not in (".ply", ".glb"):
            raise PanoError(path, "a mesh is written as .ply and .glb: --out must end in .ply or .glb")
        return [path.with_suffix(".ply"), path.with_suffix(".glb")]
    if suffix != EXTENSIONS[fmt]:
        raise PanoError(path, f"--format {fmt} writes a {EXTENSIONS[fmt]} file: --out must end in {EXTENSIONS[fmt]}")
    return [path]


def scene_cameras(run: Path) -> tuple[list[np.ndarray] | None, str | None]:
    """Camera-to-world poses of the run's training views (from the scene its marker names),
    or (None, why not)."""
    from runfs.paths import RUN_MARKER
    from pipeline.engine import complete_scene
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    marker = Path(run) / RUN_MARKER
    try:
        scene_root = json.loads(marker.read_text()).get("scene")
    except (OSError, ValueError, AttributeError):
        return None, f"{marker} does not name the run's scene"
    if not isinstance(scene_root, str):
        return None, f"{marker} does not name the run's scene"
    try:
        scene = load_scene(scene_root, check_images=False)
    except PanoError as e:
        return None, str(e)
    # poses the run recovered (the poses stage) fill in what scene.json leaves out
    scene = complete_scene(scene, Path(run), build_registry())
    return [v.pose_matrix for v in scene.manifest.train_views()], None


def build_mesh(g, run: Path, source: str, height: int, depth: int, max_points: int = 300_000,
               max_hole_m: float = 4.0):
    """The cleaned, coloured room mesh in the y-down world (see export/mesh.py)."""
    from export.mesh import points_from_centres, points_from_depth, reconstruct

    poses, why = scene_cameras(run)
    if source == "depth" and poses is None:
        raise PanoError(run, f"--mesh-source depth needs the training poses: {why}")
    if source == "auto":
        source = "depth" if poses is not None else "centres"
        if poses is None:
            console.print(f"[yellow]note:[/] {escape(why)}; meshing the Gaussians' centres instead", soft_wrap=True)
    if source == "depth":
        op = points_from_depth(g, poses, height=height)
    else:
        cams = np.stack([p[:3, 3] for p in poses]) if poses else None
        op = points_from_centres(g, cams)
    if len(op.points) > max_points:
        idx = np.sort(np.random.default_rng(0).choice(len(op.points), max_points, replace=False))
        op.points, op.colors = op.points[idx], op.colors[idx]
        op.viewpoints = None if op.viewpoints is None else op.viewpoints[idx]
    try:
        mesh = reconstruct(op, depth=depth, max_hole_m=max_hole_m)
    except ValueError as e:
        raise PanoError(run, f"no mesh: {e}") from None
    mesh.stats["source"] = source
    return mesh


def export_command(
    run: RunArg,
    format: Annotated[ExportFormat, typer.Option("--format", "-f", help="ply (standard 3DGS), splat (antimatter15), "
                                                 "spz (Niantic), or mesh (coloured surface, .ply + .glb).",
                                                 case_sensitive=False)] = ExportFormat.ply,
    y_up: Annotated[bool, typer.Option("--y-up", help="Rotate the world 180° about x: y up, z back "
                                       "(pano-pipe's world is y down).")] = False,
    out: Annotated[Optional[Path], typer.Option("--out", help="Output file (default: RUN/export/<name>.<ext>).")
                   ] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing output file.")] = False,
    mesh_source: Annotated[MeshSource, typer.Option("--mesh-source", help="mesh: back-project rendered depth at "
                                                    "the training views, or use the Gaussians' centres; auto = "
                                                    "depth when the run's scene is readable.")] = MeshSource.auto,
    mesh_height: Annotated[int, typer.Option("--mesh-height", min=8, max=2048,
                                             help="mesh: height of the depth renders (width 2×).")] = 128,
    mesh_depth: Annotated[int, typer.Option("--mesh-depth", min=5, max=12,
                                            help="mesh: screened Poisson octree depth.")] = 8,
    mesh_max_hole: Annotated[float, typer.Option(
        "--mesh-max-hole", min=0.0,
        help="mesh: close every hole at most this many metres across (the diagonal of its boundary's box) "
             "with a flat patch; 0 leaves holes open.")] = 4.0,
    glb_axes: Annotated[GlbAxes, typer.Option(
        "--glb-axes", case_sensitive=False,
        help="mesh: axes of the .glb: y-up (glTF's, so glTF viewers show the room upright) or pano-pipe "
             "(y down, as the run and the .ply).")] = GlbAxes.y_up,
) -> None:
    """Export a run's trained Gaussians (.ply / .splat / .spz) or a coloured mesh of the room."""
    from export.fileio import check_writable
    from runfs.fsutil import atomic_write
    from runfs.paths import open_run_folder
    from export.transform import to_y_up, y_up_points

    fmt = ExportFormat(format).value
    open_run_folder(run)  # a run folder holding a symbolic link is refused before anything is read
    targets = output_paths(run, fmt, y_up, out)
    for t in targets:  # refuse before any work
        check_writable(t, overwrite)
    g = load_run_model(run)

    if fmt == "mesh":
        from export.mesh import write_mesh

        mesh = build_mesh(g, Path(run), MeshSource(mesh_source).value, mesh_height, mesh_depth,
                          max_hole_m=mesh_max_hole)
        glb_y_up = GlbAxes(glb_axes) is GlbAxes.y_up
        for t in targets:
            # glTF is y up by specification: the .glb follows --glb-axes, the .ply --y-up
            up = glb_y_up if t.suffix.lower() == ".glb" else y_up
            axes = replace(mesh, vertices=y_up_points(mesh.vertices)) if up else mesh
            atomic_write(t, lambda tmp, m=axes: write_mesh(tmp, m))  # tmp keeps t's suffix
        s = mesh.stats
        closed = "watertight" if s.get("watertight") else (
            f"{s.get('boundary_loops', '?')} hole(s) left open, the largest "
            f"{(s.get('holes_across_m') or [0])[0]:.2f} m across (--mesh-max-hole)")
        console.print(f"mesh: {s['vertices']} vertices, {s['faces']} faces from {s['points']} points "
                      f"({s['source']}; {closed}); .glb {'y up' if glb_y_up else 'y down'}, "
                      f".ply {'y up' if y_up else 'y down'}", soft_wrap=True)
    else:
        gg = to_y_up(g) if y_up else g
        if fmt == "ply":
            from gaussians.ply import save_ply

            atomic_write(targets[0], lambda tmp: save_ply(tmp, gg))
        elif fmt == "splat":
            from export.splat import write_splat

            atomic_write(targets[0], lambda tmp: write_splat(tmp, gg))
        else:
            from export.spz import write_spz

            try:
                atomic_write(targets[0], lambda tmp: write_spz(tmp, gg, rub=y_up))
            except ValueError as e:
                raise PanoError(targets[0], str(e)) from None
        console.print(f"{fmt}: {len(g)} Gaussians", soft_wrap=True)
    for t in targets:
        console.print(f"[bold]wrote:[/] {escape(str(t))}", soft_wrap=True)
