"""`pano-pipe models`: fetch from a local HTTP server (no network), hash checks, the offline
message, export once, and `run all` using the fetched model on a scene without layout files."""

from __future__ import annotations

import hashlib
import http.server
import json
import os
import socket
import threading
from collections import OrderedDict
from functools import partial
from pathlib import Path

import pytest
import torch
import yaml

from layoutnet.model import HorizonNet
from runfs.errors import PanoError
from tests.clitools import invoke

torch.set_num_threads(2)


def _save_standin(path: Path) -> Path:
    """HorizonNet's architecture at 1/16 of the channels, random weights, saved as its train.py does."""
    torch.manual_seed(0)
    net = HorizonNet("resnet50", use_rnn=True, width=4, rnn_hidden=16)
    torch.save(OrderedDict({"args": {"id": "standin"}, "kwargs": {"backbone": "resnet50", "use_rnn": True},
                            "state_dict": net.state_dict()}), path)
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Server:
    def __init__(self, folder: Path):
        self.folder = folder
        self.requests: list[str] = []
        outer = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args):  # quiet; count the requests instead
                outer.requests.append(self.path)

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), partial(Handler, directory=str(folder)))
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """The stand-in checkpoint on a local HTTP server: (server, its SHA-256)."""
    folder = tmp_path_factory.mktemp("server")
    ck = _save_standin(folder / "standin.pth")
    server = _Server(folder)
    yield server, hashlib.sha256(ck.read_bytes()).hexdigest()
    server.close()


@pytest.fixture
def registry(served, tmp_path, monkeypatch):
    """An empty model cache and a registry with the stand-in (right hash, wrong hash, no hash,
    and a server that is not there)."""
    server, sha = served
    entries = [
        {"name": "horizonnet-standin", "kind": "layout", "host": "url", "source": f"{server.url}/standin.pth",
         "filename": "standin.pth", "licence": "MIT (test)", "size_mb": 1.0, "sha256": sha},
        {"name": "horizonnet-badhash", "kind": "layout", "host": "url", "source": f"{server.url}/standin.pth",
         "filename": "badhash.pth", "sha256": "0" * 64},
        {"name": "horizonnet-nohash", "kind": "layout", "host": "url", "source": f"{server.url}/standin.pth",
         "filename": "nohash.pth"},
        {"name": "horizonnet-offline", "kind": "layout", "host": "url",
         "source": f"http://127.0.0.1:{_free_port()}/standin.pth", "filename": "offline.pth", "sha256": sha},
    ]
    reg = tmp_path / "registry.yaml"
    reg.write_text(yaml.safe_dump(entries))
    cache = tmp_path / "cache"
    monkeypatch.setenv("PANO_PIPE_MODELS_REGISTRY", str(reg))
    monkeypatch.setenv("PANO_PIPE_MODELS_DIR", str(cache))
    server.requests.clear()
    return cache, sha, server


def test_fetch_checks_the_hash_exports_once_and_keeps_both(registry):
    from models.download import fetch
    from models.store import resolve_model

    cache, sha, server = registry
    log: list[str] = []
    got = fetch("horizonnet-standin", log=log.append)
    assert got.downloaded and got.exported and got.sha256 == sha
    assert got.checkpoint == cache / "standin.pth" and got.checkpoint.is_file()
    assert got.onnx == cache / "horizonnet-standin.onnx" and got.onnx.is_file()
    assert json.loads((cache / "horizonnet-standin.json").read_text())["sha256"] == sha
    assert any(f"SHA-256 {sha} verified" in m for m in log)
    assert server.requests == ["/standin.pth"]
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]  # no temporary leftovers

    stamp = got.onnx.stat().st_mtime_ns
    again = fetch("horizonnet-standin", log=log.append)
    assert not again.downloaded and not again.exported and server.requests == ["/standin.pth"]
    assert resolve_model("horizonnet-standin", "layout") == got.onnx
    assert got.onnx.stat().st_mtime_ns == stamp  # exported once


def test_cli_list_fetch_path(registry, capsys):
    cache, sha, _ = registry
    code, out, err = invoke(["models", "list"], capsys)
    text = " ".join(out.split())
    assert code == 0 and "horizonnet-zind" in text and "depth-anything-v2-small" in text and "Apache-2.0" in text
    code, out, err = invoke(["models", "path", "horizonnet-standin"], capsys)
    assert code == 2 and "pano-pipe models fetch horizonnet-standin" in err and "\n" not in err.strip()
    code, out, err = invoke(["models", "fetch", "horizonnet-standin"], capsys)
    assert code == 0, err
    assert sha in out.replace("\n", "")
    code, out, err = invoke(["models", "path", "horizonnet-standin"], capsys)
    assert code == 0 and out.strip() == str(cache / "horizonnet-standin.onnx")


