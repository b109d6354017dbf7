"""The deformation head: field features in, per-Gaussian deltas out.

Letters: N Gaussians, C input feature channels, W hidden width.

The layout is 4D Gaussian Splatting's (Wu et al. 2024): one shared Linear turns the field
features into a hidden vector, and a small MLP per deformed attribute (position, rotation,
scale, opacity, colour) decodes it. Attributes that are switched off have no branch at
all, so they cost neither parameters nor time.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.errors import ConfigError
from dyngs.fields._common import init_linear_
from dyngs.geometry import normalize_quaternion
from dyngs.types import SceneBox


@dataclass
class Deltas:
    """What the head adds to the canonical Gaussians at one time; None = not deformed."""

    means: Float[Tensor, "N 3"]
    """Δμ in world units."""
    quats: Float[Tensor, "N 4"] | None
    """Δq (w, x, y, z), added to the canonical quaternion before normalisation."""
    scales: Float[Tensor, "N 3"] | None
    """Δ log-scale."""
    opacities: Float[Tensor, " N"] | None
    """Δ opacity logit."""
    colors: Float[Tensor, "N 3"] | None
    """Δ of the degree-0 SH coefficient (RGB)."""
    turn: Float[Tensor, "N 4"] | None = None
    """A unit quaternion (w, x, y, z) that turns the Gaussian about the scene box's centre,
    its position and orientation together, before `means` and `quats` are added; the
    model resolves it into those two (`dyngs.model.resolve_turn`). None: no turn."""


@dataclass(frozen=True)
class DeformationHeadConfig:
    """Per-attribute MLP decoders on a shared trunk (4D Gaussian Splatting, Wu et al. 2024)."""

    width: int = 64
    """Hidden width of the trunk and of every attribute branch (Wu et al. 2024 use 64)."""
    rotation: bool = True
    """Deform rotations (Δq)."""
    rigid: bool = False
    """The rotation branch turns each Gaussian about the scene box's centre (its position
    with its orientation) instead of only adding to its quaternion, so that Δμ and the
    turn form a rigid motion per point: an SE(3) deformation field as in Nerfies (Park et
    al. 2021). A rigid part that turns then asks the field for one constant turn and
    translation over the part, where a translation field needs Δμ that varies across it,
    and its Gaussians' orientations follow its surface. Needs `rotation`. Off by default:
    over the MuJoCo scenes and the demo it was no measured gain on average, and it lost on
    close_proximity in every seed (docs/ACCURACY.md, "A rigid deformation head")."""
    scale: bool = False
    """Deform scales (Δ log-scale). Off by default, unlike Wu et al. 2024: with it, a
    Gaussian the field does not carry along shrinks out of sight (the antialiasing filter
    then fades it too) instead of following its surface, and others are grown where the
    object went, so the motion is drawn by Gaussians handing over rather than tracked.
    Without it, the demo's seeds agree and gain on average, thin_structure and scale_change
    gain, and no scene measured lost beyond one run's noise (docs/ACCURACY.md, "Scales
    are not deformed")."""
    opacity: bool = False
    """Deform opacities (Δ logit); off by default, as in Wu et al. 2024."""
    color: bool = False
    """Deform the base colour (Δ SH degree 0); off by default, as in Wu et al. 2024."""

    def __post_init__(self) -> None:
        if self.width < 1:
            raise ConfigError(
                f"--head.width: deformation head width must be positive, got {self.width}"
            )
        if self.rigid and not self.rotation:
            raise ConfigError(
                "--head.rigid turns Gaussians with the rotation branch: it needs --head.rotation"
            )

    def build(
        self, in_dim: int, box: SceneBox, *, generator: torch.Generator | None = None
    ) -> DeformationHead:
        """A head reading `in_dim` field features; `box` sets the position scale (its
        half-diagonal), so that Δμ fits the scene whatever its size."""
        return DeformationHead(self, in_dim, 0.5 * box.diagonal, generator=generator)


