"""Data-parallel training: batches of views, their strata and shards, and runs of two
processes on the gloo backend held to the one-process batch (docs/DISTRIBUTED.md)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dyngs.datamanagers.datamanager import DataManager, load_scene
from dyngs.datamanagers.procedural import demo_path
from dyngs.datamanagers.sampler import strata
from dyngs.engine.batch import backward_view
from dyngs.engine.checkpoint import load_checkpoint
from dyngs.engine.distributed import SINGLE, check_batch
from dyngs.errors import ConfigError
from tests.engine.helpers import TINY_SCENE, tiny_config, tiny_trainer

# ---------------------------------------------------------------- one process


def test_strata_deal_the_time_order_out_in_turn() -> None:
    times = [0.5, 0.0, 1.0, 0.25, 0.75, 0.1]
    assert strata(times, 1) == [[0, 1, 2, 3, 4, 5]]  # one view per step: every view
    two = strata(times, 2)
    assert sorted(two[0] + two[1]) == list(range(6))
    # Time order 1, 5, 3, 0, 4, 2: every other one each, so both span the sequence.
    assert two == [[1, 3, 4], [0, 2, 5]]


def _manager(batch_views: int, shard: tuple[int, int]) -> DataManager:
    scene = load_scene(demo_path(TINY_SCENE), tiny_config().dataset)
    return DataManager(scene, tiny_config().dataset, torch.device("cpu"),
                       torch.Generator().manual_seed(0), batch_views, shard)  # fmt: skip


def test_ranks_draw_the_same_views_and_hold_only_their_share() -> None:
    whole, first, second = _manager(2, (0, 1)), _manager(2, (0, 2)), _manager(2, (1, 2))
    assert sorted(first.held + second.held) == whole.held == list(range(whole.num_train))
    assert not set(first.held) & set(second.held)
    for step in range(30):
        window = 0.3 if step < 15 else 1.0
        span = 0.1 if step % 3 == 0 else None
        picks = whole.next_views(window, span)
        assert first.next_views(window, span) == second.next_views(window, span) == picks
        assert picks[0] in first.held and picks[1] in second.held
        assert first.train_batch(picks[0]).index == picks[0]
    with pytest.raises(ValueError, match="another process"):
        first.train_batch(second.held[0])
    first.release_others()
    with pytest.raises(ValueError, match="another process"):
        first.scene.train.images[second.held[0]]


def test_batch_state_resumes_and_refuses_another_batch_size() -> None:
    manager = _manager(2, (0, 1))
    for _ in range(7):
        manager.next_views(1.0)
    state = manager.state_dict()
    later = [manager.next_views(1.0) for _ in range(5)]
    again = _manager(2, (1, 2))
    again.load_state_dict(state)
    assert [again.next_views(1.0) for _ in range(5)] == later
    with pytest.raises(ConfigError, match="--batch-views 2"):
        _manager(1, (0, 1)).load_state_dict(state)


def test_more_processes_than_views_is_refused() -> None:
    check_batch(2, 2)
    with pytest.raises(ConfigError, match="2 processes but --batch-views 1"):
        check_batch(2, 1)


def test_one_process_collectives_change_nothing() -> None:
    values = [torch.arange(3.0), torch.ones(2, dtype=torch.float64)]
    SINGLE.sum_(values)
    SINGLE.max_(values)
    assert torch.equal(values[0], torch.arange(3.0)) and torch.equal(values[1], torch.ones(2))
    assert SINGLE.share([1, 2, 3]) == [1, 2, 3]
    assert SINGLE.decide(lambda: "name") == "name"
    SINGLE.check_same("anything", "configs")


def test_backward_view_keeps_each_views_mean_gradient_and_their_sum() -> None:
    means = torch.tensor([1.0, 2.0], requires_grad=True)
    other = torch.tensor([3.0], requires_grad=True)
    first = backward_view((means * 2).sum() + other.sum(), means)
    second = backward_view((means * means).sum() + 2 * other.sum(), means)
    assert first is not None and second is not None
    assert torch.equal(first, torch.tensor([2.0, 2.0]))
    assert torch.equal(second, torch.tensor([2.0, 4.0]))
    assert torch.equal(means.grad, first + second)  # type: ignore[arg-type]
    assert torch.equal(other.grad, torch.tensor([3.0]))  # type: ignore[arg-type]


def test_a_batch_of_views_trains_and_averages_the_loss(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, batch_views=3, max_iters=6)
    for step in range(6):
        stats = trainer.train_step(step)
        trainer.step = step + 1
        assert stats.applied and torch.isfinite(stats.loss)
    assert trainer.data.state_dict()["strata"] is not None


# ---------------------------------------------------------------- two processes

STEPS = 40


def _train_args(run: Path, steps: int = STEPS, *extra: str) -> list[str]:
    """A tiny run with a batch of two views that densifies every 10 steps."""
    return [
        "hexplane-4dgs", "--data", str(demo_path(TINY_SCENE)), "--output-dir", str(run.parent),
        "--run-name", run.name, "--max-iters", str(steps), "--warmup-iters", "2",
        "--batch-views", "2", "--no-tensorboard", "--num-random-points", "500",
        "--field.resolution", "8", "8", "8", "4", "--field.multires", "1",
        "--field.features", "8", "--densify.refine-start", "10", "--densify.refine-every",
        "10", "--densify.grad-threshold", "1e-5", "--densify.importance-views", "4", *extra,
    ]  # fmt: skip


def _env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


def _torchrun(processes: int, args: list[str]) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone",
            f"--nproc-per-node={processes}", "-m", "dyngs.cli", *args]  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ranks(args: list[list[str]], log_dir: Path) -> list[subprocess.Popen[bytes]]:
    """One process per rank, started as torchrun would (its environment, no agent)."""
    port, processes = _free_port(), []
    for rank, rank_args in enumerate(args):
        env = {**_env(), "RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": str(len(args)),
               "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}  # fmt: skip
        log = open(log_dir / f"rank{rank}.log", "wb")
        command = [sys.executable, "-m", "dyngs.cli", *rank_args]
        processes.append(subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env))
    return processes


@pytest.mark.slow
def test_two_processes_train_what_one_process_trains_with_the_same_batch(tmp_path: Path) -> None:
    one, two = tmp_path / "one", tmp_path / "two"
    # With the 3D filter on, whose refresh shares the views out and exchanges the maxima.
    flags = ("--gaussians.filter-3d", "0.2")
    subprocess.run([sys.executable, "-m", "dyngs.cli", *_train_args(one, STEPS, *flags)],
                   check=True, capture_output=True, env=_env())  # fmt: skip
    done = subprocess.run(_torchrun(2, _train_args(two, STEPS, *flags)), capture_output=True,
                          env=_env())  # fmt: skip
    assert done.returncode == 0, done.stderr.decode()[-3000:]
    a, b = load_checkpoint(one / "checkpoint.pt"), load_checkpoint(two / "checkpoint.pt")
    assert a["step"] == b["step"] == STEPS
    n_before = 500  # the tiny run's initial points: densification changed the count
    assert len(a["model"]["canonical.means"]) == len(b["model"]["canonical.means"]) != n_before
    assert bool((a["model"]["filter_std"] > 0).all())
    for key, value in a["model"].items():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            torch.testing.assert_close(b["model"][key], value, rtol=1e-4, atol=1e-5, msg=key)
        elif isinstance(value, torch.Tensor):
            assert torch.equal(b["model"][key], value), key
    assert a["data"] == b["data"]
    assert (two / "metrics.json").is_file() and (two / "config.json").is_file()


def _checkpoint_step(run: Path) -> int:
    try:
        return int(load_checkpoint(run / "checkpoint.pt")["step"])
    except (FileNotFoundError, ConfigError):
        return -1


@pytest.mark.slow
def test_a_killed_rank_stops_the_run_which_resumes_with_another_process_count(
    tmp_path: Path,
) -> None:
    run, steps = tmp_path / "killed", 400
    args = _train_args(run, steps, "--checkpoint-every", "5")
    ranks = _ranks([args, args], tmp_path)
    try:
        while _checkpoint_step(run) < 5:  # however long the machine takes to get there
            assert all(r.poll() is None for r in ranks), (tmp_path / "rank0.log").read_text()
            time.sleep(0.05)
        ranks[1].send_signal(signal.SIGKILL)
        code = ranks[0].wait(timeout=300)
    finally:
        for r in ranks:
            r.kill() if r.poll() is None else None
    said = (tmp_path / "rank0.log").read_text()
    assert code == 2, said
    assert "another process of the run stopped answering" in said and "--resume" in said
    kept = _checkpoint_step(run)
    assert 5 <= kept < steps
    # Resumed by one process: the batch of two views is kept, only who renders it changes.
    subprocess.run([sys.executable, "-m", "dyngs.cli", "--resume", str(run)], check=True,
                   capture_output=True, env=_env())  # fmt: skip
    assert _checkpoint_step(run) == steps


@pytest.mark.slow
def test_ranks_started_with_different_configs_refuse_to_train(tmp_path: Path) -> None:
    run = tmp_path / "mixed"
    ranks = _ranks([_train_args(run), _train_args(run, STEPS, "--seed", "1")], tmp_path)
    codes = [r.wait(timeout=300) for r in ranks]
    assert codes == [2, 2]
    for rank in range(2):
        said = (tmp_path / f"rank{rank}.log").read_text()
        assert "different configs: rank(s) 1 differ from rank 0" in said, said
    assert not (run / "checkpoint.pt").exists()
