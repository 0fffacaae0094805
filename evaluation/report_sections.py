"""Report sections that show what a stage did, each one function of the same shape.

A section takes the page being written (evaluation.report_doc.ReportDoc) and a SectionContext, writes its heading and
content when its stage ran, and returns its id (report.ReportPaths.sections), or writes nothing
and returns None when the run holds nothing for it: a section of a stage that did not run is
absent, not a placeholder. `STAGE_SECTIONS` lists them in the order the page shows them, after
the floor plan; a new section (poses, ...) is one function added there.

Every file an artifact names is looked up only inside that stage's folder (`stage_file`).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluation.report_text import fmt

__all__ = ["SectionContext", "STAGE_SECTIONS", "layout_section", "depth_alignment_section", "diagnosis_section",
           "warnings_section", "stage_warnings",
           "settings_without_effect", "settings_section", "export_links", "stage_file", "read_artifact",
           "flatten_params"]


@dataclass
class SectionContext:
    run_dir: Path
    scene: object | None  # schemas.scene.Scene, or None when the report was given no scene
    out_dir: Path
    img_dir: Path


def read_artifact(run_dir: Path, stage: str) -> dict | None:
    """A stage's artifact ({"meta", "data"}) as plain values for the report's tables, validated by
    the one typed reader (pipeline.engine.read_artifact); None when the stage wrote none."""
    from pipeline.engine import read_artifact as read_typed
    from pipeline.registry import build_registry

    if stage not in build_registry():  # a stage of an older version, named in the run log
        return None
    art = read_typed(run_dir, stage)
    return None if art is None else art.model_dump()


def stage_file(run_dir: Path, stage: str, name) -> Path | None:
    """The file `name` (as an artifact names it) inside RUN/stage/, or None when the name is not a
    plain file name there (a path elsewhere, '..') or no such file exists."""
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        return None
    path = Path(run_dir) / stage / name
    return path if path.is_file() else None


# ----------------------------------------------------------------------------- diagnosis and warnings


def stage_warnings(run_dir: Path) -> list[tuple[str, str]]:
    """(stage, warning) for every warning a stage of this run recorded (its artifact's meta.warnings:
    what ctx.warn said while it ran), stages in DAG order, each stage's in the order said."""
    from pipeline.engine import topological_order
    from pipeline.registry import build_registry

    out = []
    for stage in topological_order(build_registry()):
        art = read_artifact(run_dir, stage)
        for w in ((art or {}).get("meta") or {}).get("warnings") or []:
            out.append((stage, str(w)))
    return out


def diagnosis_section(doc, ctx: SectionContext) -> str | None:
    """What limits this run, before anything else: trained without priors (what it costs, the
    commands that fetch the models), a model that overfits its training views (the likely causes
    in order); evaluation/diagnosis.py words both. Absent when neither applies."""
    from evaluation.diagnosis import run_notes

    tr = read_artifact(ctx.run_dir, "train")
    if tr is None:
        return None
    ev = read_artifact(ctx.run_dir, "evaluate")
    notes = run_notes(tr["data"], (tr.get("meta") or {}).get("upstream"), ev["data"] if ev else None, ctx.scene)
    if not notes:
        return None
    doc.h(2, "What limits this run", "diagnosis")
    for note in notes:
        doc.p(note[0].upper() + note[1:] + ("" if note.endswith(".") else "."), "warn")
    return "diagnosis"


def warnings_section(doc, ctx: SectionContext) -> str | None:
    """Every warning a stage recorded, beside the stage that said it (fell back to a cuboid, assumed a
    camera height, heights disagree, points seen by no view, LPIPS unavailable, ...); absent when
    no stage warned."""
    rows = stage_warnings(ctx.run_dir)
    if not rows:
        return None
    doc.h(2, "Stage warnings", "warnings")
    doc.table(["stage", "warning"], [[stage, w] for stage, w in rows])
    return "warnings"


