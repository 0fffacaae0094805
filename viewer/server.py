"""The viser server behind `pano-pipe view`: build it for a run folder, get a handle, stop it.

Layers (GUI toggles): the trained Gaussians (viser's client-side splat renderer), the cameras
(train and test frustums with their names; a click flies the browser camera there), the floor
plan (union stage) and the layout cloud (sampling stage). A button renders the current viewpoint
as an equirectangular panorama with the project's renderer and saves it under RUN/view/.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runfs.paths import run_path
from viewer.data import (
    MODEL_PATH,
    CameraView,
    Target,
    floor_plan_segments,
    layout_cloud,
    level_pose,
    look_along_room,
    scene_cameras,
    splats_from_model,
)

#: The panorama-height slider's range and step: the server clamps what a client sends to it
#: (a client can send any value, and any slider min/max, over the websocket).
PANO_HEIGHT_MIN, PANO_HEIGHT_MAX, PANO_HEIGHT_STEP = 64, 2048, 64
#: Host names that reach this machine only: a viewer listening on a loopback address accepts a
#: browser's websocket only from a page served under one of these (no DNS rebinding).
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1", "[::1]")
#: The close code of a websocket refused for its Origin (RFC 6455: policy violation).
POLICY_VIOLATION = 1008

#: Colours of the camera frustums (RGB).
TRAIN_COLOUR = (30, 110, 230)
TEST_COLOUR = (230, 120, 20)
PLAN_COLOUR = (220, 30, 30)
VIEW_FOLDER = "view"


def clamp_pano_height(value, default: int = 512) -> int:
    """A panorama height a client asked for, on the slider's grid and inside its range."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not np.isfinite(v):
        v = default
    v = round(v / PANO_HEIGHT_STEP) * PANO_HEIGHT_STEP
    return int(min(max(v, PANO_HEIGHT_MIN), PANO_HEIGHT_MAX))


def origin_problem(origin: str | None, host_header: str | None, listen_host: str) -> str | None:
    """Why a websocket handshake's Origin is refused, or None.

    A browser sends the Origin of the page that opens the socket; any page the user visits may
    try ws://127.0.0.1:8080. Accepted: no Origin (not a browser: a script could send any), or an
    Origin whose host:port is the Host the request was sent to (the page the viewer served); when
    listening on a loopback address, that host must also be a loopback name (a rebound DNS name
    such as evil.example resolving to 127.0.0.1 is refused)."""
    from urllib.parse import urlsplit

    if origin is None:
        return None
    try:
        parts = urlsplit(origin)
        netloc, hostname = parts.netloc.lower(), (parts.hostname or "").lower()
    except ValueError:
        return f"malformed Origin {origin[:80]!r}"
    if parts.scheme not in ("http", "https") or not netloc:
        return f"Origin {origin[:80]!r} is not a web page"
    if netloc != (host_header or "").lower():
        return f"Origin {origin[:80]!r} is not the viewer's page ({host_header})"
    if _is_loopback(listen_host) and hostname not in LOOPBACK_NAMES and not hostname.startswith("127."):
        return f"Origin {origin[:80]!r}: a loopback viewer serves only localhost pages"
    return None


def _is_loopback(host: str) -> bool:
    return host in ("localhost", "::1") or host.startswith("127.")


class RenderQueue:
    """One render at a time, at most one waiting: a request made while one runs waits, and
    replaces the one already waiting (repeated clicks render the last viewpoint once)."""

    def __init__(self, render):
        self._render = render
        self._lock = threading.Lock()
        self._busy = False
        self._waiting = None

    def submit(self, request) -> str:
        """Run `render(request)` now ("ran"), or leave it for the running caller ("queued")."""
        with self._lock:
            if self._busy:
                self._waiting = request
                return "queued"
            self._busy = True
        while request is not None:
            try:
                self._render(request)
            finally:
                with self._lock:
                    request, self._waiting = self._waiting, None
                    if request is None:
                        self._busy = False
        return "ran"


