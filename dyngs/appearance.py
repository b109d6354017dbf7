"""Per-camera colour: a gain and an offset per channel for each camera of a rig.

Real cameras disagree on colour: exposure, white balance and vignetting differ from one
camera to the next, so a surface that several cameras see has several colours. Without a
way to say so, the Gaussians must draw one compromise for all of them, or spend their
view-dependent colour on it. Dynamic 3D Gaussians (Luiten et al. 2024) learn, for each
camera c, a scale and an offset of the rendered image, `exp(m_c)·rgb + b_c`; so does this
module, for each camera that stays put (seen by training at three or more times): a view
of its own would only let its colour absorb that view's error. Images
rendered with an alpha channel (synthetic scenes) get none: one virtual camera drew them.

The gains and offsets are centred over the cameras before use, so the average camera
draws the Gaussians as they are: a camera training never saw (a held-out camera, a novel
view) gets that average, and a rig of one camera has nothing to correct (it gets none).

Letters: C cameras, H×W image.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.datamanagers.base import Split
from dyngs.datamanagers.fixed_cameras import fixed_camera_groups
from dyngs.types import Camera

DECIMALS = 3
"""Camera centres are matched to this many decimals (`Camera.viewpoint`)."""


class CameraColours(nn.Module):
    """`exp(g_c − ḡ)·rgb + (b_c − b̄)` for the camera c a view was taken from (see the
    module docstring); identity for a camera not among `centres`."""

    centres: Tensor

    def __init__(self, centres: Float[Tensor, "C 3"]) -> None:
        super().__init__()
        self.register_buffer("centres", centres.detach().to(torch.float64).clone())
        count = len(centres)
        self.log_gains = nn.Parameter(torch.zeros(count, 3))
        self.offsets = nn.Parameter(torch.zeros(count, 3))
        self._rows: dict[tuple[float, ...], int] | None = None

    @classmethod
    def for_split(cls, split: Split) -> CameraColours | None:
        """One colour per fixed camera of a training split of photographs
        (`fixed_camera_groups`: the same camera at three or more times), by centre, in the
        order they first appear. None for RGBA renders (images with an alpha channel),
        which one virtual camera drew, so no camera's colour differs (docs/ACCURACY.md
        measures what colours cost them), and None when fewer than two cameras are fixed
        (one camera's colour is the scene's own)."""
        if split.masks is not None and split.mask_kind == "alpha":
            return None
        groups = fixed_camera_groups(split)
        centres = dict.fromkeys(split.cameras[views[0]].viewpoint(DECIMALS) for views in groups)
        if len(centres) < 2:
            return None
        return cls(torch.tensor(list(centres), dtype=torch.float64))

    def note(self) -> str:
        """What the run says of them."""
        return (
            f"[colour] {len(self)} cameras that stay put each learn a colour, a gain and an "
            "offset per channel (--optim.camera-colours 0: none)"
        )

    def __len__(self) -> int:
        return len(self.centres)

    def row(self, camera: Camera) -> int | None:
        """The row of `camera`'s viewpoint, or None for a camera not among the centres."""
        if self._rows is None:
            self._rows = {tuple(centre): i for i, centre in enumerate(self.centres.tolist())}
        return self._rows.get(camera.viewpoint(DECIMALS))

    def forward(self, rgb: Float[Tensor, "H W 3"], camera: Camera) -> Float[Tensor, "H W 3"]:
        row = self.row(camera)
        if row is None:
            return rgb
        gain = self.log_gains[row] - self.log_gains.mean(0)
        offset = self.offsets[row] - self.offsets.mean(0)
        return rgb * gain.exp().to(rgb.dtype) + offset.to(rgb.dtype)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[no-untyped-def]
        self._rows = None  # the centres come with the state
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
