"""LPIPS weights from their standard places: torchvision's backbone in the torch hub cache
(downloaded there on first use), the linear heads inside the lpips wheel (never imported)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from evalhelpers import fake_lpips_state, write_train_artifact
from test_eval_stage import _run

from evaluation import metrics as M
from evaluation.metrics import view_metrics
from stages.evaluate import Params


@pytest.fixture
def standard_places(tmp_path, monkeypatch):
    """An empty torch hub (TORCH_HOME) and a stand-in lpips package that fails if imported, so
    the lookup must read its weights file without importing it (the real one imports torchvision)."""
    monkeypatch.delenv(M.LPIPS_ENV, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    pkg = tmp_path / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ImportError('the lpips package must not be imported')\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    return hub, pkg / "weights" / "v0.1"


def test_found_in_hub_cache_and_lpips_wheel_and_used_by_evaluate(standard_places, sim_scene, sim_model,
                                                                tmp_path, monkeypatch):
    hub, heads = standard_places
    backbone, lin = fake_lpips_state(seed=3)
    hub.mkdir(parents=True)
    torch.save(backbone, hub / "alexnet-owt-7be5be79.pth")
    torch.save(lin, heads / "alex.pth")
    files = M.find_lpips_weights("alex", download=False)
    assert files.backbone == hub / "alexnet-owt-7be5be79.pth" and files.lin == heads / "alex.pth"

    write_train_artifact(tmp_path / "run", sim_model, resolution=(32, 64))
    out, ctx = _run(sim_scene, tmp_path / "run", fps_repeats=1, threads=1, lpips_download=False)
    assert out.lpips_available and out.lpips_net == "alex" and not ctx.warnings
    # The stage's number is the distance under exactly these random weights.
    expected = M.LPIPS("alex")
    expected.load_weights(backbone, lin)
    from panogeom.images import read_rgb

    d = tmp_path / "run" / "evaluate"
    v = out.views[0]
    want = view_metrics(read_rgb(d / v.render), read_rgb(d / v.gt), expected)["lpips"]
    assert v.lpips > 0 and v.lpips == pytest.approx(want, rel=0.02)  # PNG rounding of the written images
    # The heads enter linearly: heads scaled by 3 would have given three times the distance.
    tripled = M.LPIPS("alex")
    tripled.load_weights(backbone, {k: 3 * w for k, w in lin.items()})
    assert view_metrics(read_rgb(d / v.render), read_rgb(d / v.gt), tripled)["lpips"] == pytest.approx(
        3 * want, rel=1e-5)


def test_missing_backbone_is_downloaded_to_the_hub_cache(standard_places, monkeypatch):
    hub, heads = standard_places
    backbone, lin = fake_lpips_state(seed=5)
    torch.save(lin, heads / "alex.pth")
    calls = []

    def fake_download(url, **kw):  # what torch hub does: fetch into <hub>/checkpoints/<file name>
        calls.append((url, kw))
        hub.mkdir(parents=True, exist_ok=True)
        torch.save(backbone, hub / url.rsplit("/", 1)[1])
        return backbone

    monkeypatch.delenv(M.OFFLINE_ENV, raising=False)
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", fake_download)
    model = M.load_lpips("alex")
    assert [c[0] for c in calls] == ["https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"]
    assert calls[0][1]["check_hash"] and calls[0][1]["weights_only"]
    x = np.random.default_rng(0).random((32, 64, 3)).astype(np.float32)
    assert model.distance(x, x[::-1]) > 0
    # Second use: the cached file, no download.
    M.load_lpips("alex")
    assert len(calls) == 1


def test_offline_names_the_missing_file_its_url_and_where_to_put_it(standard_places, monkeypatch):
    hub, heads = standard_places
    torch.save(fake_lpips_state()[1], heads / "alex.pth")
    monkeypatch.setenv(M.OFFLINE_ENV, "1")
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", lambda *a, **k: pytest.fail("downloaded offline"))
    with pytest.raises(M.LpipsUnavailable) as e:
        M.load_lpips("alex")
    msg = str(e.value)
    assert str(hub / "alexnet-owt-7be5be79.pth") in msg
    assert "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth" in msg and "put it there" in msg


def test_failed_download_is_unavailable_not_a_crash(standard_places, monkeypatch):
    hub, heads = standard_places
    torch.save(fake_lpips_state()[1], heads / "alex.pth")
    monkeypatch.delenv(M.OFFLINE_ENV, raising=False)

    def no_network(url, **kw):
        raise OSError("Name or service not known")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_network)
    with pytest.raises(M.LpipsUnavailable, match="downloading https://download.pytorch.org/.*failed.*OSError"):
        M.load_lpips("alex")


def test_missing_heads_say_how_to_install_them(tmp_path, monkeypatch):
    monkeypatch.delenv(M.LPIPS_ENV, raising=False)
    monkeypatch.setattr(M, "lpips_package_heads", lambda net: None)
    with pytest.raises(M.LpipsUnavailable) as e:
        M.load_lpips("vgg")
    msg = str(e.value)
    assert "lpips package is not installed" in msg and "pip install --no-deps lpips==0.1.4" in msg
    assert M.LPIPS_HEADS_URL + "vgg.pth" in msg and "vgg16-397923af.pth" in msg


def test_heads_are_read_from_the_installed_wheel_without_importing_it():
    import sys

    heads = M.lpips_package_heads("alex")
    if heads is None:
        pytest.skip("the lpips wheel is not installed (make setup installs it)")
    assert heads.parts[-3:] == ("weights", "v0.1", "alex.pth") and heads.is_file()
    assert "lpips" not in sys.modules and "torchvision" not in sys.modules
    state = torch.load(heads, map_location="cpu", weights_only=True)
    assert [tuple(state[f"lin{i}.model.1.weight"].shape) for i in range(5)] == [
        (1, c, 1, 1) for c in (64, 192, 384, 256, 256)]


def test_params_default_downloads_and_can_be_turned_off():
    assert Params().lpips_download and not Params(lpips_download=False).lpips_download


def test_an_offline_download_is_tried_and_said_once_per_run(standard_places, sim_scene, sim_model, tmp_path,
                                                             monkeypatch, capsys):
    """Issue 36: offline, every evaluation tried the download again and announced it. A run that
    evaluates twice (a batch, an ablation) tries once and prints the warning once, naming the
    setting that turns LPIPS off; each artifact still records it."""
    import socket
    import urllib.error

    from stages import evaluate

    hub, heads = standard_places
    torch.save(fake_lpips_state()[1], heads / "alex.pth")
    monkeypatch.delenv(M.OFFLINE_ENV, raising=False)
    monkeypatch.setattr(M, "_FAILED_DOWNLOADS", {})
    monkeypatch.setattr(evaluate, "_LPIPS_SAID", set())
    tries = []

    def offline(url, **kw):  # what torch hub raises offline: the socket's error inside a URLError
        tries.append(url)
        print(f'Downloading: "{url}" to {hub}')  # torch hub's announcement, on stdout
        raise urllib.error.URLError(socket.gaierror(socket.EAI_NONAME, "Name or service not known"))

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    write_train_artifact(tmp_path / "run", sim_model, resolution=(32, 64))
    capsys.readouterr()
    contexts = [_run(sim_scene, tmp_path / "run", fps_repeats=1, threads=1)[1] for _ in range(2)]
    out = " ".join(capsys.readouterr().out.split())
    assert len(tries) == 1 and "Downloading" not in out
    assert out.count("LPIPS unavailable") == 1
    assert "no network: the name download.pytorch.org does not resolve" in out
    assert "--set evaluate.lpips=false turns LPIPS off" in out
    for ctx in contexts:
        assert [w for w in ctx.warnings if "LPIPS unavailable" in w and "evaluate.lpips=false" in w]
