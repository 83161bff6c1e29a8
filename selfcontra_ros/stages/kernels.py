"""Compiled per-pixel kernels (numba) behind the labeler's hot paths.

Each per-point computation of the stages exists once, here, as a scalar
``@njit`` function: the stereo Fisher information and covariance of a point,
the largest covariance eigenvalue ``u``, the Mahalanobis tests of
"within ``sigma_max``", the projection to the nearest pixel, the observation
angle and the Stage-3 tolerances. The numpy-facing functions of
:mod:`selfcontra_ros.uncertainty`, :mod:`selfcontra_ros.projection`,
:mod:`selfcontra_ros.stages._common` and the stage modules are thin wrappers
over the array kernels below, so the vectorised API and the fused stage
kernels cannot drift apart.

Conventions: points are metres in a view's left frame, pixels are flat
indices ``v * width + u``, rigid transforms are 4x4 float64 matrices, packed
symmetric matrices are ``xx, xy, xz, yy, yz, zz``. The scalar arithmetic
follows the operation order of the numpy formulas it replaced, so results
match them to the last bit or within a few ulps (BLAS may fuse operations).
Float32 inputs are widened with ``np.float64`` (numba's ``float()`` keeps float32).
Kernels use ``error_model="numpy"``: a division by zero gives inf/NaN as in
numpy instead of raising, which the validity tests then reject.
"""

from __future__ import annotations

import math
import os

# OpenMP threads that wait for work spin by default; numba's OpenMP layer then burns the cores its threads wait
# on whenever other processes share them. Measured on 2 busy cores (load ~11): Stage 1 of one view took 500-970 ms
# with 2 spinning threads, 170 ms with 1 thread and 185-230 ms with 2 passive ones. The variable is read when the
# OpenMP runtime loads (numba's at its first parallel launch); a value set by the user is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
from numba import njit, prange

__all__ = [
    "MODE_QUERY",
    "MODE_SMALLER",
    "MODE_SUM",
    "READING_PAPER",
    "READING_STD",
]

#: Codes of the tolerance readings of :data:`selfcontra_ros.stages._common.TOLERANCES`, for the kernels.
MODE_QUERY, MODE_SMALLER, MODE_SUM = 0, 1, 2
#: Codes of the Stage-3 readings of :data:`selfcontra_ros.stages.outliers.READINGS`.
READING_STD, READING_PAPER = 0, 1


# ---------------------------------------------------------------------------------------------------------------------
# Scalar device functions: one per computation.


@njit(cache=True, error_model="numpy")
def sym_inverse_scalar(
    xx: float, xy: float, xz: float, yy: float, yz: float, zz: float
) -> tuple[float, float, float, float, float, float]:
    """Inverse of one packed symmetric 3x3 matrix by the adjugate."""
    c_xx = yy * zz - yz * yz
    c_xy = xz * yz - xy * zz
    c_xz = xy * yz - xz * yy
    c_yy = xx * zz - xz * xz
    c_yz = xy * xz - xx * yz
    c_zz = xx * yy - xy * xy
    det = xx * c_xx + xy * c_xy + xz * c_xz
    inv_det = 1.0 / det
    return c_xx * inv_det, c_xy * inv_det, c_xz * inv_det, c_yy * inv_det, c_yz * inv_det, c_zz * inv_det


@njit(cache=True, error_model="numpy")
def sym_eigvalsh_scalar(xx: float, xy: float, xz: float, yy: float, yz: float, zz: float) -> tuple[float, float, float]:
    """Eigenvalues (ascending) of one packed symmetric 3x3 matrix, trigonometric closed form."""
    q = (xx + yy + zz) / 3.0
    p1 = xy * xy + xz * xz + yz * yz
    dxx, dyy, dzz = xx - q, yy - q, zz - q
    p2 = dxx * dxx + dyy * dyy + dzz * dzz + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    inv_p = 1.0 / p if p > 0 else 0.0
    bxx, byy, bzz, bxy, bxz, byz = dxx * inv_p, dyy * inv_p, dzz * inv_p, xy * inv_p, xz * inv_p, yz * inv_p
    det_b = bxx * (byy * bzz - byz * byz) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz)
    half = det_b / 2.0
    # Rounding can push |det_b / 2| a hair past 1 for (nearly) repeated eigenvalues.
    half = min(max(half, -1.0), 1.0)
    phi = math.acos(half) / 3.0
    largest = q + 2.0 * p * math.cos(phi)
    smallest = q + 2.0 * p * math.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    return smallest, middle, largest


@njit(cache=True, error_model="numpy")
def information_scalar(
    x: float, y: float, z: float, fx: float, fy: float, baseline: float, sigma_px: float
) -> tuple[float, float, float, float, float, float]:
    """Packed Fisher information ``J^T J / sigma_px^2`` (1/m^2) of one left-frame point (metres).

    Closed form for the rows ``a(1, 0, -p)``, ``c(0, 1, -q)``, ``a(1, 0, -p')``,
    ``c(0, 1, -q)`` of ``J`` with ``a = fx/z``, ``c = fy/z``, ``p = x/z``,
    ``p' = (x - b)/z``, ``q = y/z``.
    """
    a = fx / z
    c = fy / z
    a2 = a * a
    c2 = c * c
    p = x / z
    p_r = (x - baseline) / z
    q = y / z
    s = 1.0 / (sigma_px * sigma_px)
    return (
        2.0 * a2 * s,
        0.0,
        -a2 * (p + p_r) * s,
        2.0 * c2 * s,
        -2.0 * c2 * q * s,
        (a2 * (p * p + p_r * p_r) + 2.0 * c2 * q * q) * s,
    )


@njit(cache=True, error_model="numpy")
def covariance_scalar(
    x: float, y: float, z: float, fx: float, fy: float, baseline: float, sigma_px: float
) -> tuple[float, float, float, float, float, float]:
    """Packed covariance ``F^-1`` (m^2) of one left-frame point (metres)."""
    f = information_scalar(x, y, z, fx, fy, baseline, sigma_px)
    return sym_inverse_scalar(f[0], f[1], f[2], f[3], f[4], f[5])


@njit(cache=True, error_model="numpy")
def largest_eigenvalue_scalar(
    x: float, y: float, z: float, fx: float, fy: float, baseline: float, sigma_px: float
) -> float:
    """``u``: largest covariance eigenvalue (m^2) of one left-frame point; NaN if not finite or ``z <= 0``."""
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z) and z > 0):
        return np.nan
    c = covariance_scalar(x, y, z, fx, fy, baseline, sigma_px)
    return sym_eigvalsh_scalar(c[0], c[1], c[2], c[3], c[4], c[5])[2]


@njit(cache=True, error_model="numpy")
def mahalanobis_sq_scalar(
    x: float,
    y: float,
    z: float,
    dx: float,
    dy: float,
    dz: float,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
) -> float:
    """``dX^T F dX`` of offset ``d`` w.r.t. the covariance of point ``X`` (both the point's left frame, metres).

    Equals ``|J dX|^2 / sigma_px^2``, the first-order reprojection change in pixels squared.
    """
    inv_z = 1.0 / z
    e_ul = fx * inv_z * (dx - x * inv_z * dz)
    e_ur = fx * inv_z * (dx - (x - baseline) * inv_z * dz)
    e_v = fy * inv_z * (dy - y * inv_z * dz)
    return (e_ul * e_ul + e_ur * e_ur + 2.0 * e_v * e_v) / (sigma_px * sigma_px)


