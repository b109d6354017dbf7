"""Renderers: `cpu-reference` (pure PyTorch, the specification) and `cuda-tile` (gsplat)."""
