"""Stage 1 — support assessment (paper section 3.1, DESIGN section 3).

A reference measurement supports a query measurement ``X_q`` when the
observation angle ``alpha = angle(c_R - X_q, c_Q - X_q)`` between the mean
camera centres exceeds ``alpha_min`` and the reference measurement found by
lookup lies within ``sigma_max`` of ``X_q``. It then activates the angular bin
``floor(alpha / alpha_min)``; ``support`` counts distinct bins, so many views
from one direction count once. Bins are bits of a ``uint64`` mask per pixel,
OR-ed as views arrive. Stage 1 is incremental: an arriving view is tested
against each view of the window in both directions (:func:`update_support`),
and nothing already computed is recomputed.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.projection import transform
from selfcontra_ros.stages import kernels
from selfcontra_ros.stages._common import tolerance_code
from selfcontra_ros.window import View

__all__ = ["MAX_BINS", "observation_angle_deg", "support_bits", "update_support"]

#: Bits in the per-pixel mask: bins ``0 .. MAX_BINS - 1``, so ``alpha_min > 180 / (MAX_BINS - 1)`` degrees.
MAX_BINS = 64


def observation_angle_deg(
    points: NDArray[np.float64], centre_a: NDArray[np.float64], centre_b: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Angle (degrees) at each point between the directions to two camera centres (all in one frame, metres)."""
    rows = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return kernels.observation_angle_rows(
        rows, np.asarray(centre_a, dtype=np.float64).reshape(3), np.asarray(centre_b, dtype=np.float64).reshape(3)
    )


def support_bits(
    query: View,
    ref: View,
    camera: StereoCamera,
    *,
    alpha_min_deg: float,
    sigma_max: float,
    sigma_px: float,
    tolerance: str,
) -> NDArray[np.uint64]:
    """Angular bins (bit mask per query pixel, flat ``(H*W,)``) that ``ref`` activates for ``query``.

    One fused pass per query pixel (:func:`selfcontra_ros.stages.kernels.support_bits_kernel`):
    lookup, observation angle, tolerance test, bin.
    """
    # Both mean centres in the query's left frame.
    centre_q = np.array([0.5 * camera.baseline, 0.0, 0.0])
    centre_r = transform(query.pose_inv, ref.centre[None, :])[0]
    return kernels.support_bits_kernel(
        query.points,
        query.valid,
        query.u,
        ref.points,
        ref.valid,
        ref.u,
        ref.from_view(query),
        query.from_view(ref),
        centre_r,
        centre_q,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.width,
        camera.height,
        camera.baseline,
        float(sigma_px),
        float(alpha_min_deg),
        float(sigma_max),
        tolerance_code(tolerance),
        MAX_BINS,
    )


def update_support(
    new: View,
    others: list[View],
    camera: StereoCamera,
    *,
    alpha_min_deg: float,
    sigma_max: float,
    sigma_px: float,
    tolerance: str,
) -> None:
    """Stage 1 for an arriving view: OR the support ``new`` gets from every other view and gives to each, in place."""
    for other in others:
        new.support_bits |= support_bits(
            new, other, camera, alpha_min_deg=alpha_min_deg, sigma_max=sigma_max, sigma_px=sigma_px, tolerance=tolerance
        )
        other.support_bits |= support_bits(
            other, new, camera, alpha_min_deg=alpha_min_deg, sigma_max=sigma_max, sigma_px=sigma_px, tolerance=tolerance
        )
