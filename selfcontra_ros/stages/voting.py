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

Options that deviate from the paper (see
:class:`selfcontra_ros.labeler.LabelerParams` for what they measured): a
minimum observation angle for positive votes, a minimum Stage-1 support of the
query pixel for a positive label, negative votes from less accurate references,
switching the free-space votes off (all off by default), and the outline-aware
free-space vote (``free_space_neighbourhood``; the labeler's default is 2 px,
this function's 0 is the paper): a splatted point that agrees with a query
measurement a pixel or two away casts no free-space vote.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.projection import lookup, splat_nearest, transform
from selfcontra_ros.stages._common import within_tolerance
from selfcontra_ros.stages.support import observation_angle_deg
from selfcontra_ros.window import View, support_count

__all__ = ["NEGATIVE_VOTERS", "VotingResult", "consistency_voting"]

#: Which reference measurements may cast a negative vote (``negative_voters``):
#: ``more_accurate`` - only those with ``u_r < u_q``, as for positive votes (paper);
#: ``any`` - every supported one. The contradiction test already allows for the reference's own uncertainty
#: under the ``sum`` tolerance; the paper's accuracy rule discards exactly the evidence against foreground
#: fattening (a too-near query point beside an object edge is more accurate than the background behind it,
#: whose views it would occlude), and keeps it out of the vote.
NEGATIVE_VOTERS = ("more_accurate", "any")


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
    min_angle_deg: float,
    negatives_from_any: bool,
    free_space: bool,
    free_space_neighbourhood: int = 0,
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
    accurate = u_r < u_q
    eligible = found.ok & (ref_support[r_index] >= 1) & (accurate | negatives_from_any)
    sel = np.flatnonzero(eligible)
    accurate = accurate[sel]
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
    wide = np.ones(sel.size, dtype=bool)
    if min_angle_deg > 0:
        # A reference seen from nearly the query's direction repeats the query's systematic error (same
        # image patches, same matching ambiguity), so its agreement is no evidence; its contradictions are.
        centre_q = np.array([0.5 * camera.baseline, 0.0, 0.0])
        centre_r = transform(query.pose_inv, ref.centre[None, :])[0]
        wide = observation_angle_deg(x_q[sel], centre_r, centre_q) > min_angle_deg
    positive = close & accurate
    votes[sel] = np.where(positive, np.where(wide, weight, 0.0), np.where(~close & in_front, -weight, 0.0))
    # A lookup that agrees has decided this reference's vote even when it does not count: no splat vote then.
    decided = np.zeros(q_index.size, dtype=bool)
    decided[sel] = positive | (~close & in_front)

    if not free_space:
        return votes
    # Splat: free-space violation where the lookup cast no vote.
    supported = np.flatnonzero(ref.valid & (ref_support >= 1))
    source = splat_nearest(ref.points[supported], supported, query_from_ref, camera)[q_index]
    sel = np.flatnonzero(~decided & (source >= 0))
    s_index = source[sel]
    u_s = ref.u[s_index].astype(np.float64)
    more_accurate = (u_s < u_q[sel]) | negatives_from_any
    sel, s_index, u_s = sel[more_accurate], s_index[more_accurate], u_s[more_accurate]
    x_s = ref.points[s_index].astype(np.float64)
    x_s_in_q = transform(query_from_ref, x_s)
    close = within_tolerance(
        tolerance, x_q[sel], x_s, x_s_in_q, ref_from_query, u_q[sel], u_s, camera, sigma_px, sigma_max
    )
    violation = ~close & (x_s_in_q[:, 2] < x_q[sel, 2])
    if free_space_neighbourhood > 0:
        # A splatted point that agrees with a query measurement a pixel or two away lies on the query's own
        # surface: an object outline seen from a slightly different direction (or rounded differently into
        # pixels), not evidence that the query's ray passes through occupied space.
        hit = np.flatnonzero(violation)
        outline = _agrees_nearby(
            query,
            camera,
            q_index[sel[hit]],
            x_s[hit],
            x_s_in_q[hit],
            u_s[hit],
            ref_from_query,
            radius=free_space_neighbourhood,
            tolerance=tolerance,
            sigma_px=sigma_px,
            sigma_max=sigma_max,
        )
        violation[hit[outline]] = False
    votes[sel[violation]] = -(ref_support[s_index[violation]].astype(np.float64) / np.sqrt(u_s[violation]))
    return votes


def _agrees_nearby(
    query: View,
    camera: StereoCamera,
    pixels: NDArray[np.int64],
    x_s: NDArray[np.float64],
    x_s_in_q: NDArray[np.float64],
    u_s: NDArray[np.float64],
    ref_from_query: NDArray[np.float64],
    *,
    radius: int,
    tolerance: str,
    sigma_px: float,
    sigma_max: float,
) -> NDArray[np.bool_]:
    """Whether each splatted reference point agrees with a valid query measurement near its query pixel.

    Args:
        query: the query view.
        camera: the stereo camera of both views.
        pixels: flat query pixel each splatted point fell into (``(K,)``).
        x_s: the splatted points in the reference left frame (``(K, 3)``, metres).
        x_s_in_q: the same points in the query left frame (``(K, 3)``, metres).
        u_s: their largest covariance eigenvalues (m^2).
        ref_from_query: 4x4 transform from the query's to the reference's left frame.
        radius: half side of the square neighbourhood, pixels (the pixel itself is not compared again).
        tolerance: reading of "within ``sigma_max``", as for the votes.
        sigma_px: image noise, pixels.
        sigma_max: tolerance, standard deviations.
    """
    agrees = np.zeros(pixels.size, dtype=bool)
    row, col = np.divmod(pixels, camera.width)
    for dr in range(-radius, radius + 1):
        for dc in range(-radius, radius + 1):
            if dr == 0 and dc == 0:
                continue  # the pixel itself was compared by the caller
            r, c = row + dr, col + dc
            inside = (r >= 0) & (r < camera.height) & (c >= 0) & (c < camera.width)
            neighbour = np.where(inside, r * camera.width + c, 0)
            test = np.flatnonzero(inside & query.valid[neighbour] & ~agrees)
            if test.size == 0:
                continue
            near = neighbour[test]
            agrees[test] = within_tolerance(
                tolerance,
                query.points[near].astype(np.float64),
                x_s[test],
                x_s_in_q[test],
                ref_from_query,
                query.u[near].astype(np.float64),
                u_s[test],
                camera,
                sigma_px,
                sigma_max,
            )
    return agrees


def consistency_voting(
    query: View,
    refs: list[View],
    camera: StereoCamera,
    *,
    sigma_max: float,
    sigma_px: float,
    tolerance: str,
    min_angle_deg: float = 0.0,
    min_query_support: int = 0,
    negative_voters: str = "more_accurate",
    free_space_votes: bool = True,
    free_space_neighbourhood: int = 0,
) -> VotingResult:
    """Stage 2 for one query view against the reference views ``refs``.

    Args:
        query: the view to label.
        refs: the other views of the window.
        camera: the stereo camera of all views.
        sigma_max: tolerance, standard deviations.
        sigma_px: image noise, pixels.
        tolerance: reading of "within ``sigma_max``", one of :data:`~selfcontra_ros.stages._common.TOLERANCES`.
        min_angle_deg: a reference casts a *positive* vote only where its observation angle to ``X_q``
            exceeds this (degrees); 0 = the paper (every eligible reference). Negative votes are not limited.
        min_query_support: a pixel is labelled positive only if its own Stage-1 support is at least this;
            otherwise a positive sum leaves it unknown. 0 = the paper.
        negative_voters: which supported reference measurements may vote *negative*, one of
            :data:`NEGATIVE_VOTERS`: ``more_accurate`` (paper: ``u_r < u_q``, like positive votes) or ``any``.
        free_space_votes: whether the splat casts free-space-violation votes (paper: yes). Without them only
            the lookup votes (positive or occlusion).
        free_space_neighbourhood: radius in pixels; a splatted reference point that agrees (within the
            tolerance) with a valid query measurement in the ``(2r+1)^2`` neighbourhood of its query pixel
            casts no free-space vote. 0 = the paper (only the pixel itself is compared).
    """
    n = query.valid.size
    q_index = np.flatnonzero(query.valid)
    x_q = query.points[q_index].astype(np.float64)
    vote_sum = np.zeros(q_index.size)
    voted = np.zeros(q_index.size, dtype=bool)
    for ref in refs:
        votes = _reference_votes(
            query,
            ref,
            camera,
            q_index,
            x_q,
            sigma_max=sigma_max,
            sigma_px=sigma_px,
            tolerance=tolerance,
            min_angle_deg=min_angle_deg,
            negatives_from_any=negative_voters == "any",
            free_space=free_space_votes,
            free_space_neighbourhood=free_space_neighbourhood,
        )
        vote_sum += votes
        voted |= votes != 0
    full_sum = np.zeros(n)
    full_sum[q_index] = vote_sum
    full_voted = np.zeros(n, dtype=bool)
    full_voted[q_index] = voted
    labels = np.full(n, UNKNOWN, dtype=np.uint8)
    positive = full_voted & (full_sum > 0)
    if min_query_support > 0:
        positive &= support_count(query.support_bits) >= min_query_support
    labels[positive] = POSITIVE
    labels[full_voted & (full_sum < 0)] = NEGATIVE
    return VotingResult(vote_sum=full_sum, voted=full_voted, labels=labels)
