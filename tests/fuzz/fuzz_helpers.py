"""The fuzz harness: a sandbox per example, the CLI in-process, and the bad-input contract.

The contract (the hardening issue), checked after every example:

1. the exit code is 0 or 2;
2. no traceback anywhere in the output;
3. on exit 2, stderr is exactly one non-empty line (`error: <where>: <problem>`), counting what
   the real process would print there: rich output, C-level writes to fd 2 (OpenCV warnings)
   and Python warnings;
4. nothing is written outside the run folder: every path under the sandbox root except the run
   folder (the scene folder, a sentinel folder of decoys, the working folder) is unchanged;
5. on exit 2 the artifacts of the previous good run are byte-identical (the run log and the
   lock file are bookkeeping, not artifacts) and no temporary folder is left behind.

A sandbox holds, under one temporary root:

    scene/     a copy of the tiny simulated scene (3 train views, 1 test, 16x32, supplied
               layout + depth), mutated by the example
    run/       a copy of a good run of that scene (`run all --until align`)
    sentinel/  decoys outside both: a valid image, layout, depth files, a garbage "model",
               a text file; symlinks made by examples point here, hostile names aim here
    cwd/       the working folder during the run (a stray relative write lands here)

Mutations name sandbox paths through placeholders (<ROOT>, <SCENE>, <RUN>, <SENTINEL>, <CWD>)
so examples stay readable and reproducible; `Sandbox.expand` fills them in.

Set PANO_FUZZ_REPORT=/some/file.jsonl to record contract violations there (one JSON line each)
instead of failing: one run of the suite then lists every violating example, not just the first
of each test. PANO_FUZZ_TRACE=/other/file.jsonl logs every example with its exit code and
duration (to find slow ones). CI leaves both unset.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import signal
import sys
import tempfile
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from hypothesis import HealthCheck, Phase, settings

from pipeline import cli

#: Settings for every fuzz test: deterministic (the same examples on every run and machine),
#: no example database, no deadline (the first example pays for imports), no shrinking (each
#: example is a few hundred ms; the mutation's description is readable as it is).
FUZZ_SETTINGS = dict(
    derandomize=True,
    database=None,
    deadline=None,
    phases=(Phase.explicit, Phase.generate),
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                           HealthCheck.data_too_large, HealthCheck.filter_too_much],
    print_blob=False,
)


def fuzz_settings(max_examples: int):
    return settings(max_examples=max_examples, **FUZZ_SETTINGS)


#: Fast settings of the base run; every example passes them too so the base run's artifacts are
#: cache hits and only what a mutation touches reruns.
BASE_SET = ["--set", "sampling.density=25"]
#: Stages the fuzz runs execute (train and evaluate need the compiled kernel and seconds each;
#: their parameters are still validated, since planning validates every stage's).
FAST_STAGES = ("layout", "depth", "union", "sampling", "align")

SCENE_VIEWS = ("train_00", "train_01", "train_02", "test_00")
TRAIN_VIEWS = ("train_00", "train_01", "train_02")

#: Run-folder files that are bookkeeping, not artifacts: appended / rewritten on every run.
# the run log, the lock and the marker (rewritten when a run folder moved): not artifacts
BOOKKEEPING = {"run_log.jsonl", ".lock", ".pano-pipe-run"}
TEMP_PREFIXES = (".tmp-", ".old-")

REPORT_ENV = "PANO_FUZZ_REPORT"
TRACE_ENV = "PANO_FUZZ_TRACE"


# ----------------------------------------------------------------------------- the CLI in-process
@dataclass
class Result:
    args: list[str]
    code: int | str | None
    out: str
    err: str

    @property
    def err_lines(self) -> list[str]:
        return self.err.strip("\n").splitlines() if self.err.strip() else []


def _warning_filters() -> None:
    """The filters a fresh `python` process starts with (what the real CLI would print)."""
    warnings.resetwarnings()
    warnings.simplefilter("default")
    for cat in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
        warnings.filterwarnings("ignore", category=cat)


class _StringCapture:
    """capfd's interface over sys.stdout/sys.stderr, for session fixtures (no C-level output)."""

    def __init__(self):
        self.out, self.err = io.StringIO(), io.StringIO()
        self._stack = contextlib.ExitStack()
        self._stack.enter_context(contextlib.redirect_stdout(self.out))
        self._stack.enter_context(contextlib.redirect_stderr(self.err))

    def readouterr(self):
        out, err = self.out.getvalue(), self.err.getvalue()
        self.out.seek(0), self.out.truncate(), self.err.seek(0), self.err.truncate()
        return type("Captured", (), {"out": out, "err": err})

    def close(self):
        self._stack.close()


