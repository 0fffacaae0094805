"""The DAG engine: plan (keys, skip rules, staleness), then run in topological order.

A stage's cache key chains the hash of the scene files it reads, its
parameters, its code version and its upstream stages' keys, so a change
anywhere reruns exactly the stages downstream of it.
"""

from __future__ import annotations

import graphlib
import json
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ValidationError

from pipeline.console import console, track
from pipeline.errors import PanoError, describe_validation_error
from pipeline.fsutil import atomic_folder, sha256_file, sha256_json
from pipeline.stage import Loaded, StageContext, StageSpec
from schemas.artifact import Artifact, ArtifactMeta
from schemas.scene import Scene

State = Literal["up-to-date", "stale", "missing", "skipped"]
ARTIFACT = "artifact.json"
RUN_LOG = "run_log.jsonl"


@dataclass
class StagePlan:
    name: str
    state: State
    params: BaseModel | None = None
    key: str | None = None
    reason: str = ""
    last_duration_s: float | None = None
    upstream: dict[str, str] = field(default_factory=dict)
    code_version: str = ""


@dataclass
class StageResult:
    name: str
    outcome: Literal["ran", "cached", "skipped", "failed"]
    duration_s: float = 0.0
    reason: str = ""


def topological_order(registry: dict[str, StageSpec]) -> list[str]:
    graph = {name: set(spec.inputs) for name, spec in registry.items()}
    for name, deps in graph.items():
        unknown = deps - graph.keys()
        if unknown:
            raise ValueError(f"stage {name!r} depends on unknown stage(s) {sorted(unknown)}")
    try:
        return list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as e:
        raise ValueError(f"stage graph has a cycle: {' -> '.join(e.args[1])}") from None


def ancestors(registry: dict[str, StageSpec], name: str) -> set[str]:
    seen: set[str] = set()
    stack = [name]
    while stack:
        for dep in registry[stack.pop()].inputs:
            if dep not in seen:
                seen.add(dep)
                stack.append(dep)
    return seen


def read_meta(stage_dir: Path) -> ArtifactMeta | None:
    """The meta block of an existing artifact, or None if absent or unreadable."""
    try:
        raw = json.loads((stage_dir / ARTIFACT).read_text())
        return ArtifactMeta.model_validate(raw["meta"])
    except (OSError, ValueError, KeyError, ValidationError):
        return None


def load_artifact(stage_dir: Path, output: type[BaseModel]) -> Loaded:
    path = stage_dir / ARTIFACT
    try:
        art = Artifact[output].model_validate_json(path.read_text())
    except FileNotFoundError:
        raise PanoError(path, "missing; run the stage first") from None
    except ValidationError as e:
        raise describe_validation_error(path, e) from None
    return Loaded(data=art.data, dir=stage_dir)


