"""The DAG engine: plan (keys, skip rules, staleness), then run in topological order.

A stage's cache key chains the hash of the scene files it reads, its
parameters, its code version and its upstream stages' keys, so a change
anywhere reruns exactly the stages downstream of it.
"""

from __future__ import annotations

import errno
import graphlib
import json
import os
import socket
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ValidationError

from rich.markup import escape

from runtime.console import console, track
from runfs.errors import PanoError, describe_validation_error, did_you_mean, read_json
from runfs.fsutil import append_line, atomic_folder, remove_stale_temporaries, run_folder_lock, sha256_file, sha256_json
from runfs.paths import check_run_folder, mark_run_folder, run_path
from runtime.stage import Loaded, StageContext, StageSpec
from schemas.artifact import Artifact, ArtifactMeta
from schemas.scene import Scene

#: OSErrors that are the machine's, not ours: reported as one line naming the place.
_ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}

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
    #: The parameters as they enter the key (file parameters by content hash).
    params_json: dict = field(default_factory=dict)
    #: The hash of the scene inputs the key was computed from.
    scene_hash: str = ""


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
    declared = {name: i for i, name in enumerate(registry)}
    sorter = graphlib.TopologicalSorter(graph)
    try:
        sorter.prepare()
    except graphlib.CycleError as e:
        raise ValueError(f"stage graph has a cycle: {' -> '.join(e.args[1])}") from None
    # one stage at a time, the first declared of those ready: the registry's own order wherever the
    # dependencies allow it (stable and readable: poses, layout, depth, ...)
    order: list[str] = []
    ready: set[str] = set()
    while sorter.is_active():
        ready.update(sorter.get_ready())
        first = min(ready, key=declared.__getitem__)
        ready.discard(first)
        order.append(first)
        sorter.done(first)
    return order


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


def _validated(path: Path, output: type[BaseModel]) -> Artifact:
    """The artifact at `path`, validated against `output`; PanoError naming the file otherwise."""
    if not path.exists():
        raise PanoError(path, "missing; run the stage first")
    try:
        return Artifact[output].model_validate(read_json(path))
    except ValidationError as e:
        raise describe_validation_error(path, e) from None


def load_artifact(stage_dir: Path, output: type[BaseModel]) -> Loaded:
    art = _validated(stage_dir / ARTIFACT, output)
    return Loaded(data=art.data, dir=stage_dir, meta=art.meta)


def read_artifact(run_dir: Path, stage: str) -> Artifact | None:
    """The artifact `stage` wrote in `run_dir` (meta and typed data), validated against the stage's
    Output; None when it wrote none. One that does not validate is bad input (PanoError)."""
    from pipeline.registry import build_registry

    path = Path(run_dir) / stage / ARTIFACT
    if not path.exists() and not path.is_symlink():
        return None
    return _validated(path, build_registry()[stage].output)


def read_output(run_dir: Path, stage: str) -> BaseModel | None:
    """The typed data (the stage's pydantic Output) of `stage`'s artifact in `run_dir`, validated;
    None when the stage wrote none. The one way artifacts are read outside the engine."""
    art = read_artifact(run_dir, stage)
    return None if art is None else art.data


def artifact_problem(stage_dir: Path, output: type[BaseModel]) -> str | None:
    """Why an artifact whose key matches cannot be trusted, or None: its data must validate and
    every file it was written with must still be there with the size it had."""
    try:
        art = Artifact[output].model_validate_json((stage_dir / ARTIFACT).read_bytes())
    except (OSError, ValidationError) as e:
        return f"{ARTIFACT} does not validate ({str(e).splitlines()[0]})"
    for rel, size in art.meta.files.items():
        f = stage_dir / rel
        if not f.is_file():
            return f"{stage_dir.name}/{rel} is missing"
        if f.stat().st_size != size:
            return f"{stage_dir.name}/{rel} changed size ({f.stat().st_size} bytes, written with {size})"
    return None


def file_sizes(folder: Path) -> dict[str, int]:
    """Every file below `folder` (relative POSIX path -> size in bytes)."""
    return {
        p.relative_to(folder).as_posix(): p.stat().st_size
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ARTIFACT
    }