def _guard_origin(server, listen_host: str) -> None:
    """Close, before anything is exchanged, every websocket whose Origin `origin_problem` refuses,
    and drop any message such a client managed to send first."""
    ws = server._websock_server  # viser exposes no handshake hook; its connections live here
    refused: set[int] = set()

    async def check(conn) -> None:
        connection = ws._live_connections.get(conn.client_id)
        if connection is None:
            return
        headers = connection.request.headers
        problem = origin_problem(headers.get("Origin"), headers.get("Host"), listen_host)
        if problem is not None:
            refused.add(conn.client_id)
            await connection.close(POLICY_VIOLATION, "origin refused")

    handle_incoming = ws._handle_incoming_message

    async def guarded(client_id, message) -> None:
        if client_id not in refused:
            await handle_incoming(client_id, message)

    ws._client_connect_cb.insert(0, check)  # before viser's own: nothing is set up for it
    ws._handle_incoming_message = guarded


def _wxyz(rot: np.ndarray) -> np.ndarray:
    import viser.transforms as tf

    return tf.SO3.from_matrix(np.asarray(rot, dtype=np.float64)).wxyz


@dataclass
class Panorama:
    path: Path
    image: np.ndarray  # float32 RGB [H, 2H, 3] in [0,1]
    pose: np.ndarray  # the (levelled) camera-to-world it was rendered from
    seconds: float


@dataclass
class ViewerHandle:
    """A running viewer. `stop()` shuts the server down (idempotent)."""

    server: object  # viser.ViserServer
    run_dir: Path
    url: str
    model: object  # gaussians.Gaussians (on `device`)
    device: str
    cameras: list[CameraView]
    #: the colour the model was trained against (None: black), as the evaluate stage renders it
    background: tuple[float, float, float] | None = None
    layers: dict[str, object] = field(default_factory=dict)  # toggle name -> GUI checkbox
    nodes: dict[str, list] = field(default_factory=dict)  # toggle name -> scene handles
    pano_height: object = None  # GUI slider
    render_button: object = None
    pano_image: object = None  # GUI image, made on the first render
    last_panorama: Panorama | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _stopped: bool = False

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    def set_layer(self, name: str, visible: bool) -> None:
        """Show or hide one layer ("gaussians", "cameras", "floor plan", "layout cloud")."""
        for node in self.nodes.get(name, []):
            node.visible = bool(visible)

    def fly_to(self, client, c2w: np.ndarray, seconds: float = 0.4, steps: int = 12) -> None:
        """Move `client`'s camera to the pose c2w (OpenCV axes, as viser's), eased over `seconds`."""
        import viser.transforms as tf

        cam = client.camera
        c2w = np.asarray(c2w, dtype=np.float64)
        target = tf.SE3.from_rotation_and_translation(tf.SO3.from_matrix(c2w[:3, :3]), c2w[:3, 3])
        start = tf.SE3.from_rotation_and_translation(tf.SO3(np.asarray(cam.wxyz)), np.asarray(cam.position))
        delta = (start.inverse() @ target).log()
        for i in range(1, max(1, steps) + 1):
            t = i / max(1, steps)
            t = t * t * (3 - 2 * t)  # smoothstep
            pose = start @ tf.SE3.exp(delta * t)
            with client.atomic():
                cam.wxyz = pose.rotation().wxyz
                cam.position = pose.translation()
            if i < steps:
                time.sleep(seconds / steps)

    def render_panorama(self, c2w: np.ndarray, height: int = 512, level: bool = True) -> Panorama:
        """Render an equirectangular panorama (2:1) from c2w with the project's renderer, save it
        as RUN/view/panorama_NNNN.png (+ .json with its pose) and show it in the GUI."""
        from evaluation.model_io import equirect_camera, render_pose
        from panogeom.images import write_rgb

        height = clamp_pano_height(height)
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise ValueError("the camera pose is not a finite 4x4 matrix")
        pose = level_pose(c2w) if level else c2w
        with self._lock:
            out = render_pose(self.model, pose, equirect_camera(height, 2 * height), background=self.background)
            folder = run_path(self.run_dir, VIEW_FOLDER)  # a link planted meanwhile is refused
            folder.mkdir(parents=True, exist_ok=True)
            n = 1 + max([int(p.stem.split("_")[-1]) for p in folder.glob("panorama_[0-9][0-9][0-9][0-9].png")]
                        or [0])
            path = folder / f"panorama_{n:04d}.png"
            write_rgb(path, out.image)
            path.with_suffix(".json").write_text(json.dumps(
                {"pose_c2w": pose.tolist(), "height": height, "width": 2 * height,
                 "backend": out.backend, "seconds": out.seconds}, indent=1))
        pano = Panorama(path, out.image, pose, out.seconds)
        self.last_panorama = pano
        if not self._stopped:
            self._show(pano)
        return pano

    def _show(self, pano: Panorama) -> None:
        img = (np.clip(pano.image, 0, 1) * 255 + 0.5).astype(np.uint8)
        if self.pano_image is None:
            self.pano_image = self.server.gui.add_image(img, label=pano.path.name, format="jpeg")
        else:
            self.pano_image.image = img
            self.pano_image.label = pano.path.name

    def stop(self) -> None:
        if not self._stopped:
            self._stopped = True
            self.server.stop()


