"""The compiled projection of `cpu-tile` (numba): `stages.project`'s geometry, forward and
backward, one Gaussian per loop iteration.

`stages.project` is the specification: EWA splatting (Zwicker et al. 2001) as 3DGS uses
it (Kerbl et al. 2023), in float64, with its guards (docs/RENDERER.md): non-finite rows
drawn as zeros and culled, depth outside (near, far) culled and its depth replaced by 1,
the off-axis clamp in the Jacobian, +`eps2d` dilation, culling on det ≤ 0, opacity below
`alpha_min` or a non-finite det or 2D mean, and the α ≥ `alpha_min` box. In PyTorch those
are some sixty whole-array operations forward and as many backward, each a pass over
memory and a dispatch; here they are one pass, and backward is the chain rule written out
(the 3DGS backward kernels' order: conic, then 2D covariance, then 3D covariance and
quaternion, then the mean). tests/renderers/test_cpu_tile.py holds both directions to the
PyTorch stage on random scenes and every hard case, and gradcheck in float64.

Letters: N Gaussians.
"""

from __future__ import annotations

import math

import numpy as np
from numba import literal_unroll, njit, prange

OUT_COLUMNS = (2, 3, 1, 1, 2)
"""Columns of the forward's float64 outputs, one array each (so that each can be handed
to PyTorch as it is): 2D mean, conic, opacity, depth, extent."""

CHUNK = 256
"""Gaussians per call of the per-range functions the parallel loops run: a call passes the
scene's arrays, and numba counts references on each of them, which cost about as much as
projecting a Gaussian when the calls were one a Gaussian. Within a range the per-Gaussian
code is inlined. (The ranges are independent, so any split gives the same results.)"""

GRAD_COLUMNS = 11
"""Columns of the backward's output: ∂/∂mean (3), quaternion (4), scale (3), opacity."""


@njit(cache=True, nogil=True, inline="always")
def _rotation(q0: float, q1: float, q2: float, q3: float, eps: float) -> tuple:  # pragma: no cover
    """(w, x, y, z) normalised as `geometry.normalize_quaternion` does (divided by the
    largest |component| first, then by max(norm, eps)), the norm after the first division,
    that divisor, and the rotation matrix's nine entries row by row."""
    big = max(abs(q0), abs(q1), abs(q2), abs(q3))
    if not big > 0.0:
        big = 1.0
    w, x, y, z = q0 / big, q1 / big, q2 / big, q3 / big
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    n = max(norm, eps)
    w, x, y, z = w / n, x / n, y / n, z / n
    r = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return w, x, y, z, norm, n, big, r


