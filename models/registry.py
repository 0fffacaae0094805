"""Models pano-pipe knows how to get: where their authors publish them, under which licence,
and how a checkpoint becomes the ONNX file a stage runs (docs/layout.md, "Models").

A SHA-256 is recorded only where one is known without downloading the file; the authors of
HorizonNet and Depth Anything publish none, so those entries hold None and `models fetch`
prints the hash of what it downloaded and pins it in the cache (trust on first use).

More entries (a mirror, a lab's own checkpoint) come from a YAML or JSON file named by
$PANO_PIPE_MODELS_REGISTRY: a list of mappings with the fields of `KnownModel`.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Literal

from runfs.errors import PanoError

Kind = Literal["layout", "depth"]
Host = Literal["gdrive", "huggingface", "url"]

REGISTRY_ENV = "PANO_PIPE_MODELS_REGISTRY"

#: What turns a checkpoint of each kind into ONNX: "module:function", called as fn(checkpoint, out_onnx).
DEFAULT_EXPORTERS: dict[str, str] = {
    "layout": "layoutnet.export:export_checkpoint",
    "depth": "depthnet.depth_anything:export_onnx",
}
#: The only functions pano-pipe calls as an exporter: a registry entry names one of these, never any
#: other "module:function" (`os:system`, `shutil:copyfile` would run with the entry's file names).
ALLOWED_EXPORTERS = frozenset(DEFAULT_EXPORTERS.values())


@dataclass(frozen=True)
class KnownModel:
    name: str
    kind: Kind
    host: Host
    #: The download: a Google Drive file id, a Hugging Face "owner/repo", or a plain URL.
    source: str
    #: The file as published (and as it lies in the cache).
    filename: str
    licence: str
    #: Approximate download size in MB (None: unknown).
    size_mb: float | None
    #: SHA-256 of the published file, hex; None when it cannot be known without the file.
    sha256: str | None
    exporter: str
    description: str = ""

    @property
    def url(self) -> str:
        """Where a person downloads it by hand."""
        if self.host == "gdrive":
            return f"https://drive.google.com/file/d/{self.source}/view"
        if self.host == "huggingface":
            return f"https://huggingface.co/{self.source}/resolve/main/{self.filename}"
        return self.source

    @property
    def host_name(self) -> str:
        return {"gdrive": "Google Drive", "huggingface": "Hugging Face", "url": "URL"}[self.host]


_HORIZONNET_CODE = "HorizonNet code MIT"

BUILTIN: tuple[KnownModel, ...] = (
    # Google Drive ids as linked from HorizonNet's README.md, README_ZInD.md and README_MP3D.md
    # (github.com/sunset1995/HorizonNet). The four files share one architecture (ResNet-50 + LSTM);
    # ~327 MB (312 MiB): the size of that architecture saved as HorizonNet saves it (docs/layout.md).
    KnownModel(
        "horizonnet-zind", "layout", "gdrive", "1FrMdk7Z4_sTZOOW65Ek77WbjiDbV98uJ", "resnet50_rnn__zind.pth",
        f"{_HORIZONNET_CODE}; weights trained on ZInD (Zillow terms: non-commercial use)", 327.0, None,
        DEFAULT_EXPORTERS["layout"], "HorizonNet, ZInD (20k real homes; general room shapes)",
    ),
    KnownModel(
        "horizonnet-mp3d", "layout", "gdrive", "1uEEhPVw6VbjwW3lO4btb8zExV8NqojTB", "resnet50_rnn__mp3d.pth",
        f"{_HORIZONNET_CODE}; weights trained on MatterportLayout (Matterport3D terms: non-commercial "
        "academic use)", 327.0, None, DEFAULT_EXPORTERS["layout"],
        "HorizonNet, MatterportLayout (the 360-GS paper's data; general room shapes)",
    ),
    KnownModel(
        "horizonnet-st3d", "layout", "gdrive", "16v1nhL9C2VZX-qQpikCsS6LiMJn3q6gO", "resnet50_rnn__st3d.pth",
        f"{_HORIZONNET_CODE}; weights trained on Structured3D (see its terms of use)", 327.0, None,
        DEFAULT_EXPORTERS["layout"], "HorizonNet, Structured3D (synthetic rooms)",
    ),
    KnownModel(
        "horizonnet-panos2d3d", "layout", "gdrive", "1aieMd61b-3BoOeTRv2pKu9yTk5zEinn0",
        "resnet50_rnn__panos2d3d.pth",
        f"{_HORIZONNET_CODE}; weights trained on PanoContext + Stanford 2D-3D (see their terms)", 327.0, None,
        DEFAULT_EXPORTERS["layout"], "HorizonNet, PanoContext/Stanford2D3D (cuboid rooms)",
    ),
    KnownModel(
        "depth-anything-v2-small", "depth", "huggingface", "depth-anything/Depth-Anything-V2-Small",
        "depth_anything_v2_vits.pth", "Apache-2.0", 99.0, None, DEFAULT_EXPORTERS["depth"],
        "Depth Anything V2 Small (ViT-S, relative inverse depth)",
    ),
)

#: The layout model `status` suggests when none is present (real homes, general shapes).
RECOMMENDED = {"layout": "horizonnet-zind", "depth": "depth-anything-v2-small"}


def _extra_entries() -> list[KnownModel]:
    path = os.environ.get(REGISTRY_ENV)
    if not path:
        return []
    import yaml  # YAML is a superset of JSON

    p = Path(path).expanduser()
    try:
        raw = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise PanoError(p, f"cannot read the model registry (${REGISTRY_ENV}): {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise PanoError(p, f"not valid YAML/JSON: {' '.join(str(e).split())[:200]}") from None
    if not isinstance(raw, list):
        raise PanoError(p, "expected a list of models")
    names = {f.name for f in fields(KnownModel)}
    out = []
    for i, item in enumerate(raw):
        if not isinstance(item, dict):
            raise PanoError(p, f"entry {i}: expected a mapping")
        item = dict(item)
        item.setdefault("exporter", DEFAULT_EXPORTERS.get(item.get("kind"), ""))
        item.setdefault("sha256", None)
        item.setdefault("size_mb", None)
        item.setdefault("licence", "unknown")
        missing = sorted(names - set(item) - {"description"})
        unknown = sorted(set(item) - names)
        if missing or unknown:
            what = f"missing {', '.join(missing)}" if missing else f"unknown field(s) {', '.join(unknown)}"
            raise PanoError(p, f"entry {i}: {what}")
        if item["kind"] not in DEFAULT_EXPORTERS or item["host"] not in ("gdrive", "huggingface", "url"):
            raise PanoError(p, f"entry {i}: kind must be layout or depth, host gdrive, huggingface or url")
        problem = entry_problem(item)
        if problem:
            raise PanoError(p, f"entry {i}: {problem}")
        item["sha256"] = item["sha256"].lower() if item["sha256"] else None
        out.append(KnownModel(**item))
    return out


def entry_problem(item: dict) -> str | None:
    """Why a registry entry is not one pano-pipe may use, or None. Built-in entries meet it too:
    the name and the file name become file names in the model cache (safe stems: no `/`, no `..`),
    the exporter is one of ALLOWED_EXPORTERS, a plain URL is http(s)."""
    from runfs.paths import shorten, stem_problem

    for key in ("name", "filename", "source", "licence", "description"):
        if key in item and not isinstance(item[key], str):
            return f"{key} must be text"
    for key in ("name", "filename"):
        problem = stem_problem(item[key])
        if problem:
            return f"{key} {shorten(item[key])} names a file in the model cache, and it {problem}"
    if item["exporter"] not in ALLOWED_EXPORTERS:
        return (f"exporter {shorten(str(item['exporter']))} is not one pano-pipe calls; "
                f"choose {' or '.join(sorted(ALLOWED_EXPORTERS))}")
    if item["host"] == "url" and not item["source"].lower().startswith(("https://", "http://")):
        return f"source {shorten(item['source'])} must be an http(s) URL"
    size = item.get("size_mb")
    if size is not None and (isinstance(size, bool) or not isinstance(size, int | float) or not 0 < size < 1e6):
        return "size_mb must be a positive number of megabytes or null"
    sha = item.get("sha256")
    if sha is not None and not (isinstance(sha, str) and len(sha) == 64
                                and all(c in "0123456789abcdef" for c in sha.lower())):
        return "sha256 must be 64 hex digits or null"
    return None


def known_models(kind: str | None = None) -> dict[str, KnownModel]:
    """Every known model (built in, then $PANO_PIPE_MODELS_REGISTRY's, which may replace one)."""
    models = {m.name: m for m in (*BUILTIN, *_extra_entries())}
    return {n: m for n, m in models.items() if kind is None or m.kind == kind}


def get_model(name: str, kind: str | None = None) -> KnownModel:
    models = known_models()
    if name not in models:
        choices = ", ".join(n for n, m in models.items() if kind is None or m.kind == kind)
        raise PanoError(name, f"unknown model; known{' ' + kind if kind else ''} models: {choices}")
    entry = models[name]
    if kind is not None and entry.kind != kind:
        raise PanoError(name, f"a {entry.kind} model, not a {kind} model")
    return entry


def as_dict(entry: KnownModel) -> dict:
    return {**asdict(entry), "url": entry.url}
