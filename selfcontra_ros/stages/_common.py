"""Tests shared by the stages.

Is a reference measurement within ``sigma_max`` of a query measurement, and may the reference speak about the
query point at all (:func:`range_limit`)?
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.stages import kernels
from selfcontra_ros.window import View

__all__ = ["TOLERANCES", "range_limit", "tolerance_code", "tolerance_sq", "within_tolerance"]

#: Readings of "within sigma_max" (DESIGN section 3):
#: ``query``   - Mahalanobis distance under the query point's covariance (paper, Stage 2);
#: ``smaller`` - under the covariance of whichever point has the smaller ``u`` (paper, Stage 1);
#: ``sum``     - ``dX^T (C_q + C_r)^-1 dX``, the test for two noisy measurements of one point.
TOLERANCES = ("query", "smaller", "sum")

_MODE_CODES = {"query": kernels.MODE_QUERY, "smaller": kernels.MODE_SMALLER, "sum": kernels.MODE_SUM}


def tolerance_sq(
    mode: str,
    query_points: NDArray[np.float64],
    ref_points: NDArray[np.float64],
    ref_in_query: NDArray[np.float64],
    ref_from_query: NDArray[np.float64],
    u_query: NDArray[np.floating],
    u_ref: NDArray[np.floating],
    camera: StereoCamera,
    sigma_px: float,
) -> NDArray[np.float64]:
    """Squared distance, in standard deviations, of each reference measurement from its query measurement.

    Args: as :func:`within_tolerance`, without ``sigma_max``. A measurement is within ``s`` standard
    deviations when the result is ``<= s**2``. The test itself is
    :func:`selfcontra_ros.stages.kernels.tolerance_sq_scalar`, the same compiled function Stage 1's fused
    kernel calls.
    """
    return kernels.tolerance_sq_rows(
        tolerance_code(mode),
        _rows3(query_points),
        _rows3(ref_points),
        _rows3(ref_in_query),
        np.ascontiguousarray(ref_from_query, dtype=np.float64),
        np.ascontiguousarray(u_query, dtype=np.float64).reshape(-1),
        np.ascontiguousarray(u_ref, dtype=np.float64).reshape(-1),
        camera.fx,
        camera.fy,
        camera.baseline,
        float(sigma_px),
    )


def within_tolerance(
    mode: str,
    query_points: NDArray[np.float64],
    ref_points: NDArray[np.float64],
    ref_in_query: NDArray[np.float64],
    ref_from_query: NDArray[np.float64],
    u_query: NDArray[np.floating],
    u_ref: NDArray[np.floating],
    camera: StereoCamera,
    sigma_px: float,
    sigma_max: float,
) -> NDArray[np.bool_]:
    """Whether each reference measurement lies within ``sigma_max`` of its query measurement.

    Args:
        mode: one of :data:`TOLERANCES`.
        query_points: ``X_q`` in the query left frame (``(M, 3)``, metres).
        ref_points: ``X_r`` in the reference left frame (``(M, 3)``, metres).
        ref_in_query: ``X_r`` in the query left frame (``(M, 3)``, metres).
        ref_from_query: 4x4 transform from the query's to the reference's left frame.
        u_query: largest covariance eigenvalue of ``X_q`` (m^2).
        u_ref: largest covariance eigenvalue of ``X_r`` (m^2).
        camera: the stereo camera of both views.
        sigma_px: image noise, pixels.
        sigma_max: tolerance, in standard deviations.
    """
    m2 = tolerance_sq(mode, query_points, ref_points, ref_in_query, ref_from_query, u_query, u_ref, camera, sigma_px)
    return m2 <= sigma_max * sigma_max


def tolerance_code(mode: str) -> int:
    """The kernels' code (``kernels.MODE_*``) of a tolerance reading; raises ValueError naming the valid ones."""
    try:
        return _MODE_CODES[mode]
    except KeyError:
        raise ValueError(f"tolerance mode {mode!r}; expected one of {TOLERANCES}") from None


def _rows3(points: NDArray[np.floating]) -> NDArray[np.float64]:
    return np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)


def range_limit(view: View, margin_px: float | None) -> float:
    """The largest disparity (pixels) at which ``view`` may speak about a point: its range less the margin.

    inf where ``margin_px`` is ``None`` (the paper: every view speaks about every point) or the view's range
    is unknown.
    """
    if margin_px is None:
        return math.inf
    return view.max_disparity - float(margin_px)
