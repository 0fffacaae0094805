"""Training checkpoints as untrusted input, and interruptions: a crafted checkpoint runs no
code, a damaged one is warned about and training starts over, a failed save leaves no
temporary file and names the checkpoint, SIGTERM stops training like Ctrl-C."""

from __future__ import annotations

import errno
import json
import os
import pathlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from train_helpers import load_views, rooms, small_config

import stages.train as T
from gaussians.init import random_points
from gaussians.trainer import Trainer
from runfs.errors import PanoError
from schemas.scene_loader import load_scene
from runtime.stage import StageContext

BIN = Path(sys.executable).parent


def _ctx(root: Path, tmp_path: Path, resume: bool = False, name: str = "out", **params) -> StageContext:
    out = tmp_path / name
    out.mkdir(parents=True, exist_ok=True)
    base = dict(height=16, iterations=8, random_points=300, max_gaussians=2000, densify_from=4,
                densify_every=4, log_every=2, threads=1, checkpoint_every=0)
    base.update(params)
    return StageContext(scene=load_scene(root), params=T.Params(**base),
                        inputs={"align": None, "sampling": None, "union": None},
                        out_dir=out, scratch_dir=tmp_path / "scratch", resume=resume)


def _ckpt(tmp_path: Path) -> Path:
    p = tmp_path / "scratch" / T.CHECKPOINT_NAME
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def _trainer(root: Path, **cfg) -> Trainer:
    return Trainer(random_points(150, 0, rooms=rooms(root)), load_views(root), small_config(**cfg))


@pytest.fixture(scope="module")
def good_state(tiny_room) -> dict:
    """A real checkpoint's state after a few iterations (moments, stats and records all filled)."""
    tr = _trainer(tiny_room, iterations=20)
    tr.train(until=6)
    return tr.state_dict()


class _Touch:
    """Unpickling this creates `marker`: what a crafted checkpoint would do with os.system."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def _assert_started_over(ctx: StageContext, out, iterations: int = 8) -> None:
    assert out.resumed_from is None and out.iterations == iterations
    warned = [w for w in ctx.warnings if "--resume: checkpoint" in w]
    assert warned and "not usable" in warned[0] and "training from the start" in warned[0]
    assert "\n" not in warned[0] and len(warned[0]) < 400  # one line, even for torch's long messages
    log = [json.loads(s) for s in (ctx.out_dir / out.log).read_text().splitlines()]
    assert log[0]["iteration"] == 1 and log[-1]["iteration"] == iterations


# ----------------------------------------------------------------------------- 1. no code from a checkpoint


def test_crafted_checkpoint_runs_no_code_and_training_starts_over(tiny_room, tmp_path):
    marker = tmp_path / "pwned"
    torch.save({"version": 2, "payload": _Touch(marker)}, _ckpt(tmp_path))
    ctx = _ctx(tiny_room, tmp_path, resume=True)
    out = T.run(ctx)
    assert not marker.exists()
    _assert_started_over(ctx, out)
    # the refusal says why, and not torch's advice to load with weights_only=False
    warned = next(w for w in ctx.warnings if "--resume" in w)
    assert "weights_only" not in warned and "tensors and plain data" in warned


def test_checkpoint_is_plain_data_and_restores_every_rng(tiny_room, tmp_path):
    tr = _trainer(tiny_room, iterations=20)
    tr.train(until=5)
    np.random.seed(123)
    np_state = np.random.get_state()
    torch_state = torch.get_rng_state()
    ckpt = tmp_path / "c.pt"
    tr.save_checkpoint(ckpt)
    s = torch.load(ckpt, map_location="cpu", weights_only=True)  # refuses anything but tensors and plain data
    assert s["iteration"] == 5

    np.random.seed(7)
    torch.manual_seed(7)
    other = _trainer(tiny_room, iterations=20)
    other.load_checkpoint(ckpt)
    assert other.iteration == 5
    after = np.random.get_state()
    assert after[0] == np_state[0] and np.array_equal(after[1], np_state[1]) and after[2:] == np_state[2:]
    assert torch.equal(torch.get_rng_state(), torch_state)
    assert torch.equal(other.gen.get_state(), tr.gen.get_state())


# ----------------------------------------------------------------------------- 2. damaged checkpoints


def _truncated(state: dict, path: Path) -> None:
    torch.save(state, path)
    b = path.read_bytes()
    path.write_bytes(b[: len(b) // 2])


def _with(state: dict, **changes) -> dict:
    return {**state, **changes}


def _as_float64(tensors: dict) -> dict:
    return {k: v.double() if v.is_floating_point() else v for k, v in tensors.items()}


@pytest.mark.parametrize("make", [
    pytest.param(lambda s, p: p.write_bytes(np.random.default_rng(0).bytes(4096)), id="random-bytes"),
    pytest.param(lambda s, p: p.write_bytes(b""), id="empty"),
    pytest.param(_truncated, id="truncated"),
    pytest.param(lambda s, p: torch.save([1, 2, 3], p), id="a-list"),
    pytest.param(lambda s, p: torch.save(_with(s, stack=5), p), id="stack-not-a-list"),
    pytest.param(lambda s, p: torch.save(_with(s, gaussians=_as_float64(s["gaussians"])), p),
                 id="float64-model"),
])
def test_damaged_checkpoint_warns_and_trains_from_the_start(tiny_room, tmp_path, monkeypatch, good_state,
                                                            make):
    # the fingerprint must match for the structural cases to get past it: take the stage's own
    fingerprint = _stage_fingerprint(_ctx(tiny_room, tmp_path, name="probe"), monkeypatch)
    make(_with(good_state, fingerprint=fingerprint), _ckpt(tmp_path))
    ctx = _ctx(tiny_room, tmp_path, resume=True)
    out = T.run(ctx)
    _assert_started_over(ctx, out)


def _stage_fingerprint(ctx: StageContext, monkeypatch) -> str:
    """The fingerprint the stage's trainer expects, read off the trainer a run makes."""
    made: list[Trainer] = []

    class Spy(Trainer):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    with monkeypatch.context() as m:
        m.setattr(T, "Trainer", Spy)
        T.run(ctx)
    return made[0].cfg.fingerprint() + made[0].extra_fingerprint


