"""`cuda-tile`: the fast path on NVIDIA GPUs, with gsplat's tile rasterizer as the engine.

Install with `pip install dyngs[cuda]`. Held to `cpu-reference` by the parity tests in
tests/renderers/test_cuda_tile.py and the hard cases in tests/renderers/test_hard_cases.py
(skipped without a CUDA device).

How our guards map onto gsplat (v1.4+):
- near plane, far plane → `near_plane`, `far_plane`, and decided by `prepare` as well,
  because gsplat culls only z < near where the guard table culls z ≤ near; the dilation
  (`Guards.dilation`: 0.3 px², or Mip-Splatting's 0.1 when antialiased) → `eps2d`; Mip-Splatting
  compensation → `rasterize_mode="antialiased"`.
- A zero quaternion is handed over as the identity (gsplat would normalise it to NaN).
- Off-axis clamp in the EWA Jacobian: the shared rule (`stages.off_axis_limits`) is gsplat's
  own, the image's edges plus 0.3·tan(fov/2), so both draw the same footprints off screen.
- An empty scene never reaches gsplat, whose projection stops the process (SIGFPE) on it.
- α clamp: gsplat clamps α at 0.999 where we clamp at 0.99. Opacities are clamped to
  0.99 before the call, so α ≤ 0.99 everywhere; the two rules then differ only for
  Gaussians with opacity > 0.99, by at most 1 % of their α near their centre.
- Extent: gsplat's per-axis radius is ceil(min(3.33, √(2 ln(255 o)))·σ) px, the same
  opacity-aware ellipse bound as ours rounded up to whole pixels, so it never drops a
  pixel with α ≥ 1/255 either.
- Early stop: gsplat stops when T would fall to ≤ 1e-4 (we: < 1e-4); the two differ
  only when T lands exactly on the threshold.
- Non-finite parameters are culled, and depth decided, by the shared `prepare` stage
  before gsplat sees anything, exactly as in the reference.
- Means are handed over camera-relative (computed in float64 by `prepare`), so a float32
  scene far from the origin keeps its precision (docs/NUMERICS.md).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.errors import RendererUnavailable
from dyngs.geometry import normalize_quaternion
from dyngs.renderers.base import AntialiasedConfig, Guards, RenderOutput
from dyngs.renderers.stages import Prepared, prepare
from dyngs.types import Camera, Gaussians


def cuda_tile_available() -> bool:
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


@dataclass(frozen=True)
class CudaTileConfig(AntialiasedConfig):
    """gsplat's CUDA tile rasterizer (needs an NVIDIA GPU and `pip install dyngs[cuda]`)."""

    tile_size: int = 16
    """Tile edge in pixels."""
    packed: bool = False
    """gsplat's packed mode: less memory for large scenes, a little slower for small ones."""
    absgrad: bool = True
    """Also accumulate |∂L/∂means2d| per pixel (AbsGS), available to densification."""

    def build(self) -> CudaTileRenderer:
        return CudaTileRenderer(self)


