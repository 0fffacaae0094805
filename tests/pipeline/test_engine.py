"""The DAG engine on a toy registry: ordering, caching, skip rules, atomic results."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
from pydantic import BaseModel, ConfigDict

from pipeline.engine import Engine, ancestors, topological_order
from schemas.scene_loader import load_scene
from runtime.stage import StageContext, StageSpec

CALLS: Counter[str] = Counter()


class Knob(BaseModel):
    model_config = ConfigDict(extra="forbid")
    value: int = 1
    fail: bool = False
    skip: bool = False


class Out(BaseModel):
    file: str
    total: int


def make_stage(name: str, inputs: dict[str, bool], scene_inputs=("images",)) -> StageSpec:
    def run(ctx: StageContext) -> Out:
        CALLS[name] += 1
        total = ctx.params.value
        for dep in inputs:
            loaded = ctx.inputs[dep]
            if loaded is not None:
                total += loaded.data.total
                assert loaded.path(loaded.data.file).read_text() == str(loaded.data.total)
        (ctx.out_dir / "result.txt").write_text(str(total))
        if ctx.params.fail:
            raise RuntimeError("stage failed halfway")
        return Out(file="result.txt", total=total)

    def skip_reason(scene, params):
        return "asked to skip" if params.skip else None

    return StageSpec(name, Knob, Out, run, inputs=inputs, scene_inputs=scene_inputs, skip_reason=skip_reason)


def toy_registry() -> dict[str, StageSpec]:
    # a -> b -> c ; a -> d (optional input from x, which may be skipped)
    specs = [
        make_stage("x", {}),
        make_stage("a", {}),
        make_stage("b", {"a": True}),
        make_stage("c", {"b": True}),
        make_stage("d", {"a": True, "x": False}),
    ]
    return {s.name: s for s in specs}


@pytest.fixture(autouse=True)
def _reset_calls():
    CALLS.clear()


def engine(scene_dir: Path, out: Path, config=None) -> Engine:
    return Engine(load_scene(scene_dir), out, toy_registry(), config or {})


def test_topological_order_and_ancestors():
    reg = toy_registry()
    order = topological_order(reg)
    assert order.index("a") < order.index("b") < order.index("c")
    assert order.index("x") < order.index("d")
    assert ancestors(reg, "c") == {"a", "b"}
    # where the dependencies allow it, the order is the registry's (z declared first, then y after it)
    assert topological_order({"z": make_stage("z", {}), "y": make_stage("y", {"z": True}),
                              "w": make_stage("w", {})}) == ["z", "y", "w"]


def test_cycle_is_reported():
    reg = toy_registry()
    reg["a"] = make_stage("a", {"c": True})
    with pytest.raises(ValueError, match="cycle"):
        topological_order(reg)


def test_second_run_runs_nothing(tiny_scene, tmp_path):
    out = tmp_path / "run"
    first = engine(tiny_scene, out).run()
    assert {r.outcome for r in first} == {"ran"}
    assert sum(CALLS.values()) == 5
    second = engine(tiny_scene, out).run()
    assert {r.outcome for r in second} == {"cached"}
    assert sum(CALLS.values()) == 5
    assert json.loads((out / "c" / "artifact.json").read_text())["data"]["total"] == 3


def test_parameter_change_reruns_stage_and_dependents_only(tiny_scene, tmp_path):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    CALLS.clear()
    results = engine(tiny_scene, out, {"b": {"value": 5}}).run()
    assert dict(CALLS) == {"b": 1, "c": 1}
    assert {r.name: r.outcome for r in results}["d"] == "cached"
    assert json.loads((out / "c" / "artifact.json").read_text())["data"]["total"] == 7


def test_scene_file_change_reruns_readers(tiny_scene, tmp_path):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    CALLS.clear()
    img = tiny_scene / "images" / "v0.png"
    img.write_bytes(img.read_bytes())  # same bytes: still up to date
    engine(tiny_scene, out).run()
    assert not CALLS
    import cv2
    import numpy as np

    cv2.imwrite(str(img), np.zeros((8, 16, 3), np.uint8))
    engine(tiny_scene, out).run()
    assert set(CALLS) == {"x", "a", "b", "c", "d"}


def test_code_change_makes_stage_stale(tiny_scene, tmp_path, monkeypatch):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    e = engine(tiny_scene, out)
    monkeypatch.setattr(StageSpec, "code_version", lambda self: "v2" if self.name == "c" else "v1")
    plans = e.plan()
    assert plans["c"].state == "stale"


def test_skip_rules_required_and_optional(tiny_scene, tmp_path):
    out = tmp_path / "run"
    e = engine(tiny_scene, out, {"x": {"skip": True}, "a": {"skip": False}})
    plans = e.plan()
    assert plans["x"].state == "skipped" and plans["x"].reason == "asked to skip"
    assert plans["d"].state == "missing"  # optional input skipped: d still runs
    e.run()
    assert CALLS["x"] == 0 and CALLS["d"] == 1

    e = engine(tiny_scene, tmp_path / "run2", {"a": {"skip": True}})
    plans = e.plan()
    assert plans["b"].state == "skipped" and plans["b"].reason == "needs a, which is skipped"
    assert plans["c"].reason == "needs b, which is skipped"


def test_an_up_to_date_target_is_cached_and_force_reruns_it_alone(tiny_scene, tmp_path):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    CALLS.clear()
    results = engine(tiny_scene, out).run(target="b")
    assert dict(CALLS) == {} and [(r.name, r.outcome) for r in results] == [("a", "cached"), ("b", "cached")]
    results = engine(tiny_scene, out).run(target="b", force=True)
    assert dict(CALLS) == {"b": 1}
    assert [(r.name, r.outcome) for r in results] == [("a", "cached"), ("b", "ran")]


def test_until_and_force(tiny_scene, tmp_path):
    out = tmp_path / "run"
    results = engine(tiny_scene, out).run(until="b")
    assert [r.name for r in results] == ["a", "b"]
    assert not (out / "c").exists()
    CALLS.clear()
    engine(tiny_scene, out).run(until="b", force=True)
    assert dict(CALLS) == {"a": 1, "b": 1}


def test_failing_stage_leaves_previous_artifact_byte_identical(tiny_scene, tmp_path):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    before = {p: p.read_bytes() for p in (out / "b").rglob("*") if p.is_file()}
    with pytest.raises(RuntimeError, match="halfway"):
        engine(tiny_scene, out, {"b": {"value": 9, "fail": True}}).run()
    after = {p: p.read_bytes() for p in (out / "b").rglob("*") if p.is_file()}
    assert before == after
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp-")]
    log = [json.loads(line) for line in (out / "run_log.jsonl").read_text().splitlines()]
    assert log[-1]["stage"] == "b" and log[-1]["event"] == "failed"


def test_interrupted_stage_leaves_previous_artifact(tiny_scene, tmp_path, monkeypatch):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    before = (out / "a" / "artifact.json").read_bytes()
    e = engine(tiny_scene, out, {"a": {"value": 2}})

    def interrupted(ctx):
        (ctx.out_dir / "result.txt").write_text("partial")
        raise KeyboardInterrupt

    e.registry["a"] = StageSpec("a", Knob, Out, interrupted)
    with pytest.raises(KeyboardInterrupt):
        e.run()
    assert (out / "a" / "artifact.json").read_bytes() == before
    assert (out / "a" / "result.txt").read_text() == "1"


def test_run_log_records_start_end_duration(tiny_scene, tmp_path):
    out = tmp_path / "run"
    engine(tiny_scene, out).run()
    engine(tiny_scene, out).run()
    log = [json.loads(line) for line in (out / "run_log.jsonl").read_text().splitlines()]
    events = Counter((r["stage"], r["event"]) for r in log)
    assert events[("a", "start")] == 1 and events[("a", "ok")] == 1 and events[("a", "cached")] == 1
    assert all(r["duration_s"] >= 0 for r in log if r["event"] == "ok")


def test_unknown_stage_in_config_is_reported(tiny_scene, tmp_path):
    from runfs.errors import PanoError

    with pytest.raises(PanoError, match="unknown stage"):
        engine(tiny_scene, tmp_path / "run", {"nope": {}})
    e = engine(tiny_scene, tmp_path / "run", {"a": {"valu": 3}})
    with pytest.raises(PanoError, match=r"\[a\].*valu"):
        e.plan()


def test_replacing_a_model_file_reruns_the_stage(tiny_scene, tmp_path):
    from pathlib import Path as _Path

    class ModelParams(BaseModel):
        model: _Path | None = None

    def run(ctx):
        return Out(file="", total=len(ctx.params.model.read_bytes()))

    reg = {"m": StageSpec("m", ModelParams, Out, run)}
    model = tmp_path / "model.onnx"
    model.write_bytes(b"v1")
    e = Engine(load_scene(tiny_scene), tmp_path / "run", reg, {"m": {"model": str(model)}})
    e.run()
    assert Engine(load_scene(tiny_scene), tmp_path / "run", reg, {"m": {"model": str(model)}}).plan()["m"].state == "up-to-date"
    model.write_bytes(b"v2!")
    assert Engine(load_scene(tiny_scene), tmp_path / "run", reg, {"m": {"model": str(model)}}).plan()["m"].state == "stale"