def _bad_np_rng(s: dict) -> dict:
    rng = dict(s["np_rng"])
    rng["pos"] = 10**6  # numpy would accept it and crash the interpreter on the next draw
    return _with(s, np_rng=rng)


def _bad_moments(s: dict) -> dict:
    opt = dict(s["opt"])
    opt["exp_avg"] = {k: v[:-1] for k, v in opt["exp_avg"].items()}
    opt["exp_avg_sq"] = {k: v[:-1] for k, v in opt["exp_avg_sq"].items()}
    return _with(s, opt=opt)


@pytest.mark.parametrize("corrupt, reason", [
    (lambda s: {k: v for k, v in s.items() if k != "stats"}, "lacks stats"),
    (lambda s: _with(s, version=torch.tensor([2, 2])), "version"),
    (lambda s: _with(s, fingerprint=torch.zeros(3)), "different training settings"),
    (lambda s: _with(s, iteration="6"), "iteration"),
    (lambda s: _with(s, iteration=10**9), "iteration"),
    (lambda s: _with(s, gaussians={**s["gaussians"], "means": s["gaussians"]["means"][:-1]}), "Gaussians"),
    (lambda s: _with(s, gaussians={**s["gaussians"], "means": s["gaussians"]["means"] * float("nan")}),
     "non-finite"),
    (_bad_moments, "moments"),
    (lambda s: _with(s, stats={**s["stats"], "count": s["stats"]["count"][:3]}), "stats"),
    (lambda s: _with(s, gen=torch.zeros(10, dtype=torch.uint8)), "gen"),
    (lambda s: _with(s, torch_rng="x"), "torch_rng"),
    (_bad_np_rng, "np_rng"),
    (lambda s: _with(s, active_sh=9), "active_sh"),
    (lambda s: _with(s, stack=[0, 99]), "stack"),
    (lambda s: _with(s, ema={"loss": "low"}), "ema"),
    (lambda s: _with(s, records=[{"loss": torch.zeros(2)}]), "records"),
    (lambda s: _with(s, nonfinite_steps=-1), "nonfinite_steps"),  # the last field: all others were fine
])
def test_invalid_state_is_refused_before_anything_changes(tiny_room, good_state, corrupt, reason):
    tr = _trainer(tiny_room, iterations=20)
    tr.train(until=2)
    bad = corrupt(_with(good_state, fingerprint=tr.cfg.fingerprint()))
    before = tr.state_dict()
    g, opt, stats = tr.g, tr.opt, tr.stats
    torch_rng = torch.get_rng_state()
    with pytest.raises(ValueError, match=reason):
        tr.load_state_dict(bad)
    # nothing half-applied: the same objects, the same values, the same global RNG
    assert tr.g is g and tr.opt is opt and tr.stats is stats
    assert tr.iteration == 2 and tr.records == before["records"] and tr.stack == before["stack"]
    assert torch.equal(tr.gen.get_state(), before["gen"]) and torch.equal(torch.get_rng_state(), torch_rng)
    tr.train(until=4)  # and it still trains


def test_valid_state_still_loads(tiny_room, good_state):
    tr = _trainer(tiny_room, iterations=20)
    tr.load_state_dict(_with(good_state, fingerprint=tr.cfg.fingerprint()))
    assert tr.iteration == 6 and len(tr.g) == len(good_state["gaussians"]["means"])
    tr.train(until=8)


# ----------------------------------------------------------------------------- 4./5. failed saves


