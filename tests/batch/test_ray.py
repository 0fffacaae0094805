"""The Ray executor on a local Ray instance with 2 CPUs: the same artifacts as the local
executor, retries of killed workers, cached reruns, failures that stay in their scene."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from batch.executors import LocalExecutor, RayExecutor
from batch.jobs import KILL_ONCE_ENV
from batch.scheduler import run_batch
from tests.batch.conftest import FAST

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def ray_instance():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def keys_and_metrics(run_root: Path) -> dict:
    out = {}
    for art in sorted(run_root.glob("*/*/artifact.json")):
        doc = json.loads(art.read_text())
        scene, stage = art.parent.parent.name, art.parent.name
        out[(scene, stage, "key")] = doc["meta"]["key"]
        if stage == "evaluate":
            out[(scene, stage, "psnr")] = round(doc["data"]["mean"]["psnr"], 6)
            out[(scene, stage, "ssim")] = round(doc["data"]["mean"]["ssim"], 6)
    return out


def test_ray_gives_the_local_executors_artifacts(ray_instance, scenes, tmp_path):
    all_scenes = sorted(scenes.iterdir())
    local = run_batch(all_scenes, tmp_path / "local", FAST, "--set", LocalExecutor())
    remote = run_batch(all_scenes, tmp_path / "ray", FAST, "--set", RayExecutor())
    assert not any(r.failed for r in local + remote), [r.error for r in local + remote]
    a, b = keys_and_metrics(tmp_path / "local"), keys_and_metrics(tmp_path / "ray")
    assert len(a) == 4 * (7 + 2) and a == b
    # the jobs ran in Ray workers, not in this process
    import os

    log = [json.loads(x) for x in (tmp_path / "ray" / "room0" / "run_log.jsonl").read_text().splitlines()]
    assert {rec["pid"] for rec in log if rec["event"] == "start"} - {os.getpid()}
    # a rerun of the finished batch runs no stage
    again = run_batch(all_scenes, tmp_path / "ray", FAST, "--set", RayExecutor())
    # the scenes have poses: the poses stage is skipped, every other stage cached
    assert {(s == "poses", o.outcome) for r in again for s, o in r.stages.items()} == {
        (True, "skipped"), (False, "cached")}


def test_a_killed_worker_is_retried_and_completes(ray_instance, scenes, tmp_path, monkeypatch):
    marker = tmp_path / "killed-once"
    monkeypatch.setenv(KILL_ONCE_ENV, f"train:{marker}")
    # one scene: its train job's worker is SIGKILLed (isolation is the test below's)
    results = run_batch([scenes / "room0"], tmp_path / "runs", FAST, "--set", RayExecutor(retries=2))
    assert marker.is_file()  # the train job's worker was SIGKILLed ...
    assert [r.stages["train"].outcome for r in results] == ["ran"]  # ... and its retry finished
    assert not any(r.failed for r in results)
    for r in results:
        assert (r.out_dir / "evaluate" / "artifact.json").is_file()
        assert not [p for p in r.out_dir.iterdir() if p.name.startswith((".tmp-", ".old-"))]


def test_failures_stay_in_their_scene_on_ray(ray_instance, scenes, tmp_path, monkeypatch):
    """One batch, three scenes: a good one, one whose union worker is SIGKILLed with no retries
    left, one with a truncated image (a one-line error, exit code 2). The scene that fails early
    never reaches union, so the kill lands on one of the other two (which one is Ray's order)."""
    marker = tmp_path / "killed-once"
    monkeypatch.setenv(KILL_ONCE_ENV, f"union:{marker}")
    (scenes / "room3" / "images" / "train_01.png").write_bytes(b"\x89PNG truncated")
    results = run_batch([scenes / "room0", scenes / "room1", scenes / "room3"], tmp_path / "runs", FAST, "--set",
                        RayExecutor(retries=0))
    bad = results[2]
    assert bad.failed and "train_01.png" in bad.error and bad.exit_code == 2
    killed = [r for r in results[:2] if r.failed]
    assert marker.is_file() and len(killed) == 1 and killed[0].error.startswith("union: ")
    assert "train" not in killed[0].stages  # blocked: needs union's layout cloud
    ok = next(r for r in results[:2] if not r.failed)
    assert (ok.out_dir / "evaluate" / "artifact.json").is_file()
