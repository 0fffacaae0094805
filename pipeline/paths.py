"""The one rule about paths (docs/security.md).

- Every path a scene names resolves inside the scene folder, after symlinks.
- View and scene names are safe file-name stems (they become file and folder names).
- Every path the pipeline writes resolves inside the run folder; the run folder
  and the scene folder never overlap; only a folder pano-pipe made (it holds the
  marker file) is ever written into, cleaned or replaced.

Everything else in pano-pipe goes through these functions rather than joining
user text onto paths itself.
"""

from __future__ import annotations

import json
import unicodedata
from pathlib import Path, PurePosixPath, PureWindowsPath

from pipeline.errors import PanoError

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


def relative_problem(rel: str) -> str | None:
    """Why `rel` is not a relative path that stays inside its folder (lexically), or None."""
    if not isinstance(rel, str) or not rel:
        return "must be a non-empty relative path"
    if "\x00" in rel:
        return "holds a NUL character"
    if PurePosixPath(rel).is_absolute() or PureWindowsPath(rel).is_absolute() or PureWindowsPath(rel).drive:
        return "is absolute; paths in scene.json are relative to the scene folder"
    depth = 0
    for part in PurePosixPath(rel.replace("\\", "/")).parts:
        depth += -1 if part == ".." else (0 if part == "." else 1)
        if depth < 0:
            return "leaves the scene folder ('..')"
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


def check_run_folder(out_dir: Path, scene_root: Path) -> Path:
    """Refuse a run folder that overlaps the scene folder, is a file, or is a
    non-empty folder pano-pipe did not make. Returns it unchanged."""
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
        marker.write_text(json.dumps({"made_by": "pano-pipe", "scene": str(Path(scene_root).resolve()),
                                      "run": str(out_dir.resolve())}) + "\n")


def default_run_folder(scene_name: str) -> Path:
    """runs/<scene-name>/ under the working folder (the name is a checked stem)."""
    return Path("runs") / safe_stem(scene_name)
