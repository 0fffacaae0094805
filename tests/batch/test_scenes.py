"""Which scene folders a batch command line names, and where their runs go."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from batch.scenes import expand_scenes, is_batch, run_folders
from runfs.errors import PanoError


def make(root: Path, *names: str) -> list[Path]:
    out = []
    for n in names:
        (root / n).mkdir(parents=True)
        (root / n / "scene.json").write_text("{}")
        out.append(root / n)
    return out


def test_a_folder_of_scenes_expands_to_its_scene_folders_by_name(tmp_path):
    b, a = make(tmp_path / "tour", "b", "a")
    (tmp_path / "tour" / "notes").mkdir()  # no scene.json: not a scene
    assert expand_scenes([tmp_path / "tour"]) == [a, b]
    assert is_batch([tmp_path / "tour"]) and not is_batch([a]) and is_batch([a, b])


def test_order_is_kept_and_duplicates_dropped(tmp_path):
    a, b = make(tmp_path, "a", "b")
    assert expand_scenes([b, a, tmp_path / "b" / ".." / "b", a]) == [b, a]


def test_a_path_that_is_no_scene_is_kept_to_fail_alone(tmp_path):
    (a,) = make(tmp_path, "a")
    assert expand_scenes([a, tmp_path / "missing"]) == [a, tmp_path / "missing"]


def test_run_folders_are_out_root_slash_scene_name(tmp_path):
    a, b = make(tmp_path, "a", "b")
    assert run_folders([a, b], {a: "kitchen", b: "hall"}, tmp_path / "runs") == {
        a: tmp_path / "runs" / "kitchen", b: tmp_path / "runs" / "hall"}


def test_two_scenes_of_one_name_are_refused(tmp_path):
    a, b = make(tmp_path, "a", "b")
    with pytest.raises(PanoError) as info:
        run_folders([a, b], {a: "flat", b: "flat"}, tmp_path / "runs")
    assert "flat" in str(info.value) and str(b) in str(info.value) and "\n" not in str(info.value)
    json.dumps(str(info.value))
