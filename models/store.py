"""The user's model cache and the resolution of a model setting to the ONNX file a stage runs.

Cache ($PANO_PIPE_MODELS_DIR, else `models/` in the cache root of runfs.cache:
$PANO_PIPE_CACHE, $XDG_CACHE_HOME/pano-pipe or ~/.cache/pano-pipe), nothing of it inside a
scene or run folder:

    <cache>/<filename>                 a known model's checkpoint, as published
    <cache>/<name>.onnx                its ONNX export (made once, kept beside it)
    <cache>/<name>.json                what was fetched: source, SHA-256 (pinned on first fetch),
                                       and the SHA-256 of the ONNX export
    <cache>/exported/<kind>-<sha16>.onnx   the export of a user's own .pth, by content hash

A cached file is trusted only while its hash matches: the checkpoint's the registry's (or the
pinned) one, the export's the one recorded when it was made. A truncated or altered file is not
"present"; `models fetch` replaces it, a run says how to.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import tempfile
from pathlib import Path

from models.registry import ALLOWED_EXPORTERS, DEFAULT_EXPORTERS, KnownModel, get_model, known_models
from runfs.errors import PanoError

CACHE_ENV = "PANO_PIPE_MODELS_DIR"
CHECKPOINT_SUFFIXES = (".pth", ".pt", ".ckpt")


def cache_dir() -> Path:
    """Where downloaded models live (DESIGN.md): `models/` in the cache root (runfs.cache);
    $PANO_PIPE_MODELS_DIR overrides it."""
    from runfs.cache import user_cache_root

    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    return user_cache_root() / "models"


def make_cache_dir(sub: str = "") -> Path:
    """The cache folder (or `sub` inside it), made if needed; one line when the place is taken by a
    file or a link to nothing (mkdir would only say "File exists")."""
    folder = cache_dir() / sub if sub else cache_dir()
    for p in (cache_dir(), folder):
        if p.is_symlink() and not p.exists():
            raise PanoError(p, f"the model cache is a symbolic link to {os.readlink(p)}, which does not exist "
                               f"(set ${CACHE_ENV} to a folder)")
        if p.exists() and not p.is_dir():
            raise PanoError(p, f"the model cache must be a folder, this is a file (set ${CACHE_ENV} to a folder)")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _cache_file(name: str) -> Path:
    """A file directly in the cache; registry entries are checked, this keeps it so for any caller."""
    from runfs.paths import stem_problem

    if stem_problem(name):
        raise PanoError(name, f"not a file name in the model cache: it {stem_problem(name)}")
    return cache_dir() / name


def checkpoint_path(entry: KnownModel) -> Path:
    return _cache_file(entry.filename)


def onnx_path(entry: KnownModel) -> Path:
    return _cache_file(f"{entry.name}.onnx")


def record_path(entry: KnownModel) -> Path:
    return _cache_file(f"{entry.name}.json")


_hashes: dict[tuple, str] = {}


def sha256_file(path: Path) -> str:
    """The file's SHA-256, remembered for this process while its size and time stay the same
    (`status` and `models list` ask about every cached model)."""
    st = os.stat(path)
    key = (str(Path(path).resolve()), st.st_size, st.st_mtime_ns, st.st_ino)
    if key not in _hashes:
        from runfs.fsutil import sha256_file as digest

        _hashes[key] = digest(path)
    return _hashes[key]


def read_record(entry: KnownModel) -> dict:
    try:
        return json.loads(record_path(entry).read_text())
    except (OSError, ValueError):
        return {}


def expected_sha256(entry: KnownModel) -> str | None:
    """The registry's hash, else the one pinned when the file was first fetched."""
    return entry.sha256 or read_record(entry).get("sha256")


def checkpoint_problem(entry: KnownModel) -> str | None:
    """Why the cached checkpoint cannot be used ('not downloaded', a hash that differs), or None."""
    path = checkpoint_path(entry)
    if not path.is_file():
        return "not downloaded"
    want = expected_sha256(entry)
    if want is not None and (got := sha256_file(path)) != want:
        return f"SHA-256 {got} does not match {want} (truncated or altered)"
    return None


def onnx_problem(entry: KnownModel) -> str | None:
    """Why the cached ONNX export cannot be used (absent, or not the file that was exported), or None."""
    path = onnx_path(entry)
    if not path.is_file():
        return "not exported"
    want = read_record(entry).get("onnx_sha256")
    if want is None:
        return "no record of its export (made by an older pano-pipe, or not by pano-pipe)"
    if (got := sha256_file(path)) != want:
        return f"SHA-256 {got} does not match the export's {want} (truncated or altered)"
    return None


def is_present(entry: KnownModel) -> bool:
    """Ready to use without a download: a verified export or a verified checkpoint is in the cache."""
    return onnx_problem(entry) is None or checkpoint_problem(entry) is None


def missing_message(entry: KnownModel) -> str:
    """One line: how to get the file (the command, or by hand from where to where)."""
    return (f"model {entry.name} is not downloaded: run `pano-pipe models fetch {entry.name}`, or download "
            f"{entry.filename} from {entry.url} and put it at {checkpoint_path(entry)}")


def load_exporter(spec: str):
    if spec not in ALLOWED_EXPORTERS:  # registry entries are checked; this holds for any caller
        raise PanoError(spec, f"not a model exporter pano-pipe calls ({', '.join(sorted(ALLOWED_EXPORTERS))})")
    module, _, func = spec.partition(":")
    try:
        return getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as e:
        raise PanoError(spec, f"model exporter not available: {e}") from None


