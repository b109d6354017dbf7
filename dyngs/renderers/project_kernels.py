"""The compiled projection of `cpu-tile` (numba): `stages.project`'s geometry, forward and
backward, in one pass over the Gaussians each.

`stages.project` is the specification: EWA splatting (Zwicker et al. 2001) as 3DGS uses
it (Kerbl et al. 2023), in float64, with its guards (docs/RENDERER.md): non-finite rows
drawn as zeros and culled, depth outside (near, far) culled and its depth replaced by 1,
the off-axis clamp in the Jacobian, the dilation (`Guards.dilation`), culling on det ≤ 0,
opacity below `alpha_min` or a non-finite det or 2D mean, and the α ≥ `alpha_min` box. In
PyTorch those are some sixty whole-array operations forward and as many backward, each a
pass over memory and a dispatch; here they are one pass, and backward is the chain rule
written out (the 3DGS backward kernels' order: conic, then 2D covariance, then 3D
covariance and quaternion, then the mean). The parameters are first laid out by column
(`gather_scene`), each Gaussian's code is straight-line, every guard a select, and a
division is IEEE's (numba's `error_model="numpy"`; its default tests every divisor for
zero and branches to raise, which alone made these loops ~2.5× slower); each result is
the one the branching code gave, operation for operation.
tests/renderers/test_cpu_tile.py holds both directions to the PyTorch stage on random
scenes and every hard case, and gradcheck in float64.

Letters: N Gaussians.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from dyngs.compiled import noalias_option

_NOALIAS = noalias_option()

SCENE_ROWS = 11
"""Rows of the scene as the kernels read it (`gather_scene`): mean x, y, z, quaternion w,
x, y, z, scale x, y, z, opacity. One row per column, Gaussians along each: read in
sequence, where the tensors' [N, k] rows have strides numba learns only at run time."""

OUT_COLUMNS = (2, 3, 1, 1, 2)
"""Columns of the forward's float64 outputs, one array each (so that each can be handed
to PyTorch as it is): 2D mean, conic, opacity, depth, extent."""

CHUNK = 256
"""Gaussians per call of the per-range functions the parallel loops run: a call passes the
scene's arrays, and numba counts references on each of them, which cost about as much as
projecting a Gaussian when the calls were one a Gaussian. Within a range the per-Gaussian
code is inlined. (The ranges are independent, so any split gives the same results.)"""


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
    scene: np.ndarray, i: int, rot: np.ndarray, trans: np.ndarray
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """R μ + t for Gaussian i (a non-finite row, zeros in the scene, is the origin)."""
    mx, my, mz = scene[0, i], scene[1, i], scene[2, i]
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
def _span(chunk: int, n: int) -> tuple[int, int]:  # pragma: no cover - compiled
    """The Gaussians [first, end) of chunk `chunk` of `CHUNK`, of n."""
    return chunk * CHUNK, min(n, (chunk + 1) * CHUNK)