def test_wrong_hash_is_refused_and_nothing_kept(registry):
    from models.download import fetch

    cache, _, _ = registry
    with pytest.raises(PanoError, match="does not match 0000") as e:
        fetch("horizonnet-badhash", log=lambda m: None)
    assert "\n" not in str(e.value)
    assert not (cache / "badhash.pth").exists() and not (cache / "horizonnet-badhash.onnx").exists()
    assert [p.name for p in cache.iterdir()] == []


def test_unpublished_hash_is_pinned_at_the_first_fetch(registry):
    from models.download import fetch
    from models.store import resolve_model

    cache, sha, _ = registry
    log: list[str] = []
    got = fetch("horizonnet-nohash", log=log.append)
    assert got.sha256 == sha and any("pinned" in m for m in log)
    # the checkpoint changes behind our back: its export is redone only after a hash check
    got.onnx.unlink()
    with open(got.checkpoint, "ab") as f:
        f.write(b"tampered")
    with pytest.raises(PanoError, match="does not match .*pinned at its first fetch"):
        resolve_model("horizonnet-nohash", "layout")


def test_offline_message_names_the_file_the_source_and_the_place(registry, capsys):
    from models.download import fetch
    from models.store import resolve_model

    cache, _, _ = registry
    with pytest.raises(PanoError) as e:
        fetch("horizonnet-offline", log=lambda m: None)
    msg = str(e.value)
    assert "cannot download offline.pth" in msg and "127.0.0.1" in msg and str(cache / "offline.pth") in msg
    # a known model that is not in the cache: the command, the source and the place, in one line
    with pytest.raises(PanoError) as e:
        resolve_model("horizonnet-zind", "layout")
    msg = str(e.value)
    assert "pano-pipe models fetch horizonnet-zind" in msg and "resnet50_rnn__zind.pth" in msg
    assert "drive.google.com" in msg and str(cache / "resnet50_rnn__zind.pth") in msg and "\n" not in msg
    code, out, err = invoke(["models", "fetch", "horizonnet-offline"], capsys)
    assert code == 2 and err.startswith("error:") and len(err.strip().splitlines()) == 1


def test_resolve_names_checkpoints_and_onnx_files(registry, tmp_path):
    from models.store import resolve_model

    cache, _, server = registry
    ck = _save_standin(tmp_path / "mine.pth")
    onnx = resolve_model(ck, "layout")
    assert onnx.parent == cache / "exported" and onnx.name.startswith("layout-") and onnx.is_file()
    stamp = onnx.stat().st_mtime_ns
    assert resolve_model(str(ck), "layout") == onnx and onnx.stat().st_mtime_ns == stamp  # cached by content
    # a relative path is looked up in the search folders (the scene folder)
    assert resolve_model("mine.pth", "layout", search=(tmp_path,)) == onnx
    assert resolve_model(onnx, "layout") == onnx
    with pytest.raises(PanoError, match="unknown model; known layout models: .*horizonnet-zind"):
        resolve_model("horizonnet-zin", "layout")
    with pytest.raises(PanoError, match="a depth model, not a layout model"):
        resolve_model("depth-anything-v2-small", "layout")
    with pytest.raises(PanoError, match="does not exist"):
        resolve_model(tmp_path / "nope.onnx", "layout")
    assert server.requests == []


def test_run_all_uses_the_fetched_model_on_a_scene_without_layout_files(registry, tmp_path, capsys):
    from simulate.generate import generate_scene

    cache, _, _ = registry
    scene = tmp_path / "S"
    generate_scene(scene, views=2, test_views=1, height=32, effects="none")
    assert not (scene / "layout").exists()
    code, out, _ = invoke(["status", scene, "--out", tmp_path / "R0"], capsys)
    assert code == 0 and "pano-pipe models fetch horizonnet-zind" in " ".join(out.split())
    code, out, _ = invoke(["run", "layout", scene, "--out", tmp_path / "R0"], capsys)  # the run header says it
    assert code == 0 and "have no layout file and no layout model" in " ".join(out.split())

    assert invoke(["models", "fetch", "horizonnet-standin"], capsys)[0] == 0
    code, out, _ = invoke(["status", scene, "--out", tmp_path / "R"], capsys)
    text = " ".join(out.split())
    # the layout hint is gone (the depth stage still says how to get a depth model)
    assert code == 0 and "model horizonnet-standin" in text and "models fetch horizonnet" not in text
    code, out, err = invoke(["run", "all", scene, "--out", tmp_path / "R", "--set", "train.iterations=3",
                             "--set", "train.height=8", "--set", "evaluate.lpips=false"], capsys)
    assert code == 0, err
    art = json.loads((tmp_path / "R" / "layout" / "artifact.json").read_text())["data"]
    assert art["model_name"] == "horizonnet-standin"
    assert art["model"] == str(cache / "horizonnet-standin.onnx")
    assert {v["source"] for v in art["views"]} == {"model"}
    assert all(v["alignment"] is not None for v in art["views"])
    assert (tmp_path / "R" / "train" / "artifact.json").is_file()


