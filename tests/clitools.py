"""The console entry point run in-process, as a user's shell would run it."""

from __future__ import annotations

import sys
from pathlib import Path

from pipeline import cli


def run_main(args) -> int:
    """`pano-pipe ARGS` in this process, output not captured (fixtures that build a run): the exit code."""
    old = sys.argv
    sys.argv = ["pano-pipe", *map(str, args)]
    try:
        try:
            cli.main()
            return 0
        except SystemExit as e:
            return e.code if isinstance(e.code, int) else 0 if e.code is None else 1
    finally:
        sys.argv = old
        cli._state["debug"] = False


def invoke(args, capsys) -> tuple[int, str, str]:
    """`pano-pipe ARGS` in this process: (exit code, stdout, stderr)."""
    old = sys.argv
    sys.argv = ["pano-pipe", *map(str, args)]
    try:
        try:
            cli.main()
            code = 0
        except SystemExit as e:
            code = e.code
    finally:
        sys.argv = old
        cli._state["debug"] = False
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def without_kernel_notices(err: str) -> str:
    """stderr less the splatting kernel's one-time compile notices ("splatting: ..."), which
    the first render on a machine prints whatever command runs it."""
    return "".join(line for line in err.splitlines(keepends=True) if not line.startswith("splatting: "))


def run_on_full_disk(args, budget: int, cwd) -> tuple[int, str, str]:
    """`pano-pipe ARGS` in a child process whose every file write past `budget` bytes fails (EFBIG, as
    on a disk that fills up): (exit code, stdout, stderr), read through pipes, which the limit does
    not touch (pytest's capture files would be)."""
    import os
    import resource
    import signal
    import subprocess
    from pathlib import Path

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (budget, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    proc = subprocess.run([sys.executable, "-c", "from pipeline.cli import main; main()", *map(str, args)],
                          cwd=cwd, preexec_fn=limit, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    return proc.returncode, proc.stdout, proc.stderr


def shared_data() -> Path:
    """../shared/data beside the project root (a worktree may sit one folder deeper)."""
    for parent in Path(__file__).resolve().parents[1:4]:
        if (parent / "shared" / "data").is_dir():
            return parent / "shared" / "data"
    return Path(__file__).resolve().parents[2] / "shared" / "data"
