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
    return run


@pytest.fixture(scope="module")
def report(run_dir, sim_scene):
    return build_report(run_dir, sim_scene)


def test_report_has_every_section(report):
    assert report.sections == ["metrics", "views", "training", "floorplan", "durations"]
    md = report.markdown.read_text()
    for heading in ("Test metrics", "Views", "Training", "Floor plan", "Stage durations"):
        assert heading in md
    assert "LPIPS unavailable: disabled" in md
    # every image the Markdown names lies beside it and is a PNG
    names = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(names) == 4 + 1 + 1 + 1  # one view's 4 images, curves, floor plan, durations
    assert len(set(names)) == len(names)  # gt / render / error / depth are four files, not one
    for n in names:
        assert cv2.imread(str(report.folder / n)) is not None, n
    assert "| mean |" in md


def test_training_series_tolerates_key_names():
    recs = [{"iter": 1, "total_loss": 0.5, "train_psnr": 12.0, "elapsed": 0.1},
            {"iter": 2, "total_loss": 0.4, "n_gaussians": 10, "elapsed": 0.2}]
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
    # No external resource at all: the page must stand alone.
    page = report.html.read_text()
    assert not re.search(r"""(src|href)=["'](?!data:)""", page)
    dom = _chromium(["--dump-dom", url], tmp_path)
    assert dom.returncode == 0, dom.stderr[-2000:]
    imgs = re.findall(r"<img[^>]*>", dom.stdout)
    assert len(imgs) == 7
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
    assert html.count("<img") == 8 and "improves on 3D-GS* by +2.00 dB" in html
    assert "<td>12.00 ± 0.00</td>" in html
