"""A stage's code version covers every repository module it imports (issue 38): editing one makes
the stage stale, editing an unrelated one does not."""

from __future__ import annotations

import shutil
import textwrap
from pathlib import Path

import pytest
from pydantic import BaseModel

from runtime import code_closure
from runtime.code_closure import SOURCE_ROOT, code_version, import_closure
from pipeline.engine import Engine
from pipeline.registry import build_registry
from runtime.stage import StageSpec
from schemas.scene_loader import load_scene

PACKAGES = ("panogeom", "gaussians", "splatting", "stages", "pipeline", "schemas", "runfs", "evaluation", "sfm",
            "layoutnet", "depthnet", "models", "viewer", "export")


@pytest.fixture(scope="module")
def repo_copy(tmp_path_factory) -> Path:
    """The repository's packages, copied, to edit."""
    root = tmp_path_factory.mktemp("repo")
    for name in PACKAGES:
        shutil.copytree(SOURCE_ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    return root


def _append(path: Path, text: str = "\n# edited\n") -> None:
    path.write_text(path.read_text() + text)


def _versions(root: Path) -> dict[str, str]:
    return {name: code_version(spec.run.__module__, root) for name, spec in build_registry().items()}


def test_the_closure_follows_imports_at_the_top_inside_functions_and_native_sources():
    files = {p.relative_to(SOURCE_ROOT).as_posix() for p in import_closure("stages.train")}
    # stages/train.py and gaussians/view_jitter.py import panogeom; the loader reads the scene
    assert {"stages/train.py", "panogeom/equirect.py", "gaussians/view_jitter.py", "schemas/scene_loader.py",
            "splatting/csrc/splat_cpu.cpp", "splatting/csrc/project_cpu.h", "splatting/render.py"} <= files
    assert not any(f.startswith(("evaluation/", "viewer/", "sfm/")) for f in files)
    evaluate = {p.relative_to(SOURCE_ROOT).as_posix() for p in import_closure("stages.evaluate")}
    assert {"evaluation/metrics.py", "panogeom/equirect.py", "gaussians/model.py"} <= evaluate


def test_editing_an_imported_module_changes_the_version_and_an_unrelated_one_does_not(repo_copy):
    before = _versions(repo_copy)
    _append(repo_copy / "viewer" / "data.py")  # no stage imports the viewer
    assert _versions(repo_copy) == before

    _append(repo_copy / "panogeom" / "equirect.py")
    after = _versions(repo_copy)
    assert after["train"] != before["train"] and after["evaluate"] != before["evaluate"]
    assert after["union"] == before["union"]  # union imports no panogeom

    _append(repo_copy / "splatting" / "csrc" / "project_cpu.h", "\n// edited\n")
    again = _versions(repo_copy)
    assert again["train"] != after["train"] and again["sampling"] == after["sampling"]


def test_the_registry_keeps_no_hand_written_code_list():
    assert "code" not in StageSpec.__dataclass_fields__
    assert all(import_closure(spec.run.__module__) for spec in build_registry().values())


class NoParams(BaseModel):
    pass


def test_status_reports_the_stage_stale_after_an_imported_module_changes(tmp_path, tiny_scene, monkeypatch):
    root = tmp_path / "repo"
    (root / "toy_geometry").mkdir(parents=True)
    (root / "toy_geometry" / "__init__.py").write_text("")
    (root / "toy_geometry" / "angles.py").write_text("def half(x):\n    return x / 2\n")
    (root / "toy_geometry" / "unrelated.py").write_text("X = 1\n")
    (root / "toy_stage_module.py").write_text(textwrap.dedent("""
        from pydantic import BaseModel


        class Out(BaseModel):
            value: float


        def run(ctx):
            from toy_geometry.angles import half  # imported inside the function: still followed

            return Out(value=half(4))
    """))
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setattr(code_closure, "SOURCE_ROOT", root)
    import toy_stage_module

    registry = {"toy": StageSpec("toy", NoParams, toy_stage_module.Out, toy_stage_module.run)}

    def plan():
        return Engine(load_scene(tiny_scene), tmp_path / "run", registry).plan()["toy"]

    Engine(load_scene(tiny_scene), tmp_path / "run", registry).run()
    assert plan().state == "up-to-date"
    _append(root / "toy_geometry" / "unrelated.py")
    assert plan().state == "up-to-date"
    _append(root / "toy_geometry" / "angles.py")
    stale = plan()
    assert (stale.state, stale.reason) == ("stale", "code changed")
