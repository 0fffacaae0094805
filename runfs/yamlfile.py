"""Reading the user's YAML (and JSON, which YAML reads too): settings files, --set values, the
model registry. One place, so every reader gets the same guards (docs/security.md, "Limits"):

- `safe_load` semantics: plain data, never Python objects;
- a key given twice in one mapping is an error, not "the last one wins" silently;
- an error keeps the parser's problem with its line and column, in one line;
- nesting too deep for the parser is one line;
- a file is read only up to `MAX_YAML_BYTES` (a 25 MB settings file took 35 s to parse).
"""

from __future__ import annotations

from pathlib import Path

import yaml

from runfs.errors import PanoError

#: A settings file or registry is a few kB; anything over this is a mistake or an attack.
MAX_YAML_BYTES = 1 << 20

_BaseLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _UniqueKeyLoader(_BaseLoader):
    """SafeLoader that refuses a key repeated in one mapping (merge keys `<<` may still be overridden)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
            except TypeError:  # an unhashable key: the base class says so
                continue
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice in one mapping", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def yaml_problem(e: yaml.YAMLError) -> str:
    """The parser's problem in one line, with where it is (line and column, 1-based)."""
    problem = getattr(e, "problem", None)
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    if problem is None:  # ReaderError and the like: their own text is the problem
        return " ".join(str(e).split("\n  in ")[0].split())
    context = getattr(e, "context", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}" + (f" ({context})" if context else "")


def parse_yaml(text: str, where: str | Path):
    """`text` parsed as YAML/JSON; every failure a one-line PanoError naming `where`."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        raise PanoError(where, f"not valid YAML/JSON: {yaml_problem(e)}") from None
    except RecursionError:
        raise PanoError(where, "nested too deeply") from None


def read_yaml(path: Path, what: str = "file", max_bytes: int = MAX_YAML_BYTES):
    """A user's YAML/JSON file: a regular file (not a folder), at most `max_bytes`, UTF-8, parsed
    with `parse_yaml`."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except IsADirectoryError:
        raise PanoError(path, f"the {what} is a folder, not a file") from None
    except OSError as e:
        raise PanoError(path, f"cannot read the {what}: {e.strerror or e}") from None
    if len(data) > max_bytes:
        raise PanoError(path, f"the {what} is over {max_bytes // 1024} kB; a settings file is a few kB")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise PanoError(path, f"not UTF-8 text (byte {e.start})") from None
    return parse_yaml(text, path)


def yaml_scalar(value) -> str:
    """A plain value (bool, number, string, flat list) as YAML writes it on one line."""
    return yaml.safe_dump(value, default_flow_style=True, width=1 << 16).removesuffix("...\n").strip()