def _full_disk(obj, f, *a, **k) -> None:
    """torch.save on a full disk: part of the file, then ENOSPC."""
    Path(f).write_bytes(b"PK\x03\x04 half a checkpoint")
    raise OSError(errno.ENOSPC, "No space left on device")


def test_full_disk_leaves_no_temporary_file_and_names_the_checkpoint(tiny_room, tmp_path, monkeypatch):
    tr = _trainer(tiny_room, iterations=20)
    tr.train(until=2)
    ckpt = tmp_path / "c.pt"
    tr.save_checkpoint(ckpt)
    good = ckpt.read_bytes()
    tr.train(until=3)

    monkeypatch.setattr(torch, "save", _full_disk)
    with pytest.raises(OSError) as e:
        tr.save_checkpoint(ckpt)
    assert e.value.errno == errno.ENOSPC and str(ckpt) in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pt"]  # no c.pt.tmp
    assert ckpt.read_bytes() == good  # the previous checkpoint is untouched
    monkeypatch.undo()

    # the rename failing (e.g. a read-only folder) also cleans up
    def no_replace(src, dst):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(os, "replace", no_replace)
    with pytest.raises(OSError, match="c.pt"):
        tr.save_checkpoint(ckpt)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pt"] and ckpt.read_bytes() == good


def test_periodic_checkpoint_failure_is_a_one_line_error_naming_the_file(tiny_room, tmp_path, monkeypatch):
    monkeypatch.setattr(torch, "save", _full_disk)
    ckpt = _ckpt(tmp_path)
    with pytest.raises(PanoError) as e:
        T.run(_ctx(tiny_room, tmp_path, checkpoint_every=3))
    assert str(ckpt) in str(e.value) and "No space left on device" in str(e.value)
    assert "\n" not in str(e.value) and e.value.exit_code == 2
    assert not ckpt.with_name(ckpt.name + ".tmp").exists() and not ckpt.exists()


# ----------------------------------------------------------------------------- 3. SIGTERM


def test_sigterm_is_deferred_like_ctrl_c_and_the_old_handlers_come_back():
    seen = []

    def guard(signum, frame):  # stands in for the default action, which would end pytest
        seen.append(signum)

    old_term = signal.signal(signal.SIGTERM, guard)
    old_int = signal.getsignal(signal.SIGINT)
    try:
        with T._DeferredInterrupt() as stop:
            signal.raise_signal(signal.SIGTERM)
            assert stop.requested and not seen
            with pytest.raises(KeyboardInterrupt):  # a second one interrupts at once
                signal.raise_signal(signal.SIGTERM)
        assert signal.getsignal(signal.SIGTERM) is guard and signal.getsignal(signal.SIGINT) is old_int
        signal.raise_signal(signal.SIGTERM)
        assert seen == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, old_term)


def _run_log(run: Path) -> list[dict]:
    p = run / "run_log.jsonl"
    if not p.is_file():
        return []
    out = []
    for line in p.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:  # a line being written
            pass
    return out


def _training_started(run: Path) -> bool:
    """The stage logged its start and the loop its first iteration (train_log.jsonl lives in the
    stage's temporary output folder, whatever the engine calls it)."""
    if not any(r.get("stage") == "train" and r.get("event") == "start" for r in _run_log(run)):
        return False
    return any(p.stat().st_size > 0 for p in run.rglob("train_log.jsonl"))


@pytest.mark.slow
def test_sigterm_writes_a_checkpoint_and_logs_an_interruption(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([str(BIN / "pano-pipe"), "simulate", "S", "--views", "3", "--test-views", "1",
                    "--height", "32", "--effects", "none"],
                   cwd=tmp_path, env=env, check=True, capture_output=True, timeout=300)
    run = tmp_path / "RUN"
    with open(tmp_path / "stdout.txt", "wb") as out:  # a file, not a pipe: a full pipe would block the child
        proc = subprocess.Popen(
            [str(BIN / "pano-pipe"), "run", "train", "S", "--out", "RUN", "--set", "train.iterations=100000",
             "--set", "train.height=16", "--set", "train.checkpoint_every=0", "--set", "train.threads=1"],
            cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 300
            while not _training_started(run):
                assert proc.poll() is None, f"pano-pipe ended early:\n{(tmp_path / 'stdout.txt').read_text()}"
                assert time.monotonic() < deadline, "training did not start"
                time.sleep(0.2)
            time.sleep(1.0)
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    text = (tmp_path / "stdout.txt").read_text(errors="replace")
    assert rc != 0, text
    assert rc != -signal.SIGTERM, f"killed by SIGTERM instead of stopping cleanly:\n{text}"
    ckpt = run / ".scratch" / "train" / T.CHECKPOINT_NAME
    assert ckpt.is_file(), text
    assert not ckpt.with_name(ckpt.name + ".tmp").exists()
    assert torch.load(ckpt, map_location="cpu", weights_only=True)["iteration"] >= 1
    assert any(r.get("stage") == "train" and r.get("event") == "interrupted" for r in _run_log(run)), text
