"""The viewer: a viser web server, its controls, and a render thread.

`Viewer.start` serves the page; each browser that connects gets its own camera, placed
at the first training view. One background thread draws a frame for each client whose
view changed (camera, time, toggles or model), sized by `AdaptiveResolution` while the
view moves and at the full size once it stops, and sends it as the page's background
image (JPEG). Nothing else runs on the training thread: during training the model comes
from a `TrainingLink` snapshot, rebuilt here.
"""

from __future__ import annotations

import contextlib
import io
import math
import threading
import time
import warnings
from dataclasses import dataclass

import numpy as np
import viser

from dyngs.datamanagers.scene_info import SceneInfo
from dyngs.model import DynamicGaussians
from dyngs.renderers.base import Renderer
from dyngs.tools.render import world_up
from dyngs.types import Camera
from dyngs.viewer.camera import (
    BrowserPose,
    camera_of,
    frame_size,
    look_distance,
    pose_of,
    quaternion_to_matrix,
)
from dyngs.viewer.controls import Controls, ViewState
from dyngs.viewer.frames import Look, draw, model_summary
from dyngs.viewer.options import ViewerOptions, check_port, port_taken
from dyngs.viewer.resolution import SETTLE_SECONDS, AdaptiveResolution
from dyngs.viewer.training import TrainingLink

SNAPSHOT_SECONDS = 1.0
"""During training, the viewer asks for a new model at most this often (each is drawn:
the page's frames share the CPU with training)."""
IDLE_WAIT_SECONDS = 0.5
"""With nothing to draw, the render thread still wakes this often (snapshots, settling)."""
RATE_EVERY_SECONDS = 0.5
"""The frame-rate read-out is updated at most this often (each update is a message)."""


@dataclass(frozen=True)
class FrameRecord:
    """What the viewer last sent one client."""

    key: tuple
    """Everything the frame depends on: pose, canvas, time, look and model version."""
    camera: Camera
    time: float
    look: Look
    refined: bool
    """Drawn at the full size (not the small size used while moving)."""
    seconds: float
    """Render time."""


def pose_key(camera: viser.CameraHandle) -> tuple:
    return (*np.round(camera.wxyz, 9), *np.round(camera.position, 9), round(camera.fov, 9),
            camera.image_width, camera.image_height)  # fmt: skip


def orbit_centre(pose: BrowserPose, scene: SceneInfo) -> np.ndarray:
    """The point the mouse turns the camera around: on its view axis, nearest the scene
    box's centre."""
    forward = quaternion_to_matrix(pose.wxyz)[:, 2]
    centre = np.asarray(scene.scene_box.center, dtype=np.float64)
    return pose.position + forward * look_distance(pose, centre)


def place_initially(server: viser.ViserServer, scene: SceneInfo) -> None:
    """New browsers start at the first training view; the orbit turns around the scene's
    up direction (the training cameras' mean, as dyngs-render's spiral)."""
    ups = [-c.rotation[1].double().cpu().numpy() for c in scene.train.cameras]
    up = world_up(np.mean(ups, axis=0))
    server.scene.set_up_direction(up)
    pose = pose_of(scene.train.cameras[0])
    server.initial_camera.up = up
    server.initial_camera.position = pose.position
    server.initial_camera.look_at = orbit_centre(pose, scene)
    server.initial_camera.fov = pose.fov_y


def place(client: viser.ClientHandle, camera: Camera, scene: SceneInfo) -> None:
    """Put the client's camera exactly where `camera` is: the last assignment, of the
    quaternion, fixes the roll the up direction left."""
    pose = pose_of(camera)
    with client.atomic():
        client.camera.position = pose.position
        client.camera.look_at = orbit_centre(pose, scene)
        client.camera.wxyz = pose.wxyz
        client.camera.fov = pose.fov_y