# ----------------------------------------------------------------------------- layout


#: Colours of the drawn boundaries (matplotlib names): ceiling / floor.
CEILING_COLOUR = "#00e5ff"
FLOOR_COLOUR = "#ff2bd6"
#: Panoramas are drawn at most this wide in the report (they are only looked at, not measured).
OVERLAY_MAX_WIDTH = 1024


def boundary_rows(boundaries: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Column centres and rows of [2, W] boundary latitudes (radians) on an image of `height` rows
    and 2·height columns, DESIGN.md's pixel mapping: (cols [W], rows [2, W]), continuous pixels."""
    from panogeom.equirect import angles_to_pixel, column_longitudes

    b = np.asarray(boundaries, dtype=np.float64)
    phi = column_longitudes(b.shape[1])
    cols, rows = angles_to_pixel(np.broadcast_to(phi, b.shape), b, height, 2 * height)
    return cols[0], rows


def plot_layout_view(image: np.ndarray, boundaries: np.ndarray, polygon: np.ndarray, camera_height: float,
                     ceiling_distance: float, title: str, path: Path) -> None:
    """One training view: the panorama with the fitted ceiling and floor boundaries drawn on it (left)
    and the view's floor plan, seen from above in its camera frame (right)."""
    from evaluation.visuals import pyplot

    plt = pyplot()
    fig, (ax_i, ax_p) = plt.subplots(1, 2, figsize=(12, 3.6), gridspec_kw={"width_ratios": [2.6, 1]})
    h = image.shape[0]
    ax_i.imshow(np.clip(image, 0, 1), extent=(-0.5, image.shape[1] - 0.5, h - 0.5, -0.5),
                interpolation="bilinear")
    cols, rows = boundary_rows(boundaries, h)
    cols = cols * image.shape[1] / (2 * h)  # the image may not be exactly 2:1
    for row, colour, label in ((rows[0], CEILING_COLOUR, "ceiling"), (rows[1], FLOOR_COLOUR, "floor")):
        ok = np.isfinite(row)
        ax_i.plot(cols[ok], row[ok], "-", color=colour, lw=1.4, label=f"{label} boundary")
    ax_i.set_xlim(-0.5, image.shape[1] - 0.5)
    ax_i.set_ylim(h - 0.5, -0.5)
    ax_i.set_axis_off()
    ax_i.legend(loc="lower right", fontsize=8, framealpha=0.7)
    ax_i.set_title(title, fontsize=10)
    ring = np.vstack([polygon, polygon[:1]]) if len(polygon) else polygon
    if len(ring):
        ax_p.fill(ring[:, 0], ring[:, 1], color="C2", alpha=0.2)
        ax_p.plot(ring[:, 0], ring[:, 1], "-", color="C2", lw=2)
    span = float(np.ptp(polygon, axis=0).max()) if len(polygon) > 1 else 1.0
    ax_p.plot([0], [0], "o", color="C0", ms=8, markeredgecolor="k")
    ax_p.arrow(0, 0, 0, 0.15 * span, head_width=0.05 * span, color="C0", length_includes_head=True)
    ax_p.set_aspect("equal")
    ax_p.set_xlabel("camera x (m)", fontsize=8)
    ax_p.set_ylabel("camera z (m)", fontsize=8)
    ax_p.tick_params(labelsize=7)
    ax_p.grid(alpha=0.3)
    ax_p.set_title(f"floor plan: camera {camera_height:.2f} m over the floor,\n"
                   f"{ceiling_distance:.2f} m under the ceiling", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def layout_section(doc, ctx: SectionContext) -> str | None:
    """The layout stage's room on each training panorama: the ceiling and floor boundaries drawn on
    the image, and the floor plan it makes in that view's camera frame."""
    art = read_artifact(ctx.run_dir, "layout")
    if art is None:
        return None
    views = [v for v in art["data"].get("views", [])
             if isinstance(v, dict) and v.get("split", "train") == "train"]
    doc.h(2, "Layout on the training panoramas", "layout")
    scene_views = {v.name: v for v in ctx.scene.views} if ctx.scene is not None else {}
    if not scene_views:
        doc.p("No scene given: the panoramas to draw the layout on are not known.", "warn")
        return "layout"
    from panogeom.images import read_rgb

    doc.p("Each training panorama with the room the layout stage fitted to it: the ceiling boundary "
          "(cyan) and the floor boundary (magenta) where the walls meet them, and the floor plan of "
          "that view in its own camera frame (seen from above; the dot is the camera, the arrow the "
          "panorama's centre direction). Boundaries that leave the walls show where the room is wrong.",
          "note")
    drawn = 0
    for v in views:
        sv = scene_views.get(v.get("view"))
        bpath = stage_file(ctx.run_dir, "layout", v.get("boundaries"))
        if sv is None or bpath is None:
            continue
        try:
            boundaries = np.load(bpath, allow_pickle=False)
            polygon = np.asarray(v.get("floor_polygon") or np.zeros((0, 2)), dtype=np.float64).reshape(-1, 2)
            image_path = ctx.scene.image_path(sv)
            probe = read_rgb(image_path)
        except (OSError, ValueError):
            doc.p(f"{v.get('view')}: its panorama or boundaries could not be read.", "warn")
            continue
        if boundaries.ndim != 2 or boundaries.shape[0] != 2:
            continue
        h = min(probe.shape[0], OVERLAY_MAX_WIDTH // 2)
        image = probe if probe.shape[0] == h else read_rgb(image_path, size=(h, 2 * h))
        png = ctx.img_dir / f"layout-{v['view']}.png"
        method = v.get("method", "corners")
        title = (f"{v['view']}: layout from {v.get('source', '?')} ({method})"
                 + (", camera height assumed" if v.get("camera_height_assumed") else ""))
        plot_layout_view(image, boundaries, polygon, float(v.get("camera_height", 0.0)),
                         float(v.get("ceiling_distance", 0.0)), title, png)
        doc.images([(png, f"{v['view']}: layout boundaries and floor plan")], "layout")
        drawn += 1
    if not drawn:
        doc.p("The layout artifact names no training view with readable boundaries.", "warn")
    return "layout"


# ----------------------------------------------------------------------------- depth alignment


def depth_alignment_section(doc, ctx: SectionContext) -> str | None:
    """How the align stage scaled the depth to the layout: the scale (and shift), the share of
    labelled pixels that agree with the layout, the residual, ICP's refinement, per fit group."""
    art = read_artifact(ctx.run_dir, "align")
    if art is None:
        return None
    d = art["data"]
    doc.h(2, "Depth alignment", "alignment")
    if not d.get("aligned_to_layout"):
        doc.p("The depth was not aligned to a layout (no layout in this run): it is used at its own "
              f"scale ({fmt(d.get('scale'))}).", "warn")
    else:
        share, residual = d.get("inlier_share"), d.get("residual_m")
        doc.p(f"Depth scaled by {fmt(d.get('scale'))}"
              + (f", shift {fmt(d.get('shift'))}" if d.get("shift") else "")
              + (f"; {100 * share:.1f}% of the labelled pixels agree with the layout"
                 if isinstance(share, float) else "")
              + (f"; median residual {100 * residual:.2g} cm on them" if isinstance(residual, float) else "")
              + ".")
    fits = [f for f in d.get("fits", []) if isinstance(f, dict)]
    if fits:
        rows = []
        for f in fits:
            share, residual = f.get("inlier_share"), f.get("residual_m")
            rows.append([", ".join(map(str, f.get("views", []))), str(f.get("kind", "")),
                         fmt(f.get("scale")), fmt(f.get("layout_fit_scale")), fmt(f.get("icp_factor")),
                         f"{100 * share:.1f}%" if isinstance(share, (int, float)) else "—",
                         f"{100 * residual:.2g}" if isinstance(residual, (int, float)) else "—",
                         fmt(f.get("icp_fitness")), fmt(f.get("num_pixels"))])
        doc.table(["views", "depth kind", "scale", "layout-fit scale", "ICP factor", "inliers",
                   "residual (cm)", "ICP fitness", "pixels fitted"], rows)
        doc.p("scale = layout-fit scale × ICP factor. Inliers: labelled pixels whose depth agrees with the "
              "layout within align.inlier_threshold; ICP fitness: share of depth points within "
              "align.icp_max_distance of the layout cloud.", "note")
    if (art.get("meta") or {}).get("warnings"):
        doc.p("The align stage warned: see Stage warnings.", "warn")
    return "alignment"


#: The sections of STAGE results, in page order (after the floor plan). Each: (doc, ctx) -> id | None.
STAGE_SECTIONS: list[Callable] = [layout_section, depth_alignment_section]


# ----------------------------------------------------------------------------- links


#: Files `pano-pipe export` writes into RUN/export/, by suffix: what they are, and their axes as far as
#: the file itself fixes them (a name with _yup was written with --y-up; docs/export.md).
EXPORT_KINDS = {
    ".ply": ("3D Gaussians, standard 3DGS PLY", "pano-pipe axes, y down"),
    ".splat": ("3D Gaussians, antimatter15 .splat", "pano-pipe axes, y down"),
    ".spz": ("3D Gaussians, Niantic .spz", "RUB, as the format defines"),
    ".glb": ("room mesh, glTF binary", "y up unless exported with --glb-axes pano-pipe"),
}


def export_links(run_dir: Path) -> list[tuple[Path, str]]:
    """(file, text) for every export in RUN/export/ (hidden temporaries left out)."""
    folder = Path(run_dir) / "export"
    out = []
    for path in sorted(folder.glob("*")) if folder.is_dir() else []:
        suffix = path.suffix.lower()
        if path.name.startswith(".") or not path.is_file() or suffix not in EXPORT_KINDS:
            continue
        what, axes = EXPORT_KINDS[suffix]
        if path.stem.startswith("mesh") and suffix == ".ply":
            what = "room mesh, PLY"
        if path.stem.endswith("_yup") and suffix in (".ply", ".splat"):
            axes = "y up"
        out.append((path, f"export {path.name} ({what}; {axes})"))
    return out


# ----------------------------------------------------------------------------- settings without effect


def settings_without_effect(run_dir: Path, scene=None) -> dict[tuple[str, str], str]:
    """{(stage, parameter): why it had no effect} for the settings of this run that did nothing,
    from what each stage's artifact records it did (not from what was asked)."""
    out: dict[tuple[str, str], str] = {}
    tr = read_artifact(run_dir, "train")
    if tr is not None:
        p = (tr.get("meta") or {}).get("params") or {}
        td = tr["data"]
        used = td.get("settings") or {}  # the values training used (a preset's filled in)
        init = td.get("init")
        if p.get("layout_reg", True) and init in ("random", "depth"):
            why = (f"no layout cloud: the model started from {init} points, so L_layout had no layout "
                   "Gaussians to act on")
            out[("train", "layout_reg")] = why
            if p.get("lambda_layout") is not None:
                out[("train", "lambda_layout")] = why
        elif p.get("layout_reg") is False and p.get("lambda_layout") is not None:
            out[("train", "lambda_layout")] = "layout_reg is off"
        if p.get("appearance"):
            n = _train_panoramas(run_dir, scene, td)
            if n is not None and n < 2:
                out[("train", "appearance")] = (
                    "one training panorama: a per-panorama colour transform has no other panorama to differ "
                    "from, so it only trades off against the model's own colours")
        else:
            for k in ("lambda_appearance", "pin_appearance_mean", "lr_appearance"):
                if k in p and not _same(p[k], _default("train", k)):
                    out[("train", k)] = "appearance is off"
        projection = td.get("projection", p.get("projection"))
        if projection != "crops":
            for k in ("crop_fov", "crop_elevations", "crop_counts", "crop_size"):
                if k in p and not _same(p[k], _default("train", k)):
                    out[("train", k)] = f"used by projection 'crops' only; this model is '{projection}'"
        # schedules: only settings the user changed are named (a preset's own schedule is by design)
        iterations = td.get("iterations")
        start = used.get("densify_from")
        if isinstance(iterations, int) and isinstance(start, int) and start >= iterations:
            for k in ("densify_from", "densify_until", "densify_every", "densify_grad_threshold",
                      "percent_dense", "max_gaussians"):
                if k in p and not _same(p[k], _default("train", k)):
                    out[("train", k)] = (f"densification never ran: it starts at iteration {start}, training "
                                         f"stopped at {iterations}")
        reset = used.get("opacity_reset_every")
        if isinstance(iterations, int) and isinstance(reset, int) and 0 < iterations <= reset \
                and p.get("opacity_reset_every") is not None:
            out[("train", "opacity_reset_every")] = (f"no opacity reset happened: the first is due at "
                                                     f"iteration {reset}, training stopped at {iterations}")
    al = read_artifact(run_dir, "align")
    if al is not None:
        p = (al.get("meta") or {}).get("params") or {}
        d = al["data"]
        if not d.get("aligned_to_layout"):
            why = "no layout to align the depth to (the depth kept its own scale)"
            for k in ("inlier_threshold", "min_inlier_share", "labels", "ransac_iterations", "icp",
                      "icp_max_distance", "icp_iterations", "icp_max_points", "icp_max_change"):
                if k in p and not _same(p[k], _default("align", k)):
                    out[("align", k)] = why
        elif p.get("icp") is False:
            for k in ("icp_max_distance", "icp_iterations", "icp_max_points", "icp_max_change"):
                if k in p and not _same(p[k], _default("align", k)):
                    out[("align", k)] = "icp is off"
        kinds = {f.get("kind") for f in d.get("fits", []) if isinstance(f, dict)}
        if kinds and kinds <= {"metric"} and "affine_fit" in p \
                and not _same(p["affine_fit"], _default("align", "affine_fit")):
            out[("align", "affine_fit")] = ("every depth map is metric: there is no scale and shift per view "
                                            "to fit")
    dp = read_artifact(run_dir, "depth")
    if dp is not None:
        p = (dp.get("meta") or {}).get("params") or {}
        if p.get("projection", "equirect") != "cubemap":
            for k in ("face_size", "face_fov_deg", "perspective_axis"):
                if k in p and not _same(p[k], _default("depth", k)):
                    out[("depth", k)] = "used by projection 'cubemap' only"
    ev = read_artifact(run_dir, "evaluate")
    if ev is not None:
        p = (ev.get("meta") or {}).get("params") or {}
        if not ev["data"].get("lpips_available"):
            why = f"no LPIPS computed ({ev['data'].get('lpips_reason') or 'unavailable'})"
            for k in ("lpips_net", "lpips_weights"):
                if k in p and not _same(p[k], _default("evaluate", k)):
                    out[("evaluate", k)] = why
    return out


#: What _default returns for a parameter no stage declares (a custom stage, a renamed parameter).
UNKNOWN = object()


@functools.lru_cache(maxsize=1)
def _registry_defaults() -> dict[str, dict]:
    from pipeline.registry import build_registry

    out: dict[str, dict] = {}
    for name, spec in build_registry().items():
        for key, field in spec.params.model_fields.items():
            if not field.is_required():
                value = field.get_default(call_default_factory=True)
                out.setdefault(name, {})[key] = list(value) if isinstance(value, tuple) else value
    return out


def _default(stage: str, key: str):
    """The stage parameter's default (UNKNOWN when no stage declares it)."""
    return _registry_defaults().get(stage, {}).get(key, UNKNOWN)


def _train_panoramas(run_dir: Path, scene, td: dict) -> int | None:
    if scene is not None:
        return sum(1 for v in scene.views if v.split == "train")
    path = stage_file(run_dir, "train", td.get("appearance"))
    try:
        return len(json.loads(path.read_text())) if path is not None else None
    except (OSError, ValueError, TypeError):
        return None


def flatten_params(params: dict, prefix: str = "") -> list[tuple[str, str]]:
    """Nested parameters as (dotted name, value) rows; lists, booleans and None as JSON."""
    rows = []
    for k, v in params.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            rows += flatten_params(v, key + ".")
        else:
            rows.append((key, v if isinstance(v, str) else json.dumps(v)))
    return rows


def _run_defaults(stage: str, params: dict) -> dict:
    """{parameter: its default in this run}: the stage's Params.default(key) where its defaults
    depend on other settings (train's preset and projection), else the field's default."""
    from pipeline.registry import build_registry

    spec = build_registry().get(stage)
    if spec is not None and hasattr(spec.params, "default"):
        try:
            obj = spec.params.model_validate(params)
            return {k: _json_value(obj.default(k)) for k in spec.params.model_fields}
        except ValueError:  # parameters a later version no longer accepts: the fields' defaults
            pass
    return _registry_defaults().get(stage, {})


def _json_value(v):
    return list(v) if isinstance(v, tuple) else v


def settings_section(doc, params: dict[str, dict], not_applied: dict[tuple[str, str], str],
                     used: dict[str, dict] | None = None) -> str | None:
    """Every stage parameter: the value used (``used[stage]``, what a stage's artifact records it
    resolved, e.g. train's preset values, else the value recorded), its default in this run and
    what was changed; the changed ones first, all of them in a fold. A setting that had no effect
    says so and why (and is listed on its own above the table)."""

    doc.h(2, "Configuration", "config")
    if not params:
        doc.p("No stage artifact records its parameters yet.", "warn")
        return None
    if not_applied:
        doc.h(3, "Settings that had no effect")
        doc.table(["parameter", "value", "why it had no effect"],
                  [[f"{st}.{k}", _value_text(params.get(st, {}).get(k)), why]
                   for (st, k), why in not_applied.items()])
    changed, default = [], []
    for st, recorded in params.items():
        p = {k: (used or {}).get(st, {}).get(k, v) if v is None else v for k, v in recorded.items()}
        defaults = _run_defaults(st, recorded)
        for k, v in flatten_params(p) or [("(none recorded)", "")]:
            top = k.split(".")[0]
            note = ("not applied: " + not_applied[(st, top)]) if (st, top) in not_applied else ""
            d = defaults.get(top, UNKNOWN) if top in p else UNKNOWN
            is_default = d is not UNKNOWN and _same(p[top], d)
            if not is_default:
                note = "changed" + (f"; {note}" if note else "")
            (default if is_default else changed).append([f"{st}.{k}", v, "—" if d is UNKNOWN else _value_text(d),
                                                         note])
    doc.p(f"{len(changed)} parameter{'s' if len(changed) != 1 else ''} set away from the default, "
          f"{len(default)} at the default; values are those used (a preset's filled in); config.yaml "
          "beside this report has the settings as given.")
    header = ["parameter", "value used", "default", "note"]
    if changed:
        doc.table(header, changed)
    doc.details(f"all {len(changed) + len(default)} parameters (defaults included)", header,
                changed + default)
    return "config"


def _same(a, b) -> bool:
    if a is UNKNOWN or b is UNKNOWN:
        return False
    a = list(a) if isinstance(a, tuple) else a
    b = list(b) if isinstance(b, tuple) else b
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        return math.isclose(a, b, rel_tol=1e-12, abs_tol=0.0)
    return a == b


def _value_text(v) -> str:
    return v if isinstance(v, str) else json.dumps(v)