@njit(cache=True, nogil=True, inline="always")
def _camera_point(
    means: np.ndarray, i: int, finite: bool, rot: np.ndarray, trans: np.ndarray
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """R μ + t for Gaussian i (a non-finite row is drawn as the origin)."""
    if not finite:
        return trans[0], trans[1], trans[2]
    mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
    return (
        rot[0, 0] * mx + rot[0, 1] * my + rot[0, 2] * mz + trans[0],
        rot[1, 0] * mx + rot[1, 1] * my + rot[1, 2] * mz + trans[1],
        rot[2, 0] * mx + rot[2, 1] * my + rot[2, 2] * mz + trans[2],
    )


@njit(cache=True, nogil=True, inline="always")
def _jacobian_rows(
    px: float, py: float, z: float, intrinsics: np.ndarray, rot: np.ndarray
) -> tuple:  # pragma: no cover - compiled
    """T = J R (2×3, row-major) with the off-axis clamp in J, and the clamped (tx, ty)."""
    fx, fy = intrinsics[0], intrinsics[1]
    tx = min(max(px / z, -intrinsics[4]), intrinsics[8]) * z
    ty = min(max(py / z, -intrinsics[5]), intrinsics[9]) * z
    j00, j02 = fx / z, -fx * tx / (z * z)
    j11, j12 = fy / z, -fy * ty / (z * z)
    t = (
        j00 * rot[0, 0] + j02 * rot[2, 0], j00 * rot[0, 1] + j02 * rot[2, 1],
        j00 * rot[0, 2] + j02 * rot[2, 2],
        j11 * rot[1, 0] + j12 * rot[2, 0], j11 * rot[1, 1] + j12 * rot[2, 1],
        j11 * rot[1, 2] + j12 * rot[2, 2],
    )  # fmt: skip
    return t, tx, ty


@njit(cache=True, nogil=True, inline="always")
def _covariance(r: tuple, s0: float, s1: float, s2: float) -> tuple:  # pragma: no cover
    """Σ = M Mᵀ with M = R diag(s), as (M row-major, Σ row-major); tuples, not arrays, so
    that nothing is allocated per Gaussian."""
    m = (r[0] * s0, r[1] * s1, r[2] * s2, r[3] * s0, r[4] * s1, r[5] * s2,
         r[6] * s0, r[7] * s1, r[8] * s2)  # fmt: skip
    s00 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    s01 = m[0] * m[3] + m[1] * m[4] + m[2] * m[5]
    s02 = m[0] * m[6] + m[1] * m[7] + m[2] * m[8]
    s11 = m[3] * m[3] + m[4] * m[4] + m[5] * m[5]
    s12 = m[3] * m[6] + m[4] * m[7] + m[5] * m[8]
    s22 = m[6] * m[6] + m[7] * m[7] + m[8] * m[8]
    return m, (s00, s01, s02, s01, s11, s12, s02, s12, s22)


@njit(cache=True, nogil=True, inline="always")
def _times_sigma(t: tuple, sig: tuple) -> tuple:  # pragma: no cover - compiled
    """T Σ (2×3, row-major)."""
    return (
        t[0] * sig[0] + t[1] * sig[3] + t[2] * sig[6],
        t[0] * sig[1] + t[1] * sig[4] + t[2] * sig[7],
        t[0] * sig[2] + t[1] * sig[5] + t[2] * sig[8],
        t[3] * sig[0] + t[4] * sig[3] + t[5] * sig[6],
        t[3] * sig[1] + t[4] * sig[4] + t[5] * sig[7],
        t[3] * sig[2] + t[4] * sig[5] + t[5] * sig[8],
    )


@njit(cache=True, nogil=True, inline="always")
def _project_2d(t: tuple, sig: tuple) -> tuple[float, float, float]:  # pragma: no cover
    """(a, b, c) of T Σ Tᵀ."""
    u = _times_sigma(t, sig)
    cov_a = u[0] * t[0] + u[1] * t[1] + u[2] * t[2]
    cov_b = u[0] * t[3] + u[1] * t[4] + u[2] * t[5]
    cov_c = u[3] * t[3] + u[4] * t[4] + u[5] * t[5]
    return cov_a, cov_b, cov_c


@njit(cache=True, nogil=True, inline="always")
def pixel_span(m: float, e: float, size: float) -> tuple[int, int]:  # pragma: no cover
    """`stages.pixel_range` along one axis: the first and last pixel of [0, size) whose
    centre (j + 0.5) lies within m ± e, clamped in float first (so that a huge box cannot
    overflow the integer); empty when first > last. Projection (visibility) and binning
    (`tile_kernels.bin_by_depth`) both use it."""
    first = math.ceil(min(max(m - e - 0.5, -1.0), size))
    last = math.floor(min(max(m + e - 0.5, -1.0), size))
    return max(first, 0), min(last, int(size) - 1)


@njit(cache=True, nogil=True, inline="always")
def _span(chunk: int, scene: tuple) -> tuple[int, int]:  # pragma: no cover - compiled
    """The Gaussians [first, end) of a chunk of `CHUNK`."""
    return chunk * CHUNK, min(scene[0].shape[0], (chunk + 1) * CHUNK)


@njit(parallel=True, cache=True, nogil=True)
def project_forward(
    scene: tuple,
    view: tuple,
    antialiased: bool,
    out: np.ndarray,
    valid: np.ndarray,
    visible: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Fill the arrays of `out` (2D means [N, 2], conics [N, 3], opacities [N],
    depths [N], extents [N, 2]), `valid` and `visible` (see the module docstring).
    scene: (means, quaternions, scales, opacities, finite rows); view: (camera rotation,
    translation, intrinsics, limits), with intrinsics fx, fy, cx, cy, the left and top
    off-axis limits, width, height, the right and bottom off-axis limits (`off_axis_limits`),
    and limits near, far, eps2d, alpha_min, the quaternion eps and
    the extent margins (relative, absolute)."""
    for chunk in prange(-(-scene[0].shape[0] // CHUNK)):
        _forward_range(_span(chunk, scene), scene, view, antialiased, (out, valid, visible))


@njit(cache=True, nogil=True)
def _forward_range(
    span: tuple, scene: tuple, view: tuple, antialiased: bool, outputs: tuple
) -> None:  # pragma: no cover - compiled
    """Gaussians [span[0], span[1]) of `project_forward`."""
    for i in range(span[0], span[1]):
        _forward_one(i, scene, view, antialiased, outputs)


@njit(cache=True, nogil=True, inline="always")
def _forward_one(
    i: int, scene: tuple, view: tuple, antialiased: bool, outputs: tuple
) -> None:  # pragma: no cover - compiled
    """Gaussian i of `project_forward`; outputs: (out, valid, visible)."""
    out, valid, visible = outputs
    means, quats, scales, opacities, finite = scene
    rot, trans, intrinsics, limits = view
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    width, height = intrinsics[6], intrinsics[7]
    near, far, eps2d, alpha_min, quat_eps = limits[0], limits[1], limits[2], limits[3], limits[4]
    ok = finite[i]
    px, py, pz = _camera_point(means, i, ok, rot, trans)
    in_depth = pz > near and pz < far
    z = pz if in_depth else 1.0
    u, v = fx * px / z + cx, fy * py / z + cy
    if ok:
        q = (quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3])
        s0, s1, s2, o = scales[i, 0], scales[i, 1], scales[i, 2], opacities[i]
    else:
        q = (0.0, 0.0, 0.0, 0.0)
        s0, s1, s2, o = 0.0, 0.0, 0.0, 0.0
    r = _rotation(q[0], q[1], q[2], q[3], quat_eps)[7]
    sig = _covariance(r, s0, s1, s2)[1]
    t = _jacobian_rows(px, py, z, intrinsics, rot)[0]
    a, b, c = _project_2d(t, sig)
    a_d, c_d = a + eps2d, c + eps2d
    det = a_d * c_d - b * b
    if antialiased:
        o = o * math.sqrt(max(a * c - b * b, 0.0) / max(det, 1e-30))
    good = (
        ok and in_depth and det > 0 and o >= alpha_min
        and math.isfinite(det) and math.isfinite(u) and math.isfinite(v)
    )  # fmt: skip
    d = det if good else 1.0
    means2d, conics, opacity, depth, extent = out
    means2d[i, 0], means2d[i, 1] = u, v
    conics[i, 0], conics[i, 1], conics[i, 2] = c_d / d, -b / d, a_d / d
    opacity[i] = o if good else 0.0
    depth[i] = z
    level = max(2 * math.log(o / alpha_min if good else 1.0), 0.0)
    ex = math.sqrt(level * max(a_d, 0.0)) * (1 + limits[5]) + limits[6]
    ey = math.sqrt(level * max(c_d, 0.0)) * (1 + limits[5]) + limits[6]
    lo_x, hi_x = pixel_span(u, ex, width)
    lo_y, hi_y = pixel_span(v, ey, height)
    shown = good and lo_x <= hi_x and lo_y <= hi_y
    extent[i, 0] = ex if shown else 0.0
    extent[i, 1] = ey if shown else 0.0
    valid[i] = good
    visible[i] = shown


@njit(parallel=True, cache=True, nogil=True)
def project_backward(
    scene: tuple,
    view: tuple,
    valid: np.ndarray,
    antialiased: bool,
    upstream: np.ndarray,
    grads: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """`upstream` [N, 7]: ∂L/∂(2D mean, conic, opacity, depth) → `grads` [N, GRAD_COLUMNS]:
    ∂L/∂(mean, quaternion, scale, opacity). Non-finite rows get zeros, as the zeroed
    parameters of `stages.prepare` give them."""
    for chunk in prange(-(-scene[0].shape[0] // CHUNK)):
        _backward_range(_span(chunk, scene), scene, view, (valid, antialiased, upstream, grads))


@njit(cache=True, nogil=True)
def _backward_range(
    span: tuple, scene: tuple, view: tuple, rest: tuple
) -> None:  # pragma: no cover
    """Gaussians [span[0], span[1]) of `project_backward`; rest: its other arguments."""
    for i in range(span[0], span[1]):
        _backward_one(i, scene, view, rest)


@njit(cache=True, nogil=True, inline="always")
def _backward_one(i: int, scene: tuple, view: tuple, rest: tuple) -> None:  # pragma: no cover
    """Gaussian i of `project_backward` (rest: its valid rows, antialiasing, upstream and
    grads): the forward recomputed, then the chain rule back through the conic and
    opacity, the 2D covariance, the camera point and the rotation."""
    valid, antialiased, upstream, grads = rest
    means, quats, scales, opacities, finite = scene
    rot, trans, intrinsics, limits = view
    near, far, eps2d, quat_eps = limits[0], limits[1], limits[2], limits[4]
    for k in range(GRAD_COLUMNS):
        grads[i, k] = 0.0
    if not finite[i]:
        return
    px, py, pz = _camera_point(means, i, True, rot, trans)
    in_depth = pz > near and pz < far
    z = pz if in_depth else 1.0
    rotation = _rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], quat_eps)
    s = (scales[i, 0], scales[i, 1], scales[i, 2])
    m, sig = _covariance(rotation[7], s[0], s[1], s[2])
    t, tx, ty = _jacobian_rows(px, py, z, intrinsics, rot)
    cov = _project_2d(t, sig)
    g_cov, grads[i, 10] = _conic_backward(cov, eps2d, opacities[i], valid[i], antialiased,
                                          upstream, i)  # fmt: skip
    g_sig, g_j = _covariance_2d_backward(g_cov, t, sig, rot)
    g_p = _point_backward(g_j, px, py, z, tx, ty, intrinsics, upstream, i)
    for k in range(3):
        grads[i, k] = rot[0, k] * g_p[0] + rot[1, k] * g_p[1]
        if in_depth:  # culled for depth: z is the constant 1
            grads[i, k] += rot[2, k] * g_p[2]
    _rotation_backward(g_sig, m, s, rotation, quat_eps, grads, i)


@njit(cache=True, nogil=True, inline="always")
def _conic_backward(
    cov: tuple, eps2d: float, o: float, good: bool, antialiased: bool, upstream: np.ndarray, i: int
) -> tuple:  # pragma: no cover - compiled
    """∂L/∂(a, b, c) of the 2D covariance from the conic (c_d, −b, a_d) / det (det is the
    constant 1 on culled rows) and the antialiasing compensation; and ∂L/∂opacity."""
    a, b, c = cov
    a_d, c_d = a + eps2d, c + eps2d
    det = a_d * c_d - b * b
    g_ca, g_cb, g_cc, g_o = upstream[i, 2], upstream[i, 3], upstream[i, 4], upstream[i, 5]
    if not good:
        return (g_cc, -g_cb, g_ca), 0.0
    d2 = det * det
    g_a = -g_ca * c_d * c_d / d2 + g_cb * b * c_d / d2 + g_cc * (1 / det - a_d * c_d / d2)
    g_c = g_ca * (1 / det - c_d * a_d / d2) + g_cb * b * a_d / d2 - g_cc * a_d * a_d / d2
    g_b = 2 * b * (g_ca * c_d + g_cc * a_d) / d2 - g_cb * (1 / det + 2 * b * b / d2)
    if not antialiased:
        return (g_a, g_b, g_c), g_o
    num, den = a * c - b * b, max(det, 1e-30)
    comp = math.sqrt(max(num, 0.0) / den)
    if comp > 0.0:
        g_r = g_o * o / (2 * comp)
        if num >= 0.0:
            g_a, g_b, g_c = g_a + g_r * c / den, g_b - 2 * b * g_r / den, g_c + g_r * a / den
        if det >= 1e-30:
            g_det = -g_r * max(num, 0.0) / (den * den)
            g_a, g_b, g_c = g_a + g_det * c_d, g_b - 2 * b * g_det, g_c + g_det * a_d
    return (g_a, g_b, g_c), g_o * comp


@njit(cache=True, nogil=True, inline="always")
def _covariance_2d_backward(
    g_cov: tuple, t: tuple, sig: tuple, rot: np.ndarray
) -> tuple:  # pragma: no cover
    """(a, b, c) = T Σ Tᵀ: ∂L/∂Σ = Tᵀ G T and ∂L/∂T = 2 G T Σ with G = [[g_a, g_b/2],
    [g_b/2, g_c]]; then T = J R gives ∂L/∂J = ∂L/∂T Rᵀ for the entries of J that vary
    (J00, J02, J11, J12)."""
    g_a, h, g_c = g_cov[0], 0.5 * g_cov[1], g_cov[2]
    gt = (  # G T
        g_a * t[0] + h * t[3], g_a * t[1] + h * t[4], g_a * t[2] + h * t[5],
        h * t[0] + g_c * t[3], h * t[1] + g_c * t[4], h * t[2] + g_c * t[5],
    )  # fmt: skip
    # Symmetric by construction: its mirrored entries are computed once, so an isotropic
    # Gaussian's rotation gradient cancels exactly, as it does in the reference.
    g00 = t[0] * gt[0] + t[3] * gt[3]
    g01 = t[0] * gt[1] + t[3] * gt[4]
    g02 = t[0] * gt[2] + t[3] * gt[5]
    g11 = t[1] * gt[1] + t[4] * gt[4]
    g12 = t[1] * gt[2] + t[4] * gt[5]
    g22 = t[2] * gt[2] + t[5] * gt[5]
    g_t = _times_sigma(gt, sig)  # (G T) Σ, doubled below
    g_j = (
        2 * (g_t[0] * rot[0, 0] + g_t[1] * rot[0, 1] + g_t[2] * rot[0, 2]),
        2 * (g_t[0] * rot[2, 0] + g_t[1] * rot[2, 1] + g_t[2] * rot[2, 2]),
        2 * (g_t[3] * rot[1, 0] + g_t[4] * rot[1, 1] + g_t[5] * rot[1, 2]),
        2 * (g_t[3] * rot[2, 0] + g_t[4] * rot[2, 1] + g_t[5] * rot[2, 2]),
    )
    return (g00, g01, g02, g01, g11, g12, g02, g12, g22), g_j


@njit(cache=True, nogil=True, inline="always")
def _point_backward(
    g_j: tuple,
    px: float,
    py: float,
    z: float,
    tx: float,
    ty: float,
    intrinsics: np.ndarray,
    upstream: np.ndarray,
    i: int,
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """∂L/∂(camera-space point) from J (with its off-axis clamp: t = clamp(x/z)·z), the
    2D mean (fx x/z + cx, fy y/z + cy) and the depth; z as drawn (the caller drops its
    gradient where it was replaced)."""
    fx, fy = intrinsics[0], intrinsics[1]
    left, top, right, bottom = intrinsics[4], intrinsics[5], intrinsics[8], intrinsics[9]
    g_j00, g_j02, g_j11, g_j12 = g_j
    z2, z3 = z * z, z * z * z
    g_z = -g_j00 * fx / z2 - g_j11 * fy / z2 + g_j02 * 2 * fx * tx / z3 + g_j12 * 2 * fy * ty / z3
    g_tx, g_ty = -g_j02 * fx / z2, -g_j12 * fy / z2
    g_px, g_py = 0.0, 0.0
    rx, ry = px / z, py / z
    if -left <= rx <= right:
        g_px += g_tx
    else:
        g_z += g_tx * min(max(rx, -left), right)
    if -top <= ry <= bottom:
        g_py += g_ty
    else:
        g_z += g_ty * min(max(ry, -top), bottom)
    g_u, g_v = upstream[i, 0], upstream[i, 1]
    g_px += g_u * fx / z
    g_py += g_v * fy / z
    g_z += -g_u * fx * px / z2 - g_v * fy * py / z2 + upstream[i, 6]
    return g_px, g_py, g_z


@njit(cache=True, nogil=True, inline="always")
def _rotation_backward(
    g_sig: tuple, m: tuple, s: tuple, rotation: tuple, quat_eps: float, grads: np.ndarray, i: int
) -> None:  # pragma: no cover - compiled
    """Σ = M Mᵀ with M = R diag(s): ∂L/∂M = 2 ∂L/∂Σ M (∂L/∂Σ symmetric), ∂L/∂s_q =
    Σ_p ∂L/∂M_pq R_pq and ∂L/∂R = ∂L/∂M diag(s); then back through the rotation of a unit
    quaternion (`geometry.quaternion_to_rotation`) and its normalisation."""
    qw, qx, qy, qz, norm, n, big, r = rotation
    gm = (
        2 * (g_sig[0] * m[0] + g_sig[1] * m[3] + g_sig[2] * m[6]),
        2 * (g_sig[0] * m[1] + g_sig[1] * m[4] + g_sig[2] * m[7]),
        2 * (g_sig[0] * m[2] + g_sig[1] * m[5] + g_sig[2] * m[8]),
        2 * (g_sig[3] * m[0] + g_sig[4] * m[3] + g_sig[5] * m[6]),
        2 * (g_sig[3] * m[1] + g_sig[4] * m[4] + g_sig[5] * m[7]),
        2 * (g_sig[3] * m[2] + g_sig[4] * m[5] + g_sig[5] * m[8]),
        2 * (g_sig[6] * m[0] + g_sig[7] * m[3] + g_sig[8] * m[6]),
        2 * (g_sig[6] * m[1] + g_sig[7] * m[4] + g_sig[8] * m[7]),
        2 * (g_sig[6] * m[2] + g_sig[7] * m[5] + g_sig[8] * m[8]),
    )
    grads[i, 7] = gm[0] * r[0] + gm[3] * r[3] + gm[6] * r[6]
    grads[i, 8] = gm[1] * r[1] + gm[4] * r[4] + gm[7] * r[7]
    grads[i, 9] = gm[2] * r[2] + gm[5] * r[5] + gm[8] * r[8]
    g_r = (gm[0] * s[0], gm[1] * s[1], gm[2] * s[2], gm[3] * s[0], gm[4] * s[1], gm[5] * s[2],
           gm[6] * s[0], gm[7] * s[1], gm[8] * s[2])  # fmt: skip
    gw = 2 * (-qz * g_r[1] + qy * g_r[2] + qz * g_r[3] - qx * g_r[5] - qy * g_r[6] + qx * g_r[7])
    gx = 2 * (qy * g_r[1] + qz * g_r[2] + qy * g_r[3] - 2 * qx * g_r[4] - qw * g_r[5]
              + qz * g_r[6] + qw * g_r[7] - 2 * qx * g_r[8])  # fmt: skip
    gy = 2 * (-2 * qy * g_r[0] + qx * g_r[1] + qw * g_r[2] + qx * g_r[3] + qz * g_r[5]
              - qw * g_r[6] + qz * g_r[7] - 2 * qy * g_r[8])  # fmt: skip
    gz = 2 * (-2 * qz * g_r[0] - qw * g_r[1] + qx * g_r[2] + qw * g_r[3] - 2 * qz * g_r[4]
              + qy * g_r[5] + qx * g_r[6] + qy * g_r[7])  # fmt: skip
    # q / max(|q|, eps) after dividing by the (constant) largest component.
    if norm >= quat_eps:
        dot = qw * gw + qx * gx + qy * gy + qz * gz
        gw, gx, gy, gz = gw - qw * dot, gx - qx * dot, gy - qy * dot, gz - qz * dot
    scale = 1.0 / (n * big)
    grads[i, 3], grads[i, 4] = gw * scale, gx * scale
    grads[i, 5], grads[i, 6] = gy * scale, gz * scale


@njit(cache=True, nogil=True)
def finite_rows(arrays: tuple, finite: np.ndarray) -> None:  # pragma: no cover - compiled
    """finite[i] = whether every entry of row i of every [N, k] array in `arrays` is
    finite (`dyngs.ops.finite_rows`, in one pass over the rows and no temporaries)."""
    finite[:] = True
    for values in literal_unroll(arrays):
        for i in range(values.shape[0]):
            for j in range(values.shape[1]):
                if not np.isfinite(values[i, j]):
                    finite[i] = False