def test_google_drive_and_hugging_face_go_through_their_clients(registry, tmp_path, monkeypatch):
    """The built-in HorizonNet entry calls gdown with the authors' file id; a Hugging Face entry
    calls hf_hub_download with repo and file name (the clients stubbed: no network here)."""
    import gdown
    import huggingface_hub

    from models.download import fetch

    cache, sha, _ = registry
    standin = _save_standin(tmp_path / "standin.pth")
    calls = []

    def fake_gdown(id=None, output=None, quiet=False, **kw):
        calls.append(("gdrive", id, Path(output).name))
        Path(output).write_bytes(standin.read_bytes())
        return output

    def fake_hf(repo_id, filename, local_dir=None, **kw):
        calls.append(("hf", repo_id, filename))
        out = Path(local_dir) / filename
        out.write_bytes(standin.read_bytes())
        return str(out)

    monkeypatch.setattr(gdown, "download", fake_gdown)
    monkeypatch.setattr(huggingface_hub, "hf_hub_download", fake_hf)
    monkeypatch.setattr("models.download.check_reachable", lambda host, port: None)  # the hosts "answer"
    got = fetch("horizonnet-zind", log=lambda m: None)
    assert calls == [("gdrive", "1FrMdk7Z4_sTZOOW65Ek77WbjiDbV98uJ", "resnet50_rnn__zind.pth")]
    assert got.checkpoint == cache / "resnet50_rnn__zind.pth" and got.onnx.is_file() and got.sha256 == sha

    reg = Path(os.environ["PANO_PIPE_MODELS_REGISTRY"])
    entries = yaml.safe_load(reg.read_text()) + [
        {"name": "horizonnet-hf", "kind": "layout", "host": "huggingface", "source": "someone/horizonnet",
         "filename": "hf.pth", "sha256": sha}]
    reg.write_text(yaml.safe_dump(entries))
    got = fetch("horizonnet-hf", log=lambda m: None)
    assert calls[-1] == ("hf", "someone/horizonnet", "hf.pth") and got.onnx.is_file()
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]


def test_a_download_that_is_not_a_checkpoint_is_not_kept(registry, served):
    from models.download import fetch

    cache, _, server = registry
    page = server.folder / "quota.html"
    page.write_text("<html>Too many users have viewed or downloaded this file recently</html>")
    reg = Path(os.environ["PANO_PIPE_MODELS_REGISTRY"])
    reg.write_text(yaml.safe_dump(yaml.safe_load(reg.read_text()) + [
        {"name": "horizonnet-page", "kind": "layout", "host": "url", "source": f"{server.url}/quota.html",
         "filename": "page.pth"}]))
    with pytest.raises(PanoError, match="not a readable PyTorch checkpoint.*the download was removed"):
        fetch("horizonnet-page", log=lambda m: None)
    assert not (cache / "page.pth").exists() and not (cache / "horizonnet-page.onnx").exists()


def test_a_missing_exporter_is_said_before_any_download(registry):
    from models.download import fetch

    cache, _, server = registry
    reg = Path(os.environ["PANO_PIPE_MODELS_REGISTRY"])
    reg.write_text(yaml.safe_dump(yaml.safe_load(reg.read_text()) + [
        {"name": "horizonnet-noexport", "kind": "layout", "host": "url", "source": f"{server.url}/standin.pth",
         "filename": "noexport.pth", "exporter": "layoutnet.nowhere:export"}]))
    with pytest.raises(PanoError, match="exporter 'layoutnet.nowhere:export' is not one pano-pipe calls"):
        fetch("horizonnet-noexport", log=lambda m: None)
    assert server.requests == [] and not (cache / "noexport.pth").exists()


def _add_entries(*entries) -> None:
    reg = Path(os.environ["PANO_PIPE_MODELS_REGISTRY"])
    reg.write_text(yaml.safe_dump(yaml.safe_load(reg.read_text()) + list(entries)))


