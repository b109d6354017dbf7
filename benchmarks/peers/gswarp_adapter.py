"""gswarp (NVIDIA Warp's port of the 3DGS rasterizer) on the CPU, for bench_renderer.py.

gswarp's public rasterizer refuses CPU tensors, so this calls the autograd function behind
it; its tile kernels need Warp's experimental CPU blocks (without them the image is nearly
empty). Warp's CPU kernels run on one thread whatever THREADS says. Install (its own
environment; see docs/RENDERER.md): pip install torch==2.13.0 gswarp.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

THREADS = int(os.environ.get("THREADS", "2"))
os.environ["OMP_NUM_THREADS"] = str(THREADS)
sys.path.insert(0, str(Path(__file__).parent))

import numpy as np  # noqa: E402
import scene as scene_file  # noqa: E402


def main() -> None:
    args = scene_file.adapter_args()

    from importlib.metadata import version

    import torch
    import warp as wp

    torch.set_num_threads(THREADS)
    wp.config.quiet = True
    wp.config.enable_cpu_blocks = True
    wp.init()
    from gswarp import GaussianRasterizationSettings
    from gswarp._internal.frontend import common, standard_autograd
    from gswarp.methods.baseline_3dgs import METHOD

    s = scene_file.load(args.scene)
    width, height = int(s["width"]), int(s["height"])
    k = s["K"].astype(np.float64)
    w2c = s["world_to_camera"].astype(np.float64)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    near, far = 0.01, 1e4
    # The 3DGS rasterizer takes row-vector matrices: view = w2cᵀ, proj = (P w2c)ᵀ, with the
    # principal point as a shear of NDC.
    p = np.zeros((4, 4))
    p[0, 0], p[0, 2] = 2 * fx / width, 2 * cx / width - 1
    p[1, 1], p[1, 2] = 2 * fy / height, 2 * cy / height - 1
    p[2, 2], p[2, 3], p[3, 2] = far / (far - near), -far * near / (far - near), 1.0
    settings = GaussianRasterizationSettings(
        image_height=height, image_width=width, tanfovx=width / (2 * fx),
        tanfovy=height / (2 * fy), bg=torch.zeros(3), scale_modifier=1.0,
        viewmatrix=torch.tensor(w2c.T, dtype=torch.float32),
        projmatrix=torch.tensor((p @ w2c).T, dtype=torch.float32), sh_degree=0,
        campos=torch.tensor(np.linalg.inv(w2c)[:3, 3], dtype=torch.float32),
        prefiltered=False, debug=False, auto_tune=False, auto_tune_verbose=False,
    )  # fmt: skip
    plan = common.plan_for(METHOD)
    tensors = {name: torch.tensor(s[name], dtype=torch.float32) for name in
               ("means", "scales", "colors", "quats")}  # fmt: skip
    tensors["opacities"] = torch.tensor(s["opacities"], dtype=torch.float32)[:, None]
    forward_s, total_s = [], []
    for repeat in range(args.repeats + 1):
        leaves = {n: t.clone().requires_grad_(args.backward) for n, t in tensors.items()}
        started = time.perf_counter()
        with torch.set_grad_enabled(args.backward):
            q = leaves["quats"] / leaves["quats"].norm(dim=1, keepdim=True)
            screen = torch.zeros_like(leaves["means"], requires_grad=args.backward)
            image = standard_autograd.rasterize_gaussians(
                plan, leaves["means"], screen, torch.Tensor([]), leaves["colors"],
                leaves["opacities"], leaves["scales"], q, torch.Tensor([]), settings,
            )[0]  # fmt: skip
        middle = time.perf_counter()
        if args.backward:
            image.sum().backward()
        if repeat > 0:  # the first run compiles and warms up
            forward_s.append(middle - started)
            total_s.append(time.perf_counter() - started)
    scene_file.save_result(
        args.out,
        image.detach().permute(1, 2, 0).numpy(),
        {"peer": "gswarp", "version": version("gswarp"), "forward_s": forward_s,
         "total_s": total_s, "threads_used": 1,
         "notes": f"warp-lang {version('warp-lang')} on the CPU, one thread"},
    )  # fmt: skip


if __name__ == "__main__":
    main()
