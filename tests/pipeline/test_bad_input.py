"""Bad input: one line naming the file and the problem, exit code 2, no traceback."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import cli


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    """Without --out a run writes runs/<scene>/ under the working folder: keep that in tmp."""
    monkeypatch.chdir(tmp_path)


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    old = sys.argv
    sys.argv = ["pano-pipe", *args]
    try:
        with pytest.raises(SystemExit) as exc:
            cli.main()
    finally:
        sys.argv = old
    captured = capsys.readouterr()
    return exc.value.code, captured.err + captured.out


def edit_manifest(scene: Path, change) -> None:
    data = json.loads((scene / "scene.json").read_text())
    change(data)
    (scene / "scene.json").write_text(json.dumps(data))


def not_rigid(d):
    d["views"][1]["pose"][0][0] = 2.0


def duplicate(d):
    d["views"][1]["name"] = d["views"][0]["name"]


def no_train(d):
    for v in d["views"]:
        v["split"] = "test"


def wrong_last_row(d):
    d["views"][0]["pose"][3] = [0, 0, 1, 1]


MANIFEST_CASES = {
    "pose not rigid": (not_rigid, "scene.json", "views.1.pose: not a rigid transform"),
    "duplicate view": (duplicate, "scene.json", "duplicate view name 'v0'"),
    "empty train split": (no_train, "scene.json", "the train split is empty"),
    "bad last row": (wrong_last_row, "scene.json", "views.0.pose: last row must be"),
}


@pytest.mark.parametrize("case", sorted(MANIFEST_CASES))
def test_manifest_problems(case, tiny_scene, capsys):
    change, file, message = MANIFEST_CASES[case]
    edit_manifest(tiny_scene, change)
    code, err = run_cli(["run", "all", str(tiny_scene)], capsys)
    assert code == 2
    assert file in err and message in err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_missing_folder(tmp_path, capsys):
    code, err = run_cli(["run", "all", str(tmp_path / "nowhere")], capsys)
    assert code == 2 and "nowhere: scene folder does not exist" in err


def test_missing_manifest(tmp_path, capsys):
    code, err = run_cli(["status", str(tmp_path)], capsys)
    assert code == 2 and "scene.json: missing" in err


def test_invalid_json(tiny_scene, capsys):
    (tiny_scene / "scene.json").write_text('{"views": [')
    code, err = run_cli(["run", "all", str(tiny_scene)], capsys)
    assert code == 2 and "scene.json: invalid JSON at line 1" in err


def test_missing_image(tiny_scene, capsys):
    (tiny_scene / "images" / "v1.png").unlink()
    code, err = run_cli(["run", "all", str(tiny_scene)], capsys)
    assert code == 2 and "v1.png: image missing (named by scene.json views.1.image)" in err


def test_unreadable_image(tiny_scene, capsys):
    (tiny_scene / "images" / "v0.png").write_bytes(b"not a png")
    code, err = run_cli(["run", "all", str(tiny_scene)], capsys)
    assert code == 2 and "v0.png: unreadable image" in err


def test_image_not_two_to_one(tiny_scene, capsys):
    import cv2

    cv2.imwrite(str(tiny_scene / "images" / "v2.png"), np.zeros((10, 10, 3), np.uint8))
    code, err = run_cli(["run", "all", str(tiny_scene)], capsys)
    assert code == 2 and "v2.png: not an equirectangular 2:1 image: 10x10" in err


def test_debug_shows_traceback(tmp_path, capsys):
    from runfs.errors import PanoError

    old = sys.argv
    sys.argv = ["pano-pipe", "--debug", "run", "all", str(tmp_path / "nowhere")]
    try:
        with pytest.raises(PanoError):
            cli.main()
    finally:
        sys.argv = old
        cli._state["debug"] = False


def test_config_errors_name_the_file(tiny_scene, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("train: [1, 2")
    code, err = run_cli(["run", "all", str(tiny_scene), "--config", str(bad)], capsys)
    assert code == 2 and "bad.yaml: not valid YAML/JSON" in err
    code, err = run_cli(["run", "all", str(tiny_scene), "--set", "oops"], capsys)
    assert code == 2 and "--set: 'oops' is not STAGE.PARAM=VALUE" in err