def export(checkpoint: Path, out: Path, exporter: str) -> Path:
    """checkpoint → ONNX at `out`, written beside it under a temporary name and renamed into place,
    so an interrupted export never leaves a half file that a later run would take for a model."""
    fn = load_exporter(exporter)
    made = not out.parent.exists()
    make_cache_dir(out.parent.name if out.parent != cache_dir() else "")
    fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".onnx", dir=out.parent)
    os.close(fd)
    try:
        fn(checkpoint, Path(tmp))
        os.replace(tmp, out)
    except BaseException:
        if made:  # a failed export leaves nothing in the cache, not even the folder it made
            Path(tmp).unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                out.parent.rmdir()
        raise
    finally:
        Path(tmp).unlink(missing_ok=True)
    return out


def verify(entry: KnownModel, path: Path) -> str:
    """The file's SHA-256, raising (and naming both hashes) when it differs from the expected one."""
    digest = sha256_file(path)
    want = expected_sha256(entry)
    if want is not None and digest != want:
        pinned = "" if entry.sha256 else " (pinned at its first fetch; `models fetch --force` replaces it)"
        raise PanoError(path, f"SHA-256 {digest} does not match {entry.name}'s {want}{pinned}")
    return digest


def ensure_onnx(entry: KnownModel) -> Path:
    """The known model's ONNX file, verified, exporting its cached checkpoint once (again when the
    export is not the file that was made); PanoError when neither is usable."""
    onnx = onnx_path(entry)
    if onnx_problem(entry) is None:
        return onnx
    ckpt = checkpoint_path(entry)
    if not ckpt.is_file():
        if onnx.is_file():
            raise PanoError(onnx, f"{onnx_problem(entry)}; run `pano-pipe models fetch {entry.name}` to replace it")
        raise PanoError(ckpt, missing_message(entry))
    digest = verify(entry, ckpt)
    from runtime.console import console

    console.print(f"exporting {entry.name} to ONNX (once; kept at {onnx})", soft_wrap=True)
    export(ckpt, onnx, entry.exporter)
    write_record(entry, digest)
    return onnx


def write_record(entry: KnownModel, digest: str) -> None:
    """What was fetched and exported: the checkpoint's hash (pinned) and the export's (checked on use)."""
    from runfs.fsutil import atomic_write_text

    onnx = onnx_path(entry)
    rec = {"name": entry.name, "kind": entry.kind, "source": entry.url, "filename": entry.filename,
           "sha256": digest, "sha256_published": entry.sha256 is not None, "exporter": entry.exporter,
           "onnx_sha256": sha256_file(onnx) if onnx.is_file() else None}
    atomic_write_text(record_path(entry), json.dumps(rec, indent=2) + "\n")


def _export_user_checkpoint(path: Path, kind: str) -> Path:
    """A user's own checkpoint, exported once into the cache under its content hash."""
    out = cache_dir() / "exported" / f"{kind}-{sha256_file(path)[:16]}.onnx"
    if not out.is_file():
        from runtime.console import console

        console.print(f"exporting {path} to ONNX (once; kept at {out})", soft_wrap=True)
        export(path, out, DEFAULT_EXPORTERS[kind])
    return out


def _find_file(value: str, search: tuple[Path, ...]) -> Path | None:
    given = Path(value).expanduser()
    for candidate in [given] if given.is_absolute() else [given, *(d / given for d in search)]:
        if candidate.is_file():
            return candidate.resolve()
    return None


def resolve_model(value: str | Path, kind: str, search: tuple[Path, ...] = ()) -> Path:
    """A model setting → the ONNX file to run. `value` is a known name (`pano-pipe models list`), a
    checkpoint (.pth/.pt/.ckpt; exported on first use, cached by content hash) or an .onnx file.
    A relative path is tried from the working folder, then from each of `search` (the scene folder)."""
    if kind not in DEFAULT_EXPORTERS:
        raise ValueError(f"unknown model kind {kind!r}")
    text = str(value)
    if text in known_models():
        return ensure_onnx(get_model(text, kind))
    path = Path(text)
    if path.suffix.lower() not in (".onnx", *CHECKPOINT_SUFFIXES):
        if len(path.parts) == 1 and not path.suffix:  # meant as a name
            get_model(text, kind)  # raises, listing the known names
        raise PanoError(text, f"expected a known {kind} model name, a checkpoint (.pth) or an .onnx file")
    found = _find_file(text, search)
    if found is None:
        where = "the working folder" + "".join(f" and {d}" for d in search)
        raise PanoError(text, f"{kind} model file does not exist (looked in {where})")
    if found.suffix.lower() == ".onnx":
        return found
    return _export_user_checkpoint(found, kind)


def cached_model(kind: str) -> KnownModel | None:
    """The first known model of `kind` that is in the cache (recommended one first), or None."""
    from models.registry import RECOMMENDED

    models = known_models(kind)
    order = sorted(models, key=lambda n: (n != RECOMMENDED.get(kind), list(models).index(n)))
    return next((models[n] for n in order if is_present(models[n])), None)


def known_name(path: Path) -> str | None:
    """The known model whose cached ONNX file `path` is, else None."""
    try:
        resolved = Path(path).resolve()
    except OSError:
        return None
    return next((e.name for e in known_models().values() if onnx_path(e).resolve() == resolved), None)


def model_label(path: Path) -> str:
    """How a stage names the model it runs: 'NAME (path)' for a known model, else the path."""
    name = known_name(Path(path))
    return f"{name} ({path})" if name else str(path)


def fetch_hint(kind: str) -> str:
    """The one-line advice when no `kind` model is at hand: the command that gets the recommended one."""
    from models.registry import RECOMMENDED

    return f"get one: pano-pipe models fetch {RECOMMENDED[kind]}"
