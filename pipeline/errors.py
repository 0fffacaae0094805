"""User-facing errors: one line naming the file and the problem, exit code 2."""

from __future__ import annotations

from pathlib import Path


class PanoError(Exception):
    """Bad input or configuration. The CLI prints `error: <where>: <problem>` and exits 2."""

    exit_code = 2

    def __init__(self, where: str | Path | None, problem: str):
        self.where = str(where) if where is not None else None
        self.problem = problem
        super().__init__(f"{self.where}: {problem}" if self.where else problem)


def describe_validation_error(where: str | Path, err) -> PanoError:
    """Turn a pydantic ValidationError into a one-line PanoError naming the field."""
    first = err.errors()[0]
    field = ".".join(str(p) for p in first.get("loc", ()))
    msg = first.get("msg", "invalid")
    msg = msg.removeprefix("Value error, ")
    extra = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return PanoError(where, f"{field}: {msg}{extra}" if field else f"{msg}{extra}")
