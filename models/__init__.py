"""Models pano-pipe can fetch (layout, depth): registry, user cache, resolution of a model setting."""

from models.registry import KnownModel, get_model, known_models
from models.store import cache_dir, cached_model, missing_message, resolve_model

__all__ = ["KnownModel", "get_model", "known_models", "cache_dir", "cached_model", "missing_message",
           "resolve_model"]
