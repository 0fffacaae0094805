"""Pydantic v2 models of the scene manifest and every stage artifact."""

from __future__ import annotations

from pydantic import BaseModel


def all_schemas() -> dict[str, type[BaseModel]]:
    """Name -> model, for `pano-pipe schema DIR` (artifacts wrapped in their envelope)."""
    from pipeline.registry import build_registry
    from schemas.artifact import Artifact
    from schemas.scene import SceneManifest

    out: dict[str, type[BaseModel]] = {"scene": SceneManifest}
    for name, spec in build_registry().items():
        out[f"{name}.artifact"] = Artifact[spec.output]
    return out
