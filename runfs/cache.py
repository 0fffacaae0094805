"""The one place that decides where pano-pipe keeps its per-user cache (the compiled kernel,
downloaded models): `$PANO_PIPE_CACHE`, else `$XDG_CACHE_HOME/pano-pipe`, else
`~/.cache/pano-pipe` (the XDG base directory rule)."""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "PANO_PIPE_CACHE"


def user_cache_root() -> Path:
    """The cache root (nothing of it inside a scene or run folder)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "pano-pipe"
