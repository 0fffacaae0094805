"""`pano-pipe view`: the data it shows, the panorama button, and the page in a real headless
chromium (driven over the DevTools protocol: no chromedriver needed)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from simulate.generate import generate_scene
from tests.clitools import run_main

CHROMIUM = Path(os.environ.get("PANO_PIPE_CHROMIUM", "/usr/bin/chromium"))
#: How long the browser may take for one step (start, a DevTools reply, a drawn frame). Generous on
#: purpose: software WebGL on a busy 2-core machine took over a minute for one screenshot; a working
#: viewer answers in seconds, so only a broken one waits this long.
BROWSER_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A scene S and a finished (tiny) run R of it."""
    root = tmp_path_factory.mktemp("view")
    generate_scene(root / "S", views=3, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R",
                     "--set", "train.iterations=5", "--set", "train.height=8"]) == 0
    assert (root / "R" / "train" / "point_cloud.ply").is_file()
    return root


@pytest.fixture(scope="module")
def viewer(finished):
    pytest.importorskip("viser")
    from viewer.data import resolve_target
    from viewer.server import start_viewer

    h = start_viewer(resolve_target(finished / "S", finished / "R"), port=_free_port(), pano_height=64)
    yield h
    h.stop()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------ data (no server)
def test_splats_match_the_model(finished):
    from evaluation.model_io import load_model
    from viewer.data import SH_C0, splats_from_model

    g = load_model(finished / "R" / "train" / "point_cloud.ply")
    s = splats_from_model(g)
    assert len(s) == len(g) > 0
    assert s.covariances.shape == (len(g), 3, 3) and s.opacities.shape == (len(g), 1)
    # covariance eigenvalues are the squared scales
    ev = np.sort(np.linalg.eigvalsh(s.covariances[:5].astype(np.float64)), axis=1)
    sc = np.sort(np.exp(g.log_scales[:5].detach().double().numpy()) ** 2, axis=1)
    np.testing.assert_allclose(ev, sc, rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(s.rgbs[0], np.clip(0.5 + SH_C0 * g.sh_dc[0].reshape(3).numpy(), 0, 1), atol=1e-6)
    assert ((s.opacities > 0) & (s.opacities < 1)).all()


def test_layers_read_from_the_run(finished):
    from viewer.data import floor_plan_segments, layout_cloud, resolve_target, scene_cameras

    segs = floor_plan_segments(finished / "R")
    room = json.loads((finished / "R" / "union" / "artifact.json").read_text())["data"]["rooms"][0]
    assert segs.shape[1:] == (2, 3)
    ys = segs[:, :, 1].ravel()
    assert np.all(np.isclose(ys, room["floor_y"], atol=1e-5) | np.isclose(ys, room["ceiling_y"], atol=1e-5))
    assert np.isclose(ys, room["floor_y"], atol=1e-5).any() and np.isclose(ys, room["ceiling_y"], atol=1e-5).any()
    pts, col = layout_cloud(finished / "R")
    assert pts.shape == col.shape and col.dtype == np.uint8
    t = resolve_target(finished / "R")  # a run folder directly: its scene from the marker
    cams = scene_cameras(t.scene)
    assert sorted(c.split for c in cams) == ["test", "train", "train", "train"]
    assert {c.name for c in cams} == {v.name for v in t.scene.views}


def test_missing_model_is_one_clear_error(finished, tmp_path):
    from runfs.errors import PanoError
    from viewer.data import resolve_target

    with pytest.raises(PanoError, match="no run folder"):
        resolve_target(finished / "S", tmp_path / "nothing")
    with pytest.raises(PanoError, match="neither a scene folder"):
        resolve_target(tmp_path)


def test_level_pose_keeps_yaw_and_position():
    from viewer.data import level_pose

    yaw, pitch = 0.7, 0.4
    ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rx = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = ry @ rx, (1, -1.5, 2)
    lv = level_pose(c2w)
    np.testing.assert_allclose(lv[:3, :3], ry, atol=1e-12)
    np.testing.assert_allclose(lv[:3, 3], (1, -1.5, 2))


# ------------------------------------------------------------------ server
def test_panorama_button_renders_and_saves(viewer, finished):
    from viewer.server import _renderer

    class Cam:
        cam = viewer.cameras[0]
        import viser.transforms as tf
        wxyz = tf.SO3.from_matrix(cam.c2w[:3, :3]).wxyz
        position = cam.c2w[:3, 3]

    class Client:
        camera = Cam

    class Status:
        content = ""

    class Event:
        client = Client

    viewer.pano_height.value = 64
    status = Status()
    _renderer(viewer, status)(Event)
    assert status.content.startswith("Saved"), status.content
    pano = viewer.last_panorama
    assert pano.path.parent == finished / "R" / "view" and pano.path.is_file()
    import cv2

    img = cv2.imread(str(pano.path))
    assert img.shape == (64, 128, 3) and img.std() > 5  # 2:1, not blank
    meta = json.loads(pano.path.with_suffix(".json").read_text())
    np.testing.assert_allclose(np.asarray(meta["pose_c2w"])[:3, 3], viewer.cameras[0].c2w[:3, 3])
    # the same render as evaluation's renderer from that (level) camera pose, against the colour
    # the model was trained against (the train artifact's settled background)
    from evaluation.model_io import equirect_camera, render_pose
    from pipeline.engine import read_output

    background = tuple(read_output(finished / "R", "train").settings["background"])
    assert viewer.background == pytest.approx(background) and max(background) > 0.05
    ref = render_pose(viewer.model, viewer.cameras[0].c2w, equirect_camera(64, 128), background=background).image
    assert np.abs(pano.image - ref).max() < 1e-5
    assert viewer.pano_image is not None  # shown in the GUI
    assert not viewer.render_button.disabled


def test_toggles_hide_their_nodes(viewer):
    assert set(viewer.layers) == {"gaussians", "cameras", "floor plan", "layout cloud"}
    assert len(viewer.nodes["cameras"]) == 2 * 4  # a frustum and a label per view
    viewer.set_layer("floor plan", False)
    assert not viewer.nodes["floor plan"][0].visible
    viewer.set_layer("floor plan", True)
    assert viewer.nodes["floor plan"][0].visible


def test_view_command_exits_cleanly_on_ctrl_c(finished, monkeypatch, capsys):
    from viewer import command

    def interrupt(_seconds):
        raise KeyboardInterrupt

    monkeypatch.setattr(command.time, "sleep", interrupt)
    command.view_command(finished / "R", port=_free_port())
    out = capsys.readouterr().out
    assert "http://127.0.0.1:" in out and "viewer stopped" in out


# ------------------------------------------------------------------ real browser
#: Console messages that are not the viewer's fault (software WebGL in a headless browser).
#: viser's splat quad has 2-D "position" vertices, so three.js computes a NaN bounding sphere for it
#: (harmless: viser draws the splats itself; it does not depend on our data).
BENIGN = ("favicon.ico", "GPU stall due to ReadPixels", "Automatic fallback to software WebGL",
          "THREE.BufferGeometry.computeBoundingSphere(): Computed radius is NaN")


class Chromium:
    """Headless chromium over the DevTools protocol (websocket-client)."""

    def __init__(self, profile: Path, width: int = 800, height: int = 600):
        import websocket

        args = [str(CHROMIUM), "--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                f"--window-size={width},{height}", "--remote-debugging-port=0", f"--user-data-dir={profile}",
                "about:blank"]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = profile / "DevToolsActivePort"
        deadline = time.time() + BROWSER_TIMEOUT_S
        while not (port_file.is_file() and port_file.read_text().strip()):
            if time.time() > deadline or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not open its DevTools port")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=10).read())
        page = next(p for p in pages if p.get("type") == "page")
        self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=BROWSER_TIMEOUT_S, suppress_origin=True)
        self.next_id = 0
        self.console: list[str] = []
        for method in ("Runtime.enable", "Log.enable", "Page.enable"):
            self.call(method)

    def _event(self, msg: dict) -> None:
        m, p = msg.get("method"), msg.get("params", {})
        if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            self.console.append("console: " + " ".join(str(a.get("value", a.get("description", "")))
                                                        for a in p.get("args", [])))
        elif m == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.console.append("exception: " + str(d.get("exception", {}).get("description", d.get("text"))))
        elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            e = p["entry"]
            self.console.append(f"log: {e.get('text')} {e.get('url', '')}")

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def screenshot(self) -> np.ndarray:
        import cv2

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    def errors(self) -> tuple[list[str], list[str]]:
        """(errors, ignored benign ones)."""
        bad = [m for m in self.console if not any(b in m for b in BENIGN)]
        return bad, [m for m in self.console if m not in bad]

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _wait_for(fn, timeout: float, what: str):
    deadline = time.time() + timeout
    while time.time() < deadline:
        got = fn()
        if got is not None and got is not False:
            return got
        time.sleep(0.25)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _view(img: np.ndarray) -> np.ndarray:
    """The 3D view below viser's notification and left of its control panel (800x~450 window)."""
    h, w = img.shape[:2]
    return img[int(h * 0.35):, : int(w * 0.57)].astype(int)