class Engine:
    def __init__(
        self,
        scene: Scene,
        out_dir: Path,
        registry: dict[str, StageSpec],
        config: dict[str, dict] | None = None,
        config_source: str = "config",
    ):
        self.scene = scene
        self.out_dir = Path(out_dir)
        self.registry = registry
        self.order = topological_order(registry)
        self.config = config or {}
        self.config_source = config_source
        unknown = set(self.config) - set(registry)
        if unknown:
            raise PanoError(config_source, f"unknown stage(s) {sorted(unknown)}; stages are {self.order}")
        self._fingerprints: dict[str, str] = {}
        self._file_hashes: dict[Path, str] = {}

    # -- planning ---------------------------------------------------------
    def params_for(self, name: str) -> BaseModel:
        spec = self.registry[name]
        try:
            return spec.params.model_validate(self.config.get(name, {}))
        except ValidationError as e:
            raise describe_validation_error(f"{self.config_source} [{name}]", e) from None

    def scene_fingerprint(self, kinds: tuple[str, ...]) -> str:
        parts = [sha256_json(self.scene.manifest.model_dump(mode="json"))]
        for kind in sorted(kinds):
            if kind not in self._fingerprints:
                self._fingerprints[kind] = sha256_json(
                    {str(p.relative_to(self.scene.root)): sha256_file(p) for p in self._scene_files(kind)}
                )
            parts.append(f"{kind}:{self._fingerprints[kind]}")
        return sha256_json(parts)

    def _scene_files(self, kind: str) -> list[Path]:
        s = self.scene
        if kind == "images":
            files = [s.image_path(v) for v in s.views]
        elif kind == "layout":
            files = [s.layout_path(v) for v in s.views]
        elif kind == "depth":
            files = [s.depth_path(v) for v in s.views]
        elif kind == "gt":
            files = [s.gt_depth_path(v) for v in s.views]
            if s.manifest.floor_plan:
                files.append(s.path(s.manifest.floor_plan))
        else:
            raise ValueError(f"unknown scene input kind {kind!r}")
        return [f for f in files if f is not None and f.is_file()]

    def param_file_hashes(self, params: BaseModel) -> dict[str, str]:
        """Content hashes of files named by parameters (models): replacing one reruns the stage."""
        out = {}
        for field_name, value in params:
            if isinstance(value, Path) and value.is_file():
                if value not in self._file_hashes:
                    self._file_hashes[value] = sha256_file(value)
                out[field_name] = self._file_hashes[value]
        return out

    def plan(self) -> dict[str, StagePlan]:
        plans: dict[str, StagePlan] = {}
        for name in self.order:
            spec = self.registry[name]
            params = self.params_for(name)
            reason = spec.skip_reason(self.scene, params) if spec.skip_reason else None
            if reason is None:
                for dep, required in spec.inputs.items():
                    if required and plans[dep].state == "skipped":
                        reason = f"needs {dep}, which is skipped"
                        break
            meta = read_meta(self.out_dir / name)
            last = meta.duration_s if meta else None
            if reason is not None:
                plans[name] = StagePlan(name, "skipped", params, reason=reason, last_duration_s=last)
                continue
            upstream = {
                dep: plans[dep].key or "skipped" for dep in spec.inputs
            }
            code = spec.code_version()
            key = sha256_json(
                {
                    "stage": name,
                    "scene": self.scene_fingerprint(spec.scene_inputs),
                    "params": params.model_dump(mode="json"),
                    "param_files": self.param_file_hashes(params),
                    "code": code,
                    "upstream": upstream,
                }
            )
            if meta is None:
                state: State = "missing"
            elif meta.key == key:
                state = "up-to-date"
            else:
                state = "stale"
            plans[name] = StagePlan(
                name, state, params, key, last_duration_s=last, upstream=upstream, code_version=code
            )
        return plans

    # -- running ----------------------------------------------------------
    def select(self, target: str | None = None, until: str | None = None) -> list[str]:
        """Stages a run touches: all, or the target/until stage and its ancestors, in order."""
        stop = target or until
        if stop is None:
            return list(self.order)
        if stop not in self.registry:
            raise PanoError(None, f"unknown stage {stop!r}; stages are {', '.join(self.order)}")
        wanted = ancestors(self.registry, stop) | {stop}
        return [n for n in self.order if n in wanted]

    def run(
        self,
        target: str | None = None,
        until: str | None = None,
        force: bool = False,
        resume: bool = False,
    ) -> list[StageResult]:
        """Run the selected stages. `target` is always rerun; `force` reruns every selected stage."""
        plans = self.plan()
        results: list[StageResult] = []
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for name in self.select(target, until):
            p = plans[name]
            if p.state == "skipped":
                self._log(name, "skipped", reason=p.reason)
                results.append(StageResult(name, "skipped", reason=p.reason))
                continue
            if p.state == "up-to-date" and not force and name != target:
                self._log(name, "cached")
                results.append(StageResult(name, "cached", p.last_duration_s or 0.0))
                continue
            results.append(self._run_stage(p, plans, resume=resume))
        return results

    def _run_stage(self, p: StagePlan, plans: dict[str, StagePlan], resume: bool) -> StageResult:
        spec = self.registry[p.name]
        inputs: dict[str, Loaded | None] = {}
        for dep in spec.inputs:
            if plans[dep].state == "skipped":
                inputs[dep] = None
            else:
                inputs[dep] = load_artifact(self.out_dir / dep, self.registry[dep].output)
        console.print(f"[bold cyan]▶ {p.name}[/] {spec.description}")
        self._log(p.name, "start")
        t0 = time.perf_counter()
        scratch = self.out_dir / ".scratch" / p.name
        try:
            with atomic_folder(self.out_dir / p.name) as tmp:
                ctx = StageContext(
                    scene=self.scene,
                    params=p.params,
                    inputs=inputs,
                    out_dir=tmp,
                    track=track,
                    scratch_dir=scratch,
                    resume=resume,
                )
                data = spec.run(ctx)
                if not isinstance(data, spec.output):
                    raise TypeError(f"stage {p.name} returned {type(data).__name__}, not {spec.output.__name__}")
                duration = time.perf_counter() - t0
                meta = ArtifactMeta(
                    stage=p.name,
                    key=p.key or "",
                    scene_hash=self.scene_fingerprint(spec.scene_inputs),
                    params=p.params.model_dump(mode="json"),
                    code_version=p.code_version,  # as planned: the key was computed from it
                    upstream=p.upstream,
                    created=datetime.now(timezone.utc),
                    duration_s=duration,
                    warnings=ctx.warnings,
                )
                art = Artifact[spec.output](meta=meta, data=data)
                (tmp / ARTIFACT).write_text(art.model_dump_json(indent=2))
        except BaseException as e:
            outcome = "interrupted" if isinstance(e, KeyboardInterrupt) else "failed"
            self._log(p.name, outcome, duration_s=time.perf_counter() - t0, error=str(e))
            raise
        self._log(p.name, "ok", duration_s=duration)
        console.print(f"[green]✓ {p.name}[/] {duration:.2f} s")
        return StageResult(p.name, "ran", duration)

    def _log(self, stage: str, event: str, **fields) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        record = {"time": datetime.now(timezone.utc).isoformat(), "stage": stage, "event": event, **fields}
        with open(self.out_dir / RUN_LOG, "a") as f:
            f.write(json.dumps(record) + "\n")