def start_viewer(target: Target, host: str = "127.0.0.1", port: int = 8080, pano_height: int = 512,
                 device: str | None = None) -> ViewerHandle:
    """Load the run folder's model and layers, start a viser server on host:port, return its handle."""
    import torch
    import viser

    from evaluation.model_io import load_model, recorded_background
    from pipeline.engine import read_artifact

    run_dir = Path(target.run_dir)
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    model = load_model(run_dir / MODEL_PATH, device=device)
    train = read_artifact(run_dir, "train")
    background = None if train is None else recorded_background(train.data.settings, train.meta.params)
    splats = splats_from_model(model)
    cameras = scene_cameras(target.scene)

    server = viser.ViserServer(host=host, port=port, verbose=False)
    _guard_origin(server, host)
    server.gui.configure_theme(control_width="medium")
    server.scene.set_up_direction("-y")  # the world is y down: no data are rotated
    h = ViewerHandle(server=server, run_dir=run_dir, url=f"http://{_url_host(host)}:{server.get_port()}",
                     model=model, device=device, cameras=cameras, background=background)

    # initial viewpoint: the first training camera (inside the room), looking level along the room's
    # longest free direction (its own forward axis may face a wall a hand's breadth away)
    train = [c for c in cameras if c.split == "train"] or cameras
    if train:
        position = train[0].c2w[:3, 3]
        server.initial_camera.position = tuple(position)
        server.initial_camera.look_at = tuple(position + look_along_room(position, splats.centers))
    elif len(splats):
        centre = np.median(splats.centers, axis=0)
        server.initial_camera.position = tuple(centre + np.array([0.0, -3.0, -3.0]))
        server.initial_camera.look_at = tuple(centre)
    server.initial_camera.up = (0.0, -1.0, 0.0)

    # -- layers
    h.nodes["gaussians"] = [server.scene.add_gaussian_splats(
        "/gaussians", centers=splats.centers, covariances=splats.covariances, rgbs=splats.rgbs,
        opacities=splats.opacities)]
    cam_nodes = []
    for cam in cameras:
        colour = TRAIN_COLOUR if cam.split == "train" else TEST_COLOUR
        name = f"/cameras/{cam.split}/{cam.name}"
        frustum = server.scene.add_camera_frustum(
            name, fov=np.pi / 2, aspect=2.0, scale=0.15, color=colour,
            wxyz=_wxyz(cam.c2w[:3, :3]), position=cam.c2w[:3, 3])
        label = server.scene.add_label(f"{name}/label", f"{cam.name} ({cam.split})", position=(0.0, 0.0, 0.0))
        frustum.on_click(_flyer(h, cam))
        cam_nodes += [frustum, label]
    h.nodes["cameras"] = cam_nodes
    segs = floor_plan_segments(run_dir)
    if segs is not None:
        h.nodes["floor plan"] = [server.scene.add_line_segments(
            "/floor_plan", points=segs, colors=PLAN_COLOUR, thickness=3.0, thickness_units="screen")]
    cloud = layout_cloud(run_dir)
    if cloud is not None:
        h.nodes["layout cloud"] = [server.scene.add_point_cloud(
            "/layout_cloud", points=cloud[0], colors=cloud[1], point_size=0.015, visible=False)]

    # -- GUI
    server.gui.add_markdown(f"**pano-pipe view** · `{run_dir.name}` · {len(splats)} Gaussians")
    with server.gui.add_folder("Layers"):
        defaults = {"gaussians": True, "cameras": True, "floor plan": True, "layout cloud": False}
        for name in ("gaussians", "cameras", "floor plan", "layout cloud"):
            available = name in h.nodes
            box = server.gui.add_checkbox(name if available else f"{name} (not in run)",
                                          initial_value=defaults[name] and available, disabled=not available)
            box.on_update(_toggler(h, name, box))
            h.layers[name] = box
    if cameras:
        with server.gui.add_folder("Go to camera"):
            for cam in cameras:
                btn = server.gui.add_button(f"{cam.name} ({cam.split})")
                btn.on_click(_flyer(h, cam))
    with server.gui.add_folder("Panorama"):
        h.pano_height = server.gui.add_slider("height (px)", min=PANO_HEIGHT_MIN, max=PANO_HEIGHT_MAX,
                                              step=PANO_HEIGHT_STEP, initial_value=clamp_pano_height(pano_height))
        h.render_button = server.gui.add_button("Render 360° panorama here")
        status = server.gui.add_markdown("Renders the current viewpoint (levelled) and saves it to "
                                         f"`{shown_path(run_dir / VIEW_FOLDER)}/`.")
        h.render_button.on_click(_renderer(h, status))
    return h


