"""Hostile input and faults (docs/security.md): nothing outside the scene and run folders is read,
written or deleted; every failure is one line with exit code 2; the cache cannot lie.

Each test names the defect of the hardening issue it guards (#1 .. #15)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.signals import Terminated
from tests.clitools import invoke, run_main
from runfs.fsutil import run_folder_lock
from simulate.generate import generate_scene

FAST = ["--set", "train.iterations=5", "--set", "train.height=8"]


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    """(exit code, stderr): reports go to stdout."""
    code, _, err = invoke(args, capsys)
    return code, err


def assert_one_line(code: int, out: str, *expected: str) -> None:
    assert code == 2, out
    assert "Traceback" not in out
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1, out
    for text in expected:
        assert text in lines[0], (text, lines[0])


def tree(root: Path) -> dict[str, bytes]:
    """Every file below root: relative path -> bytes (symlinks as their target text)."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        if p.is_symlink():
            out[str(p.relative_to(root))] = os.readlink(p).encode()
        elif p.is_file():
            out[str(p.relative_to(root))] = p.read_bytes()
    return out


def edit(scene: Path, change) -> None:
    data = json.loads((scene / "scene.json").read_text())
    change(data)
    (scene / "scene.json").write_text(json.dumps(data))


@pytest.fixture(scope="module")
def base_scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("base") / "S"
    generate_scene(root, views=3, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    return root


@pytest.fixture
def work(tmp_path, base_scene, monkeypatch) -> Path:
    """A copy of the scene in tmp/S, the working folder tmp/cwd (stray relative writes land there)."""
    shutil.copytree(base_scene, tmp_path / "S")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    return tmp_path


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, base_scene) -> Path:
    """A complete run of the base scene (fast settings), to copy."""
    root = tmp_path_factory.mktemp("finished")
    shutil.copytree(base_scene, root / "S")
    assert run_main(["run", "all", root / "S", "--out", root / "R", *FAST]) == 0
    assert (root / "R" / "evaluate" / "artifact.json").is_file()
    return root


@pytest.fixture
def finished(tmp_path, finished_run, monkeypatch) -> Path:
    shutil.copytree(finished_run / "S", tmp_path / "S")
    shutil.copytree(finished_run / "R", tmp_path / "R")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    return tmp_path


# ----------------------------------------------------------------------------- #1 clean
@pytest.mark.parametrize("name", ["/some/folder", "../../victim", "..", "."])
def test_clean_refuses_a_scene_name_that_is_a_path(work, name, capsys):
    victim = work / "victim"
    (victim / "keep").mkdir(parents=True)
    (victim / "keep" / "f").write_text("precious")
    edit(work / "S", lambda d: d.update(name=name))
    code, out = run_cli(["clean", work / "S"], capsys)
    assert_one_line(code, out, "scene.json", "name")
    code, out = run_cli(["run", "all", work / "S"], capsys)
    assert_one_line(code, out, "scene.json", "name")
    assert (victim / "keep" / "f").read_text() == "precious"


def test_clean_deletes_only_run_folders(finished, capsys):
    other = finished / "other"
    other.mkdir()
    (other / "f").write_text("precious")
    code, out = run_cli(["clean", finished / "S", "--out", other], capsys)
    assert_one_line(code, out, "not a pano-pipe run folder")
    assert (other / "f").read_text() == "precious"
    code, out = run_cli(["clean", finished / "S", "--out", finished / "S"], capsys)
    assert_one_line(code, out, "the run folder is the scene folder")
    assert (finished / "S" / "scene.json").is_file()
    code, out = run_cli(["clean", finished / "S", "--out", finished / "R", "--yes"], capsys)
    assert code == 0 and not (finished / "R").exists()


# ----------------------------------------------------------------------------- #2 --out overlaps
@pytest.mark.parametrize("where", ["S", "S/sub", "."])
def test_out_overlapping_the_scene_is_refused(work, where, capsys):
    before = tree(work / "S")
    out = work if where == "." else work / where
    code, text = run_cli(["run", "all", work / "S", "--out", out, *FAST], capsys)
    assert_one_line(code, text, "scene folder")
    assert tree(work / "S") == before


