"""The page's controls (viser GUI elements) and the state they set.

The controls write `ViewState` under its lock and wake the render loop; the render loop
reads it, and writes back what it measured (frame rate, model summary) through the
read-outs here.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import viser

from dyngs.datamanagers.scene_info import SceneInfo
from dyngs.types import Camera
from dyngs.viewer.frames import Look
from dyngs.viewer.training import TrainingLink

TIME_STEP = 0.001
"""Resolution of the time slider (a thousand steps over the sequence)."""
DEFAULT_SPEED = 0.1
"""Playback speed in sequences per second: 10 s from t = 0 to t = 1."""


@dataclass
class ViewState:
    """What the controls set; read by the render loop under `lock`."""

    time: float = 0.0
    playing: bool = False
    speed: float = DEFAULT_SPEED
    """Sequences per second while playing."""
    look: Look = field(default_factory=Look)
    changed_at: float = 0.0
    """When time or look last changed, by `time.time()` as viser stamps camera updates (a
    time drag counts as moving, like a camera drag)."""
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)


def view_names(scene: SceneInfo) -> dict[str, Camera]:
    """The views the camera dropdown offers, by label ("train 0", "test 3", …)."""
    views: dict[str, Camera] = {}
    for split in ("train", "val", "test"):
        for index, camera in enumerate(getattr(scene, split).cameras):
            views[f"{split} {index}"] = camera
    return views


class Controls:
    """Builds the GUI on `server` and keeps `state` in step with it."""

    def __init__(
        self,
        server: viser.ViserServer,
        scene: SceneInfo,
        state: ViewState,
        wake: Callable[[], None],
        jump: Callable[[viser.ClientHandle | None, Camera], None],
        link: TrainingLink | None = None,
    ) -> None:
        self.state, self.wake, self.link = state, wake, link
        gui = server.gui
        self.views = view_names(scene)
        with gui.add_folder("Time"):
            self.time = gui.add_slider("Time", 0.0, 1.0, TIME_STEP, 0.0)
            self.play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self.speed = gui.add_slider(
                "Speed", 0.01, 1.0, 0.01, DEFAULT_SPEED, hint="Sequences per second while playing"
            )
            self.rate = gui.add_markdown("")
        with gui.add_folder("View"):
            self.view = gui.add_dropdown("Camera", tuple(self.views), initial_value="train 0")
            self.deform = gui.add_checkbox(
                "Deformation", True, hint="Off: the canonical Gaussians, undeformed"
            )
            self.motion = gui.add_checkbox(
                "Static / dynamic", False, hint="Blue: static Gaussians, orange: dynamic"
            )
            self.depth = gui.add_checkbox("Depth", False, hint="Expected depth, near is red")
        with gui.add_folder("Model"):
            self.model = gui.add_markdown("")
            self.training = self._training_controls(gui) if link is not None else None
        self._wire(jump)

    def _training_controls(self, gui: Any) -> Any:
        button = gui.add_button("Pause training", icon=viser.Icon.PLAYER_PAUSE)

        @button.on_click
        def _(_: Any) -> None:
            assert self.link is not None
            self.set_paused(not self.link.paused)

        return button

    def set_paused(self, paused: bool) -> None:
        """Pause or resume training, and say which on the button."""
        if self.link is None or self.training is None:
            return
        if paused:
            self.link.pause()
            self.training.label, self.training.icon = "Resume training", viser.Icon.PLAYER_PLAY
        else:
            self.link.resume()
            self.training.label, self.training.icon = "Pause training", viser.Icon.PLAYER_PAUSE

    def _wire(self, jump: Callable[[viser.ClientHandle | None, Camera], None]) -> None:
        @self.time.on_update
        def _(_: Any) -> None:
            self._set(time=float(self.time.value))

        @self.speed.on_update
        def _(_: Any) -> None:
            self._set(speed=float(self.speed.value))

        @self.play.on_click
        def _(_: Any) -> None:
            playing = not self.state.playing
            self.play.label = "Pause" if playing else "Play"
            self.play.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY
            self._set(playing=playing)

        for box in (self.deform, self.motion, self.depth):
            box.on_update(lambda _: self._set_look())

        @self.view.on_update
        def _(event: Any) -> None:
            jump(event.client, self.views[self.view.value])

    def _set_look(self) -> None:
        look = Look(
            deform=self.deform.value, motion_colors=self.motion.value, depth=self.depth.value
        )
        self._set(look=look)

    def _set(self, **changes: Any) -> None:
        with self.state.lock:
            for name, value in changes.items():
                setattr(self.state, name, value)
            self.state.changed_at = time.time()  # the clock of viser's camera timestamps
        self.wake()

    def advance(self, seconds: float) -> float:
        """Move playback on by `seconds` of wall time (wrapping at t = 1); the new time."""
        with self.state.lock:
            t = (self.state.time + self.state.speed * seconds) % 1.0
        # Assigning calls back into `_set`. viser's value setter takes a wider type than
        # its getter returns, which mypy reads as read-only (python/mypy#3004).
        self.time.value = round(t / TIME_STEP) * TIME_STEP  # type: ignore[misc]
        with self.state.lock:  # the slider shows steps; playback keeps the exact time
            self.state.time = t
        return t

    def snapshot(self) -> ViewState:
        """A copy of the state, to render from without holding the lock."""
        with self.state.lock:
            return dataclasses.replace(self.state, lock=threading.Lock())
