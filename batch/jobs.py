"""One stage of one scene: the unit of work every executor runs.

`run_stage_job` takes and returns plain, picklable data, opens everything it needs itself
(scene, registry, engine) and never raises: a failure comes back as an outcome with its one
line. It runs where the executor puts it, this process or a Ray worker on another machine,
with the run folder on storage both see.
"""

from __future__ import annotations

import os
import signal
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

#: Fault injection for checking a cluster's retries (docs/scale.md): "STAGE:MARKER" makes the
#: first job of STAGE that finds no MARKER file create it and kill its own process (SIGKILL),
#: as an out-of-memory kill or a lost node would. Unset in normal use.
KILL_ONCE_ENV = "PANO_PIPE_INJECT_KILL_ONCE"
#: A failed scene's error as the batch summary shows it: one line, at most this long.
ERROR_CHARS = 300


@dataclass(frozen=True)
class StageJob:
    scene_dir: Path
    out_dir: Path
    stage: str
    config: dict = field(default_factory=dict)
    config_source: str = "--set"
    force: bool = False
    resume: bool = False
    #: CPUs the executor gave the job (torch's thread count); None: leave it as it is
    threads: int | None = None


@dataclass
class JobOutcome:
    stage: str
    #: ran / cached / skipped (as the engine says), or failed (error holds the one line)
    outcome: str
    duration_s: float = 0.0
    reason: str = ""
    error: str = ""
    #: exit code class of the failure: 2 bad input, 1 an internal error
    exit_code: int = 0
    host: str = ""
    pid: int = 0


def run_stage_job(job: StageJob) -> JobOutcome:
    """Bring `job.stage` of its scene up to date; every failure is returned, never raised
    (except an interrupt, which the executor handles)."""
    from pipeline.engine import Engine
    from runfs.errors import PanoError, one_line
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    where = {"host": socket.gethostname(), "pid": os.getpid()}
    _maybe_inject_kill(job.stage)
    t0 = time.perf_counter()
    if job.threads:
        # a pooled worker keeps the thread count of whatever it ran first; set it per job
        import torch

        torch.set_num_threads(job.threads)
    try:
        scene = load_scene(job.scene_dir)
        engine = Engine(scene, job.out_dir, build_registry(), job.config, config_source=job.config_source)
        res = engine.run_one(job.stage, force=job.force, resume=job.resume)
        return JobOutcome(job.stage, res.outcome, res.duration_s, res.reason, **where)
    except PanoError as e:
        return JobOutcome(job.stage, "failed", time.perf_counter() - t0, error=one_line(e, ERROR_CHARS),
                          exit_code=e.exit_code, **where)
    except OSError as e:
        where_ = e.filename or job.out_dir
        return JobOutcome(job.stage, "failed", time.perf_counter() - t0,
                          error=one_line(f"{where_}: {e.strerror or e}", ERROR_CHARS), exit_code=2, **where)
    except Exception as e:  # noqa: BLE001 (a bug of ours, in one scene: the batch goes on)
        return JobOutcome(job.stage, "failed", time.perf_counter() - t0, exit_code=1, **where,
                          error=one_line(f"{type(e).__name__}: {e} (an internal error)", ERROR_CHARS))


def _maybe_inject_kill(stage: str) -> None:
    spec = os.environ.get(KILL_ONCE_ENV, "")
    target, sep, marker = spec.partition(":")
    if not sep or target != stage:
        return
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return
    os.close(fd)
    os.kill(os.getpid(), signal.SIGKILL)