def test_out_that_is_a_file_or_a_foreign_folder(work, capsys):
    (work / "file").write_text("x")
    assert_one_line(*run_cli(["run", "all", work / "S", "--out", work / "file"], capsys), "is a file")
    (work / "home").mkdir()
    (work / "home" / "notes.txt").write_text("mine")
    assert_one_line(*run_cli(["run", "all", work / "S", "--out", work / "home"], capsys), "not a pano-pipe run")
    assert tree(work / "home") == {"notes.txt": b"mine"}


# ----------------------------------------------------------------------------- #3 view names
@pytest.mark.parametrize(
    "name", ["../../../escaped", "/abs/name", "a/b", "nul\x00byte", "x" * 300, ".hidden", "-rf", "new\nline"]
)
def test_unsafe_view_names_are_refused(work, name, capsys):
    edit(work / "S", lambda d: d["views"][0].update(name=name))
    before = tree(work)
    code, out = run_cli(["run", "all", work / "S", "--out", work / "R"], capsys)
    assert_one_line(code, out, "scene.json", "views.0.name")
    assert tree(work) == before  # nothing written anywhere (no run folder either)


def test_unicode_view_names_are_fine(work, capsys):
    edit(work / "S", lambda d: d["views"][0].update(name="Küche 1 [Süd]"))
    code, out = run_cli(["run", "layout", work / "S", "--out", work / "R"], capsys)
    assert code == 0, out
    assert (work / "R" / "layout" / "Küche 1 [Süd].boundaries.npy").is_file()


# ----------------------------------------------------------------------------- #5 exit codes
@pytest.mark.parametrize("exc", [KeyboardInterrupt, lambda: __import__("typer").Exit(130), Terminated])
def test_interrupts_exit_130(work, exc, monkeypatch, capsys):
    from pipeline.engine import Engine

    def interrupted(self, *a, **k):
        raise exc()

    monkeypatch.setattr(Engine, "run", interrupted)
    code, err = run_cli(["run", "all", work / "S", "--out", work / "R"], capsys)
    assert code == 130 and err.startswith("interrupted")


def test_internal_error_exits_1_in_one_line(work, monkeypatch, capsys):
    from pipeline.engine import Engine

    def broken(self, *a, **k):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(Engine, "run", broken)
    code, out = run_cli(["run", "all", work / "S", "--out", work / "R"], capsys)
    assert code == 1 and "ZeroDivisionError: a bug" in out and len(out.strip().splitlines()) == 1


# ----------------------------------------------------------------------------- #6 scene paths
def test_scene_paths_stay_inside_the_scene(work, capsys):
    outside = work / "outside.png"
    shutil.copy(work / "S" / "images" / "train_00.png", outside)
    for image in ["../outside.png", str(outside), "images/../../outside.png"]:
        edit(work / "S", lambda d: d["views"][0].update(image=image))
        assert_one_line(*run_cli(["run", "all", work / "S", "--out", work / "R"], capsys), "views.0.image")
    # a symlink pointing out is refused; one pointing inside is followed
    (work / "S" / "images" / "link.png").symlink_to(outside)
    edit(work / "S", lambda d: d["views"][0].update(image="images/link.png"))
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "outside the scene folder")
    (work / "S" / "images" / "link.png").unlink()
    (work / "S" / "images" / "link.png").symlink_to(work / "S" / "images" / "train_00.png")
    code, out = run_cli(["status", work / "S", "--out", work / "R"], capsys)
    assert code == 0, out


def test_files_found_by_name_may_not_link_outside(work, capsys):
    layout = work / "S" / "layout" / "train_00.json"
    shutil.move(layout, work / "train_00.json")
    layout.symlink_to(work / "train_00.json")
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "layout/train_00.json",
                    "outside the scene folder")


def test_symlink_loop_is_one_line(work, capsys):
    (work / "S" / "images" / "loop.png").symlink_to(work / "S" / "images" / "loop.png")
    edit(work / "S", lambda d: d["views"][0].update(image="images/loop.png"))
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "loop.png")


