"""What a newcomer types first: --version, a bare `run`, a misspelt stage or parameter, a flag
given a value, `params` piped into grep, and the first ETA of a long task."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from runtime import console as console_module
from runtime.console import PlainProgress
from pipeline.registry import build_registry
from simulate.generate import generate_scene
from tests.clitools import invoke

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("newcomer")
    generate_scene(root / "S", views=2, test_views=1, height=16, effects="none", with_layout=True)
    return root / "S"


def test_version_prints_the_project_version(capsys):
    code, out, err = invoke(["--version"], capsys)
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert code == 0 and out.strip() == f"pano-pipe {version}" and err == ""


def test_bare_run_says_what_it_takes_with_an_example(capsys):
    code, out, err = invoke(["run"], capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert "pano-pipe run all" in err and "train" in err and "--help" in err


@pytest.mark.parametrize("typo, meant", [("train.iteratons", "iterations"),
                                         ("train.lr_opactiy", "lr_opacity")])
def test_a_misspelt_parameter_suggests_the_closest(scene, tmp_path, capsys, typo, meant):
    code, out, err = invoke(["status", scene, "--out", tmp_path / "R", "--set", f"{typo}=3"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"did you mean {meant}?" in err and "`pano-pipe params train` lists all" in err
    closest = err.split("the closest: ")[1].split(" (")[0].split(", ")
    assert meant in closest and len(closest) <= 4  # a few names, not all 60-odd


def test_a_misspelt_stage_in_set_suggests_the_closest(scene, tmp_path, capsys):
    code, out, err = invoke(["status", scene, "--out", tmp_path / "R", "--set", "trian.iterations=3"], capsys)
    assert code == 2 and "did you mean train?" in err


def test_a_parameter_far_from_every_name_gets_no_suggestion(scene, tmp_path, capsys):
    code, out, err = invoke(["status", scene, "--out", tmp_path / "R", "--set", "train.zzzzqqq=3"], capsys)
    assert code == 2 and "did you mean" not in err and "the closest: " in err and "pano-pipe params train" in err


@pytest.mark.parametrize("args, meant", [
    (["--until", "trian"], "train"),
    (["--set", "train.iteratons=3"], "iterations"),
])
def test_run_refuses_a_typo_before_printing_anything(scene, tmp_path, capsys, args, meant):
    code, out, err = invoke(["run", "all", scene, "--out", tmp_path / "R", *args], capsys)
    assert code == 2 and out == "", out  # no banner, no table: nothing ran
    assert f"did you mean {meant}?" in err
    assert not (tmp_path / "R").exists()


def test_run_of_a_misspelt_stage_suggests_it(scene, tmp_path, capsys):
    code, out, err = invoke(["run", "evalute", scene, "--out", tmp_path / "R"], capsys)
    assert code == 2 and out == "" and "did you mean evaluate?" in err


def test_help_shows_on_off_options_as_bare_flags(capsys):
    code, out, err = invoke(["export", "--help"], capsys)
    assert code == 0
    line = next(l for l in out.splitlines() if "--y-up" in l)
    assert "<bool>" not in out and "bool" not in line
    assert "--mesh-depth" in out and "<int" in out  # options with values still show their type


@pytest.mark.parametrize("value", ["true", "false", "1"])
def test_a_flag_given_a_value_says_it_is_a_flag(tmp_path, capsys, value):
    code, out, err = invoke(["export", tmp_path / "nothing", "--y-up", value], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "--y-up is a flag" in err and "write --y-up to turn it on" in err


def test_a_stray_argument_that_follows_no_flag_gets_no_flag_hint(tmp_path, capsys):
    code, out, err = invoke(["export", tmp_path / "nothing", "true"], capsys)
    assert code == 2 and "unexpected extra argument" in err and "is a flag" not in err


def test_flags_parse_as_flags(tmp_path, capsys):
    # the flag itself is accepted: the command gets as far as the missing run folder
    code, out, err = invoke(["export", tmp_path / "nothing", "--y-up", "--overwrite"], capsys)
    assert code == 2 and "no such run folder" in err


def test_piped_params_are_one_unwrapped_line_per_parameter(capsys, monkeypatch):
    monkeypatch.setattr(console_module.console, "_force_terminal", False)
    monkeypatch.setattr(console_module.console, "_width", 40)  # a narrow pipe must not wrap either
    code, out, err = invoke(["params"], capsys)
    assert code == 0
    rows = [line.split("\t") for line in out.splitlines() if not line.startswith("#")]
    names = [r[0] for r in rows]
    expected = [f"{s}.{f}" for s, spec in build_registry().items() for f in spec.params.model_fields]
    assert names == expected and all(len(r) == 4 for r in rows)
    assert any(r[0] == "poses.working_height" for r in rows)


def test_every_parameter_has_a_description():
    missing = [f"{s}.{f}" for s, spec in build_registry().items()
               for f, info in spec.params.model_fields.items() if not (info.description or "").strip()]
    assert missing == []


def test_first_eta_leaves_out_the_warm_up(capsys, monkeypatch):
    clock = {"now": 0.0}
    monkeypatch.setattr(console_module.time, "monotonic", lambda: clock["now"])
    with PlainProgress(every_s=0.0) as progress:
        task = progress.add_task("train", total=1000)
        clock["now"] = 300.0  # the kernel compile and the first iteration
        progress.update(task, completed=1)
        for i in range(2, 12):
            clock["now"] += 0.5  # then 2 iterations/s
            progress.update(task, completed=i)
    lines = capsys.readouterr().out.splitlines()
    assert "ETA" not in lines[0]
    eta = float(re.search(r"ETA (\d+) s", lines[-1]).group(1))
    assert eta == pytest.approx((1000 - 11) / 2.0, abs=1)
