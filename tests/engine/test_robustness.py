"""A trainer that never loses a run: non-finite steps are skipped and counted, a streak of
them stops the run with its last good checkpoint, and Ctrl-C or SIGKILL lose nothing."""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dyngs.datamanagers.procedural import demo_path
from dyngs.engine.checkpoint import load_checkpoint
from dyngs.engine.trainer import TrainingDiverged, all_finite
from dyngs.engine.writer import NullWriter
from dyngs.renderers.base import RenderOutput
from tests.engine.helpers import TINY_SCENE, assert_same_state, tiny_trainer


class PoisonedRenderer:
    """Wraps a renderer and returns NaN images on chosen calls."""

    def __init__(self, inner, bad_calls: set[int]) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.bad_calls, self.calls = inner, bad_calls, 0

    def __call__(self, gaussians, camera, background, **options) -> RenderOutput:  # type: ignore[no-untyped-def]
        out = self.inner(gaussians, camera, background, **options)
        if self.calls in self.bad_calls:
            out.rgb = out.rgb * float("nan")
        self.calls += 1
        return out


def _snapshot(trainer) -> dict[str, torch.Tensor]:  # type: ignore[no-untyped-def]
    state = trainer.model.state_dict()
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in state.items()}


@pytest.mark.parametrize("bad", [None, "nan", "inf", "-inf", "loss"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_fused_finiteness_check_is_the_per_tensor_one(
    bad: str | None, dtype: torch.dtype
) -> None:
    # all_finite checks every gradient in one fused call per dtype; the reference is an
    # isfinite per tensor. Gradients of two dtypes, one missing, the bad value in each.
    gen = torch.Generator().manual_seed(7)
    params = [torch.nn.Parameter(torch.zeros(n, dtype=d))
              for n, d in ((1000, dtype), (7, torch.float32), (3, dtype), (50, dtype))]  # fmt: skip
    optimizer = torch.optim.SGD([{"params": params[:2]}, {"params": params[2:]}], lr=0.1)
    for where in range(3):
        for p in params[:3]:
            p.grad = torch.randn(p.shape, generator=gen, dtype=p.dtype)
        loss = torch.tensor(float("nan") if bad == "loss" else 0.5)
        if bad in ("nan", "inf", "-inf"):
            params[where].grad[-1] = float(bad)  # type: ignore[index]
        before = [p.grad.clone() for p in params[:3]]  # type: ignore[union-attr]
        want = bool(torch.isfinite(loss)) and all(
            bool(torch.isfinite(p.grad).all()) for p in params if p.grad is not None
        )
        assert bool(all_finite(loss, optimizer)) == want == (bad is None)
        for p, old in zip(params[:3], before, strict=True):  # the check leaves them as they were
            assert torch.equal(p.grad.nan_to_num(), old.nan_to_num())  # type: ignore[union-attr]


def test_non_finite_steps_are_skipped_and_counted(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, warmup_iters=0)
    trainer.renderer = PoisonedRenderer(trainer.renderer, bad_calls={1, 2})
    trainer.train_step(0)
    before = _snapshot(trainer)
    moments = {
        id(p): {k: v.clone() for k, v in s.items()} for p, s in trainer.optimizer.state.items()
    }
    for step in (1, 2):
        stats = trainer.train_step(step)
        assert not stats.applied and not torch.isfinite(stats.loss)
    after = _snapshot(trainer)
    assert_same_state(before, after)  # nothing reached the parameters
    for p, s in trainer.optimizer.state.items():
        assert all(torch.equal(v, moments[id(p)][k]) for k, v in s.items())
    assert trainer.counters.skipped_steps == 2 and trainer.counters.bad_streak == 2
    assert trainer.train_step(3).applied and trainer.counters.bad_streak == 0
    assert torch.isfinite(trainer.model.canonical.means).all()


class _Scalars(NullWriter):
    def __init__(self) -> None:
        self.values: dict[str, float] = {}

    def scalar(self, tag: str, value: float, step: int) -> None:
        self.values[tag] = value


def test_gaussians_with_nan_parameters_are_culled_counted_and_reported(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, warmup_iters=0)
    trainer.writer = writer = _Scalars()
    with torch.no_grad():
        trainer.model.canonical.means[3, 1] = float("nan")
        trainer.model.canonical.log_scales[7, 0] = float("inf")
    stats = trainer.train_step(0)
    assert stats.applied and torch.isfinite(stats.loss)  # culled, never propagated
    others = torch.ones(len(trainer.model.canonical), dtype=torch.bool)
    others[[3, 7]] = False
    assert torch.isfinite(trainer.model.canonical.means[others]).all()
    info = trainer.log(stats, rate=1.0)
    assert "culled non-finite 2" in info
    assert writer.values["train/nonfinite_gaussians_culled"] == 2
    assert "culled" not in trainer.log(stats, rate=1.0)  # counted per log interval


def test_a_streak_of_bad_steps_stops_with_the_checkpoint_intact(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, warmup_iters=0, max_bad_steps=3)
    trainer.train_step(0)
    trainer.step = 1
    trainer.save()
    saved = load_checkpoint(trainer.checkpoint_path())
    trainer.renderer = PoisonedRenderer(trainer.renderer, bad_calls=set(range(100)))
    with pytest.raises(TrainingDiverged, match="3 consecutive steps had a non-finite loss"):
        for step in range(1, 10):
            trainer.train_step(step)
    kept = load_checkpoint(trainer.checkpoint_path())
    assert kept["step"] == 1
    assert_same_state(saved["model"], kept["model"])


# ---------------------------------------------------------------- real processes


def _train_command(run_dir: Path, max_iters: int) -> list[str]:
    return [
        sys.executable, "-m", "dyngs.cli", "hexplane-4dgs",
        "--data", str(demo_path(TINY_SCENE)),
        "--max-iters", str(max_iters), "--warmup-iters", "4", "--checkpoint-every", "2",
        "--no-tensorboard", "--field.resolution", "8", "8", "8", "4", "--field.multires", "1",
        "--field.features", "8", "--num-random-points", "500",
        "--output-dir", str(run_dir.parent), "--run-name", run_dir.name,
    ]  # fmt: skip


def _checkpoint_step(run_dir: Path) -> int:
    path = run_dir / "checkpoint.pt"
    try:
        return int(load_checkpoint(path)["step"]) if path.exists() else -1
    except Exception:
        return -1


def _wait_for_step(process: subprocess.Popen, run_dir: Path, step: int) -> int:
    """Poll until the run has a checkpoint at `step` or later; however long that takes on
    a busy machine, it ends when the checkpoint is there or the process is gone."""
    while True:
        reached = _checkpoint_step(run_dir)
        if reached >= step:
            return reached
        if process.poll() is not None:
            raise AssertionError(f"training ended (code {process.returncode}) before step {step}")
        time.sleep(0.05)


@pytest.mark.slow
def test_sigkill_at_a_random_step_then_resume_equals_an_uninterrupted_run(tmp_path: Path) -> None:
    total = 200  # long enough that the kill lands before the end, however fast a step is
    env = dict(os.environ)
    straight = tmp_path / "straight"
    subprocess.run(_train_command(straight, total), check=True, capture_output=True, env=env)

    killed = tmp_path / "killed"
    kill_after = random.Random().randrange(4, total // 2)
    process = subprocess.Popen(_train_command(killed, total), stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, env=env)  # fmt: skip
    try:
        # Killed as soon as the step is seen: it lands wherever the run is by then, in a
        # step or in the middle of writing the next checkpoint.
        _wait_for_step(process, killed, kill_after)
        process.send_signal(signal.SIGKILL)
        process.wait()
    finally:
        if process.poll() is None:
            process.kill()
    at_kill = _checkpoint_step(killed)
    assert 0 < at_kill < total, f"killed after step {kill_after}; checkpoint at {at_kill}"

    subprocess.run([sys.executable, "-m", "dyngs.cli", "--resume", str(killed)], check=True,
                   capture_output=True, env=env)  # fmt: skip
    a = load_checkpoint(straight / "checkpoint.pt")
    b = load_checkpoint(killed / "checkpoint.pt")
    assert a["step"] == b["step"] == total
    assert_same_state(a["model"], b["model"], f"(killed at {at_kill})")
    for key in ("lifecycle", "data"):
        assert str(a[key]) == str(b[key])


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
def test_ctrl_c_saves_a_checkpoint_and_exits_cleanly(tmp_path: Path) -> None:
    run = tmp_path / "interrupted"
    # The run gets SIGINT's default disposition, as from a terminal, even when this test
    # run inherited it ignored (started in the background by a non-interactive shell).
    # Python keeps an ignored SIGINT ignored, and so does dyngs-train.
    process = subprocess.Popen(_train_command(run, 10_000), stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True,
                               preexec_fn=_default_sigint)  # fmt: skip
    try:
        _wait_for_step(process, run, 4)
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate()  # it stops after the current step, however slow
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, output
    assert "Traceback" not in output
    # It stops between steps, and the checkpoint holds the step it names.
    stopped = re.search(r"interrupted at step (\d+)", output)
    assert stopped is not None, output
    assert _checkpoint_step(run) == int(stopped.group(1)) >= 4
