"""Data-parallel training on torch.distributed: the group of processes a run trains in.

`torchrun --nproc-per-node P -m dyngs.cli …` starts P processes and gives each RANK,
WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT. `ProcessGroup.join` reads them and
joins the group (gloo on CPUs, NCCL when the run trains on CUDA); without them, or with
WORLD_SIZE 1, it is a group of one where every collective is a no-op, so one process
trains exactly as it always has.

What the group does for the trainer:
- sums gradients and step statistics over the ranks (`sum_`), takes the largest of
  per-Gaussian maxima (`max_`), so that every rank steps the same model and takes every
  decision that changes its shape from the same numbers;
- checks at the start that every rank resolved the same config (`check_same`);
- lets rank 0 decide what only one process may (`decide`: the run folder's name);
- turns a peer's death or silence into `RankLost`, one line, instead of a hang.

Letters: R ranks.
"""

from __future__ import annotations

import datetime
import hashlib
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import torch
import torch.distributed as dist
from torch import Tensor

from dyngs.errors import ConfigError, UserError

T = TypeVar("T")

ENVIRONMENT = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
"""What torchrun sets for each process it starts."""


class RankLost(UserError):
    """Another process of the run died or stopped answering; this one stops too."""

    def stopped(self, step: int, run_dir: Path) -> RankLost:
        """The same, saying where training stopped and how to go on."""
        return RankLost(
            f"{self}; training stopped at step {step}. The last checkpoint is kept in "
            f"{run_dir}: resume with torchrun … dyngs-train --resume {run_dir}"
        )


def _lost(error: Exception, rank: int) -> RankLost:
    """A failed collective as one line: gloo reports a dead peer as a closed connection
    on the next collective, and a silent one as a timeout."""
    first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    first = re.sub(r"^\[[^\]]*\.(cc|cpp|h):\d+\]\s*", "", first)  # gloo's source location
    first = first.split(". ")[0]  # gloo goes on with advice to read the other's logs
    return RankLost(f"rank {rank}: another process of the run stopped answering ({first})")


