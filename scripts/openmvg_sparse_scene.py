r"""A sparse real walk-through from ../shared/data/openmvg_flat, for docs/training.md's real-pixel
360-against-crops study (issue 39).

Writes OUT (a scene folder) with `pano-pipe new`'s defaults (pipeline.new_scene.new_scene: the 11
hand-held THETA panoramas copied, no poses, the 35° nadir cap, no camera height, `new`'s pano-pipe.yaml; the
studies before docs/training.md's "Settings for real captures" ran without that file: repeat them
with `--set train.random_turn_interp=bicubic`), then makes the
split sparse: only the TRAIN panoramas (by default the two ends of the walk and its middle,
R0010210, R0010215, R0010220) train, every other one is "split": "test". The poses stage places all
11 whatever the split (docs/poses.md: test views are posed with the others and left out of
training), so held-out views keep their poses. With --run RUN_DIR the poses stage is run too (at
--working-height rows; it caches in RUN_DIR/poses) and each view's position and its distance to the
nearest training camera is printed.

    PYTHONPATH=$PWD .venv/bin/python scripts/openmvg_sparse_scene.py /tmp/i39/flat3 \
        --run /tmp/i39/base3 --working-height 256
    PYTHONPATH=$PWD .venv/bin/python scripts/openmvg_sparse_scene.py /tmp/i39/flat4 \
        --train R0010210,R0010213,R0010217,R0010220

A study then passes the same `--set poses.working_height=H` to scripts/study_360.py (its --base is
the run folder whose upstream stages are shared), so the poses stage is not rerun at another height.

`diagnose SCENE RUN...` measures the study's run folders on their held-out views: holes (accumulated
alpha), brightness (mean render against ground truth per channel, colour-fit PSNR, the learned
appearance transforms' mean), and where the error sits (near or far from the training cameras;
ceiling, walls and floor by latitude band; per band also the render's local detail in SSIM's window
over the ground truth's, "texture"), then prints mean ± std per variant over the seeds:

    PYTHONPATH=$PWD .venv/bin/python scripts/openmvg_sparse_scene.py diagnose /tmp/i39/flat3 \
        /tmp/i39/s128-runs/{crops,360}-s{0,1,2} [--per-view]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "openmvg_flat"
DEFAULT_TRAIN = ("R0010210", "R0010215", "R0010220")


def make_scene(out: Path, train: tuple[str, ...]) -> Path:
    from pipeline.new_scene import new_scene

    images = sorted((DATA / "images").glob("*.jpg"))
    names = {p.stem for p in images}
    if missing := [t for t in train if t not in names]:
        raise SystemExit(f"--train: {', '.join(missing)} not among {DATA / 'images'}'s panoramas")
    if (out / "scene.json").is_file():
        raise SystemExit(f"{out}: already a scene (give a new or empty folder)")
    path = new_scene(out, images, test_every=0)  # every view trains; the split is set below
    scene = json.loads(path.read_text())
    for view in scene["views"]:
        view["split"] = "train" if view["name"] in train else "test"
    path.write_text(json.dumps(scene, indent=1))
    held = [v["name"] for v in scene["views"] if v["split"] == "test"]
    print(f"wrote {out}: {len(scene['views'])} panoramas, training {', '.join(train)}; {len(held)} held out")
    return path


def run_poses(scene_dir: Path, run_dir: Path, working_height: int | None) -> None:
    from pipeline.engine import Engine
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    config = {"poses": {"working_height": working_height}} if working_height else {}
    engine = Engine(
        load_scene(scene_dir), run_dir, build_registry(), config, config_source="openmvg_sparse_scene"
    )
    engine.run(until="poses")
    views = engine.completed_scene("train").manifest.views
    posed = [v for v in views if v.pose is not None]
    centre = {v.name: np.asarray(v.pose, dtype=np.float64)[:3, 3] for v in posed}
    train = [v.name for v in posed if v.split == "train"]
    print(f"poses: {len(posed)} of {len(views)} placed")
    for v in views:
        if v.name not in centre:
            print(f"  {v.name} {v.split}: not placed")
            continue
        c = centre[v.name]
        near = min(
            ((float(np.linalg.norm(c - centre[t])), t) for t in train if t != v.name), default=(np.nan, "-")
        )
        print(
            f"  {v.name} {v.split:5s} at ({c[0]:+.2f}, {c[1]:+.2f}, {c[2]:+.2f}) m; "
            f"nearest training camera {near[1]} {near[0]:.2f} m"
        )


BANDS = (("ceiling", 30.0, 90.0), ("walls", -30.0, 30.0), ("floor", -90.0, -30.0))  # latitude, degrees
NEAR_M = 0.3  # a held-out view this close to a training camera counts as near


def _psnr(mse: float) -> float:
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def local_std(image: np.ndarray) -> np.ndarray:
    """[H,W,C] standard deviation in SSIM's window (evaluation.metrics.gaussian_window) around each
    pixel: the variance whose uncorrelated part SSIM's structure term charges."""
    import cv2

    from evaluation.metrics import gaussian_window

    k = gaussian_window()
    image = image.astype(np.float32)
    mean = cv2.sepFilter2D(image, -1, k, k)
    return np.sqrt(np.clip(cv2.sepFilter2D(image * image, -1, k, k) - mean * mean, 0.0, None))


