"""What a stage is: a pure function from typed inputs to a typed artifact.

A stage module (stages/<name>.py) defines

    class Params(BaseModel): ...                       # its parameters
    class Output(BaseModel): ...                       # the `data` of its artifact.json (schemas/)
    def skip_reason(scene, params) -> str | None: ...  # why this scene does not call for it
    def run(ctx: StageContext) -> Output: ...          # the work; writes files into ctx.out_dir

and pipeline/registry.py wires it into the DAG.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel

from schemas.artifact import ArtifactMeta
from schemas.scene import Scene, View

P = TypeVar("P", bound=BaseModel)
D = TypeVar("D", bound=BaseModel)


@dataclass(frozen=True)
class StageSpec:
    name: str
    params: type[BaseModel]
    output: type[BaseModel]
    run: Callable[[StageContext], BaseModel]
    #: upstream stage -> required? A skipped required input skips this stage;
    #: a skipped optional input reaches `run` as None.
    inputs: dict[str, bool] = field(default_factory=dict)
    #: Kinds of scene files the stage reads (images, layout, depth, masks, gt; see the engine's
    #: _KIND_FIELDS): only those enter its cache key.
    scene_inputs: tuple[str, ...] = ("images",)
    #: The views whose manifest entries and files the stage reads (None = all): a changed test
    #: image must not retrain the model.
    reads_views: Callable[[Scene, BaseModel], list[View]] | None = None
    skip_reason: Callable[[Scene, BaseModel], str | None] | None = None
    #: For a stage only some scenes call for: why this one does ("3 views have no pose in
    #: scene.json"); `status` shows it beside the cache state when the stage will run.
    run_reason: Callable[[Scene, BaseModel], str] | None = None
    #: Fills in what a parameter names (a model name -> its ONNX file in the user's cache, a cached
    #: model where none is set); runs after validation, before the cache key is made.
    resolve_params: Callable[[Scene, BaseModel], BaseModel] | None = None
    #: One line for `status` and the run header when the scene lacks something the user can get
    #: (the command that gets it); None when nothing is missing.
    hint: Callable[[Scene, BaseModel], str | None] | None = None
    description: str = ""
    #: For a stage whose artifact fills in what the scene left out (poses): (scene, its artifact) ->
    #: the completed scene. Every stage downstream of it runs on the completed scene.
    completes_scene: Callable[[Scene, Loaded], Scene] | None = None
    #: What one run of the stage occupies, for a batch executor: {"CPU": n, "GPU": g}.
    resources: Callable[[BaseModel], dict[str, float]] = field(default=lambda params: {"CPU": 1.0})

    def code_version(self) -> str:
        """The hash of the repository sources the stage's module imports (runtime/code_closure.py)."""
        from runtime.code_closure import code_version

        return code_version(self.run.__module__)


@dataclass
class Loaded(Generic[D]):
    """An upstream artifact: its typed data, the folder its relative paths resolve against, and
    its meta (the parameters it was made with; None where a test builds one by hand)."""

    data: D
    dir: Path
    meta: ArtifactMeta | None = None

    def path(self, rel: str) -> Path:
        """A file the artifact names: relative, inside the stage's folder, no link on the way."""
        from runfs.paths import run_path

        return run_path(self.dir, rel, named_by=f"{self.dir.name}/artifact.json")


@dataclass
class StageContext(Generic[P]):
    scene: Scene
    params: P
    inputs: dict[str, Loaded | None]
    out_dir: Path
    #: Progress reporter: ctx.track(iterable, "what", total=n) yields the items.
    track: Callable[..., Iterable[Any]] = field(default=lambda it, description="", total=None: it)
    warnings: list[str] = field(default_factory=list)
    #: A folder that survives a failed or interrupted attempt (checkpoints for --resume).
    scratch_dir: Path | None = None
    resume: bool = False

    def input(self, name: str) -> Loaded | None:
        return self.inputs.get(name)

    def warn(self, message: str) -> None:
        from rich.markup import escape

        from runtime.console import console

        console.print(f"[yellow]warning:[/] {escape(message)}")
        self.warnings.append(message)
