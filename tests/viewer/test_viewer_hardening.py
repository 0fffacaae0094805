"""The viewer's socket (hardening issue, second pass, class 4): a page of another site cannot drive
it, the server clamps what a client sends, and renders run one at a time with a queue of one."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from simulate.generate import generate_scene
from tests.clitools import run_main
from viewer.server import RenderQueue, clamp_pano_height, origin_problem


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    pytest.importorskip("viser")
    from viewer.data import resolve_target
    from viewer.server import start_viewer

    root = tmp_path_factory.mktemp("view-hard")
    generate_scene(root / "S", views=2, test_views=0, height=16, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R",
                     "--set", "train.iterations=5", "--set", "train.height=8"]) == 0
    h = start_viewer(resolve_target(root / "S", root / "R"), port=_free_port(), pano_height=64)
    yield h
    h.stop()


def _first_frame_or_close(url: str, origin: str | None):
    """Open the viewer's websocket as a browser on page `origin` would: ("message", None) when the
    server talks, ("closed", code) when it closes the socket."""
    import viser
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(url, origin=origin, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=20,
                 max_size=None) as ws:
        try:
            ws.recv(timeout=20)
            ws.recv(timeout=2)
        except ConnectionClosed as e:
            return "closed", e.rcvd.code if e.rcvd else None
        except TimeoutError:
            pass
        return "message", None


def test_a_page_of_another_site_cannot_open_the_socket(viewer):
    url = f"ws://127.0.0.1:{viewer.port}"
    assert _first_frame_or_close(url, "http://evil.example") == ("closed", 1008)
    assert _first_frame_or_close(url, f"http://127.0.0.1:{viewer.port + 1}") == ("closed", 1008)
    assert _first_frame_or_close(url, f"http://127.0.0.1:{viewer.port}") == ("message", None)
    assert _first_frame_or_close(url, None) == ("message", None)  # a script, not a browser page


@pytest.mark.parametrize("origin, host, listen, refused", [
    ("http://127.0.0.1:8080", "127.0.0.1:8080", "127.0.0.1", False),
    ("http://localhost:8080", "localhost:8080", "127.0.0.1", False),
    ("https://evil.example", "127.0.0.1:8080", "127.0.0.1", True),
    ("http://evil.example:8080", "evil.example:8080", "127.0.0.1", True),  # DNS rebinding
    ("http://evil.example:8080", "evil.example:8080", "0.0.0.0", False),  # served to the network
    ("null", "127.0.0.1:8080", "127.0.0.1", True),  # a sandboxed frame or a file:// page
    ("file://", "127.0.0.1:8080", "127.0.0.1", True),
    (None, "127.0.0.1:8080", "127.0.0.1", False),
])
def test_origin_rule(origin, host, listen, refused):
    assert (origin_problem(origin, host, listen) is not None) == refused


@pytest.mark.parametrize("sent, used", [(2560, 2048), (10 ** 9, 2048), (-5, 64), (0, 64), (100, 128),
                                        (float("nan"), 512), (float("inf"), 512), ("x", 512), (512, 512)])
def test_slider_values_are_clamped_on_the_server(sent, used):
    assert clamp_pano_height(sent) == used


def test_a_client_setting_the_height_over_the_slider_max_gets_the_max(viewer, monkeypatch):
    from viewer.server import _renderer

    seen = []
    monkeypatch.setattr(type(viewer), "render_panorama", lambda self, c2w, height: seen.append(height) or
                        (_ for _ in ()).throw(RuntimeError("not rendered")))

    class Camera:
        wxyz, position = (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)

    class Event:
        class client:
            camera = Camera

    class Status:
        content = ""

    viewer.pano_height.value = 2560  # what a client's GuiUpdateMessage sets: viser does not clamp it
    _renderer(viewer, Status())(Event)
    assert seen == [2048]
    Camera.position = (float("nan"), 0.0, 0.0)
    status = Status()
    _renderer(viewer, status)(Event)
    assert seen == [2048] and "refused" in status.content


def test_renders_run_one_at_a_time_with_a_queue_of_one():
    started, running, overlap = [], [0], []
    gate = threading.Event()

    def render(request):
        running[0] += 1
        overlap.append(running[0])
        started.append(request)
        if request == 0:
            gate.wait(10)
        time.sleep(0.01)
        running[0] -= 1

    q = RenderQueue(render)
    first = threading.Thread(target=q.submit, args=(0,))
    first.start()
    while not started:
        time.sleep(0.001)
    outcomes = [q.submit(i) for i in range(1, 20)]  # 19 clicks while the first renders
    assert outcomes == ["queued"] * 19
    gate.set()
    first.join(10)
    assert started == [0, 19]  # the first, then the last click once; the others dropped
    assert max(overlap) == 1
    assert q.submit(20) == "ran" and started[-1] == 20
