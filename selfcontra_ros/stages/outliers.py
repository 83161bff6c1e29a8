"""Stage 3 — outlier detection (paper section 3.3, DESIGN section 3).

For query pixels still unknown after Stage 2:

1. trivial outliers (a valid disparity that does not project into the right
   image, ``u - d < 0``) are negative; pixels without disparity stay unknown;
2. the augmented depth map: per query pixel, all reference points splatting
   into it are candidates, nearest first; the first candidate validated by a
   relaxed vote of every other view (each +1, -1 or nothing, see
   :func:`candidate_tolerance`) with at least ``min_positive_votes`` +1 votes and
   a positive sum gives ``z_aug``;
3. the pixel is negative if ``z_q < z_aug - margin(u_aug)`` (see
   :func:`augmented_margin`), ``u_aug`` being the uncertainty of the augmented
   point as if Q's stereo pair alone measured it.

The two Stage-3 tolerances are read here and only here (:data:`READINGS`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.projection import lookup, pixel_rays, splat_all
from selfcontra_ros.uncertainty import largest_covariance_eigenvalue
from selfcontra_ros.window import View

__all__ = [
    "READINGS",
    "augmented_depth",
    "augmented_margin",
    "candidate_tolerance",
    "outlier_negatives",
    "trivial_outliers",
]

#: Readings of the paper's Stage-3 tolerances. ``std`` (default): standard
#: deviations in metres, ``(sqrt(u_a) + sqrt(u_r)) * sigma_max`` and
#: ``sigma_max * sqrt(u_aug)``. ``paper``: the literal formulas
#: ``(1/sqrt(u_a) + 1/sqrt(u_r)) * sigma_max`` and ``sigma_max / sqrt(u_aug)``
#: (units of 1/metre; kept for reproduction, DESIGN section 3).
READINGS = ("std", "paper")


def candidate_tolerance(
    u_candidate: NDArray[np.floating], u_ref: NDArray[np.floating], sigma_max: float, reading: str
) -> NDArray[np.float64]:
    """Border (metres along the reference ray) between a +1 and a -1/none vote for an augmented-depth candidate.

    ``u_candidate`` is the candidate's uncertainty as seen from the query pair
    (the candidate is a depth hypothesis on the query ray), ``u_ref`` that of
    the voting reference measurement, both m^2.
    """
    if reading == "std":
        return (np.sqrt(u_candidate) + np.sqrt(u_ref)) * sigma_max
    if reading == "paper":
        return (1.0 / np.sqrt(u_candidate) + 1.0 / np.sqrt(u_ref)) * sigma_max
    raise ValueError(f"stage3 tolerance reading {reading!r}; expected one of {READINGS}")


def augmented_margin(u_aug: NDArray[np.floating], sigma_max: float, reading: str) -> NDArray[np.float64]:
    """How far (metres) the query depth must lie in front of the augmented depth to be negative."""
    if reading == "std":
        return sigma_max * np.sqrt(u_aug)
    if reading == "paper":
        return sigma_max / np.sqrt(u_aug)
    raise ValueError(f"stage3 tolerance reading {reading!r}; expected one of {READINGS}")


@lru_cache(maxsize=4)
def _rays(camera: StereoCamera) -> NDArray[np.float64]:
    return pixel_rays(camera)


def trivial_outliers(query: View, camera: StereoCamera) -> NDArray[np.bool_]:
    """Valid query pixels (flat) whose point does not project into the right image (``u - d < 0``).

    A valid disparity is > 0, so its depth is never behind the camera; the
    invalid pixels (no disparity at all) are not outliers.
    """
    columns = np.tile(np.arange(camera.width, dtype=np.float32), camera.height)
    with np.errstate(invalid="ignore"):
        return query.valid & (columns - query.disparity.ravel() < 0)


def _relaxed_votes(
    points: NDArray[np.float64],
    u_candidate: NDArray[np.float64],
    query: View,
    voters: list[View],
    camera: StereoCamera,
    sigma_max: float,
    reading: str,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(number of +1 votes, vote sum) of every voter for candidate points (query left frame, metres)."""
    plus = np.zeros(points.shape[0], dtype=np.int64)
    total = np.zeros(points.shape[0], dtype=np.int64)
    for view in voters:
        found = lookup(points, view.from_view(query), camera, view.valid)
        sel = np.flatnonzero(found.ok)
        r_index = found.ref_index[sel]
        range_candidate = np.linalg.norm(found.points_in_ref[sel], axis=-1)
        range_ref = np.linalg.norm(view.points[r_index].astype(np.float64), axis=-1)
        tol = candidate_tolerance(u_candidate[sel], view.u[r_index].astype(np.float64), sigma_max, reading)
        agree = np.abs(range_candidate - range_ref) <= tol
        # In front of the reference surface: the candidate would block that view's line of sight.
        blocks = ~agree & (range_candidate < range_ref)
        plus[sel] += agree
        total[sel] += agree.astype(np.int64) - blocks
    return plus, total