def run_cli(args: list[str], capfd=None) -> Result:
    """`pano-pipe ARGS` in this process; stdout/stderr captured at the file-descriptor level by
    pytest's capfd (or, without it, at the sys.stdout/sys.stderr level)."""
    own = capfd is None
    if own:
        capfd = _StringCapture()
    capfd.readouterr()
    old_argv = sys.argv
    old_term = signal.getsignal(signal.SIGTERM)
    old_debug = cli._state.get("debug", False)
    old_env = os.environ.get("PANO_PIPE_MAX_MEGAPIXELS")
    sys.argv = ["pano-pipe", *args]
    code: int | str | None = 0
    with warnings.catch_warnings(record=True) as caught:
        _warning_filters()
        try:
            cli.main()
        except SystemExit as e:
            code = e.code
        finally:
            sys.argv = old_argv
            signal.signal(signal.SIGTERM, old_term)
            cli._state["debug"] = old_debug
            if old_env is None:
                os.environ.pop("PANO_PIPE_MAX_MEGAPIXELS", None)
            else:
                os.environ["PANO_PIPE_MAX_MEGAPIXELS"] = old_env
    captured = capfd.readouterr()
    if own:
        capfd.close()
    err = captured.err
    for w in caught:  # the real process would have printed these on stderr
        err += warnings.formatwarning(w.message, w.category, w.filename, w.lineno, w.line)
    if code is None:
        code = 0
    return Result(list(args), code, captured.out, err)


