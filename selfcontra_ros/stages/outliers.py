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

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.stages import kernels
from selfcontra_ros.stages._common import range_limit
from selfcontra_ros.window import View

__all__ = [
    "READINGS",
    "augmented_depth",
    "augmented_margin",
    "candidate_tolerance",
    "free_space_witnesses",
    "outlier_negatives",
    "trivial_outliers",
]

#: Readings of the paper's Stage-3 tolerances. ``std`` (default): standard
#: deviations in metres, ``(sqrt(u_a) + sqrt(u_r)) * sigma_max`` and
#: ``sigma_max * sqrt(u_aug)``. ``paper``: the literal formulas
#: ``(1/sqrt(u_a) + 1/sqrt(u_r)) * sigma_max`` and ``sigma_max / sqrt(u_aug)``
#: (units of 1/metre; kept for reproduction, DESIGN section 3).
READINGS = ("std", "paper")

_READING_CODES = {"std": kernels.READING_STD, "paper": kernels.READING_PAPER}


def candidate_tolerance(
    u_candidate: NDArray[np.floating], u_ref: NDArray[np.floating], sigma_max: float, reading: str
) -> NDArray[np.float64]:
    """Border (metres along the reference ray) between a +1 and a -1/none vote for an augmented-depth candidate.

    ``u_candidate`` is the candidate's uncertainty as seen from the query pair
    (the candidate is a depth hypothesis on the query ray), ``u_ref`` that of
    the voting reference measurement, both m^2. The formula of each reading is
    :func:`selfcontra_ros.stages.kernels.candidate_tolerance_scalar`, which the
    augmented-depth kernel calls too.
    """
    u_c, u_r = np.broadcast_arrays(np.asarray(u_candidate, dtype=np.float64), np.asarray(u_ref, dtype=np.float64))
    out = kernels.candidate_tolerance_rows(
        np.ascontiguousarray(u_c).reshape(-1),
        np.ascontiguousarray(u_r).reshape(-1),
        float(sigma_max),
        _reading(reading),
    )
    return out.reshape(u_c.shape)


def augmented_margin(u_aug: NDArray[np.floating], sigma_max: float, reading: str) -> NDArray[np.float64]:
    """How far (metres) the query depth must lie in front of the augmented depth to be negative.

    The formula of each reading is :func:`selfcontra_ros.stages.kernels.augmented_margin_scalar`.
    """
    u = np.asarray(u_aug, dtype=np.float64)
    out = kernels.augmented_margin_rows(np.ascontiguousarray(u).reshape(-1), float(sigma_max), _reading(reading))
    return out.reshape(u.shape)


def _reading(reading: str) -> int:
    """The kernels' code of a Stage-3 reading; raises ValueError naming the valid ones."""
    try:
        return _READING_CODES[reading]
    except KeyError:
        raise ValueError(f"stage3 tolerance reading {reading!r}; expected one of {READINGS}") from None


class _Scratch(threading.local):
    """Per-thread work buffers of :func:`augmented_depth`, by name (contents never outlive one call)."""

    def __init__(self) -> None:
        self.buffers: dict[str, NDArray[Any]] = {}


_SCRATCH = _Scratch()


def _scratch(name: str, shape: tuple[int, ...], dtype: type[np.generic]) -> NDArray[Any]:
    """A C-contiguous buffer of ``shape`` for this thread, reused while the views keep their size.

    Holds at most one buffer per name: the largest number of views (first axis) seen so far, sliced.
    """
    buffer = _SCRATCH.buffers.get(name)
    if buffer is None or buffer.dtype != dtype or buffer.shape[1:] != shape[1:] or buffer.shape[0] < shape[0]:
        buffer = np.empty(shape, dtype=dtype)
        _SCRATCH.buffers[name] = buffer
    return buffer[: shape[0]]


