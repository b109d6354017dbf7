"""A brute-force float64 reference renderer: the specification fast renderers are checked against.

Every pixel is tested against every Gaussian: no tiles, no bounding boxes. The loop runs over
Gaussians in depth order and is vectorised over pixels. Written for clarity, not speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dyngs.types import Camera, Gaussians

EPS2D = 0.3  # px² added to every 2D covariance by the plain rule (Kerbl et al. 2023)
MIP_FILTER = 0.1  # px² added instead when antialiased (Mip-Splatting, Yu et al. 2024)
OFF_AXIS = 1.3  # EWA Jacobian clamp: the image widened by 0.3·tan(fov/2) on each side
ALPHA_MIN = 1.0 / 255.0  # pairs with α below this are skipped
ALPHA_MAX = 0.99  # α is clamped to at most this
T_MIN = 1e-4  # a pixel stops before its transmittance would fall below this
QUAT_EPS = 1e-12

# Real spherical harmonics in the 3DGS sign convention, derived from their closed forms.
C0 = 1.0 / (2.0 * math.sqrt(math.pi))
C1 = math.sqrt(3.0 / (4.0 * math.pi))
_PI = math.pi
C2 = [
    math.sqrt(15 / (4 * _PI)),
    -math.sqrt(15 / (4 * _PI)),
    math.sqrt(5 / (16 * _PI)),
    -math.sqrt(15 / (4 * _PI)),
    math.sqrt(15 / (16 * _PI)),
]
C3 = [
    -math.sqrt(35 / (32 * _PI)),
    math.sqrt(105 / (4 * _PI)),
    -math.sqrt(21 / (32 * _PI)),
    math.sqrt(7 / (16 * _PI)),
    -math.sqrt(21 / (32 * _PI)),
    math.sqrt(105 / (16 * _PI)),
    -math.sqrt(35 / (32 * _PI)),
]


@dataclass
class OracleResult:
    rgb: Tensor  # [H, W, 3] float64
    alpha: Tensor  # [H, W, 1] float64
    depth: Tensor  # [H, W, 1] float64
    touches: Tensor  # [N] bool: some pixel has α ≥ 1/255 for this Gaussian (early stop ignored)
    fragile: Tensor  # [H, W] bool: a threshold decision here is close enough to flip in float32
    contribution: Tensor  # [N] float64: each Gaussian's blending weight summed over pixels


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis Y_k(dir) for unit directions [M, 3] → [M, (degree + 1)²], order l, then m."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            C2[0] * x * y,
            C2[1] * y * z,
            C2[2] * (2 * zz - xx - yy),
            C2[3] * x * z,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def quat_to_rotation(q: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z) → [N, 3, 3], normalised robustly; a zero quaternion → identity."""
    m = q.abs().amax(dim=-1, keepdim=True)
    q = torch.where(m > 0, q / torch.where(m > 0, m, 1.0), 0.0)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(QUAT_EPS)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(-1, 3, 3)


