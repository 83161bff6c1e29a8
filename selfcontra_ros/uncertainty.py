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
The per-point formulas live once, as compiled scalar functions, in
:mod:`selfcontra_ros.stages.kernels`; the functions here apply them to arrays
of any leading shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.stages import kernels

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
    ``p = x/z``, ``p' = (x - b)/z``, ``q = y/z``
    (:func:`selfcontra_ros.stages.kernels.information_scalar`).
    """
    rows, shape = _rows(points, 3)
    return kernels.information_rows(rows, camera.fx, camera.fy, camera.baseline, float(sigma_px)).reshape(*shape, 6)


def covariance(points: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """Covariance ``C = F^-1`` (packed ``(..., 6)``, m^2) of left-frame points."""
    return sym_inverse(information(points, camera, sigma_px))


def largest_covariance_eigenvalue(points: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """``u`` = largest eigenvalue of the covariance (m^2) per left-frame point; NaN where the point is invalid.

    Computed as the largest eigenvalue of ``C`` rather than ``1/min eig(F)``:
    the largest eigenvalue of the trigonometric formula has no cancellation.
    A point is invalid when not finite or at ``z <= 0``. Float32 points are
    read as they are (widened per point), without a float64 copy.
    """
    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    shape = p.shape[:-1]
    rows = np.ascontiguousarray(p.reshape(-1, 3))
    return kernels.largest_eigenvalue_rows(rows, camera.fx, camera.fy, camera.baseline, float(sigma_px)).reshape(shape)


def mahalanobis_sq(points: ArrayLike, delta: ArrayLike, camera: StereoCamera, sigma_px: float) -> FloatArray:
    """Squared Mahalanobis length ``dX^T F dX`` of offsets ``delta`` w.r.t. the covariance of ``points``.

    Both in the left frame of the camera that measured ``points`` (metres).
    Uses ``dX^T F dX = |J dX|^2 / sigma_px^2`` (the first-order reprojection
    change in pixels), so no matrix is formed or inverted.
    """
    p, d = np.broadcast_arrays(np.asarray(points, dtype=np.float64), np.asarray(delta, dtype=np.float64))
    rows_p, shape = _rows(p, 3)
    rows_d, _ = _rows(d, 3)
    out = kernels.mahalanobis_sq_rows(rows_p, rows_d, camera.fx, camera.fy, camera.baseline, float(sigma_px))
    return out.reshape(shape)


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
    a, b, d = np.broadcast_arrays(
        np.asarray(points_a, dtype=np.float64), np.asarray(points_b, dtype=np.float64), np.asarray(delta_a, np.float64)
    )
    rows_a, shape = _rows(a, 3)
    rows_b, _ = _rows(b, 3)
    rows_d, _ = _rows(d, 3)
    r = np.ascontiguousarray(rotation_ab, dtype=np.float64)
    out = kernels.mahalanobis_sq_sum_rows(
        rows_a, rows_b, r, rows_d, camera.fx, camera.fy, camera.baseline, float(sigma_px)
    )
    return out.reshape(shape)


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
    rows, shape = _rows(s, 6)
    r = np.ascontiguousarray(rotation, dtype=np.float64)
    return kernels.rotate_sym_rows(rows, r).reshape(*shape, 6)


def sym_inverse(s: ArrayLike) -> FloatArray:
    """Inverse of packed symmetric 3x3 matrices by the adjugate (``(..., 6)``); inf/NaN where singular."""
    rows, shape = _rows(s, 6)
    return kernels.sym_inverse_rows(rows).reshape(*shape, 6)


def sym_quadratic_form(s: ArrayLike, d: ArrayLike) -> FloatArray:
    """``d^T S d`` for packed symmetric ``S`` (``(..., 6)``) and vectors ``d`` (``(..., 3)``)."""
    a = np.asarray(s, dtype=np.float64)
    v = np.asarray(d, dtype=np.float64)
    shape = np.broadcast_shapes(a.shape[:-1], v.shape[:-1])
    rows_s, _ = _rows(np.broadcast_to(a, (*shape, 6)), 6)
    rows_d, _ = _rows(np.broadcast_to(v, (*shape, 3)), 3)
    return kernels.quadratic_form_rows(rows_s, rows_d).reshape(shape)


def sym_eigvalsh(s: ArrayLike) -> FloatArray:
    """Eigenvalues (ascending, ``(..., 3)``) of packed symmetric 3x3 matrices, trigonometric closed form."""
    rows, shape = _rows(s, 6)
    return kernels.sym_eigvalsh_rows(rows).reshape(*shape, 3)


def _rows(a: ArrayLike, width: int) -> tuple[FloatArray, tuple[int, ...]]:
    """``a`` (``(..., width)``) as a contiguous float64 ``(M, width)`` array for the kernels, and its leading shape."""
    arr = np.asarray(a, dtype=np.float64)
    shape = arr.shape[:-1]
    return np.ascontiguousarray(arr.reshape(-1, width)), shape
