"""Which training views a step draws: shuffled epochs and frontier draws, over strata.

A step of `--batch-views V` draws one view from each of V strata: the training views in
time order, dealt out in turn (view j of the time order goes to stratum j mod V), so
that every stratum spans the whole sequence and a time window or a frontier holds views
of each. Each stratum is a `ViewSampler` with its own seed; with V = 1 the one stratum is
every view, drawn exactly as the datamanager always drew them.

The strata depend on V alone, never on how many processes train: every rank draws the
same views, and rank r renders (and loads the images of) strata r, r + P, … only.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right

import torch

STRATUM_SEED_STRIDE = 2**40
"""Stratum k's seed is the run's data seed + k × this: far apart from any epoch count."""
FRONTIER_SEED_OFFSET = 2**62
"""Frontier draw k uses seed + this + k, so the draws never repeat an epoch's permutation."""


def strata(times: list[float], count: int) -> list[list[int]]:
    """The views (indices into `times`) of each of `count` strata, each in index order."""
    by_time = sorted(range(len(times)), key=times.__getitem__)
    return [sorted(by_time[k::count]) for k in range(count)]


class ViewSampler:
    """Shuffled epochs and frontier draws over `views` (split indices, in index order) of
    a split whose view times are `times`.

    Epoch e is a permutation drawn from a generator seeded with (seed + e); frontier draw
    k from one seeded with (seed + 2⁶² + k): the whole state is three integers."""

    def __init__(self, times: list[float], views: list[int], seed: int) -> None:
        if not views:
            raise ValueError("a sampler needs at least one view")
        self.views = views
        self.times = [times[i] for i in views]
        self.seed = seed
        self.epoch = 0
        self.position = 0
        self.frontier_draws = 0
        self.order = self._permutation(0)
        self.earliest = min(self.times)
        self.by_time = sorted(range(len(views)), key=self.times.__getitem__)
        self.sorted_times = [self.times[i] for i in self.by_time]

    def _permutation(self, epoch: int) -> list[int]:
        generator = torch.Generator().manual_seed(self.seed + epoch)
        return torch.randperm(len(self.views), generator=generator).tolist()

    def next(self, max_time: float = 1.0) -> int:
        """The next view; every view comes once per epoch, in shuffled order. Views later
        than `max_time` are passed over in this epoch; if none is that early, the earliest
        views stand in."""
        max_time = max(max_time, self.earliest)
        while True:
            if self.position >= len(self.order):
                self.epoch += 1
                self.position = 0
                self.order = self._permutation(self.epoch)
            local = self.order[self.position]
            self.position += 1
            if self.times[local] <= max_time:
                return self.views[local]

    def upcoming(self) -> int | None:
        """The view `next` will consider first, within this epoch (to read ahead)."""
        if self.position < len(self.order):
            return self.views[self.order[self.position]]
        return None

    def window_end(self, max_time: float) -> int:
        """How many of the views, in time order, have t ≤ max_time (at least the earliest)."""
        return bisect_right(self.sorted_times, max(max_time, self.earliest))

    def frontier(self, max_time: float, span: float) -> int:
        """A view drawn at random from those with max_time − span ≤ t ≤ max_time (the
        latest views before max_time when none is that recent)."""
        times = self.sorted_times
        end = self.window_end(max_time)
        low = min(max_time - span, times[end - 1])
        start = bisect_left(times, low, hi=end)
        seed = self.seed + FRONTIER_SEED_OFFSET + self.frontier_draws
        generator = torch.Generator().manual_seed(seed)
        self.frontier_draws += 1
        pick = start + int(torch.randint(end - start, (1,), generator=generator))
        return self.views[self.by_time[pick]]

    def state_dict(self) -> dict[str, int]:
        return {
            "seed": self.seed,
            "epoch": self.epoch,
            "position": self.position,
            "frontier_draws": self.frontier_draws,
        }

    def load_state_dict(self, state: dict[str, int]) -> None:
        position = int(state["position"])
        if not 0 <= position <= len(self.views) or int(state["epoch"]) < 0:
            raise ValueError(f"invalid sampler state {state}")
        self.seed = int(state["seed"])
        self.epoch = int(state["epoch"])
        self.position = position
        self.order = self._permutation(self.epoch)
        self.frontier_draws = int(state.get("frontier_draws", 0))  # absent before it existed
