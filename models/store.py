"""The user's model cache and the resolution of a model setting to the ONNX file a stage runs.

Cache ($PANO_PIPE_MODELS_DIR, else $XDG_CACHE_HOME/pano-pipe/models, else
~/.cache/pano-pipe/models), nothing of it inside a scene or run folder:

    <cache>/<filename>                 a known model's checkpoint, as published
    <cache>/<name>.onnx                its ONNX export (made once, kept beside it)
    <cache>/<name>.json                what was fetched: source, SHA-256 (pinned on first fetch)
    <cache>/exported/<kind>-<sha16>.onnx   the export of a user's own .pth, by content hash
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import tempfile
from pathlib import Path

from models.registry import DEFAULT_EXPORTERS, KnownModel, get_model, known_models
from runfs.errors import PanoError

CACHE_ENV = "PANO_PIPE_MODELS_DIR"
CHECKPOINT_SUFFIXES = (".pth", ".pt", ".ckpt")


def cache_dir() -> Path:
    """Where downloaded models live (DESIGN.md); $PANO_PIPE_MODELS_DIR overrides it."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or "~/.cache"
    return Path(base).expanduser() / "pano-pipe" / "models"


def checkpoint_path(entry: KnownModel) -> Path:
    return cache_dir() / entry.filename


def onnx_path(entry: KnownModel) -> Path:
    return cache_dir() / f"{entry.name}.onnx"


def record_path(entry: KnownModel) -> Path:
    return cache_dir() / f"{entry.name}.json"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_record(entry: KnownModel) -> dict:
    try:
        return json.loads(record_path(entry).read_text())
    except (OSError, ValueError):
        return {}


def expected_sha256(entry: KnownModel) -> str | None:
    """The registry's hash, else the one pinned when the file was first fetched."""
    return entry.sha256 or read_record(entry).get("sha256")


def is_present(entry: KnownModel) -> bool:
    """Ready to use without a download: the export or the checkpoint is in the cache."""
    return onnx_path(entry).is_file() or checkpoint_path(entry).is_file()


def missing_message(entry: KnownModel) -> str:
    """One line: how to get the file (the command, or by hand from where to where)."""
    return (f"model {entry.name} is not downloaded: run `pano-pipe models fetch {entry.name}`, or download "
            f"{entry.filename} from {entry.url} and put it at {checkpoint_path(entry)}")


def load_exporter(spec: str):
    module, _, func = spec.partition(":")
    try:
        return getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as e:
        raise PanoError(spec, f"model exporter not available: {e}") from None


def export(checkpoint: Path, out: Path, exporter: str) -> Path:
    """checkpoint → ONNX at `out`, written beside it under a temporary name and renamed into place,
    so an interrupted export never leaves a half file that a later run would take for a model."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fn = load_exporter(exporter)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".onnx", dir=out.parent)
    os.close(fd)
    try:
        fn(checkpoint, Path(tmp))
        os.replace(tmp, out)
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
    """The known model's ONNX file, exporting its cached checkpoint once; PanoError when absent."""
    onnx = onnx_path(entry)
    if onnx.is_file():
        return onnx
    ckpt = checkpoint_path(entry)
    if not ckpt.is_file():
        raise PanoError(ckpt, missing_message(entry))
    digest = verify(entry, ckpt)
    from pipeline.console import console

    console.print(f"exporting {entry.name} to ONNX (once; kept at {onnx})", soft_wrap=True)
    export(ckpt, onnx, entry.exporter)
    write_record(entry, digest)
    return onnx


def write_record(entry: KnownModel, digest: str) -> None:
    rec = {"name": entry.name, "kind": entry.kind, "source": entry.url, "filename": entry.filename,
           "sha256": digest, "sha256_published": entry.sha256 is not None, "exporter": entry.exporter}
    record_path(entry).write_text(json.dumps(rec, indent=2) + "\n")


def _export_user_checkpoint(path: Path, kind: str) -> Path:
    """A user's own checkpoint, exported once into the cache under its content hash."""
    out = cache_dir() / "exported" / f"{kind}-{sha256_file(path)[:16]}.onnx"
    if not out.is_file():
        from pipeline.console import console

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