@pytest.mark.parametrize("name, host", [("horizonnet-zind", "drive.google.com"),
                                        ("horizonnet-hf", "huggingface.co"),
                                        ("horizonnet-web", "models.example.org")])
def test_fetch_without_network_is_one_whole_line_at_once(registry, monkeypatch, capsys, name, host):
    """Issue 36: offline, `models fetch` printed twelve lines (the client's retries) and a sentence cut
    in the middle. The network is made to fail as offline (no name resolves): one line on stderr,
    whole (it ends with where to put the file), said before any client is called."""
    import time

    import gdown
    import huggingface_hub
    import pooch

    cache, sha, _ = registry
    _add_entries({"name": "horizonnet-hf", "kind": "layout", "host": "huggingface", "source": "someone/horizonnet",
                  "filename": "hf.pth", "sha256": sha},
                 {"name": "horizonnet-web", "kind": "layout", "host": "url",
                  "source": "https://models.example.org/web.pth", "filename": "web.pth", "sha256": sha})

    def offline(*args, **kwargs):
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", offline)
    for module, fn in ((gdown, "download"), (huggingface_hub, "hf_hub_download"), (pooch, "retrieve")):
        monkeypatch.setattr(module, fn, lambda *a, **k: pytest.fail("a client was called offline"))
    t0 = time.perf_counter()
    code, out, err = invoke(["models", "fetch", name], capsys)
    assert time.perf_counter() - t0 < 10  # no retries first
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    line = " ".join(err.split())
    filename = {"horizonnet-zind": "resnet50_rnn__zind.pth", "horizonnet-hf": "hf.pth",
                "horizonnet-web": "web.pth"}[name]
    assert line.startswith("error: ") and f"cannot download {filename}: no network: the name {host} does not resolve" \
        in line
    assert line.endswith(f"put it at {cache / filename}")  # whole: the sentence ends where it should
    assert "Retry" not in err and not list(cache.glob(".fetch-*"))


def test_the_clients_retry_chatter_is_not_shown(registry, monkeypatch):
    """Where the host is not checked first (behind a proxy), Hugging Face's client retries five times
    and logs each retry: those records are dropped, the failure is one line in words."""
    import logging

    import huggingface_hub.utils._http as hf_http

    from models.download import fetch

    cache, sha, _ = registry
    _add_entries({"name": "horizonnet-hf", "kind": "layout", "host": "huggingface", "source": "someone/horizonnet",
                  "filename": "hf.pth", "sha256": sha})
    monkeypatch.setattr("models.download.check_reachable", lambda host, port: None)
    monkeypatch.setattr("models.download._hf_endpoint", lambda: f"http://127.0.0.1:{_free_port()}")
    monkeypatch.setattr(hf_http.time, "sleep", lambda s: None)  # the retries, without their waits
    for k in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(k, raising=False)
    records: list[logging.LogRecord] = []

    class Collect(logging.Handler):
        def emit(self, record):
            records.append(record)

    handler = Collect(level=logging.DEBUG)
    logging.getLogger("huggingface_hub").addHandler(handler)
    try:
        with pytest.raises(PanoError) as e:
            fetch("horizonnet-hf", log=lambda m: None)
    finally:
        logging.getLogger("huggingface_hub").removeHandler(handler)
    assert [r.getMessage() for r in records if r.levelno < logging.ERROR] == []
    msg = str(e.value)
    assert "\n" not in msg and "cannot download hf.pth: 127.0.0.1:" in msg and "refused the connection" in msg
    assert msg.endswith(f"put it at {cache / 'hf.pth'}")
    assert logging.getLogger("huggingface_hub").level != logging.ERROR  # restored after the download


def test_a_long_client_message_is_cut_at_a_sentence_end():
    from models.network import describe_failure, first_sentences

    hf = ("An error happened while trying to locate the file on the Hub and we cannot find the requested files "
          "in the local cache. Please check your connection and try again or make sure your Internet "
          "connection is on.")
    short = first_sentences(OSError(hf), limit=150)
    assert short == "OSError: " + hf.split(". ")[0] + "."
    assert first_sentences(OSError(hf)) == "OSError: " + hf  # fits: whole
    assert first_sentences(OSError("x" * 40 + " " + "y" * 400), limit=100).endswith("x" * 40 + " …")
    # the socket's error inside the client's wrapper is what is said
    try:
        try:
            raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
        except OSError as inner:
            raise FileNotFoundError(hf) from inner
    except OSError as outer:
        assert describe_failure(outer, "huggingface.co", 443) == \
            "no network: the name huggingface.co does not resolve (Name or service not known)"