@dataclass(frozen=True)
class ProcessGroup:
    """This process's place in the run: `rank` of `size`, `local_rank` on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the one process that writes checkpoints, TensorBoard and metrics."""
        return self.rank == 0

    @staticmethod
    def requested_size() -> int:
        """How many processes the launcher started (WORLD_SIZE; 1 without one)."""
        return int(os.environ.get("WORLD_SIZE", "1"))

    @staticmethod
    def join(timeout_s: float, device: str = "auto") -> ProcessGroup:
        """The group torchrun's environment describes, initialised; one process when the
        environment names none. Collectives wait at most `timeout_s` for the others.
        `device` (the run's `--device`) picks the backend: NCCL when it trains on CUDA."""
        size = ProcessGroup.requested_size()
        if size <= 1:
            return ProcessGroup()
        missing = [name for name in ENVIRONMENT if name not in os.environ]
        if missing:
            raise ConfigError(
                f"WORLD_SIZE is {size} but {', '.join(missing)} is not set: start several "
                "processes with torchrun (torchrun --nproc-per-node P -m dyngs.cli …)"
            )
        group = ProcessGroup(int(os.environ["RANK"]), size, int(os.environ["LOCAL_RANK"]))
        cuda = device != "cpu" and torch.cuda.is_available()
        if cuda:
            torch.cuda.set_device(group.local_rank)
        if not dist.is_initialized():
            dist.init_process_group(
                "nccl" if cuda else "gloo",
                rank=group.rank,
                world_size=size,
                timeout=datetime.timedelta(seconds=timeout_s),
            )
        return group

    def device(self, device: torch.device) -> torch.device:
        """The device this rank trains on: its own GPU (LOCAL_RANK) when the run is on CUDA
        and names no index."""
        if self.distributed and device.type == "cuda" and device.index is None:
            return torch.device("cuda", self.local_rank)
        return device

    def share(self, items: Sequence[T]) -> list[T]:
        """This rank's share of a list every rank holds alike: items r, r + R, r + 2R, …"""
        return list(items[self.rank :: self.size])

    # ------------------------------------------------------------ collectives

    def sum_(self, tensors: Sequence[Tensor]) -> None:
        """Replace each tensor by its sum over the ranks, in place (one collective per
        dtype)."""
        self._reduce(tensors, dist.ReduceOp.SUM)

    def max_(self, tensors: Sequence[Tensor]) -> None:
        """Replace each tensor by its elementwise maximum over the ranks, in place."""
        self._reduce(tensors, dist.ReduceOp.MAX)

    def _reduce(self, tensors: Sequence[Tensor], op: dist.ReduceOp.RedOpType) -> None:
        if not self.distributed or not tensors:
            return
        for dtype in dict.fromkeys(t.dtype for t in tensors):
            same = [t for t in tensors if t.dtype == dtype]
            flat = torch.cat([t.reshape(-1) for t in same])
            self._all_reduce(flat, op)
            offset = 0
            for t in same:
                t.copy_(flat[offset : offset + t.numel()].view_as(t))
                offset += t.numel()

    def _all_reduce(self, flat: Tensor, op: dist.ReduceOp.RedOpType) -> None:
        self._collective(lambda: dist.all_reduce(flat, op=op))

    def gather(self, item: T) -> list[T]:
        """Every rank's `item` (picklable), in rank order."""
        if not self.distributed:
            return [item]
        gathered: list[T | None] = [None] * self.size
        self._collective(lambda: dist.all_gather_object(gathered, item))
        return gathered  # type: ignore[return-value]  # every slot is filled

    def decide(self, choose: Callable[[], T]) -> T:
        """What rank 0's `choose()` returns, on every rank. A `UserError` it raises is
        raised on every rank, so that no rank waits for a decision that never comes."""
        outcome: list[tuple[str, object]] = [("", None)]
        if self.is_main:
            try:
                outcome[0] = ("ok", choose())
            except UserError as error:
                outcome[0] = ("error", str(error))
        if self.distributed:
            self._collective(lambda: dist.broadcast_object_list(outcome, src=0))
        kind, value = outcome[0]
        if kind == "error":
            raise ConfigError(str(value))
        return value  # type: ignore[return-value]  # rank 0's choose() made it

    def check_same(self, text: str, what: str) -> None:
        """Fail, on every rank, unless every rank holds the same `text` (its hash is
        compared): ranks started with different commands would train different models."""
        digest = hashlib.sha256(text.encode()).hexdigest()[:12]
        digests = self.gather(digest)
        differ = [rank for rank, other in enumerate(digests) if other != digests[0]]
        if differ:
            ranks = ", ".join(str(rank) for rank in differ)
            raise ConfigError(
                f"the processes of this run have different {what}: rank(s) {ranks} differ "
                f"from rank 0 ({digests[differ[0]]} against {digests[0]}); start every "
                "process with the same command"
            )

    def _collective(self, call: Callable[[], object]) -> None:
        try:
            call()
        except RuntimeError as error:  # gloo and NCCL errors derive from it
            raise _lost(error, self.rank) from error

    def close(self) -> None:
        """Leave the group, after a run that ended well or failed alike (`dyngs.cli`). With
        a peer killed it returns at once on gloo (tests/engine/test_distributed.py kills
        one); leaving it up at exit let gloo's threads abort the process now and then."""
        if self.distributed and dist.is_initialized():
            dist.destroy_process_group()


SINGLE = ProcessGroup()
"""The group of one process: no collectives, rank 0."""


def check_batch(processes: int, batch_views: int) -> None:
    """Each process renders at least one view per step: P processes need P views."""
    if processes > batch_views:
        raise ConfigError(
            f"{processes} processes but --batch-views {batch_views}: each process renders "
            f"its share of a step's views, so use --batch-views {processes} or more (or "
            f"start at most {batch_views} processes)"
        )