@njit(cache=True, error_model="numpy")
def rotate_sym_scalar(
    s0: float, s1: float, s2: float, s3: float, s4: float, s5: float, r: np.ndarray
) -> tuple[float, float, float, float, float, float]:
    """``R S R^T`` of one packed symmetric matrix (``r``: 3x3 rotation into the new frame)."""
    m = ((s0, s1, s2), (s1, s3, s4), (s2, s4, s5))
    # t = R S, then out = t R^T, each entry summed over k = 0, 1, 2 in order.
    t00 = r[0, 0] * m[0][0] + r[0, 1] * m[1][0] + r[0, 2] * m[2][0]
    t01 = r[0, 0] * m[0][1] + r[0, 1] * m[1][1] + r[0, 2] * m[2][1]
    t02 = r[0, 0] * m[0][2] + r[0, 1] * m[1][2] + r[0, 2] * m[2][2]
    t10 = r[1, 0] * m[0][0] + r[1, 1] * m[1][0] + r[1, 2] * m[2][0]
    t11 = r[1, 0] * m[0][1] + r[1, 1] * m[1][1] + r[1, 2] * m[2][1]
    t12 = r[1, 0] * m[0][2] + r[1, 1] * m[1][2] + r[1, 2] * m[2][2]
    t20 = r[2, 0] * m[0][0] + r[2, 1] * m[1][0] + r[2, 2] * m[2][0]
    t21 = r[2, 0] * m[0][1] + r[2, 1] * m[1][1] + r[2, 2] * m[2][1]
    t22 = r[2, 0] * m[0][2] + r[2, 1] * m[1][2] + r[2, 2] * m[2][2]
    return (
        t00 * r[0, 0] + t01 * r[0, 1] + t02 * r[0, 2],
        t00 * r[1, 0] + t01 * r[1, 1] + t02 * r[1, 2],
        t00 * r[2, 0] + t01 * r[2, 1] + t02 * r[2, 2],
        t10 * r[1, 0] + t11 * r[1, 1] + t12 * r[1, 2],
        t10 * r[2, 0] + t11 * r[2, 1] + t12 * r[2, 2],
        t20 * r[2, 0] + t21 * r[2, 1] + t22 * r[2, 2],
    )


@njit(cache=True, error_model="numpy")
def quadratic_form_scalar(
    s0: float, s1: float, s2: float, s3: float, s4: float, s5: float, dx: float, dy: float, dz: float
) -> float:
    """``d^T S d`` for one packed symmetric ``S``."""
    return s0 * dx * dx + s3 * dy * dy + s5 * dz * dz + 2.0 * (s1 * dx * dy + s2 * dx * dz + s4 * dy * dz)


@njit(cache=True, error_model="numpy")
def mahalanobis_sq_sum_scalar(
    xa: float,
    ya: float,
    za: float,
    xb: float,
    yb: float,
    zb: float,
    r_ab: np.ndarray,
    dx: float,
    dy: float,
    dz: float,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
) -> float:
    """``dX^T (C_a + C_b)^-1 dX`` (dimensionless) of two measurements of one point.

    ``a`` is in A's left frame, ``b`` in B's, the offset ``d`` in A's;
    ``r_ab`` rotates B-frame vectors into A's frame.
    """
    ca = covariance_scalar(xa, ya, za, fx, fy, baseline, sigma_px)
    cb0 = covariance_scalar(xb, yb, zb, fx, fy, baseline, sigma_px)
    cb = rotate_sym_scalar(cb0[0], cb0[1], cb0[2], cb0[3], cb0[4], cb0[5], r_ab)
    inv = sym_inverse_scalar(ca[0] + cb[0], ca[1] + cb[1], ca[2] + cb[2], ca[3] + cb[3], ca[4] + cb[4], ca[5] + cb[5])
    return quadratic_form_scalar(inv[0], inv[1], inv[2], inv[3], inv[4], inv[5], dx, dy, dz)


@njit(cache=True, error_model="numpy")
def tolerance_sq_scalar(
    mode: int,
    xq: float,
    yq: float,
    zq: float,
    xr: float,
    yr: float,
    zr: float,
    xrq: float,
    yrq: float,
    zrq: float,
    ref_from_query: np.ndarray,
    u_q: float,
    u_r: float,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
) -> float:
    """Squared distance compared against ``sigma_max^2`` by the tolerance reading ``mode`` (``MODE_*``).

    ``q`` is ``X_q`` (query frame), ``r`` is ``X_r`` (reference frame), ``rq``
    is ``X_r`` in the query frame; ``u_q``, ``u_r`` their ``u`` (m^2).
    """
    dx, dy, dz = xrq - xq, yrq - yq, zrq - zq
    if mode == MODE_QUERY:
        return mahalanobis_sq_scalar(xq, yq, zq, dx, dy, dz, fx, fy, baseline, sigma_px)
    if mode == MODE_SMALLER:
        if u_q <= u_r:
            return mahalanobis_sq_scalar(xq, yq, zq, dx, dy, dz, fx, fy, baseline, sigma_px)
        r = ref_from_query
        rdx = dx * r[0, 0] + dy * r[0, 1] + dz * r[0, 2]
        rdy = dx * r[1, 0] + dy * r[1, 1] + dz * r[1, 2]
        rdz = dx * r[2, 0] + dy * r[2, 1] + dz * r[2, 2]
        return mahalanobis_sq_scalar(xr, yr, zr, rdx, rdy, rdz, fx, fy, baseline, sigma_px)
    # MODE_SUM: the reference covariance rotated into the query frame (R_qr = R_rq^T).
    r_qr = ref_from_query[:3, :3].T
    return mahalanobis_sq_sum_scalar(xq, yq, zq, xr, yr, zr, r_qr, dx, dy, dz, fx, fy, baseline, sigma_px)


#: Safety factor of the bound in :func:`tolerance_sq_capped_scalar`: the bound must reject only what the exact test
#: rejects, despite ``u`` stored in float32 (relative error 6e-8) and the rounding of the 3x3 inversions (relative
#: error about condition number x 1e-16, the condition of these covariances staying far below 1e8).
_BOUND_SAFETY = 1.01


@njit(cache=True, error_model="numpy")
def tolerance_sq_capped_scalar(
    mode: int,
    xq: float,
    yq: float,
    zq: float,
    xr: float,
    yr: float,
    zr: float,
    xrq: float,
    yrq: float,
    zrq: float,
    ref_from_query: np.ndarray,
    u_q: float,
    u_r: float,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
    cap: float,
) -> float:
    """:func:`tolerance_sq_scalar`, or ``inf`` when a cheap bound proves it larger than ``cap``.

    Every reading is a quadratic form ``d^T S d`` of the offset ``d`` whose
    matrix ``S`` (an information matrix, or the inverse of a sum of
    covariances) has its smallest eigenvalue at least ``1 / (u_q + u_r)``, so
    ``m2 >= |d|^2 / (u_q + u_r)``. A lookup that lands on another surface is
    rejected by that bound without the three 3x3 inversions of the ``sum``
    reading; compared with any limit up to ``cap``, the result decides as the
    exact value would. Non-finite inputs fall through to the exact test.
    """
    dx, dy, dz = xrq - xq, yrq - yq, zrq - zq
    if dx * dx + dy * dy + dz * dz > cap * (np.float64(u_q) + np.float64(u_r)) * _BOUND_SAFETY:
        return np.inf
    return tolerance_sq_scalar(
        mode, xq, yq, zq, xr, yr, zr, xrq, yrq, zrq, ref_from_query, u_q, u_r, fx, fy, baseline, sigma_px
    )


