"""splax (JAX with NVIDIA Warp kernels) on the CPU, for bench_renderer.py.

splax declares jax[cuda], so it is installed without its dependencies; its kernels are
Warp kernels that Warp also registers for JAX's CPU backend, with two settings this
adapter makes: Warp's experimental CPU blocks on, and no CUDA-graph capture. Forward
times are a jitted forward alone; total times are one jitted value-and-gradient call
(JAX fuses the two). Install (its own environment; see docs/RENDERER.md):
pip install jax jaxlib warp-lang && pip install --no-deps splax.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

THREADS = int(os.environ.get("THREADS", "2"))
os.environ["OMP_NUM_THREADS"] = str(THREADS)
os.environ["JAX_PLATFORMS"] = "cpu"
os.environ["XLA_FLAGS"] = (
    f"--xla_cpu_multi_thread_eigen={'true' if THREADS > 1 else 'false'} "
    f"intra_op_parallelism_threads={THREADS}"
)
sys.path.insert(0, str(Path(__file__).parent))

import numpy as np  # noqa: E402
import scene as scene_file  # noqa: E402


def main() -> None:
    args = scene_file.adapter_args()

    from importlib.metadata import version

    import warp as wp

    wp.config.quiet = True
    wp.config.enable_cpu_blocks = True
    plain = wp.jax_callable

    def without_graphs(*a, **kw):  # CUDA-graph capture is refused on the CPU
        kw["graph_mode"] = wp.JaxCallableGraphMode.NONE
        return plain(*a, **kw)

    wp.jax_callable = without_graphs
    import jax
    import jax.numpy as jnp
    import splax

    s = scene_file.load(args.scene)
    width, height = int(s["width"]), int(s["height"])
    k = s["K"].astype(np.float64)
    sh0 = 0.5 / np.sqrt(np.pi)  # splax colours are SH: rgb = sh0 · c + 0.5
    camera = dict(
        viewmat=jnp.asarray(s["world_to_camera"], jnp.float32), background=jnp.zeros(3),
        img_shape=(height, width), f=(float(k[0, 0]), float(k[1, 1])),
        c=(float(k[0, 2]), float(k[1, 2])),
    )  # fmt: skip
    quats = jnp.asarray(s["quats"], jnp.float32)

    def image(means, scales, opacities, colors):  # type: ignore[no-untyped-def]
        o = jnp.clip(opacities, 1e-6, 1 - 1e-6)
        rgb, _ = splax.render(means, jnp.log(scales), quats, ((colors - 0.5) / sh0)[:, None, :],
                              jnp.log(o) - jnp.log1p(-o), **camera)  # fmt: skip
        return rgb

    forward = jax.jit(image)
    both = jax.jit(jax.value_and_grad(lambda *p: jnp.sum(image(*p)), argnums=(0, 1, 2, 3)))
    params = tuple(
        jnp.asarray(s[n], jnp.float32) for n in ("means", "scales", "opacities", "colors")
    )
    forward_s, total_s = [], []
    for repeat in range(args.repeats + 1):
        started = time.perf_counter()
        rgb = forward(*params).block_until_ready()
        middle = time.perf_counter()
        if args.backward:
            jax.block_until_ready(both(*params))
        if repeat > 0:
            forward_s.append(middle - started)
            total_s.append(time.perf_counter() - middle if args.backward else middle - started)
    scene_file.save_result(
        args.out, np.asarray(rgb),
        {"peer": "splax", "version": version("splax"), "forward_s": forward_s,
         "total_s": total_s, "threads_used": THREADS,
         "notes": f"jax {jax.__version__} on the CPU, warp-lang {version('warp-lang')}"},
    )  # fmt: skip


if __name__ == "__main__":
    main()
