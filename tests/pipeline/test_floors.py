"""Imports run one way, down the floors docs/architecture.md describes ("Floors"): no module
imports a module on a higher floor but the few listed here, each with its reason, and nothing
new joins them unnoticed."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

#: Floor of each package, lowest first; modules in TOP are on the top floor wherever they live.
FLOORS = {
    "runfs": 0,  # files, paths, limits, errors: imports nothing of pano-pipe
    "schemas": 1, "panogeom": 1, "runtime": 1,  # data contracts, conventions, the stage contract, the console
    "splatting": 2, "models": 2,  # the renderer; the model registry and cache
    "gaussians": 3, "layoutnet": 3, "depthnet": 3, "sfm": 3, "simulate": 3, "evaluation": 3, "export": 3,
    "floorplan": 3, "depthalign": 3,  # the layout's geometry; depth made metric by it
    "stages": 4,  # one module per stage: glue over the floors below
    "pipeline": 5,  # the DAG, the engine, settings, importers
    "batch": 6, "viewer": 6,  # drive the engine / read run folders
}
#: Commands and applications kept beside their packages (docs/architecture.md): the top floor.
TOP = ("pipeline.cli", "evaluation.commands", "evaluation.report", "evaluation.report_sections",
       "evaluation.report_poses", "evaluation.experiments", "evaluation.ablate_estimate")
TOP_NAMES = {"command", "commands", "bench", "bench_commands", "benchmarks", "bench_train"}
#: The imports that still run up, each with why it is left.
ALLOWED_UP = {
    # the crops' camera rig is the renderer's type; the artifact records it as the renderer describes it
    ("schemas.train", "splatting"),
    # a fly-through's camera path from a nerfstudio file: the importers' conversion, not a copy of it
    ("evaluation.flythrough", "pipeline.importers"),
}


def _floor(module: str) -> int | None:
    if module in TOP or module.rsplit(".", 1)[-1] in TOP_NAMES or module.startswith(TOP):
        return 7
    return FLOORS.get(module.split(".")[0])


def _module_of(name: str) -> str:
    """The longest prefix of a dotted name that is a module or package of the repository."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        path = REPO.joinpath(*parts[:k])
        if path.with_suffix(".py").is_file() or (path / "__init__.py").is_file():
            return ".".join(parts[:k])
    return name


def upward_imports() -> set[tuple[str, str]]:
    found = set()
    for package in FLOORS:
        for path in (REPO / package).rglob("*.py"):
            module = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
            here = _floor(module)
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [f"{node.module}.{a.name}" for a in node.names]
                else:
                    continue
                for name in names:
                    target = _module_of(name)
                    there = _floor(target)
                    if there is not None and target.split(".")[0] in FLOORS and there > here:
                        found.add((module, target))
    return found


def test_imports_run_down_the_floors():
    up = upward_imports()
    assert up - ALLOWED_UP == set(), sorted(up - ALLOWED_UP)
    assert len(ALLOWED_UP) <= 5
    # and the allowance is not stale: each listed import still exists
    assert ALLOWED_UP <= up, sorted(ALLOWED_UP - up)


def test_the_floor_check_sees_an_import_that_runs_up(tmp_path, monkeypatch):
    """A stage module importing the engine is caught (the check is not vacuous)."""
    fake = tmp_path / "stages"
    fake.mkdir()
    (fake / "__init__.py").write_text("")
    (fake / "bad.py").write_text("from pipeline.engine import Engine\n")
    (tmp_path / "pipeline").mkdir()
    (tmp_path / "pipeline" / "__init__.py").write_text("")
    (tmp_path / "pipeline" / "engine.py").write_text("")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert ("stages.bad", "pipeline.engine") in upward_imports()