@njit(cache=True, error_model="numpy")
def transform_scalar(t: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    """``t`` (4x4 rigid transform) applied to one point."""
    return (
        t[0, 0] * x + t[0, 1] * y + t[0, 2] * z + t[0, 3],
        t[1, 0] * x + t[1, 1] * y + t[1, 2] * z + t[1, 3],
        t[2, 0] * x + t[2, 1] * y + t[2, 2] * z + t[2, 3],
    )


@njit(cache=True, error_model="numpy")
def project_scalar(
    x: float, y: float, z: float, fx: float, fy: float, cx: float, cy: float, width: int, height: int
) -> int:
    """Flat index of the nearest pixel of a left-frame point, or -1 behind the camera / outside the image."""
    if not z > 0:
        return -1
    inv_z = 1.0 / z
    col = np.rint(fx * x * inv_z + cx)
    row = np.rint(fy * y * inv_z + cy)
    if col >= 0 and col <= width - 1 and row >= 0 and row <= height - 1:
        return int(row) * width + int(col)
    return -1


@njit(cache=True, error_model="numpy")
def observation_angle_scalar(
    x: float, y: float, z: float, ax: float, ay: float, az: float, bx: float, by: float, bz: float
) -> float:
    """Angle (degrees) at point ``X`` between the directions to centres ``a`` and ``b`` (one frame, metres)."""
    tax, tay, taz = ax - x, ay - y, az - z
    tbx, tby, tbz = bx - x, by - y, bz - z
    dot = tax * tbx + tay * tby + taz * tbz
    cos = dot / (math.sqrt(tax * tax + tay * tay + taz * taz) * math.sqrt(tbx * tbx + tby * tby + tbz * tbz))
    cos = min(max(cos, -1.0), 1.0)
    return math.degrees(math.acos(cos))


@njit(cache=True, error_model="numpy")
def candidate_tolerance_scalar(u_candidate: float, u_ref: float, sigma_max: float, reading: int) -> float:
    """Stage 3: border (metres along the reference ray) between a +1 and a -1/none vote (``READING_*``)."""
    if reading == READING_STD:
        return (math.sqrt(u_candidate) + math.sqrt(u_ref)) * sigma_max
    return (1.0 / math.sqrt(u_candidate) + 1.0 / math.sqrt(u_ref)) * sigma_max


@njit(cache=True, error_model="numpy")
def augmented_margin_scalar(u_aug: float, sigma_max: float, reading: int) -> float:
    """Stage 3: how far (metres) the query depth must lie in front of the augmented depth to be negative."""
    if reading == READING_STD:
        return sigma_max * math.sqrt(u_aug)
    return sigma_max / math.sqrt(u_aug)


# ---------------------------------------------------------------------------------------------------------------------
# Array kernels over rows (the numpy-facing wrappers call these with contiguous arrays). Serial: callers use them
# on a few hundred to a few hundred thousand rows, where starting threads costs more than it saves (and much more
# when other processes hold the cores). The fused stage kernels, which all stages now use, are parallel.


@njit(cache=True, error_model="numpy")
def information_rows(points: np.ndarray, fx: float, fy: float, baseline: float, sigma_px: float) -> np.ndarray:
    """Packed Fisher information ``(M, 6)`` of ``(M, 3)`` points."""
    out = np.empty((points.shape[0], 6))
    for i in range(points.shape[0]):
        f = information_scalar(points[i, 0], points[i, 1], points[i, 2], fx, fy, baseline, sigma_px)
        for k in range(6):
            out[i, k] = f[k]
    return out


@njit(cache=True, error_model="numpy")
def sym_inverse_rows(s: np.ndarray) -> np.ndarray:
    """Inverses ``(M, 6)`` of packed symmetric matrices ``(M, 6)``."""
    out = np.empty_like(s)
    for i in range(s.shape[0]):
        inv = sym_inverse_scalar(s[i, 0], s[i, 1], s[i, 2], s[i, 3], s[i, 4], s[i, 5])
        for k in range(6):
            out[i, k] = inv[k]
    return out


@njit(cache=True, error_model="numpy")
def sym_eigvalsh_rows(s: np.ndarray) -> np.ndarray:
    """Ascending eigenvalues ``(M, 3)`` of packed symmetric matrices ``(M, 6)``."""
    out = np.empty((s.shape[0], 3))
    for i in range(s.shape[0]):
        e = sym_eigvalsh_scalar(s[i, 0], s[i, 1], s[i, 2], s[i, 3], s[i, 4], s[i, 5])
        out[i, 0], out[i, 1], out[i, 2] = e[0], e[1], e[2]
    return out


@njit(cache=True, error_model="numpy")
def rotate_sym_rows(s: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``R S R^T`` ``(M, 6)`` of packed symmetric matrices ``(M, 6)``."""
    out = np.empty_like(s)
    for i in range(s.shape[0]):
        r = rotate_sym_scalar(s[i, 0], s[i, 1], s[i, 2], s[i, 3], s[i, 4], s[i, 5], rotation)
        for k in range(6):
            out[i, k] = r[k]
    return out


@njit(cache=True, error_model="numpy")
def quadratic_form_rows(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``d^T S d`` ``(M,)`` for packed ``S`` ``(M, 6)`` and vectors ``d`` ``(M, 3)``."""
    out = np.empty(s.shape[0])
    for i in range(s.shape[0]):
        out[i] = quadratic_form_scalar(s[i, 0], s[i, 1], s[i, 2], s[i, 3], s[i, 4], s[i, 5], d[i, 0], d[i, 1], d[i, 2])
    return out


@njit(cache=True, error_model="numpy", parallel=True)
def largest_eigenvalue_rows(points: np.ndarray, fx: float, fy: float, baseline: float, sigma_px: float) -> np.ndarray:
    """``u`` ``(M,)`` (m^2, NaN invalid) of ``(M, 3)`` left-frame points (float32 or float64)."""
    out = np.empty(points.shape[0])
    for i in prange(points.shape[0]):
        out[i] = largest_eigenvalue_scalar(
            np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2]), fx, fy, baseline, sigma_px
        )
    return out


@njit(cache=True, error_model="numpy")
def mahalanobis_sq_rows(
    points: np.ndarray, delta: np.ndarray, fx: float, fy: float, baseline: float, sigma_px: float
) -> np.ndarray:
    """``dX^T F dX`` ``(M,)`` of offsets ``(M, 3)`` w.r.t. the covariance of points ``(M, 3)``."""
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        out[i] = mahalanobis_sq_scalar(
            points[i, 0], points[i, 1], points[i, 2], delta[i, 0], delta[i, 1], delta[i, 2], fx, fy, baseline, sigma_px
        )
    return out


