"""The viewer without a browser: its render path and toggles, the port check and its one-line
error, the `--viewer` flags of dyngs-train, and the training hook's snapshots and pause.
(tests/tools/test_view_browser.py drives the page in Chromium.)"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from dyngs.cli import main as train_main
from dyngs.cli import split_viewer_args
from dyngs.errors import ConfigError
from dyngs.runs import LoadedRun, load_run
from dyngs.tools.view import main as view_main
from dyngs.viewer.frames import DYNAMIC_COLOR, STATIC_COLOR, Look, draw, model_summary
from dyngs.viewer.options import PortTaken, ViewerOptions, check_port
from dyngs.viewer.training import Snapshot, TrainingLink
from tests.engine.helpers import output_layer, tiny_trainer
from tests.tools.conftest import TINY_FLAGS


@pytest.fixture(scope="module")
def fading(fading_run: Path) -> LoadedRun:
    return load_run(fading_run)


def _frame(run: LoadedRun, t: float, look: Look | None = None) -> np.ndarray:
    camera = run.scene.train.cameras[0]
    image = draw(run.model, run.renderer, camera, t, run.scene.background, look or Look())
    return image.astype(float)


def test_the_frame_follows_time(fading: LoadedRun) -> None:
    assert np.abs(_frame(fading, 0.0) - _frame(fading, 1.0)).mean() > 5  # of 255


def test_deformation_off_draws_the_canonical_gaussians(fading_run: Path) -> None:
    run = load_run(fading_run)
    with torch.no_grad():  # three steps leave the head at zero: make it move the dynamic half
        layer = output_layer(run.model.head, "means")
        assert layer is not None
        layer.bias.fill_(0.2)
    camera, background = run.scene.train.cameras[0], run.scene.background
    with torch.no_grad():
        canonical = run.renderer(run.model.at(0.3, deform=False), camera, background).rgb
    off, on = _frame(run, 0.3, Look(deform=False)), _frame(run, 0.3)
    assert np.abs(off - canonical.numpy() * 255).max() <= 0.5 + 1e-3  # 8-bit rounding only
    assert np.abs(on - off).mean() > 1  # and with deformation on, the dynamic half moved


def test_motion_colours_paint_static_and_dynamic_gaussians(fading: LoadedRun) -> None:
    image = _frame(fading, 0.0, Look(motion_colors=True))
    drawn = np.abs(image - fading.scene.background.numpy() * 255).max(-1) > 10
    # Every drawn pixel is a blend of the two colours and the background: its hue lies
    # between blue and orange, never green- or purple-dominant as the scene's own are.
    red_minus_blue = image[..., 0] - image[..., 2]
    assert (red_minus_blue[drawn] > 60).mean() > 0.05
    assert (red_minus_blue[drawn] < -60).mean() > 0.05
    # And the most orange pixel is the dynamic colour over the background, the most blue
    # the static one: background + w · (paint − background), mostly paint. (Not the paint
    # alone: the antialiased renderer draws the tiny run's small Gaussians at less than
    # full opacity.)
    pixels = image.reshape(-1, 3).astype(np.float64)
    background = fading.scene.background.numpy() * 255
    for pixel, paint in (
        (pixels[red_minus_blue.argmax()], np.array(DYNAMIC_COLOR) * 255),
        (pixels[red_minus_blue.argmin()], np.array(STATIC_COLOR) * 255),
    ):
        towards = paint - background
        w = float((pixel - background) @ towards / (towards @ towards))
        assert w > 0.5
        assert np.abs(background + w * towards - pixel).max() < 10


def test_depth_is_a_ramp_over_what_is_drawn(fading: LoadedRun) -> None:
    image = _frame(fading, 0.0, Look(depth=True))
    with torch.no_grad():
        out = fading.renderer(fading.model.at(0.0), fading.scene.train.cameras[0],
                              fading.scene.background)  # fmt: skip
    empty = out.alpha[..., 0].numpy() < 0.5
    assert empty.any() and (~empty).any()
    assert (image[empty] == 0).all() and (image[~empty].max(-1) > 0).all()
    assert len(np.unique(image[~empty].reshape(-1, 3), axis=0)) > 10  # a ramp, not a flat fill


def test_the_model_summary_counts_gaussians_and_dynamic_share(fading: LoadedRun) -> None:
    count = len(fading.model.canonical)
    assert model_summary(fading.model).startswith(f"{count:,} Gaussians (50 % dynamic), ")
    assert model_summary(fading.model).endswith(" MiB")


# ---------------------------------------------------------------------- the port


@pytest.fixture
def taken_port() -> Iterator[int]:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        yield listener.getsockname()[1]


def test_a_taken_port_is_one_clear_line(
    taken_port: int, tiny_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(PortTaken, match=f"127.0.0.1:{taken_port}.*--port"):
        check_port("127.0.0.1", taken_port)
    with pytest.raises(SystemExit) as exit_info:
        view_main(["--load-dir", str(tiny_run), "--host", "127.0.0.1",
                   "--port", str(taken_port)])  # fmt: skip
    assert exit_info.value.code == 2
    said = capsys.readouterr().out.strip()
    assert said.startswith("error:") and f"127.0.0.1:{taken_port}" in said and "--port" in said
    assert "\n" not in said


def test_a_free_port_passes() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free = probe.getsockname()[1]
    check_port("127.0.0.1", free)
    check_port("127.0.0.1", 0)


def test_train_refuses_a_taken_viewer_port_before_training(
    taken_port: int, tiny_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        train_main(["hexplane-4dgs", "--data", str(tiny_data), "--output-dir", str(tmp_path),
                    "--viewer", "--viewer-host", "127.0.0.1",
                    f"--viewer-port={taken_port}"])  # fmt: skip
    assert exit_info.value.code == 2
    assert f"127.0.0.1:{taken_port}" in capsys.readouterr().out
    assert not any(tmp_path.iterdir())  # no run folder was made


# ------------------------------------------------------------ dyngs-train flags


def test_viewer_flags_are_taken_out_of_the_training_arguments() -> None:
    assert split_viewer_args(["hexplane-4dgs", "--data", "x"]) == (
        None, ["hexplane-4dgs", "--data", "x"],
    )  # fmt: skip
    options, rest = split_viewer_args(["--viewer", "hexplane-4dgs", "--viewer-port", "9000"])
    assert options == ViewerOptions(port=9000) and rest == ["hexplane-4dgs"]
    options, rest = split_viewer_args(["--resume", "RUN", "--viewer-host=0.0.0.0"])
    assert options == ViewerOptions(host="0.0.0.0") and rest == ["--resume", "RUN"]
    with pytest.raises(ConfigError, match="--viewer-port needs a value"):
        split_viewer_args(["--viewer-port"])
    with pytest.raises(ConfigError, match="must be a number"):
        split_viewer_args(["--viewer-port", "http"])


# ----------------------------------------------------------- the training hook


def _wait(condition: Callable[[], bool], what: str) -> None:
    """Poll a condition the training thread will make true (generous limit, no race)."""
    deadline = time.monotonic() + 60
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def _taken(link: TrainingLink) -> Snapshot:
    """The snapshot the training thread will hand over (waited for, generous limit)."""
    taken: list[Snapshot] = []

    def took() -> bool:
        snapshot = link.take()
        taken.extend([snapshot] if snapshot is not None else [])
        return bool(taken)

    _wait(took, "no snapshot came")
    return taken[0]


@pytest.mark.slow
def test_the_hook_snapshots_on_request_and_holds_training_while_paused(tmp_path: Path) -> None:
    link = TrainingLink()
    trainer = tiny_trainer(tmp_path, max_iters=3)
    trainer.hooks.append(link)
    link.pause()
    link.request()
    training = threading.Thread(target=trainer.train, daemon=True)
    training.start()
    try:
        first = _taken(link)
        assert first.step == 1
        link.request()  # served while paused, at the same step
        again = _taken(link)
        assert again.step == 1 and trainer.step == 1 and training.is_alive()
    finally:  # a failed assertion must not leave training paused
        link.resume()
        training.join()
    assert trainer.step == 3
    # The snapshot is a copy: training went on without changing it.
    model = first.model()
    assert len(model.canonical) == first.state["canonical.means"].shape[0]
    assert not torch.equal(first.state["canonical.means"], trainer.model.canonical.means.detach())
    assert link.hook_seconds and "snapshot" in link.hook_summary()


@pytest.mark.slow
def test_train_with_the_viewer_serves_it_and_ends_with_the_run(
    tiny_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    train_main(["hexplane-4dgs", "renderer:cpu-reference", "--data", str(tiny_data),
                "--output-dir", str(tmp_path), "--run-name", "run", "--max-iters", "3",
                *TINY_FLAGS, "--viewer", "--viewer-host", "127.0.0.1",
                "--viewer-port", "0"])  # fmt: skip
    said = capsys.readouterr().out
    assert "viewer at http://127.0.0.1:" in said and "can pause training" in said
    assert (tmp_path / "run" / "metrics.json").is_file()
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert not [key for key in config if "viewer" in key]  # not part of the training recipe