# ----------------------------------------------------------------------------- #7 rich markup
def test_user_text_is_not_markup(work, capsys):
    (work / "S" / "layout" / "train_00.json").unlink()
    (work / "S" / "layout" / "train_00.txt").write_text("[/x] 1\n")
    edit(work / "S", lambda d: d["views"][0].update(layout="layout/train_00.txt"))
    code, out = run_cli(["run", "layout", work / "S", "--out", work / "R"], capsys)
    assert_one_line(code, out, "train_00.txt")
    weird = work / "a[/b]"
    shutil.copytree(work / "S", weird)
    (weird / "images" / "train_01.png").unlink()
    assert_one_line(*run_cli(["status", weird, "--out", work / "R"], capsys), "a[/b]", "train_01.png")
    code, out = run_cli(["status", work / "S", "--out", work / "R", "--set", "train.bogus=1"], capsys)
    assert_one_line(code, out, "--set [train]: bogus")


# ----------------------------------------------------------------------------- #8 image size
def png_header_only(path: Path, width: int, height: int) -> None:
    """A PNG whose header says width x height (a bomb is refused before decoding, so no pixels)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))


def test_huge_images_are_refused_before_decoding(work, capsys, monkeypatch):
    png_header_only(work / "S" / "images" / "train_00.png", 20000, 10000)
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "train_00.png", "200 megapixels",
                    "limit of 64")
    # the limit is a setting: a small one refuses the scene's own 32x16 images
    code, out = run_cli(["--max-megapixels", "0.0001", "status", work / "S", "--out", work / "R"], capsys)
    assert_one_line(code, out, "megapixels")
    monkeypatch.delenv("PANO_PIPE_MAX_MEGAPIXELS", raising=False)


def test_tiny_images_are_blamed_on_the_image(work, capsys):
    cv2.imwrite(str(work / "S" / "images" / "train_00.png"), np.zeros((1, 2, 3), np.uint8))
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "train_00.png", "2x1")


# ----------------------------------------------------------------------------- #9 lock, leftovers
def test_a_second_run_on_the_same_folder_is_refused(finished, capsys):
    with run_folder_lock(finished / "R"):
        code, out = run_cli(["run", "all", finished / "S", "--out", finished / "R", *FAST], capsys)
        assert_one_line(code, out, "in use by another pano-pipe run", f"pid {os.getpid()}")
    code, out = run_cli(["run", "all", finished / "S", "--out", finished / "R", *FAST], capsys)
    assert code == 0, out


def test_stale_temporaries_are_removed_at_the_start(finished, capsys):
    for leftover in [".tmp-depth-1234abcd", ".old-train-deadbeef"]:
        (finished / "R" / leftover).mkdir()
        (finished / "R" / leftover / "x").write_text("half")
    (finished / "R" / ".scratch" / "train").mkdir(parents=True, exist_ok=True)
    (finished / "R" / ".scratch" / "train" / "checkpoint.pt.tmp").write_bytes(b"half")
    code, out = run_cli(["run", "all", finished / "S", "--out", finished / "R", *FAST], capsys)
    assert code == 0, out
    left = [p.name for p in (finished / "R").rglob("*") if p.name.startswith((".tmp-", ".old-"))]
    assert not left and not list((finished / "R").rglob("*.tmp"))


# ----------------------------------------------------------------------------- #10 the cache
def states(run, capsys) -> dict[str, tuple[str, str]]:
    from pipeline.cli import make_engine

    engine = make_engine(run / "S", run / "R", None, FAST[1::2])
    return {name: (p.state, p.reason) for name, p in engine.plan().items()}


def test_a_missing_artifact_file_makes_the_stage_stale(finished, capsys):
    assert states(finished, capsys)["train"][0] == "up-to-date"
    (finished / "R" / "train" / "point_cloud.ply").unlink()
    state, reason = states(finished, capsys)["train"]
    assert state == "stale" and "train/point_cloud.ply is missing" in reason
    code, out = run_cli(["run", "evaluate", finished / "S", "--out", finished / "R", *FAST], capsys)
    assert code == 0, out
    assert (finished / "R" / "train" / "point_cloud.ply").is_file()
    assert states(finished, capsys)["train"][0] == "up-to-date"


def test_invalid_artifact_data_or_a_changed_file_makes_the_stage_stale(finished, capsys):
    art = finished / "R" / "union" / "artifact.json"
    doc = json.loads(art.read_text())
    doc["data"] = {"nonsense": True}
    art.write_text(json.dumps(doc))
    state, reason = states(finished, capsys)["union"]
    assert state == "stale" and "does not validate" in reason
    npz = next((finished / "R" / "sampling").glob("*.npz"))
    npz.write_bytes(npz.read_bytes()[:-10])
    state, reason = states(finished, capsys)["sampling"]
    assert state == "stale" and "changed size" in reason


def test_stale_says_what_changed(finished, capsys):
    from pipeline.cli import make_engine

    engine = make_engine(finished / "S", finished / "R", None, ["train.iterations=6", "train.height=8"])
    plans = engine.plan()
    assert plans["train"].state == "stale" and "iterations" in plans["train"].reason
    assert plans["evaluate"].state == "stale" and "upstream changed: train" in plans["evaluate"].reason


# ----------------------------------------------------------------------------- #11 model files
def test_model_files_enter_the_key_by_content_and_resolve_from_the_scene(work, capsys):
    from pydantic import BaseModel

    from pipeline.engine import Engine
    from schemas.scene_loader import load_scene
    from runtime.stage import StageSpec

    class Params(BaseModel):
        model: Path | None = None

    class Out(BaseModel):
        pass

    registry = {"m": StageSpec("m", Params, Out, lambda ctx: Out())}
    scene = load_scene(work / "S")
    (work / "S" / "model.onnx").write_bytes(b"model A")

    def key() -> str:
        engine = Engine(scene, work / "R", registry, {"m": {"model": "model.onnx"}})
        plan = engine.plan()["m"]
        assert plan.params.model == (work / "S" / "model.onnx").resolve()  # what the stage gets
        return plan.key

    a = key()
    (work / "S" / "model.onnx").write_bytes(b"model B")
    assert key() != a
    with pytest.raises(Exception, match="does not exist"):
        Engine(scene, work / "R", registry, {"m": {"model": "nowhere.onnx"}}).plan()


def test_stage_models_are_file_parameters():
    from stages import depth, layout

    for stage in (depth, layout):
        assert "Path" in str(stage.Params.model_fields["model"].annotation), stage.__name__


# ----------------------------------------------------------------------------- #12 one line, exit 2
def test_bad_input_is_one_line(work, capsys):
    s = work / "S"
    (s / "scene.json").write_bytes(b'{"views": "\xff\xfe"}')
    assert_one_line(*run_cli(["status", s, "--out", work / "R"], capsys), "scene.json", "UTF-8")
    (s / "scene.json").write_text("[" * 100_000 + "]" * 100_000)
    assert_one_line(*run_cli(["status", s, "--out", work / "R"], capsys), "scene.json", "nested too deeply")


def test_bad_config_is_one_line(work, capsys):
    s = work / "S"
    assert_one_line(*run_cli(["status", s, "--out", work / "R", "--set", "train.iterations=[1"], capsys),
                    "--set", "not valid YAML")
    cfg = work / "cfg.yaml"
    cfg.write_bytes(b"train:\n  iterations: \xff\n")
    assert_one_line(*run_cli(["status", s, "--out", work / "R", "--config", cfg], capsys), "cfg.yaml", "UTF-8")
    cfg.write_text("[" * 100_000)
    code, out = run_cli(["status", s, "--out", work / "R", "--config", cfg], capsys)
    assert_one_line(code, out, "cfg.yaml")


def test_huge_translation_is_refused_at_the_manifest(work, capsys):
    edit(work / "S", lambda d: d["views"][1]["pose"][0].__setitem__(3, 1e308))
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "views.1.pose", "translation")


def test_pickled_ground_truth_depth_names_the_file(finished, capsys):
    gt = next(iter(sorted((finished / "S" / "gt" / "depth").glob("*"))))
    pickled = gt.with_suffix(".npy")
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    rel = pickled.relative_to(finished / "S").as_posix()
    edit(finished / "S", lambda d: [v.update(gt_depth=rel) for v in d["views"] if v["split"] == "test"])
    before = tree(finished / "R" / "evaluate")
    code, out = run_cli(["run", "evaluate", finished / "S", "--out", finished / "R", *FAST], capsys)
    assert_one_line(code, out, pickled.name, "pickled")
    assert tree(finished / "R" / "evaluate") == before


def test_full_disk_is_one_line_naming_the_stage(finished, capsys, monkeypatch):
    import stages.union

    def full(ctx):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(stages.union, "run", full)
    from pipeline.registry import build_registry

    build_registry.cache_clear()
    try:
        before = tree(finished / "R" / "union")
        code, out = run_cli(["run", "union", finished / "S", "--out", finished / "R", "--force"], capsys)
        assert_one_line(code, out, "union", "No space left on device")
        assert tree(finished / "R" / "union") == before
        assert not [p for p in (finished / "R").iterdir() if p.name.startswith(".tmp-")]
    finally:
        build_registry.cache_clear()


# ----------------------------------------------------------------------------- #13 simulate
def test_simulate_never_replaces_a_folder_it_did_not_write(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    args = ["simulate", mine, "--views", "1", "--test-views", "0", "--height", "16", "--effects", "none"]
    assert_one_line(*run_cli(args, capsys), "mine", "did not write")
    assert tree(mine) == {"thesis.tex": b"years of work"}
    sim = tmp_path / "sim"
    args[1] = sim
    assert run_cli(args, capsys)[0] == 0
    assert run_cli(args, capsys)[0] == 0  # its own output is replaced


# ----------------------------------------------------------------------------- #15 smaller
def test_depth_map_messages(work, capsys):
    d = work / "S" / "depth" / "train_00.png"
    cv2.imwrite(str(d), np.full((2, 4), 1000, np.uint16))
    assert_one_line(*run_cli(["run", "depth", work / "S", "--out", work / "R"], capsys), "train_00.png", "4x2", "too small")
    cv2.imwrite(str(d), np.full((5, 4), 1000, np.uint16))
    assert_one_line(*run_cli(["run", "depth", work / "S", "--out", work / "R"], capsys), "4x5 (width x height)",
                    "e.g. 10x5")


def test_absurd_camera_height_is_blamed_on_the_manifest(work, capsys):
    edit(work / "S", lambda d: d["views"][0].update(camera_height=1e300))
    assert_one_line(*run_cli(["status", work / "S", "--out", work / "R"], capsys), "scene.json",
                    "views.0.camera_height")


def test_a_changed_test_image_does_not_retrain(finished, capsys):
    test_view = next(v for v in json.loads((finished / "S" / "scene.json").read_text())["views"]
                     if v["split"] == "test")
    img = finished / "S" / test_view["image"]
    cv2.imwrite(str(img), 255 - cv2.imread(str(img)))
    st = states(finished, capsys)
    assert {k: v[0] for k, v in st.items() if k != "evaluate"} == {
        "poses": "skipped", **{k: "up-to-date" for k in ("layout", "depth", "union", "sampling", "align", "train")}
    }
    assert st["evaluate"][0] == "stale" and "scene inputs changed" in st["evaluate"][1]


def test_naming_a_file_reruns_only_the_stages_that_read_it(finished, capsys):
    """The manifest enters a stage's key only through the fields the stage reads: naming a view's
    depth file (or changing a ground-truth path) leaves layout cached."""
    scene = finished / "S"
    depth_dir = scene / "supplied_depth"
    depth_dir.mkdir()
    np.save(depth_dir / "d.npy", np.full((16, 32), 2.0, np.float32))

    def name_depth(data):
        data["views"][0]["depth"] = "supplied_depth/d.npy"

    edit(scene, name_depth)
    st = states(finished, capsys)
    assert st["layout"][0] == "up-to-date"
    assert st["depth"][0] == "stale" and "scene inputs changed" in st["depth"][1]


def test_run_files_are_never_written_through_a_symlink(finished, capsys):
    """A planted link in a run folder (.lock, run_log.jsonl) is refused, not followed."""
    secret = finished / "secret.txt"
    secret.write_text("keep me")
    for name in (".lock", "run_log.jsonl"):
        link = finished / "R" / name
        original = link.read_bytes() if link.is_file() else None
        link.unlink(missing_ok=True)
        link.symlink_to(secret)
        code, err = run_cli(["run", "all", finished / "S", "--out", finished / "R", *FAST], capsys)
        assert_one_line(code, err, name, "symbolic link")
        assert secret.read_text() == "keep me"
        link.unlink()
        if original is not None:
            link.write_bytes(original)
