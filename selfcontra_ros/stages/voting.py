"""Stage 2 — consistency voting (paper section 3.2, DESIGN section 3).

Every reference view votes at most once per query pixel, in this priority:

1. *positive*, from the lookup: the reference measurement lies within
   ``sigma_max`` of ``X_q``: ``+support_r / sqrt(u_r)``;
2. *occlusion*, from the lookup: outside the tolerance and ``X_q`` lies in
   front of ``X_r`` along the reference ray (distance from the reference left
   camera): ``-support_r / sqrt(u_r)``;
3. *free-space violation*, from the z-buffer splat: the nearest reference
   point falling into the query pixel is outside the tolerance and in front of
   ``X_q`` (depth in the query): ``-support_r / sqrt(u_r)``.

Only reference measurements with ``support_r >= 1`` and ``u_r < u_q`` vote;
the splat z-buffer is built from the supported reference points only, so an
unsupported point in front cannot hide a supported one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.projection import lookup, splat_nearest, transform
from selfcontra_ros.stages._common import within_tolerance
from selfcontra_ros.window import View, support_count

__all__ = ["VotingResult", "consistency_voting"]


@dataclass(frozen=True)
class VotingResult:
    """Stage-2 output for one query view, flat ``(H*W,)`` arrays.

    Attributes:
        vote_sum: sum of the votes per pixel (0 where none).
        voted: whether the pixel received at least one vote.
        labels: ``POSITIVE`` where the sum is > 0, ``NEGATIVE`` where < 0, else ``UNKNOWN``.
    """

    vote_sum: NDArray[np.float64]
    voted: NDArray[np.bool_]
    labels: NDArray[np.uint8]


def _reference_votes(
    query: View,
    ref: View,
    camera: StereoCamera,
    q_index: NDArray[np.int64],
    x_q: NDArray[np.float64],
    *,
    sigma_max: float,
    sigma_px: float,
    tolerance: str,
) -> NDArray[np.float64]:
    """The vote (0 for none) of one reference view for each valid query pixel ``q_index``."""
    votes = np.zeros(q_index.size)
    u_q = query.u[q_index].astype(np.float64)
    ref_from_query = ref.from_view(query)
    query_from_ref = query.from_view(ref)
    ref_support = support_count(ref.support_bits)

    # Lookup: positive or occlusion.
    found = lookup(x_q, ref_from_query, camera, ref.valid)
    r_index = found.ref_index
    u_r = ref.u[r_index].astype(np.float64)
    eligible = found.ok & (ref_support[r_index] >= 1) & (u_r < u_q)
    sel = np.flatnonzero(eligible)
    x_r = ref.points[r_index[sel]].astype(np.float64)
    close = within_tolerance(
        tolerance,
        x_q[sel],
        x_r,
        transform(query_from_ref, x_r),
        ref_from_query,
        u_q[sel],
        u_r[sel],
        camera,
        sigma_px,
        sigma_max,
    )
    in_front = np.linalg.norm(found.points_in_ref[sel], axis=-1) < np.linalg.norm(x_r, axis=-1)
    weight = ref_support[r_index[sel]].astype(np.float64) / np.sqrt(u_r[sel])
    votes[sel] = np.where(close, weight, np.where(in_front, -weight, 0.0))

    # Splat: free-space violation where the lookup cast no vote.
    supported = np.flatnonzero(ref.valid & (ref_support >= 1))
    source = splat_nearest(ref.points[supported], supported, query_from_ref, camera)[q_index]
    sel = np.flatnonzero((votes == 0) & (source >= 0))
    s_index = source[sel]
    u_s = ref.u[s_index].astype(np.float64)
    more_accurate = u_s < u_q[sel]
    sel, s_index, u_s = sel[more_accurate], s_index[more_accurate], u_s[more_accurate]
    x_s = ref.points[s_index].astype(np.float64)
    x_s_in_q = transform(query_from_ref, x_s)
    close = within_tolerance(
        tolerance, x_q[sel], x_s, x_s_in_q, ref_from_query, u_q[sel], u_s, camera, sigma_px, sigma_max
    )
    violation = ~close & (x_s_in_q[:, 2] < x_q[sel, 2])
    votes[sel[violation]] = -(ref_support[s_index[violation]].astype(np.float64) / np.sqrt(u_s[violation]))
    return votes


def consistency_voting(
    query: View,
    refs: list[View],
    camera: StereoCamera,
    *,
    sigma_max: float,
    sigma_px: float,
    tolerance: str,
) -> VotingResult:
    """Stage 2 for one query view against the reference views ``refs``."""
    n = query.valid.size
    q_index = np.flatnonzero(query.valid)
    x_q = query.points[q_index].astype(np.float64)
    vote_sum = np.zeros(q_index.size)
    voted = np.zeros(q_index.size, dtype=bool)
    for ref in refs:
        votes = _reference_votes(
            query, ref, camera, q_index, x_q, sigma_max=sigma_max, sigma_px=sigma_px, tolerance=tolerance
        )
        vote_sum += votes
        voted |= votes != 0
    full_sum = np.zeros(n)
    full_sum[q_index] = vote_sum
    full_voted = np.zeros(n, dtype=bool)
    full_voted[q_index] = voted
    labels = np.full(n, UNKNOWN, dtype=np.uint8)
    labels[full_voted & (full_sum > 0)] = POSITIVE
    labels[full_voted & (full_sum < 0)] = NEGATIVE
    return VotingResult(vote_sum=full_sum, voted=full_voted, labels=labels)
