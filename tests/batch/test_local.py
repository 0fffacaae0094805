"""Batches with the local executor, through the CLI: per-scene run folders, DAG order,
failures that stay in their scene, reruns that run nothing, Ctrl-C."""

from __future__ import annotations

import json
from pathlib import Path


import batch.scheduler as scheduler
from batch.executors import LocalExecutor
from batch.scheduler import run_batch
from tests.clitools import invoke, without_kernel_notices
from pipeline.registry import build_registry
from tests.batch.conftest import FAST, FAST_SET

STAGES = list(build_registry())


def run_cli(args, capsys) -> tuple[int, str, str]:
    return invoke(args, capsys)


def events(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "run_log.jsonl").read_text().splitlines()]


def test_batch_runs_every_scene_into_its_own_run_folder(scenes, tmp_path, capsys):
    code, out, err = run_cli(["run", "all", scenes, "--out", tmp_path / "runs", *FAST_SET], capsys)
    assert code == 0, out + err
    for i in range(4):
        run = tmp_path / "runs" / f"room{i}"
        assert (run / "evaluate" / "artifact.json").is_file()
        assert (run / ".pano-pipe-run").is_file()
    # not on a terminal: one plain line per finished job, then the summary table
    assert "room2/train: ran" in out and "batch summary" in out and "4 of 4 scenes succeeded" in out
    assert without_kernel_notices(err) == ""


def test_jobs_follow_the_dag_and_one_scene_after_another(scenes, tmp_path):
    calls = []

    def recording(job):
        calls.append((job.scene_dir.name, job.stage))
        return scheduler_job(job)

    scheduler_job = scheduler.run_stage_job
    scheduler.run_stage_job = recording
    try:
        results = run_batch([scenes / "room0", scenes / "room1"], tmp_path / "runs", FAST, "--set",
                            LocalExecutor())
    finally:
        scheduler.run_stage_job = scheduler_job
    assert not any(r.failed for r in results)
    registry = build_registry()
    for scene in ("room0", "room1"):
        done = [stage for s, stage in calls if s == scene]
        assert sorted(done) == sorted(STAGES)
        for stage in done:
            assert all(done.index(dep) < done.index(stage) for dep in registry[stage].inputs)
    # local: the first scene finishes before the second starts
    assert [s for s, _ in calls] == ["room0"] * len(STAGES) + ["room1"] * len(STAGES)


def test_a_bad_scene_fails_alone_with_exit_code_1(scenes, tmp_path, capsys):
    img = scenes / "room1" / "images" / "train_00.png"
    img.write_bytes(b"not a png")
    code, out, err = run_cli(["run", "all", scenes, "--out", tmp_path / "runs", *FAST_SET], capsys)
    assert code == 1
    assert "3 of 4 scenes succeeded" in out
    # the error in full, one line, after the table
    line = next(ln for ln in out.splitlines() if ln.startswith("room1: "))
    assert str(scenes / "room1" / "images" / "train_00.png") in line
    for i in (0, 2, 3):
        assert (tmp_path / "runs" / f"room{i}" / "evaluate" / "artifact.json").is_file()
    assert not (tmp_path / "runs" / "room1" / "train").exists()
    assert "Traceback" not in out + err


def test_a_failing_stage_blocks_only_its_own_scene(scenes, tmp_path):
    # union needs a layout; room2's supplied layout is made unreadable after loading is fine
    layout = next((scenes / "room2" / "layout").glob("*.json"))
    layout.write_text("{ not json")
    results = run_batch(sorted(scenes.iterdir()), tmp_path / "runs", FAST, "--set", LocalExecutor())
    bad = next(r for r in results if r.name == "room2")
    assert bad.failed and bad.error.startswith("layout: ") and str(layout.name) in bad.error
    assert bad.stages["layout"].exit_code == 2
    # the stages that need layout never ran; depth (independent of it) did
    assert "union" not in bad.stages and bad.stages["depth"].outcome == "ran"
    assert all(not r.failed for r in results if r.name != "room2")


