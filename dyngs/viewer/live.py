"""`dyngs-train --viewer`: the viewer of a run as it trains.

`LiveViewer` is the step hook `run_training` is given. After the first step it serves the
page (the scene's cameras are known by then) and from then on hands the viewer the
model through a `TrainingLink`: a snapshot when the page asks, never a render in the
training thread. When training ends, `finished` shows the final model (the run folder's
checkpoint: the end of training may still prune and crop).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console

from dyngs.datamanagers.scene_info import SceneInfo
from dyngs.renderers import renderer_name
from dyngs.runs import load_run
from dyngs.viewer.frames import fastest_renderer
from dyngs.viewer.options import ViewerOptions
from dyngs.viewer.server import Viewer
from dyngs.viewer.training import TrainingLink

if TYPE_CHECKING:
    from dyngs.engine.report import StepStats
    from dyngs.engine.trainer import Trainer


class LiveViewer:
    """A `StepHook` that serves the viewer of the training run and can pause it."""

    def __init__(self, options: ViewerOptions, console: Console) -> None:
        self.options, self.console = options, console
        self.link = TrainingLink()
        self.viewer: Viewer | None = None
        self.device = "cpu"

    def __call__(self, trainer: Trainer, stats: StepStats) -> None:
        if self.viewer is None:
            self._start(trainer)
        self.link(trainer, stats)

    def _start(self, trainer: Trainer) -> None:
        self.device = str(trainer.device)
        renderer = fastest_renderer(trainer.device)
        scene = SceneInfo.of(trainer.scene)
        title = f"dyngs · {trainer.run_dir.name} (training)"
        self.viewer = Viewer(scene, renderer.build(), self.options, self.link, title)
        url = self.viewer.start()
        self.console.print(
            f"viewer at {url}: the model as it trains ({renderer_name(renderer)}); "
            "its page can pause training",
            highlight=False,
        )

    def finished(self, run_dir: Path) -> None:
        """Show the run's final model (from its folder) instead of training snapshots."""
        if self.viewer is None:
            return
        run = load_run(run_dir, device=self.device)
        self.viewer.training_ended(run.model, f"step {run.step:,}: training finished")

    def wait_if_interactive(self) -> None:
        """On a terminal, keep showing the final model until Ctrl-C; elsewhere (a script,
        a CI job) return at once, so the command still ends with its run."""
        if self.viewer is None or not self.console.is_terminal:
            return
        self.console.print(
            f"the viewer at {self.viewer.url} shows the final model; Ctrl-C closes it"
        )
        stop = threading.Event()
        while not stop.wait(0.5):  # short waits, so Ctrl-C is seen at once
            pass

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.stop()
            self.viewer = None
