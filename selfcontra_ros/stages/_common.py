"""Tests shared by the stages: is a reference measurement within ``sigma_max`` of a query measurement?"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.uncertainty import mahalanobis_sq, mahalanobis_sq_sum

__all__ = ["TOLERANCES", "within_tolerance"]

#: Readings of "within sigma_max" (DESIGN section 3):
#: ``query``   - Mahalanobis distance under the query point's covariance (paper, Stage 2);
#: ``smaller`` - under the covariance of whichever point has the smaller ``u`` (paper, Stage 1);
#: ``sum``     - ``dX^T (C_q + C_r)^-1 dX``, the test for two noisy measurements of one point.
TOLERANCES = ("query", "smaller", "sum")


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
    delta = ref_in_query - query_points
    limit = sigma_max * sigma_max
    if mode == "query":
        return mahalanobis_sq(query_points, delta, camera, sigma_px) <= limit
    rotation_rq = ref_from_query[:3, :3]
    if mode == "smaller":
        m_query = mahalanobis_sq(query_points, delta, camera, sigma_px)
        m_ref = mahalanobis_sq(ref_points, delta @ rotation_rq.T, camera, sigma_px)
        return np.where(u_query <= u_ref, m_query, m_ref) <= limit
    if mode == "sum":
        return mahalanobis_sq_sum(query_points, ref_points, rotation_rq.T, delta, camera, sigma_px) <= limit
    raise ValueError(f"tolerance mode {mode!r}; expected one of {TOLERANCES}")
