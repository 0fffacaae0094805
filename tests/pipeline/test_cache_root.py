"""One cache root for the compiled kernel and the models: $PANO_PIPE_CACHE, else
$XDG_CACHE_HOME/pano-pipe, else ~/.cache/pano-pipe."""

from __future__ import annotations

from pathlib import Path

from models.store import cache_dir
from splatting import raster_cpp


def test_the_kernel_and_the_models_follow_xdg_cache_home(tmp_path, monkeypatch):
    monkeypatch.delenv("PANO_PIPE_CACHE", raising=False)
    monkeypatch.delenv("PANO_PIPE_MODELS_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert raster_cpp.build_dir().parent == tmp_path / "xdg" / "pano-pipe"
    assert raster_cpp.build_dir().name.startswith("splatting-")
    assert cache_dir() == tmp_path / "xdg" / "pano-pipe" / "models"


def test_pano_pipe_cache_moves_both_and_models_dir_only_the_models(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("PANO_PIPE_CACHE", str(tmp_path / "mine"))
    monkeypatch.delenv("PANO_PIPE_MODELS_DIR", raising=False)
    assert raster_cpp.build_dir().parent == tmp_path / "mine"
    assert cache_dir() == tmp_path / "mine" / "models"
    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(tmp_path / "models"))
    assert cache_dir() == tmp_path / "models" and raster_cpp.build_dir().parent == tmp_path / "mine"


def test_without_either_the_cache_is_under_home(tmp_path, monkeypatch):
    for name in ("PANO_PIPE_CACHE", "XDG_CACHE_HOME", "PANO_PIPE_MODELS_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert raster_cpp.build_dir().parent == Path(tmp_path) / ".cache" / "pano-pipe"
    assert cache_dir() == Path(tmp_path) / ".cache" / "pano-pipe" / "models"
