"""The report: content of the Markdown twin, and the HTML rendered by headless Chromium."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from evalhelpers import run_evaluate, write_train_artifact

from evaluation.report import build_report, stage_durations, training_series
from evaluation.report_plots import plot_floor_plan, plot_training_curves

CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture(scope="module")
def run_dir(sim_scene, sim_model, tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    write_train_artifact(run, sim_model, resolution=(32, 64), duration_s=12.5)
    run_evaluate(sim_scene, run, fps_repeats=1, lpips=False)
    log = [{"time": "t", "stage": "train", "event": "ok", "duration_s": 12.5},
           {"time": "t", "stage": "evaluate", "event": "ok", "duration_s": 0.5},
           {"time": "t", "stage": "layout", "event": "skipped", "reason": "no layout"}]
    (run / "run_log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in log) + '{"half-written')
    (run / "render").mkdir()
    (run / "render" / "flythrough-train-pano.mp4").write_bytes(b"not really a video")
    art = json.loads((run / "train" / "artifact.json").read_text())
    art["meta"]["params"] = {"iterations": 50, "preset": "fast", "lr": {"means": 0.00016}, "background": None}
    (run / "train" / "artifact.json").write_text(json.dumps(art))
    return run


@pytest.fixture(scope="module")
def report(run_dir, sim_scene):
    return build_report(run_dir, sim_scene)


def test_report_has_every_section(report):
    assert report.sections == ["files", "metrics", "views", "training", "floorplan", "config", "durations"]
    md = report.markdown.read_text()
    for heading in ("Files", "Test metrics", "Views", "Training", "Floor plan", "Configuration", "Stage durations"):
        assert heading in md
    assert "LPIPS unavailable: disabled" in md
    # every image the Markdown names lies beside it and is a PNG
    names = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    # one view: gt, render, error, depth, gt depth, depth error + 4 colour bars; 2 training charts,
    # floor plan, durations
    assert len(names) == 10 + 2 + 1 + 1
    assert len(set(names)) == len(names)  # gt / render / error / depth are four files, not one
    for n in names:
        assert cv2.imread(str(report.folder / n)) is not None, n
    assert "| mean |" in md
    # the model's cost beside its metrics (write_train_artifact: 50 iterations, 1.0 s, a 360° model)
    assert "Gaussians after 50 iterations (one training image each) in 1.0 s of training; 360° splatting, " \
           "test panoramas rendered directly." in md


def test_training_series_reads_the_columns_the_trainer_writes():
    recs = [{"iteration": 1, "loss": 0.5, "psnr": 12.0, "seconds": 0.1},
            {"iteration": 2, "loss": 0.4, "psnr": None, "num_gaussians": 10, "seconds": 0.2}]
    s = training_series(recs)
    assert s["iteration"].tolist() == [1, 2] and s["loss"].tolist() == [0.5, 0.4]
    assert np.isnan(s["psnr"][1]) and np.isnan(s["num_gaussians"][0])
    assert s["elapsed"].tolist() == [0.1, 0.2]


def test_stage_durations(run_dir):
    rows = {r["stage"]: r for r in stage_durations(run_dir)}
    assert rows["train"]["duration_s"] == 12.5 and rows["train"]["runs"] == 1
    assert rows["layout"]["status"].startswith("skipped")
    assert "union" not in rows


def test_report_without_evaluation_says_what_to_run(tmp_path, sim_scene):
    r = build_report(tmp_path, sim_scene)
    text = r.markdown.read_text()
    assert "No evaluation yet" in text and "No training artifact" in text
    assert r.sections == ["floorplan"]  # drawn from the scene's poses


def _chromium(args: list[str], tmp: Path, timeout: int = 90) -> subprocess.CompletedProcess:
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
           f"--user-data-dir={tmp / 'profile'}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium absent (Debian package 'chromium'; make installs it)")
def test_html_renders_in_headless_chromium(report, tmp_path):
    url = report.html.resolve().as_uri()
    # Every image embedded: the page stands alone; its only hrefs are relative links to the run's files.
    page = report.html.read_text()
    assert not re.search(r"""src=["'](?!data:)""", page)
    assert not re.search(r"""href=["'](?![^"':]+["'])""", page)  # no scheme, nothing absolute
    dom = _chromium(["--dump-dom", url], tmp_path)
    assert dom.returncode == 0, dom.stderr[-2000:]
    imgs = re.findall(r"<img[^>]*>", dom.stdout)
    assert len(imgs) == 14
    for tag in imgs:
        m = re.search(r'src="data:image/png;base64,([^"]+)"', tag)
        assert m, tag[:200]
        arr = cv2.imdecode(np.frombuffer(base64.b64decode(m.group(1)), np.uint8), cv2.IMREAD_COLOR)
        assert arr is not None and arr.size > 0
    assert "Stage durations" in dom.stdout
    # Every image decoded in the browser: naturalWidth > 0 is not visible in the DOM dump,
    # so check the screenshot instead — non-blank, with the images' colours in it.
    shot = tmp_path / "shot.png"
    r = _chromium([f"--screenshot={shot}", "--window-size=1200,2400", "--hide-scrollbars", url], tmp_path)
    assert shot.is_file(), r.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (2400, 1200)
    assert img.std() > 20  # not a blank page
    colourful = (img.max(axis=2).astype(int) - img.min(axis=2)) > 60
    assert colourful.mean() > 0.01  # the embedded images (renders, colour maps) show