def _covered(img: np.ndarray) -> float:
    """Fraction of the 3D view that is not viser's white background (grid lines are thin)."""
    return float((_view(img).min(axis=2) < 245).mean())


def _changed(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(_view(a) - _view(b)).mean())


def test_page_draws_the_splats_in_headless_chromium(viewer, capsys):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} absent (Debian package 'chromium')")
    try:
        import websocket  # noqa: F401  (websocket-client, a selenium dependency)
    except ImportError:
        pytest.skip("websocket-client not installed (pip install websocket-client)")
    import viser.transforms as tf

    profile = Path(tempfile.mkdtemp(prefix="pano-view-chromium-"))
    try:
        try:
            br = Chromium(profile)
        except RuntimeError as e:
            pytest.skip(str(e))
        try:
            before = len(viewer.server.get_clients())
            br.call("Page.navigate", url=viewer.url)
            client = _wait_for(lambda: [c for c in viewer.server.get_clients().values()][before:] or None,
                               BROWSER_TIMEOUT_S, "the page to connect")[0]
            _wait_for(lambda: client.camera.update_timestamp > 0, BROWSER_TIMEOUT_S, "the client camera")
            # splats are sorted and drawn client-side: wait until they cover the 3D view
            first = _wait_for(lambda: (lambda s: s if _covered(s) > 0.5 else None)(br.screenshot()),
                              BROWSER_TIMEOUT_S, "the Gaussians to be drawn")
            assert _view(first).std() > 5, "the 3D view is blank"
            # the server moves the browser's camera: the picture changes
            cam = viewer.cameras[-1]
            with client.atomic():
                client.camera.wxyz = tf.SO3.from_matrix(cam.c2w[:3, :3]).wxyz
                client.camera.position = cam.c2w[:3, 3]
            second = _wait_for(lambda: (lambda s: s if _changed(first, s) > 5 else None)(br.screenshot()),
                               BROWSER_TIMEOUT_S, "the view to change after moving the camera")
            assert _covered(second) > 0.5
            # the "gaussians" toggle hides them: back to (nearly) white background
            viewer.layers["gaussians"].value = False
            viewer.set_layer("gaussians", False)
            _wait_for(lambda: _covered(br.screenshot()) < 0.3, BROWSER_TIMEOUT_S, "the Gaussians to disappear")
            viewer.set_layer("gaussians", True)
            viewer.layers["gaussians"].value = True
            bad, ignored = br.errors()
            with capsys.disabled():
                print(f"\nbrowser console: {len(bad)} error(s), ignored {ignored}")
            assert not bad, bad
        finally:
            br.close()
    finally:
        shutil.rmtree(profile, ignore_errors=True)


