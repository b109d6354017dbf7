"""benchmarks/deal_tiles.py: its deal in turn is the rule cpu-tile used before `_Plan.deal`,
and its imbalance measure reads a deal's bounds."""

from __future__ import annotations

import numpy as np
import torch

from dyngs.renderers import cpu_tile
from dyngs.renderers.base import Guards
from dyngs.renderers.stages import TileBins
from tests.tools.conftest import load_benchmark


def _plan(counts: list[int]) -> cpu_tile._Plan:
    count = torch.tensor(counts)
    bins = TileBins(torch.zeros(int(count.sum()), dtype=torch.long), count.cumsum(0) - count,
                    count)  # fmt: skip
    return cpu_tile._Plan(bins, (8 * len(counts), 8, 8), Guards(), 2, False, True)


def test_in_turn_deals_busiest_first_alternately() -> None:
    deal_tiles = load_benchmark("deal_tiles")
    order, bounds = deal_tiles.in_turn(_plan([0, 5, 3, 3, 2, 0, 7, 1]))
    # Busiest first: 6 (7), 1 (5), 2 (3), 3 (3), 4 (2), 7 (1); thread 0 takes the 1st,
    # 3rd and 5th, thread 1 the others.
    assert bounds.tolist() == [0, 3, 6]
    assert order.tolist() == [6, 2, 4, 1, 3, 7]


def test_busiest_excess_is_the_busiest_threads_cells_over_the_mean() -> None:
    deal_tiles = load_benchmark("deal_tiles")
    work = np.array([[30, 1], [10, 1], [20, 1], [0, 0]])
    assert deal_tiles.busiest_excess(work, np.array([0, 2, 4])) == 40 / 30 - 1
    assert deal_tiles.busiest_excess(work, np.array([0, 4, 4])) == 1.0  # one idle thread
    assert deal_tiles.busiest_excess(np.zeros((0, 2)), np.array([0, 0, 0])) == 0.0