def trivial_outliers(query: View, camera: StereoCamera) -> NDArray[np.bool_]:
    """Valid query pixels (flat) whose point does not project into the right image (``u - d < 0``).

    A valid disparity is > 0, so its depth is never behind the camera; the
    invalid pixels (no disparity at all) are not outliers.
    """
    columns = np.tile(np.arange(camera.width, dtype=np.float32), camera.height)
    with np.errstate(invalid="ignore"):
        return query.valid & (columns - query.disparity.ravel() < 0)


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
    range_margin_px: float | None = None,
) -> NDArray[np.float64]:
    """Augmented depth (metres, flat ``(H*W,)``, NaN where no valid candidate) for the ``pending`` query pixels.

    Candidates of a pixel are all reference points splatting into it
    (:func:`~selfcontra_ros.stages.kernels.splat_into_pending`), nearest
    first; the first one validated by the relaxed vote of every reference
    (:func:`~selfcontra_ros.stages.kernels.candidate_is_valid`) wins, and
    farther candidates of that pixel are never voted on. The nearest
    candidate is voted on first for all pixels; only pixels where it fails
    sort their other candidates. With ``range_margin_px`` (see
    :func:`~selfcontra_ros.stages._common.range_limit`) a reference casts no vote on a candidate beyond its
    disparity range.
    """
    pending = np.ascontiguousarray(pending, dtype=np.bool_).reshape(-1)
    if not refs or not pending.any():
        return np.full(pending.size, np.nan)
    code = _reading(reading)
    # Stacked copies (about 8 MB per view at KITTI size): indexing one 3-D array in the kernels' inner loops
    # costs nothing, while a list of arrays costs a reference-count update per access. The copies go into
    # per-thread buffers kept between calls: fresh arrays of this size are mapped anew by every allocation, and
    # touching their pages for the first time cost more than the copies themselves (measured 57-158 ms against
    # 4 ms for nine views' points).
    v, n = len(refs), pending.size
    ref_points = np.stack([ref.points for ref in refs], out=_scratch("points", (v, n, 3), np.float32))
    ref_valid = np.stack([ref.valid for ref in refs], out=_scratch("valid", (v, n), np.bool_))
    ref_u = np.stack([ref.u for ref in refs], out=_scratch("u", (v, n), np.float32))
    query_from_ref = np.stack([query.from_view(ref) for ref in refs])
    ref_from_query = np.stack([ref.from_view(query) for ref in refs])
    geometry = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    pixel = _scratch("pixel", (v, n), np.int32)
    depth = _scratch("depth", (v, n), np.float64)
    kernels.splat_into_pending(pixel, depth, pending, ref_points, ref_valid, query_from_ref, *geometry)
    best = kernels.nearest_candidate(pixel, depth, pending.size)
    vote = (ref_points, ref_valid, ref_u, ref_from_query, *geometry, camera.baseline)
    limits = np.array([range_limit(ref, range_margin_px) for ref in refs])
    rest = (float(sigma_px), float(sigma_max), code, int(min_positive_votes), limits)
    # Round 1: each pixel's nearest candidate (on the synthetic street it is the validated one for 97 % of pixels).
    z_aug, retry = kernels.vote_nearest(best, *vote, *rest)
    if retry.any():
        # Later rounds, only for pixels whose nearest candidate failed: their farther ones, nearest first.
        start, sorted_depth = kernels.group_candidates(pixel, depth, retry)
        kernels.vote_farther(z_aug, best, start, sorted_depth, *vote, *rest)
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
    refs: list[View] | None = None,
    min_free_space_views: int = 0,
    min_depth_ratio: float = 1.0,
    range_margin_px: float | None = None,
    reliable_witnesses: bool = False,
) -> NDArray[np.bool_]:
    """Pending query pixels (flat) whose depth lies in front of the augmented depth by more than the margin.

    One pass per pixel (:func:`selfcontra_ros.stages.kernels.outlier_negatives_kernel`); the margin is
    :func:`augmented_margin` of ``u_aug``, the augmented point's uncertainty as seen by Q's pair alone.
    With ``min_free_space_views > 0`` (a deviation, see ``LabelerParams.stage3_min_free_space_views``)
    such a pixel stays negative only where at least that many of ``refs`` see through its point
    (:func:`free_space_witnesses`). With ``min_depth_ratio > 1`` (a deviation, see
    ``LabelerParams.stage3_min_depth_ratio``) it must also lie in front by that factor:
    ``z_aug >= min_depth_ratio * z_q``.
    """
    negative = kernels.outlier_negatives_kernel(
        np.ascontiguousarray(query.points[:, 2]),
        np.ascontiguousarray(z_aug, dtype=np.float64).reshape(-1),
        np.ascontiguousarray(pending, dtype=np.bool_).reshape(-1),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.width,
        camera.baseline,
        float(sigma_px),
        float(sigma_max),
        _reading(reading),
    )
    if min_depth_ratio > 1:
        pixels = np.flatnonzero(negative)
        query_depth = query.points[pixels, 2].astype(np.float64)
        agreed_depth = np.asarray(z_aug, dtype=np.float64).reshape(-1)[pixels]
        negative[pixels[agreed_depth < min_depth_ratio * query_depth]] = False
    if min_free_space_views > 0:
        if refs is None:
            raise ValueError("outlier_negatives: min_free_space_views > 0 needs the references (refs)")
        pixels = np.flatnonzero(negative)
        witnesses = free_space_witnesses(
            query,
            refs,
            pixels,
            camera,
            sigma_max=sigma_max,
            reading=reading,
            range_margin_px=range_margin_px,
            reliable_only=reliable_witnesses,
        )
        negative[pixels[witnesses < min_free_space_views]] = False
    return negative


def free_space_witnesses(
    query: View,
    refs: list[View],
    pixels: NDArray[np.integer],
    camera: StereoCamera,
    *,
    sigma_max: float,
    reading: str,
    range_margin_px: float | None = None,
    reliable_only: bool = False,
) -> NDArray[np.int32]:
    """How many of ``refs`` see through the query point of each flat pixel index in ``pixels``.

    A reference sees through ``X_q`` where ``X_q`` projects onto one of its
    valid measurements lying behind ``X_q`` along its ray by more than
    :func:`candidate_tolerance` of the two uncertainties (the free-space
    violation of DESIGN section 3, counted per view). Stage 3 calls ``X_q`` an
    outlier because a surface the views agree on lies behind it; a view that
    looked through ``X_q``'s place is the evidence that nothing stands there. With ``range_margin_px``
    (see :func:`~selfcontra_ros.stages._common.range_limit`) a view in which ``X_q`` lies beyond its
    disparity range is no witness: its matcher could not have seen ``X_q``, so it measures something
    farther whether ``X_q`` is there or not. With ``reliable_only`` only the references' reliable
    measurements (``View.reliable``, as for Stage-2 votes) witness.
    """
    pixels = np.ascontiguousarray(pixels, dtype=np.int64)
    count = np.zeros(pixels.size, dtype=np.int32)
    code = _reading(reading)
    for ref in refs:
        kernels.free_space_witnesses_kernel(
            count,
            pixels,
            query.points,
            query.u,
            ref.points[None],
            (ref.reliable if reliable_only else ref.valid)[None],
            ref.u[None],
            ref.from_view(query),
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            camera.width,
            camera.height,
            float(sigma_max),
            code,
            camera.fx * camera.baseline,
            range_limit(ref, range_margin_px),
        )
    return count
