"""Stage 1 — support assessment (paper section 3.1, DESIGN section 3).

A reference measurement supports a query measurement ``X_q`` when the
observation angle ``alpha = angle(c_R - X_q, c_Q - X_q)`` between the mean
camera centres exceeds ``alpha_min`` and the reference measurement found by
lookup lies within ``sigma_max`` of ``X_q``. It then activates the angular bin
``floor(alpha / alpha_min)``; ``support`` counts distinct bins, so many views
from one direction count once. Bins are bits of a ``uint64`` mask per pixel,
OR-ed as views arrive.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.projection import lookup, transform
from selfcontra_ros.stages._common import within_tolerance
from selfcontra_ros.window import View

__all__ = ["MAX_BINS", "observation_angle_deg", "support_bits", "update_support"]

#: Bits in the per-pixel mask: bins ``0 .. MAX_BINS - 1``, so ``alpha_min > 180 / (MAX_BINS - 1)`` degrees.
MAX_BINS = 64


def observation_angle_deg(
    points: NDArray[np.float64], centre_a: NDArray[np.float64], centre_b: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Angle (degrees) at each point between the directions to two camera centres (all in one frame, metres)."""
    to_a = centre_a - points
    to_b = centre_b - points
    cos = np.einsum("ij,ij->i", to_a, to_b) / (np.linalg.norm(to_a, axis=-1) * np.linalg.norm(to_b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


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
    """Angular bins (bit mask per query pixel, flat ``(H*W,)``) that ``ref`` activates for ``query``."""
    bits = np.zeros(query.valid.size, dtype=np.uint64)
    q_index = np.flatnonzero(query.valid)
    x_q = query.points[q_index].astype(np.float64)
    ref_from_query = ref.from_view(query)
    found = lookup(x_q, ref_from_query, camera, ref.valid)

    # Both mean centres in the query's left frame.
    centre_q = np.array([0.5 * camera.baseline, 0.0, 0.0])
    centre_r = transform(query.pose_inv, ref.centre[None, :])[0]
    alpha = observation_angle_deg(x_q, centre_r, centre_q)
    keep = found.ok & (alpha > alpha_min_deg)
    q_index, x_q, alpha = q_index[keep], x_q[keep], alpha[keep]
    r_index = found.ref_index[keep]

    x_r = ref.points[r_index].astype(np.float64)
    x_r_in_q = transform(query.from_view(ref), x_r)
    close = within_tolerance(
        tolerance,
        x_q,
        x_r,
        x_r_in_q,
        ref_from_query,
        query.u[q_index],
        ref.u[r_index],
        camera,
        sigma_px,
        sigma_max,
    )
    bins = np.minimum(np.floor(alpha[close] / alpha_min_deg), MAX_BINS - 1).astype(np.uint64)
    bits[q_index[close]] = np.left_shift(np.uint64(1), bins)
    return bits


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