def augmented_depth(
    query: View,
    refs: list[View],
    pending: NDArray[np.bool_],
    camera: StereoCamera,
    *,
    sigma_max: float,
    sigma_px: float,
    reading: str,
    min_positive_votes: int,
) -> NDArray[np.float64]:
    """Augmented depth (metres, flat ``(H*W,)``, NaN where no valid candidate) for the ``pending`` query pixels.

    Candidates are processed in rounds by their rank in depth order per
    pixel; a pixel leaves the rounds at its first valid candidate, so the
    nearest valid one wins and far candidates of settled pixels are never voted on.
    """
    n = query.valid.size
    z_aug = np.full(n, np.nan)
    pix_parts, depth_parts = [], []
    for ref in refs:
        src = np.flatnonzero(ref.valid)
        splat = splat_all(ref.points[src], src, query.from_view(ref), camera)
        keep = pending[splat.query_index]
        pix_parts.append(splat.query_index[keep])
        depth_parts.append(splat.depth[keep])
    if not pix_parts:
        return z_aug
    pix = np.concatenate(pix_parts)
    depth = np.concatenate(depth_parts)
    if pix.size == 0:
        return z_aug
    order = np.lexsort((depth, pix))
    pix, depth = pix[order], depth[order]
    group_start = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]])
    group_size = np.diff(np.r_[group_start, pix.size])
    rank = np.arange(pix.size) - np.repeat(group_start, group_size)
    by_rank = np.argsort(rank, kind="stable")
    bounds = np.searchsorted(rank[by_rank], np.arange(int(rank.max()) + 2))
    rays = _rays(camera)
    resolved = np.zeros(n, dtype=bool)
    for k in range(bounds.size - 1):
        idx = by_rank[bounds[k] : bounds[k + 1]]
        idx = idx[~resolved[pix[idx]]]
        if idx.size == 0:
            continue
        points = depth[idx, None] * rays[pix[idx]]
        u_candidate = largest_covariance_eigenvalue(points, camera, sigma_px)
        plus, total = _relaxed_votes(points, u_candidate, query, refs, camera, sigma_max, reading)
        valid = (plus >= min_positive_votes) & (total > 0)
        z_aug[pix[idx[valid]]] = depth[idx[valid]]
        resolved[pix[idx[valid]]] = True
    return z_aug


def outlier_negatives(
    query: View,
    z_aug: NDArray[np.float64],
    pending: NDArray[np.bool_],
    camera: StereoCamera,
    *,
    sigma_max: float,
    sigma_px: float,
    reading: str,
) -> NDArray[np.bool_]:
    """Pending query pixels (flat) whose depth lies in front of the augmented depth by more than the margin."""
    has = pending & np.isfinite(z_aug)
    sel = np.flatnonzero(has)
    points = z_aug[sel, None] * _rays(camera)[sel]
    u_aug = largest_covariance_eigenvalue(points, camera, sigma_px)
    z_q = query.points[sel, 2].astype(np.float64)
    negative = np.zeros(pending.size, dtype=bool)
    negative[sel] = z_q < z_aug[sel] - augmented_margin(u_aug, sigma_max, reading)
    return negative
