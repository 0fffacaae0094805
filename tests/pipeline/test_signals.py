"""SIGTERM to every long command, as a scheduler or `kill` sends it (docs/security.md, Signals).

Each command runs as a real process; the signal is sent once its long part has started and, for
the poses stage, once the native library that takes SIGTERM (pycolmap's glog) is loaded: only
structure from motion loads it (issue 35), mid-command. Promised: exit code 130, one line
on stderr, no temporary file or folder left, the run log recording `interrupted`.
Hardening issue 2 (second pass): pycolmap's glog replaced our handler, so these died with 143
and a 35-line stack dump, leaving `.tmp-*` folders.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from simulate.generate import generate_scene
from tests.clitools import run_main

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A tiny scene and a finished run of it: (root holding S/ and R/)."""
    root = tmp_path_factory.mktemp("sigterm")
    generate_scene(root / "S", views=3, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R",
                     "--set", "train.iterations=5", "--set", "train.height=8"]) == 0
    return root


def _maps(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return ""


def _catches_sigterm(pid: int) -> bool:
    """Whether the process has a handler for SIGTERM and does not hold it back: the CLI installs
    ours first thing in main(); before, a SIGTERM ends the process by the default action (while
    nothing is written yet)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    masks = {ln.split()[0]: int(ln.split()[1], 16) for ln in status.splitlines()
             if ln.startswith(("SigCgt:", "SigBlk:"))}
    bit = 1 << (signal.SIGTERM - 1)
    return bool(masks.get("SigCgt:", 0) & bit) and not masks.get("SigBlk:", 0) & bit


def terminate_when(args: list, ready, cwd: Path, timeout: float = 240.0, settle: float = 0.0,
                   loads_pycolmap: bool = False) -> tuple[int, str, str]:
    """Run `pano-pipe ARGS`; once `ready(stdout so far, pid)` holds, the process handles SIGTERM
    and, with `loads_pycolmap`, pycolmap is loaded (and `settle` seconds later), send SIGTERM.
    Returns (exit code, stdout, stderr)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-c", "from pipeline.cli import main; main()", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env)
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    deadline = time.monotonic() + timeout
    try:
        while not (ready("".join(out), proc.pid) and (not loads_pycolmap or "pycolmap" in _maps(proc.pid))
                   and _catches_sigterm(proc.pid)):
            assert proc.poll() is None, f"finished before the signal: {proc.returncode}\n{''.join(out)}" \
                                        f"\n{proc.stderr.read()}"
            assert time.monotonic() < deadline, "the long part never started"
            time.sleep(0.05)
        time.sleep(settle)
        assert proc.poll() is None, "finished before the signal"
        proc.send_signal(signal.SIGTERM)
        err = proc.stderr.read()
        proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(timeout=10)
    return proc.returncode, "".join(out), err


def assert_interrupted(code: int, out: str, err: str, folder: Path) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 130, (code, err[-3000:])
    assert len(lines) == 1 and lines[0].startswith("interrupted"), err[-3000:]
    assert "Traceback" not in out + err
    left = [p for p in folder.rglob("*") if p.name.startswith((".tmp-", ".old-")) or ".tmp" in p.suffixes]
    assert not left, left


def last_event(run: Path, stage: str) -> str:
    records = [json.loads(ln) for ln in (run / "run_log.jsonl").read_text().splitlines() if ln.strip()]
    return [r["event"] for r in records if r["stage"] == stage][-1]


@pytest.mark.parametrize("method", ["auto", "equirect"])
def test_sigterm_during_poses(tmp_path, method):
    """`run poses`: the upright solver (auto places every view with it), and structure from motion
    in pycolmap, which installs glog's handler when the stage imports it, mid-command."""
    from sfm.bench import unposed_copy

    sim = tmp_path / "sim"
    generate_scene(sim, views=4, test_views=0, height=256, effects="none")
    scene = tmp_path / "scene"
    unposed_copy(sim, scene)
    run = tmp_path / "run"
    code, out, err = terminate_when(["run", "poses", scene, "--out", run, "--set", f"poses.method={method}"],
                                    lambda o, _: "▶ poses" in o, tmp_path, loads_pycolmap=method == "equirect")
    assert_interrupted(code, out, err, run)
    assert last_event(run, "poses") == "interrupted"
    assert not (run / "poses").exists()


def test_sigterm_during_training(trained, tmp_path):
    run = tmp_path / "run"
    code, out, err = terminate_when(
        ["run", "train", trained / "S", "--out", run, "--set", "train.iterations=100000", "--set", "train.height=8"],
        lambda o, _: "▶ train" in o, tmp_path)
    assert_interrupted(code, out, err, run)
    assert last_event(run, "train") == "interrupted"


def test_sigterm_during_mesh_export(trained, tmp_path):
    import shutil

    run = tmp_path / "R"
    shutil.copytree(trained / "R", run)
    code, out, err = terminate_when(
        ["export", run, "--format", "mesh", "--mesh-height", "2048", "--mesh-depth", "5"],
        lambda o, pid: True, tmp_path, settle=0.5)
    assert_interrupted(code, out, err, run)
    assert not (run / "export").exists() or not any((run / "export").iterdir())


def test_sigterm_stops_the_viewer(trained, tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code, out, err = terminate_when(["view", trained / "R", "--port", port], lambda o, _: "viewer:" in o, tmp_path)
    assert_interrupted(code, out, err, trained / "R")
    assert "viewer stopped" in out


def test_sigterm_during_render(trained, tmp_path):
    import shutil

    run = tmp_path / "R"
    shutil.copytree(trained / "R", run)
    code, out, err = terminate_when(
        ["render", trained / "S", "--out", run, "--frames", "100000", "--height", "64"],
        lambda o, _: (run / "render").is_dir() and any((run / "render").iterdir()), tmp_path)
    assert_interrupted(code, out, err, run)
    assert not list((run / "render").glob("*.mp4"))
