"""The envelope every stage artifact shares: `artifact.json` = {meta, data}."""

from __future__ import annotations

from datetime import datetime
from typing import Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

T = TypeVar("T", bound=BaseModel)


class ArtifactMeta(BaseModel):
    """What the engine needs to decide whether a stage is up to date."""

    model_config = ConfigDict(extra="forbid")

    stage: str
    key: str = Field(description="Hash of scene inputs, parameters, code version and upstream keys.")
    scene_hash: str
    params: dict = Field(description="The stage parameters the artifact was made with.")
    code_version: str
    upstream: dict[str, str] = Field(description="Upstream stage -> its key, or 'skipped'.")
    created: datetime
    duration_s: float
    warnings: list[str] = Field(default_factory=list)
    files: dict[str, int] = Field(
        default_factory=dict, description="Every file the stage wrote (relative path -> bytes): checked before reuse."
    )


class Artifact(BaseModel, Generic[T]):
    """`<run>/<stage>/artifact.json`; file paths inside `data` are relative to the stage folder."""

    model_config = ConfigDict(extra="forbid")

    schema_version: Literal[1] = 1
    meta: ArtifactMeta
    data: T