def turn_quaternion(v: Float[Tensor, "N 3"]) -> Float[Tensor, "N 4"]:
    """The unit quaternion normalise(1, v/2): the identity at v = 0, a turn by 2·atan(|v|/2)
    ≈ |v| radians about v for small v, smooth everywhere (no 0/0 at v = 0, unlike the
    axis-angle exponential), and every turn short of a half turn reachable."""
    return normalize_quaternion(torch.cat((torch.ones_like(v[:, :1]), 0.5 * v), dim=-1))


def _branch(width: int, out: int, generator: torch.Generator | None) -> nn.Sequential:
    """Linear(W, W), ReLU, Linear(W, out) with the last Linear all zero, after an identity.

    Every branch reads ReLU(trunk), which `DeformationHead.forward` computes once for all
    of them (each branch applying its own ReLU computed it, and its backward, once per
    branch). The identity keeps the layers' indices, so the checkpoints' keys
    (`means.1.weight`, …) stay those of the branches that began with a ReLU."""
    last = nn.Linear(width, out)
    # Zero weights and bias: every delta is exactly 0 at step 0, so training starts from the
    # canonical (static) scene. The last layer still gets a gradient at once (its input,
    # the hidden activations, is non-zero); the layers before it get one from the second
    # step on, when the last layer's weights are no longer zero.
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(
        nn.Identity(), init_linear_(nn.Linear(width, width), generator), nn.ReLU(), last
    )


class DeformationHead(nn.Module):
    """Turns [N, C] field features into `Deltas`.

    Δμ is the position branch's output times `position_scale` (the scene box's
    half-diagonal, from the config's `build`): the branch works in box-relative units,
    so one learning rate fits scenes of any size. 4DGaussians gets the same effect by
    multiplying the deformation learning rate by the scene extent; scaling the output
    keeps the optimiser settings scene-independent. Rotation, scale, opacity and colour
    deltas are dimensionless (normalised-quaternion, log and logit space) and are not
    scaled.
    """

    def __init__(
        self,
        config: DeformationHeadConfig,
        in_dim: int,
        position_scale: float = 1.0,
        *,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        if in_dim < 1:
            raise ValueError(f"deformation head needs in_dim ≥ 1, got {in_dim}")
        if not position_scale > 0:
            raise ValueError(f"position_scale must be positive, got {position_scale}")
        self.config = config
        self.in_dim = in_dim
        self.position_scale = float(position_scale)
        w = config.width
        self.trunk = init_linear_(nn.Linear(in_dim, w), generator)
        self.means = _branch(w, 3, generator)
        self.quats = _branch(w, 3 if config.rigid else 4, generator) if config.rotation else None
        self.scales = _branch(w, 3, generator) if config.scale else None
        self.opacities = _branch(w, 1, generator) if config.opacity else None
        self.colors = _branch(w, 3, generator) if config.color else None

    def forward(self, features: Float[Tensor, "N C"]) -> Deltas:
        if features.ndim != 2 or features.shape[1] != self.in_dim:
            raise ValueError(f"features must be [N, {self.in_dim}], got {tuple(features.shape)}")
        hidden = torch.relu(self.trunk(features))  # every branch's first layer
        # The branches run in the order of `Deltas`' fields: that order fixes how the trunk's
        # gradient is summed, so runs stay the same to the bit whichever head is chosen.
        means = self.means(hidden) * self.position_scale
        rotation = self.quats(hidden) if self.quats is not None else None
        turn = None
        if rotation is not None and self.config.rigid:
            turn = turn_quaternion(rotation)
            rotation = None  # the turn replaces Δq
        return Deltas(
            means=means,
            quats=rotation,
            turn=turn,
            scales=self.scales(hidden) if self.scales is not None else None,
            opacities=self.opacities(hidden).squeeze(-1) if self.opacities is not None else None,
            colors=self.colors(hidden) if self.colors is not None else None,
        )

    def extra_repr(self) -> str:
        return f"in_dim={self.in_dim}, position_scale={self.position_scale:g}"