def diagnose_run(scene, run: Path) -> list[dict]:
    """Per held-out view of `run` (a study run folder: train + evaluate): the render's accumulated
    alpha (mean, and the fraction below 0.5: holes), its mean colour against the ground truth's per
    channel (0-255), PSNR and colour-fit PSNR (evaluation.metrics.colour_fit over the view's valid
    pixels), SSIM, the same per latitude band (the fit is the whole view's), PSNR with what the
    background shows filled by the training panoramas' mean colour (render + (1 - alpha) * mean:
    what closing the holes with that colour would give), PSNR with the mean of the training
    panoramas' learned appearance transforms applied (the gauge), the alpha on dark pixels, and the
    distance to the nearest training camera; and, where the run has a layout, where the model puts
    the room against it (`layout_depth_ratios`, one figure per run). Renders as the evaluate stage does (crops stitched from their
    rig, against the background the model was trained against) at its resolution, and reads its ground
    truth."""
    import torch

    from evaluation import metrics as M
    from evaluation.model_io import equirect_camera, load_model, recorded_background, render_pose
    from panogeom.images import read_rgb
    from pipeline.engine import complete_scene, read_meta, read_output
    from pipeline.registry import build_registry
    from schemas.scene_loader import valid_mask
    from evaluation.metrics import flat_metrics
    from stages.evaluate import stitch_rig, training_mean_colour

    done = complete_scene(scene, run, build_registry())
    tdata, ev = read_output(run, "train"), read_output(run, "evaluate")
    g = load_model(run / "train" / "point_cloud.ply")
    meta = read_meta(run / "train")
    background = np.asarray(
        recorded_background(tdata.settings, None if meta is None else meta.params) or (0.0, 0.0, 0.0)
    )
    h, w = ev.resolution
    lat = 90.0 - (np.arange(h) + 0.5) * 180.0 / h
    train = [v for v in done.manifest.views if v.split == "train" and v.pose is not None]
    centres = np.array([np.asarray(v.pose_matrix)[:3, 3] for v in train])
    train_mean = np.mean(
        [read_rgb(done.image_path(v), size=(h, w)).reshape(-1, 3).mean(0) for v in train], axis=0
    )
    train_mean = train_mean / 255.0 if train_mean.max() > 1.5 else train_mean
    logged = {m.view: m for m in ev.views}
    flat_colour = training_mean_colour(done, (h, w))  # the floor: evaluate's flat image
    # the appearance gauge: the mean over the training panoramas of their learned gain and bias (test
    # views are rendered without one); applied to the test renders, what pinning it would roughly give
    gauge = None
    if (run / "train" / "appearance.json").is_file():
        tr = json.loads((run / "train" / "appearance.json").read_text())
        gauge = (
            np.mean([t["gain"] for t in tr.values()], axis=0),
            np.mean([t["bias"] for t in tr.values()], axis=0),
        )
    rows = []
    for v in done.manifest.test_views():
        if v.pose is None:
            continue
        gt = read_rgb(run / "evaluate" / "gt" / f"{v.name}.png").astype(np.float32)
        gt = gt / 255.0 if gt.max() > 1.5 else gt
        # drawn against black, so that both the evaluated render (over the trained background) and the
        # holes filled by the training mean are one blend away
        r = render_pose(
            g, v.pose_matrix, equirect_camera(h, w), background=torch.zeros(3), rig=stitch_rig(tdata, (h, w))
        )
        image = np.clip(r.image + (1.0 - r.alpha[..., None]) * background, 0.0, 1.0)
        mask = valid_mask(done, v, h, w)
        mask = np.ones((h, w), bool) if mask is None else mask
        fitted = M.colour_fit(image, gt, mask)
        filled = np.clip(r.image + (1.0 - r.alpha[..., None]) * train_mean, 0.0, 1.0)
        err, err_fit = ((image - gt) ** 2).mean(-1), ((fitted - gt) ** 2).mean(-1)
        std_render, std_gt = local_std(image).mean(-1), local_std(gt).mean(-1)
        dark = gt.mean(-1) < 0.2
        row = {
            "view": v.name,
            "nearest_train_m": float(
                np.min(np.linalg.norm(centres - np.asarray(v.pose_matrix)[:3, 3], axis=1))
            ),
            "psnr": _psnr(err[mask].mean()),
            "psnr_logged": logged[v.name].psnr if v.name in logged else None,
            "psnr_colorfit": _psnr(err_fit[mask].mean()),
            "ssim": M.ssim(image, gt, mask=mask),
            "ssim_colorfit": M.ssim(fitted, gt, mask=mask),
            **flat_metrics(flat_colour, gt, mask),
            "psnr_filled": _psnr(((filled - gt) ** 2).mean(-1)[mask].mean()),
            "psnr_gauge": (
                _psnr(((np.clip(image * gauge[0] + gauge[1], 0, 1) - gt) ** 2).mean(-1)[mask].mean())
                if gauge is not None
                else None
            ),
            "alpha": float(r.alpha[mask].mean()),
            "holes": float((r.alpha[mask] < 0.5).mean()),
            # where the alpha is low: the dark ground-truth pixels (luminance < 0.2), their share and alpha
            "dark_share": float(dark[mask].mean()),
            "dark_alpha": float(r.alpha[mask & dark].mean()) if (mask & dark).any() else None,
            "render_rgb": [round(float(x) * 255, 1) for x in image[mask].mean(0)],
            "gt_rgb": [round(float(x) * 255, 1) for x in gt[mask].mean(0)],
            "train_rgb": [round(float(x) * 255, 1) for x in train_mean],  # the training panoramas' mean
            "gauge_gain_bias": None
            if gauge is None
            else [[round(float(x), 3) for x in gauge[0]], [round(float(x) * 255, 1) for x in gauge[1]]],
        }
        for band, lo, hi in BANDS:
            m = mask & ((lat >= lo) & (lat < hi))[:, None]
            if m.any():
                row[f"{band}_psnr"], row[f"{band}_psnr_colorfit"] = (
                    _psnr(err[m].mean()),
                    _psnr(err_fit[m].mean()),
                )
                row[f"{band}_holes"] = float((r.alpha[m] < 0.5).mean())
                row[f"{band}_ssim"] = M.ssim(image, gt, mask=m)  # the band's pixels, the rest zeroed
                # texture: the render's local detail over the ground truth's (1 = as much; above 1 with
                # SSIM falling, detail that is not where the ground truth has it)
                row[f"{band}_texture"] = float(std_render[m].mean() / max(std_gt[m].mean(), 1e-12))
        rows.append(row)
    depth = layout_depth_ratios(done, run, g, tdata, h, w)  # one figure per run: on every row
    return [{**row, **depth} for row in rows]


