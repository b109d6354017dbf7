"""`--time-budget MINUTES`: fit the whole training schedule into a wall-clock budget.

The schedule (warm-up aside) is laid out in fractions of `max_iters`: the time window
widens over `time_ramp` of it, densification stops at `refine_stop` of it, learning rates
decay over all of it. So a budget is met by choosing `max_iters`. A step's cost is not
known in advance: it grows several-fold as Gaussians are added and falls as they turn
static, so a calibration at the start would mislead. `TimeBudget` measures instead: after
every log interval from the end of the warm-up on (whose static steps are several times
faster than the rest), it takes the rate of the recent steps and re-plans `max_iters` so
that the remaining steps fit the remaining time, within [step + 1, `ceiling`]. It changes
the plan only when it moves by more than `REPLAN_TOLERANCE` and not in the last
`SETTLED_SHARE` of the run; each change is reported.

A re-plan changes the pace of the schedule, not its place: the schedule keeps the position
it has reached and runs to its end over the new number of steps left
(`schedules.repaced`). Recomputing its fractions from each new total instead moved them
backwards whenever a plan grew (the time window narrowed again, the learning rates rose),
and the plans do swing, as the step's cost changes over a run; that cost the budgeted
runs accuracy against the same number of fixed steps (docs/ACCURACY.md, "The README's
demo on two idle cores").
A budgeted run depends on the machine's speed, so unlike every other run it does not
repeat to the digit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

REPLAN_TOLERANCE = 0.03
"""Re-plan only when the new step count differs from the current by more than this share."""

SETTLED_SHARE = 0.1
"""The last share of the run keeps its plan."""

RECENT_STEPS = 200
"""The rate is measured over about this many of the latest steps."""

GROWTH = 4
"""A budget may lengthen a run with a data-sized step count up to this many times."""


@dataclass
class TimeBudget:
    """Re-plans `max_iters` to end training within `seconds` (see the module docstring)."""

    seconds: float
    ceiling: int
    """The most steps a plan may hold."""
    marks: list[tuple[int, float]] = field(default_factory=list)
    """(step, training seconds) at the latest log intervals."""

    @classmethod
    def of(cls, minutes: float | None, steps: int, sized: bool) -> TimeBudget | None:
        """The budget of `--time-budget MINUTES` for a run of `steps` (None without one);
        a data-sized step count may grow `GROWTH` times, a given one is the ceiling."""
        if minutes is None:
            return None
        return cls(60.0 * minutes, steps * GROWTH if sized else steps)

    def plan(self, step: int, elapsed: float, planned: int) -> int | None:
        """The new step count after `step` steps in `elapsed` seconds, or None to keep
        `planned`."""
        self.marks.append((step, elapsed))
        while len(self.marks) > 2 and step - self.marks[1][0] >= RECENT_STEPS:
            self.marks.pop(0)
        first_step, first_time = self.marks[0]
        if step <= first_step or elapsed <= first_time or step >= (1 - SETTLED_SHARE) * planned:
            return None
        rate = (step - first_step) / (elapsed - first_time)
        wanted = step + int(max(self.seconds - elapsed, 0.0) * rate)
        wanted = min(max(wanted, step + 1), self.ceiling)
        if abs(wanted - planned) <= REPLAN_TOLERANCE * planned:
            return None
        return wanted

    def said(self, step: int, elapsed: float, planned: int, deformation_scale: float) -> str:
        """The line a re-plan prints: the steps it chose, and the share of its rates the
        deformation learns at for that many (`optim.deformation_rate_scale`)."""
        left = max(self.seconds - elapsed, 0.0)
        return (
            f"[budget] step {step}: {planned} steps fit the {left:.0f} s left "
            f"(the deformation at {deformation_scale:.2f}× its rates)"
        )

    def state_dict(self) -> dict[str, Any]:
        return {"seconds": self.seconds, "ceiling": self.ceiling, "marks": list(self.marks)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.marks = [(int(s), float(t)) for s, t in state.get("marks", [])]