@njit(parallel=True, cache=True, nogil=True)
def gather_scene(arrays: tuple, scene: np.ndarray, finite: np.ndarray) -> None:  # pragma: no cover
    """Lay the parameters out as the projection kernels read them, and check them.

    arrays: (means [N, 3], quaternions [N, 4], scales [N, 3], opacities [N, 1], colours
    [N, k]), each in any float dtype. finite[i] = whether every entry of row i of every
    array is finite (`dyngs.ops.finite_rows`); scene [`SCENE_ROWS`, N] (float64) gets the
    first four arrays' columns as rows (mean x, y, z, quaternion w, x, y, z, scale x, y, z,
    opacity), zeros in the columns of rows that are not finite, which the reference draws
    as zeros."""
    n = finite.shape[0]
    for chunk in prange(-(-n // CHUNK)):
        _gather_range(_span(chunk, n), arrays, scene, finite)


@njit(cache=True, nogil=True)
def _gather_range(
    span: tuple, arrays: tuple, scene: np.ndarray, finite: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Rows [span[0], span[1]) of `gather_scene`: the check row by row, then the copy
    column by column (each a sequential write; row by row, eleven streams at once, it was
    four times slower)."""
    means, quats, scales, opacities, colors = arrays
    first, end = span
    bad = 0
    for i in range(first, end):
        ok = (_row_finite(means, i) & _row_finite(quats, i) & _row_finite(scales, i)
              & _row_finite(opacities, i) & _row_finite(colors, i))  # fmt: skip
        finite[i] = ok
        bad += not ok
    _put_columns(means, scene, 0, span)
    _put_columns(quats, scene, 3, span)
    _put_columns(scales, scene, 7, span)
    _put_columns(opacities, scene, 10, span)
    if bad:
        for i in range(first, end):
            if not finite[i]:
                scene[:, i] = 0.0


@njit(cache=True, nogil=True, inline="always")
def _row_finite(values: np.ndarray, i: int) -> bool:  # pragma: no cover - compiled
    ok = True
    for j in range(values.shape[1]):
        ok &= np.isfinite(values[i, j])
    return ok


@njit(cache=True, nogil=True, inline="always")
def _put_columns(
    values: np.ndarray, scene: np.ndarray, row: int, span: tuple
) -> None:  # pragma: no cover - compiled
    for j in range(values.shape[1]):
        lane = scene[row + j]
        for i in range(span[0], span[1]):
            lane[i] = values[i, j]


@njit(parallel=True, cache=True, nogil=True)
def project_forward(
    scene: np.ndarray,
    finite: np.ndarray,
    view: tuple,
    antialiased: bool,
    out: tuple,
    valid: np.ndarray,
    visible: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Fill the arrays of `out` (2D means [N, 2], conics [N, 3], opacities [N],
    depths [N], extents [N, 2]), `valid` and `visible` (see the module docstring).
    scene and finite: as `gather_scene` left them; view: (camera rotation, translation,
    intrinsics, limits), with intrinsics fx, fy, cx, cy, the left and top off-axis limits,
    width, height, the right and bottom off-axis limits (`off_axis_limits`), and limits
    near, far, the dilation, alpha_min, the quaternion eps and the extent margins (relative,
    absolute)."""
    n = finite.shape[0]
    for chunk in prange(-(-n // CHUNK)):
        _forward_range(_span(chunk, n), scene, finite, view, antialiased, (out, valid, visible))


@njit(cache=True, nogil=True)
def _forward_range(
    span: tuple,
    scene: np.ndarray,
    finite: np.ndarray,
    view: tuple,
    antialiased: bool,
    outputs: tuple,
) -> None:  # pragma: no cover - compiled
    """Gaussians [span[0], span[1]) of `project_forward` (outputs: out, valid, visible):
    their arithmetic in `_forward_lanes`, into one array per quantity, then written out
    row by row. Written straight into the [N, k] outputs, the same arithmetic took 2.4×
    as long (a demo frame; 1.7× at 200 000 Gaussians), and so did the backward's."""
    out, valid, visible = outputs
    first, end = span
    k = end - first
    lanes = (np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k),
             np.empty(k), np.empty(k), np.empty(k))  # fmt: skip
    good, shown = np.empty(k, dtype=np.bool_), np.empty(k, dtype=np.bool_)
    _forward_lanes(first, end, scene, finite, view, antialiased, lanes, good, shown)
    means2d, conics, opacity, depth, extent = out
    for j in range(k):
        i = first + j
        means2d[i, 0], means2d[i, 1] = lanes[0][j], lanes[1][j]
        conics[i, 0], conics[i, 1], conics[i, 2] = lanes[2][j], lanes[3][j], lanes[4][j]
        opacity[i], depth[i] = lanes[5][j], lanes[6][j]
        extent[i, 0], extent[i, 1] = lanes[7][j], lanes[8][j]
        valid[i], visible[i] = good[j], shown[j]


# Straight-line code per Gaussian (every guard a select), IEEE division and `noalias`
# output lanes (no overlap checks between a dozen arrays). LLVM still runs it one Gaussian
# at a time, because the loop reads the camera from its arrays in every iteration; with
# the camera hoisted into tuples of floats it vectorises (eight lanes of AVX-512), but that
# measured no faster on a demo frame or at 200 000 Gaussians, so it stays the simpler way.
@njit(cache=True, nogil=True, error_model="numpy", **_NOALIAS)
def _forward_lanes(
    first: int,
    end: int,
    scene: np.ndarray,
    finite: np.ndarray,
    view: tuple,
    antialiased: bool,
    lanes: tuple,
    good: np.ndarray,
    shown: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Gaussians [first, end): lanes (2D mean x, y, conic a, b, c, opacity, depth,
    extent x, y), whether each is valid (`good`) and visible (`shown`), indexed from
    `first`."""
    rot, trans, intrinsics, limits = view
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    width, height = intrinsics[6], intrinsics[7]
    near, far, dilation, alpha_min, quat_eps = limits[0], limits[1], limits[2], limits[3], limits[4]
    grow, margin = 1 + limits[5], limits[6]
    u_, v_, ca_, cb_, cc_, o_, z_, ex_, ey_ = lanes
    for i in range(first, end):
        j = i - first
        px, py, pz = _camera_point(scene, i, rot, trans)
        in_depth = (pz > near) & (pz < far)
        z = pz if in_depth else 1.0
        u, v = fx * px / z + cx, fy * py / z + cy
        q0, q1, q2, q3 = scene[3, i], scene[4, i], scene[5, i], scene[6, i]
        r = _rotation(q0, q1, q2, q3, quat_eps)[7]
        sig = _covariance(r, scene[7, i], scene[8, i], scene[9, i])[1]
        t = _jacobian_rows(px, py, z, intrinsics, rot)[0]
        a, b, c = _project_2d(t, sig)
        a_d, c_d = a + dilation, c + dilation
        det = a_d * c_d - b * b
        o = scene[10, i]
        if antialiased:
            o = o * math.sqrt(max(a * c - b * b, 0.0) / max(det, 1e-30))
        ok = (
            finite[i] & in_depth & (det > 0) & (o >= alpha_min)
            & np.isfinite(det) & np.isfinite(u) & np.isfinite(v)
        )  # fmt: skip
        d = det if ok else 1.0
        level = max(2 * math.log(o / alpha_min if ok else 1.0), 0.0)
        ex = math.sqrt(level * max(a_d, 0.0)) * grow + margin
        ey = math.sqrt(level * max(c_d, 0.0)) * grow + margin
        lo_x, hi_x = pixel_span(u, ex, width)
        lo_y, hi_y = pixel_span(v, ey, height)
        seen = ok & (lo_x <= hi_x) & (lo_y <= hi_y)
        u_[j], v_[j] = u, v
        ca_[j], cb_[j], cc_[j] = c_d / d, -b / d, a_d / d
        o_[j] = o if ok else 0.0
        z_[j] = z
        ex_[j] = ex if seen else 0.0
        ey_[j] = ey if seen else 0.0
        good[j] = ok
        shown[j] = seen


@njit(parallel=True, cache=True, nogil=True)
def project_backward(
    scene: np.ndarray,
    finite: np.ndarray,
    view: tuple,
    valid: np.ndarray,
    antialiased: bool,
    upstream: tuple,
    grads: tuple,
) -> None:  # pragma: no cover - compiled
    """`upstream` (∂L/∂ 2D means [N, 2], conics [N, 3], opacities [N], depths [N], in
    float64) → `grads` (∂L/∂ means [N, 3], quaternions [N, 4], scales [N, 3], opacities
    [N], each in its parameter's dtype, rounded once). Rows that are not finite get
    zeros, as the zeroed parameters of `stages.prepare` give them."""
    n = finite.shape[0]
    for chunk in prange(-(-n // CHUNK)):
        _backward_range(_span(chunk, n), scene, finite, view,
                        (valid, antialiased, upstream, grads))  # fmt: skip


@njit(cache=True, nogil=True)
def _backward_range(
    span: tuple, scene: np.ndarray, finite: np.ndarray, view: tuple, rest: tuple
) -> None:  # pragma: no cover - compiled
    """Gaussians [span[0], span[1]) of `project_backward` (rest: its valid rows,
    antialiasing, upstream and grads): the upstream gradients laid out as lanes, the
    Gaussians' arithmetic in `_backward_lanes`, the results written out."""
    valid, antialiased, upstream, grads = rest
    first, end = span
    k = end - first
    g_means2d, g_conics, g_opacity, g_depth = upstream
    up = (np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k),
          np.empty(k))  # fmt: skip
    for j in range(k):
        i = first + j
        up[0][j], up[1][j] = g_means2d[i, 0], g_means2d[i, 1]
        up[2][j], up[3][j], up[4][j] = g_conics[i, 0], g_conics[i, 1], g_conics[i, 2]
        up[5][j], up[6][j] = g_opacity[i], g_depth[i]
    out = (np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k),
           np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k))  # fmt: skip
    _backward_lanes(first, end, scene, finite, view, valid, antialiased, up, out)
    means, quats, scales, opacities = grads
    for j in range(k):
        i = first + j
        for c in range(3):
            means[i, c] = out[c][j]
            scales[i, c] = out[7 + c][j]
        for c in range(4):
            quats[i, c] = out[3 + c][j]
        opacities[i] = out[10][j]


@njit(cache=True, nogil=True, error_model="numpy", **_NOALIAS)
def _backward_lanes(
    first: int,
    end: int,
    scene: np.ndarray,
    finite: np.ndarray,
    view: tuple,
    valid: np.ndarray,
    antialiased: bool,
    up: tuple,
    out: tuple,
) -> None:  # pragma: no cover - compiled
    """Gaussians [first, end) of `project_backward`, straight-line as `_forward_lanes`:
    the forward recomputed, then the chain rule back through the conic and opacity, the
    2D covariance, the camera point and the rotation. up: the seven upstream lanes; out:
    the eleven gradient lanes (mean, quaternion, scale, opacity), indexed from `first`."""
    rot, trans, intrinsics, limits = view
    near, far, dilation, quat_eps = limits[0], limits[1], limits[2], limits[4]
    for i in range(first, end):
        j = i - first
        px, py, pz = _camera_point(scene, i, rot, trans)
        in_depth = (pz > near) & (pz < far)
        z = pz if in_depth else 1.0
        rotation = _rotation(scene[3, i], scene[4, i], scene[5, i], scene[6, i], quat_eps)
        s = (scene[7, i], scene[8, i], scene[9, i])
        m, sig = _covariance(rotation[7], s[0], s[1], s[2])
        t, tx, ty = _jacobian_rows(px, py, z, intrinsics, rot)
        cov = _project_2d(t, sig)
        upstream = (up[0][j], up[1][j], up[2][j], up[3][j], up[4][j], up[5][j], up[6][j])
        g_cov, g_o = _conic_backward(cov, dilation, scene[10, i], valid[i], antialiased,
                                     upstream)  # fmt: skip
        g_sig, g_j = _covariance_2d_backward(g_cov, t, sig, rot)
        g_p = _point_backward(g_j, px, py, z, tx, ty, intrinsics, upstream)
        g_s, g_q = _rotation_backward(g_sig, m, s, rotation, quat_eps)
        ok = finite[i]
        for c in range(3):
            g_mean = rot[0, c] * g_p[0] + rot[1, c] * g_p[1]
            g_mean = g_mean + rot[2, c] * g_p[2] if in_depth else g_mean  # else z is 1
            out[c][j] = g_mean if ok else 0.0
            out[7 + c][j] = g_s[c] if ok else 0.0
        for c in range(4):
            out[3 + c][j] = g_q[c] if ok else 0.0
        out[10][j] = g_o if ok else 0.0


@njit(cache=True, nogil=True, inline="always")
def _conic_backward(
    cov: tuple, dilation: float, o: float, good: bool, antialiased: bool, upstream: tuple
) -> tuple:  # pragma: no cover - compiled
    """∂L/∂(a, b, c) of the 2D covariance from the conic (c_d, −b, a_d) / det (det is the
    constant 1 on culled rows) and the antialiasing compensation; and ∂L/∂opacity. Every
    branch a select (`_backward_lanes`)."""
    a, b, c = cov
    a_d, c_d = a + dilation, c + dilation
    det = a_d * c_d - b * b
    g_ca, g_cb, g_cc, g_o = upstream[2], upstream[3], upstream[4], upstream[5]
    d2 = det * det
    g_a = -g_ca * c_d * c_d / d2 + g_cb * b * c_d / d2 + g_cc * (1 / det - a_d * c_d / d2)
    g_c = g_ca * (1 / det - c_d * a_d / d2) + g_cb * b * a_d / d2 - g_cc * a_d * a_d / d2
    g_b = 2 * b * (g_ca * c_d + g_cc * a_d) / d2 - g_cb * (1 / det + 2 * b * b / d2)
    g_opacity = g_o
    if antialiased:
        num, den = a * c - b * b, max(det, 1e-30)
        comp = math.sqrt(max(num, 0.0) / den)
        g_r = g_o * o / (2 * comp)  # used only where comp > 0
        with_num = (comp > 0.0) & (num >= 0.0)
        g_a = g_a + g_r * c / den if with_num else g_a
        g_b = g_b - 2 * b * g_r / den if with_num else g_b
        g_c = g_c + g_r * a / den if with_num else g_c
        g_det = -g_r * max(num, 0.0) / (den * den)
        with_det = (comp > 0.0) & (det >= 1e-30)
        g_a = g_a + g_det * c_d if with_det else g_a
        g_b = g_b - 2 * b * g_det if with_det else g_b
        g_c = g_c + g_det * a_d if with_det else g_c
        g_opacity = g_o * comp
    g_a = g_a if good else g_cc
    g_b = g_b if good else -g_cb
    g_c = g_c if good else g_ca
    return (g_a, g_b, g_c), g_opacity if good else 0.0


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
    upstream: tuple,
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
    rx, ry = px / z, py / z
    inside_x = (-left <= rx) & (rx <= right)
    inside_y = (-top <= ry) & (ry <= bottom)
    g_px = 0.0 + g_tx if inside_x else 0.0
    g_z = g_z if inside_x else g_z + g_tx * min(max(rx, -left), right)
    g_py = 0.0 + g_ty if inside_y else 0.0
    g_z = g_z if inside_y else g_z + g_ty * min(max(ry, -top), bottom)
    g_u, g_v = upstream[0], upstream[1]
    g_px += g_u * fx / z
    g_py += g_v * fy / z
    g_z += -g_u * fx * px / z2 - g_v * fy * py / z2 + upstream[6]
    return g_px, g_py, g_z


@njit(cache=True, nogil=True, inline="always")
def _rotation_backward(
    g_sig: tuple, m: tuple, s: tuple, rotation: tuple, quat_eps: float
) -> tuple:  # pragma: no cover - compiled
    """Σ = M Mᵀ with M = R diag(s): ∂L/∂M = 2 ∂L/∂Σ M (∂L/∂Σ symmetric), ∂L/∂s_q =
    Σ_p ∂L/∂M_pq R_pq and ∂L/∂R = ∂L/∂M diag(s); then back through the rotation of a unit
    quaternion (`geometry.quaternion_to_rotation`) and its normalisation. Returns
    (∂L/∂s, ∂L/∂q)."""
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
    g_s = (
        gm[0] * r[0] + gm[3] * r[3] + gm[6] * r[6],
        gm[1] * r[1] + gm[4] * r[4] + gm[7] * r[7],
        gm[2] * r[2] + gm[5] * r[5] + gm[8] * r[8],
    )
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
    dot = qw * gw + qx * gx + qy * gy + qz * gz
    if norm >= quat_eps:
        gw, gx, gy, gz = gw - qw * dot, gx - qx * dot, gy - qy * dot, gz - qz * dot
    scale = 1.0 / (n * big)
    return g_s, (gw * scale, gx * scale, gy * scale, gz * scale)
