"""A scene calls only for what it can use: the real registry's skip rules, and `status`/`schema`."""

from __future__ import annotations

import json
import sys

import pytest

import simulate
from pipeline import cli
from pipeline.engine import Engine
from pipeline.registry import build_registry
from schemas.scene_loader import load_scene


def plan(scene_dir, tmp_path):
    return Engine(load_scene(scene_dir), tmp_path / "run", build_registry()).plan()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    out = {}
    for name, layout, depth in [("both", True, True), ("layout", True, False), ("bare", False, False)]:
        simulate.generate_scene(
            root / name, preset="cuboid", views=2, test_views=1, height=16, effects="none",
            with_layout=layout, with_depth=depth,
        )
        out[name] = root / name
    return out


def test_layout_and_depth_run_everything(scenes, tmp_path):
    states = {k: p.state for k, p in plan(scenes["both"], tmp_path).items()}
    assert states.pop("poses") == "skipped"  # every view has a pose
    assert set(states.values()) == {"missing"}


def test_no_depth_skips_depth_and_align(scenes, tmp_path):
    p = plan(scenes["layout"], tmp_path)
    assert p["depth"].state == "skipped" and "no depth files" in p["depth"].reason
    assert p["align"].state == "skipped" and p["align"].reason == "needs depth, which is skipped"
    assert {p[s].state for s in ("layout", "union", "sampling", "train", "evaluate")} == {"missing"}


def test_no_priors_trains_from_random_init(scenes, tmp_path):
    p = plan(scenes["bare"], tmp_path)
    assert p["layout"].state == "skipped" and "no layout source" in p["layout"].reason
    for stage in ("union", "sampling", "depth", "align"):
        assert p[stage].state == "skipped"
    assert p["train"].state == "missing" and p["evaluate"].state == "missing"


def test_supplied_layout_needs_no_model(scenes, tmp_path):
    # With files supplied the layout stage runs without any model configured.
    p = Engine(load_scene(scenes["layout"]), tmp_path / "run", build_registry(), {"layout": {}}).plan()
    assert p["layout"].state == "missing" and p["layout"].params.model is None


def run_ok(args: list[str]) -> None:
    old = sys.argv
    sys.argv = ["pano-pipe", *args]
    try:
        cli.main()  # returns normally on success
    finally:
        sys.argv = old


def test_status_table_says_why(scenes, tmp_path, capsys):
    run_ok(["status", str(scenes["bare"]), "--out", str(tmp_path / "run")])
    out = capsys.readouterr().out  # progress and tables go to stdout; stderr holds errors only
    assert "skipped" in out and "no layout source" in out and "missing" in out
    # and the one line that says how to get a layout model
    assert "pano-pipe models fetch horizonnet-zind" in " ".join(out.split())


def test_schema_command_writes_every_schema(tmp_path):
    run_ok(["schema", str(tmp_path)])
    names = sorted(p.name for p in tmp_path.glob("*.schema.json"))
    assert names == sorted(["scene.schema.json"] + [f"{s}.artifact.schema.json" for s in build_registry()])
    scene_schema = json.loads((tmp_path / "scene.schema.json").read_text())
    assert "views" in scene_schema["properties"]
