"""Adam with one parameter group per kind of parameter, each with its own exponentially
decaying learning rate, and the row surgery that keeps Adam's state in step with the
Gaussians when densification adds or removes some.

Letters: N Gaussians before a topology change, M after.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Int
from torch import Tensor, nn

from dyngs.errors import ConfigError
from dyngs.model import DynamicGaussians


@dataclass(frozen=True)
class OptimConfig:
    """Learning rates: initial → final, decayed exponentially over the run.

    Gaussian rates are those of 3D Gaussian Splatting (Kerbl et al. 2023); the deformation's
    are ten times those of 4D Gaussian Splatting (Wu et al. 2024) for a run of up to
    `deformation_steps` steps, and less for a longer one (`deformation_rate_scale`).
    Position rates are multiplied by the scene's extent so they mean the same on any scene
    scale.
    """

    means: tuple[float, float] = (1.6e-4, 1.6e-6)
    """Centres, in units of the scene extent."""
    quats: float = 1e-3
    log_scales: float = 5e-3
    opacity_logits: float = 5e-2
    sh_dc: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20
    time_centers: float = 1e-4
    """τ of temporal opacity, in units of the sequence (Spacetime Gaussians, Li et al.
    2024, use 1e-4)."""
    time_log_scales: float = 3e-3
    """log σ of temporal opacity: a tenth of Spacetime Gaussians' 3e-2 (Li et al. 2024).
    At 3e-2 the lifetimes of the points carved per time window shrank to about one
    frame's spacing on monocular sequences, so an object moving across a gap in the
    training times was drawn as two sets of Gaussians cross-fading, faint in between
    (mujoco-texture: +2.6 and +6.2 dB at 3e-3 over two seeds; docs/ACCURACY.md)."""
    grid: tuple[float, float] = (1.6e-2, 1.6e-4)
    """Feature planes of a plane-based field, for a run of `deformation_steps` steps: 10×
    4DGaussians' rates, chosen on 1 500-step runs (docs/TRAINING.md)."""
    network: tuple[float, float] = (1.6e-3, 1.6e-5)
    """MLP weights of the field and the deformation head (10× 4DGaussians', as above)."""
    deformation_steps: int | None = 3000
    """A run of more steps than this divides the deformation's rates (`grid`, `network`)
    by steps / `deformation_steps`, down to `deformation_floor` of them, so that rate ×
    steps stays near 4DGaussians' rate × 30 000 (Wu et al. 2024 train ~20 000 steps at
    their rates). Every step moves the field, which all Gaussians and times share, towards
    one view; a run with more steps can afford smaller moves, and one with fewer needs
    larger ones: a rate that suits 10 000 steps loses the motion in 3 000, and the other
    way round (docs/ACCURACY.md, "The deformation's rates sized to the run"). A
    `--time-budget` run sizes them again at each re-plan. None: the rates as given, for a
    run of any length."""
    deformation_floor: float = 0.3
    """The least share of `grid` and `network` a long run gets: the slowest rates measured
    to help; at a tenth the moving objects were lost."""
    eps: float = 1e-15
    """Adam's epsilon; 3DGS uses 1e-15 so tiny gradients still move parameters."""
    fused: bool = True
    """Use PyTorch's fused Adam kernel where it has one (CPU and CUDA): one vectorised pass
    over every parameter, where the per-tensor Adam (`--optim.no-fused`, its reference)
    does Python and scalar work per parameter and took about three times as long
    (docs/TRAINING.md). The two agree up to float32 rounding."""
    camera_colours: float = 1e-3
    """Per-camera colour (`dyngs.appearance`): the rate of each camera's log-gains and
    offsets, for every camera of a capture of photographs that training sees at three or
    more times (RGBA renders get none). Ten times Dynamic 3D Gaussians' 1e-4 (Luiten et
    al. 2024), whose first frame alone trains 10 000 steps. 0: no per-camera colour,
    every camera draws the Gaussians as they are."""
    hold_deformation_rates: bool = False
    """Hold the field's and the head's rates (`grid`, `network`) at their start while the
    training views' time window widens (`--time-ramp`), and decay them over the rest of
    the run, so that each time is learned at the rate the first ones had. Off by default:
    it did not help consistently across seeds (docs/CAPACITY.md)."""

    def __post_init__(self) -> None:
        if self.deformation_steps is not None and self.deformation_steps < 1:
            raise ConfigError(
                f"--optim.deformation-steps must be ≥ 1 or None, got {self.deformation_steps}"
            )
        if not self.camera_colours >= 0.0:  # NaN fails too
            raise ConfigError(f"--optim.camera-colours must be ≥ 0, got {self.camera_colours}")
        if not 0.0 < self.deformation_floor <= 1.0:
            raise ConfigError(
                f"--optim.deformation-floor must be in (0, 1], got {self.deformation_floor}"
            )


DEFORMATION_GROUPS = ("grid", "network")
"""Optimizer groups of the deformation field and head (feature planes, MLP weights)."""


def _is_grid(param: nn.Parameter) -> bool:
    """Feature grids (plane stacks) have three or more dimensions; weights and biases fewer."""
    return param.ndim >= 3


