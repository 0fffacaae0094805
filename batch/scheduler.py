"""Run the DAG over many scenes with any executor.

Per scene: its stages in DAG order, a stage submitted once every input stage is done (ran,
cached or skipped); scenes side by side as far as the executor's resources allow. A failed
stage blocks what depends on it in its scene and nothing else. The batch holds every scene's
run-folder lock for its whole life, so two batches (or a batch and a `run`) never share a
run folder; the jobs themselves run under that lock wherever they are.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from batch.executors import Executor
from batch.jobs import JobOutcome, StageJob, run_stage_job
from batch.progress import Board
from batch.scenes import run_folders
from runfs.errors import PanoError

DONE = ("ran", "cached", "skipped")


@dataclass
class SceneResult:
    name: str
    scene_dir: Path
    out_dir: Path | None
    stages: dict[str, JobOutcome] = field(default_factory=dict)
    error: str = ""
    exit_code: int = 0
    started: float | None = None
    ended: float | None = None

    @property
    def failed(self) -> bool:
        return bool(self.error) or any(o.outcome == "failed" for o in self.stages.values())

    def count(self, outcome: str) -> int:
        return sum(o.outcome == outcome for o in self.stages.values())

    def row(self) -> dict:
        wall = (self.ended - self.started) if self.started is not None and self.ended is not None else 0.0
        return {"scene": self.name, "ran": self.count("ran"), "cached": self.count("cached"),
                "skipped": self.count("skipped"), "failed": self.count("failed") + (1 if self.error and
                                                                                      not self.stages else 0),
                "wall_s": wall, "psnr": test_psnr(self.out_dir), "error": self.error}


def test_psnr(out_dir: Path | None) -> float | None:
    """The evaluate stage's mean test PSNR, if the run folder has one."""
    from pipeline.engine import read_output

    evaluate = read_output(out_dir, "evaluate") if out_dir is not None else None
    return evaluate.mean.get("psnr") if evaluate is not None else None


def run_batch(scene_dirs: list[Path], out_root: Path, config: dict, config_source: str, executor: Executor,
              target: str | None = None, until: str | None = None, force: bool = False,
              resume: bool = False, force_upstream: bool = False,
              config_for: Callable[[Path], tuple[dict, str]] | None = None) -> list[SceneResult]:
    """Run the selected stages of every scene; returns one result per scene, in order. `target`,
    `force` and `force_upstream` as in Engine.run. `config_for(scene_root)`, when given, is each
    scene's own configuration (its pano-pipe.yaml under the command's --config/--set), as a
    single run reads it; otherwise every scene runs with `config`."""
    from pipeline.engine import Engine, select_stages
    from runfs.fsutil import run_folder_lock
    from runfs.paths import run_folder_name
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    registry = build_registry()
    selected = select_stages(registry, target, until)  # an unknown stage fails the whole command
    results: list[SceneResult] = []
    scenes = {}
    configs: dict[Path, tuple[dict, str]] = {}
    for scene_dir in scene_dirs:  # a scene that does not load fails alone, before anything runs
        try:
            scene = load_scene(scene_dir)
            run_folder_name(scene.name, scene.root)  # the batch's OUT/<name>/, as a single run's runs/<name>/
            configs[scene_dir] = config_for(scene.root) if config_for else (config, config_source)
        except PanoError as e:
            results.append(SceneResult(Path(scene_dir).name, scene_dir, None, error=str(e), exit_code=e.exit_code))
            continue
        scenes[scene_dir] = scene
        results.append(SceneResult(scene.name, scene_dir, None))
    folders = run_folders(list(scenes), {d: s.name for d, s in scenes.items()}, out_root)
    with contextlib.ExitStack() as locks:
        for r in results:
            if r.error:
                continue
            r.out_dir = folders[r.scene_dir]
            try:
                scene_cfg, scene_source = configs[r.scene_dir]
                engine = Engine(scenes[r.scene_dir], r.out_dir, registry, scene_cfg, config_source=scene_source)
                for name in selected:  # parameters checked before anything runs
                    engine.params_for(name)
                locks.enter_context(run_folder_lock(r.out_dir))
                engine.prepare_run_folder()
            except PanoError as e:
                r.error, r.exit_code = str(e), e.exit_code
        jobs = _SceneJobs(registry, selected, config, config_source, target, force, resume, force_upstream,
                          configs)
        with Board([r.name for r in results], selected, executor.name) as board:
            _schedule(results, jobs, executor, board)
    return results