class Viewer:
    """The web viewer of one scene; show a model with `show` (any time, any thread)."""

    def __init__(
        self,
        scene: SceneInfo,
        renderer: Renderer,
        options: ViewerOptions | None = None,
        link: TrainingLink | None = None,
        title: str = "dyngs",
    ) -> None:
        options = options or ViewerOptions()
        self.scene, self.renderer, self.options, self.link = scene, renderer, options, link
        self.title = title
        self.frames: dict[int, FrameRecord] = {}
        """The last frame sent to each client, by client id (tests wait on these)."""
        self.resolution = AdaptiveResolution(options.max_side, 1.0 / options.target_fps)
        self._model: DynamicGaussians | None = None
        self._model_version = 0
        self._model_note = ""
        self._model_lock = threading.Lock()
        self._wake = threading.Event()
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._rate = 0.0
        self._rate_shown_at = 0.0
        self._last_sent = 0.0
        self._last_size = "none yet"
        self._failure = ""
        self._asked_at = -math.inf
        self.server: viser.ViserServer | None = None
        self.controls: Controls | None = None

    # ----------------------------------------------------------------- lifecycle

    def start(self) -> str:
        """Serve the page and start drawing; returns its URL. `PortTaken` when the port
        is in use."""
        host, port = self.options.host, self.options.port
        check_port(host, port)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner; we print the URL
            server = viser.ViserServer(host=host, port=port, label=self.title, verbose=False)
        if port != 0 and server.get_port() != port:  # taken between the check and now
            server.stop()
            raise port_taken(host, port)
        self.server = server
        place_initially(server, self.scene)
        state = ViewState()
        self.controls = Controls(server, self.scene, state, self._wake.set, self._jump, self.link)
        self._show_summary()
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self._thread = threading.Thread(target=self._loop, name="dyngs-viewer", daemon=True)
        self._thread.start()
        return self.url

    @property
    def url(self) -> str:
        assert self.server is not None, "start() first"
        host = self.options.host
        shown = f"[{host}]" if ":" in host else host
        return f"http://{shown}:{self.server.get_port()}"

    def stop(self) -> None:
        self._stopped.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
        if self.server is not None:
            self.server.stop()

    def show(
        self, model: DynamicGaussians, note: str = "", unless_ended: TrainingLink | None = None
    ) -> None:
        """Draw `model` from now on (`note`: a line shown under its summary). A snapshot
        from `unless_ended` is dropped if training ended while it was being rebuilt."""
        with self._model_lock:
            if unless_ended is not None and self.link is not unless_ended:
                return
            self._model = model
            self._model_version += 1
            self._model_note = note
        self._show_summary()
        self._wake.set()

    def training_ended(self, model: DynamicGaussians, note: str) -> None:
        """Show the final `model` from now on, and take the training controls away."""
        with self._model_lock:
            self.link = None
        if self.controls is not None and self.controls.training is not None:
            self.controls.training.visible = False
        self.show(model, note)

    def _show_summary(self) -> None:
        with self._model_lock:
            model, note = self._model, self._model_note
        if self.controls is not None and model is not None:
            self.controls.model.content = model_summary(model) + (f"  \n{note}" if note else "")

    # ------------------------------------------------------------------ cameras

    def _place(self, client: viser.ClientHandle, camera: Camera) -> None:
        place(client, camera, self.scene)
        self._wake.set()

    def _jump(self, client: viser.ClientHandle | None, camera: Camera) -> None:
        assert self.server is not None
        targets = [client] if client is not None else list(self.server.get_clients().values())
        for target in targets:
            self._place(target, camera)

    def _on_connect(self, client: viser.ClientHandle) -> None:
        client.camera.on_update(lambda _: self._wake.set())
        self._place(client, self.scene.train.cameras[0])

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        """The last page closing resumes a paused training: no one is left to resume it."""
        assert self.server is not None
        self.frames.pop(client.client_id, None)
        if self.controls is not None and not self.server.get_clients():
            self.controls.set_paused(False)

    # -------------------------------------------------------------- render thread

    def _loop(self) -> None:
        """Draw until stopped: advance playback, take new snapshots, serve each client."""
        assert self.server is not None and self.controls is not None
        last = time.monotonic()
        while not self._stopped.is_set():
            self._wake.clear()
            now = time.monotonic()
            view = self.controls.snapshot()
            if view.playing:
                self.controls.advance(now - last)
                view = self.controls.snapshot()
            last = now
            try:
                clients = list(self.server.get_clients().values())
                if clients:  # no page open: no snapshot, training is left alone
                    self._refresh_model()
                pending = False
                for client in clients:
                    pending |= self._serve(client, view)
                self._show_rate(view.playing)
            except Exception as error:  # a frame that fails must not end the page (or training)
                self._report(error)
                pending = False
            if not view.playing:
                self._wake.wait(SETTLE_SECONDS / 4 if pending else IDLE_WAIT_SECONDS)

    def _training(self) -> bool:
        """Whether a training run is feeding the page (and not paused)."""
        link = self.link
        return link is not None and not link.paused

    def _report(self, error: Exception) -> None:
        """Say once, on the terminal and on the page, that frames fail, and why."""
        said = f"viewer: drawing failed ({type(error).__name__}: {error})"
        if said != self._failure:
            self._failure = said
            warnings.warn(said, stacklevel=1)
            if self.controls is not None:
                self.controls.rate.content = said

    def _refresh_model(self) -> None:
        """During training: ask for a snapshot now and then, and show the one that came."""
        link = self.link
        if link is None:
            return
        now = time.monotonic()
        if now - self._asked_at >= SNAPSHOT_SECONDS:
            link.request()
            self._asked_at = now
        snapshot = link.take()
        if snapshot is None:
            return
        model = snapshot.model()
        paused = "  · paused" if link.paused else ""
        note = f"step {snapshot.step:,} of {snapshot.steps:,}{paused}  \n{link.hook_summary()}"
        self.show(model, note, unless_ended=link)

    def _serve(self, client: viser.ClientHandle, view: ViewState) -> bool:
        """Send `client` a new frame if its view changed, or the full-size frame once it
        stopped moving; returns whether a full-size frame is still to come."""
        camera = client.camera
        if camera.image_width < 1 or camera.image_height < 1:
            return False  # no canvas yet
        with self._model_lock:
            model, version = self._model, self._model_version
        if model is None:
            return False
        key = (pose_key(camera), view.time, view.look, version)
        last = self.frames.get(client.client_id)
        moving = (
            view.playing
            or time.time() - max(camera.update_timestamp, view.changed_at) < SETTLE_SECONDS
            or self._training()  # a new model every second: small frames, training's CPU
        )
        if last is not None and last.key == key and (last.refined or moving):
            return not last.refined
        side = self.resolution.side(moving)
        self._send(client, model, key, view, side)
        return moving

    def _send(
        self,
        client: viser.ClientHandle,
        model: DynamicGaussians,
        key: tuple,
        view: ViewState,
        side: int,
    ) -> None:
        """Draw one frame for `client` with long side `side` and send it."""
        camera = client.camera
        canvas_side = max(camera.image_width, camera.image_height)
        side = min(side, canvas_side)
        width, height = frame_size(camera.image_width / camera.image_height, side)
        pose = BrowserPose(np.array(camera.wxyz), np.array(camera.position), float(camera.fov))
        drawn = camera_of(pose, width, height, self.scene.train.cameras[0])
        started = time.perf_counter()
        image = draw(model, self.renderer, drawn, view.time, self.scene.background, view.look)
        seconds = time.perf_counter() - started
        refined = side >= min(self.options.max_side, canvas_side)
        self.resolution.measured(side, seconds)
        client.scene.set_background_image(image, format="jpeg",
                                          jpeg_quality=self.options.jpeg_quality)  # fmt: skip
        self.frames[client.client_id] = FrameRecord(key, drawn, view.time, view.look, refined,
                                                    seconds)  # fmt: skip
        self._last_size = f"{width}×{height}"
        self._count_frame()

    def _count_frame(self) -> None:
        now = time.monotonic()
        interval, self._last_sent = now - self._last_sent, now
        if interval < 2.0:  # frames in a run of motion; a gap starts a new run
            rate = 1.0 / max(interval, 1e-6)
            self._rate = rate if self._rate == 0.0 else 0.8 * self._rate + 0.2 * rate

    def _show_rate(self, playing: bool) -> None:
        now = time.monotonic()
        if self.controls is None or now - self._rate_shown_at < RATE_EVERY_SECONDS:
            return
        self._rate_shown_at = now
        self.controls.rate.content = f"{self._rate:.1f} frames/s · last frame {self._last_size}"
