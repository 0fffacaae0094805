"""The CLI imports what a command needs when it needs it (issue 35, item 5): listing the commands
loads no torch, OpenCV, pycolmap or open3d, and a scene whose poses are all given runs where
pycolmap is not installed."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "cv2", "pycolmap", "open3d")

#: Prints, as the process exits, which of HEAVY it imported; `pycolmap` made unimportable when asked.
PROBE = """
import atexit, json, sys
if {hide_pycolmap}:
    sys.modules["pycolmap"] = None  # as if not installed: importing it raises ImportError
atexit.register(lambda: print("IMPORTED " + json.dumps(
    sorted(m for m in {heavy!r} if sys.modules.get(m) is not None))))
{body}
"""


def _run(body: str, *args, hide_pycolmap: bool = False) -> tuple[int, str, list[str]]:
    code = PROBE.format(hide_pycolmap=hide_pycolmap, heavy=HEAVY, body=body)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}
    proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, env=env, timeout=300)
    marker = [ln for ln in proc.stdout.splitlines() if ln.startswith("IMPORTED ")]
    assert marker, proc.stdout + proc.stderr
    return proc.returncode, proc.stdout + proc.stderr, json.loads(marker[-1].removeprefix("IMPORTED "))


def test_importing_the_cli_loads_no_heavy_library():
    code, out, imported = _run("import pipeline.cli")
    assert code == 0, out
    assert imported == [], imported


def test_help_loads_no_heavy_library():
    code, out, imported = _run("from pipeline.cli import main; main()", "--help")
    assert code == 0 and "Usage" in out and "run" in out, out
    assert imported == [], imported


def test_a_scene_with_every_pose_runs_without_pycolmap(tiny_scene, tmp_path):
    run = tmp_path / "run"
    main = "from pipeline.cli import main; main()"
    code, out, imported = _run(main, "status", tiny_scene, "--out", run, hide_pycolmap=True)
    assert code == 0, out
    assert "poses" in out and "skipped" in out
    code, out, imported = _run(main, "run", "union", tiny_scene, "--out", run, hide_pycolmap=True)
    assert code == 0, out
    assert "pycolmap" not in imported