@dataclass
class _SceneJobs:
    """How a scene's stages become jobs: the DAG restricted to the selected stages."""

    registry: dict
    selected: list[str]
    config: dict
    config_source: str
    target: str | None
    force: bool
    resume: bool
    force_upstream: bool = False
    #: each scene's own (configuration, its source); `config` for a scene not in it
    scene_configs: dict[Path, tuple[dict, str]] = field(default_factory=dict)

    def deps(self, name: str) -> list[str]:
        return [d for d in self.registry[name].inputs if d in self.selected]

    def resources(self, name: str) -> dict[str, float]:
        spec = self.registry[name]
        return spec.resources(spec.params.model_validate(self.config.get(name, {})))

    def job(self, r: SceneResult, name: str, threads: int | None) -> StageJob:
        from pipeline.engine import forced

        config, source = self.scene_configs.get(r.scene_dir, (self.config, self.config_source))
        return StageJob(r.scene_dir, r.out_dir, name, config, source,
                        force=forced(name, self.target, self.force, self.force_upstream), resume=self.resume,
                        threads=threads)


def _schedule(results: list[SceneResult], jobs: _SceneJobs, executor: Executor, board: Board) -> None:
    """Submit each job once its inputs are done, until every job has an outcome."""
    from runtime.console import console as stage_console

    state: dict[tuple[int, str], str] = {}
    for i, r in enumerate(results):
        for name in jobs.selected:
            state[(i, name)] = "blocked" if r.error else "waiting"
            if r.error:
                board.set(r.name, name, "blocked")
    resources = {name: jobs.resources(name) for name in jobs.selected}

    def started(key: tuple[int, str]) -> None:
        state[key] = "running"
        board.set(results[key[0]].name, key[1], "running")

    quiet, stage_console.quiet = stage_console.quiet, True  # the board draws; the stages stay silent
    try:
        while True:
            for (i, name), s in list(state.items()):
                if s != "waiting":
                    continue
                inputs = [state[(i, d)] for d in jobs.deps(name)]
                if any(x in ("failed", "blocked") for x in inputs):
                    state[(i, name)] = "blocked"
                    board.set(results[i].name, name, "blocked")
                elif all(x in DONE for x in inputs):
                    k = jobs.selected.index(name)
                    threads = max(1, int(resources[name]["CPU"])) if executor.shares_cores else None
                    executor.submit((i, name), run_stage_job, jobs.job(results[i], name, threads),
                                    resources[name], priority=(i, k))
                    state[(i, name)] = "queued"
                    board.set(results[i].name, name, "queued")
            if not any(s in ("queued", "running") for s in state.values()):
                break
            if not executor.reports_start:  # a remote job's start shows in its scene's run log
                _mark_running(results, state, board)
            for (i, name), outcome in executor.wait(timeout=0.5, on_start=started):
                _record(results[i], name, outcome, state, board, i)
            board.tick()
    except BaseException:
        executor.cancel()  # Ctrl-C: running jobs are stopped, their stages keep their old results
        raise
    finally:
        stage_console.quiet = quiet


def _record(r: SceneResult, name: str, outcome, state: dict, board: Board, i: int) -> None:
    if not isinstance(outcome, JobOutcome):  # the executor gave up (a worker kept dying)
        outcome = JobOutcome(name, "failed", error=_describe(outcome), exit_code=1)
    r.stages[name] = outcome
    now = time.time()
    if r.started is None:
        r.started = now - outcome.duration_s
    r.ended = now
    state[(i, name)] = outcome.outcome
    board.set(r.name, name, outcome.outcome,
              outcome.error or (f"{outcome.duration_s:.1f} s" if outcome.outcome == "ran" else outcome.reason))
    if outcome.outcome == "failed" and not r.error:
        r.error, r.exit_code = f"{name}: {outcome.error}", outcome.exit_code


def _mark_running(results: list[SceneResult], state: dict, board: Board) -> None:
    """Queued jobs whose stage has started on a worker (its run log says so): shown as running."""
    for (i, name), s in state.items():
        if s == "queued" and _started(results[i].out_dir, name):
            state[(i, name)] = "running"
            board.set(results[i].name, name, "running")


def _started(out_dir: Path | None, stage: str) -> bool:
    """Whether the last record of `stage` in the run log is its start."""
    from pipeline.engine import RUN_LOG

    if out_dir is None:
        return False
    try:
        with open(out_dir / RUN_LOG, "rb") as f:
            f.seek(0, 2)
            f.seek(max(0, f.tell() - 8192))
            tail = f.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return False
    for line in reversed(tail):
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and rec.get("stage") == stage:
            return rec.get("event") == "start"
    return False


def _describe(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return f"{type(e).__name__}: {text[:200]}"
