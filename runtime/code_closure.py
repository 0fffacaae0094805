"""A stage's code version: the hash of every repository source its module can run.

The closure follows the static imports of each module (at the top and inside functions), found
by parsing the source with `ast`, never by importing it, and stays inside the repository;
a package in it brings the native sources it compiles at runtime (splatting/csrc/*.cpp, *.h).
A hand-kept list of what a stage depends on went stale (issue 38): editing
panogeom/equirect.py left `train` "up-to-date".
"""

from __future__ import annotations

import ast
import hashlib
from functools import lru_cache
from pathlib import Path

#: The repository root: top-level packages below it are ours, everything else is a library.
SOURCE_ROOT = Path(__file__).resolve().parents[1]

#: Sources a package compiles at runtime (torch cpp_extension): part of its code.
NATIVE_SUFFIXES = (".cpp", ".cc", ".c", ".cu", ".cuh", ".h", ".hpp")


def code_version(module: str, root: Path | None = None) -> str:
    """16 hex digits of the contents of `module`'s import closure inside `root` (the repository)."""
    root = (root or SOURCE_ROOT).resolve()
    h = hashlib.sha256()
    for path in sorted(import_closure(module, root)):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(b"\0")
        h.update(_digest(path, *_stamp(path)))
    return h.hexdigest()[:16]


def import_closure(module: str, root: Path | None = None) -> frozenset[Path]:
    """Every file of the repository `module` imports, directly or not, with its packages'
    `__init__.py` and native sources. Found once per process (status plans every stage, often
    twice); the files' contents are hashed on each call."""
    return _closure(module, (root or SOURCE_ROOT).resolve())


@lru_cache(maxsize=None)
def _closure(module: str, root: Path) -> frozenset[Path]:
    files: set[Path] = set()
    todo = [module]
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for path, file_module, is_package in _module_files(name, root):
            if path in files:
                continue
            files.add(path)
            if is_package:
                files.update(_native_sources(path.parent))
            todo.extend(_imports(path, file_module, is_package))
    return frozenset(files)


def _stamp(path: Path) -> tuple[int, int]:
    """What decides whether a cached hash of `path` still holds."""
    st = path.stat()
    return st.st_mtime_ns, st.st_size


def _module_files(name: str, root: Path) -> list[tuple[Path, str, bool]]:
    """The files importing `name` executes, inside `root`: each enclosing package's __init__.py
    and the module itself (file, its module name, is a package); [] for a module outside the
    repository."""
    parts = name.split(".")
    out = []
    for i in range(1, len(parts) + 1):
        base = root.joinpath(*parts[:i])
        if (base / "__init__.py").is_file():
            out.append((base / "__init__.py", ".".join(parts[:i]), True))
        elif i == len(parts) and base.with_suffix(".py").is_file():
            out.append((base.with_suffix(".py"), name, False))
        elif not base.is_dir():  # a namespace package folder goes on; anything else is not ours
            return out
    return out


def _imports(path: Path, module: str, is_package: bool) -> tuple[str, ...]:
    """Module names `path` imports anywhere in its body (`from a import b` yields a and a.b: b
    may be a submodule; a name that is not a module finds no file)."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    package = module if is_package else module.rpartition(".")[0]
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base:
                names.append(base)
            names.extend(f"{base}.{alias.name}" if base else alias.name for alias in node.names
                         if alias.name != "*")
    return tuple(names)


def _native_sources(package_dir: Path) -> set[Path]:
    """Native sources in a package's own folders (a sub-package brings its own when imported)."""
    out = set()
    for p in package_dir.rglob("*"):
        if p.suffix in NATIVE_SUFFIXES and p.is_file() and not _in_subpackage(p, package_dir):
            out.add(p)
    return out


def _in_subpackage(path: Path, package_dir: Path) -> bool:
    folder = path.parent
    while folder != package_dir:
        if (folder / "__init__.py").is_file():
            return True
        folder = folder.parent
    return False


@lru_cache(maxsize=None)
def _digest(path: Path, mtime_ns: int, size: int) -> bytes:
    return hashlib.sha256(path.read_bytes()).digest()
