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
switching the free-space votes off (all off by default), the outline-aware
free-space vote (``free_space_neighbourhood``; the labeler's default is 2 px,
this function's 0 is the paper): a splatted point that agrees with a query
measurement a pixel or two away casts no free-space vote, and a hysteresis
(``positive_sigma`` / ``negative_sigma``; the labeler's defaults 1.5 / 3, this
function's ``None`` is ``sigma_max`` for both, the paper): a lookup votes
positive only within the first, for an occlusion only beyond the second, and
not at all in between; free-space violations keep ``sigma_max``.

One more deviation, on by default in the labeler: no positive label in the
*fattening band* of the query's own disparity map (:func:`fattening_band`),
the pixels with a valid neighbour close by whose disparity is more than
``edge_jump_px`` below their own. A window-based matcher spreads a foreground disparity a few pixels onto
the background beside an object's edge (foreground fattening), mostly on the
side the right camera cannot see (left of the object in the left image). Such
a fattened point lies a few centimetres beside the object's surface, inside
the depth uncertainty of every reference that sees that surface, and nearby
references repeat the same fattening: the multi-view test confirms it, and
on the synthetic scenes these were most of the wrong positives. Pixels of
the band stay open to negative votes and to Stage 3. The same band of each
*reference* (``free_space_band``, on in the labeler) keeps that reference's
fattened points out of the free-space z-buffer, where they would vote against
the correct background they float in front of. In the band a negative may
also ask for more than one view voting against it (``band_min_negative_views``;
the labeler's default 2, this function's 1 is the paper). Last, a pixel no
reference voted on may be confirmed by views less accurate than itself
(``fallback_accuracy_ratio``, ``fallback_min_views``; off here, the paper): such
agreement never casts a vote, so it gives positives only where the paper's rule
has no evidence at all.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.projection import transform
from selfcontra_ros.stages import kernels
from selfcontra_ros.stages._common import range_limit, tolerance_code
from selfcontra_ros.window import View, support_count

__all__ = [
    "NEGATIVE_VOTERS",
    "OCCLUSION_VOTES",
    "VotingResult",
    "band_background",
    "band_backgrounds",
    "consistency_voting",
    "contradicted_positives",
    "fattening_band",
    "hole_margin",
    "view_band",
]

#: Which reference measurements may cast a negative vote (``negative_voters``):
#: ``more_accurate`` - only those with ``u_r < u_q``, as for positive votes (paper);
#: ``any`` - every supported one. The contradiction test already allows for the reference's own uncertainty
#: under the ``sum`` tolerance; the paper's accuracy rule discards exactly the evidence against foreground
#: fattening (a too-near query point beside an object edge is more accurate than the background behind it,
#: whose views it would occlude), and keeps it out of the vote;
#: ``band`` - every supported one for the query pixels in the query's own :func:`fattening_band` (where that
#: evidence matters, and which can never be positive), the more accurate ones elsewhere. Needs
#: ``edge_jump_px > 0``; otherwise it is ``more_accurate``.
NEGATIVE_VOTERS = ("more_accurate", "any", "band")

#: Where a lookup's occlusion (``X_q`` in front of the reference's measured surface) casts a negative vote
#: (``occlusion_votes``): ``everywhere`` (paper), or only in the query's own :func:`fattening_band` (``band``;
#: needs ``edge_jump_px > 0``, otherwise it is ``everywhere``). Outside the band the occlusion still decides
#: the reference's vote, as no vote.
OCCLUSION_VOTES = ("everywhere", "band")

# The lookup kernel's fallback counter when there is none (never written: its ratio is then 0).
_NO_FALLBACK = np.zeros(0, dtype=np.int32)


@dataclass(frozen=True)
class VotingResult:
    """Stage-2 output for one query view, flat ``(H*W,)`` arrays.

    Attributes:
        vote_sum: sum of the votes per pixel (0 where none).
        voted: whether the pixel received at least one vote.
        labels: ``POSITIVE`` where the sum is > 0 (or, unvoted, by the fallback of less accurate views),
            ``NEGATIVE`` where < 0, else ``UNKNOWN``.
    """

    vote_sum: NDArray[np.float64]
    voted: NDArray[np.bool_]
    labels: NDArray[np.uint8]


def _reference_votes(
    vote_sum: NDArray[np.float64],
    voted: NDArray[np.bool_],
    query: View,
    ref: View,
    camera: StereoCamera,
    *,
    sigma_max: float,
    sigma_px: float,
    mode: int,
    positive_sigma: float,
    negative_sigma: float,
    min_angle_deg: float,
    negatives_from_any: NDArray[np.bool_],
    occlusion_votes: NDArray[np.bool_],
    free_space: bool,
    free_space_neighbourhood: int,
    splat_bits: NDArray[np.uint64] | None = None,
    free_space_sum: NDArray[np.float64] | None = None,
    free_space_voted: NDArray[np.bool_] | None = None,
    positive_accuracy_ratio: float = 1.0,
    fallback_views: NDArray[np.int32] | None = None,
    fallback_accuracy_ratio: float = 1.0,
    disparity_limit: float = math.inf,
) -> None:
    """Add the vote (if any) of one reference view to every valid query pixel, in place (flat ``(H*W,)``).

    A lookup within ``positive_sigma`` votes positive, one beyond ``negative_sigma`` may vote for an
    occlusion; one in between casts no vote. The splat's free-space test keeps ``sigma_max``. Three compiled
    passes: the lookup (:func:`selfcontra_ros.stages.kernels.lookup_votes_kernel`), then, for the pixels it left
    undecided, the z-buffer splat of the supported reference points
    (:func:`selfcontra_ros.stages.kernels.splat_supported_kernel`) and the free-space test
    (:func:`selfcontra_ros.stages.kernels.free_space_votes_kernel`). ``splat_bits`` (default the reference's
    ``support_bits``) are the support the splat and its votes use: zero leaves a reference point out.
    ``negatives_from_any`` (flat, per query pixel): where any supported reference measurement may vote negative,
    not only a more accurate one. ``occlusion_votes`` (flat, per query pixel): where a lookup's occlusion votes.
    ``free_space_sum`` / ``free_space_voted`` (flat, both or neither): where the
    free-space votes go instead of ``vote_sum`` / ``voted``. ``positive_accuracy_ratio``: a lookup votes
    positive where ``u_r < positive_accuracy_ratio * u_q`` (1: only a more accurate one, the paper).
    ``fallback_views`` (flat int32, or ``None``): one is added where a measurement that may not vote positive,
    but is less accurate by under ``fallback_accuracy_ratio``, agrees; it casts no vote.
    ``disparity_limit``: where ``X_q``'s disparity in the reference exceeds this (pixels), the reference casts no
    vote at all (inf: the paper).
    """
    ref_from_query = ref.from_view(query)
    query_from_ref = query.from_view(ref)
    geometry = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    # Both mean centres in the query's left frame, for the observation angle of min_angle_deg.
    centre_q = np.array([0.5 * camera.baseline, 0.0, 0.0])
    centre_r = transform(query.pose_inv, ref.centre[None, :])[0]
    pending = np.zeros(query.valid.size, dtype=bool)
    kernels.lookup_votes_kernel(
        vote_sum,
        voted,
        pending,
        query.points,
        query.valid,
        query.u,
        ref.points,
        ref.valid,
        ref.u,
        ref.support_bits,
        ref_from_query,
        query_from_ref,
        centre_r,
        centre_q,
        *geometry,
        camera.baseline,
        float(sigma_px),
        mode,
        float(positive_sigma) ** 2,
        float(negative_sigma) ** 2,
        float(min_angle_deg),
        negatives_from_any,
        float(positive_accuracy_ratio),
        occlusion_votes,
        _NO_FALLBACK if fallback_views is None else fallback_views,
        0.0 if fallback_views is None else float(fallback_accuracy_ratio),
        float(disparity_limit),
    )
    if not free_space:
        return
    # The splat's voters: the reference's support unless the caller leaves more of its points out.
    bits = ref.support_bits if splat_bits is None else splat_bits
    # The z-buffer only for the pixels the lookup left undecided.
    source = kernels.splat_supported_kernel(ref.points, ref.valid, bits, query_from_ref, pending, *geometry)
    kernels.free_space_votes_kernel(
        vote_sum if free_space_sum is None else free_space_sum,
        voted if free_space_voted is None else free_space_voted,
        pending,
        source,
        query.points,
        query.valid,
        query.u,
        ref.points,
        ref.u,
        bits,
        ref_from_query,
        query_from_ref,
        camera.width,
        camera.height,
        camera.fx,
        camera.fy,
        camera.baseline,
        float(sigma_px),
        mode,
        # Free-space violations keep sigma_max: the query point lies behind the reference's surface, where its
        # linearised covariance (u grows as depth^4) is wide, so a wider test would miss most of them.
        float(sigma_max) * float(sigma_max),
        negatives_from_any,
        int(free_space_neighbourhood),
    )


def fattening_band(
    disparity: NDArray[np.floating],
    *,
    jump_px: float,
    occluded_side_px: int,
    other_px: int,
    below_px: int | None = None,
) -> NDArray[np.bool_]:
    """Pixels that may carry foreground fattening: a disparity over ``jump_px`` larger than one close by.

    A pixel is in the band when a valid pixel in the window from ``occluded_side_px`` columns to its left to
    ``other_px`` columns to its right, ``other_px`` rows above and below, has a disparity smaller by more than
    ``jump_px``. The window reaches further left because, in a left disparity map, the background left of
    an object is hidden from the right camera and fattening spreads there furthest. With ``below_px`` the
    window also takes the ``below_px`` rows below the pixel, ``other_px`` columns either side: a single-pass
    semi-global matcher (OpenCV's ``MODE_SGBM`` and ``MODE_SGBM_3WAY``, the package's default) aggregates
    costs only along paths that run left to right, right to left or downward, so it carries an object's
    disparity down onto a weakly textured background below the object's lower edge, and never up.

    Args:
        disparity: HxW left disparity, pixels; non-finite or <= 0 is invalid (never in the band, never a
            neighbour).
        jump_px: disparity drop, pixels, that makes an edge (the 3 px error rule makes ~3-4 natural).
        occluded_side_px: how far left of a pixel to look for a drop, pixels.
        other_px: how far right, up and down to look, pixels.
        below_px: how far down to look straight below the pixel (``other_px`` columns either side), pixels;
            None, or not above ``other_px``: ``other_px``.

    Returns:
        HxW bool mask.
    """
    d = np.asarray(disparity, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    window = (occluded_side_px, other_px, other_px if below_px is None else below_px)
    (smallest,) = band_backgrounds(d, [window])
    with np.errstate(invalid="ignore"):
        return valid & (d - smallest > jump_px)


def band_background(disparity: NDArray[np.floating], *, occluded_side_px: int, other_px: int) -> NDArray[np.float32]:
    """The smallest valid disparity in each pixel's :func:`fattening_band` window (HxW float32; inf: none).

    For a band pixel this is the background level beyond its disparity drop: the disparity a fattened pixel
    should have had.
    """
    (smallest,) = band_backgrounds(disparity, [(occluded_side_px, other_px)])
    return smallest


def band_backgrounds(
    disparity: NDArray[np.floating], windows: Iterable[tuple[int, int] | tuple[int, int, int]]
) -> Iterator[NDArray[np.float32]]:
    """:func:`band_background` for each ``(occluded_side_px, other_px[, below_px])`` of ``windows``, in order.

    ``below_px`` adds the strip of :func:`fattening_band`'s ``below_px``. The invalid pixels are set to inf
    once for all windows (that copy costs more than a window's minimum).
    """
    d = np.asarray(disparity, dtype=np.float32)
    filled = np.where(np.isfinite(d) & (d > 0), d, np.float32(np.inf)).astype(np.float32)
    for window in windows:
        occluded_side_px, other_px = window[0], window[1]
        kernel = np.ones((2 * other_px + 1, occluded_side_px + other_px + 1), np.uint8)
        # Erosion is a moving minimum; the anchor puts the pixel ``occluded_side_px`` columns from the window's
        # left.
        smallest = cv2.erode(filled, kernel, anchor=(occluded_side_px, other_px), borderType=cv2.BORDER_REPLICATE)
        below_px = window[2] if len(window) > 2 else other_px
        if below_px > other_px:
            # The strip below: the pixel's row and the below_px rows under it, other_px columns either side.
            strip = np.ones((below_px + 1, 2 * other_px + 1), np.uint8)
            below = cv2.erode(filled, strip, anchor=(other_px, 0), borderType=cv2.BORDER_REPLICATE)
            smallest = np.minimum(smallest, below)
        yield np.asarray(smallest, dtype=np.float32)


def hole_margin(disparity: NDArray[np.floating], margin_px: float) -> NDArray[np.bool_]:
    """Valid pixels within ``margin_px`` (Euclidean, pixels) of a *hole* in the disparity map (HxW bool).

    A hole is an invalid pixel (non-finite or <= 0) right of its row's first valid one: a place inside the
    matched area where the query algorithm found no disparity (a surface nearer than its disparity range, a
    saturated window, a textureless patch whose best cost sat at disparity 0). Each row's leading invalid run
    (the left strip a matcher cannot match, or a row with no match at all) is not a hole.
    """
    d = np.asarray(disparity, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    holes = ~valid & (np.cumsum(valid, axis=1) > 0)
    if margin_px <= 0 or not holes.any():
        return np.zeros(d.shape, dtype=bool)
    distance = cv2.distanceTransform((~holes).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return valid & (distance <= np.float32(margin_px))


def contradicted_positives(labels: NDArray[np.uint8], radius_px: int, share: float) -> NDArray[np.bool_]:
    """Positive pixels whose surroundings the views contradicted (HxW bool).

    A positive pixel is returned where more than ``share`` of the labelled pixels (positive or negative, the
    pixel itself included) in the ``(2 radius_px + 1)^2`` square around it are negative. The query
    algorithm's errors are spatially coherent (SGM fills a textureless wall or the fringe of a failed match
    from the same wrong evidence), so a region the multi-view test contradicts is a failing region, and a pixel
    in it that the views confirmed was most often confirmed by the same mistake repeated. ``share >= 1``
    returns nothing.

    Raises:
        ValueError: if ``labels`` is not 2-D or ``radius_px`` is negative.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"labels must be HxW, got shape {labels.shape}")
    if radius_px < 0:
        raise ValueError(f"radius_px must be >= 0, got {radius_px}")
    positive = labels == POSITIVE
    if share >= 1 or not positive.any():
        return np.zeros(labels.shape, dtype=bool)
    size = (2 * int(radius_px) + 1,) * 2
    negative = labels == NEGATIVE
    # Unnormalised box sums are exact integer counts in float32 (windows of far fewer than 2^24 pixels).
    negatives = cv2.boxFilter(negative.astype(np.float32), -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    labelled = (positive | negative).astype(np.float32)
    counted = cv2.boxFilter(labelled, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    return positive & (negatives > np.float32(share) * counted)


def view_band(
    view: View,
    camera: StereoCamera,
    jump_px: float,
    occluded_side_px: int,
    other_px: int,
    below_px: int | None = None,
) -> NDArray[np.bool_]:
    """The :func:`fattening_band` of a view's disparity (flat), computed once per view and size (``View.bands``).

    A ``below_px`` of None or not above ``other_px`` is the symmetric band and shares its cache entry.
    """
    below = int(other_px if below_px is None else max(below_px, other_px))
    key = (float(jump_px), int(occluded_side_px), int(other_px), below)
    band = view.bands.get(key)
    if band is None:
        band = fattening_band(
            view.disparity.reshape(camera.height, camera.width),
            jump_px=jump_px,
            occluded_side_px=occluded_side_px,
            other_px=other_px,
            below_px=below,
        ).ravel()
        view.bands[key] = band
    return band


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
    abstain_ambiguous: bool = True,
    free_space_band: bool = False,
    hole_margin_px: float = 0.0,
    free_space_min_views: int = 1,
    positive_accuracy_ratio: float = 1.0,
    occlusion_votes: str = "everywhere",
    band_min_negative_views: int = 1,
    fallback_accuracy_ratio: float = 1.0,
    fallback_min_views: int = 2,
    range_margin_px: float | None = None,
    edge_below_px: int | None = None,
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
            :data:`NEGATIVE_VOTERS`: ``more_accurate`` (paper: ``u_r < u_q``, like positive votes), ``any``, or
            ``band`` (any inside the query's fattening band of ``edge_jump_px``, more accurate elsewhere).
        free_space_votes: whether the splat casts free-space-violation votes (paper: yes). Without them only
            the lookup votes (positive or occlusion).
        free_space_neighbourhood: radius in pixels; a splatted reference point that agrees (within the
            tolerance) with a valid query measurement in the ``(2r+1)^2`` neighbourhood of its query pixel
            casts no free-space vote. 0 = the paper (only the pixel itself is compared).
        edge_jump_px: > 0: no positive label in the :func:`fattening_band` of the query's disparity with this
            jump (pixels); 0 = the paper (no band).
        edge_occluded_side_px: the band's reach to the left of a pixel, pixels.
        edge_other_px: the band's reach to the right, up and down, pixels.
        edge_below_px: the band's reach down for the positive rule alone, pixels (the band's other uses keep
            ``edge_other_px``); ``None`` = ``edge_other_px``.
        positive_sigma: a reference measurement votes positive only within this many standard deviations
            (the tolerance above); ``None`` = ``sigma_max`` (the paper).
        negative_sigma: a lookup votes for an occlusion only beyond this many standard deviations; ``None`` =
            ``sigma_max`` (the paper). Between the two: no vote. Free-space violations keep ``sigma_max``.
        abstain_ambiguous: query pixels the view marks unreliable (``View.reliable``) are never positive;
            false: only the references' unreliable pixels are left out (they never vote). Query pixels the
            view marks clipped (``View.clipped``, saturated grey values) are never positive either way.
        free_space_band: with ``edge_jump_px > 0``, a reference point in the reference's own
            :func:`fattening_band` is left out of the free-space z-buffer (it is the reference's foreground
            fattening, floating in front of correct background); false = the paper.
        hole_margin_px: > 0: no positive label within this many pixels of a hole in the query's disparity
            (:func:`hole_margin`); 0 = the paper.
        free_space_min_views: outside the query's own fattening band (of ``edge_jump_px``; without it, everywhere)
            a pixel's free-space votes count only where at least this many reference views cast one; inside the
            band one is enough. 1 = the paper.
        positive_accuracy_ratio: a reference measurement may vote *positive* where ``u_r`` is below this many
            times ``u_q`` (>= 1); 1 = the paper (only a more accurate one). Negative votes keep
            ``negative_voters``.
        occlusion_votes: where a lookup's occlusion (``X_q`` in front of the reference's measured surface)
            votes negative, one of :data:`OCCLUSION_VOTES`: ``everywhere`` (paper) or ``band`` (only in the
            query's fattening band of ``edge_jump_px``).
        band_min_negative_views: in the query's own fattening band (of ``edge_jump_px``), a negative sum
            labels a pixel negative only where at least this many reference views cast a negative vote
            (occlusion or free-space) on it; otherwise it stays unknown. 1 = the paper (any negative sum).
        fallback_accuracy_ratio: > ``positive_accuracy_ratio``: a pixel that no reference voted on is
            positive where at least ``fallback_min_views`` references less accurate than that ratio allows, but
            by under this many times ``u_q``, agree within ``positive_sigma`` (and the angle); such agreement
            casts no vote, so every vote and every other label is that of the paper's rule. 1 = the paper (off).
            The query's own match must be reliable (``View.reliable``) whatever ``abstain_ambiguous``; the
            positive label's other conditions (band, hole margin, support) apply alike.
        fallback_min_views: the agreeing less accurate references a fallback positive needs (>= 1).
        range_margin_px: not ``None``: a reference casts no vote on a query point whose disparity in it
            would exceed its ``View.max_disparity`` minus this margin (pixels): its matcher could not have
            measured that point, so its measurement there says nothing about it. ``None`` = the paper.
    """
    n = query.valid.size
    mode = tolerance_code(tolerance)
    if not positive_accuracy_ratio >= 1.0:
        raise ValueError(f"positive_accuracy_ratio must be >= 1, got {positive_accuracy_ratio}")
    if negative_voters not in NEGATIVE_VOTERS:
        raise ValueError(f"negative_voters must be one of {NEGATIVE_VOTERS}, got {negative_voters!r}")
    if occlusion_votes not in OCCLUSION_VOTES:
        raise ValueError(f"occlusion_votes must be one of {OCCLUSION_VOTES}, got {occlusion_votes!r}")
    if band_min_negative_views < 1:
        raise ValueError(f"band_min_negative_views must be >= 1, got {band_min_negative_views}")
    if fallback_min_views < 1:
        raise ValueError(f"fallback_min_views must be >= 1, got {fallback_min_views}")
    # The query's own fattening band (none without edge_jump_px), which several rules below read.
    query_band = (
        view_band(query, camera, edge_jump_px, edge_occluded_side_px, edge_other_px)
        if edge_jump_px > 0
        else np.zeros(n, dtype=bool)
    )
    if negative_voters == "any":
        from_any = np.ones(n, dtype=bool)
    elif negative_voters == "band":
        from_any = query_band
    else:
        from_any = np.zeros(n, dtype=bool)
    occluding = query_band if occlusion_votes == "band" and edge_jump_px > 0 else np.ones(n, dtype=bool)
    full_sum = np.zeros(n)
    full_voted = np.zeros(n, dtype=bool)
    # Free-space votes apart when the number of views casting them matters: their sum over the references, and
    # per reference which pixels got one (a reference casts at most one per pixel).
    counted = free_space_votes and free_space_min_views > 1
    fs_sum = np.zeros(n) if counted else None
    fs_voted = np.zeros(n, dtype=bool) if counted else None
    fs_views = np.zeros(n, dtype=np.int32)
    # Per pixel, how many references voted negative (only where the band asks for more than one): each reference's
    # votes go to arrays of their own first (a reference casts at most one vote per pixel, so adding them to the
    # sums afterwards gives the very same sums).
    counting = band_min_negative_views > 1 and edge_jump_px > 0
    negative_views = np.zeros(n, dtype=np.int32) if counting else None
    ref_sum = np.zeros(n) if counting else full_sum
    ref_voted = np.zeros(n, dtype=bool) if counting else full_voted
    # Per pixel, how many less accurate references agree (only where the fallback positive is on).
    fallback = np.zeros(n, dtype=np.int32) if fallback_accuracy_ratio > positive_accuracy_ratio else None
    # One reference after the other, as the paper sums votes: the sums do not depend on how pixels are split
    # between threads.
    for ref in refs:
        # Only the reference's reliable measurements vote (window.ambiguous_pixels): an unsupported
        # measurement never votes, so masking the support is enough.
        gated = ref
        if not ref.reliable[ref.valid].all():
            gated = dataclasses.replace(ref, support_bits=np.where(ref.reliable, ref.support_bits, np.uint64(0)))
        splat_bits = None
        if free_space_band and edge_jump_px > 0:
            band = view_band(ref, camera, edge_jump_px, edge_occluded_side_px, edge_other_px)
            splat_bits = np.where(band, np.uint64(0), gated.support_bits)
        _reference_votes(
            ref_sum,
            ref_voted,
            query,
            gated,
            camera,
            sigma_max=sigma_max,
            sigma_px=sigma_px,
            mode=mode,
            positive_sigma=sigma_max if positive_sigma is None else positive_sigma,
            negative_sigma=sigma_max if negative_sigma is None else negative_sigma,
            min_angle_deg=min_angle_deg,
            negatives_from_any=from_any,
            occlusion_votes=occluding,
            free_space=free_space_votes,
            free_space_neighbourhood=free_space_neighbourhood,
            splat_bits=splat_bits,
            free_space_sum=fs_sum,
            free_space_voted=fs_voted,
            positive_accuracy_ratio=positive_accuracy_ratio,
            fallback_views=fallback,
            fallback_accuracy_ratio=fallback_accuracy_ratio,
            disparity_limit=range_limit(ref, range_margin_px),
        )
        if negative_views is not None:
            negative_views += ref_sum < 0
            full_sum += ref_sum
            full_voted |= ref_voted
            ref_sum.fill(0.0)
            ref_voted.fill(False)
        if fs_voted is not None:
            if negative_views is not None:
                negative_views += fs_voted  # a free-space vote is always negative
            fs_views += fs_voted
            fs_voted.fill(False)
    if fs_sum is not None:
        enough = (fs_views >= free_space_min_views) | query_band
        keep = enough & (fs_views > 0)
        full_sum[keep] += fs_sum[keep]
        full_voted |= keep
    labels = np.full(n, UNKNOWN, dtype=np.uint8)
    positive = full_voted & (full_sum > 0)
    if fallback is not None:
        # Weaker evidence than a vote: the query's own match must be unambiguous too (View.reliable).
        positive |= ~full_voted & (fallback >= fallback_min_views) & query.reliable
    if abstain_ambiguous:
        positive &= query.reliable  # an ambiguous match abstains from positives
    if query.clipped is not None:
        positive &= ~query.clipped  # a saturated pixel's match comes from its neighbours' texture
    if min_query_support > 0:
        positive &= support_count(query.support_bits) >= min_query_support
    if edge_jump_px > 0:
        # The band as the positive rule sees it (the symmetric query_band itself without a longer reach down).
        positive &= ~view_band(query, camera, edge_jump_px, edge_occluded_side_px, edge_other_px, edge_below_px)
    if hole_margin_px > 0:
        positive &= ~hole_margin(query.disparity.reshape(camera.height, camera.width), hole_margin_px).ravel()
    labels[positive] = POSITIVE
    negative = full_voted & (full_sum < 0)
    if negative_views is not None:
        negative &= ~query_band | (negative_views >= band_min_negative_views)
    labels[negative] = NEGATIVE
    return VotingResult(vote_sum=full_sum, voted=full_voted, labels=labels)