def surface_distance_ratios(rendered, layout_distance: np.ndarray, label: np.ndarray) -> dict[str, np.ndarray]:
    """Per surface of the layout (panogeom.surfaces' labels), the rendered distance over the layout's at
    the opaque pixels (alpha > 0.5). `rendered` is evaluation.model_io.render_pose's: its depth is
    already the expected distance (normalised by alpha once; a second division would put every
    translucent surface behind its layout)."""
    from panogeom.surfaces import CEILING, FLOOR, WALL

    alpha, distance = np.asarray(rendered.alpha), np.asarray(rendered.depth)
    out = {}
    for name, code in (("ceiling", CEILING), ("walls", WALL), ("floor", FLOOR)):
        m = (label == code) & (alpha > 0.5) & np.isfinite(layout_distance)
        out[name] = distance[m] / layout_distance[m]
    return out


def layout_depth_ratios(done, run: Path, g, tdata, h: int, w: int) -> dict:
    """Where the model puts the room, against the layout: per surface of the layout (ceiling, walls,
    floor, as the layout labels each pixel), the median over the training views' pixels with alpha
    > 0.5 of the rendered (expected) distance over the layout's, rendered from each training
    view with a layout. 1 is on the layout; above it, behind. Empty without a layout stage."""
    import torch

    from evaluation.model_io import equirect_camera, render_pose
    from pipeline.engine import read_output
    from floorplan.layout_depth import layout_depth_map
    from stages.evaluate import stitch_rig

    layout = read_output(run, "layout")
    if layout is None:  # no layout stage in this run: nothing to compare with
        return {}
    layouts = {lv.view: lv for lv in layout.views}
    ratios: dict[str, list[np.ndarray]] = {}
    for v in done.manifest.views:
        lv = layouts.get(v.name)
        if v.split != "train" or v.pose is None or lv is None:
            continue
        ld, label = layout_depth_map(np.asarray(lv.floor_polygon), lv.camera_height, lv.ceiling_distance, h, w)
        r = render_pose(g, v.pose_matrix, equirect_camera(h, w), background=torch.zeros(3),
                        rig=stitch_rig(tdata, (h, w)))
        for name, r_surface in surface_distance_ratios(r, ld, label).items():
            ratios.setdefault(name, []).append(r_surface)
    return {f"{name}_depth_ratio": float(np.median(np.concatenate(rs))) for name, rs in ratios.items()
            if sum(x.size for x in rs)}


