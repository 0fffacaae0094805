"""The console entry point run in-process, as a user's shell would run it."""

from __future__ import annotations

import sys

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
