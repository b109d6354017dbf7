"""Which needle of `test_anisotropy_of_1e6` makes cuda-tile differ, and by how much.

Draws each needle of that hard case alone, then all three, with cuda-tile (float32) and
cpu-reference in float32, both on the GPU, and prints each one's largest difference from
cpu-reference in float64 on the same device, inside and outside the one-pixel coverage
band, and the radii each gives. Run by `benchmarks/gpu_check.sh` beside the tests;
`python benchmarks/gpu_anisotropy.py cpu` runs it with cpu-reference standing in for
cuda-tile (a check of the script itself).
"""

from __future__ import annotations

import sys

import torch

from dyngs.renderers.cpu_reference import CpuReferenceConfig
from dyngs.renderers.cuda_tile import CudaTileConfig
from tests.renderers.test_hard_cases import _boundary_band, _camera, _gaussians

QUATS = [[0.9, 0.1, 0.3, 0.2], [0.6, -0.5, 0.2, 0.4], [0.3, 0.1, -0.9, 0.2]]
MEANS = [[0.1, 0.1, 2.0], [-0.3, 0.2, 3.0], [0.2, -0.2, 2.5]]
SCALES = [[1.0, 1e-6, 1e-6], [1e-6, 1e-6, 1.0], [1e2, 1e-4, 1e-4]]


def main(device: str) -> None:
    fast = CudaTileConfig if device == "cuda" else CpuReferenceConfig
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    for pick in ([0], [1], [2], [0, 1, 2]):
        scene = _gaussians(
            [MEANS[i] for i in pick], [SCALES[i] for i in pick], quats=[QUATS[i] for i in pick]
        )
        camera = _camera().to(device)
        outs = {
            name: config(antialiased=False).build()(
                scene.to(device, dtype), camera, background.to(device, dtype)
            )
            for name, config, dtype in (
                ("fast", fast, torch.float32),
                ("ref32", CpuReferenceConfig, torch.float32),
                ("ref64", CpuReferenceConfig, torch.float64),
            )
        }
        truth = outs["ref64"]
        band = _boundary_band(truth.alpha.float()) | _boundary_band(outs["fast"].alpha.float())
        for name in ("fast", "ref32"):
            diff = (outs[name].rgb.double() - truth.rgb.double()).abs().amax(-1)
            row, col = divmod(int(diff.argmax()), diff.shape[1])
            print(
                f"needles {pick} {name}: off-band max {float(diff[~band].max()):.3g}, "
                f"band max {float(diff[band].max()) if band.any() else 0.0:.3g}, "
                f"{int((diff > 1e-4).sum())} of {diff.numel()} pixels > 1e-4, "
                f"worst at ({row}, {col})"
            )
        radii = f"fast {outs['fast'].radii.tolist()}, ref {truth.radii.tolist()}"
        print(f"needles {pick} radii: {radii}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "cuda")