def build_optimizer(
    model: DynamicGaussians, config: OptimConfig, extent: float
) -> torch.optim.Adam:
    """One Adam, one group per parameter kind; each group records its schedule."""
    groups: list[dict] = []

    def group(
        name: str, params: list[nn.Parameter], start: float, end: float | None = None
    ) -> None:
        if params:
            end = start if end is None else end
            groups.append(
                {"name": name, "params": params, "lr": start, "lr_start": start, "lr_end": end}
            )

    c = model.canonical
    group("means", [c.means], config.means[0] * extent, config.means[1] * extent)
    group("quats", [c.quats], config.quats)
    group("log_scales", [c.log_scales], config.log_scales)
    group("opacity_logits", [c.opacity_logits], config.opacity_logits)
    group("sh_dc", [c.sh_dc], config.sh_dc)
    group("sh_rest", [c.sh_rest], config.sh_rest)
    group("time_centers", [c.time_centers], config.time_centers)
    group("time_log_scales", [c.time_log_scales], config.time_log_scales)
    deformation = [*model.field.parameters(), *model.head.parameters()]
    grid, network = DEFORMATION_GROUPS
    group(grid, [p for p in deformation if _is_grid(p)], *config.grid)
    group(network, [p for p in deformation if not _is_grid(p)], *config.network)
    if model.colours is not None:
        group("camera_colours", list(model.colours.parameters()), config.camera_colours)
    params = [p for g in groups for p in g["params"]]
    fused = config.fused and _fusable(params)
    return torch.optim.Adam(groups, lr=0.0, eps=config.eps, fused=fused)


FUSED_DEVICES = ("cpu", "cuda")
"""Where PyTorch has a fused Adam kernel."""


def _fusable(params: Sequence[Tensor]) -> bool:
    """Whether the fused Adam kernel takes every parameter (a device it has, floating)."""
    return all(p.device.type in FUSED_DEVICES and p.is_floating_point() for p in params)


def deformation_rate_scale(config: OptimConfig, steps: int) -> float:
    """The share of `grid` and `network` a run of `steps` steps learns at:
    `deformation_steps` / steps, within [`deformation_floor`, 1] (see OptimConfig)."""
    if config.deformation_steps is None or steps <= config.deformation_steps:
        return 1.0
    return max(config.deformation_steps / steps, config.deformation_floor)


def set_learning_rates(
    optimizer: torch.optim.Optimizer,
    progress: float,
    deformation_progress: float | None = None,
    deformation_scale: float = 1.0,
) -> None:
    """Log-linear interpolation from lr_start to lr_end as progress goes from 0 to 1; the
    groups in DEFORMATION_GROUPS follow `deformation_progress` instead, when given, and
    are multiplied by `deformation_scale`."""
    for g in optimizer.param_groups:
        own, scale = progress, 1.0
        if g["name"] in DEFORMATION_GROUPS:
            own = progress if deformation_progress is None else deformation_progress
            scale = deformation_scale
        own = min(max(own, 0.0), 1.0)
        start, end = g["lr_start"], g["lr_end"]
        rate = (
            start if start == end else math.exp((1 - own) * math.log(start) + own * math.log(end))
        )
        g["lr"] = rate * scale


def replace_rows(
    optimizer: torch.optim.Optimizer,
    old: nn.Parameter,
    new: nn.Parameter,
    source: Int[Tensor, " M"],
    fresh: Bool[Tensor, " M"],
) -> None:
    """Point `optimizer` at `new` in place of `old`, whose rows were rearranged: row i of
    `new` came from row source[i] of `old`. Adam's moments follow their rows; rows marked
    `fresh` (new Gaussians from a clone or split) start from zero moments, as in 3DGS."""
    for g in optimizer.param_groups:
        for i, p in enumerate(g["params"]):
            if p is not old:
                continue
            g["params"][i] = new
            state = optimizer.state.pop(old, None)
            if state:
                for key, value in state.items():
                    if (
                        isinstance(value, Tensor)
                        and value.ndim > 0
                        and value.shape[0] == old.shape[0]
                    ):
                        moved = value[source].clone()
                        moved[fresh] = 0
                        state[key] = moved
                optimizer.state[new] = state
            return
    raise KeyError("parameter is not in the optimizer")


def replace_params(
    optimizer: torch.optim.Optimizer,
    old: Sequence[nn.Parameter],
    new: Sequence[nn.Parameter],
    remap: Callable[[Sequence[Tensor]], list[Tensor]],
) -> None:
    """Point `optimizer` at `new` in place of `old`, all in one group, where `remap` turns
    tensors laid out like `old` into tensors laid out like `new` (a cropped field). Adam's
    moments go through `remap`; its step count carries over."""
    holder = next(g for g in optimizer.param_groups if any(p is old[0] for p in g["params"]))
    holder["params"] = [p for p in holder["params"] if all(p is not q for q in old)] + list(new)
    states = [optimizer.state.pop(p, {}) for p in old]
    if not all(states):
        return  # no step taken yet: nothing to carry
    moved = {
        key: remap([s[key] for s in states])
        for key, value in states[0].items()
        if isinstance(value, Tensor) and value.shape == old[0].shape
    }
    for i, p in enumerate(new):
        state = {key: value for key, value in states[0].items() if key not in moved}
        optimizer.state[p] = state | {key: values[i] for key, values in moved.items()}