def summarise(rows: list[dict]) -> dict:
    """Means over views: all, near (nearest training camera < NEAR_M) and far."""
    keys = [
        k
        for k in rows[0]
        if k not in ("view", "render_rgb", "gt_rgb", "train_rgb", "gauge_gain_bias")
        and rows[0][k] is not None
    ]
    out = {k: float(np.mean([r[k] for r in rows if r.get(k) is not None])) for k in keys}
    out["render_rgb"] = [round(float(x), 1) for x in np.mean([r["render_rgb"] for r in rows], axis=0)]
    out["gt_rgb"] = [round(float(x), 1) for x in np.mean([r["gt_rgb"] for r in rows], axis=0)]
    out["train_rgb"] = rows[0]["train_rgb"]
    out["gauge_gain_bias"] = rows[0].get("gauge_gain_bias")
    for part, sel in (
        ("near", lambda r: r["nearest_train_m"] < NEAR_M),
        ("far", lambda r: r["nearest_train_m"] >= NEAR_M),
    ):
        chosen = [r for r in rows if sel(r)]
        if chosen:
            for k in ("psnr", "psnr_colorfit", "ssim", "holes"):
                out[f"{part}_{k}"] = float(np.mean([r[k] for r in chosen]))
    return out


TABLE_KEYS = (
    "psnr",
    "psnr_colorfit",
    "psnr_gauge",
    "ssim",
    "ssim_colorfit",
    "flat_psnr",
    "flat_ssim",
    "alpha",
    "holes",
    "dark_alpha",
    "psnr_filled",
    "near_psnr",
    "far_psnr",
    "near_ssim",
    "far_ssim",
    "ceiling_psnr",
    "walls_psnr",
    "floor_psnr",
    "ceiling_psnr_colorfit",
    "walls_psnr_colorfit",
    "floor_psnr_colorfit",
    "ceiling_ssim",
    "walls_ssim",
    "floor_ssim",
    "walls_holes",
    "floor_holes",
    "ceiling_texture",
    "walls_texture",
    "floor_texture",
    "ceiling_depth_ratio",
    "walls_depth_ratio",
    "floor_depth_ratio",
)


