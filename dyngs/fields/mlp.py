"""`field:mlp`: a positional-encoding MLP of (x, y, z, t), as in Deformable 3D Gaussians.

Letters: N points, D input coordinates, L frequencies, E encoded width, W hidden width.

Deformable 3D Gaussians (Yang et al. 2024) feed sin/cos encodings of the position (10
frequencies) and time (6 frequencies) to an 8×256 ReLU MLP that re-injects its input
halfway (the NeRF skip, Mildenhall et al. 2020). This field is that trunk; the shared
deformation head turns its last hidden layer into deltas. It has no planes, so plane
regularizers cost nothing with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.errors import ConfigError
from dyngs.fields._common import init_linear_, space_time
from dyngs.fields.base import PlaneGrids
from dyngs.types import SceneBox


@dataclass(frozen=True)
class MLPFieldConfig:
    """Positional-encoding MLP field (Deformable 3D Gaussians, Yang et al. 2024)."""

    position_frequencies: int = 10
    """Sin/cos frequency bands of the box-normalised position (Yang et al. 2024 use 10)."""
    time_frequencies: int = 6
    """Sin/cos frequency bands of the normalised time (Yang et al. 2024 use 6)."""
    depth: int = 6
    """Number of Linear+ReLU layers; the encoded input is re-injected before layer depth // 2."""
    width: int = 128
    """Hidden width; also the field's out_dim."""

    def __post_init__(self) -> None:
        if self.position_frequencies < 0 or self.time_frequencies < 0:
            raise ConfigError(
                "mlp field frequencies must be ≥ 0, got "
                f"{self.position_frequencies}, {self.time_frequencies}"
            )
        if self.depth < 1 or self.width < 1:
            raise ConfigError(f"mlp field needs depth, width ≥ 1, got {self.depth}, {self.width}")

    def build(self, box: SceneBox, *, generator: torch.Generator | None = None) -> MLPField:
        return MLPField(self, box, generator=generator)


def positional_encoding(x: Float[Tensor, "N D"], frequencies: int) -> Float[Tensor, "N E"]:
    """[x, sin(2ᵏπx), cos(2ᵏπx)] for k < `frequencies` (NeRF's γ, Mildenhall et al. 2020),
    E = D·(1 + 2·frequencies). The raw input is kept, as in Yang et al. 2024."""
    if frequencies == 0:
        return x
    bands = torch.pi * torch.exp2(torch.arange(frequencies, dtype=x.dtype, device=x.device))
    angles = (x.unsqueeze(-1) * bands).flatten(1)  # [N, D·L], coordinate-major
    return torch.cat([x, angles.sin(), angles.cos()], dim=1)


class MLPField(nn.Module):
    """Features of (x, y, z, t) from a ReLU MLP over their positional encodings.

    Position is normalised by the scene box to [-1, 1]³ and t ∈ [0, 1] mapped to 2t − 1,
    with no clamp: the encoding is defined everywhere, so points outside the box get an
    extrapolated (finite) feature and keep their gradient. The output is the last hidden
    layer after its ReLU, `out_dim = width`.
    """

    out_dim: int

    def __init__(
        self,
        config: MLPFieldConfig,
        box: SceneBox,
        *,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.box = box
        self.out_dim = config.width
        self.in_dim = 3 * (1 + 2 * config.position_frequencies) + (1 + 2 * config.time_frequencies)
        # The NeRF skip: the encoding is concatenated to the input of layer `skip`.
        self.skip = config.depth // 2 if config.depth >= 2 else None
        layers = []
        for i in range(config.depth):
            fan_in = self.in_dim if i == 0 else config.width
            if i == self.skip:
                fan_in += self.in_dim
            layers.append(init_linear_(nn.Linear(fan_in, config.width), generator))
        self.layers = nn.ModuleList(layers)

    def encode(self, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "N E"]:
        """The MLP's input: encodings of the normalised position and time."""
        coords = space_time(self.box, xyz, t)
        return torch.cat(
            [
                positional_encoding(coords[:, :3], self.config.position_frequencies),
                positional_encoding(coords[:, 3:], self.config.time_frequencies),
            ],
            dim=1,
        )

    def forward(self, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "N W"]:
        encoded = self.encode(xyz, t)
        h = encoded
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                h = torch.cat([h, encoded], dim=1)
            h = F.relu(layer(h))
        return h

    def planes(self) -> PlaneGrids:
        """No planes: plane regularizers see empty lists."""
        return PlaneGrids()
