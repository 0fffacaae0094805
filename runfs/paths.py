"""The one rule about paths (docs/security.md).

- Every path a scene names resolves inside the scene folder, after symlinks.
- View and scene names are safe file-name stems (they become file and folder names).
- Every path the pipeline reads, writes or deletes under a run folder stays inside it: the run
  folder holds no symbolic link (pano-pipe never makes one; `open_run_folder` refuses a folder
  holding one before any command touches it), and a path an artifact names is relative and
  stays inside its folder (`run_path`, which also refuses a link on the way, so a link planted
  while a command runs is refused too where the path is opened). The run folder and the scene
  folder never overlap; only a folder pano-pipe made (it holds the marker file) is ever written
  into, cleaned or replaced.

Everything else in pano-pipe goes through these functions rather than joining
user text onto paths itself.
"""

from __future__ import annotations

import json
import os
import unicodedata
from pathlib import Path, PurePosixPath, PureWindowsPath

from runfs.errors import PanoError
from runfs.fsutil import atomic_write_text

#: Longest name in UTF-8 bytes: file systems allow 255, and suffixes such as
#: `.raw_boundaries.npy` or `.tmp-<stage>-xxxxxxxx` must still fit.
MAX_STEM_BYTES = 128
#: Characters no stem may hold: path separators, and those Windows forbids in names.
_FORBIDDEN = set('/\\:*?"<>|')

#: The marker file of a run folder: `clean` deletes and `run` writes only folders holding it.
RUN_MARKER = ".pano-pipe-run"


def stem_problem(name: str) -> str | None:
    """Why `name` is not a safe file-name stem, or None if it is."""
    if not isinstance(name, str) or not name:
        return "must be a non-empty name"
    if len(name.encode("utf-8", "surrogatepass")) > MAX_STEM_BYTES:
        return f"is longer than {MAX_STEM_BYTES} bytes"
    bad = sorted({c for c in name if c in _FORBIDDEN or unicodedata.category(c)[0] == "C"})
    if bad:
        shown = ", ".join(repr(c) for c in bad[:3])
        return f"holds {shown}; a name becomes a file name, so it may not hold / \\ : * ? \" < > | or control characters"
    if name[0] in ".-":
        return "may not start with '.' or '-' (hidden files, command-line options)"
    if name != name.strip() or name.endswith("."):
        return "may not start or end with a space, or end with '.'"
    return None


def safe_stem(name: str) -> str:
    """`name` if it is a safe file-name stem; else ValueError saying why (pydantic validators use this)."""
    problem = stem_problem(name)
    if problem:
        raise ValueError(f"{shorten(name)} is not a safe name: it {problem}")
    return name


def shorten(text: str, limit: int = 60) -> str:
    """repr() of user text for a one-line message: escapes control characters, cut to `limit`."""
    r = repr(text)
    return r if len(r) <= limit else r[: limit - 4] + "...'"


def relative_problem(rel: str, folder: str = "scene folder", named_in: str = "scene.json") -> str | None:
    """Why `rel` is not a relative path that stays inside its folder (lexically), or None."""
    if not isinstance(rel, str) or not rel:
        return "must be a non-empty relative path"
    if "\x00" in rel:
        return "holds a NUL character"
    if PurePosixPath(rel).is_absolute() or PureWindowsPath(rel).is_absolute() or PureWindowsPath(rel).drive:
        return f"is absolute; paths in {named_in} are relative to the {folder}"
    depth = 0
    for part in PurePosixPath(rel.replace("\\", "/")).parts:
        depth += -1 if part == ".." else (0 if part == "." else 1)
        if depth < 0:
            return f"leaves the {folder} ('..')"
    return None


def safe_relative(rel: str) -> str:
    """`rel` if it is a relative path that stays inside its folder; else ValueError (for validators)."""
    problem = relative_problem(rel)
    if problem:
        raise ValueError(f"{shorten(rel)} {problem}")
    return rel


