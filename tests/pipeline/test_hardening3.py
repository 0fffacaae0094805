"""Hardening, third pass (issue 37): one test (or a few) per item, each failing before its fix.

The fuzz suite generates each class too: tests/fuzz/test_fuzz_hardening3.py.
"""

from __future__ import annotations

import ast
import contextlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote

import pytest
import torch
import yaml

from simulate.generate import generate_scene
from tests import hostile_files as hostile
from tests.clitools import invoke, run_main
from tests.pipeline.test_hardening2 import assert_one_line, tree

REPO = Path(__file__).resolve().parents[2]
FAST = ["--set", "train.iterations=5", "--set", "train.height=8"]
#: A test view name the docs allow, holding Markdown that a careless report turns into a link,
#: an image (a web beacon when remote) and a heading.
HOSTILE_VIEW = "Küche 1 [Süd] [click](evil.html) ![i](beacon.png) # h"


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished run of a scene whose test view has HOSTILE_VIEW as its name."""
    root = tmp_path_factory.mktemp("h3")
    generate_scene(root / "S", views=3, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    doc = json.loads((root / "S" / "scene.json").read_text())
    for v in doc["views"]:
        if v["split"] == "test":
            v["name"] = HOSTILE_VIEW
            v.pop("gt_depth", None)
    (root / "S" / "scene.json").write_text(json.dumps(doc))
    assert run_main(["run", "all", root / "S", "--out", root / "R", *FAST]) == 0
    return root


@pytest.fixture
def run(tmp_path, finished_run, monkeypatch) -> Path:
    """tmp/S (the scene), tmp/R (a finished run), tmp/secret/ (outside both), cwd tmp/cwd."""
    shutil.copytree(finished_run / "S", tmp_path / "S")
    shutil.copytree(finished_run / "R", tmp_path / "R")
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "evil.pth").write_bytes(b"not a checkpoint")
    (tmp_path / "secret" / "model.onnx").write_bytes(b"not a model")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    return tmp_path


def _status(run: Path, capsys, *extra):
    return invoke(["status", run / "S", "--out", run / "R", *extra], capsys)


def _scene_yaml(run: Path, settings) -> None:
    (run / "S" / "pano-pipe.yaml").write_text(settings if isinstance(settings, str) else yaml.safe_dump(settings))


# ----------------------------------------------------------------------------- 1. onnxruntime telemetry
def _columns_layout_onnx(path: Path) -> Path:
    from layoutnet.export import export_onnx

    class Columns(torch.nn.Module):
        def forward(self, x):
            m = x.mean(dim=(1, 2)).unsqueeze(1)
            return torch.cat([-(0.3 + 0.4 * m), 0.2 + 0.5 * m], dim=1), 4.0 * m - 2.0

    export_onnx(Columns(), path)
    return path


def test_a_run_with_an_onnx_model_writes_nothing_in_home(tmp_path):
    generate_scene(tmp_path / "S", views=2, test_views=0, height=16, effects="none")
    model = _columns_layout_onnx(tmp_path / "layout.onnx")
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ORT_", "XDG_", "PANO_PIPE_"))}
    env.update(HOME=str(home), PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", "from pipeline.cli import main; main()", "run", "layout",
                           str(tmp_path / "S"), "--out", str(tmp_path / "R"), "--set", f"layout.model={model}"],
                          env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    written = sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())
    # the documented caches (docs/security.md, "Writes"): matplotlib's font list is not one of them either
    assert written == [], written


def test_onnxruntime_is_used_only_through_models_onnxrt():
    """The class: any module that imports onnxruntime itself would skip the telemetry switch."""
    offenders = []
    for path in REPO.rglob("*.py"):
        rel = path.relative_to(REPO)
        if rel.parts[0] in (".venv", "tests") or rel.as_posix() == "models/onnxrt.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] == "onnxruntime" for n in names):
                offenders.append(str(rel))
    assert offenders == []


# ----------------------------------------------------------------------------- 2. non-finite settings and models
@pytest.mark.parametrize("setting", ["train.lr_position_init=inf", "train.lr_sh_dc=.inf", "train.extent=inf",
                                     "train.lambda_l1=1e400", "train.background=[.nan,0,0]",
                                     "evaluate.background=[.inf,0,0]"])
def test_non_finite_settings_are_refused_when_validated(run, setting, capsys):
    stage, param = setting.split("=")[0].split(".")
    assert_one_line(*_status(run, capsys, "--set", setting), param, "finite")
    _scene_yaml(run, f"{stage}: {{{param}: {setting.split('=')[1]}}}\n")  # the same from the scene's file
    assert_one_line(*_status(run, capsys), param, "finite")


def test_every_float_setting_of_every_stage_is_finite_checked():
    from pydantic import ValidationError

    from pipeline.registry import build_registry

    checked = 0
    for name, spec in build_registry().items():
        for field, info in spec.params.model_fields.items():
            if "float" not in str(info.annotation):
                continue
            value = [float("inf")] * 3 if "tuple" in str(info.annotation) else float("inf")
            with pytest.raises(ValidationError, match="finite"):
                spec.params.model_validate({field: value})
            checked += 1
    assert checked > 40


def test_a_model_of_nans_is_never_written_nor_exported(run, capsys, monkeypatch):
    from gaussians.ply import load_ply, save_ply

    ply = run / "R" / "train" / "point_cloud.ply"
    g = load_ply(ply)
    g.means[0, 0] = float("nan")
    with pytest.raises(ValueError, match="1 of .* NaN or Inf"):
        save_ply(run / "x.ply", g)
    assert not (run / "x.ply").exists()
    hostile.nan_model(ply)
    for fmt in ("ply", "splat", "spz", "mesh"):
        code, out, err = invoke(["export", run / "R", "--format", fmt], capsys)
        assert_one_line(code, out, err, "point_cloud.ply", "NaN or Inf")
    assert not (run / "R" / "export").exists() or not any((run / "R" / "export").iterdir())


def test_training_that_diverges_keeps_no_model(run, capsys, monkeypatch):
    import gaussians.trainer

    final = gaussians.trainer.Trainer.final_gaussians

    def diverged(self):  # what a NaN loss leaves: some Gaussians NaN
        g = final(self)
        g.sh_dc[: max(1, len(g) // 7)] = float("nan")
        return g

    monkeypatch.setattr(gaussians.trainer.Trainer, "final_gaussians", diverged)
    before = tree(run / "R" / "train")
    code, out, err = invoke(["run", "train", run / "S", "--out", run / "R", "--force", *FAST], capsys)
    assert_one_line(code, out, err, "train", "diverged", "NaN or Inf")
    assert tree(run / "R" / "train") == before


# ----------------------------------------------------------------------------- 3. report of a diverged run
def test_report_renders_whatever_metrics_exist(run, capsys):
    art = run / "R" / "evaluate" / "artifact.json"
    doc = json.loads(art.read_text())
    for v in doc["data"]["views"]:
        v["psnr"] = v["ssim"] = None
        v["ws_psnr"] = float("nan")
    doc["data"]["mean"] = {"psnr": None, "ssim": None}
    art.write_text(json.dumps(doc))
    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert code == 0, err
    md = (run / "R" / "report" / "report.md").read_text()
    assert "Missing from the evaluation" in md and "psnr, ssim" in md
    assert "PSNR — dB, SSIM —" in md


# ----------------------------------------------------------------------------- 4, 5. report.md is Markdown-safe
def _rendered_report(run: Path, capsys) -> tuple[str, str, str]:
    from markdown_it import MarkdownIt

    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert code == 0, err
    md = (run / "R" / "report" / "report.md").read_text(encoding="utf-8")
    html = (run / "R" / "report" / "report.html").read_text(encoding="utf-8")
    return md, MarkdownIt("commonmark").enable("table").render(md), html


def test_report_md_lets_no_markdown_through(run, capsys):
    from html.parser import HTMLParser

    hostile_value = "![i](http://beacon.example/p.png)\n# heading\u202e [x](evil.html)"
    art = run / "R" / "train" / "artifact.json"
    doc = json.loads(art.read_text())
    doc["meta"]["params"]["backend"] = hostile_value  # what a pano-pipe.yaml of hostile text would leave
    art.write_text(json.dumps(doc))
    md, rendered, html = _rendered_report(run, capsys)

    class Tags(HTMLParser):
        def __init__(self):
            super().__init__()
            self.tags = []

        def handle_starttag(self, tag, attrs):
            self.tags.append((tag, dict(attrs)))

    tags = Tags()
    tags.feed(rendered)
    hrefs = [a.get("href", "") for t, a in tags.tags if t == "a"]
    srcs = [a.get("src", "") for t, a in tags.tags if t == "img"]
    assert not [h for h in hrefs if "evil.html" in h]
    assert all(s.startswith("img/") for s in srcs), srcs  # no remote image, no beacon.png
    assert sum(t == "h1" for t, _ in tags.tags) == 1  # the title only
    for text in (md, html):
        assert "\u202e" not in text
    assert "\\u202e" in md and "\\u202e" in html  # shown, not obeyed
    assert "[click](evil.html)" in unquote(rendered) or "[click](evil.html)" in rendered


def test_report_md_images_resolve_for_names_the_docs_allow(run, capsys):
    from html.parser import HTMLParser

    md, rendered, _ = _rendered_report(run, capsys)

    class Srcs(HTMLParser):
        def __init__(self):
            super().__init__()
            self.srcs = []

        def handle_starttag(self, tag, attrs):
            if tag == "img":
                self.srcs.append(dict(attrs)["src"])

    parser = Srcs()
    parser.feed(rendered)
    view_images = [s for s in parser.srcs if "K%C3%BCche" in s]
    assert view_images, parser.srcs
    for src in parser.srcs:
        assert (run / "R" / "report" / unquote(src)).is_file(), src


# ----------------------------------------------------------------------------- 6. a scene file reaching outside
@pytest.mark.parametrize("target", ["secret-yaml", "/etc/passwd", "dangling", "folder"])
def test_a_scene_settings_file_must_be_a_file_of_the_scene(run, target, capsys):
    own = run / "S" / "pano-pipe.yaml"
    if target == "secret-yaml":
        (run / "secret" / "s.yaml").write_text("layout: {tta: true}\n")
        own.symlink_to(run / "secret" / "s.yaml")
    elif target == "dangling":
        own.symlink_to(run / "secret" / "nothing.yaml")
    elif target == "folder":
        own.mkdir()
    else:
        own.symlink_to(target)
    code, out, err = _status(run, capsys)
    line = assert_one_line(code, out, err, "pano-pipe.yaml")
    assert ("symbolic link" if target != "folder" else "not a regular file") in line
    assert "root:" not in out + err


@pytest.mark.parametrize("value", ["../secret/evil.pth", "<SECRET>/evil.pth", "<SECRET>/model.onnx",
                                   "~/evil.pth", "link/evil.pth"])
def test_scene_settings_name_files_only_inside_the_scene(run, value, capsys):
    (run / "S" / "link").symlink_to(run / "secret")
    value = value.replace("<SECRET>", str(run / "secret"))
    _scene_yaml(run, {"layout": {"model": value}})
    line = assert_one_line(*_status(run, capsys), "pano-pipe.yaml")
    assert "layout.model" in line and ("inside the scene" in line or "outside the scene" in line), line


def test_a_model_file_given_on_the_command_line_may_lie_anywhere(run, capsys):
    (run / "S" / "models").mkdir()
    shutil.copy(run / "secret" / "model.onnx", run / "S" / "models" / "m.onnx")
    _scene_yaml(run, {"layout": {"model": "models/m.onnx"}})  # inside the scene: fine
    code, out, err = _status(run, capsys)
    assert code == 0, err
    code, out, err = _status(run, capsys, "--set", f"layout.model={run / 'secret' / 'model.onnx'}")
    assert code == 0, err


def test_a_failed_export_of_a_users_checkpoint_leaves_nothing_in_the_cache(tmp_path, monkeypatch):
    from models.store import resolve_model
    from runfs.errors import PanoError

    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(tmp_path / "cache"))
    (tmp_path / "cache").mkdir()
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(PanoError):
        resolve_model(str(tmp_path / "bad.pth"), "layout")
    assert list((tmp_path / "cache").iterdir()) == []


# ----------------------------------------------------------------------------- 7. working resolution
@pytest.mark.parametrize("setting", ["evaluate.resolution=[50000,100000]", "train.height=60000",
                                     "train.crop_size=20000", "depth.output_height=30000"])
def test_working_sizes_over_the_pixel_limit_are_refused_before_anything_runs(run, setting, capsys, monkeypatch):
    stage, param = setting.split("=")[0].split(".")
    assert_one_line(*_status(run, capsys, "--set", setting), param, "megapixels")
    _scene_yaml(run, f"{stage}: {{{param}: {setting.split('=')[1]}}}\n")
    assert_one_line(*_status(run, capsys), param, "megapixels")
    monkeypatch.setenv("PANO_PIPE_MAX_MEGAPIXELS", "1e5")  # the limit raised on purpose: accepted
    code, out, err = _status(run, capsys)
    assert code == 0, err


def test_every_size_setting_is_held_to_the_pixel_limit():
    """The class: a stage setting that sets a working image size is marked, so it is checked."""
    import re

    from pipeline.registry import build_registry
    from schemas.stage_params import field_extra

    unmarked = [f"{name}.{field}" for name, spec in build_registry().items()
                for field, info in spec.params.model_fields.items()
                if re.search(r"(^|_)(height|size|resolution)$", field) and "float" not in str(info.annotation)
                and "pixels" not in field_extra(info)]
    assert unmarked == []


# ----------------------------------------------------------------------------- 8, 9. a full disk
@contextlib.contextmanager
def full_disk(after_bytes: int):
    """Every file write past `after_bytes` fails (EFBIG), as on a disk that fills up."""
    old = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (after_bytes, old[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old)
        signal.signal(signal.SIGXFSZ, old_handler)


@pytest.mark.parametrize("fmt", ["ply", "splat", "spz"])
def test_an_export_on_a_full_disk_names_the_file_and_leaves_nothing(run, fmt, capsys):
    out_dir = run / "out"
    out_dir.mkdir()
    target = out_dir / f"x.{fmt}"
    with full_disk(2000):
        code, out, err = invoke(["export", run / "R", "--format", fmt, "--out", target], capsys)
    assert_one_line(code, out, err, str(target))
    assert list(out_dir.iterdir()) == []
    code, out, err = invoke(["export", run / "R", "--format", "mesh", "--out", out_dir / "m.ply"], capsys)
    assert code == 0, err


def test_a_report_on_a_full_disk_leaves_the_previous_report(run, capsys):
    assert invoke(["report", run / "S", "--out", run / "R"], capsys)[0] == 0
    before = tree(run / "R" / "report")
    with full_disk(30_000):
        code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert_one_line(code, out, err)
    assert tree(run / "R" / "report") == before
    assert not [p for p in (run / "R").iterdir() if p.name.startswith(".tmp-")]


def test_sampling_on_a_full_disk_is_one_line(run):
    from tests.clitools import run_on_full_disk

    code, out, err = run_on_full_disk(["run", "sampling", run / "S", "--out", run / "R", "--force",
                                       "--set", "sampling.density=400"], 4000, run / "cwd")
    assert_one_line(code, out, err, "sampling")
    assert "RPly" not in err


# ----------------------------------------------------------------------------- 10. the model registry
@pytest.mark.parametrize("entry, problem", [
    ({"name": "../../escape"}, "name '../../escape'"),
    ({"filename": "../../decoy/x.pth"}, "filename '../../decoy/x.pth'"),
    ({"filename": ".hidden.pth"}, "filename"),
    ({"exporter": "shutil:copyfile"}, "exporter 'shutil:copyfile' is not one pano-pipe calls"),
    ({"exporter": "os:system"}, "exporter 'os:system'"),
    ({"source": "file:///etc/passwd"}, "http(s) URL"),
    ({"size_mb": "big"}, "size_mb"),
])
def test_registry_entries_are_checked_like_built_in_ones(tmp_path, monkeypatch, capsys, entry, problem):
    good = {"name": "mine", "kind": "layout", "host": "url", "source": "https://example.com/x.pth",
            "filename": "x.pth"}
    reg = tmp_path / "reg.yaml"
    reg.write_text(yaml.safe_dump([{**good, **entry}]))
    monkeypatch.setenv("PANO_PIPE_MODELS_REGISTRY", str(reg))
    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(tmp_path / "cache"))
    for command in (["models", "path", entry.get("name", "mine")], ["models", "list"]):
        assert_one_line(*invoke(command, capsys), "reg.yaml", problem)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reg.yaml"]


def test_built_in_models_meet_the_registry_rules():
    from dataclasses import asdict

    from models.registry import BUILTIN, entry_problem

    assert [entry_problem(asdict(m)) for m in BUILTIN] == [None] * len(BUILTIN)


def test_only_allowed_exporters_are_ever_called():
    from models.store import load_exporter
    from runfs.errors import PanoError

    with pytest.raises(PanoError, match="not a model exporter"):
        load_exporter("os:system")


# ----------------------------------------------------------------------------- 11. a corrupt cached model
def test_a_truncated_cached_model_is_not_reported_ready(tmp_path, monkeypatch, capsys):
    from models.registry import get_model
    from models.store import checkpoint_path, onnx_path, write_record
    from runfs.fsutil import sha256_file

    cache = tmp_path / "cache"
    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(cache))
    entry = get_model("horizonnet-zind")
    cache.mkdir()
    model = _columns_layout_onnx(onnx_path(entry))
    checkpoint_path(entry).write_bytes(b"pretend checkpoint")
    write_record(entry, sha256_file(checkpoint_path(entry)))  # as `models fetch` leaves it
    code, out, err = invoke(["models", "path", "horizonnet-zind"], capsys)
    assert code == 0 and out.strip() == str(model), err
    model.write_bytes(model.read_bytes()[:1000])  # truncated
    checkpoint_path(entry).write_bytes(b"pretend checkpoint, altered")
    code, out, err = invoke(["models", "list"], capsys)
    assert code == 0 and "horizonnet-zind layout 327 MB present: damaged" in " ".join(out.split()), out
    assert_one_line(*invoke(["models", "path", "horizonnet-zind"], capsys), "does not match")


def test_fetch_repairs_a_damaged_cached_checkpoint_without_force(tmp_path, monkeypatch):
    import hashlib

    from models import download
    from models.download import fetch

    good = b"the real checkpoint"
    reg = tmp_path / "reg.yaml"
    reg.write_text(yaml.safe_dump([{"name": "standin", "kind": "layout", "host": "url",
                                    "source": "https://example.com/s.pth", "filename": "s.pth",
                                    "sha256": hashlib.sha256(good).hexdigest()}]))
    monkeypatch.setenv("PANO_PIPE_MODELS_REGISTRY", str(reg))
    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(tmp_path / "cache"))

    def served(entry, folder, want):
        (folder / entry.filename).write_bytes(good)
        return folder / entry.filename

    def exporter(checkpoint, out):
        _columns_layout_onnx(out)

    monkeypatch.setattr(download, "_download", served)
    monkeypatch.setattr("layoutnet.export.export_checkpoint", exporter)
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "s.pth").write_bytes(good[:5])  # a truncated earlier download
    log = []
    got = fetch("standin", log=log.append)
    assert got.downloaded and (tmp_path / "cache" / "s.pth").read_bytes() == good
    assert any("damaged" in m for m in log)


# ----------------------------------------------------------------------------- 12. YAML errors
def test_yaml_errors_keep_the_problem_and_where(run, capsys):
    _scene_yaml(run, "layout:\n  tta: true\n  bad: [1, 2\n")
    line = assert_one_line(*_status(run, capsys), "pano-pipe.yaml")
    assert "line " in line and "column " in line and "expected" in line, line


# ----------------------------------------------------------------------------- 13. the refused pickle
def test_a_refused_pickle_says_what_and_why(tmp_path):
    from layoutnet.export import load_checkpoint
    from runfs.errors import PanoError

    class Payload:
        def __reduce__(self):
            return (os.system, ("true",))

    torch.save({"state_dict": Payload()}, tmp_path / "evil.pth")
    with pytest.raises(PanoError) as e:
        load_checkpoint(tmp_path / "evil.pth")
    assert "system" in e.value.problem and "would run code" in e.value.problem
    assert "weights_only` set to `False" not in e.value.problem and "Re-running" not in e.value.problem


# ----------------------------------------------------------------------------- 14. the small ones
def test_one_view_without_a_pose_says_so(tmp_path, capsys):
    generate_scene(tmp_path / "S", views=1, test_views=0, height=16, effects="none")
    doc = json.loads((tmp_path / "S" / "scene.json").read_text())
    doc["views"][0].pop("pose")
    (tmp_path / "S" / "scene.json").write_text(json.dumps(doc))
    code, out, err = invoke(["run", "poses", tmp_path / "S", "--out", tmp_path / "R"], capsys)
    assert_one_line(code, out, err, "at least two")


@pytest.mark.parametrize("field, value, expected", [
    ("nadir_mask_deg", float("nan"), "finite"), ("camera_height", 1e-300, "greater than or equal to 0.05"),
    ("camera_height", True, "valid number"), ("camera_height", float("inf"), "finite"),
])
def test_scene_numbers_are_checked_for_what_they_are(run, field, value, expected, capsys):
    doc = json.loads((run / "S" / "scene.json").read_text())
    (doc if field == "nadir_mask_deg" else doc["views"][0])[field] = value
    (run / "S" / "scene.json").write_text(json.dumps(doc))
    assert_one_line(*_status(run, capsys), field, expected)


@pytest.mark.parametrize("kind", ["file", "dangling"])
def test_a_models_dir_that_is_not_a_folder_says_so(tmp_path, monkeypatch, kind):
    from models.download import fetch
    from runfs.errors import PanoError

    place = tmp_path / "models"
    if kind == "file":
        place.write_text("x")
    else:
        place.symlink_to(tmp_path / "nowhere")
    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(place))
    with pytest.raises(PanoError, match="model cache"):
        fetch("horizonnet-zind", log=lambda m: None)


def test_duplicate_keys_and_huge_settings_files_are_refused(run, capsys):
    _scene_yaml(run, "layout:\n  tta: true\nlayout:\n  tta: false\n")
    assert_one_line(*_status(run, capsys), "pano-pipe.yaml", "given twice", "line 3")
    _scene_yaml(run, "layout: {tta: true}\n" + "# padding\n" * 200_000)
    assert_one_line(*_status(run, capsys), "pano-pipe.yaml", "over 1024 kB")