class CudaTileRenderer:
    def __init__(self, config: CudaTileConfig | None = None, guards: Guards | None = None) -> None:
        if not torch.cuda.is_available():
            raise RendererUnavailable(
                "renderer cuda-tile needs a CUDA device and none is available; "
                "use renderer:cpu-reference"
            )
        if importlib.util.find_spec("gsplat") is None:
            raise RendererUnavailable(
                "renderer cuda-tile needs gsplat, which is not installed; "
                "run `pip install dyngs[cuda]` or use renderer:cpu-reference"
            )
        from gsplat import rasterization

        self._rasterization = rasterization
        self.config = config or CudaTileConfig()
        self.guards = guards or Guards()

    def __call__(
        self, gaussians: Gaussians, camera: Camera, background: Float[Tensor, " 3"]
    ) -> RenderOutput:
        """gsplat does not report each Gaussian's contribution, so this is not a
        `ContributionRenderer`: a run with it prunes by opacity and size alone, and says so."""
        g = gaussians
        ready = prepare(g, camera)
        if len(g) == 0:
            return self._background_only(g, camera, background, ready)
        inputs = self._inputs(g, camera, ready)
        background = background.to(device=g.means.device, dtype=g.means.dtype)
        # gsplat 1.5.3's packed path asserts a background of shape [channels] where its own
        # `rasterization` hands over [cameras, channels], so every packed render with a
        # background stopped (seen on an H200). Packed renders therefore composite onto
        # black and add the background here: rgb + T·background, T = 1 − α, which is what
        # gsplat's kernel adds, and autograd carries it through α.
        own_background = self.config.packed
        rgbd, alpha, meta = self._rasterization(
            **inputs,
            width=camera.width,
            height=camera.height,
            near_plane=camera.near,
            far_plane=camera.far,
            eps2d=self.guards.dilation(self.config.antialiased),
            sh_degree=g.sh_degree,
            packed=self.config.packed,
            tile_size=self.config.tile_size,
            backgrounds=None if own_background else background[None],
            render_mode="RGB+ED",
            absgrad=self.config.absgrad,
            rasterize_mode="antialiased" if self.config.antialiased else "classic",
        )
        rgb = rgbd[0, ..., :3]
        if own_background:
            rgb = rgb + (1 - alpha[0]) * background
        ids = meta["gaussian_ids"] if self.config.packed else None
        radii = self._rows(meta["radii"], ids, len(g))
        if radii.ndim == 1:  # gsplat < 1.5 returns one radius per Gaussian
            radii = radii[:, None].expand(-1, 2)
        # gsplat may give a radius to a row it draws nothing of (one culled here, or too
        # faint: o < 1/255); as in the reference, such rows are not visible and have radius 0.
        visible = (radii > 0).all(dim=-1) & ready.finite & ready.in_depth
        visible &= inputs["opacities"] >= self.guards.alpha_min
        means2d, absgrad = self._screen_gradients(meta["means2d"], ids, len(g))
        return RenderOutput(
            rgb=rgb,
            alpha=alpha[0],
            depth=rgbd[0, ..., 3:4],
            means2d=means2d,
            radii=torch.where(visible[:, None], radii, 0).int(),
            visible=visible,
            num_nonfinite=ready.num_nonfinite,
            means2d_absgrad=absgrad,
        )

    @staticmethod
    def _rows(t: Tensor, ids: Tensor | None, n: int) -> Tensor:
        """One row per Gaussian of a per-Gaussian output of gsplat: its first camera's rows,
        or, in packed mode (which lists only the drawn Gaussians), scattered back by `ids`
        with zeros elsewhere."""
        if ids is None:
            return t[0]
        return t.new_zeros(n, *t.shape[1:]).index_copy(0, ids, t)

    def _screen_gradients(
        self, full: Tensor, ids: Tensor | None, n: int
    ) -> tuple[Tensor, Tensor | None]:
        """The 2D means, one row per Gaussian, whose `.grad` backward fills, and a buffer it
        fills with gsplat's absolute gradient (None unless asked for).

        gsplat rasterizes from its own 2D means tensor, `full`, so no view or copy of it
        that we hand out lies on the loss's path, and `retain_grad` on one stays None (so it
        was: no run densified on a GPU until 2026-11-27, when a trained demo ended with
        fewer Gaussians than it began with). A hook on `full` runs once all of its gradient
        is in, after gsplat's backward has also hung its absolute gradient on it as
        `.absgrad`, and copies both out, row by row."""
        means2d = self._rows(full.detach(), ids, n)
        if not full.requires_grad:
            return means2d, None
        absgrad = full.new_zeros(n, 2) if self.config.absgrad else None

        def fill(grad: Tensor) -> None:
            with torch.no_grad():
                rows = self._rows(grad, ids, n)
                means2d.grad = rows if means2d.grad is None else means2d.grad + rows
                value = getattr(full, "absgrad", None)
                if absgrad is not None and value is not None:
                    absgrad.copy_(self._rows(value, ids, n))

        full.register_hook(fill)
        return means2d, absgrad

    @staticmethod
    def _background_only(
        g: Gaussians, camera: Camera, background: Tensor, ready: Prepared
    ) -> RenderOutput:
        """An empty scene, drawn without gsplat: its projection kernel stops the whole
        process (SIGFPE) when handed zero Gaussians. The outputs stay in the autograd graph
        of the (empty) parameters, as any other scene's do, so backward runs as usual."""
        # A sum over zero rows is exactly 0: this adds nothing but the graph's edges.
        tie = sum(t.sum() for t in (g.means, g.quats, g.scales, g.opacities, g.colors))
        shape = (camera.height, camera.width)
        alpha = g.means.new_zeros(*shape, 1) + tie
        rgb = background.to(alpha).expand(*shape, 3) + tie
        return RenderOutput(
            rgb=rgb,
            alpha=alpha,
            depth=alpha.clone(),
            means2d=g.means.new_zeros(0, 2),
            radii=torch.zeros(0, 2, dtype=torch.int32, device=g.means.device),
            visible=torch.zeros(0, dtype=torch.bool, device=g.means.device),
            num_nonfinite=ready.num_nonfinite,
        )

    def _inputs(self, g: Gaussians, camera: Camera, ready: Prepared) -> dict[str, Tensor]:
        """gsplat's per-Gaussian inputs and camera, from the prepared Gaussians. Only the
        colour coefficients in use are handed over (`prepare` keeps those alone), so that
        nothing gsplat reads can hold a value the finiteness check did not see."""
        device, dtype = g.means.device, g.means.dtype
        K = torch.tensor(
            [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
            device=device,
            dtype=dtype,
        )
        # gsplat projects in float32, where a scene 1e4 units from the origin loses ~1e-3
        # units of camera-relative position. So it sees the means shifted by the camera
        # centre c = −Rᵀt in float64, μ − c, and the translation t + Rc (≈ 0):
        # R(μ − c) + (t + Rc) = Rμ + t, whatever rounding left in R. SH directions are
        # unchanged when R is orthonormal; a float32 R is so only to ~1e-7, which far from
        # the origin moves the camera centre gsplat derives by ~1e-7·|t|: keep
        # world_to_camera in float64 there (docs/NUMERICS.md).
        viewmat = torch.eye(4, device=device, dtype=torch.float64)
        viewmat[:3, :3] = ready.rotation
        viewmat[:3, 3] = ready.translation + ready.rotation @ ready.center
        # gsplat culls only z < near; the guard table culls z ≤ near (and z ≥ far), decided
        # in `prepare`: a culled row gets opacity 0, so gsplat draws nothing of it.
        opacities = torch.where(ready.in_depth, ready.opacities, 0).to(dtype)
        # gsplat normalises quaternions itself, and a zero one would become NaN there; the
        # guard table makes it the identity rotation, as `quaternion_to_rotation` does.
        quats = normalize_quaternion(ready.quats.to(dtype), self.guards.quat_eps)
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], device=device, dtype=quats.dtype)
        return {
            "means": ready.relative_means().to(dtype),
            "quats": torch.where((quats == 0).all(dim=-1, keepdim=True), identity, quats),
            "scales": ready.scales.to(dtype),
            "opacities": opacities.clamp(0, self.guards.alpha_max),
            "colors": ready.colors,
            "viewmats": viewmat.to(dtype)[None],
            "Ks": K[None],
        }