# ------------------------------------------------------------------ first viewpoint, messages
def test_look_along_room_faces_the_far_end_of_a_long_room():
    from viewer.data import look_along_room

    rng = np.random.default_rng(0)
    # a 10 m x 3 m corridor (x from -1 to 9, z from -1.5 to 1.5), walls sampled densely, camera near x = 0
    n = 4000
    xs = rng.uniform(-1, 9, n)
    m = n // 4

    def end_wall(x: float) -> np.ndarray:
        return np.stack([np.full(m, x), rng.uniform(-1, 1, m), rng.uniform(-1.5, 1.5, m)], 1)

    walls = np.concatenate([np.stack([xs, rng.uniform(-1, 1, n), np.full(n, -1.5)], 1),
                            np.stack([xs, rng.uniform(-1, 1, n), np.full(n, 1.5)], 1),
                            end_wall(-1.0), end_wall(9.0)])
    d = look_along_room(np.zeros(3), walls)
    assert d[1] == 0 and np.linalg.norm(d) == pytest.approx(1.0)
    assert d[0] > 0.97  # along +x, down the corridor
    assert np.allclose(look_along_room(np.zeros(3), walls[:5]), [0, 0, 1])  # too few points: +z


def test_viewer_starts_at_the_first_training_camera_looking_along_the_room(viewer):
    from viewer.data import look_along_room

    first = next(c for c in viewer.cameras if c.split == "train")
    cam = viewer.server.initial_camera
    position = np.asarray(cam.position, dtype=np.float64)
    np.testing.assert_allclose(position, first.c2w[:3, 3], atol=1e-6)
    ahead = np.asarray(cam.look_at, dtype=np.float64) - position
    assert abs(ahead[1]) < 1e-6  # level
    from viewer.data import splats_from_model

    expected = look_along_room(position, splats_from_model(viewer.model).centers)
    np.testing.assert_allclose(ahead / np.linalg.norm(ahead), expected, atol=1e-5)


def test_panorama_messages_name_the_real_folder(tmp_path, monkeypatch):
    from viewer.server import shown_path

    monkeypatch.chdir(tmp_path)
    assert shown_path(tmp_path / "runs" / "demo" / "view") == "runs/demo/view"
    assert shown_path(Path("runs/demo/view")) == "runs/demo/view"
    elsewhere = Path(tempfile.gettempdir()).resolve() / "elsewhere"
    if not str(elsewhere).startswith(str(tmp_path)):
        assert shown_path(elsewhere) == elsewhere.as_posix()