# ----------------------------------------------------------------------------- the base scene and run
def write_png(path: Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    Path(path).write_bytes(buf.tobytes())


def build_base(root: Path) -> tuple[Path, Path]:
    """The tiny scene and a good run of it (until align); built once per session."""
    from simulate.generate import generate_scene

    scene = root / "scene"
    generate_scene(scene, views=3, test_views=1, height=16, seed=0, effects="none",
                   with_layout=True, with_depth=True)
    # files scene.json does not name: fewer files make every sandbox copy cheaper
    shutil.rmtree(scene / "gt" / "layout")
    for f in (scene / "gt" / "depth").glob("*.png"):
        f.unlink()
    run = root / "run"
    with chdir(root):
        res = run_cli(["run", "all", str(scene), "--out", str(run), "--until", "align", *BASE_SET])
    assert res.code == 0, f"the base run failed: {res.err}"
    return scene, run


@contextlib.contextmanager
def chdir(path: Path):
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


# ----------------------------------------------------------------------------- the sandbox
def _sha(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def tree_snapshot(root: Path, exclude: Path | None = None) -> dict[str, tuple]:
    """Every entry below `root` (symlinks not followed): relative path -> (kind, content)."""
    snap: dict[str, tuple] = {}
    root = Path(root)
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        d = Path(dirpath)
        if exclude is not None and d == exclude:
            dirnames[:] = []
            continue
        for name in dirnames + filenames:
            p = d / name
            if exclude is not None and p == exclude:
                continue
            rel = p.relative_to(root).as_posix()
            try:
                if p.is_symlink():
                    snap[rel] = ("link", os.readlink(p))
                elif p.is_dir():
                    snap[rel] = ("dir",)
                elif p.is_file():
                    snap[rel] = ("file", _sha(p))
                else:
                    snap[rel] = ("other",)
            except OSError as e:  # unreadable: record that, do not crash the harness
                snap[rel] = ("error", str(e))
    return snap


def diff_snapshots(before: dict, after: dict) -> list[str]:
    problems = []
    for rel in sorted(before.keys() - after.keys()):
        problems.append(f"removed {rel}")
    for rel in sorted(after.keys() - before.keys()):
        problems.append(f"created {rel}")
    for rel in sorted(before.keys() & after.keys()):
        if before[rel] != after[rel]:
            problems.append(f"changed {rel}")
    return problems


class Sandbox:
    def __init__(self, root: Path, base_scene: Path, base_run: Path):
        self.root = Path(root)
        self.scene = self.root / "scene"
        self.run = self.root / "run"
        self.sentinel = self.root / "sentinel"
        self.cwd = self.root / "cwd"
        shutil.copytree(base_scene, self.scene, symlinks=True)
        shutil.copytree(base_run, self.run, symlinks=True)
        self.cwd.mkdir()
        self._make_sentinel(base_scene)

    def _make_sentinel(self, base_scene: Path) -> None:
        s = self.sentinel
        (s / "images").mkdir(parents=True)
        for f in (base_scene / "images").iterdir():  # valid images, reachable only by escaping
            shutil.copy(f, s / "images" / f.name)
        shutil.copy(base_scene / "images" / "train_00.png", s / "img.png")
        shutil.copy(base_scene / "layout" / "train_00.json", s / "layout.json")
        shutil.copy(base_scene / "depth" / "train_00.png", s / "depth.png")
        shutil.copy(base_scene / "gt" / "depth" / "train_00.npy", s / "depth.npy")
        shutil.copy(base_scene / "scene.json", s / "scene.json")
        (s / "model.onnx").write_bytes(b"\x08\x07garbage, not an ONNX model\n")
        (s / "secret.txt").write_text("keep me\n")
        (s / "run_log.jsonl").write_text("")
        (s / "config.yaml").write_text("layout: {}\n")

    # placeholders -> sandbox paths
    def expand(self, value):
        if isinstance(value, str):
            for key, path in (("<ROOT>", self.root), ("<SCENE>", self.scene), ("<RUN>", self.run),
                              ("<SENTINEL>", self.sentinel), ("<CWD>", self.cwd)):
                value = value.replace(key, str(path))
            return value
        if isinstance(value, list):
            return [self.expand(v) for v in value]
        if isinstance(value, dict):
            return {self.expand(k) if isinstance(k, str) else k: self.expand(v) for k, v in value.items()}
        return value

    # the manifest
    def manifest(self) -> dict:
        return json.loads((self.scene / "scene.json").read_text())

    def write_manifest(self, data: dict) -> None:
        (self.scene / "scene.json").write_text(json.dumps(data, indent=1))

    def view(self, data: dict, name: str) -> dict:
        return next(v for v in data["views"] if v["name"] == name)

    def outside(self) -> dict:
        return tree_snapshot(self.root, exclude=self.run)

    def run_files(self) -> dict:
        return tree_snapshot(self.run) if self.run.is_dir() and not self.run.is_symlink() else {}


#: Sandboxes are deleted on a background thread (deleting ~100 small files and folders costs
#: as much as an example on a slow disk); `wait_for_cleanup` joins it at the end of the session.
_cleaner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fuzz-cleanup")
_pending: list = []


def wait_for_cleanup() -> None:
    while _pending:
        _pending.pop().result()


@contextlib.contextmanager
def sandbox(base: tuple[Path, Path], parent: Path):
    root = Path(tempfile.mkdtemp(prefix="fz-", dir=parent))
    try:
        yield Sandbox(root, *base)
    finally:
        _pending.append(_cleaner.submit(shutil.rmtree, root, ignore_errors=True))


# ----------------------------------------------------------------------------- the contract
def completed_stages(run_dir: Path, log_before: int) -> set[str]:
    """Stages the run log says finished ("ok") after its first `log_before` bytes."""
    try:
        with open(run_dir / "run_log.jsonl", "rb") as f:
            f.seek(log_before)
            lines = f.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return set()
    done = set()
    for line in lines:
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and rec.get("event") == "ok":
            done.add(str(rec.get("stage")))
    return done


def _log_size(run_dir: Path) -> int:
    try:
        return (run_dir / "run_log.jsonl").stat().st_size
    except OSError:
        return 0


def contract_problems(res: Result, before_outside: dict, after_outside: dict,
                      before_run: dict, after_run: dict, completed: set[str] = frozenset()) -> list[str]:
    problems = []
    if res.code not in (0, 2):
        problems.append(f"exit code {res.code!r}, expected 0 or 2")
    if "Traceback" in res.out + res.err:
        problems.append("a traceback in the output")
    if res.code == 2:
        lines = res.err_lines
        if len(lines) != 1 or not lines[0].strip():
            problems.append(f"exit 2 with {len(lines)} lines on stderr, expected exactly one")
        elif not lines[0].startswith("error: "):
            problems.append("exit 2 and the stderr line does not start with 'error: '")
    outside = diff_snapshots(before_outside, after_outside)
    if outside:
        problems.append("written outside the run folder: " + "; ".join(outside[:8])
                        + (f" (+{len(outside) - 8} more)" if len(outside) > 8 else ""))
    if res.code == 2:
        art_before = {k: v for k, v in before_run.items() if k not in BOOKKEEPING}
        art_after = {k: v for k, v in after_run.items() if k in art_before}
        changed = diff_snapshots(art_before, art_after)
        if changed:
            # say which changes come from upstream stages that re-ran fine before the failing one
            notes = [c + (" (its stage re-ran ok in this run)" if c.split()[-1].split("/")[0] in completed else "")
                     for c in changed]
            problems.append("failed run changed previous artifacts: " + "; ".join(notes[:8])
                            + (f" (+{len(notes) - 8} more)" if len(notes) > 8 else ""))
        left = sorted(k for k in after_run.keys() - before_run.keys()
                      if Path(k).name.startswith(TEMP_PREFIXES))
        if left:
            problems.append("failed run left temporaries: " + "; ".join(left[:4]))
    return problems


def check(mutation, res: Result, sb: Sandbox, before_outside: dict, before_run: dict, test: str = "",
          log_before: int = 0) -> None:
    """Assert the contract for one example; the message shows the mutation, the command and output."""
    problems = contract_problems(res, before_outside, sb.outside(), before_run, sb.run_files(),
                                 completed_stages(sb.run, log_before))
    if not problems:
        return
    report = os.environ.get(REPORT_ENV)
    args = [a.replace(str(sb.root), "<ROOT>") for a in res.args]
    err = res.err.replace(str(sb.root), "<ROOT>")
    out = res.out.replace(str(sb.root), "<ROOT>")
    if report:
        with open(report, "a") as f:
            f.write(json.dumps({"test": test, "mutation": repr(mutation), "args": args, "code": res.code,
                                "problems": problems, "stderr": err[-3000:], "stdout": out[-1000:]}) + "\n")
        return
    raise AssertionError(
        "bad-input contract broken\n"
        f"  mutation: {mutation!r}\n"
        f"  command:  pano-pipe {' '.join(args)}\n"
        f"  exit:     {res.code!r}\n"
        "  problems:\n" + "".join(f"    - {p}\n" for p in problems)
        + "  stderr:\n" + _indent(err[-4000:]) + ("  stdout:\n" + _indent(out[-2000:]) if out.strip() else "")
    )


def _indent(text: str) -> str:
    return "".join(f"    | {line}\n" for line in text.splitlines()) or "    | (empty)\n"


def run_example(sb: Sandbox, args: list[str], capfd, mutation, test: str = "") -> Result:
    """Snapshot, run `pano-pipe ARGS` from the sandbox's working folder, check the contract."""
    before_outside = sb.outside()
    before_run = sb.run_files()
    log_before = _log_size(sb.run)
    t0 = time.perf_counter()
    with chdir(sb.cwd):
        res = run_cli([sb.expand(a) for a in args], capfd)
    seconds = time.perf_counter() - t0
    if os.environ.get(TRACE_ENV):
        with open(os.environ[TRACE_ENV], "a") as f:
            f.write(json.dumps({"test": test, "mutation": repr(mutation)[:300], "code": res.code,
                                "seconds": round(seconds, 3)}) + "\n")
    check(mutation, res, sb, before_outside, before_run, test, log_before)
    return res


def run_args(until: str | None = "align", command: str = "run-all") -> list[str]:
    """The pano-pipe arguments of a run of the sandbox scene into the sandbox run folder."""
    if command == "status":
        return ["status", "<SCENE>", "--out", "<RUN>", *BASE_SET]
    if command == "clean":
        return ["clean", "<SCENE>", "--out", "<RUN>", "--yes"]
    if command.startswith("run-stage-"):
        return ["run", command.removeprefix("run-stage-"), "<SCENE>", "--out", "<RUN>", *BASE_SET]
    extra = ["--until", until] if until else []
    return ["run", "all", "<SCENE>", "--out", "<RUN>", *extra, *BASE_SET]


# ----------------------------------------------------------------------------- shared hostile values
#: View / scene names: path tricks, markup, control characters, lengths over file-system limits.
HOSTILE_NAMES = [
    "../x", "../../sentinel/pwn", "../../../sentinel/pwn", "<SENTINEL>/pwn", "a/b", "a\\b", "\x00",
    "x\x00y", "[/b]", "[red]x[/red]", "[/]", "[link=file:///etc/passwd]x", "x" * 129, "x" * 300,
    "é" * 200, "💥" * 70, ".", "..", "", " ", " x", "x ", "x.", "-rf", "--out", ".hidden", "CON",
    "a:b", "a*b", "a?b", 'a"b', "a<b>", "a|b", "\u202eevil", "line\nbreak", "tab\tx", "\r", "~",
    "~root", "$HOME", "%s%n", "ünïcödé ✓", "name with spaces", "train_00",
]

#: Relative paths as scene.json may give them: escapes, absolute, odd forms, existing and not.
HOSTILE_PATHS = [
    "../sentinel/img.png", "../../sentinel/img.png", "<SENTINEL>/img.png", "<SCENE>/images/train_00.png",
    "images/../images/train_00.png", "images/../../sentinel/img.png", "./images/train_00.png",
    "images//train_00.png", "images/./train_00.png", "images/train_00.png/", "images", ".", "..", "",
    "\x00", "images/train_00.png\x00.txt", "C:\\x.png", "C:x.png", "\\\\server\\share\\x.png",
    "\\..\\sentinel\\img.png", "..\\sentinel\\img.png", "~/x.png", "file:///etc/passwd",
    "images/missing.png", "images/" + "x" * 300 + ".png", "scene.json", "/dev/null", "/proc/self/environ",
    "[/b].png", "images/💥.png", "layout/train_00.json", "depth/train_00.png", "gt/depth/train_00.npy",
    "gt/floor_plan.json",
]

NUMBERS = [0, -1, 1, 1e308, -1e308, float("inf"), float("-inf"), float("nan"), 1e-308, 5e-324,
           10 ** 400, -(10 ** 400), 2 ** 63, 2 ** 64, 1e5, 1e5 + 1, 100.0, 100.0001, 1e-9, True, False]


def deep(depth: int, leaf=0):
    """A list nested `depth` deep, built without recursion."""
    value = leaf
    for _ in range(depth):
        value = [value]
    return value


def json_dumps_deep(value) -> str:
    """json.dumps for values nested too deep for the recursive encoder."""
    depth = 0
    while isinstance(value, list) and len(value) == 1 and isinstance(value[0], list):
        value = value[0]
        depth += 1
    return "[" * depth + json.dumps(value) + "]" * depth



