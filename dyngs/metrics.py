"""Evaluation metrics: PSNR, SSIM and LPIPS (v0.1, AlexNet).

Letters: H×W image, B images, C channels. Images are float HWC RGB in [0, 1] (data
range 1); a metric returns a 0-d tensor (call float() on it for a report).

LPIPS (Zhang et al. 2018) is computed here in plain torch from two weight files
(see ../shared/weights/README.md): torchvision's ImageNet AlexNet feature stack and the
LPIPS v0.1 linear layers, looked up under $TORCH_HOME/hub/checkpoints. When they are
absent `load_lpips` returns None after one warning, and LPIPS is reported as null.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.losses.photometric import SSIM_WINDOW, ssim_map

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
"""torchvision's ImageNet AlexNet (keys features.{0,3,6,8,10}.{weight,bias})."""
LPIPS_LIN_FILE = "lpips-v0.1-alex-lin.pth"
"""LPIPS v0.1 linear layers for AlexNet (keys lin{0..4}.model.1.weight, [1, C, 1, 1])."""

_URLS = {
    ALEXNET_FILE: "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
    LPIPS_LIN_FILE: "https://github.com/richzhang/PerceptualSimilarity/raw/master/lpips/weights/v0.1/alex.pth",
}


def psnr(pred: Float[Tensor, "H W C"], target: Float[Tensor, "H W C"]) -> Float[Tensor, ""]:
    """Peak signal-to-noise ratio in dB for data range 1: −10·log10(MSE).

    Identical images give +inf (MSE = 0); it is not capped, so that a perfect
    reconstruction is never confused with a merely good one. Callers that average over
    frames should expect it (json.dumps writes it as Infinity).
    """
    if pred.shape != target.shape:
        raise ValueError(f"shapes differ: {tuple(pred.shape)} and {tuple(target.shape)}")
    mse = (pred - target).square().mean()
    return -10.0 * torch.log10(mse)


def ssim(
    pred: Float[Tensor, "H W C"], target: Float[Tensor, "H W C"], window_size: int = SSIM_WINDOW
) -> Float[Tensor, ""]:
    """Mean SSIM (Wang et al. 2004): 11×11 Gaussian window, σ = 1.5, data range 1.

    Averaged over the 'valid' map (no padding), as in the authors' MATLAB code and
    scikit-image with gaussian_weights=True; 3DGS-style evaluation scripts average a
    zero-padded 'same' map instead, which differs at the borders by about 1e-3. The
    window shrinks to fit images smaller than 11 px (dyngs.losses.photometric).
    """
    return ssim_map(pred, target, window_size, padding="valid").mean()


