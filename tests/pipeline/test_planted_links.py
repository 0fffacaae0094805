"""Symbolic links planted in a run folder (hardening issue, second pass, class 1).

For each command, the paths it touches under the run folder are *generated* by running it once
on a finished run and recording every path it opens, lists, makes, renames or deletes (Python's
audit events), plus every entry whose content changed (writes by native code: OpenCV, ffmpeg).
Then a symbolic link is planted at each of those paths (and at each folder on the way), pointing
out of the run folder at a copy of what was there, and the command is run again: it must refuse
in one line (exit 2), or for `clean` remove the link without following it, and nothing outside
the run folder may change. Before the fix, links at R/report, R/.scratch, R/export, R/render,
R/sweep and R/view carried writes and deletes outside, and reads followed R/train/point_cloud.ply.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import socket
import sys
from pathlib import Path

import numpy as np
import pytest

from simulate.generate import generate_scene
from tests.clitools import invoke, run_main

FAST = ["--set", "train.iterations=5", "--set", "train.height=8"]
#: Files per folder a link is planted at (all folders on the way always are): the rule is the same
#: for every file of a folder, and each example costs a command run.
FILES_PER_FOLDER = 2

COMMANDS: dict[str, list[str]] = {
    "run": ["run", "all", "<S>", "--out", "<R>", "--force", *FAST],
    "status": ["status", "<S>", "--out", "<R>"],
    "report": ["report", "<S>", "--out", "<R>"],
    "render": ["render", "<S>", "--out", "<R>", "--frames", "2", "--height", "8"],
    "export": ["export", "<R>", "--format", "splat"],
    "export-mesh": ["export", "<R>", "--format", "mesh", "--mesh-height", "16", "--mesh-depth", "5"],
    "sweep": ["sweep", "<S>", "--out", "<R>", "--iterations", "3", "--heights", "8", "--caps", "default"],
    "view": ["view", "<R>", "--port", "<PORT>"],
    "clean": ["clean", "<S>", "--out", "<R>", "--yes"],
}

_recording: list[str] | None = None
_EVENTS_ONE = {"open", "os.mkdir", "os.remove", "os.rmdir", "shutil.rmtree", "os.listdir", "os.scandir",
               "os.truncate", "os.chmod", "os.utime", "os.chown"}
_EVENTS_TWO = {"os.rename", "shutil.copyfile", "shutil.copytree", "shutil.move", "os.link", "os.symlink"}


def _audit(event: str, args) -> None:
    if _recording is None:
        return
    if event in _EVENTS_ONE:
        paths = args[:1]
    elif event in _EVENTS_TWO:
        paths = args[:2]
    else:
        return
    for p in paths:
        if isinstance(p, (str, bytes, os.PathLike)):
            _recording.append(os.path.abspath(os.fsdecode(p)))


sys.addaudithook(_audit)


def _snapshot(root: Path) -> dict[str, tuple]:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = ("link", os.readlink(p))
            elif p.is_file():
                out[rel] = ("file", hashlib.sha256(p.read_bytes()).hexdigest())
            else:
                out[rel] = ("dir",)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _is_temporary(name: str) -> bool:
    return name.startswith((".tmp-", ".old-")) or ".tmp" in name or name == ".lock"


def _run(name: str, scene: Path, run: Path, capsys, monkeypatch) -> tuple:
    args = [a.replace("<S>", str(scene)).replace("<R>", str(run)).replace("<PORT>", str(_free_port()))
            for a in COMMANDS[name]]
    if name == "view":  # serve, render one panorama (what the GUI button does), then stop as Ctrl-C does
        import viewer.command
        import viewer.server

        real_start = viewer.server.start_viewer

        def start_and_render(*a, **k):
            handle = real_start(*a, **k)
            handle.render_panorama(np.eye(4), 64)
            return handle

        def stop(_seconds):
            raise KeyboardInterrupt

        monkeypatch.setattr(viewer.server, "start_viewer", start_and_render)
        monkeypatch.setattr(viewer.command.time, "sleep", stop)
    try:
        return invoke(args, capsys)
    finally:
        monkeypatch.undo()


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("links")
    generate_scene(root / "S", views=2, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R", *FAST]) == 0
    return root / "S", root / "R"


def touched_paths(name: str, base: tuple[Path, Path], tmp: Path, capsys, monkeypatch) -> list[str]:
    """Run `name` once on a copy of the finished run: the paths under the run folder it touched."""
    global _recording
    scene, base_run = base
    run = tmp / "R"
    shutil.copytree(base_run, run, symlinks=True)
    before = _snapshot(run)
    _recording = []
    try:
        code, out, err = _run(name, scene, run, capsys, monkeypatch)
    finally:
        recorded, _recording = _recording, None
    assert code == 0, err
    after = _snapshot(run) if run.exists() else {}
    changed = {k for k in before.keys() | after.keys() if before.get(k) != after.get(k)}
    rels = set(changed)
    for p in recorded:
        path = Path(p)
        if path == run or run not in path.parents:
            continue
        rels.add(path.relative_to(run).as_posix())
    shutil.rmtree(run, ignore_errors=True)
    return sorted(rels)


def link_sites(rels: list[str]) -> list[str]:
    """Every folder on the way to a touched path, and up to FILES_PER_FOLDER touched files of each
    folder; temporary names (random) are covered by their folder."""
    folders, files = set(), {}
    for rel in rels:
        parts = rel.split("/")
        keep = []
        for part in parts:  # up to the first temporary component
            if _is_temporary(part):
                break
            keep.append(part)
        for i in range(1, len(keep)):
            folders.add("/".join(keep[:i]))
        if keep and len(keep) == len(parts):
            files.setdefault("/".join(keep[:-1]), set()).add("/".join(keep))
    sites = set(folders)
    for folder, names in files.items():
        sites |= set(sorted(n for n in names if n not in folders)[:FILES_PER_FOLDER])
    return sorted(sites)


def plant(run: Path, site: str, sentinel: Path) -> Path:
    """Replace run/site with a link to a copy of it under `sentinel` (an empty folder when the
    command would make it)."""
    path = run / site
    path.parent.mkdir(parents=True, exist_ok=True)
    target = sentinel / site.replace("/", "__")
    if path.is_dir():
        shutil.copytree(path, target, symlinks=True)
        shutil.rmtree(path)
    elif path.exists():
        shutil.copy2(path, target)
        path.unlink()
    elif "." in Path(site).name and not site.startswith("."):  # a file the command makes
        target.write_bytes(b"keep me\n")
    else:
        target.mkdir()
    path.symlink_to(target)
    return target


@pytest.mark.parametrize("name", list(COMMANDS))
def test_a_link_at_every_path_a_command_touches_is_refused(name, base, tmp_path, capsys, monkeypatch):
    if name == "view":
        pytest.importorskip("viser")
    scene, base_run = base
    sites = link_sites(touched_paths(name, base, tmp_path / "capture", capsys, monkeypatch))
    assert sites, "the command touched nothing under the run folder"
    scene_before = _snapshot(scene)
    problems = []
    for i, site in enumerate(sites):
        root = tmp_path / f"ex{i}"
        sentinel = root / "sentinel"
        sentinel.mkdir(parents=True)
        run = root / "R"
        shutil.copytree(base_run, run, symlinks=True)
        plant(run, site, sentinel)
        outside = _snapshot(sentinel)
        code, out, err = _run(name, scene, run, capsys, monkeypatch)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        if name == "clean":
            ok = code == 0 and not run.exists()
        else:
            ok = code == 2 and len(lines) == 1 and "symbolic link" in lines[0] and "Traceback" not in out + err
        if not ok:
            problems.append(f"{site}: exit {code}, stderr {err.strip()[-300:]!r}")
        if _snapshot(sentinel) != outside:
            problems.append(f"{site}: changed what the link points at")
        shutil.rmtree(root, ignore_errors=True)
    assert _snapshot(scene) == scene_before
    assert not problems, f"{name}: {len(problems)} of {len(sites)} planted links:\n" + "\n".join(problems)
