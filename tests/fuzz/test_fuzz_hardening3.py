"""Generators for the classes of the third hardening pass (issue 37): settings that are not finite or
set a working size over the pixel limit, a scene's settings file reaching outside its folder, the
report of hostile or diverged artifacts (Markdown, missing metrics), the model registry and cache,
hostile model files, a full disk at any write, and scene numbers of the wrong kind. Each example is
checked against the bad-input contract (fuzz_helpers) and the class's own promise."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from html.parser import HTMLParser

import pytest
import yaml
from hypothesis import example, given
from hypothesis import strategies as st

from fuzz_helpers import BASE_SET, SCENE_VIEWS, fuzz_settings, run_args, run_example, sandbox
from pipeline.registry import build_registry
from schemas.stage_params import field_extra

REGISTRY = build_registry()
FLOAT_SETTINGS = sorted((name, field, "tuple" in str(info.annotation)) for name, spec in REGISTRY.items()
                        for field, info in spec.params.model_fields.items() if "float" in str(info.annotation))
SIZE_SETTINGS = sorted((name, field, field_extra(info)["pixels"]) for name, spec in REGISTRY.items()
                       for field, info in spec.params.model_fields.items() if "pixels" in field_extra(info))
HOSTILE_MARKDOWN = [
    "[click](evil.html)", "![i](http://beacon.example/p.png)", "# heading", "line\n# heading", "a | b",
    "<img src=x>", "&amp;", "\u202eevil", "*em* _em_ `code`", "1. item", "- item", "> quote", "\\", "Küche 1 [Süd]",
    "[x]: http://evil.example", "<http://evil.example>", "~~s~~", "|---|",
]


@contextlib.contextmanager
def models_cache(sb):
    """The model cache inside the run folder (writes there are allowed; the user's own untouched)."""
    old = {k: os.environ.get(k) for k in ("PANO_PIPE_MODELS_DIR", "PANO_PIPE_MODELS_REGISTRY")}
    os.environ["PANO_PIPE_MODELS_DIR"] = str(sb.run / "models-cache")
    try:
        yield sb.run / "models-cache"
    finally:
        for k, v in old.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)


# ----------------------------------------------------------------------------- settings: finite, sizes
@given(setting=st.one_of(st.sampled_from(FLOAT_SETTINGS), st.sampled_from(SIZE_SETTINGS)),
       value=st.sampled_from([".inf", "-.inf", ".nan", "1e400", "-1e400", "[.nan, 0, 0]", "[0, .inf, 0]",
                              "60000", "[50000, 100000]", "[100000, 100000]"]),
       where=st.sampled_from(["--set", "scene-file"]))
@example(setting=("train", "lr_position_init", False), value=".inf", where="--set")
@example(setting=("evaluate", "resolution", "hw"), value="[50000, 100000]", where="scene-file")
@fuzz_settings(max_examples=25)
def test_settings_not_finite_or_too_large(setting, value, where, fuzz_base, tmp_path, capfd):
    stage, param, _ = setting
    with sandbox(fuzz_base, tmp_path) as sb:
        args = run_args("align", "status")
        if where == "--set":
            args += ["--set", f"{stage}.{param}={value}"]
        else:
            (sb.scene / "pano-pipe.yaml").write_text(f"{stage}:\n  {param}: {value}\n")
        res = run_example(sb, args, capfd, (setting, value, where), "settings-finite")
        bad_number = value.strip("[]-").startswith((".inf", ".nan", "1e400")) or ".nan" in value or ".inf" in value
        same_shape = (setting[2] is True) == value.startswith("[")  # a list for a tuple setting, else a number
        if bad_number and same_shape and "float" in str(REGISTRY[stage].params.model_fields[param].annotation):
            assert res.code == 2 and param in res.err and "finite" in res.err, res.err


# ----------------------------------------------------------------------------- the scene's settings file
SCENE_FILES = ["link-sentinel-config", "link-secret", "link-passwd", "link-dangling", "link-self", "folder",
               "duplicate", "syntax", "huge", "tab", "model-outside", "model-abs", "model-home", "model-link",
               "model-inside", "weights-outside", "model-name"]