class LPIPS(nn.Module):
    """LPIPS v0.1 with AlexNet (Zhang et al. 2018), in plain torch.

    The five ReLU outputs of AlexNet's feature stack are unit-normalised over channels per
    pixel, their squared differences weighted by the per-layer linear (1×1, no bias)
    layers, averaged over space and summed over layers. The weights are frozen; gradients
    still flow to the images, so it can serve as a loss too.
    """

    MIN_SIZE = 31
    """Smallest H and W AlexNet's strides and pools accept (the second max-pool needs a
    3×3 input, i.e. a 7×7 output of the first convolution)."""

    # LPIPS' ScalingLayer: ImageNet statistics expressed for inputs in [-1, 1].
    _SHIFT = (-0.030, -0.088, -0.188)
    _SCALE = (0.458, 0.448, 0.450)
    # ε of LPIPS' normalize_tensor, added to the norm.
    _EPS = 1e-10

    shift: Tensor
    scale: Tensor

    def __init__(self) -> None:
        super().__init__()
        # AlexNet's convolutions (Krizhevsky et al. 2012, torchvision's variant).
        self.convs = nn.ModuleList(
            [
                nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
                nn.Conv2d(64, 192, kernel_size=5, padding=2),
                nn.Conv2d(192, 384, kernel_size=3, padding=1),
                nn.Conv2d(384, 256, kernel_size=3, padding=1),
                nn.Conv2d(256, 256, kernel_size=3, padding=1),
            ]
        )
        self.lins = nn.ModuleList(
            [nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in (64, 192, 384, 256, 256)]
        )
        self.register_buffer("shift", torch.tensor(self._SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(self._SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_state_dicts(cls, alexnet: dict[str, Tensor], lins: dict[str, Tensor]) -> LPIPS:
        """Build from torchvision's AlexNet state dict and LPIPS' v0.1 linear layers.

        Only `features.{0,3,6,8,10}` are read; the classifier is ignored (in the shared
        checkpoint it is zero-stride views).
        """
        model = cls()
        state: dict[str, Tensor] = {}
        for i, index in enumerate((0, 3, 6, 8, 10)):
            state[f"convs.{i}.weight"] = alexnet[f"features.{index}.weight"]
            state[f"convs.{i}.bias"] = alexnet[f"features.{index}.bias"]
            state[f"lins.{i}.weight"] = lins[f"lin{i}.model.1.weight"]
        state["shift"] = model.shift
        state["scale"] = model.scale
        model.load_state_dict(state, strict=True)
        return model

    def features(self, x: Float[Tensor, "B 3 H W"]) -> list[Tensor]:
        """The five ReLU outputs; max-pools sit before the second and third convolutions."""
        taps = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = nn.functional.max_pool2d(x, kernel_size=3, stride=2)
            x = nn.functional.relu(conv(x))
            taps.append(x)
        return taps

    def forward(
        self, pred: Float[Tensor, "*B H W 3"], target: Float[Tensor, "*B H W 3"]
    ) -> Float[Tensor, "*B"]:
        """LPIPS distance of images in [0, 1] (one per leading index; 0-d for one image)."""
        if pred.shape != target.shape or pred.shape[-1] != 3:
            raise ValueError(
                f"images must both be [..., H, W, 3], got {tuple(pred.shape)} and "
                f"{tuple(target.shape)}"
            )
        height, width = pred.shape[-3], pred.shape[-2]
        if min(height, width) < self.MIN_SIZE:
            raise ValueError(
                f"LPIPS (AlexNet) needs images of at least {self.MIN_SIZE}×{self.MIN_SIZE} "
                f"pixels, got {height}×{width}"
            )
        batch = pred.shape[:-3]
        both = torch.cat([pred.reshape(-1, height, width, 3), target.reshape(-1, height, width, 3)])
        x = both.permute(0, 3, 1, 2).to(self.shift.dtype)
        x = ((2.0 * x - 1.0) - self.shift) / self.scale
        total = x.new_zeros(both.shape[0] // 2)
        for feature, lin in zip(self.features(x), self.lins, strict=True):
            # vector_norm's gradient is 0 (not NaN) where a pixel's features are all 0.
            unit = feature / (torch.linalg.vector_norm(feature, dim=1, keepdim=True) + self._EPS)
            a, b = unit.chunk(2)
            total = total + lin((a - b).square()).mean(dim=(1, 2, 3))
        return total.reshape(batch)


def load_lpips(device: torch.device | str | None = None, download: bool = False) -> LPIPS | None:
    """LPIPS from $TORCH_HOME/hub/checkpoints, or None (with one warning) when a weight
    file is missing. With `download`, missing files are first fetched with
    torch.hub.load_state_dict_from_url (off by default: evaluation never reaches for the
    network on its own)."""
    folder = Path(torch.hub.get_dir()) / "checkpoints"
    missing = [name for name in (ALEXNET_FILE, LPIPS_LIN_FILE) if not (folder / name).is_file()]
    failure = ""
    if missing and download:
        try:
            for name in missing:
                torch.hub.load_state_dict_from_url(
                    _URLS[name],
                    model_dir=str(folder),
                    file_name=name,
                    check_hash=name == ALEXNET_FILE,
                    weights_only=True,
                )
        except (OSError, RuntimeError) as error:  # URLError is an OSError
            failure = f" (download failed: {error})"
        missing = [name for name in missing if not (folder / name).is_file()]
    if missing:
        warnings.warn(
            f"LPIPS weights {', '.join(missing)} not found in {folder}{failure}; "
            "LPIPS will be reported as null",
            stacklevel=2,
        )
        return None
    alexnet = torch.load(folder / ALEXNET_FILE, map_location="cpu", weights_only=True)
    lins = torch.load(folder / LPIPS_LIN_FILE, map_location="cpu", weights_only=True)
    return LPIPS.from_state_dicts(alexnet, lins).to(device)