def test_a_rerun_of_a_finished_batch_runs_no_stage(scenes, tmp_path):
    run_batch(sorted(scenes.iterdir()), tmp_path / "runs", FAST, "--set", LocalExecutor())
    again = run_batch(sorted(scenes.iterdir()), tmp_path / "runs", FAST, "--set", LocalExecutor())
    # the scenes have poses: the poses stage is skipped, every other stage cached
    assert {(s == "poses", o.outcome) for r in again for s, o in r.stages.items()} == {
        (True, "skipped"), (False, "cached")}


def test_ctrl_c_stops_the_batch_and_a_rerun_continues(scenes, tmp_path, capsys, monkeypatch):
    real = scheduler.run_stage_job
    count = {"n": 0}

    def interrupted_at_the_twelfth_job(job):  # 8 stages of room0, then poses, layout, depth of room1
        count["n"] += 1
        if count["n"] == 12:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(scheduler, "run_stage_job", interrupted_at_the_twelfth_job)
    code, out, err = run_cli(["run", "all", scenes, "--out", tmp_path / "runs", *FAST_SET], capsys)
    assert code == 130 and "interrupted" in err, (out, err)
    monkeypatch.setattr(scheduler, "run_stage_job", real)
    results = run_batch(sorted(scenes.iterdir()), tmp_path / "runs", FAST, "--set", LocalExecutor())
    outcomes = [(r.name, s, o.outcome) for r in results for s, o in r.stages.items()]
    # room0 was done before the interrupt, room1's first two stages too
    assert {o for n, s, o in outcomes if n == "room0" and s != "poses"} == {"cached"}
    assert [o for n, s, o in outcomes if n == "room1" and s in ("layout", "depth")] == ["cached", "cached"]
    assert not any(r.failed for r in results)
    assert all((tmp_path / "runs" / r.name / "evaluate" / "artifact.json").is_file() for r in results)


def test_a_batch_refuses_a_run_folder_in_use(scenes, tmp_path):
    from runfs.fsutil import run_folder_lock
    from runfs.paths import mark_run_folder

    mark_run_folder(tmp_path / "runs" / "room0", scenes / "room0")
    with run_folder_lock(tmp_path / "runs" / "room0"):
        results = run_batch([scenes / "room0", scenes / "room1"], tmp_path / "runs", FAST, "--set",
                            LocalExecutor())
    assert results[0].failed and "in use by another pano-pipe run" in results[0].error
    assert not results[1].failed


def test_unknown_stage_and_bad_parameters_fail_the_whole_command(scenes, tmp_path, capsys):
    code, out, err = run_cli(["run", "bogus", scenes, "--out", tmp_path / "runs"], capsys)
    assert code == 2 and "unknown stage 'bogus'" in err and len(err.strip().splitlines()) == 1
    code, out, err = run_cli(["run", "all", scenes, "--out", tmp_path / "runs", "--set", "train.iterations=-3"],
                             capsys)
    assert code == 1 and "train" in out  # every scene reports the bad parameter
    assert not (tmp_path / "runs" / "room0" / "layout").exists()


def test_single_scene_command_line_is_unchanged(scenes, tmp_path, capsys):
    code, out, err = run_cli(["run", "all", scenes / "room0", "--out", tmp_path / "one", "--until", "union"],
                             capsys)
    assert code == 0, err
    assert (tmp_path / "one" / "union" / "artifact.json").is_file()  # --out is the run folder itself


def test_unknown_executor_is_one_line(scenes, tmp_path, capsys):
    code, out, err = run_cli(["run", "all", scenes, "--out", tmp_path / "runs", "--executor", "dask"], capsys)
    assert code == 2 and err.strip() == "error: --executor: must be local or ray, got 'dask'"
    assert not (tmp_path / "runs").exists()
