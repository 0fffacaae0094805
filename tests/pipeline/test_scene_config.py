"""Settings that stay with the scene: pano-pipe.yaml in the scene folder, below --config and --set;
a run folder belongs to one scene folder; printed follow-up commands keep the flags given."""

from __future__ import annotations

import shutil
from pathlib import Path

import simulate
from pipeline.cli import command_flags, make_engine
from tests.clitools import invoke


def _scene(tmp_path: Path, name: str = "scene") -> Path:
    scene = tmp_path / name
    simulate.generate_scene(scene, preset="cuboid", views=2, test_views=1, height=32, effects="none")
    return scene


def test_scene_file_sits_below_config_and_set(tmp_path):
    scene = _scene(tmp_path)
    (scene / "pano-pipe.yaml").write_text("train:\n  iterations: 11\n  height: 16\nposes:\n  method: upright\n")
    engine = make_engine(scene, tmp_path / "run", None, None)
    assert engine.params_for("train").iterations == 11 and engine.params_for("poses").method == "upright"
    config = tmp_path / "cfg.yaml"
    config.write_text("train:\n  iterations: 22\n")
    engine = make_engine(scene, tmp_path / "run", config, None)
    # --config wins for the parameter it sets; the scene's other parameters stay
    assert engine.params_for("train").iterations == 22 and engine.params_for("train").height == 16
    engine = make_engine(scene, tmp_path / "run", config, ["train.iterations=33"])
    assert engine.params_for("train").iterations == 33


def test_a_bad_scene_file_is_one_line_naming_it(tmp_path, capsys):
    scene = _scene(tmp_path)
    (scene / "pano-pipe.yaml").write_text("train: [1, 2\n")
    code, _, err = invoke(["status", scene, "--out", tmp_path / "run"], capsys)
    assert code == 2 and "pano-pipe.yaml" in err and len(err.strip().splitlines()) == 1


def test_run_folder_of_another_scene_folder_is_refused(tmp_path, capsys):
    scene = _scene(tmp_path)
    copy = tmp_path / "copy"
    shutil.copytree(scene, copy)  # the same name in scene.json: the same default run folder
    run = tmp_path / "run"
    code, _, err = invoke(["run", "poses", scene, "--out", run], capsys)  # posed: the stage is skipped
    assert code == 0, err
    for command in (["status"], ["run", "all"], ["report"]):
        code, _, err = invoke([*command, copy, "--out", run], capsys)
        assert code == 2 and len(err.strip().splitlines()) == 1, (command, err)
        assert str(scene.resolve()) in err and str(copy) in err
    code, _, err = invoke(["status", scene, "--out", run], capsys)
    assert code == 0, err


def test_a_scene_moved_with_its_run_folder_keeps_it(tmp_path, capsys):
    scene = _scene(tmp_path)
    code, _, err = invoke(["run", "poses", scene, "--out", tmp_path / "run"], capsys)
    assert code == 0, err
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    shutil.copytree(scene, moved / "scene")
    shutil.copytree(tmp_path / "run", moved / "run")
    code, _, err = invoke(["run", "poses", moved / "scene", "--out", moved / "run"], capsys)
    assert code == 0, err
    # the moved run folder now belongs to the moved scene, and only to it
    code, _, err = invoke(["status", scene, "--out", moved / "run"], capsys)
    assert code == 2 and str((moved / "scene").resolve()) in err


def test_follow_up_commands_keep_the_flags():
    assert command_flags(Path("runs/x"), Path("my cfg.yaml"), ["train.iterations=30", "poses.method=upright"]) == (
        " --out runs/x --config 'my cfg.yaml' --set train.iterations=30 --set poses.method=upright")
    assert command_flags(None, None, None) == ""


def test_a_batch_reads_each_scenes_own_file(tmp_path, capsys):
    """`run STAGE A B` runs each scene with its own pano-pipe.yaml, as `run STAGE A` would."""
    import json

    scenes = []
    for name in ("alpha", "beta"):
        scene = tmp_path / name
        simulate.generate_scene(scene, preset="cuboid", views=2, test_views=0, height=32, effects="none",
                                with_layout=True)
        scenes.append(scene)
    (scenes[0] / "pano-pipe.yaml").write_text("layout:\n  align: 'off'\n")
    out = tmp_path / "out"
    code, _, err = invoke(["run", "layout", *scenes, "--out", out], capsys)
    assert code == 0, err
    aligns = {}
    for scene in scenes:
        name = json.loads((scene / "scene.json").read_text()).get("name", scene.name)
        meta = json.loads((out / name / "layout" / "artifact.json").read_text())["meta"]
        aligns[scene.name] = meta["params"]["align"]
    assert aligns == {"alpha": "off", "beta": "auto"}
