"""`--executor ray --address`: an address nothing (or something other than Ray) answers at is one
line and exit 2 within --connect-timeout, and Ray's own log stays off stderr (hardening issue,
second pass, class 6: it hung for minutes printing Ray's warnings)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from simulate.generate import generate_scene

pytest.importorskip("ray")
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ray-connect")
    generate_scene(root / "S", views=2, test_views=0, height=16, effects="none")
    return root / "S"


def _run(args: list, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", "from pipeline.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, env=env, timeout=240)


def _assert_one_line(res: subprocess.CompletedProcess, *expected: str) -> None:
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, res.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: --address:"), res.stderr[-2000:]
    for text in expected:
        assert text in lines[0]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_nothing_listening(scene, tmp_path):
    res = _run(["run", "all", scene, "--out", tmp_path / "R", "--executor", "ray",
                "--address", f"127.0.0.1:{_closed_port()}", "--connect-timeout", "5"], tmp_path)
    _assert_one_line(res, "cannot reach a Ray cluster")
    assert not (tmp_path / "R").exists()


def test_something_else_listening(scene, tmp_path):
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    accepted = []
    threading.Thread(target=lambda: [accepted.append(server.accept()) for _ in range(16)], daemon=True).start()
    try:
        res = _run(["run", "all", scene, "--out", tmp_path / "R", "--executor", "ray",
                    "--address", f"127.0.0.1:{server.getsockname()[1]}", "--connect-timeout", "4"], tmp_path)
    finally:
        server.close()
    _assert_one_line(res, "no Ray cluster answered", "within 4 s")
    assert not (tmp_path / "R").exists()


def test_an_address_that_is_not_one(scene, tmp_path):
    res = _run(["run", "all", scene, "--executor", "ray", "--address", "not an address"], tmp_path)
    _assert_one_line(res, "is not HOST:PORT")