def resolved(path: Path) -> Path:
    """`path` with symlinks followed; a loop or an unreadable link is a one-line PanoError."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as e:  # RuntimeError: a symlink loop (Python < 3.13)
        raise PanoError(path, f"cannot resolve the path ({e.__class__.__name__}: a symlink loop?)") from None


def is_inside(path: Path, root: Path) -> bool:
    """Whether `path` resolves (symlinks followed) to `root` or below it."""
    return resolved(path).is_relative_to(resolved(root))


def scene_file(root: Path, rel: str, named_by: str | None = None) -> Path:
    """`root / rel`, refusing what resolves outside the scene folder (through '..', an
    absolute path or a symlink). The path need not exist."""
    problem = relative_problem(rel)
    where = f" (named by {named_by})" if named_by else ""
    if problem:
        raise PanoError(Path(root) / "scene.json", f"{shorten(rel)} {problem}{where}")
    path = Path(root) / rel
    if not is_inside(path, root):
        raise PanoError(path, f"resolves outside the scene folder (a symlink?){where}; "
                              "every file a scene names must lie inside it")
    return path


def overlap_problem(a: Path, b: Path) -> str | None:
    """How folder a overlaps folder b ("is", "lies inside", "contains"), or None."""
    ra, rb = resolved(a), resolved(b)
    if ra == rb:
        return "is"
    if ra.is_relative_to(rb):
        return "lies inside"
    if rb.is_relative_to(ra):
        return "contains"
    return None


def check_run_folder(out_dir: Path, scene_root: Path, links_ok: bool = False) -> Path:
    """Refuse a run folder that overlaps the scene folder, is a file, is a non-empty folder
    pano-pipe did not make, or (unless `links_ok`: `clean` removes links without following them)
    holds a symbolic link. Returns it unchanged."""
    out_dir = Path(out_dir)
    problem = overlap_problem(out_dir, scene_root)
    if problem:
        raise PanoError(out_dir, f"the run folder {problem} the scene folder {scene_root}; "
                                 "choose an --out outside the scene (outputs would replace scene files)")
    if out_dir.exists() and not out_dir.is_dir():
        raise PanoError(out_dir, "--out is a file, not a folder")
    if out_dir.is_dir() and not is_run_folder(out_dir) and any(out_dir.iterdir()):
        raise PanoError(out_dir, f"not a pano-pipe run folder (no {RUN_MARKER}) and not empty; "
                                 "choose a new or empty folder for --out")
    if not links_ok:
        refuse_links(out_dir)
    owner = run_folder_scene(out_dir)
    if owner is not None and resolved(owner) != resolved(scene_root):
        raise PanoError(out_dir, f"this run folder belongs to the scene folder {owner}, not {scene_root} "
                                 "(a copy of a scene keeps its name); choose another --out")
    return out_dir


def _marker(out_dir: Path) -> dict:
    try:
        marker = json.loads((Path(out_dir) / RUN_MARKER).read_text())
    except (OSError, ValueError):
        return {}
    return marker if isinstance(marker, dict) else {}


def run_folder_scene(out_dir: Path) -> Path | None:
    """The scene folder a run folder belongs to: the one its marker records, while the run folder
    is where the marker says it was made. A run folder moved or copied (with its scene, say) and
    a marker from before the run folder was recorded belong to no scene yet: the next run claims
    them (mark_run_folder)."""
    marker = _marker(out_dir)
    scene, made_at = marker.get("scene"), marker.get("run")
    if not (isinstance(scene, str) and scene and isinstance(made_at, str) and made_at):
        return None
    if resolved(Path(made_at)) != resolved(out_dir):
        return None
    return Path(scene)


# ----------------------------------------------------------------------------- inside a run folder
LINK_PROBLEM = ("is a symbolic link inside the run folder; pano-pipe never makes one, and reading, "
                "writing or deleting through it would reach outside the run folder (remove it)")


def refuse_links(run_dir: Path) -> None:
    """Refuse a run folder that holds a symbolic link anywhere below it (the folder itself may be
    one: the user named it). Every command calls this (through `check_run_folder` or
    `open_run_folder`) before it reads, writes or deletes anything in the folder."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return
    stack = [run_dir]
    while stack:
        folder = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError as e:
            raise PanoError(folder, f"cannot list the run folder: {e.strerror or e}") from None
        for entry in entries:
            if entry.is_symlink():
                raise PanoError(entry.path, LINK_PROBLEM)
            if entry.is_dir(follow_symlinks=False):
                stack.append(Path(entry.path))