@njit(cache=True, error_model="numpy")
def mahalanobis_sq_sum_rows(
    points_a: np.ndarray,
    points_b: np.ndarray,
    rotation_ab: np.ndarray,
    delta_a: np.ndarray,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
) -> np.ndarray:
    """``dX^T (C_a + C_b)^-1 dX`` ``(M,)`` row by row (see :func:`mahalanobis_sq_sum_scalar`)."""
    out = np.empty(points_a.shape[0])
    for i in range(points_a.shape[0]):
        out[i] = mahalanobis_sq_sum_scalar(
            points_a[i, 0],
            points_a[i, 1],
            points_a[i, 2],
            points_b[i, 0],
            points_b[i, 1],
            points_b[i, 2],
            rotation_ab,
            delta_a[i, 0],
            delta_a[i, 1],
            delta_a[i, 2],
            fx,
            fy,
            baseline,
            sigma_px,
        )
    return out


@njit(cache=True, error_model="numpy")
def tolerance_sq_rows(
    mode: int,
    query_points: np.ndarray,
    ref_points: np.ndarray,
    ref_in_query: np.ndarray,
    ref_from_query: np.ndarray,
    u_query: np.ndarray,
    u_ref: np.ndarray,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
) -> np.ndarray:
    """:func:`tolerance_sq_scalar` row by row (``(M,)``)."""
    out = np.empty(query_points.shape[0])
    for i in range(query_points.shape[0]):
        out[i] = tolerance_sq_scalar(
            mode,
            query_points[i, 0],
            query_points[i, 1],
            query_points[i, 2],
            ref_points[i, 0],
            ref_points[i, 1],
            ref_points[i, 2],
            ref_in_query[i, 0],
            ref_in_query[i, 1],
            ref_in_query[i, 2],
            ref_from_query,
            np.float64(u_query[i]),
            np.float64(u_ref[i]),
            fx,
            fy,
            baseline,
            sigma_px,
        )
    return out


@njit(cache=True, error_model="numpy")
def observation_angle_rows(points: np.ndarray, centre_a: np.ndarray, centre_b: np.ndarray) -> np.ndarray:
    """Observation angles ``(M,)`` (degrees) at ``(M, 3)`` points between two centres."""
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        out[i] = observation_angle_scalar(
            points[i, 0],
            points[i, 1],
            points[i, 2],
            centre_a[0],
            centre_a[1],
            centre_a[2],
            centre_b[0],
            centre_b[1],
            centre_b[2],
        )
    return out