def stale_reason(meta: ArtifactMeta, plan: StagePlan, params_json: dict, scene_hash: str) -> str:
    """What changed since an artifact was made (its key no longer matches)."""
    changed = sorted(k for k in params_json.keys() | meta.params.keys() if params_json.get(k) != meta.params.get(k))
    if changed:
        return "parameters changed: " + ", ".join(changed[:4]) + (" ..." if len(changed) > 4 else "")
    if meta.code_version != plan.code_version:
        return "code changed"
    ups = sorted(k for k in plan.upstream.keys() | meta.upstream.keys()
                 if plan.upstream.get(k) != meta.upstream.get(k))
    if ups:
        return "upstream changed: " + ", ".join(ups)
    if meta.scene_hash != scene_hash:
        return "scene inputs changed"
    return "model files changed"


def forced(name: str, target: str | None, force: bool, force_upstream: bool) -> bool:
    """Whether a run reruns `name` even if it is up to date (Engine.run's rule): `force` reruns the
    named stage (every stage without one), `force_upstream` every stage the run touches; a named
    stage that is up to date is otherwise reported cached, as `--force`'s help says."""
    return force_upstream or (force and (target is None or name == target))


def select_stages(registry: dict[str, StageSpec], target: str | None = None, until: str | None = None) -> list[str]:
    """Stages a run touches: all, or the target/until stage and its ancestors, in DAG order."""
    order = topological_order(registry)
    stop = target or until
    if stop is None:
        return order
    if stop not in registry:
        raise PanoError(None, f"unknown stage {stop!r}{did_you_mean(stop, order)}; "
                              f"stages are {', '.join(order)}")
    wanted = ancestors(registry, stop) | {stop}
    return [n for n in order if n in wanted]


#: The manifest field of a view that names its file of each scene input kind.
_KIND_FIELDS = {"images": "image", "layout": "layout", "depth": "depth", "gt": "gt_depth", "masks": "mask"}


