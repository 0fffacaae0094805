"""The C++ kernel's first build is a step of its own before training, not training time."""

from __future__ import annotations

import json

import pytest

from simulate.generate import generate_scene
from splatting import raster_cpp
from stages import train as train_stage
from tests.clitools import invoke

TINY = ["--set", "train.iterations=2", "--set", "train.height=8", "--set", "train.device=cpu"]


@pytest.fixture()
def events(monkeypatch):
    """What happened, in order: the kernel's build (made to look first-time) and the training loop."""
    seen = []
    real_load, real_train = raster_cpp.load, train_stage.Trainer.train

    def load():
        seen.append("kernel")
        return real_load()

    def train(self, *args, **kwargs):
        seen.append("training")
        return real_train(self, *args, **kwargs)

    monkeypatch.setattr(raster_cpp, "load", load)
    monkeypatch.setattr(train_stage.Trainer, "train", train)
    return seen


def test_a_first_build_comes_before_training_and_is_recorded_apart(tmp_path, capsys, monkeypatch, events):
    monkeypatch.setattr(raster_cpp, "is_built", lambda: False)
    generate_scene(tmp_path / "S", views=2, test_views=0, height=16, effects="none")
    code, out, err = invoke(["run", "train", tmp_path / "S", "--out", tmp_path / "R", *TINY], capsys)
    assert code == 0, err
    assert events[:2] == ["kernel", "training"]  # train_seconds is timed inside the training loop
    said = " ".join(out.split())
    assert "compiling the C++ CPU kernel (once per machine; not counted as training)" in said
    assert said.index("C++ kernel built in") < said.index("model: ")
    data = json.loads((tmp_path / "R" / "train" / "artifact.json").read_text())["data"]
    assert data["kernel_build_seconds"] is not None and data["kernel_build_seconds"] >= 0


def test_a_built_kernel_is_no_step(tmp_path, capsys, monkeypatch, events):
    monkeypatch.setattr(raster_cpp, "is_built", lambda: True)
    generate_scene(tmp_path / "S", views=2, test_views=0, height=16, effects="none")
    code, out, err = invoke(["run", "train", tmp_path / "S", "--out", tmp_path / "R", *TINY], capsys)
    assert code == 0, err
    assert "compiling the C++" not in out
    assert json.loads((tmp_path / "R" / "train" / "artifact.json").read_text())["data"].get(
        "kernel_build_seconds") is None