@njit(cache=True, error_model="numpy")
def project_rows(
    points: np.ndarray,
    transform: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Transform ``(M, 3)`` points by a 4x4 ``transform`` and project them.

    Returns the transformed points ``(M, 3)`` float64 and the flat pixel index
    ``(M,)`` of each (-1 behind the camera, outside the image or not finite).
    """
    m = points.shape[0]
    moved = np.empty((m, 3))
    index = np.empty(m, dtype=np.int64)
    for i in range(m):
        x, y, z = transform_scalar(
            transform, np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        )
        moved[i, 0], moved[i, 1], moved[i, 2] = x, y, z
        index[i] = project_scalar(x, y, z, fx, fy, cx, cy, width, height)
    return moved, index


@njit(cache=True, error_model="numpy")
def splat_nearest_kernel(
    points: np.ndarray,
    source: np.ndarray,
    transform: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
) -> np.ndarray:
    """Z-buffer: per pixel, the ``source`` of the moved point nearest the camera (``(H*W,)``, -1 where none).

    ``points`` (``(M, 3)``) are moved by the 4x4 ``transform`` and projected;
    among equal depths the later point wins (the order a numpy fancy
    assignment leaves). Sequential: a z-buffer is a reduction with write
    conflicts, and one pass is memory-bound anyway.
    """
    n_pixels = width * height
    best = np.full(n_pixels, np.inf)
    out = np.full(n_pixels, -1, dtype=np.int64)
    for i in range(points.shape[0]):
        x, y, z = transform_scalar(
            transform, np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        )
        zbuffer_keep(best, out, project_scalar(x, y, z, fx, fy, cx, cy, width, height), z, source[i])
    return out


@njit(cache=True, error_model="numpy")
def zbuffer_keep(best: np.ndarray, out: np.ndarray, p: int, z: float, source: int) -> None:
    """One z-buffer step: keep ``source`` at pixel ``p`` (-1: none) if its depth ``z`` (metres) is the nearest so
    far or ties it (``<=``: among equal depths the later point wins)."""
    if p >= 0 and z <= best[p]:
        best[p] = z
        out[p] = source


@njit(cache=True, error_model="numpy")
def support_count_scalar(bits: np.uint64) -> int:
    """Number of set bits of one Stage-1 mask (the paper's ``support``: distinct angular bins)."""
    count = 0
    b = np.uint64(bits)
    # Clearing the lowest set bit per step: masks hold a handful of bins, so this beats a table or SWAR here.
    while b != np.uint64(0):
        b &= b - np.uint64(1)
        count += 1
    return count


@njit(cache=True, error_model="numpy")
def splat_supported_kernel(
    points: np.ndarray,
    valid: np.ndarray,
    support_bits: np.ndarray,
    transform: np.ndarray,
    need: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
) -> np.ndarray:
    """Stage 2's z-buffer: per query pixel with ``need`` set, the flat reference index of the nearest valid,
    supported (``support >= 1``) reference point (``(H*W,)``, -1 where none or not needed).

    The same z-buffer as :func:`splat_nearest_kernel` on those points in index
    order, without gathering them first; pixels not needed are never written,
    which spares most random memory writes when few pixels are left to decide.
    """
    n_pixels = width * height
    best = np.full(n_pixels, np.inf)
    out = np.full(n_pixels, -1, dtype=np.int64)
    for i in range(points.shape[0]):
        if not valid[i] or support_bits[i] == np.uint64(0):
            continue
        x, y, z = transform_scalar(
            transform, np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        )
        p = project_scalar(x, y, z, fx, fy, cx, cy, width, height)
        if p >= 0 and need[p]:
            zbuffer_keep(best, out, p, z, i)
    return out


@njit(cache=True, error_model="numpy")
def _angle_surely_below(
    x: float, y: float, z: float, centre_a: np.ndarray, centre_b: np.ndarray, cos_reject: float
) -> bool:
    """Cheap pre-test: ``cos(alpha) > cos_reject`` without ``acos`` or square roots (``alpha`` of
    :func:`observation_angle_scalar`); only a sure rejection, the exact test follows otherwise."""
    tax, tay, taz = centre_a[0] - x, centre_a[1] - y, centre_a[2] - z
    tbx, tby, tbz = centre_b[0] - x, centre_b[1] - y, centre_b[2] - z
    dot = tax * tbx + tay * tby + taz * tbz
    if dot <= 0:
        return False
    return dot * dot > cos_reject * cos_reject * (tax * tax + tay * tay + taz * taz) * (
        tbx * tbx + tby * tby + tbz * tbz
    )


@njit(cache=True, error_model="numpy")
def _angle_surely_above(
    x: float, y: float, z: float, centre_a: np.ndarray, centre_b: np.ndarray, cos_accept: float
) -> bool:
    """Cheap pre-test: ``cos(alpha) < cos_accept`` without ``acos`` or square roots; only a sure acceptance
    (``False`` when in doubt, e.g. a point at a centre), so the exact angle may wait until a bin is needed."""
    tax, tay, taz = centre_a[0] - x, centre_a[1] - y, centre_a[2] - z
    tbx, tby, tbz = centre_b[0] - x, centre_b[1] - y, centre_b[2] - z
    norms = (tax * tax + tay * tay + taz * taz) * (tbx * tbx + tby * tby + tbz * tbz)
    if not norms > 0:
        return False
    dot = tax * tbx + tay * tby + taz * tbz
    if cos_accept > 0:
        return dot <= 0 or dot * dot < cos_accept * cos_accept * norms
    return dot < 0 and dot * dot > cos_accept * cos_accept * norms


@njit(cache=True, error_model="numpy", parallel=True)
def support_bits_kernel(
    q_points: np.ndarray,
    q_valid: np.ndarray,
    q_u: np.ndarray,
    r_points: np.ndarray,
    r_valid: np.ndarray,
    r_u: np.ndarray,
    ref_from_query: np.ndarray,
    query_from_ref: np.ndarray,
    centre_r: np.ndarray,
    centre_q: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    baseline: float,
    sigma_px: float,
    alpha_min_deg: float,
    sigma_max: float,
    mode: int,
    max_bins: int,
) -> np.ndarray:
    """Stage 1: the angular bin bit each valid query pixel gets from one reference view (``(N,)`` uint64).

    Per query pixel: observation angle above ``alpha_min_deg`` between the
    mean centres (both given in the query frame), lookup in the reference
    (transform, nearest pixel, valid reference measurement) and the tolerance
    test ``mode``; then bit ``min(floor(alpha / alpha_min), max_bins - 1)``.
    """
    n = q_valid.shape[0]
    bits = np.zeros(n, dtype=np.uint64)
    limit = sigma_max * sigma_max
    # Cosine above which the angle is below alpha_min beyond any rounding doubt (on forward motion most pixels).
    cos_reject = math.cos(math.radians(alpha_min_deg)) + 1e-9
    # Cosine below which the angle is above alpha_min beyond any rounding doubt: the exact angle (acos) is then
    # needed only for the bin of a supporting measurement.
    cos_accept = math.cos(math.radians(alpha_min_deg)) - 1e-9
    for i in prange(n):
        if not q_valid[i]:
            continue
        xq, yq, zq = np.float64(q_points[i, 0]), np.float64(q_points[i, 1]), np.float64(q_points[i, 2])
        # The angle first: it needs no memory access, and on forward motion it rejects most pixels.
        if _angle_surely_below(xq, yq, zq, centre_r, centre_q, cos_reject):
            continue
        above = _angle_surely_above(xq, yq, zq, centre_r, centre_q, cos_accept)
        alpha = 0.0
        if not above:
            alpha = observation_angle_scalar(
                xq, yq, zq, centre_r[0], centre_r[1], centre_r[2], centre_q[0], centre_q[1], centre_q[2]
            )
            if not alpha > alpha_min_deg:
                continue
        x, y, z = transform_scalar(ref_from_query, xq, yq, zq)
        j = project_scalar(x, y, z, fx, fy, cx, cy, width, height)
        if j < 0 or not r_valid[j]:
            continue
        xr, yr, zr = np.float64(r_points[j, 0]), np.float64(r_points[j, 1]), np.float64(r_points[j, 2])
        xrq, yrq, zrq = transform_scalar(query_from_ref, xr, yr, zr)
        m2 = tolerance_sq_capped_scalar(
            mode,
            xq,
            yq,
            zq,
            xr,
            yr,
            zr,
            xrq,
            yrq,
            zrq,
            ref_from_query,
            q_u[i],
            r_u[j],
            fx,
            fy,
            baseline,
            sigma_px,
            limit,
        )
        if m2 <= limit:
            if above:
                alpha = observation_angle_scalar(
                    xq, yq, zq, centre_r[0], centre_r[1], centre_r[2], centre_q[0], centre_q[1], centre_q[2]
                )
            # alpha > alpha_min > 0 here, so truncation is the floor.
            b = min(int(alpha / alpha_min_deg), max_bins - 1)
            bits[i] = np.uint64(1) << np.uint64(b)
    return bits


@njit(cache=True, error_model="numpy", parallel=True)
def splat_into_pending(
    pixel: np.ndarray,
    depth: np.ndarray,
    pending: np.ndarray,
    ref_points: np.ndarray,
    ref_valid: np.ndarray,
    query_from_ref: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
) -> None:
    """Fill ``pixel`` (query pixel, -1 if none or not pending) and ``depth`` (metres in the query, set only where
    ``pixel >= 0``) of every reference point, ``(V, N)`` each, in place (the caller's buffers are reused)."""
    n_refs, n = ref_valid.shape
    for k in range(n_refs):
        t = query_from_ref[k]
        for s in prange(n):
            pixel[k, s] = -1
            if ref_valid[k, s]:
                x, y, z = transform_scalar(
                    t, np.float64(ref_points[k, s, 0]), np.float64(ref_points[k, s, 1]), np.float64(ref_points[k, s, 2])
                )
                p = project_scalar(x, y, z, fx, fy, cx, cy, width, height)
                if p >= 0 and pending[p]:
                    pixel[k, s] = p
                    depth[k, s] = z


@njit(cache=True, error_model="numpy")
def nearest_candidate(pixel: np.ndarray, depth: np.ndarray, n_pixels: int) -> np.ndarray:
    """Per query pixel, the smallest splatted depth (metres; inf where none) of :func:`splat_into_pending`'s output."""
    best = np.full(n_pixels, np.inf)
    n_refs, n_points = pixel.shape
    for k in range(n_refs):
        for s in range(n_points):
            p = pixel[k, s]
            if p >= 0 and depth[k, s] < best[p]:
                best[p] = depth[k, s]
    return best


@njit(cache=True, error_model="numpy")
def group_candidates(pixel: np.ndarray, depth: np.ndarray, select: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The splatted depths falling into the ``select``-ed query pixels, grouped by pixel and sorted ascending.

    Returns ``(start, sorted_depth)``: pixel ``p``'s candidates are
    ``sorted_depth[start[p]:start[p + 1]]`` (metres).
    """
    n = select.shape[0]
    n_refs, n_points = pixel.shape
    # Counting sort by pixel (sequential: concurrent increments of one counter would conflict).
    count = np.zeros(n + 1, dtype=np.int64)
    for k in range(n_refs):
        for s in range(n_points):
            p = pixel[k, s]
            if p >= 0 and select[p]:
                count[p + 1] += 1
    start = np.cumsum(count)
    fill = start[:-1].copy()
    out = np.empty(start[-1])
    for k in range(n_refs):
        for s in range(n_points):
            p = pixel[k, s]
            if p >= 0 and select[p]:
                out[fill[p]] = depth[k, s]
                fill[p] += 1
    _sort_groups(start, out)
    return start, out


@njit(cache=True, error_model="numpy", parallel=True)
def _sort_groups(start: np.ndarray, values: np.ndarray) -> None:
    """Sort ``values[start[p]:start[p + 1]]`` ascending for every group ``p``, in place (insertion sort: the
    groups are short, about one entry per reference view)."""
    for p in prange(start.shape[0] - 1):
        for a in range(start[p] + 1, start[p + 1]):
            value = values[a]
            b = a - 1
            while b >= start[p] and values[b] > value:
                values[b + 1] = values[b]
                b -= 1
            values[b + 1] = value


@njit(cache=True, error_model="numpy", inline="always")
def reference_ranges_scalar(
    ref_from_query: np.ndarray,
    x: float,
    y: float,
    z: float,
    ref_points: np.ndarray,
    ref_valid: np.ndarray,
    k: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    focal_baseline: float,
    limit: float,
) -> tuple[int, float, float]:
    """Stage 3's lookup of a query-frame point in reference ``k`` (``ref_points[k]``, ``ref_valid[k]``).

    Returns ``(j, range_point, range_measured)``: the reference pixel the
    point projects to, the point's distance from the reference's left camera
    and that of the reference's measurement at ``j`` (metres); ``j = -1``
    (ranges NaN) outside the image, without a valid measurement there, or where
    the point's disparity in the reference (``focal_baseline / depth``) exceeds
    ``limit`` pixels: a point the reference's matcher could not have measured.
    """
    rx, ry, rz = transform_scalar(ref_from_query, x, y, z)
    j = project_scalar(rx, ry, rz, fx, fy, cx, cy, width, height)
    if j < 0 or not ref_valid[k, j] or focal_baseline > limit * rz:
        return -1, np.nan, np.nan
    px, py, pz = np.float64(ref_points[k, j, 0]), np.float64(ref_points[k, j, 1]), np.float64(ref_points[k, j, 2])
    return j, math.sqrt(rx * rx + ry * ry + rz * rz), math.sqrt(px * px + py * py + pz * pz)


@njit(cache=True, error_model="numpy")
def candidate_is_valid(
    p: int,
    d: float,
    ref_points: np.ndarray,
    ref_valid: np.ndarray,
    ref_u: np.ndarray,
    ref_from_query: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    baseline: float,
    sigma_px: float,
    sigma_max: float,
    reading: int,
    min_positive_votes: int,
    ref_limit: np.ndarray,
) -> bool:
    """Stage 3's relaxed vote on one candidate: query pixel ``p``'s ray at depth ``d`` (metres).

    Each reference ``k`` (``ref_from_query[k]`` moves query points into it)
    votes by lookup: +1 within :func:`candidate_tolerance_scalar` of its
    measurement along its ray (distance from its left camera), -1 if in front
    by more (the candidate would block its line of sight), nothing if behind,
    without a valid measurement there, or where the candidate's disparity in it
    exceeds ``ref_limit[k]`` pixels (inf: no limit). Valid: at least
    ``min_positive_votes`` +1 votes and a positive sum.
    """
    # The pixel's ray: the same expressions as projection.pixel_rays.
    x = d * ((np.float64(p % width) - cx) / fx)
    y = d * ((np.float64(p // width) - cy) / fy)
    z = d * 1.0
    u_c = -1.0  # computed at the first vote that needs it
    focal_baseline = fx * baseline
    plus = 0
    total = 0
    n_refs = ref_points.shape[0]
    for k in range(n_refs):
        j, range_c, range_r = reference_ranges_scalar(
            ref_from_query[k],
            x,
            y,
            z,
            ref_points,
            ref_valid,
            k,
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            focal_baseline,
            ref_limit[k],
        )
        if j >= 0:
            if u_c < 0:
                u_c = largest_eigenvalue_scalar(x, y, z, fx, fy, baseline, sigma_px)
            tol = candidate_tolerance_scalar(u_c, np.float64(ref_u[k, j]), sigma_max, reading)
            if abs(range_c - range_r) <= tol:
                plus += 1
                total += 1
            elif range_c < range_r:
                total -= 1
        # Stop as soon as the remaining voters cannot change the outcome (same result, fewer lookups).
        remaining = n_refs - 1 - k
        if plus + remaining < min_positive_votes or total + remaining <= 0:
            return False
        if plus >= min_positive_votes and total - remaining > 0:
            return True
    return plus >= min_positive_votes and total > 0


@njit(cache=True, error_model="numpy", parallel=True)
def vote_nearest(
    best: np.ndarray,
    ref_points: np.ndarray,
    ref_valid: np.ndarray,
    ref_u: np.ndarray,
    ref_from_query: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    baseline: float,
    sigma_px: float,
    sigma_max: float,
    reading: int,
    min_positive_votes: int,
    ref_limit: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3, first round: the relaxed vote on each pixel's nearest candidate ``best`` (inf where none).

    Returns ``z_aug`` (metres, NaN where not validated) and the pixels whose
    nearest candidate was rejected (they go on with their farther candidates).
    """
    n = best.shape[0]
    z_aug = np.full(n, np.nan)
    retry = np.zeros(n, dtype=np.bool_)
    for p in prange(n):
        d = best[p]
        if not math.isfinite(d):
            continue
        if candidate_is_valid(
            p,
            d,
            ref_points,
            ref_valid,
            ref_u,
            ref_from_query,
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            baseline,
            sigma_px,
            sigma_max,
            reading,
            min_positive_votes,
            ref_limit,
        ):
            z_aug[p] = d
        else:
            retry[p] = True
    return z_aug, retry


@njit(cache=True, error_model="numpy", parallel=True)
def vote_farther(
    z_aug: np.ndarray,
    best: np.ndarray,
    start: np.ndarray,
    depth: np.ndarray,
    ref_points: np.ndarray,
    ref_valid: np.ndarray,
    ref_u: np.ndarray,
    ref_from_query: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    baseline: float,
    sigma_px: float,
    sigma_max: float,
    reading: int,
    min_positive_votes: int,
    ref_limit: np.ndarray,
) -> None:
    """Stage 3, later rounds, in place: per pixel, the nearest valid candidate of ``depth`` farther than ``best``.

    A candidate is the pixel's ray at a depth, so one at the depth already
    rejected (``best``) would be rejected again and is skipped.
    """
    for p in prange(start.shape[0] - 1):
        for c in range(start[p], start[p + 1]):
            d = depth[c]
            if d <= best[p]:
                continue
            if candidate_is_valid(
                p,
                d,
                ref_points,
                ref_valid,
                ref_u,
                ref_from_query,
                fx,
                fy,
                cx,
                cy,
                width,
                height,
                baseline,
                sigma_px,
                sigma_max,
                reading,
                min_positive_votes,
                ref_limit,
            ):
                z_aug[p] = d
                break


@njit(cache=True, error_model="numpy")
def candidate_tolerance_rows(u_candidate: np.ndarray, u_ref: np.ndarray, sigma_max: float, reading: int) -> np.ndarray:
    """:func:`candidate_tolerance_scalar` element by element (``(M,)``, metres)."""
    out = np.empty(u_candidate.shape[0])
    for i in range(u_candidate.shape[0]):
        out[i] = candidate_tolerance_scalar(u_candidate[i], u_ref[i], sigma_max, reading)
    return out


@njit(cache=True, error_model="numpy")
def augmented_margin_rows(u_aug: np.ndarray, sigma_max: float, reading: int) -> np.ndarray:
    """:func:`augmented_margin_scalar` element by element (``(M,)``, metres)."""
    out = np.empty(u_aug.shape[0])
    for i in range(u_aug.shape[0]):
        out[i] = augmented_margin_scalar(u_aug[i], sigma_max, reading)
    return out


@njit(cache=True, error_model="numpy", parallel=True)
def outlier_negatives_kernel(
    z_query: np.ndarray,
    z_aug: np.ndarray,
    pending: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    baseline: float,
    sigma_px: float,
    sigma_max: float,
    reading: int,
) -> np.ndarray:
    """Stage 3: pending pixels whose query depth ``z_query`` lies in front of ``z_aug`` by more than the margin.

    ``u_aug`` is the uncertainty of the augmented point (the pixel's ray at
    ``z_aug``) as if Q's pair alone measured it; pixels without ``z_aug`` (NaN) are never negative.
    """
    n = pending.shape[0]
    negative = np.zeros(n, dtype=np.bool_)
    for p in prange(n):
        d = z_aug[p]
        if not pending[p] or not math.isfinite(d):
            continue
        ray_x = (np.float64(p % width) - cx) / fx
        ray_y = (np.float64(p // width) - cy) / fy
        u_aug = largest_eigenvalue_scalar(d * ray_x, d * ray_y, d * 1.0, fx, fy, baseline, sigma_px)
        negative[p] = np.float64(z_query[p]) < d - augmented_margin_scalar(u_aug, sigma_max, reading)
    return negative


@njit(cache=True, error_model="numpy", parallel=True)
def free_space_witnesses_kernel(
    count: np.ndarray,
    pixels: np.ndarray,
    query_points: np.ndarray,
    query_u: np.ndarray,
    ref_points: np.ndarray,
    ref_valid: np.ndarray,
    ref_u: np.ndarray,
    ref_from_query: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    sigma_max: float,
    reading: int,
    focal_baseline: float,
    limit: float,
) -> None:
    """Stage 3, in place: add 1 to ``count[i]`` where one reference sees through query pixel ``pixels[i]``'s point.

    The reference sees through ``X_q`` where ``X_q`` projects onto a valid
    measurement of it lying *behind* ``X_q`` (along the reference ray) by more
    than :func:`candidate_tolerance_scalar` of the two uncertainties: that
    view looked through the place where the query puts a surface. One
    reference per call, as a stack of one (``ref_points[None]``, a view: no
    copy of the window), looked up by :func:`reference_ranges_scalar` as the
    candidates' votes are; a reference in which ``X_q``'s disparity
    (``focal_baseline / depth``) exceeds ``limit`` pixels is no witness.
    """
    for i in prange(pixels.shape[0]):
        p = pixels[i]
        x, y, z = np.float64(query_points[p, 0]), np.float64(query_points[p, 1]), np.float64(query_points[p, 2])
        j, range_q, range_r = reference_ranges_scalar(
            ref_from_query, x, y, z, ref_points, ref_valid, 0, fx, fy, cx, cy, width, height, focal_baseline, limit
        )
        if j >= 0 and range_r - range_q > candidate_tolerance_scalar(
            np.float64(query_u[p]), np.float64(ref_u[0, j]), sigma_max, reading
        ):
            count[i] += 1


# ---------------------------------------------------------------------------------------------------------------------
# Stage 2: consistency voting of one reference view, all query pixels in one pass.


@njit(cache=True, error_model="numpy")
def agrees_nearby_scalar(
    i: int,
    xs: float,
    ys: float,
    zs: float,
    xsq: float,
    ysq: float,
    zsq: float,
    u_s: float,
    q_points: np.ndarray,
    q_valid: np.ndarray,
    q_u: np.ndarray,
    ref_from_query: np.ndarray,
    width: int,
    height: int,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
    mode: int,
    radius: int,
    limit_sq: float,
) -> bool:
    """Whether a splatted reference point agrees with a valid query measurement near query pixel ``i``.

    ``s`` is the point in the reference frame, ``sq`` in the query frame
    (metres), ``u_s`` its ``u`` (m^2). The ``(2 radius + 1)^2 - 1``
    neighbours of ``i`` (not ``i`` itself) are tested in row-major order with
    the tolerance ``mode``: agreement is a squared distance ``<= limit_sq``.
    """
    row = i // width
    col = i - row * width
    for dr in range(-radius, radius + 1):
        r = row + dr
        if r < 0 or r >= height:
            continue
        for dc in range(-radius, radius + 1):
            c = col + dc
            if (dr == 0 and dc == 0) or c < 0 or c >= width:
                continue
            k = r * width + c
            if not q_valid[k]:
                continue
            m2 = tolerance_sq_capped_scalar(
                mode,
                np.float64(q_points[k, 0]),
                np.float64(q_points[k, 1]),
                np.float64(q_points[k, 2]),
                xs,
                ys,
                zs,
                xsq,
                ysq,
                zsq,
                ref_from_query,
                np.float64(q_u[k]),
                u_s,
                fx,
                fy,
                baseline,
                sigma_px,
                limit_sq,
            )
            if m2 <= limit_sq:
                return True
    return False


@njit(cache=True, error_model="numpy", parallel=True)
def lookup_votes_kernel(
    vote_sum: np.ndarray,
    voted: np.ndarray,
    pending: np.ndarray,
    q_points: np.ndarray,
    q_valid: np.ndarray,
    q_u: np.ndarray,
    r_points: np.ndarray,
    r_valid: np.ndarray,
    r_u: np.ndarray,
    r_bits: np.ndarray,
    ref_from_query: np.ndarray,
    query_from_ref: np.ndarray,
    centre_r: np.ndarray,
    centre_q: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    baseline: float,
    sigma_px: float,
    mode: int,
    positive_sq: float,
    negative_sq: float,
    min_angle_deg: float,
    negatives_from_any: np.ndarray,
    positive_accuracy_ratio: float,
    occlusion_votes: np.ndarray,
    fallback_views: np.ndarray,
    fallback_accuracy_ratio: float,
    limit: float,
) -> None:
    """Stage 2, lookup: add one reference view's positive or occlusion vote to each valid query pixel, in place.

    Per valid query pixel ``i`` (``X_q``, query frame): ``X_q`` into the
    reference, nearest pixel ``j``; a valid, supported (``support_r >= 1``)
    measurement that is more accurate (``u_r < u_q``, or any where
    ``negatives_from_any[i]``, a bool per query pixel), or that may vote positive
    (``u_r < positive_accuracy_ratio * u_q``, a ratio >= 1), is compared by the squared tolerance distance
    ``m2`` (reading ``mode``). Within ``positive_sq`` and allowed to vote positive:
    ``+support_r / sqrt(u_r)``, or no vote when the observation angle between
    the mean centres ``centre_r``, ``centre_q`` (query frame, metres) is not
    above ``min_angle_deg`` (> 0); beyond ``negative_sq`` with ``X_q`` nearer
    the reference camera than ``X_r`` (occlusion), from a measurement that may vote
    negative: ``-support_r / sqrt(u_r)``. Either of these, or a measurement allowed to
    vote positive that agrees only between the two tolerances, decides the
    reference's vote; ``pending[i]`` is set where nothing decided it (the splat's
    turn, :func:`free_space_votes_kernel`). An occlusion casts its vote only where ``occlusion_votes[i]`` (a
    bool per query pixel); elsewhere it still decides the reference's vote, as no vote.

    A measurement that may not vote positive but is less accurate by under ``fallback_accuracy_ratio``
    (``u_r < fallback_accuracy_ratio * u_q``) and agrees within ``positive_sq`` (and the angle) adds one to
    ``fallback_views[i]`` instead (int32 per query pixel): it casts no vote and decides nothing, so the votes
    are those ``positive_accuracy_ratio`` alone gives.

    ``vote_sum[i] += vote`` and ``voted[i] |= vote != 0``: called once per
    reference in window order, the sums are those of adding whole vote arrays
    reference by reference. Each pixel writes only its own entries.

    Where ``X_q``'s disparity in the reference (``fx * baseline / depth``) exceeds ``limit`` pixels (inf: no
    limit), the reference could not have measured ``X_q``: it casts no vote there and decides it (no splat vote).
    """
    n = q_valid.shape[0]
    cap = max(positive_sq, negative_sq)  # beyond both limits the exact distance changes nothing
    focal_baseline = fx * baseline
    for i in prange(n):
        if not q_valid[i]:
            continue
        xq, yq, zq = np.float64(q_points[i, 0]), np.float64(q_points[i, 1]), np.float64(q_points[i, 2])
        u_q = np.float64(q_u[i])
        vote = 0.0
        decided = False
        x, y, z = transform_scalar(ref_from_query, xq, yq, zq)
        j = project_scalar(x, y, z, fx, fy, cx, cy, width, height)
        if j >= 0 and focal_baseline > limit * z:
            j = -1  # beyond the reference's disparity range: it abstains on X_q
            decided = True
        if j >= 0 and r_valid[j] and r_bits[j] != np.uint64(0):
            u_r = np.float64(r_u[j])
            may_negative = u_r < u_q or negatives_from_any[i]
            may_positive = u_r < positive_accuracy_ratio * u_q
            may_fallback = not may_positive and u_r < fallback_accuracy_ratio * u_q
            if may_negative or may_positive or may_fallback:
                xr, yr, zr = np.float64(r_points[j, 0]), np.float64(r_points[j, 1]), np.float64(r_points[j, 2])
                xrq, yrq, zrq = transform_scalar(query_from_ref, xr, yr, zr)
                m2 = tolerance_sq_capped_scalar(
                    mode,
                    xq,
                    yq,
                    zq,
                    xr,
                    yr,
                    zr,
                    xrq,
                    yrq,
                    zrq,
                    ref_from_query,
                    u_q,
                    u_r,
                    fx,
                    fy,
                    baseline,
                    sigma_px,
                    cap,
                )
                far = m2 > negative_sq
                in_front = math.sqrt(x * x + y * y + z * z) < math.sqrt(xr * xr + yr * yr + zr * zr)
                weight = np.float64(support_count_scalar(r_bits[j])) / math.sqrt(u_r)
                if m2 <= positive_sq and (may_positive or may_fallback):
                    # A reference seen from nearly the query's direction repeats the query's systematic error
                    # (same image patches, same ambiguity): its agreement decides its vote but does not count.
                    if min_angle_deg <= 0 or (
                        observation_angle_scalar(
                            xq, yq, zq, centre_r[0], centre_r[1], centre_r[2], centre_q[0], centre_q[1], centre_q[2]
                        )
                        > min_angle_deg
                    ):
                        if may_positive:
                            vote = weight
                        else:
                            fallback_views[i] += 1
                elif far and in_front and may_negative and occlusion_votes[i]:
                    vote = -weight
                # A lookup that agrees only roughly (between the two tolerances) decides too: no splat vote then.
                decided = (not far and may_positive) or (far and in_front and may_negative)
        pending[i] = not decided
        if vote != 0.0:
            vote_sum[i] += vote
            voted[i] = True


@njit(cache=True, error_model="numpy", parallel=True)
def free_space_votes_kernel(
    vote_sum: np.ndarray,
    voted: np.ndarray,
    pending: np.ndarray,
    source: np.ndarray,
    q_points: np.ndarray,
    q_valid: np.ndarray,
    q_u: np.ndarray,
    r_points: np.ndarray,
    r_u: np.ndarray,
    r_bits: np.ndarray,
    ref_from_query: np.ndarray,
    query_from_ref: np.ndarray,
    width: int,
    height: int,
    fx: float,
    fy: float,
    baseline: float,
    sigma_px: float,
    mode: int,
    free_space_sq: float,
    negatives_from_any: np.ndarray,
    radius: int,
) -> None:
    """Stage 2, splat: add one reference view's free-space-violation vote to each ``pending`` query pixel, in place.

    The splatted reference point ``source[i]`` (flat reference index, -1:
    none; :func:`splat_supported_kernel`), if more accurate than ``X_q``
    (``u_s < u_q``, or any where ``negatives_from_any[i]``), not within
    ``free_space_sq`` (squared tolerance distance, reading ``mode``) and in
    front of ``X_q`` (depth in the query), votes ``-support_s / sqrt(u_s)``,
    unless ``radius > 0`` and it agrees within ``free_space_sq`` with a valid
    query measurement next to ``i`` (:func:`agrees_nearby_scalar`).
    Accumulates like :func:`lookup_votes_kernel`.
    """
    n = q_valid.shape[0]
    for i in prange(n):
        s = source[i]
        if s < 0 or not pending[i]:
            continue
        u_q = np.float64(q_u[i])
        u_s = np.float64(r_u[s])
        if not (u_s < u_q or negatives_from_any[i]):
            continue
        xq, yq, zq = np.float64(q_points[i, 0]), np.float64(q_points[i, 1]), np.float64(q_points[i, 2])
        xs, ys, zs = np.float64(r_points[s, 0]), np.float64(r_points[s, 1]), np.float64(r_points[s, 2])
        xsq, ysq, zsq = transform_scalar(query_from_ref, xs, ys, zs)
        if not zsq < zq:
            continue
        m2 = tolerance_sq_capped_scalar(
            mode,
            xq,
            yq,
            zq,
            xs,
            ys,
            zs,
            xsq,
            ysq,
            zsq,
            ref_from_query,
            u_q,
            u_s,
            fx,
            fy,
            baseline,
            sigma_px,
            free_space_sq,
        )
        if m2 <= free_space_sq:
            continue
        # A splatted point agreeing with a query measurement a pixel or two away lies on the query's own surface
        # (an outline seen from elsewhere), not in the query's line of sight.
        if radius > 0 and agrees_nearby_scalar(
            i,
            xs,
            ys,
            zs,
            xsq,
            ysq,
            zsq,
            u_s,
            q_points,
            q_valid,
            q_u,
            ref_from_query,
            width,
            height,
            fx,
            fy,
            baseline,
            sigma_px,
            mode,
            radius,
            free_space_sq,
        ):
            continue
        vote = -(np.float64(support_count_scalar(r_bits[s])) / math.sqrt(u_s))
        if vote != 0.0:
            vote_sum[i] += vote
            voted[i] = True