def complete_scene(scene: Scene, run_dir: Path, registry: dict[str, StageSpec], stage: str | None = None) -> Scene:
    """`scene` completed by the artifacts in `run_dir` of the scene-completing stages upstream of
    `stage` (all of them when None), in DAG order; a stage without an artifact (not run yet)
    leaves the scene as it is. Completing only fills in what the scene leaves out, so the artifact
    of a stage the scene no longer calls for changes nothing."""
    upstream = ancestors(registry, stage) if stage is not None else set(registry)
    for name in topological_order(registry):
        spec = registry[name]
        if spec.completes_scene is None or name not in upstream or not (run_dir / name / ARTIFACT).is_file():
            continue
        scene = spec.completes_scene(scene, load_artifact(run_dir / name, spec.output))
    return scene


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
        self.out_dir = check_run_folder(Path(out_dir), scene.root)
        self.registry = registry
        self.order = topological_order(registry)
        self.config = config or {}
        self.config_source = config_source
        unknown = set(self.config) - set(registry)
        if unknown:
            hints = "".join(did_you_mean(u, self.order) for u in sorted(unknown))
            raise PanoError(config_source,
                            f"unknown stage(s) {sorted(unknown)}{hints}; stages are {self.order}")
        self._fingerprints: dict[str, str] = {}
        self._file_hashes: dict[Path, str] = {}

    # -- planning ---------------------------------------------------------
    def params_for(self, name: str) -> BaseModel:
        """The stage's validated parameters; a file parameter (a model) resolved to the file it names."""
        spec = self.registry[name]
        try:
            params = spec.params.model_validate(self.config.get(name, {}))
        except ValidationError as e:
            raise describe_validation_error(f"{self.config_source} [{name}]", e, list(spec.params.model_fields),
                                            listed_by=f"pano-pipe params {name}") from None
        files = {k: self._param_file(name, k, v) for k, v in params if isinstance(v, Path)}
        params = params.model_copy(update=files) if files else params
        return spec.resolve_params(self.scene, params) if spec.resolve_params else params

    def hints(self) -> list[str]:
        """The stages' one-line hints (what the scene lacks and the command that gets it)."""
        out = []
        for name in self.order:
            spec = self.registry[name]
            if spec.hint and (line := spec.hint(self.scene, self.params_for(name))):
                out.append(line)
        return out

    def _param_file(self, stage: str, field_name: str, value: Path) -> Path:
        """A file named by a parameter: as given (from the working folder), else relative to the
        scene folder; the same rule for the cache key and for the stage."""
        given = Path(value).expanduser()
        for candidate in [given] if given.is_absolute() else [given, self.scene.root / given]:
            if candidate.is_file():
                return candidate.resolve()
        raise PanoError(value, f"file does not exist ({stage}.{field_name}; looked in the working folder "
                               "and the scene folder)")

    def scene_fingerprint(self, kinds: tuple[str, ...], views: list | None = None) -> str:
        """Hash of the manifest entries of `views` (default all) and of their files of `kinds`."""
        views = self.scene.views if views is None else views
        # only the manifest fields of the kinds read: naming a depth file must not rerun layout
        unread = {field for kind, field in _KIND_FIELDS.items() if kind not in kinds}
        manifest = self.scene.manifest.model_dump(
            mode="json", exclude={"views", "name"} | ({"floor_plan"} if "gt" not in kinds else set())
            | ({"nadir_mask_deg"} if "masks" not in kinds else set()))
        manifest["views"] = [v.model_dump(mode="json", exclude=unread) for v in views]
        parts = [sha256_json(manifest)]
        for kind in sorted(kinds):
            hashes = {}
            for p in self._scene_files(kind, views):
                if p not in self._file_hashes:
                    self._file_hashes[p] = sha256_file(p)
                hashes[p.relative_to(self.scene.root).as_posix()] = self._file_hashes[p]
            parts.append(f"{kind}:{sha256_json(hashes)}")
        return sha256_json(parts)

    def _scene_files(self, kind: str, views: list) -> list[Path]:
        s = self.scene
        if kind == "images":
            files = [s.image_path(v) for v in views]
        elif kind == "layout":
            files = [s.layout_path(v) for v in views]
        elif kind == "depth":
            files = [s.depth_path(v) for v in views]
        elif kind == "masks":
            files = [s.mask_path(v) for v in views]
        elif kind == "gt":
            files = [s.gt_depth_path(v) for v in views]
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

    def _stage_scene_hash(self, spec: StageSpec, params: BaseModel) -> str:
        views = spec.reads_views(self.scene, params) if spec.reads_views else None
        return self.scene_fingerprint(spec.scene_inputs, views)

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
            file_hashes = self.param_file_hashes(params)
            # a model enters the key by content, not by where it lies
            params_json = {**params.model_dump(mode="json"), **{k: f"sha256:{h}" for k, h in file_hashes.items()}}
            scene_hash = self._stage_scene_hash(spec, params)
            key = sha256_json(
                {"stage": name, "scene": scene_hash, "params": params_json, "code": code, "upstream": upstream}
            )
            plan = StagePlan(name, "missing", params, key, last_duration_s=last, upstream=upstream,
                             code_version=code, params_json=params_json, scene_hash=scene_hash)
            if meta is None:
                plan.reason = "never run" if not (self.out_dir / name).exists() else "no readable artifact.json"
            elif meta.key != key:
                plan.state, plan.reason = "stale", stale_reason(meta, plan, params_json, scene_hash)
            elif problem := artifact_problem(self.out_dir / name, spec.output):
                plan.state, plan.reason = "stale", problem
            else:
                plan.state, plan.reason = "up-to-date", "scene files, parameters, code and upstream unchanged"
            if plan.state != "up-to-date" and spec.run_reason:
                plan.reason = f"{plan.reason}; {spec.run_reason(self.scene, params)}"
            plans[name] = plan
        return plans

    # -- running ----------------------------------------------------------
    def select(self, target: str | None = None, until: str | None = None) -> list[str]:
        """Stages a run touches: all, or the target/until stage and its ancestors, in order."""
        return select_stages(self.registry, target, until)

    def run(
        self,
        target: str | None = None,
        until: str | None = None,
        force: bool = False,
        resume: bool = False,
        force_upstream: bool = False,
    ) -> list[StageResult]:
        """Run the selected stages, each only if it is not up to date, except: `target` is always
        rerun; `force` reruns `target` (every selected stage when there is none);
        `force_upstream` reruns every selected stage."""
        with run_folder_lock(self.out_dir):
            self.prepare_run_folder()
            return self._run_locked(target, until, force, resume, force_upstream)

    def _run_locked(self, target: str | None, until: str | None, force: bool, resume: bool,
                    force_upstream: bool) -> list[StageResult]:
        plans = self.plan()
        return [self._step(name, plans, forced(name, target, force, force_upstream), resume)
                for name in self.select(target, until)]

    def run_one(self, name: str, force: bool = False, resume: bool = False) -> StageResult:
        """Bring one stage up to date, its upstream stages being done already: the unit of work a
        batch executor schedules (pipeline.batch). The caller holds the run folder's lock and has
        prepared the folder (`prepare_run_folder`)."""
        if name not in self.registry:
            raise PanoError(None, f"unknown stage {name!r}{did_you_mean(name, self.order)}; "
                                  f"stages are {', '.join(self.order)}")
        # a retried task (its worker killed mid-stage) finds its predecessor's temporary folder
        remove_stale_temporaries(self.out_dir, stage=name)
        return self._step(name, self.plan(), force, resume)

    def prepare_run_folder(self) -> None:
        """Mark the run folder as pano-pipe's and remove what killed runs left (under its lock)."""
        mark_run_folder(self.out_dir, self.scene.root)
        remove_stale_temporaries(self.out_dir)

    def _step(self, name: str, plans: dict[str, StagePlan], force: bool, resume: bool) -> StageResult:
        p = plans[name]
        if p.state == "skipped":
            self._log(name, "skipped", reason=p.reason)
            return StageResult(name, "skipped", reason=p.reason)
        if p.state == "up-to-date" and not force:
            self._log(name, "cached")
            return StageResult(name, "cached", p.last_duration_s or 0.0)
        return self._run_stage(p, plans, resume=resume)

    def completed_scene(self, stage: str | None = None) -> Scene:
        """The scene as the stages upstream of `stage` (every stage when None) completed it, from
        their artifacts in the run folder (see StageSpec.completes_scene)."""
        return complete_scene(self.scene, self.out_dir, self.registry, stage)

    def _run_stage(self, p: StagePlan, plans: dict[str, StagePlan], resume: bool) -> StageResult:
        spec = self.registry[p.name]
        # the plan keyed the stage on the scene as given plus its upstream keys; it runs on the
        # scene its upstream stages completed
        scene = self.completed_scene(p.name)
        inputs: dict[str, Loaded | None] = {}
        for dep in spec.inputs:
            if plans[dep].state == "skipped":
                inputs[dep] = None
            else:
                inputs[dep] = load_artifact(self.out_dir / dep, self.registry[dep].output)
        # the start is logged before the banner and the banner printed inside the try: an interrupt
        # that comes as soon as the banner shows is logged as this stage's (it raced the log before)
        self._log(p.name, "start", host=socket.gethostname(), pid=os.getpid())  # which worker, in a batch
        t0 = time.perf_counter()
        scratch = run_path(self.out_dir, f".scratch/{p.name}")
        try:
            console.print(f"[bold cyan]▶ {p.name}[/] {escape(spec.description)}")
            with atomic_folder(run_path(self.out_dir, p.name)) as tmp:
                ctx = StageContext(
                    scene=scene,
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
                    scene_hash=p.scene_hash,  # as planned, like the code version
                    params=p.params_json,
                    files=file_sizes(tmp),
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
            self._log(p.name, outcome, duration_s=time.perf_counter() - t0, error=str(e) or type(e).__name__)
            if isinstance(e, OSError) and e.errno in _ENVIRONMENT_ERRNOS:
                # a full disk or a read-only folder: name where, even when the library did not
                raise PanoError(e.filename or self.out_dir / p.name, f"{e.strerror} (stage {p.name})") from e
            raise
        self._log(p.name, "ok", duration_s=duration)
        console.print(f"[green]✓ {p.name}[/] {duration:.2f} s")
        return StageResult(p.name, "ran", duration)

    def _log(self, stage: str, event: str, **fields) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        record = {"time": datetime.now(timezone.utc).isoformat(), "stage": stage, "event": event, **fields}
        append_line(self.out_dir / RUN_LOG, json.dumps(record))