@given(kind=st.sampled_from(SCENE_FILES), command=st.sampled_from(["status", "run-stage-layout"]))
@example(kind="link-passwd", command="status")
@example(kind="model-outside", command="run-stage-layout")
@fuzz_settings(max_examples=25)
def test_scene_settings_file(kind, command, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb, models_cache(sb):
        own = sb.scene / "pano-pipe.yaml"
        settings = {
            "duplicate": "layout:\n  tta: true\nlayout:\n  tta: false\n", "syntax": "layout: {tta: [1, 2\n",
            "huge": "layout: {tta: true}\n" + "#" * (2 << 20) + "\n", "tab": "layout:\n\ttta: true\n",
            "model-outside": "layout: {model: ../sentinel/model.onnx}\n",
            "model-abs": f"layout: {{model: {sb.sentinel / 'model.onnx'}}}\n",
            "model-home": "layout: {model: ~/model.onnx}\n", "model-link": "layout: {model: out/model.onnx}\n",
            "model-inside": "layout: {model: model.onnx}\n",
            "weights-outside": "evaluate: {lpips_weights: ../sentinel}\n",
            "model-name": "layout: {model: horizonnet-zind}\n",
        }
        targets = {"link-sentinel-config": sb.sentinel / "config.yaml", "link-secret": sb.sentinel / "secret.txt",
                   "link-passwd": "/etc/passwd", "link-dangling": sb.sentinel / "nothing.yaml", "link-self": own}
        if kind in targets:
            own.symlink_to(targets[kind])
        elif kind == "folder":
            own.mkdir()
        else:
            own.write_text(settings[kind])
        if kind == "model-link":
            (sb.scene / "out").symlink_to(sb.sentinel)
        if kind == "model-inside":
            shutil.copy(sb.sentinel / "model.onnx", sb.scene / "model.onnx")
        res = run_example(sb, run_args("layout", command), capfd, (kind, command), "scene-settings")
        if kind != "model-inside" and kind != "model-name":
            assert res.code == 2 and "pano-pipe.yaml" in res.err, res.err
        if kind == "link-passwd":
            assert "root:" not in res.out + res.err


# ----------------------------------------------------------------------------- the report
class _Tags(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


#: What an evaluation of a model that diverged (or of a perfect render) leaves: null, NaN, Inf.
METRIC_VALUES = [None, float("nan"), float("inf"), -1.0, 0.0, 23.5]


@given(names=st.lists(st.sampled_from(HOSTILE_MARKDOWN), min_size=1, max_size=3, unique=True),
       metrics=st.dictionaries(st.sampled_from(["psnr", "ssim", "ws_psnr", "lpips"]),
                               st.sampled_from(METRIC_VALUES), max_size=4),
       setting=st.sampled_from(HOSTILE_MARKDOWN))
@example(names=["[click](evil.html)"], metrics={"psnr": None, "ssim": float("nan")}, setting="line\n# heading")
@fuzz_settings(max_examples=20)
def test_report_of_hostile_or_diverged_artifacts(names, metrics, setting, fuzz_base, tmp_path, capfd):
    from markdown_it import MarkdownIt

    with sandbox(fuzz_base, tmp_path) as sb:
        edir = sb.run / "evaluate"
        (edir / "gt").mkdir(parents=True)
        views = []
        for name in names:
            shutil.copy(sb.scene / "images" / "test_00.png", edir / "gt" / "test_00.png")
            view = {"view": name, "split": "test", "gt": "gt/test_00.png", "render": "gt/test_00.png",
                    "error": "gt/test_00.png", "depth": "gt/none.png", "depth_npy": "gt/none.npy", "psnr": 20.0,
                    "ssim": 0.5, "ws_psnr": 20.0, "render_seconds": 0.1}
            views.append(view)
        data = {"views": views, "mean": {"psnr": 20.0, "ssim": 0.5}, "resolution": [16, 32], "fps": 10.0,
                "fps_repeats": 1, "backend": "cpp", "device": "cpu", "threads": 1, "num_gaussians": 10,
                "split": "test", "lpips_available": False, "lpips_reason": setting, "csv": "metrics.csv", "on_train_views": False}
        for key, value in metrics.items():
            for record in (data["mean"], *views):
                record[key] = value
        align = sb.run / "align" / "artifact.json"
        doc = json.loads(align.read_text())
        meta = {**doc["meta"], "stage": "evaluate", "params": {"backend": setting}, "files": {}}
        (edir / "artifact.json").write_text(json.dumps({"meta": meta, "data": data}))
        doc["meta"]["params"]["voxel_size"] = setting
        align.write_text(json.dumps(doc))
        res = run_example(sb, ["report", "<SCENE>", "--out", "<RUN>"], capfd, (names, metrics, setting), "report")
        from runfs.paths import stem_problem

        if any(stem_problem(n) for n in names):  # a tampered artifact: view names are file names too
            assert res.code == 2 and "evaluate/artifact.json" in res.err, res.err
            return
        assert res.code == 0, res.err
        md = (sb.run / "report" / "report.md").read_text(encoding="utf-8")
        tags = _Tags()
        tags.feed(MarkdownIt("commonmark").enable("table").render(md))
        assert not [a for t, a in tags.tags if t == "a" and "evil" in a.get("href", "")]
        assert all(a.get("src", "").startswith("img/") for t, a in tags.tags if t == "img")
        assert sum(t == "h1" for t, _ in tags.tags) == 1
        assert "\u202e" not in md + (sb.run / "report" / "report.html").read_text(encoding="utf-8")


# ----------------------------------------------------------------------------- the model registry and cache
REGISTRY_FIELDS = st.fixed_dictionaries({}, optional={
    "name": st.sampled_from(["../../escape", "a/b", ".hidden", "-x", "ok-name", "x" * 200, "", "CON", 5]),
    "filename": st.sampled_from(["../../decoy/x.pth", "/etc/passwd", "a/b.pth", ".x.pth", "ok.pth", "", "..", 7]),
    "exporter": st.sampled_from(["os:system", "shutil:copyfile", "builtins:eval", "layoutnet.export:nope",
                                 "depthnet.depth_anything:export_onnx", "", None]),
    "source": st.sampled_from(["file:///etc/passwd", "ftp://x/y", "https://127.0.0.1:9/x.pth", "", None]),
    "sha256": st.sampled_from(["0" * 64, "xyz", None, 5]),
    "size_mb": st.sampled_from([None, -1, "big", float("nan"), 1e300, True]),
    "kind": st.sampled_from(["layout", "depth", "nope"]),
})


@given(fields=REGISTRY_FIELDS, command=st.sampled_from(["list", "path", "fetch"]))
@example(fields={"name": "../../escape", "filename": "../../decoy/x.pth", "exporter": "shutil:copyfile"},
         command="path")
@fuzz_settings(max_examples=25)
def test_model_registry_entries(fields, command, fuzz_base, tmp_path, capfd):
    entry = {"name": "mine", "kind": "layout", "host": "url", "source": "https://127.0.0.1:9/x.pth",
             "filename": "x.pth", **fields}
    with sandbox(fuzz_base, tmp_path) as sb, models_cache(sb):
        reg = sb.run / "registry.yaml"
        reg.write_text(yaml.safe_dump([entry]))
        os.environ["PANO_PIPE_MODELS_REGISTRY"] = str(reg)
        args = ["models", command] + ([str(entry["name"])] if command != "list" else [])
        res = run_example(sb, args, capfd, (fields, command), "registry")
        if command != "list":
            assert res.code == 2
        outside = [p for p in sb.run.rglob("*") if p.is_file() and "models-cache" not in p.parts
                   and p.name != "registry.yaml" and not (sb.run / "layout").exists()]
        assert not [p for p in outside if p.suffix in (".pth", ".onnx")]


@given(damage=st.sampled_from(["truncate", "flip", "empty", "folder", "link-out"]),
       command=st.sampled_from(["list", "path", "run-layout"]))
@fuzz_settings(max_examples=12)
def test_corrupt_cached_models(damage, command, fuzz_base, tmp_path, capfd):
    from models.registry import get_model
    from models.store import checkpoint_path, onnx_path, write_record
    from runfs.fsutil import sha256_file

    with sandbox(fuzz_base, tmp_path) as sb, models_cache(sb) as cache:
        cache.mkdir()
        entry = get_model("horizonnet-zind")
        onnx = onnx_path(entry)
        onnx.write_bytes(b"\x08\x07" + b"pretend onnx model " * 100)
        checkpoint_path(entry).write_bytes(b"pretend checkpoint")
        write_record(entry, sha256_file(checkpoint_path(entry)))
        checkpoint_path(entry).unlink()
        if damage == "truncate":
            onnx.write_bytes(onnx.read_bytes()[:100])
        elif damage == "flip":
            data = bytearray(onnx.read_bytes())
            data[50] ^= 1
            onnx.write_bytes(bytes(data))
        elif damage == "empty":
            onnx.write_bytes(b"")
        elif damage == "folder":
            onnx.unlink()
            onnx.mkdir()
        else:
            onnx.unlink()
            onnx.symlink_to(sb.sentinel / "model.onnx")
        args = (["models", command, "horizonnet-zind"][: 2 if command == "list" else 3] if command != "run-layout"
                else ["run", "layout", "<SCENE>", "--out", "<RUN>", "--force", "--set", "layout.model=horizonnet-zind",
                      *BASE_SET])
        res = run_example(sb, args, capfd, (damage, command), "corrupt-cache")
        if command == "list":
            assert "horizonnet-zind layout 327 MB present: yes" not in " ".join(res.out.split())
        else:
            assert res.code == 2


# ----------------------------------------------------------------------------- hostile model files
def _pickled(path):
    import torch

    class Payload:
        def __reduce__(self):
            return (os.system, ("touch pwned",))

    torch.save({"state_dict": Payload()}, path)


@given(kind=st.sampled_from(["pickle", "truncated", "garbage", "empty", "zip-of-nothing"]),
       stage=st.sampled_from(["layout", "depth"]), suffix=st.sampled_from([".pth", ".pt", ".ckpt"]))
@fuzz_settings(max_examples=12)
def test_hostile_model_files(kind, stage, suffix, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb, models_cache(sb):
        path = sb.cwd / f"model{suffix}"
        if kind == "pickle":
            _pickled(path)
        elif kind == "truncated":
            _pickled(path)
            path.write_bytes(path.read_bytes()[:200])
        elif kind == "garbage":
            path.write_bytes(b"\x80\x04garbage" * 10)
        elif kind == "empty":
            path.write_bytes(b"")
        else:
            import zipfile

            with zipfile.ZipFile(path, "w") as z:
                z.writestr("x", b"")
        before = sorted(p.name for p in sb.cwd.iterdir())
        args = ["run", stage, "<SCENE>", "--out", "<RUN>", "--force", "--set", f"{stage}.model={path}", *BASE_SET]
        res = run_example(sb, args, capfd, (kind, stage, suffix), "model-files")
        assert res.code == 2
        assert sorted(p.name for p in sb.cwd.iterdir()) == before  # nothing ran: no 'pwned'
        if kind == "pickle":
            assert "would run code" in res.err and "Re-running" not in res.err, res.err
        assert not (sb.run / "models-cache" / "exported").exists()


# ----------------------------------------------------------------------------- a full disk
def run_on_full_disk(sb, args: list[str], budget: int):
    from fuzz_helpers import Result
    from tests.clitools import run_on_full_disk as run

    args = [sb.expand(a) for a in args]
    return Result(args, *run(args, budget, sb.cwd))


@given(budget=st.sampled_from([0, 100, 1000, 4000, 20_000, 100_000]),
       command=st.sampled_from(["run-stage-sampling", "run-stage-align", "report"]))
@example(budget=4000, command="run-stage-sampling")
@fuzz_settings(max_examples=6)
def test_full_disk(budget, command, fuzz_base, tmp_path):
    from fuzz_helpers import completed_stages, contract_problems

    with sandbox(fuzz_base, tmp_path) as sb:
        if command == "report":
            args = ["report", "<SCENE>", "--out", "<RUN>"]
        else:  # a new sampling seed: sampling and align rerun, the rest is cached
            args = run_args(None, command) + ["--set", "sampling.seed=7"]
        before_outside, before_run = sb.outside(), sb.run_files()
        log_before = (sb.run / "run_log.jsonl").stat().st_size
        res = run_on_full_disk(sb, args, budget)
        problems = contract_problems(res, before_outside, sb.outside(), before_run, sb.run_files(),
                                     completed_stages(sb.run, log_before))
        # a stage that finished before the disk filled was rightly replaced
        problems = [p for p in problems if not (p.startswith("failed run changed previous artifacts") and
                                                p.count("(its stage re-ran ok") == p.count("changed ") - 1)]
        assert problems == [], (budget, command, problems, res.err[-2000:])
        assert "RPly" not in res.err and "libpng" not in res.err


# ----------------------------------------------------------------------------- scene numbers
@given(view=st.sampled_from(SCENE_VIEWS),
       field=st.sampled_from(["camera_height", "nadir_mask_deg", "pose"]),
       value=st.sampled_from([True, False, float("nan"), float("inf"), 1e-300, 0.0, -1.0, "1.5", 1e300, None]))
@example(view="train_00", field="camera_height", value=True)
@fuzz_settings(max_examples=20)
def test_scene_numbers(view, field, value, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb:
        data = sb.manifest()
        if field == "nadir_mask_deg":
            data[field] = value
        elif field == "pose":
            v = sb.view(data, view)
            if v.get("pose") is None:
                return
            v["pose"][0][3] = value
        else:
            sb.view(data, view)[field] = value
        sb.write_manifest(data)
        res = run_example(sb, run_args("align", "status"), capfd, (view, field, value), "scene-numbers")
        if value is not None or field == "pose":
            tiny = value == 1e-300 and field == "camera_height"  # under 5 cm; a tiny nadir cap is fine
            if value in (True, False, "1.5") or tiny or (isinstance(value, float) and (value != value or
                                                                                      abs(value) == float("inf"))):
                assert res.code == 2 and (field if field != "pose" else "pose") in res.err, res.err


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
