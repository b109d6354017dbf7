"""The views of one step: each view's loss goes backward alone, its statistics kept, then
gradients and statistics are summed over the processes.

A step of `--batch-views V` minimises the mean of its views' losses. Each view's loss,
divided by V, goes backward on its own (one view's graph in memory at a time), and the
gradients add up in the parameters as autograd accumulates them. Under P processes each
rank does this for its share of the views, then `exchange` sums the gradients, the loss
and the densification statistics over the ranks: the result is the one-process batch
mean, up to the order of the float sums. Every rank then holds the same gradients and the
same statistics, so every optimizer step and every change of the model's shape is the
same on every rank.

Letters: N Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dyngs.datamanagers.datamanager import TrainBatch
from dyngs.engine.densify import StepStatistics
from dyngs.engine.distributed import ProcessGroup
from dyngs.renderers.base import RenderOutput


@dataclass
class ViewResult:
    """What one view of a step left: its loss and terms (detached, not divided by the
    view count), its render, and its densification statistics."""

    loss: Tensor
    terms: dict[str, Tensor]
    out: RenderOutput
    batch: TrainBatch
    stats: StepStatistics | None


def backward_view(loss: Tensor, means: Tensor) -> Tensor | None:
    """Backward of one view's `loss`, gradients added to the parameters' as usual; returns
    the part `means` got from this view alone (what the view's pull statistic needs).

    `means.grad` is set aside and restored as (earlier + this view's): the same sum
    autograd's accumulation makes, so a batch's gradient does not depend on this."""
    earlier = means.grad
    means.grad = None
    loss.backward()
    own = means.grad
    if earlier is not None:
        means.grad = earlier if own is None else earlier + own
    return own


def step_loss(results: list[ViewResult], views: int) -> Tensor:
    """This rank's share of the step's loss: Σ of its views' losses / `views`."""
    total = torch.stack([r.loss for r in results]).sum()
    return total if views == 1 else total / views


def step_statistics(results: list[ViewResult]) -> StepStatistics | None:
    """This rank's views' statistics together (None when no view reached the screen)."""
    stats = [r.stats for r in results if r.stats is not None]
    if not stats:
        return None
    combined = stats[0]
    for other in stats[1:]:
        combined = combined.combine(other)
    return combined


def exchange(
    group: ProcessGroup,
    optimizer: torch.optim.Optimizer,
    loss: Tensor,
    stats: StepStatistics | None,
    n: int,
) -> StepStatistics | None:
    """Sum the gradients, the loss (in place) and the statistics over the ranks and take
    the statistics' maxima; returns the whole step's statistics (`n` Gaussians). A no-op
    with one process.

    A parameter no view of any rank reached keeps no gradient (as in one process, so that
    Adam leaves it alone); one that some rank's view reached gets the sum."""
    if not group.distributed:
        return stats
    params = [p for g in optimizer.param_groups for p in g["params"]]
    # Which parameters any rank reached, first (a few bytes): the field gets no gradient
    # through the static warm-up, and its zeros need not travel.
    reached = torch.tensor([float(p.grad is not None) for p in params], device=loss.device)
    group.sum_([reached])
    params = [p for p, any_rank in zip(params, reached.tolist(), strict=True) if any_rank > 0]
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    stats = stats or StepStatistics.zeros(n, loss.device)
    group.sum_([*(p.grad for p in params if p.grad is not None), loss, *stats.sums()])
    group.max_(stats.maxima())
    return stats
