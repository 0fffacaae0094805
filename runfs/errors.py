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


def one_line(message: object, limit: int | None = None) -> str:
    """`message` (text or an exception) as one line: every run of whitespace, line breaks
    included, one space; an exception without text by its type's name; at most `limit` characters."""
    text = " ".join(str(message).split())
    if not text and isinstance(message, BaseException):
        text = type(message).__name__
    return text if limit is None or len(text) <= limit else text[: limit - 3] + "..."


def did_you_mean(word: str, choices) -> str:
    """' (did you mean X?)' naming the closest of `choices` to a misspelt `word`, or ''."""
    import difflib

    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def describe_validation_error(where: str | Path, err, valid_names=None, listed_by: str | None = None) -> PanoError:
    """Turn a pydantic ValidationError into a one-line PanoError naming the field; an unknown
    field names the closest few of `valid_names` (the model's fields) when given, and the command
    that lists them all (`listed_by`), else all of them."""
    import difflib

    first = err.errors()[0]
    field = ".".join(str(p) for p in first.get("loc", ()))
    msg = first.get("msg", "invalid")
    msg = msg.removeprefix("Value error, ")
    if first.get("type") == "extra_forbidden" and valid_names:
        name = str(first.get("loc", ("",))[-1])
        if listed_by:
            closest = difflib.get_close_matches(name, [str(v) for v in valid_names], n=4, cutoff=0.0)
            msg = (f"unknown parameter{did_you_mean(name, valid_names)}; the closest: {', '.join(closest)} "
                   f"(`{listed_by}` lists all {len(valid_names)})")
        else:
            msg = f"unknown parameter{did_you_mean(name, valid_names)}; valid ones: {', '.join(valid_names)}"
    extra = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return PanoError(where, f"{field}: {msg}{extra}" if field else f"{msg}{extra}")


def read_json(path: Path):
    """A user's JSON file, every failure a one-line PanoError naming it."""
    import json

    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise PanoError(path, f"not UTF-8 text (byte {e.start})") from None
    except OSError as e:
        raise PanoError(path, f"cannot read: {e.strerror or e}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise PanoError(path, f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise PanoError(path, "JSON nested too deeply") from None
