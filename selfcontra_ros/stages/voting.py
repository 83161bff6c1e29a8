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

One more deviation, on by default in the labeler: no positive label in the
*fattening band* of the query's own disparity map (:func:`fattening_band`),
the pixels with a disparity more than ``edge_jump_px`` below their own close
by. A window-based matcher spreads a foreground disparity a few pixels onto
the background beside an object's edge (foreground fattening), mostly on the
side the right camera cannot see (left of the object in the left image). Such
a fattened point lies a few centimetres beside the object's surface, inside
the depth uncertainty of every reference that sees that surface, and nearby
references repeat the same fattening: the multi-view test confirms it, and
on the synthetic scenes these were most of the wrong positives. Pixels of
the band stay open to negative votes and to Stage 3.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.projection import lookup, splat_nearest, transform
from selfcontra_ros.stages._common import tolerance_sq, within_tolerance
from selfcontra_ros.stages.support import observation_angle_deg
from selfcontra_ros.window import View, support_count

__all__ = ["NEGATIVE_VOTERS", "VotingResult", "consistency_voting", "fattening_band"]

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
    positive_sigma: float | None = None,
    negative_sigma: float | None = None,
) -> NDArray[np.float64]:
    """The vote (0 for none) of one reference view for each valid query pixel ``q_index``.

    A lookup within ``positive_sigma`` votes positive, one beyond ``negative_sigma`` may vote for an
    occlusion; one in between casts no vote (both default to ``sigma_max``, the paper). The splat's
    free-space test keeps ``sigma_max``.
    """
    pos_sq = (sigma_max if positive_sigma is None else positive_sigma) ** 2
    neg_sq = (sigma_max if negative_sigma is None else negative_sigma) ** 2
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
    m2 = tolerance_sq(
        tolerance, x_q[sel], x_r, transform(query_from_ref, x_r), ref_from_query, u_q[sel], u_r[sel], camera, sigma_px
    )
    close = m2 <= pos_sq
    far = m2 > neg_sq
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
    votes[sel] = np.where(positive, np.where(wide, weight, 0.0), np.where(far & in_front, -weight, 0.0))
    # A lookup that agrees has decided this reference's vote even when it does not count, and so has one
    # that agrees only roughly (between the two tolerances): no splat vote then.
    decided = np.zeros(q_index.size, dtype=bool)
    decided[sel] = (~far & accurate) | (far & in_front)

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
    # Free-space violations keep sigma_max: the query point lies behind the reference's surface, where its
    # linearised covariance (u grows as depth^4) is wide, so a wider test would miss most of them.
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


def fattening_band(
    disparity: NDArray[np.floating], *, jump_px: float, occluded_side_px: int, other_px: int
) -> NDArray[np.bool_]:
    """Pixels that may carry foreground fattening: a disparity over ``jump_px`` larger than one close by.

    A pixel is in the band when a valid pixel in the window from ``occluded_side_px`` columns to its left to
    ``other_px`` columns to its right, ``other_px`` rows above and below, has a disparity smaller by more than
    ``jump_px``. The window reaches further left because, in a left disparity map, the background left of
    an object is hidden from the right camera and fattening spreads there furthest.

    Args:
        disparity: HxW left disparity, pixels; non-finite or <= 0 is invalid (never in the band, never a
            neighbour).
        jump_px: disparity drop, pixels, that makes an edge (the 3 px error rule makes ~3-4 natural).
        occluded_side_px: how far left of a pixel to look for a drop, pixels.
        other_px: how far right, up and down to look, pixels.

    Returns:
        HxW bool mask.
    """
    d = np.asarray(disparity, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    filled = np.where(valid, d, np.float32(np.inf)).astype(np.float32)
    kernel = np.ones((2 * other_px + 1, occluded_side_px + other_px + 1), np.uint8)
    # Erosion is a moving minimum; the anchor puts the pixel ``occluded_side_px`` columns from the window's left.
    smallest = cv2.erode(filled, kernel, anchor=(occluded_side_px, other_px), borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore"):
        return valid & (filled - smallest > jump_px)


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
    edge_jump_px: float = 0.0,
    edge_occluded_side_px: int = 16,
    edge_other_px: int = 3,
    positive_sigma: float | None = None,
    negative_sigma: float | None = None,
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
        edge_jump_px: > 0: no positive label in the :func:`fattening_band` of the query's disparity with this
            jump (pixels); 0 = the paper (no band).
        edge_occluded_side_px: the band's reach to the left of a pixel, pixels.
        edge_other_px: the band's reach to the right, up and down, pixels.
        positive_sigma: a reference measurement votes positive only within this many standard deviations
            (the tolerance above); ``None`` = ``sigma_max`` (the paper).
        negative_sigma: a lookup votes for an occlusion only beyond this many standard deviations; ``None`` =
            ``sigma_max`` (the paper). Between the two: no vote. Free-space violations keep ``sigma_max``.
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
            positive_sigma=positive_sigma,
            negative_sigma=negative_sigma,
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
    if edge_jump_px > 0:
        shape = (camera.height, camera.width)
        positive &= ~fattening_band(
            query.disparity.reshape(shape),
            jump_px=edge_jump_px,
            occluded_side_px=edge_occluded_side_px,
            other_px=edge_other_px,
        ).ravel()
    labels[positive] = POSITIVE
    labels[full_voted & (full_sum < 0)] = NEGATIVE
    return VotingResult(vote_sum=full_sum, voted=full_voted, labels=labels)