def run_path(folder: Path, rel: str | Path, named_by: str | None = None) -> Path:
    """`folder / rel` for a folder of a run (the run folder, a stage's folder), refusing a `rel`
    that is absolute or leaves the folder ('..'), and a symbolic link at any component below
    `folder` (existing or not yet: the path need not exist). Paths named by artifacts and every
    file a command writes or deletes in a run folder go through here."""
    folder = Path(folder)
    text = rel.as_posix() if isinstance(rel, PurePosixPath | Path) else rel
    where = f" (named by {named_by})" if named_by else ""
    problem = relative_problem(text, folder="run folder", named_in="artifacts")
    if problem:
        raise PanoError(folder / "artifact.json" if named_by else folder, f"{shorten(str(text))} {problem}{where}")
    path = folder
    for part in PurePosixPath(text.replace("\\", "/")).parts:
        if part in ("", "."):
            continue
        path = path / part
        if path.is_symlink():
            raise PanoError(path, LINK_PROBLEM)
    return path


def open_run_folder(run_dir: Path, must_exist: bool = True) -> Path:
    """An existing run folder given to a command that reads it (export, view): a pano-pipe run
    folder holding no symbolic link."""
    run_dir = Path(run_dir)
    if not run_dir.exists():
        if must_exist:
            raise PanoError(run_dir, "no such run folder")
        return run_dir
    if not run_dir.is_dir():
        raise PanoError(run_dir, "not a folder (expected a pano-pipe run folder)")
    refuse_links(run_dir)
    return run_dir


def is_run_folder(path: Path) -> bool:
    """A folder pano-pipe made: it holds the marker (or, made before the marker existed, a run log
    and nothing but stage-like folders and run files)."""
    path = Path(path)
    if (path / RUN_MARKER).is_file():
        return True
    return (path / "run_log.jsonl").is_file() and (path / "run_log.jsonl").stat().st_size > 0


def mark_run_folder(out_dir: Path, scene_root: Path) -> None:
    """Create the run folder (if needed) and its marker."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    marker = out_dir / RUN_MARKER
    if not marker.is_file() or run_folder_scene(out_dir) is None:  # new, moved, or from before "run"
        record = {"made_by": "pano-pipe", "scene": str(Path(scene_root).resolve()), "run": str(out_dir.resolve())}
        atomic_write_text(marker, json.dumps(record) + "\n")


def run_folder_name(scene_name: str, scene_root: Path | None = None) -> str:
    """The name of a scene's run folder (runs/<name>/, a batch's OUT/<name>/): its scene name,
    which must be a safe stem. The name comes from scene.json, else from the folder's name, which
    nothing checked before (`scan 10:30`, `-x`, `.x`)."""
    problem = stem_problem(scene_name)
    if problem:
        raise PanoError(scene_root, f"the scene name {shorten(scene_name)} (scene.json \"name\", else the "
                                    f"folder's name) names its run folder, and it {problem}; set a \"name\" in "
                                    "scene.json (or give --out)")
    return scene_name


def default_run_folder(scene_name: str, scene_root: Path | None = None) -> Path:
    """runs/<scene-name>/ under the working folder (the name is a checked stem)."""
    return Path("runs") / run_folder_name(scene_name, scene_root)