def test_report_includes_experiments_when_present(run_dir, sim_scene, tmp_path):
    from evaluation import experiments as E

    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    rows = []
    for label, p in (("3D-GS*", 12.0), ("+ layout init", 14.0)):
        r = E.AblationRow(label, label, {})
        r.runs = [{"psnr": p, "ssim": 0.5, "ws_psnr": p, "lpips": None, "train_seconds": 1.0, "num_gaussians": 9}]
        rows.append(r)
    (run / "ablate").mkdir()
    E.plot_ablation(rows, run / "ablate" / "ablation.png")
    (run / "ablate" / "ablation.md").write_text("# x\n\n" + E.ablation_table(rows) + "\n")
    (run / "ablate" / "ablation.json").write_text(json.dumps({"notes": E.ordering_notes(rows)}))
    rep = build_report(run, sim_scene)
    assert rep.sections[-1] == "ablate"
    html = rep.html.read_text()
    assert html.count("<img") == 15 and "improves on 3D-GS* by +2.00 dB" in html
    assert "<td>12.00 ± 0.00</td>" in html


# ----------------------------------------------------------------------------- colour bars, depth, cameras, links


def test_report_false_colour_maps_have_colour_bars_with_units(report):
    page = report.html.read_text()
    bars = re.findall(r'<img class="cbar" alt="colour bar: ([^"]+)"', page)
    # error, rendered depth, ground-truth depth, depth error
    assert len(bars) == 4
    assert any("image intensity" in b and "0 … 0.25" in b for b in bars)
    assert sum("distance along the ray (m)" in b for b in bars) == 2
    assert any("depth| (m)" in b for b in bars)
    for b in bars:
        assert re.search(r"\d … \d", b), b  # its range
    md = report.markdown.read_text()
    for kind in ("error", "depth", "gt-depth", "depth-error"):
        png = report.folder / "img" / f"view-test_00-colorbar-{kind}.png"
        assert cv2.imread(str(png)) is not None and f"img/{png.name}" in md


def test_ground_truth_depth_maps_only_where_gt_exists(report, run_dir, sim_scene, tmp_path):
    img = report.folder / "img"
    assert (img / "view-test_00-gt-depth.png").is_file() and (img / "view-test_00-depth-error.png").is_file()
    assert "Depth error over" in report.markdown.read_text()
    # the same run reported against a scene without ground-truth depth
    views = [v.model_copy(update={"gt_depth": None}) for v in sim_scene.manifest.views]
    no_gt = sim_scene.model_copy(update={"manifest": sim_scene.manifest.model_copy(update={"views": views})})
    rep = build_report(run_dir, no_gt, out_dir=tmp_path / "rep")
    names = {p.name for p in (rep.folder / "img").iterdir()}
    assert "view-test_00-gt-depth.png" not in names and "view-test_00-depth-error.png" not in names
    assert "view-test_00-colorbar-depth.png" in names  # the rendered depth keeps its bar
    md = rep.markdown.read_text()
    assert "|depth error|" not in md.replace("\\|", "|") and "Depth error over" not in md


def test_floor_plan_labels_every_camera(report, sim_scene, tmp_path):
    names = [v.name for v in sim_scene.views]
    assert {v.split for v in sim_scene.views} == {"train", "test"}
    assert report.camera_labels == names
    md = report.markdown.read_text()
    assert all(f"{v.name} ({v.split})" in md for v in sim_scene.views)
    rooms = [{"polygon": [[-2, -2], [2, -2], [2, 2], [-2, 2]], "holes": []}]
    assert plot_floor_plan(sim_scene, tmp_path / "p.png", rooms) == names
    assert cv2.imread(str(tmp_path / "p.png")) is not None
    assert plot_floor_plan(None, tmp_path / "q.png") == [] and not (tmp_path / "q.png").exists()


def test_training_chart(report, tmp_path):
    md = report.markdown.read_text()
    assert "Test PSNR is measured only at the end" in md
    assert "img/training_curves.png" in md
    shape = cv2.imread(str(report.folder / "img" / "training_curves.png")).shape
    assert shape[1] >= 1000  # big enough to read
    recs = [{"iteration": i, "loss": 1.0 / i, "psnr": 10.0 + i} for i in range(1, 21)]
    labels = plot_training_curves(training_series(recs), tmp_path / "c.png", (20.0, 28.0, "final test"))
    assert "final test" in labels and "training loss" in labels
    assert plot_training_curves({}, tmp_path / "none.png") == []


