"""CLI command `pano-pipe export RUN --format ply|splat|spz|sog|html|mesh` (pipeline/cli.py registers it).

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

from runtime.console import console
from runfs.errors import PanoError

EXTENSIONS = {"ply": ".ply", "splat": ".splat", "spz": ".spz", "sog": ".sog", "html": ".html", "mesh": ".ply"}


class ExportFormat(str, Enum):
    ply = "ply"
    splat = "splat"
    spz = "spz"
    sog = "sog"
    html = "html"
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
    if fmt == "sog" and path.name.lower() == "meta.json":  # unbundled: meta.json, its textures beside it
        from export.sog import SOG_FILES

        return [path.parent / name for name in SOG_FILES]
    if suffix != EXTENSIONS[fmt]:
        also = " (or name a meta.json: the textures go beside it)" if fmt == "sog" else ""
        raise PanoError(path, f"--format {fmt} writes a {EXTENSIONS[fmt]} file: --out must end in "
                              f"{EXTENSIONS[fmt]}{also}")
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


def write_sog_targets(targets: list[Path], g, iterations: int) -> list[Path]:
    """Write the SOG of `g`: one .sog bundle, or meta.json and its textures (the files written)."""
    from export.sog import sog_encode, zip_bytes
    from runfs.fsutil import atomic_write

    try:
        files = sog_encode(g, iterations=iterations)
    except ValueError as e:
        raise PanoError(targets[0], str(e)) from None
    shn = json.loads(files["meta.json"]).get("shN")
    if shn:
        console.print(f"sog: SH palette of {shn['count']} entries in {files.seconds:.1f} s", soft_wrap=True)
    if len(targets) == 1:
        data = zip_bytes(files)
        atomic_write(targets[0], lambda tmp: tmp.write_bytes(data))
        return targets
    written = [t for t in targets if t.name in files]
    for t in sorted(written, key=lambda t: t.name == "meta.json"):  # meta.json last: it names the rest
        atomic_write(t, lambda tmp, b=files[t.name]: tmp.write_bytes(b))
    return written


def page_camera(run: Path, g, y_up: bool) -> tuple[dict | None, str | None]:
    """The HTML page's first view: at the first training camera, level, looking along the room
    (first-person), or (None, why not)."""
    from export.transform import y_up_points
    from viewer.data import look_along_room

    poses, why = scene_cameras(run)
    if not poses:
        return None, why or "the run's scene has no training views"
    eye = np.asarray(poses[0], dtype=np.float64)[:3, 3]
    means = g.means.detach().cpu().double().numpy()
    if y_up:  # `g` is rotated already; look_along_room works in pano-pipe's y-down world, as the poses
        means = y_up_points(means)
    fwd = look_along_room(eye, means)
    if y_up:
        eye, fwd = y_up_points(eye), y_up_points(fwd)
    return {"eye": eye.tolist(), "target": (eye + 0.5 * fwd).tolist(), "mode": "walk", "fovy": 70.0}, None


def export_command(
    run: RunArg,
    format: Annotated[ExportFormat, typer.Option("--format", "-f", help="ply (standard 3DGS), splat (antimatter15), "
                                                 "spz (Niantic), sog (PlayCanvas, WebP textures in a zip), "
                                                 "html (one self-contained viewer page), or mesh (coloured "
                                                 "surface, .ply + .glb).",
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
    sog_iterations: Annotated[int, typer.Option(
        "--sog-iterations", min=0, max=100,
        help="sog: k-means iterations of the SH palette (more: closer view-dependent colour, slower).")] = 10,
) -> None:
    """Export a run's trained Gaussians (.ply / .splat / .spz / .sog / an .html page) or a room mesh."""
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
        if s.get("watertight"):
            closed = "watertight"
        elif s.get("closed"):  # every edge between two faces, but faces cross (flat hole patches do)
            closed = (f"closed, but {s.get('self_intersecting_faces')} faces cross another: not watertight "
                      f"for readers that reject self-intersection (open3d)")
        else:
            closed = (f"{s.get('boundary_loops', '?')} hole(s) left open, the largest "
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
        elif fmt == "spz":
            from export.spz import write_spz

            try:
                atomic_write(targets[0], lambda tmp: write_spz(tmp, gg, rub=y_up))
            except ValueError as e:
                raise PanoError(targets[0], str(e)) from None
        elif fmt == "sog":
            targets = write_sog_targets(targets, gg, sog_iterations)
        else:
            from export.html import write_html

            camera, why = page_camera(Path(run), gg, y_up)
            if camera is None:
                console.print(f"[yellow]note:[/] {escape(why)}; the page starts outside the model",
                              soft_wrap=True)
            up = (0.0, 1.0, 0.0) if y_up else (0.0, -1.0, 0.0)
            atomic_write(targets[0], lambda tmp: write_html(tmp, gg, camera=camera, up=up,
                                                            title=f"{Path(run).resolve().name} (pano-pipe)"))
        size = sum(t.stat().st_size for t in targets)
        console.print(f"{fmt}: {len(g)} Gaussians, {size / 1e6:.2f} MB", soft_wrap=True)
    for t in targets:
        console.print(f"[bold]wrote:[/] {escape(str(t))}", soft_wrap=True)
