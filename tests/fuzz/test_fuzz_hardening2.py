"""Generators for the classes of the second hardening pass (issue 21): links planted anywhere in a
run folder, files whose headers claim huge payloads, and interruptions (SIGTERM / Ctrl-C) at any
file operation of a run. Each example is checked against the bad-input contract (fuzz_helpers)
and the class's own promise."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from hypothesis import example, given
from hypothesis import strategies as st

from fuzz_helpers import (
    BASE_SET,
    BOOKKEEPING,
    TEMP_PREFIXES,
    TRAIN_VIEWS,
    chdir,
    completed_stages,
    diff_snapshots,
    fuzz_settings,
    run_args,
    run_cli,
    run_example,
    sandbox,
)
from tests import hostile_files as hostile

# ----------------------------------------------------------------------------- planted links
#: Where a link may be planted: entries of the base run (until align) and folders commands make.
LINK_SITES = ["layout", "layout/artifact.json", "depth", "depth/depth", "union", "union/artifact.json",
              "sampling", "sampling/cloud.npz", "align", "align/artifact.json", ".pano-pipe-run",
              "run_log.jsonl", ".lock", ".scratch", ".scratch/train", "report", "report/img", "render",
              "export", "sweep", "ablate", "view", "train", "evaluate", ".tmp-layout-00000000"]
LINK_TARGETS = ["<SENTINEL>", "<SENTINEL>/secret.txt", "<SENTINEL>/nope", "../sentinel", "<SCENE>",
                "<SCENE>/scene.json", "/", "<SELF>"]
LINK_COMMANDS = ["run-all", "run-stage-layout", "status", "clean", "report", "export"]


@given(site=st.sampled_from(LINK_SITES), target=st.sampled_from(LINK_TARGETS),
       command=st.sampled_from(LINK_COMMANDS))
@example(site="report", target="<SENTINEL>", command="report")
@example(site=".scratch", target="<SENTINEL>", command="run-all")
@example(site="layout/artifact.json", target="<SENTINEL>/secret.txt", command="status")
@fuzz_settings(max_examples=20)
def test_planted_links(site, target, command, fuzz_base, tmp_path, capfd):
    import shutil

    with sandbox(fuzz_base, tmp_path) as sb:
        link = sb.run / site
        link.parent.mkdir(parents=True, exist_ok=True)
        if link.is_dir() and not link.is_symlink():
            shutil.rmtree(link)
        else:
            link.unlink(missing_ok=True)
        link.symlink_to(str(link) if target == "<SELF>" else sb.expand(target))
        if command == "report":
            args = ["report", "<SCENE>", "--out", "<RUN>"]
        elif command == "export":
            args = ["export", "<RUN>", "--format", "splat"]
        else:
            args = run_args("align", command if command != "run-all" else "run-all")
        res = run_example(sb, args, capfd, (site, target, command), "planted-links")
        if command == "clean":  # removes the link itself (nothing outside changed: the contract), or refuses
            assert res.code == 2 or not os.path.lexists(link), res.err
        else:  # a link anywhere in the run folder is refused before anything is read or written
            assert res.code == 2 and "symbolic link" in res.err, (site, command, res.code, res.err)


# ----------------------------------------------------------------------------- hostile headers
BIG = st.sampled_from([2 ** 15, 16000, 100_000, 2 ** 31 - 1, 2 ** 32 - 1])
SMALL = st.sampled_from([1, 8, 16, 32])


@st.composite
def hostile_depth(draw):
    """(extension, bytes) of a depth file whose header claims more than it holds or than the limit."""
    kind = draw(st.sampled_from(["png16", "png8", "exr", "npy", "npy-header"]))
    w, h = draw(BIG), draw(st.one_of(BIG, SMALL))
    if draw(st.booleans()):
        w, h = h, w
    if kind.startswith("png"):
        return ".png", hostile.png(min(w, 2 ** 31 - 1), min(h, 2 ** 31 - 1), bit_depth=16 if kind == "png16" else 8)
    if kind == "exr":
        return ".exr", hostile.exr(min(w, 2 ** 31 - 1), min(h, 2 ** 31 - 1))
    pad = 20000 if kind == "npy-header" else 0
    return ".npy", hostile.npy((h, w), dtype=draw(st.sampled_from(["<f4", "<f8", "<u2"])), header_pad=pad)


@given(view=st.sampled_from(TRAIN_VIEWS), file=hostile_depth(), as_image=st.booleans())
@example(view="train_00", file=(".png", hostile.png(16000, 8000, bit_depth=16)), as_image=False)
@example(view="train_01", file=(".exr", hostile.exr(16000, 8000)), as_image=False)
@fuzz_settings(max_examples=15)
def test_hostile_headers(view, file, as_image, fuzz_base, tmp_path, capfd):
    ext, raw = file
    with sandbox(fuzz_base, tmp_path) as sb:
        data = sb.manifest()
        v = sb.view(data, view)
        if as_image and ext == ".png":  # the panorama itself
            (sb.scene / v["image"]).write_bytes(raw)
        else:
            (sb.scene / "depth").mkdir(exist_ok=True)
            (sb.scene / "depth" / f"{view}{ext}").write_bytes(raw)
            v["depth"] = f"depth/{view}{ext}"
            sb.write_manifest(data)
        res = run_example(sb, run_args("depth"), capfd, (view, ext, len(raw), as_image), "headers")
        assert res.code == 2, res.err  # every claim is over the limit, over the file, or truncated


# ----------------------------------------------------------------------------- interruptions
_trap: dict = {"root": None, "left": 0, "fired": False}
_WRITES = {"open", "os.mkdir", "os.rename", "os.remove", "os.rmdir", "shutil.rmtree", "os.truncate"}


def _interrupt_at(event: str, args) -> None:
    """Raise Terminated (what our SIGTERM handler raises) at the n-th file operation under the run
    folder, or at the first one after it while the signals are held back: a signal arriving there."""
    root = _trap["root"]
    if root is None or _trap["fired"] or event not in _WRITES or not args:
        return
    path = args[0]
    if not isinstance(path, (str, bytes, os.PathLike)) or not os.path.abspath(os.fsdecode(path)).startswith(root):
        return
    _trap["left"] -= 1
    if _trap["left"] <= 0 and not _held():  # a signal held back (signals_held) waits for the block's end
        from pipeline.signals import Terminated

        _trap["fired"] = True
        raise Terminated()


def _held() -> bool:
    import signal

    return signal.SIGTERM in signal.pthread_sigmask(signal.SIG_BLOCK, [])


sys.addaudithook(_interrupt_at)


def _complete(stage_dir: Path) -> bool:
    """A stage folder holding a valid artifact and every file it lists, at its size."""
    import json

    try:
        meta = json.loads((stage_dir / "artifact.json").read_text())["meta"]
        return all((stage_dir / rel).stat().st_size == size for rel, size in meta["files"].items())
    except (OSError, ValueError, KeyError, TypeError):
        return False


@given(at=st.integers(min_value=1, max_value=400))
@example(at=1)
@example(at=25)
@fuzz_settings(max_examples=12)
def test_interrupted_anywhere(at, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb:
        before_outside, before_run = sb.outside(), sb.run_files()
        log_before = (sb.run / "run_log.jsonl").stat().st_size
        _trap.update(root=str(sb.run), left=at, fired=False)
        try:
            with chdir(sb.cwd):
                res = run_cli(["run", "all", str(sb.scene), "--out", str(sb.run), "--until", "align", "--force",
                               *BASE_SET], capfd)
        finally:
            fired = _trap["fired"]
            _trap.update(root=None, fired=False)
        lines = res.err_lines
        assert "Traceback" not in res.out + res.err
        assert not diff_snapshots(before_outside, sb.outside())
        if not fired:
            assert res.code == 0, res.err
            return
        assert res.code == 130 and len(lines) == 1 and lines[0].startswith("interrupted"), (at, res.code, res.err)
        after = sb.run_files()
        left = [k for k in after if Path(k).name.startswith(TEMP_PREFIXES) or Path(k).name.endswith(".tmp")]
        assert not left, (at, left)
        # stages that finished: logged "ok", or whose new result was swapped in whole just before
        # the (held-back) signal was handled
        done = completed_stages(sb.run, log_before) | {
            k.split("/")[0] for k in after if k.endswith("/artifact.json") and after[k] != before_run.get(k)
            and _complete(sb.run / k.split("/")[0])}
        artifacts = {k: v for k, v in before_run.items() if k not in BOOKKEEPING}
        changed = [c for c in diff_snapshots(artifacts, {k: v for k, v in after.items() if k in artifacts})
                   if c.split()[-1].split("/")[0] not in done]
        assert not changed, (at, changed)