def test_report_links_resolve_and_move_with_the_run(report, run_dir, sim_scene, tmp_path):
    import yaml

    page = report.html.read_text()
    hrefs = re.findall(r'href="([^"]+)"', page)
    assert hrefs == report.links
    assert "../train/point_cloud.ply" in hrefs and "../render/flythrough-train-pano.mp4" in hrefs
    assert "config.yaml" in hrefs and "../run_log.jsonl" in hrefs
    md = report.markdown.read_text()
    for h in hrefs:
        assert (report.folder / h).is_file(), h
        assert f"]({h})" in md
    cfg = yaml.safe_load((report.folder / "config.yaml").read_text())
    assert cfg["stages"]["train"]["iterations"] == 50 and cfg["stages"]["train"]["lr"] == {"means": 0.00016}
    assert "| train.lr.means | 0.00016 |" in md and "| train.preset | fast |" in md
    # move the run folder (report included): every link still resolves
    moved = tmp_path / "elsewhere" / "run"
    shutil.copytree(run_dir, moved)
    for h in hrefs:
        assert (moved / "report" / h).is_file(), h


def test_per_view_table_lists_each_view(run_dir, sim_scene, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    path = run / "evaluate" / "artifact.json"
    art = json.loads(path.read_text())
    first = art["data"]["views"][0]
    first["psnr"] = 35.0
    art["data"]["views"].append({**first, "view": "test_01", "psnr": 19.0, "ssim": 0.5})
    path.write_text(json.dumps(art))
    md = build_report(run, sim_scene).markdown.read_text()
    rows = [ln for ln in md.splitlines() if ln.startswith("| test_0")]
    assert [r.split("|")[1].strip() for r in rows] == ["test_00", "test_01"]
    assert "| 35 |" in rows[0] and "| 19 |" in rows[1]
    assert "best test_00 35.00 dB, worst test_01 19.00 dB (16.00 dB apart)" in md
    header = next(ln for ln in md.splitlines() if ln.startswith("| view |"))
    assert "PSNR of a flat image (dB)" in header and "SSIM of a flat image" in header  # the floor, beside


def test_report_shows_baseline_and_360_side_by_side(run_dir, sim_scene, tmp_path):
    """With an ablation's baseline and 360 rows, the report shows their held-out render, error and
    depth side by side (here both rows point at the same evaluated run), depths on one scale."""
    from evaluation import experiments as E

    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    rows = []
    for key, label, proj in (("layout-init", "+ layout init", "crops"), ("layout-reg", "+ layout reg", "360")):
        r = E.AblationRow(key, label, {"projection": proj})
        r.runs = [{"psnr": 14.0, "ssim": 0.5, "dir": str(run)}]
        rows.append(r)
    (run / "ablate").mkdir()
    E.plot_ablation(rows, run / "ablate" / "ablation.png")
    (run / "ablate" / "ablation.json").write_text(json.dumps(
        {"notes": [], "variants": [{"key": r.key, "label": r.label, "settings": r.settings, "runs": r.runs}
                                   for r in rows]}))
    rep = build_report(run, sim_scene)
    md = rep.markdown.read_text()
    assert "Held-out views: baseline against 360" in md
    ev = json.loads((run / "evaluate" / "artifact.json").read_text())["data"]["views"]
    name = ev[0]["view"]
    for key in ("layout-init", "layout-reg"):
        assert f"+ {'layout init' if key == 'layout-init' else 'layout reg'}: render, PSNR" in md
        depth = cv2.imread(str(rep.folder / "img" / f"ablate-{name}-{key}-depth.png"))
        assert depth is not None and depth.std() > 0
    # one depth scale for both: the same model drawn twice gives the same picture
    a, b = (cv2.imread(str(rep.folder / "img" / f"ablate-{name}-{k}-depth.png")) for k in ("layout-init", "layout-reg"))
    assert np.array_equal(a, b)


def test_sizes_read_height_by_width_and_the_kernel_build_is_apart(run_dir, sim_scene, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    art = json.loads((run / "train" / "artifact.json").read_text())
    art["data"]["kernel_build_seconds"] = 61.25
    (run / "train" / "artifact.json").write_text(json.dumps(art))
    md = " ".join(build_report(run, sim_scene).markdown.read_text().split())
    h, w = json.loads((run / "evaluate" / "artifact.json").read_text())["data"]["resolution"]
    assert h < w  # a panorama: H×W reads e.g. 16×32, as the CLI and the settings say
    assert f"for a {h}×{w} (H×W) panorama" in md and f"evaluated at {h}×{w}" in md and f"{w}×{h}" not in md
    train_s = art["data"]["train_seconds"]
    assert f"in {train_s:.1f} s of training (after 61.2 s compiling the C++ kernel, once per machine)" in md