def render_oracle(
    gaussians: Gaussians,
    camera: Camera,
    background: Tensor,
    *,
    antialiased: bool = False,
    alpha_window: float = 1e-4,
    transmittance_window: float = 1e-3,
) -> OracleResult:
    out_device = gaussians.means.device
    dev = out_device if out_device.type != "mps" else torch.device("cpu")  # MPS has no float64
    n, h, w = len(gaussians), camera.height, camera.width
    means, quats = gaussians.means.to(dev).double(), gaussians.quats.to(dev).double()
    scales, opac = gaussians.scales.to(dev).double(), gaussians.opacities.to(dev).double()
    colors = gaussians.colors.to(dev).double()
    if gaussians.sh_degree is not None:
        colors = colors[:, : (gaussians.sh_degree + 1) ** 2]  # only the coefficients in use
    bg = background.to(dev).double().reshape(3)
    w2c = camera.world_to_camera.to(dev).double()
    rot_w, t_w = w2c[:3, :3], w2c[:3, 3]

    # 1. Drop Gaussians with any non-finite parameter; zero them so the maths below stays finite.
    keep = torch.cat([means, quats, scales, opac[:, None], colors.flatten(1)], 1).isfinite().all(1)
    k = keep[:, None]
    means, quats, scales = means.where(k, 0.0), quats.where(k, 0.0), scales.where(k, 0.0)
    opac = opac.where(keep, 0.0)
    colors = colors.where(keep.reshape(-1, *[1] * (colors.ndim - 1)), 0.0)

    # 2-3. 3D covariance Σ = R S Sᵀ Rᵀ.
    rs = quat_to_rotation(quats) * scales[:, None, :]  # R @ diag(s)
    cov3 = rs @ rs.transpose(1, 2)

    # 4-5. Camera space, near/far culling, projected centre.
    p = means @ rot_w.T + t_w
    x, y, z = p.unbind(-1)
    keep &= (z > camera.near) & (z < camera.far)
    zs = torch.where(keep, z, 1.0)  # safe divisor for dropped Gaussians
    u = camera.fx * x / zs + camera.cx
    v = camera.fy * y / zs + camera.cy

    # 6. EWA Jacobian with the off-axis clamp; 2D covariance J W Σ Wᵀ Jᵀ.
    # Bounds: the image's edges widened by (OFF_AXIS − 1)·tan(fov/2) on each side.
    tan_x, tan_y = 0.5 * camera.width / camera.fx, 0.5 * camera.height / camera.fy
    left = camera.cx / camera.fx + (OFF_AXIS - 1) * tan_x
    right = (camera.width - camera.cx) / camera.fx + (OFF_AXIS - 1) * tan_x
    top = camera.cy / camera.fy + (OFF_AXIS - 1) * tan_y
    bottom = (camera.height - camera.cy) / camera.fy + (OFF_AXIS - 1) * tan_y
    xc = (x / zs).clamp(-left, right) * zs
    yc = (y / zs).clamp(-top, bottom) * zs
    jac = torch.zeros(n, 2, 3, dtype=torch.float64, device=dev)
    jac[:, 0, 0], jac[:, 0, 2] = camera.fx / zs, -camera.fx * xc / zs**2
    jac[:, 1, 1], jac[:, 1, 2] = camera.fy / zs, -camera.fy * yc / zs**2
    jw = jac @ rot_w
    cov2 = jw @ cov3 @ jw.transpose(1, 2)

    # 7. Dilation, antialiasing compensation, degenerate culling.
    dilation = MIP_FILTER if antialiased else EPS2D
    cov2d = cov2 + dilation * torch.eye(2, dtype=torch.float64, device=dev)
    det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] * cov2[:, 1, 0]
    det_d = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    keep &= det_d > 0  # a NaN determinant (overflow) also drops the Gaussian
    det_ds = torch.where(keep, det_d, 1.0)
    if antialiased:
        opac = opac * torch.sqrt(det.clamp_min(0.0) / det_ds)
    # 8. Conic Q = Σ2d⁻¹ as (a, b, c) with Q = [[a, b], [b, c]].
    qa, qb, qc = cov2d[:, 1, 1] / det_ds, -cov2d[:, 0, 1] / det_ds, cov2d[:, 0, 0] / det_ds
    keep &= u.isfinite() & v.isfinite() & qa.isfinite() & qb.isfinite() & qc.isfinite()

    # 9. Colour: RGB as given, or SH evaluated from the camera centre, clamped below at 0.
    if gaussians.sh_degree is None:
        rgb_g = colors
    else:
        dirs = means - (-rot_w.T @ t_w)
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        basis = sh_basis(dirs, gaussians.sh_degree)  # [N, K]
        rgb_g = ((basis[:, :, None] * colors).sum(1) + 0.5).clamp_min(0.0)

    # 10-11. Front-to-back compositing over flattened pixels, Gaussians by z (stable sort).
    rows, cols = torch.meshgrid(
        torch.arange(h, device=dev, dtype=torch.float64),
        torch.arange(w, device=dev, dtype=torch.float64),
        indexing="ij",
    )
    px, py = cols.reshape(-1) + 0.5, rows.reshape(-1) + 0.5
    n_px = h * w
    trans = torch.ones(n_px, dtype=torch.float64, device=dev)
    acc_c = torch.zeros(n_px, 3, dtype=torch.float64, device=dev)
    acc_d = torch.zeros(n_px, dtype=torch.float64, device=dev)
    acc_a = torch.zeros(n_px, dtype=torch.float64, device=dev)
    done = torch.zeros(n_px, dtype=torch.bool, device=dev)
    fragile = torch.zeros(n_px, dtype=torch.bool, device=dev)
    touches = torch.zeros(n, dtype=torch.bool, device=dev)
    contribution = torch.zeros(n, dtype=torch.float64, device=dev)

    idx = torch.nonzero(keep).reshape(-1)
    order = idx[torch.sort(z[idx], stable=True).indices].tolist()
    for g in order:
        dx, dy = px - u[g], py - v[g]
        power = 0.5 * (qa[g] * dx * dx + 2 * qb[g] * dx * dy + qc[g] * dy * dy)
        alpha = (opac[g] * torch.exp(-power)).clamp_max(ALPHA_MAX)
        touches[g] = bool((alpha >= ALPHA_MIN).any())
        live = ~done
        fragile |= live & ((alpha - ALPHA_MIN).abs() <= alpha_window * ALPHA_MIN)
        hit = live & (alpha >= ALPHA_MIN)
        test = trans * (1 - alpha)
        fragile |= hit & ((test - T_MIN).abs() <= transmittance_window * T_MIN)
        stop = hit & (test < T_MIN)
        done |= stop
        draw = hit & ~stop
        wgt = torch.where(draw, alpha * trans, 0.0)
        acc_c += wgt[:, None] * rgb_g[g]
        acc_d += wgt * z[g]
        acc_a += wgt
        contribution[g] = wgt.sum()
        trans = torch.where(draw, test, trans)

    rgb = acc_c + trans[:, None] * bg
    depth = torch.where(acc_a > 0, acc_d / torch.where(acc_a > 0, acc_a, 1.0), 0.0)
    return OracleResult(
        rgb=rgb.reshape(h, w, 3).to(out_device),
        alpha=acc_a.reshape(h, w, 1).to(out_device),
        depth=depth.reshape(h, w, 1).to(out_device),
        touches=touches.to(out_device),
        fragile=fragile.reshape(h, w).to(out_device),
        contribution=contribution.to(out_device),
    )
