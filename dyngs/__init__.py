"""dyngs: dynamic (4D) Gaussian Splatting.

`dyngs.rasterize(...)` draws Gaussians given as raw tensors with any registered renderer
(`dyngs.renderers.rasterize`); the package map is docs/DESIGN.md.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.2.0"


def __getattr__(name: str) -> Any:
    # Imported on first use, so that `import dyngs.errors` does not load PyTorch.
    if name == "rasterize":
        from dyngs.renderers import rasterize

        return rasterize
    raise AttributeError(f"module 'dyngs' has no attribute {name!r}")