def diagnose(scene_dir: Path, runs: list[Path], per_view: bool) -> None:
    from schemas.scene_loader import load_scene

    scene = load_scene(scene_dir)
    by: dict[str, list[dict]] = {}
    for run in runs:
        rows = diagnose_run(scene, run)
        if per_view:
            for r in rows:
                print(
                    json.dumps(
                        {
                            "run": run.name,
                            **{k: round(x, 4) if isinstance(x, float) else x for k, x in r.items()},
                        }
                    ),
                    flush=True,
                )
        s = summarise(rows)
        by.setdefault(run.name.rsplit("-s", 1)[0], []).append(s)
        print(
            json.dumps(
                {
                    "run": run.name,
                    "summary": True,
                    **{k: round(x, 4) if isinstance(x, float) else x for k, x in s.items()},
                }
            ),
            flush=True,
        )
    # mean ± std over the seeds of each variant (run folders <variant>-s<seed>, as study_360 names them)
    print("| figure | " + " | ".join(f"{name} ({len(ss)})" for name, ss in by.items()) + " |")
    print("|---|" + "---|" * len(by))
    for k in TABLE_KEYS:
        cells = []
        for ss in by.values():
            vals = [x[k] for x in ss if x.get(k) is not None]
            d = 3 if any(w in k for w in ("alpha", "holes", "ssim", "ratio", "texture")) else 2
            cells.append(
                "—"
                if not vals
                else f"{np.mean(vals):.{d}f} ± {np.std(vals, ddof=1) if len(vals) > 1 else 0:.{d}f}"
            )
        print(f"| {k} | " + " | ".join(cells) + " |")
    for name, ss in by.items():
        rgb = np.mean([x["render_rgb"] for x in ss], axis=0)
        print(
            f"{name}: mean render RGB {rgb.round(1).tolist()}, ground truth {ss[0]['gt_rgb']}, "
            f"training panoramas {ss[0]['train_rgb']}; mean gain / bias (0-255) of the training panoramas' "
            f"appearance, per seed: {[x['gauge_gain_bias'] for x in ss]}"
        )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "diagnose":
        ap = argparse.ArgumentParser(
            description="held-out holes, brightness and where the error sits, per run"
        )
        ap.add_argument("scene", type=Path)
        ap.add_argument("runs", type=Path, nargs="+", help="study run folders (train + evaluate)")
        ap.add_argument("--per-view", action="store_true", help="also one line per held-out view")
        args = ap.parse_args(argv[1:])
        diagnose(args.scene, args.runs, args.per_view)
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="scene folder to write (new or empty)")
    ap.add_argument("--train", default=",".join(DEFAULT_TRAIN), help="training panoramas, comma separated")
    ap.add_argument("--run", type=Path, help="also run the poses stage into this run folder")
    ap.add_argument("--working-height", type=int, default=256, help="poses.working_height (rows) with --run")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        raise SystemExit(f"{DATA}: openmvg_flat is not there (see ../shared/data/README.md)")
    make_scene(args.out, tuple(t.strip() for t in args.train.split(",") if t.strip()))
    if args.run:
        run_poses(args.out, args.run, args.working_height)
    return 0


if __name__ == "__main__":
    sys.exit(main())
