"""Uncertainty of stereo-triangulated points, in closed form and vectorised.

A point ``X = (x, y, z)`` in the left camera frame (metres) is observed as the
four image coordinates ``(u_l, v_l, u_r, v_r)`` (pixels) of the rectified pair.
With ``J`` the 4x3 Jacobian of those coordinates w.r.t. ``X`` and isotropic
image noise ``sigma_px`` (pixels), first-order backward propagation gives the
Fisher information ``F = J^T J / sigma_px^2`` (1/m^2) and the covariance
``C = F^-1`` (m^2). ``u``, the largest eigenvalue of ``C``, is the variance
along the most uncertain axis (mostly the viewing ray).

Symmetric 3x3 matrices are stored packed as ``(..., 6)`` arrays in the order
``xx, xy, xz, yy, yz, zz`` so that every operation is a handful of elementwise
numpy expressions over all pixels at once (no per-pixel linear algebra calls).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.geometry import StereoCamera

__all__ = [
    "covariance",
    "information",
    "largest_covariance_eigenvalue",
    "mahalanobis_sq",
    "mahalanobis_sq_sum",
    "mean_camera_centre",
    "rotate_sym",
    "stereo_jacobian",
    "stereo_observation",
    "sym_eigvalsh",
    "sym_from_matrix",
    "sym_inverse",
    "sym_quadratic_form",
    "sym_to_matrix",
]

FloatArray = NDArray[np.float64]

# Packed index of each (row, column) entry of a symmetric 3x3 matrix.
_SYM_INDEX = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


def stereo_observation(points: ArrayLike, camera: StereoCamera) -> FloatArray:
    """Image coordinates ``(u_l, v_l, u_r, v_r)`` (pixels, ``(..., 4)``) of left-frame points (``(..., 3)``, metres)."""
    p = np.asarray(points, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    u_l = camera.fx * x / z + camera.cx
    v_l = camera.fy * y / z + camera.cy
    u_r = camera.fx * (x - camera.baseline) / z + camera.cx
    return np.stack([u_l, v_l, u_r, v_l], axis=-1)


def stereo_jacobian(points: ArrayLike, camera: StereoCamera) -> FloatArray:
    """Analytic Jacobian ``d(u_l, v_l, u_r, v_r)/dX`` (``(..., 4, 3)``, pixels per metre) at left-frame points."""
    p = np.asarray(points, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    a = camera.fx / z
    c = camera.fy / z
    zero = np.zeros_like(z)
    row_ul = np.stack([a, zero, -a * x / z], axis=-1)
    row_vl = np.stack([zero, c, -c * y / z], axis=-1)
    row_ur = np.stack([a, zero, -a * (x - camera.baseline) / z], axis=-1)
    return np.stack([row_ul, row_vl, row_ur, row_vl], axis=-2)


def information(points: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """Fisher information ``F = J^T J / sigma_px^2`` (packed ``(..., 6)``, 1/m^2) of left-frame points.

    Closed form of ``J^T J`` for the rows ``a(1, 0, -p)``, ``c(0, 1, -q)``,
    ``a(1, 0, -p')``, ``c(0, 1, -q)`` with ``a = fx/z``, ``c = fy/z``,
    ``p = x/z``, ``p' = (x - b)/z``, ``q = y/z``.
    """
    pts = np.asarray(points, dtype=np.float64)
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    a2 = (camera.fx / z) ** 2
    c2 = (camera.fy / z) ** 2
    p = x / z
    p_r = (x - camera.baseline) / z
    q = y / z
    s = 1.0 / sigma_px**2
    out = np.empty((*z.shape, 6))
    out[..., 0] = 2.0 * a2 * s
    out[..., 1] = 0.0
    out[..., 2] = -a2 * (p + p_r) * s
    out[..., 3] = 2.0 * c2 * s
    out[..., 4] = -2.0 * c2 * q * s
    out[..., 5] = (a2 * (p * p + p_r * p_r) + 2.0 * c2 * q * q) * s
    return out


def covariance(points: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """Covariance ``C = F^-1`` (packed ``(..., 6)``, m^2) of left-frame points."""
    return sym_inverse(information(points, camera, sigma_px))


def largest_covariance_eigenvalue(points: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """``u`` = largest eigenvalue of the covariance (m^2) per left-frame point; NaN where the point is invalid.

    Computed as the largest eigenvalue of ``C`` rather than ``1/min eig(F)``:
    the largest eigenvalue of the trigonometric formula has no cancellation.
    """
    pts = np.asarray(points, dtype=np.float64)
    ok = np.all(np.isfinite(pts), axis=-1) & (pts[..., 2] > 0)
    safe = np.where(ok[..., None], pts, np.array([0.0, 0.0, 1.0]))
    u = sym_eigvalsh(covariance(safe, camera, sigma_px))[..., 2]
    return np.where(ok, u, np.nan)


def mahalanobis_sq(points: ArrayLike, delta: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """Squared Mahalanobis length ``dX^T F dX`` of offsets ``delta`` w.r.t. the covariance of ``points``.

    Both in the left frame of the camera that measured ``points`` (metres).
    Uses ``dX^T F dX = |J dX|^2 / sigma_px^2`` (the first-order reprojection
    change in pixels), so no matrix is formed or inverted.
    """
    p = np.asarray(points, dtype=np.float64)
    d = np.asarray(delta, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    inv_z = 1.0 / z
    e_ul = camera.fx * inv_z * (dx - x * inv_z * dz)
    e_ur = camera.fx * inv_z * (dx - (x - camera.baseline) * inv_z * dz)
    e_v = camera.fy * inv_z * (dy - y * inv_z * dz)
    return (e_ul * e_ul + e_ur * e_ur + 2.0 * e_v * e_v) / sigma_px**2


def mahalanobis_sq_sum(
    points_a: ArrayLike,
    points_b: ArrayLike,
    rotation_ab: ArrayLike,
    delta_a: ArrayLike,
    camera: StereoCamera,
    sigma_px: float,
) -> FloatArray:
    """``dX^T (C_a + C_b)^-1 dX`` for two noisy measurements of one point (dimensionless).

    Args:
        points_a: points in the left frame of camera A (``(..., 3)``, metres).
        points_b: points in the left frame of camera B (``(..., 3)``, metres).
        rotation_ab: 3x3 rotation taking B-frame vectors into A's frame.
        delta_a: offsets ``X_b - X_a`` expressed in A's frame (metres).
        camera: the stereo camera of both views.
        sigma_px: image noise, pixels.
    """
    c_a = covariance(points_a, camera, sigma_px)
    c_b = rotate_sym(covariance(points_b, camera, sigma_px), rotation_ab)
    return sym_quadratic_form(sym_inverse(c_a + c_b), delta_a)


def mean_camera_centre(pose: ArrayLike, camera: StereoCamera) -> FloatArray:
    """World position (metres) of the midpoint of the left and right optical centres of a pair at ``pose``."""
    t = np.asarray(pose, dtype=np.float64)
    return t[:3, :3] @ np.array([0.5 * camera.baseline, 0.0, 0.0]) + t[:3, 3]


def sym_to_matrix(s: ArrayLike) -> FloatArray:
    """Unpack ``(..., 6)`` symmetric matrices to ``(..., 3, 3)``."""
    return np.asarray(s, dtype=np.float64)[..., _SYM_INDEX]


def sym_from_matrix(m: ArrayLike) -> FloatArray:
    """Pack ``(..., 3, 3)`` symmetric matrices to ``(..., 6)`` (upper triangle)."""
    a = np.asarray(m, dtype=np.float64)
    return np.stack([a[..., 0, 0], a[..., 0, 1], a[..., 0, 2], a[..., 1, 1], a[..., 1, 2], a[..., 2, 2]], axis=-1)


def rotate_sym(s: ArrayLike, rotation: ArrayLike) -> FloatArray:
    """``R S R^T`` of packed symmetric matrices: moves a covariance or information into a rotated frame.

    ``rotation`` takes vectors of the matrices' frame into the new frame;
    Mahalanobis distances are unchanged when the offsets are rotated too.
    """
    r = np.asarray(rotation, dtype=np.float64)
    return sym_from_matrix(r @ sym_to_matrix(s) @ r.T)


def sym_inverse(s: ArrayLike) -> FloatArray:
    """Inverse of packed symmetric 3x3 matrices by the adjugate (``(..., 6)``)."""
    a = np.asarray(s, dtype=np.float64)
    xx, xy, xz, yy, yz, zz = (a[..., i] for i in range(6))
    c_xx = yy * zz - yz * yz
    c_xy = xz * yz - xy * zz
    c_xz = xy * yz - xz * yy
    c_yy = xx * zz - xz * xz
    c_yz = xy * xz - xx * yz
    c_zz = xx * yy - xy * xy
    det = xx * c_xx + xy * c_xy + xz * c_xz
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
    return np.stack([c_xx, c_xy, c_xz, c_yy, c_yz, c_zz], axis=-1) * inv_det[..., None]


def sym_quadratic_form(s: ArrayLike, d: ArrayLike) -> FloatArray:
    """``d^T S d`` for packed symmetric ``S`` (``(..., 6)``) and vectors ``d`` (``(..., 3)``)."""
    a = np.asarray(s, dtype=np.float64)
    v = np.asarray(d, dtype=np.float64)
    dx, dy, dz = v[..., 0], v[..., 1], v[..., 2]
    return (
        a[..., 0] * dx * dx
        + a[..., 3] * dy * dy
        + a[..., 5] * dz * dz
        + 2.0 * (a[..., 1] * dx * dy + a[..., 2] * dx * dz + a[..., 4] * dy * dz)
    )


def sym_eigvalsh(s: ArrayLike) -> FloatArray:
    """Eigenvalues (ascending, ``(..., 3)``) of packed symmetric 3x3 matrices, trigonometric closed form."""
    a = np.asarray(s, dtype=np.float64)
    xx, xy, xz, yy, yz, zz = (a[..., i] for i in range(6))
    q = (xx + yy + zz) / 3.0
    p1 = xy * xy + xz * xz + yz * yz
    dxx, dyy, dzz = xx - q, yy - q, zz - q
    p2 = dxx * dxx + dyy * dyy + dzz * dzz + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_p = np.where(p > 0, 1.0 / p, 0.0)
    bxx, byy, bzz, bxy, bxz, byz = dxx * inv_p, dyy * inv_p, dzz * inv_p, xy * inv_p, xz * inv_p, yz * inv_p
    det_b = bxx * (byy * bzz - byz * byz) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz)
    phi = np.arccos(np.clip(det_b / 2.0, -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    return np.stack([smallest, middle, largest], axis=-1)