def shown_path(path: Path) -> str:
    """A path as the user can open it: relative to the working folder when inside it
    (runs/demo/view), else absolute."""
    path = Path(path).absolute()
    try:
        return path.relative_to(Path.cwd()).as_posix()
    except ValueError:
        return path.as_posix()


def _url_host(host: str) -> str:
    return "localhost" if host in ("0.0.0.0", "::", "") else host


def _flyer(h: ViewerHandle, cam: CameraView):
    def callback(event) -> None:
        if event.client is not None:
            h.fly_to(event.client, cam.c2w)

    return callback


def _toggler(h: ViewerHandle, name: str, box):
    def callback(_event) -> None:
        h.set_layer(name, box.value)

    return callback


def _renderer(h: ViewerHandle, status):
    """The render button's callback: the client's viewpoint and the slider's height, both checked
    on the server (a client sends what it likes), rendered through one RenderQueue."""

    def render(request) -> None:
        c2w, height = request
        h.render_button.disabled = True
        status.content = "Rendering…"
        try:
            pano = h.render_panorama(c2w, height)
            status.content = (f"Saved `{shown_path(pano.path)}` "
                              f"({pano.image.shape[0]}×{pano.image.shape[1]} H×W, {pano.seconds:.2f} s).")
        except Exception as exc:  # a failed render must not kill the server
            status.content = f"Render failed: {type(exc).__name__}: {exc}"
        finally:
            h.render_button.disabled = False

    queue = RenderQueue(render)

    def callback(event) -> None:
        client = event.client
        if client is None:
            return
        import viser.transforms as tf

        wxyz = np.asarray(client.camera.wxyz, dtype=np.float64)
        position = np.asarray(client.camera.position, dtype=np.float64)
        if wxyz.shape != (4,) or position.shape != (3,) or not (np.isfinite(wxyz).all() and np.isfinite(position).all()) \
                or np.linalg.norm(wxyz) < 1e-9:
            status.content = "Render refused: the browser sent no valid camera pose."
            return
        c2w = np.eye(4)
        c2w[:3, :3] = tf.SO3(wxyz / np.linalg.norm(wxyz)).as_matrix()
        c2w[:3, 3] = position
        if queue.submit((c2w, clamp_pano_height(h.pano_height.value))) == "queued":
            status.content = "Rendering… (one more render queued)"

    return callback
