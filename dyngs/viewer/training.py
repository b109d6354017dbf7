"""The link between a training run and the viewer: a step hook that hands the viewer a
copy of the model when it asks for one, and holds training while the page pauses it.

The hook runs in the training thread after every step (`dyngs.engine.trainer.StepHook`).
On most steps it only reads two flags. When the viewer has asked for the current model it
clones the model's tensors (a memory copy, no rebuild, no render), so training never waits
for a frame; the viewer rebuilds the model from the copy on its own thread. Measured hook
times are in docs/VIEWER.md.
"""

from __future__ import annotations

import signal
import statistics
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType
from typing import TYPE_CHECKING, Any

import torch

from dyngs.config import TrainConfig
from dyngs.model import DynamicGaussians

if TYPE_CHECKING:
    from dyngs.engine.report import StepStats
    from dyngs.engine.trainer import Trainer

PAUSE_POLL_SECONDS = 0.05
"""How often a paused hook looks for a snapshot request or the end of the pause."""


@dataclass(frozen=True)
class Snapshot:
    """The model's tensors at one step, enough to rebuild it away from training."""

    state: dict[str, Any]
    config: TrainConfig
    step: int
    steps: int
    """The run's planned step count."""

    def model(self) -> DynamicGaussians:
        """The model as it was at `step` (built anew: training goes on with its own)."""
        cfg = self.config
        return DynamicGaussians.load(cfg.gaussians, cfg.field, cfg.head, self.state).eval()


def clone_state(model: DynamicGaussians) -> dict[str, Any]:
    """A copy of the model's state_dict whose tensors training will not change."""
    return {
        key: value.detach().clone() if isinstance(value, torch.Tensor) else value
        for key, value in model.state_dict().items()
    }


class TrainingLink:
    """A `StepHook` for the viewer: snapshots on request, pause and resume."""

    def __init__(self) -> None:
        self._requested = threading.Event()
        self._running = threading.Event()  # cleared while paused
        self._running.set()
        self._lock = threading.Lock()
        self._snapshot: Snapshot | None = None
        self.hook_seconds: list[float] = []
        """Time each snapshot held the training thread."""
        self.step = 0

    # -------------------------------------------------------------- viewer side

    def request(self) -> None:
        """Ask for a snapshot at the end of the next step (or now, if paused)."""
        self._requested.set()

    def take(self) -> Snapshot | None:
        """The newest snapshot not yet taken, if any."""
        with self._lock:
            snapshot, self._snapshot = self._snapshot, None
        return snapshot

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def hook_summary(self) -> str:
        """Median and longest time a snapshot held training, for the page."""
        if not self.hook_seconds:
            return "no snapshot yet"
        median = statistics.median(self.hook_seconds) * 1e3
        return f"snapshot {median:.1f} ms (longest {max(self.hook_seconds) * 1e3:.1f} ms)"

    # ------------------------------------------------------------ training side

    def __call__(self, trainer: Trainer, stats: StepStats) -> None:
        self.step = trainer.step
        self._serve(trainer)
        if self.paused:
            with _resume_on_interrupt(self):
                while not self._running.wait(PAUSE_POLL_SECONDS):
                    self._serve(trainer)

    def _serve(self, trainer: Trainer) -> None:
        if not self._requested.is_set():
            return
        self._requested.clear()
        started = time.perf_counter()
        snapshot = Snapshot(clone_state(trainer.model), trainer.config, trainer.step,
                            trainer.config.steps)  # fmt: skip
        with self._lock:
            self._snapshot = snapshot
        self.hook_seconds.append(time.perf_counter() - started)


@contextmanager
def _resume_on_interrupt(link: TrainingLink) -> Iterator[None]:
    """While paused in the main thread, Ctrl-C resumes training as well as doing what it
    did before (the trainer's first Ctrl-C stops at the end of the step), so a paused
    run still stops on one Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)

    def on_interrupt(signum: int, frame: FrameType | None) -> None:
        link.resume()
        if callable(previous):
            previous(signum, frame)
        elif previous == signal.SIG_DFL:
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, on_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
