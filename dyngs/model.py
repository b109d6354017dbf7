"""The 4D model: canonical Gaussians plus a deformation field and head.

Letters: N Gaussians, K SH coefficients per channel, F field features, P points.

Raw parameters are unconstrained (log-scales, opacity logits, unnormalised quaternions,
SH coefficients); `activate` is the one place where they become drawable Gaussians.

The model is self-contained: it is built from its component configs, a scene box and a
Gaussian count (`DynamicGaussians.build`), and its `state_dict` holds everything that
decides what it draws (parameters, the static/dynamic flags, the active SH degree,
whether it deforms yet, the scene box), so `DynamicGaussians.load` rebuilds it from a
checkpoint without the dataset or an optimizer, and `model.at(t)` needs nothing else.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor, nn

from dyngs.appearance import CameraColours
from dyngs.errors import ConfigError
from dyngs.fields.base import Field, FieldSpec, Head, HeadSpec
from dyngs.fields.heads import Deltas
from dyngs.geometry import normalize_quaternion, quaternion_multiply, quaternion_to_rotation
from dyngs.neighbors import knn
from dyngs.ops import finite_rows
from dyngs.sh import num_sh_bases, rgb_to_sh0
from dyngs.types import Camera, Gaussians, SceneBox

_EXTRA = "_extra_state"
"""The state_dict key of `DynamicGaussians.get_extra_state` (PyTorch's convention)."""

# Names of the per-Gaussian parameters, in a fixed order (checkpoints, optimizer groups).
GAUSSIAN_PARAMS = (
    "means",
    "quats",
    "log_scales",
    "opacity_logits",
    "sh_dc",
    "sh_rest",
    "time_centers",
    "time_log_scales",
)

DRAWN_PARAMS = GAUSSIAN_PARAMS[:6]
"""The parameters of a static 3DGS Gaussian (what a PLY export holds): a snapshot at one
time has its temporal opacity folded into its opacity."""

ETERNAL = 30.0
"""`time_log_scales` of a Gaussian that exists at every time (the default). Any value at or
above `TEMPORAL_LIMIT` means the same: its opacity is not scaled and its time parameters
get no gradient."""

TEMPORAL_LIMIT = math.log(100.0)
"""A Gaussian whose time scale σ is under this (e^4.6 = 100, in units of the sequence)
has temporal opacity; at σ = 100 it would fade by 5e-5 over the whole sequence anyway."""


@dataclass(frozen=True)
class GaussianConfig:
    """Canonical Gaussians: initialisation and colour model."""

    sh_degree: int = 3
    """Highest spherical-harmonic degree of the colour model."""
    sh_degree_interval: int = 1000
    """Every this many iterations the active SH degree may rise by one (3DGS's schedule)."""
    sh_evidence: float = 0.5
    """… but only when view-dependent error asks for it: while a band is frozen at zero its
    gradient is gathered over the views, and the degree rises when that gradient is this
    consistent (Σ_g |Σ_v ∂L/∂band| / Σ_g Σ_v |∂L/∂band|): about 1/√views for error that does
    not depend on the view, 2/3 for a tint linear in the view direction. 0: rise on
    schedule regardless (3DGS)."""
    init_opacity: float = 0.1
    """Opacity of every initial Gaussian (Kerbl et al. 2023)."""
    init_scale_neighbors: int = 3
    """Initial scale: mean distance to this many nearest initial points (Kerbl et al. 2023)."""
    max_init_points: int | None = None
    """Initial points beyond this many are subsampled (seeded). None: the data-sized
    Gaussian budget (dyngs/engine/capacity.py), so that a dense or random cloud never starts a
    scene above what it needs."""
    filter_3d: float = 0.0
    """Mip-Splatting's 3D smoothing filter (Yu et al. 2024, whose s = 0.2 this is): each
    Gaussian is drawn convolved with an isotropic Gaussian of variance s/ν², where ν is
    the finest sampling rate (focal length ÷ depth, pixels per world unit) of any training
    view that sees it (`dyngs.engine.smoothing`), with its opacity scaled to keep its
    mass. A Gaussian finer than its views can resolve is otherwise free to shrink to a
    needle or a speck that fits those views' pixels and aliases everywhere else. The
    filter is set from all training views when the run starts and every
    `--densify.refine-every` steps (`set_filter`); it is saved with the model, so
    evaluation draws as training did. 0: no filter (the default: on our scenes it is not
    a measured gain, and each refresh deforms the model at every training time,
    docs/ACCURACY.md); 0.2 is Mip-Splatting's."""

    def __post_init__(self) -> None:
        if not (self.filter_3d >= 0.0 and math.isfinite(self.filter_3d)):
            raise ConfigError(f"--gaussians.filter-3d must be ≥ 0 and finite, got {self.filter_3d}")


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def subsample_points(
    points: Float[Tensor, "P 3"],
    colors: Float[Tensor, "P 3"] | None,
    limit: int | None,
    generator: torch.Generator,
    lifetimes: Float[Tensor, "P 2"] | None = None,
) -> tuple[Float[Tensor, "N 3"], Float[Tensor, "N 3"] | None, Float[Tensor, "N 2"] | None]:
    """At most `limit` of the points (and their colours and lifetimes), drawn without
    replacement."""
    if limit is not None and len(points) > limit:
        keep = torch.randperm(len(points), generator=generator)[:limit]
        points = points[keep]
        colors = None if colors is None else colors[keep]
        lifetimes = None if lifetimes is None else lifetimes[keep]
    return points, colors, lifetimes


def neighbour_distance(points: Float[Tensor, "P 3"], k: int) -> Float[Tensor, " P"]:
    """Each point's mean distance to its k nearest others, the initial scale of 3D Gaussian
    Splatting (Kerbl et al. 2023). Where those k all coincide with the point, as when one
    carved place becomes several temporal Gaussians, one per stretch of time it is held
    (`init_points.lifetimes`), the place's mean distance to its k nearest other places
    instead: at the 1e-7 floor such a Gaussian drew nothing, so it never had a gradient,
    kept its initial opacity and was never pruned (hfu-3cam ended with 7 553 of them, 14 %
    of its Gaussians). Every other point keeps exactly the plain distance."""
    dist = _mean_nearest(points, k)
    stuck = dist == 0
    if bool(stuck.any()):
        places, where = torch.unique(points, dim=0, return_inverse=True)
        if len(places) > 1:
            spread = _mean_nearest(places, min(k, len(places) - 1))
            dist = torch.where(stuck, spread[where], dist)
    return dist


def _mean_nearest(points: Float[Tensor, "P 3"], k: int) -> Float[Tensor, " P"]:
    """Each point's mean distance to its k nearest others."""
    return (points[:, None, :] - points[knn(points, k)]).norm(dim=-1).mean(dim=-1)


class CanonicalGaussians(nn.Module):
    """The Gaussians at rest, as raw learnable parameters."""

    means: nn.Parameter
    quats: nn.Parameter
    log_scales: nn.Parameter
    opacity_logits: nn.Parameter
    sh_dc: nn.Parameter
    sh_rest: nn.Parameter
    time_centers: nn.Parameter
    """τ: the time a temporal Gaussian is most opaque at (see `temporal_factor`)."""
    time_log_scales: nn.Parameter
    """log σ of its temporal opacity; `ETERNAL` (or anything ≥ `TEMPORAL_LIMIT`) for a
    Gaussian that exists at every time."""

    def __init__(self, num: int, sh_degree: int) -> None:
        super().__init__()
        self.sh_degree = sh_degree
        rest = num_sh_bases(sh_degree) - 1
        self.means = nn.Parameter(torch.zeros(num, 3))
        self.quats = nn.Parameter(torch.zeros(num, 4))
        self.log_scales = nn.Parameter(torch.zeros(num, 3))
        self.opacity_logits = nn.Parameter(torch.zeros(num))
        self.sh_dc = nn.Parameter(torch.zeros(num, 1, 3))
        self.sh_rest = nn.Parameter(torch.zeros(num, rest, 3))
        self.time_centers = nn.Parameter(torch.full((num,), 0.5))
        self.time_log_scales = nn.Parameter(torch.full((num,), ETERNAL))

    def __len__(self) -> int:
        return self.means.shape[0]

    @classmethod
    def from_points(
        cls,
        points: Float[Tensor, "P 3"],
        colors: Float[Tensor, "P 3"] | None,
        config: GaussianConfig,
        generator: torch.Generator,
    ) -> CanonicalGaussians:
        """Gaussians at the points (subsampled to `config.max_init_points`)."""
        points, colors, _ = subsample_points(points, colors, config.max_init_points, generator)
        model = cls(len(points), config.sh_degree)
        model.initialize(points, colors, config)
        return model

    @torch.no_grad()
    def initialize(
        self,
        points: Float[Tensor, "N 3"],
        colors: Float[Tensor, "N 3"] | None,
        config: GaussianConfig,
        lifetimes: Float[Tensor, "N 2"] | None = None,
    ) -> None:
        """Place one Gaussian at each point, as 3D Gaussian Splatting does (Kerbl et al.
        2023): unrotated, isotropic with the mean distance to its nearest points as scale,
        `config.init_opacity`, and the point's colour (grey without one). `lifetimes`
        gives each point's (τ, σ) of temporal opacity; σ = inf (or no lifetimes): eternal."""
        if len(points) != len(self):
            raise ValueError(f"{len(points)} points for {len(self)} Gaussians")
        points = points.float()
        k = min(config.init_scale_neighbors, max(len(points) - 1, 1))
        self.means.copy_(points)
        self.quats.zero_()
        self.quats[:, 0] = 1.0
        dist = neighbour_distance(points, k) if len(points) > 1 else torch.ones(len(points))
        self.log_scales.copy_(dist.clamp_min(1e-7).log()[:, None].expand(-1, 3))
        self.opacity_logits.fill_(_logit(config.init_opacity))
        rgb = torch.full_like(points, 0.5) if colors is None else colors.float().clamp(0, 1)
        self.sh_dc.copy_(rgb_to_sh0(rgb)[:, None, :])
        self.sh_rest.zero_()
        self.time_centers.fill_(0.5)
        self.time_log_scales.fill_(ETERNAL)
        if lifetimes is not None:
            if lifetimes.shape != (len(points), 2):
                raise ValueError(
                    f"lifetimes must be [{len(points)}, 2], got {tuple(lifetimes.shape)}"
                )
            temporal = torch.isfinite(lifetimes[:, 1])
            self.time_centers.copy_(torch.where(temporal, lifetimes[:, 0].float(), 0.5))
            sigma = lifetimes[:, 1].float().clamp_min(1e-4).log()
            self.time_log_scales.copy_(
                torch.where(temporal, sigma.clamp_max(TEMPORAL_LIMIT), ETERNAL)
            )

    def temporal(self) -> Bool[Tensor, " N"]:
        """Gaussians with temporal opacity."""
        return self.time_log_scales < TEMPORAL_LIMIT

    def temporal_factor(self, t: float | Float[Tensor, " N"]) -> Float[Tensor, " N"]:
        """What each Gaussian's opacity is multiplied by at time t (one time, or one per
        Gaussian): exp(−½((t − τ)/σ)²), the temporal radial basis of Spacetime Gaussians (Li
        et al. 2024), for temporal Gaussians; exactly 1, with no gradient to τ or σ, for
        eternal ones."""
        z = (t - self.time_centers) * torch.exp(-self.time_log_scales.clamp_max(TEMPORAL_LIMIT))
        return torch.where(self.temporal(), torch.exp(-0.5 * z * z), 1.0)

    def peak_presence(self) -> Float[Tensor, " N"]:
        """The largest temporal factor each Gaussian reaches at a time of the sequence, t ∈
        [0, 1]: its factor at the time nearest τ. Under 1 only for a Gaussian whose τ has
        left the sequence, which no view sees at full opacity again."""
        with torch.no_grad():
            return self.temporal_factor(self.time_centers.clamp(0.0, 1.0))

    def params(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in GAUSSIAN_PARAMS}

    def finite_rows(self) -> Bool[Tensor, " N"]:
        """Gaussians whose every raw parameter is finite (the others are culled when drawn)."""
        return finite_rows(*self.params().values())

    def replace(self, values: dict[str, Tensor]) -> None:
        """Swap every per-Gaussian parameter for a new tensor (after densification or on
        loading a checkpoint with a different count)."""
        for name in GAUSSIAN_PARAMS:
            setattr(self, name, nn.Parameter(values[name].detach().contiguous()))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[no-untyped-def]
        # Models saved before temporal opacity existed: every Gaussian eternal.
        if prefix + "means" in state_dict and prefix + "time_centers" not in state_dict:
            count = state_dict[prefix + "means"].shape[0]
            like = state_dict[prefix + "opacity_logits"]
            state_dict[prefix + "time_centers"] = torch.full((count,), 0.5).to(like)
            state_dict[prefix + "time_log_scales"] = torch.full((count,), ETERNAL).to(like)
        # A checkpoint may hold any number of Gaussians: resize before copying.
        shapes = {n: state_dict[prefix + n] for n in GAUSSIAN_PARAMS if prefix + n in state_dict}
        if len(shapes) == len(GAUSSIAN_PARAMS):
            self.replace({n: torch.empty_like(t) for n, t in shapes.items()})
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def activate(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    sh: Float[Tensor, "N K 3"],
    sh_degree: int,
    presence: Float[Tensor, " N"] | None = None,
) -> Gaussians:
    """Raw parameters → drawable Gaussians (the one place activations are applied);
    `presence` (temporal opacity, in [0, 1]) scales the opacities."""
    opacities = torch.sigmoid(opacity_logits)
    return Gaussians(
        means=means,
        quats=normalize_quaternion(quats),
        scales=log_scales.exp(),
        opacities=opacities if presence is None else opacities * presence,
        colors=sh[:, : num_sh_bases(sh_degree)],
        sh_degree=sh_degree,
    )


def smooth_3d(
    scales: Float[Tensor, "N 3"], opacities: Float[Tensor, " N"], std: Float[Tensor, " N"]
) -> tuple[Float[Tensor, "N 3"], Float[Tensor, " N"]]:
    """Each Gaussian convolved with an isotropic one of standard deviation `std`: variances
    add, s'ᵢ = √(sᵢ² + std²), and the opacity is scaled by Πᵢ sᵢ/s'ᵢ = √(det Σ / det Σ'),
    so that the blob keeps the mass it had (Mip-Splatting's 3D filter, Yu et al. 2024).
    `hypot` neither overflows nor underflows, and each factor is in (0, 1]. Rows with a
    non-finite scale or a zero `std` are returned as they are (the renderer culls the
    former), so that neither NaN values nor NaN gradients come from the filter."""
    keep = (std <= 0) | ~torch.isfinite(scales).all(dim=-1) | ~torch.isfinite(std)
    safe = torch.where(keep[:, None], 1.0, scales)
    widened = torch.hypot(safe, torch.where(keep, 1.0, std)[:, None])
    factor = (safe / widened).prod(dim=-1)
    return (
        torch.where(keep[:, None], scales, widened),
        torch.where(keep, opacities, opacities * factor),
    )


def resolve_turn(
    d: Deltas, xyz: Float[Tensor, "N 3"], quats: Float[Tensor, "N 4"], box: SceneBox
) -> Deltas:
    """`d` with its turn folded into additive Δμ and Δq, as every consumer of deltas reads
    them: the point turns about the box's centre c, μ + Δμ → c + R(μ − c) + Δμ, and the
    quaternion turns with it, q + Δq → turn ⊗ q + Δq (the same orientation once
    normalised, since the turn is a unit quaternion)."""
    if d.turn is None:
        return d
    quats = torch.where(finite_rows(quats)[:, None], quats, 0.0)  # as xyz in deltas
    centre = xyz.new_tensor(box.center)
    arm = xyz - centre
    turned = (quaternion_to_rotation(d.turn) @ arm[:, :, None]).squeeze(-1)
    dq = quaternion_multiply(d.turn, quats) - quats
    return Deltas(
        means=d.means + (turned - arm),
        quats=dq if d.quats is None else dq + d.quats,
        scales=d.scales,
        opacities=d.opacities,
        colors=d.colors,
    )


def _check_time(t: float) -> None:
    if not 0.0 <= t <= 1.0 or math.isnan(t):
        raise ValueError(f"time must be in [0, 1], got {t}")


class DynamicGaussians(nn.Module):
    """Canonical Gaussians deformed over time by `head(field(μ, t))`.

    `dynamic` marks the Gaussians that are deformed; the others are drawn from their
    canonical parameters and never query the field (dyngs/engine/motion.py decides which).
    When none is dynamic, the model is a static 3DGS model and the field is never run.

    `active_sh_degree` is the SH degree drawn with (it rises during training) and
    `deforming` whether the deformation is on (off during the static warm-up); both are
    saved in the state_dict with the scene box, so `at(t)` draws what training drew.
    `filter_std` is each Gaussian's 3D smoothing filter (`smooth_3d`; zero: none), a
    buffer for the same reason. `colours` is the capture's per-camera colour
    (`dyngs.appearance`; None until the trainer gives the model its cameras'), which
    training and evaluation apply to each camera's render (`camera_colour`).
    """

    dynamic: Tensor
    filter_std: Tensor
    field: Field
    colours: CameraColours | None

    def __init__(self, canonical: CanonicalGaussians, field: Field, head: Head, box: SceneBox):
        super().__init__()
        self.canonical = canonical
        self.field = field
        self.head = head
        self.box = box
        self.register_buffer("dynamic", torch.ones(len(canonical), dtype=torch.bool))
        self.register_buffer("filter_std", torch.zeros(len(canonical)))
        self.register_module("colours", None)
        self.active_sh_degree = 0
        self.deforming = True

    @classmethod
    def build(
        cls,
        gaussians: GaussianConfig,
        field: FieldSpec,
        head: HeadSpec,
        box: SceneBox,
        num: int,
        generator: torch.Generator | None = None,
    ) -> DynamicGaussians:
        """A model of `num` Gaussians at the origin (see `CanonicalGaussians.initialize`),
        with its field and head built for `box`; random initial values of the field and
        head come from `generator`."""
        canonical = CanonicalGaussians(num, gaussians.sh_degree)
        built_field = field.build(box, generator=generator)
        built_head = head.build(built_field.out_dim, box, generator=generator)
        return cls(canonical, built_field, built_head, box)

    @classmethod
    def load(
        cls,
        gaussians: GaussianConfig,
        field: FieldSpec,
        head: HeadSpec,
        state: dict[str, Any],
    ) -> DynamicGaussians:
        """The model a `state_dict` describes, built from the configs it was trained with:
        no dataset, no optimizer. Raises ValueError when the state does not fit them."""
        extra = state.get(_EXTRA)
        if not isinstance(extra, dict) or "box" not in extra:
            raise ValueError("the model state has no scene box (written by dyngs before 0.2)")
        lower, upper = extra["box"]
        box = SceneBox(tuple(lower), tuple(upper))
        num = state["canonical.means"].shape[0]
        model = cls.build(gaussians, field, head, box, num, torch.Generator().manual_seed(0))
        if (centres := state.get("colours.centres")) is not None:
            model.colours = CameraColours(centres)
        model.load_state_dict(state)
        return model

    def get_extra_state(self) -> dict[str, Any]:
        return {
            "active_sh_degree": self.active_sh_degree,
            "deforming": self.deforming,
            "box": [list(self.box.lower), list(self.box.upper)],
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        box = SceneBox(tuple(state["box"][0]), tuple(state["box"][1]))
        if box != self.box:
            raise ValueError(f"the state's scene box {box} is not this model's {self.box}")
        degree = int(state["active_sh_degree"])
        if not 0 <= degree <= self.canonical.sh_degree:
            raise ValueError(f"active SH degree {degree} beyond {self.canonical.sh_degree}")
        self.active_sh_degree = degree
        self.deforming = bool(state["deforming"])

    @property
    def deforms(self) -> bool:
        """Whether drawing runs the field: deformation on, and some Gaussian dynamic."""
        return self.deforming and self.any_dynamic()

    def deltas(
        self, t: float, index: Int[Tensor, " M"] | None = None
    ) -> tuple[Deltas, Int[Tensor, " M"] | None]:
        """Deformation of the Gaussians in `index` (default: every dynamic one) at time t."""
        _check_time(t)
        means = self.canonical.means
        if index is None and not bool(self.dynamic.all()):
            index = self.dynamic.nonzero().squeeze(1)
        xyz = means if index is None else means.index_select(0, index)
        xyz = torch.where(finite_rows(xyz)[:, None], xyz, 0.0)  # see raw_at
        times = xyz.new_full((len(xyz), 1), t)
        d = self.head(self.field(xyz, times))
        if d.turn is not None:
            quats: Tensor = self.canonical.quats
            quats = quats if index is None else quats.index_select(0, index)
            d = resolve_turn(d, xyz, quats, self.box)
        return d, index

    def any_dynamic(self) -> bool:
        return bool(self.dynamic.any())

    def dynamic_fraction(self) -> float:
        """Share of the Gaussians that are deformed (0 for an empty model)."""
        return float(self.dynamic.float().mean()) if len(self.dynamic) else 0.0

    def raw_at(
        self, t: float, deform: bool | None = None, only: Bool[Tensor, " N"] | None = None
    ) -> dict[str, Tensor]:
        """Raw (unactivated) parameters at time t, keyed like GAUSSIAN_PARAMS: the canonical
        ones plus the head's deltas (the canonical ones alone when `deform`, by default
        the model's `deforming`, is False). Exports read these; `at` activates them.
        `only`: deform just the dynamic Gaussians it marks; the others keep their canonical
        parameters (`at`'s `absent_below`)."""
        deform = self.deforming if deform is None else deform
        _check_time(t)
        c = self.canonical
        raw: dict[str, Tensor] = dict(c.params())
        if deform and self.any_dynamic():
            chosen: Int[Tensor, " M"] | None = None
            if only is not None:
                wanted = self.dynamic & only
                if not bool(wanted.any()):
                    return raw
                chosen = None if bool(wanted.all()) else wanted.nonzero().squeeze(1)
            d, index = self.deltas(t, chosen)
            # A Gaussian with a non-finite parameter is culled when drawn, but its activation
            # still passes NaN back (exp(inf) · 0); cut its deltas off so that NaN never
            # reaches the field and head, whose gradients every other Gaussian shares.
            finite = c.finite_rows()
            finite = finite if index is None else finite.index_select(0, index)

            def add(base: Tensor, delta: Tensor | None) -> Tensor:
                if delta is None:
                    return base
                mask = finite.reshape(-1, *[1] * (delta.dim() - 1))
                delta = torch.where(mask, delta, 0.0)
                return base + delta if index is None else base.index_add(0, index, delta)

            raw["means"] = add(c.means, d.means)
            raw["quats"] = add(c.quats, d.quats)
            raw["log_scales"] = add(c.log_scales, d.scales)
            raw["opacity_logits"] = add(c.opacity_logits, d.opacities)
            raw["sh_dc"] = add(c.sh_dc, None if d.colors is None else d.colors[:, None, :])
        return raw

    def camera_colour(self, rgb: Float[Tensor, "H W 3"], camera: Camera) -> Float[Tensor, "H W 3"]:
        """`rgb`, a render through `camera`, in that camera's colour (`colours`); as it is
        for a model without per-camera colours."""
        return rgb if self.colours is None else self.colours(rgb, camera)

    def at(
        self,
        t: float,
        *,
        sh_degree: int | None = None,
        deform: bool | None = None,
        absent_below: float = 0.0,
    ) -> Gaussians:
        """Drawable Gaussians at time t, with the model's active SH degree and deformation
        unless overridden (`deform=False`: the canonical Gaussians).

        `absent_below`: a renderer's α floor (`Guards.alpha_min`). A temporal Gaussian whose
        presence at t is under it is left undeformed, since it draws nothing there: its
        opacity, at most its presence (an opacity, the head's change to it included, is at
        most 1, and the 3D and antialiasing filters only lower it), is under the floor, so
        the renderer skips it, and its pixels and gradients are those it would have had
        deformed (none). The field and head then run on the Gaussians present at t only:
        on a monocular sequence with short lifetimes, about half of them. Only for a
        caller that reads nothing but the drawn image: these Gaussians' means are not
        where they would be at t."""
        c = self.canonical
        presence = c.temporal_factor(t) if bool(c.temporal().any()) else None
        only = None
        if presence is not None and absent_below > 0:
            only = presence.detach().double() >= absent_below  # exactly as the floor reads
        raw = self.raw_at(t, self.deforming if deform is None else deform, only)
        degree = self.active_sh_degree if sh_degree is None else sh_degree
        # Only the bands drawn: the demo draws 4 of 16 coefficients, and the rest would be
        # copied forward and zero-filled backward on every step for nothing.
        rest = raw["sh_rest"][:, : num_sh_bases(degree) - 1]
        sh = torch.cat((raw["sh_dc"], rest), dim=1)
        g = activate(
            raw["means"], raw["quats"], raw["log_scales"], raw["opacity_logits"], sh, degree,
            presence,
        )  # fmt: skip
        if not self.filtered:
            return g
        scales, opacities = smooth_3d(g.scales, g.opacities, self.filter_std.to(g.scales))
        return dataclasses.replace(g, scales=scales, opacities=opacities)

    @property
    def filtered(self) -> bool:
        """Whether any Gaussian is drawn through a 3D smoothing filter."""
        return bool((self.filter_std > 0).any())

    @torch.no_grad()
    def set_filter(self, rates: Float[Tensor, " N"], strength: float) -> None:
        """Mip-Splatting's 3D filter from each Gaussian's finest sampling rate ν (pixels per
        world unit; 0 where no training view sees it): standard deviation
        √strength / ν, and for the unseen the widest in use (the coarsest rate's), as Yu
        et al. 2024 do. No rate at all leaves the filter as it is."""
        if rates.shape != self.filter_std.shape:
            raise ValueError(f"{tuple(rates.shape)} rates for {len(self.filter_std)} Gaussians")
        seen = (rates > 0) & torch.isfinite(rates)
        if not bool(seen.any()):
            return
        coarsest = rates[seen].min()
        finest = torch.where(seen, rates, coarsest).to(self.filter_std)
        self.filter_std.copy_(math.sqrt(strength) / finest)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[no-untyped-def]
        if prefix + "dynamic" in state_dict:  # the checkpoint's Gaussian count
            self.dynamic = torch.empty_like(state_dict[prefix + "dynamic"])
            # Models saved before the 3D filter existed were trained and drawn without one.
            filter_std = state_dict.setdefault(
                prefix + "filter_std", torch.zeros(len(self.dynamic))
            )
            self.filter_std = torch.empty_like(filter_std)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def on_topology(self, source: Int[Tensor, " M"], fresh: Bool[Tensor, " M"]) -> None:
        # New Gaussians inherit their source's dynamic flag and 3D filter.
        self.dynamic = self.dynamic[source]
        self.filter_std = self.filter_std[source]
