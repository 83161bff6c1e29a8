"""The self-contradiction labeler: a sliding window of views and the three stages.

One :class:`Labeler` per stereo camera. Feed it one disparity map and pose
per frame with :meth:`Labeler.add_view`; it keeps the last ``window_size``
kept views, runs Stage 1 (support) incrementally as each view arrives, and
labels a view once ``label_delay`` newer views have arrived (Stages 2 and 3
against every other view then in the window). :meth:`Labeler.flush` labels the
views still waiting at the end of a sequence. No ROS import: the offline
command and the ROS node both call this object.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Hashable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, UNKNOWN
from selfcontra_ros.matching.base import to_grey
from selfcontra_ros.stages._common import TOLERANCES
from selfcontra_ros.stages.outliers import READINGS, augmented_depth, outlier_negatives, trivial_outliers
from selfcontra_ros.stages.support import MAX_BINS, update_support
from selfcontra_ros.stages.voting import NEGATIVE_VOTERS, OCCLUSION_VOTES, consistency_voting, contradicted_positives
from selfcontra_ros.window import (
    TEXTURE_MEASURES,
    View,
    ViewWindow,
    ambiguous_pixels,
    make_view,
    saturated_pixels,
    support_count,
)

__all__ = ["CROSS_CHECK_MATCHERS", "LabelResult", "Labeler", "LabelerParams"]

#: Values of ``LabelerParams.cross_check_matcher`` (:mod:`selfcontra_ros.cross_check`); ``none`` is the paper.
CROSS_CHECK_MATCHERS = ("none", "census_sgm")


@dataclass(frozen=True)
class LabelerParams:
    """Parameters of the labeler; the defaults are the package defaults (``config/labeler.yaml`` mirrors them).

    Attributes:
        window_size: views kept in the sliding window (memory is bounded by it).
            Default 20 (the paper labelled KITTI with 21 views, the labelled
            one in the middle): at KITTI's ~1 m per frame a view then sees the
            scene from up to ~10 m before and after. On forward motion most
            pixels only reach angles above ``alpha_min`` with such a baseline;
            on the synthetic street a window of 10 left about half the
            coverage (16 % against 30 % on 20 frames) at lower accuracy.
            About 10 MB per view at KITTI size.
        label_delay: a view is labelled when this many newer views have
            arrived (``0 <= label_delay < window_size``). Default 10, half the
            window: the labelled view sits in the middle of its references, so
            views from both sides of it (forward motion: behind and ahead) vote.
        alpha_min_deg: minimum observation angle and angular bin width, degrees.
            Default 7 (deviation; paper: 10). On forward motion the angle is
            what leaves a pixel unlabelled: on the street's tuning seeds 37 %
            of the evaluated pixels had correct depth, no Stage-1 support and
            no vote, most of them at 3-20 px of disparity. Swept on tuning
            seeds 1-10 at 613x185 (accuracy / coverage / positive precision,
            %, means; the worst sequence's positive precision): 10 -> 8 -> 7
            -> 5 gave street 98.79 / 31.65 / 99.64 -> 98.92 / 37.77 / 99.62 ->
            98.95 / 40.50 / 99.61 -> 98.98 / 45.66 / 99.56, room 98.54 / 31.46
            / 99.23 (worst 98.16) -> 98.59 / 34.26 / 99.24 (97.72) -> 98.63 /
            35.49 / 99.28 (97.68) -> 98.61 / 37.73 / 99.20 (96.61), orbit
            98.35 / 65.59 / 98.45 -> 98.22 / 68.16 / 98.31 -> 98.17 / 69.15 /
            98.26 -> 98.11 / 70.59 / 98.20. At KITTI size (street and room
            seeds 1-5), 10 -> 7: street 97.72 / 28.92 / 99.49 -> 97.93 / 35.98
            / 99.41, room 96.33 / 32.11 / 99.44 -> 96.46 / 33.96 / 99.44.
            What a smaller angle costs: views closer in direction repeat more
            of the query's errors, and the new wrong positives are those
            (orbit: the far ground at the horizon, true disparity about 1 px
            matched at 4-5 px; room seed 4: a horizontal window sill, 7 px
            too near); 7 is where room's worst sequence stopped losing
            (8: 97.72, 7: 97.68, 5: 96.61 %) while street still gained.
        sigma_max: tolerance in standard deviations (paper: 2).
        sigma_px: isotropic image noise, pixels, for the point covariances.
        stage1_tolerance: ``sum`` (default: ``dX^T (C_q + C_r)^-1 dX``, more
            coverage, slightly lower accuracy) or ``smaller`` (paper:
            covariance of the more accurate point); ``query`` is accepted
            too. Measured with the Stage-2 defaults (seed 1, 20 labelled
            frames, cached SGBM runs): street 98.4 / 32.2 with ``smaller``
            -> 97.4 / 45.5 with ``sum`` (accuracy / coverage, %), orbit
            98.8 / 61.1 -> 98.8 / 71.5.
        stage2_tolerance: ``sum`` (default, DESIGN section 3) or ``query``
            (paper: the query covariance alone); ``smaller`` is accepted too.
        stage3_tolerance: ``std`` (tolerances as standard deviations, metres;
            DESIGN section 3) or ``paper`` (the literal formulas).
        stage2_min_angle_deg: degrees; a reference casts a *positive* Stage-2
            vote only where its observation angle to ``X_q`` exceeds this
            (deviation from the paper, which lets every supported, more
            accurate reference vote; 0 = the paper). Rationale: the paper's
            own argument for Stage 1 (views from nearly the same direction
            share systematic errors); negative votes are not limited because
            a shared error cannot make two views contradict.
        stage2_min_query_support: a pixel is labelled positive only if its own
            Stage-1 support is at least this; a positive vote sum without it
            leaves the pixel unknown (and open to Stage 3). 0 = the paper.
        stage2_negative_voters: ``more_accurate`` (paper: negative votes, like
            positive ones, only from references with ``u_r < u_q``) or ``any``
            (every supported reference may vote negative; the contradiction is
            still tested against ``sigma_max`` with the tolerance above, which
            under ``sum`` includes the reference's uncertainty). Deviation
            aimed at foreground fattening: a too-near query point beside an
            object edge is more accurate than the background it hides, so the
            paper's rule silences exactly the views it occludes. ``band``
            (default): ``any`` for the query pixels inside the query's own
            fattening band (``stage2_edge_*``; they can never be positive),
            ``more_accurate`` elsewhere; without ``stage2_edge_jump_px`` it is
            ``more_accurate``. Label benchmark, seeds 1-10 at 613x185,
            ``more_accurate`` -> ``band`` (accuracy / coverage / positive /
            negative precision / bad recall, %): street 97.87 / 33.17 / 99.22
            / 72.0 / 15.3 -> 97.74 / 33.34 / 99.22 / 73.0 / 17.6, orbit 98.08
            / 68.27 / 98.30 / 68.3 / 6.7 -> 98.02 / 68.48 / 98.30 / 73.1 /
            10.5, room 97.66 / 34.15 / 98.19 / 96.7 / 38.6 -> 97.49 / 34.53 /
            98.19 / 96.3 / 39.5 (room's worst sequence 95.17 -> 94.30: there
            the new negatives are about two thirds right); the Ensemble
            forest's self / ground-truth AUSC ratio street 1.342 -> 1.339,
            orbit 2.771 -> 2.533, room 1.062 -> 1.053. Held out (seeds 11-13,
            1226x370): street 96.40 / 30.54 / 98.62 / 83.0 / 21.1 -> 96.30 /
            30.87 / 98.62 / 83.1 / 22.6, orbit 98.79 / 63.36 / 99.07 / 63.9 /
            7.0 -> 98.70 / 63.54 / 99.07 / 64.8 / 9.5, room 95.49 / 34.95 /
            96.42 / 95.0 / 40.6 -> 95.44 / 36.25 / 96.42 / 94.9 / 42.9: a
            tenth of a point of accuracy for a third more of orbit's wrong
            pixels found. Everywhere outside the band the votes are those of
            ``more_accurate``.
        stage2_occlusion_votes: where a lookup's *occlusion* (``X_q`` in front
            of the reference's measured surface by more than
            ``stage2_negative_sigma``) votes negative: ``everywhere`` (the
            paper) or ``band`` (default): only for the query pixels in the
            query's own fattening band (``stage2_edge_*``); elsewhere the
            occlusion decides the reference's vote as no vote. Deviation:
            outside the band a query error is rarely a too-near point (that
            is foreground fattening, which the band holds), so a reference
            that sees farther than ``X_q`` there has mostly mismeasured
            itself: a surface nearer than its range, horizontal stripes or
            wood grain that only the query matched (the aperture problem), a
            textureless patch filled from the background. Per pixel
            (tuning seeds at 1226x370: street 1, 2, 4, 5, orbit 1, 2, 4, 5,
            room 1, 5, 7, 10; a throwaway script counting, per Stage-2
            negative, the references whose lookup found an occlusion):
            outside the band 42 200 of these negatives sat on right depth
            and 11 900 on wrong depth (78 % wrong; room seed 5 alone 21 100
            of 26 700), and more views did not make them right (3 or more
            views: 6 400 wrong, 1 400 right); in the band 90 % were right.
            Label benchmark, tuning seeds 1-10 at 1226x370,
            ``everywhere`` -> ``band`` (accuracy / coverage / positive /
            negative precision / bad recall, %, means; worst accuracy and
            negative precision): street 98.16 / 37.14 / 99.41 / 78.03 /
            19.98 (95.95, 59.86) -> 98.27 / 37.16 / 99.39 / 80.29 / 19.82
            (96.11, 63.70); orbit 99.03 / 64.32 / 99.22 / 78.10 / 9.72
            (98.44, 67.46) -> 99.05 / 64.33 / 99.22 / 79.91 / 9.66 (98.46,
            68.92); room 96.72 / 34.65 / 99.60 / 94.98 / 39.33 (93.29,
            90.97) -> 96.84 / 34.73 / 99.60 / 95.14 / 39.31 (94.27, 92.06).
            What it costs: a pixel whose only contradiction was such an
            occlusion is unknown, or positive where positive votes remain
            (street's positive precision -0.02 points). Held-out figures
            and the forest's in ``docs/label_quality.md``.
        stage2_free_space_votes: whether the Stage-2 splat casts free-space
            violation votes (paper and default: true). Off, a query point
            lying *behind* the references' surface is never negative in
            Stage 2 (nor in Stage 3, which only flags points in front), so
            the paper's reading stays the default.

        Measured on the synthetic scenes (seed 1, raw SGBM sgbm_3way, DESIGN
        section 8 metrics; accuracy / coverage, %), the four Stage-2 options
        above against the defaults: ``stage2_min_angle_deg: 10`` street 20
        frames 84.9 / 8.1 (defaults 96.1 / 30.3: on forward motion most
        references lie within 10 degrees), orbit 20 frames 94.1 / 43.9
        (defaults 95.4 / 61.9); ``stage2_negative_voters: any`` street 94.3 /
        31.2, orbit 93.5 / 63.0 (more wrong negatives); adding
        ``stage2_min_query_support: 1`` changed nothing measurable; positive
        precision stayed within 0.3 points in all of them.
        ``stage2_free_space_votes: false``: street 20 frames 96.4 / 29.6, orbit
        12 frames 96.4 / 51.0 (defaults 95.6 / 51.4; Stage-2 negative
        precision on orbit 43 % -> 70 %: most free-space votes there fall on
        correct background beside objects, from references' foreground
        fattening and silhouette points splatted onto it).
        stage2_free_space_neighbourhood: radius, pixels (default 2; 0 = the
            paper). A splatted reference point that agrees, within the Stage-2
            tolerance, with a valid query measurement in the ``(2r+1)^2``
            neighbourhood of the query pixel it falls into casts no free-space
            vote there. Deviation: such a point lies on the query's own
            surface, an object outline seen from another direction or a
            reference's foreground fattening by a pixel or two, not in the
            query's line of sight; a query point behind the surface finds no
            agreeing neighbour and stays negative. Measured (30 frames, same
            setup; accuracy / coverage / positive precision / negative
            precision, %): street 94.77 / 33.79 / 97.39 / 62.2 with 0 ->
            95.30 / 33.10 / 97.28 / 62.8 with 2; orbit 95.15 / 65.99 / 96.43 /
            38.9 -> 95.66 / 65.71 / 96.29 / 46.0. On 15 frames radius 1 gave
            street 96.11 / 21.87 and orbit 95.96 / 56.37, radius 2 96.20 /
            21.82 and 96.10 / 56.32, radius 3 96.22 / 21.81 and 96.16 / 56.29
            (0: 95.60 / 22.03 and 95.57 / 56.56): the tolerance itself stops
            the test at about two pixels sideways, so 3 adds little for twice
            the neighbours.
            Tried against fattened positives and not kept: a positive vote
            only where the reference's row neighbours (1 or 2 px either side
            of the lookup pixel) agree with ``X_q`` as well; 15 frames with
            radius 2 above, row 1: street 96.18 / 21.45, positive precision
            99.00 (98.91 without), orbit 96.17 / 55.68, 96.75 (96.63); row 2:
            street 96.00 / 20.18 / 99.14, orbit 96.28 / 54.58 / 96.91. It
            removes true edge positives as much as fattened ones.
        stage2_free_space_band: whether a reference point inside the
            reference's own fattening band (:func:`~selfcontra_ros.stages.voting.fattening_band`
            of the reference's disparity, with the ``stage2_edge_*`` sizes)
            is left out of the free-space z-buffer (default true; false =
            the paper; without ``stage2_edge_jump_px`` it does nothing). Such
            a point is the reference's foreground fattening: it floats in
            front of the background beside an object, and splatted into the
            query it lands on correct background pixels, which it would vote
            negative. Measured by the source of every negative (seeds 1-5
            at 613x185): on ``orbit`` 61 % of the negatives came from
            free-space votes and 82 % of those sat on correct depth (errors
            median 0.7 px); the band removed 67 % of those votes. Label
            benchmark, seeds 1-10 at 613x185, false -> true (accuracy /
            coverage / positive / negative precision, %): street 97.75 /
            33.26 / 99.26 / 68.8 -> 97.87 / 33.17 / 99.22 / 72.0, orbit
            97.70 / 68.43 / 98.31 / 45.5 -> 98.08 / 68.27 / 98.30 / 68.3,
            room 97.48 / 34.34 / 98.26 / 95.9 -> 97.66 / 34.15 / 98.19 / 96.7.
            The remaining free-space negatives on ``orbit`` (a third) are
            still mostly wrong: they come from correct reference points whose
            depth error, seen from a view tens of degrees away, moves them a
            pixel or more sideways past an object's outline; a wider
            ``stage2_free_space_neighbourhood`` (4, 7) removed them in
            proportion, right and wrong alike (77 % wrong either way).
        stage2_free_space_min_views: outside the query pixel's own
            fattening band (``stage2_edge_*``), its free-space votes count
            only where at least this many reference views cast one (1: the
            paper); in the band, where the splat finds foreground
            fattening, one is enough. Measured by source (seeds 1, 4, 6 of
            ``orbit`` at 613x185): Stage-2 negatives outside the band were
            29 % of all negatives and 84 % wrong, two thirds of every wrong
            negative, and 96 % of them had free-space votes alone: single
            views whose correct points, a pixel off past an object's
            outline, land in front of the query's surface. A query point
            truly behind the surface (too far: the wall of
            ``test_patch_behind_surface_is_negative``) is seen through by
            many views. Label benchmark, seeds 1-10 at 613x185, with
            ``stage2_hole_margin_px: 4``, 1 -> 2 -> 3 (default) -> free-space
            votes only in the band (negative precision, its worst sequence /
            bad recall / accuracy, %): orbit 73.10, 55.1 / 10.53 / 98.12 ->
            83.64, 74.0 / 10.34 / 98.23 -> 86.01, 77.4 / 10.28 / 98.25 ->
            (with an 8 px margin) 86.94, 79.3 / 10.19; street 73.00 / 17.63
            / 97.89 -> 72.92 / 17.49 / 97.89 -> 72.87 / 17.43 / 97.89;
            room 96.32 / 39.45 / 97.61 -> 96.48 / 39.39 / 97.64 -> 96.50 /
            39.36 / 97.64; coverage within 0.1 point.
        stage2_band_min_negative_views: in the query pixel's own fattening
            band (``stage2_edge_*``), a negative vote sum labels it negative
            only where at least this many reference views voted against it
            (occlusion or free space); with fewer it stays unknown (and open
            to Stage 3). 1 = the paper; default 2. Deviation: in the band any
            supported view may vote negative (``stage2_negative_voters:
            band``), and a single one is weak evidence there: per pixel
            (1226x370, a throwaway script over the Stage-2 votes) the band's
            negatives cast by one view alone were 57 % right on street seed
            1, 44 % on orbit seed 1 and 82 % on room seed 51 (where they were
            42 % of the wrong negatives, 76 % of their votes from a view whose
            own depth was wrong at that pixel), against 85-100 % right with two
            views or more. The forest loses nothing by it: training draws
            the band's unlabelled pixels as negatives anyway
            (:func:`~selfcontra_ros.confidence.training.band_negatives`). The
            contradicted-region rule (``contradicted_share``) still counts
            the held-back negatives. Label benchmark, tuning seeds 1-10 at
            1226x370, 1 -> 2 (accuracy / coverage / positive / negative
            precision, %, mean; worst accuracy): street 98.25 / 39.38 / 99.43
            / 79.3 (95.96) -> 98.62 / 39.01 / 99.43 / 85.4 (96.62); orbit
            99.15 / 66.74 / 99.34 / 78.9 (98.66) -> 99.27 / 66.61 / 99.34 /
            89.7 (98.88); room 96.85 / 37.89 / 99.61 / 94.9 (94.33) -> 97.18
            / 37.42 / 99.61 / 95.4 (95.46). Bad recall falls by about a point
            (street 18.4, orbit 8.5, room 38.8 %). 3 on room seed 51 (held
            out): accuracy 95.89 against 95.58 at 2 and 94.00 at 1, coverage
            30.79 against 31.69 and 33.89 %.
        stage2_hole_margin_px: pixels; no Stage-2 positive label on a query
            pixel this near (Euclidean) to a *hole* in its own disparity map
            (:func:`~selfcontra_ros.stages.voting.hole_margin`: an invalid
            pixel right of its row's first valid one), 0 = the paper.
            Default 4. Deviation: where the query algorithm found no
            disparity at all inside the matched area (a surface nearer than
            its range, a textureless patch whose best cost sat at disparity
            0, an occlusion), its neighbours are the fringe of that failure,
            filled by SGM's smoothness from the same wrong evidence; nearby
            views make the same mistake, so the votes confirm them. The
            pixels stay open to negative votes and Stage 3. Per pixel
            (tuning seeds at 1226x370: room 5 and 10, street 4 and 5, orbit
            1 and 4), the wrong positives lie a median 8 px from a hole, the
            right ones 19 px (room); margin 0 / 4 / 8 px, coverage /
            positive precision, %: room 33.70 / 95.74 -> 33.14 / 97.07 ->
            31.98 / 98.19, street 25.70 / 98.78 -> 25.20 / 99.04 -> 23.97 /
            99.30, orbit 59.59 / 98.98 -> 57.01 / 99.18 -> 51.91 / 99.38.
            Label benchmark, seeds 1-10 at 613x185, 0 -> 4 -> 8 px
            (accuracy / coverage / positive precision, worst sequence's
            positive precision, %): street 97.74 / 33.34 / 99.22, 97.66 ->
            97.89 / 32.63 / 99.43, 97.96 -> 97.95 / 31.27 / 99.62, 98.57;
            orbit 98.02 / 68.48 / 98.30, 97.13 -> 98.12 / 66.18 / 98.41,
            97.27 -> 98.23 / 61.79 / 98.54, 97.40; room 97.49 / 34.53 /
            98.19, 95.08 -> 97.61 / 33.98 / 98.46, 96.33 -> 97.72 / 32.68 /
            98.79, 96.85. 8 px would leave ``orbit`` (many occlusion holes
            beside correct, textured objects) 1.8 points above its 60 %
            coverage target on the tuning seeds; 4 keeps most of the gain
            for a third of the cost. Restricting the margin to low texture,
            to holes of 10 px or more, or leaving out holes a foreground
            edge explains (occlusions) each kept less precision than it
            saved coverage. A hole-free map (e.g. a matcher that fills
            everything) makes it a no-op.
        contradicted_share: after Stage 3, a positive label is withdrawn
            (unknown) where more than this share of the labelled pixels in
            the square around it are negative
            (:func:`~selfcontra_ros.stages.voting.contradicted_positives`;
            trivial outliers do not count). Default 0.1; 1 = the paper.
            Deviation: the query algorithm's errors are spatially coherent
            (SGM fills a textureless wall, the fringe of a failed match or
            the panel under a shelf board from the same wrong evidence), and
            nearby views repeat them, so inside a region the multi-view test
            contradicts, a pixel the views confirm was most often confirmed
            by the same mistake. Per pixel on the tuning seeds (1-10 at
            613x185, labels of the defaults before it; share of the wrong /
            right positives withdrawn, then mean positive precision, its
            worst sequence, coverage, %), half-width 16 px (2.6 deg):
            share 0.05: room 73 / 13, 99.45, 98.47, 31.44; street 43 / 4,
            99.73, 99.23, 31.32; 0.1: room 60 / 8.5, 99.24, 98.18, 32.26;
            street 35 / 2.1, 99.68, 99.04, 31.93; orbit 3.5 / 0.7, 98.46,
            97.33, 65.60; 0.2: room 41 / 4.1, 99.00, 97.51, 33.10; street
            22 / 0.9, 99.60, 98.78, 32.33 (without: room 98.44, 96.28, 33.94;
            street 99.43, 97.96, 32.62; orbit 98.40, 97.27, 66.11). A
            half-width of 8 px withdrew fewer wrong positives for the same
            coverage (room at 0.05: 48 / 5.8), 32 px right positives beside
            any negative region (room at 0.1: 76 / 20). Label benchmark,
            held-out seeds 11-13 at 1226x370, 1 -> 0.1 (accuracy /
            coverage / positive precision, its worst sequence, %): street
            96.49 / 30.23 / 98.89, 98.60 -> 96.78 / 28.88 / 99.42, 99.39;
            orbit 99.04 / 60.96 / 99.24, 99.18 -> 99.07 / 60.49 / 99.27,
            99.20; room 95.68 / 35.73 / 97.05, 94.04 -> 96.02 / 32.53 /
            99.19, 98.18. On real KITTI 06 it withdraws 4.3 of 31.1 points
            of positives (negatives unchanged): the sky and vegetation
            around trees and poles are negative regions there. The
            symmetric rule (a negative withdrawn where positives surround
            it) was measured the same way and not added: +0.2 points of
            accuracy, and it withdraws the isolated wrong pixels a
            confidence measure must learn to find.
        contradicted_radius_deg: half-width of that square as an angle,
            degrees (``round(fx tan(angle))`` pixels: 16 px at 613x185, 32
            px at KITTI's 1226x370), so the rule means the same at any image
            size: the query algorithm's failing regions grow with the
            resolution.
        stage2_positive_accuracy_ratio: a reference measurement may vote
            positive in Stage 2 where its ``u`` is below this many times the
            query's (>= 1; 1 = the paper, default: only a more accurate
            one). Negative votes keep ``stage2_negative_voters``. Why it
            exists: with the 7-degree angle, 16 % of street's evaluated
            pixels (tuning seeds, 613x185) had correct depth and Stage-1
            support but no vote, three quarters of them near points whose
            only supported, reliable lookups were less accurate views (a
            camera moving forward loses a near point at the image border
            from its newer, closer views). Tuning seeds 1-10 at 613x185,
            1 -> 2 -> 4 -> 16 (accuracy / coverage / positive precision,
            its worst sequence / bad recall, %): street 98.95 / 40.50 /
            99.61, 99.22 / 15.6 -> 99.04 / 50.15 / 99.55, 99.01 / 15.1 ->
            99.05 / 52.96 / 99.49, 98.91 / 14.6 -> 99.01 / 54.34 / 99.41,
            98.58 / 14.2; orbit 98.17 / 69.15 / 98.26, 97.14 / 9.6 ->
            98.11 / 79.05 / 98.14, 97.02 / 7.1 -> 98.08 / 79.61 / 98.09,
            96.97 / 6.9 -> 98.07 / 79.66 / 98.09, 96.97 / 6.9; room 98.63 /
            35.49 / 99.28, 97.68 / 38.0 -> 98.84 / 39.05 / 99.15, 97.17 /
            37.9 -> 98.84 / 39.32 / 99.13, 97.02 / 37.9 (16 as 4). Not the
            default: every scene's positive precision fell, orbit lost 2.5
            points of bad recall (its vote sums turn positive where
            negatives were), and the forest trained on the labels did not
            gain (label benchmark's ``--confidence``, self / ground-truth
            AUSC ratio, 1 -> 2: street 1.342 -> 1.363, orbit 2.689 -> 2.762,
            room 1.038 -> 1.044; over forest seeds 0-2 street's ratio at 1
            spans 1.342-1.348, orbit's 2.602-2.689).
        stage2_fallback_accuracy_ratio: a query pixel that *no* reference
            voted on (no more accurate view agreed or contradicted) is
            positive where at least ``stage2_fallback_min_views`` less
            accurate references, each with ``u_r`` under this many times
            ``u_q``, agree within ``stage2_positive_sigma``, its own match is
            reliable (``View.reliable``: weaker evidence than a vote asks the
            query's match to be unambiguous) and every other condition of a
            positive holds (not in the fattening band, not beside a hole,
            not in a contradicted region). Their agreement casts no vote, so
            every vote, every negative and every label the paper's rule gives
            stays as it was; the fallback only fills pixels that rule has no
            evidence on. 1 = the paper (off); default 2, with two views.
            Deviation, for coverage: a camera moving forward loses the near
            points at the image border from its newer views, and on an orbit
            half the window is farther from a point than the query; such
            pixels had correct depth and support but no vote. Unlike
            ``stage2_positive_accuracy_ratio``, which lets the same views
            vote and so outweighs negatives (it cost orbit 2.5 points of bad
            recall), this never turns a negative into a positive: negative
            precision and bad recall are unchanged on every sequence. Tuning
            seeds 1-10 at 1226x370 (accuracy / coverage / positive
            precision, its worst sequence, %): street 98.62 / 39.01 / 99.43,
            98.71 -> 98.65 / 41.72 / 99.43, 98.68; orbit 99.27 / 66.61 /
            99.34, 99.00 -> 99.25 / 74.73 / 99.31, 98.96; room 97.18 /
            37.42 / 99.61, 99.25 -> 97.24 / 38.65 / 99.59, 99.16. Variants
            on the tuning seeds:
            without the reliability condition street 42.46 / 99.42, 98.66,
            room 39.71 / 99.56, 99.08 (held out, room seed 40 then fell to
            98.47, under the 98.5 % floor; 98.51 with it); one view instead
            of two, street 48.58 % coverage but its worst positive precision
            98.38 % (seed 7, a plain facade the farther views match as
            wrongly as the query); ratio 4, street 48.01 %, worst 98.53 %;
            three views, room 38.99 / 99.59, 99.13.
        stage2_fallback_min_views: the agreeing less accurate references a
            fallback positive needs (default 2).
        stage2_positive_sigma: a reference votes positive in Stage 2 only
            within this many standard deviations (default 1.25; the paper:
            ``sigma_max``). Measured on four street frames (seed 1), 2 -> 1.5:
            accuracy 97.2 -> 97.9 % at coverage 35.3 -> 35.1 %. 1.5 -> 1.25
            came with ``ambiguity_min_texture`` 2 -> 1.8, whose new votes
            from faintly textured references also confirm errors just over
            3 px on near plain surfaces (room seed 40, held out: positive
            precision 98.57 -> 98.32 % with the texture change alone, 98.52 %
            with both). Tuning seeds 1-10 at 1226x370, texture 1.8, 1.5 ->
            1.25 (accuracy / coverage / positive / negative precision, %):
            street 98.25 / 40.03 / 99.37 / 79.7 -> 98.25 / 39.38 / 99.43 /
            79.3 (worst sequence's positive precision 98.62 -> 98.71), orbit
            99.08 / 67.75 / 99.25 / 79.6 -> 99.15 / 66.74 / 99.34 / 78.9, room
            96.88 / 38.15 / 99.55 / 94.9 -> 96.85 / 37.89 / 99.61 / 94.9.
        stage2_negative_sigma: and votes for an occlusion only beyond this
            many (default 3; the paper: ``sigma_max``); in between it casts
            no vote. Deviation: a hysteresis band, as for any detector with
            two kinds of error. Free-space violations keep ``sigma_max``: the
            query point then lies behind the surface, where its linearised
            covariance (``u`` grows as depth^4) is so wide that a point pushed
            to 2.5 times its depth sits near 2 standard deviations.
        stage2_edge_jump_px: disparity drop, pixels, that marks an object edge
            for the fattening band (default 4; 0 = the paper, no band): no
            Stage-2 positive label on a pixel whose disparity exceeds by
            more than this a valid disparity up to
            ``stage2_edge_occluded_side_px`` (default 20) columns to its
            left or ``stage2_edge_other_px`` (default 4) pixels to its right,
            above or below (:func:`selfcontra_ros.stages.voting.fattening_band`).
            Deviation from the paper, against foreground fattening: a
            window-based matcher spreads an object's disparity onto the
            background beside it, furthest on the left (hidden from the
            right camera); the fattened points lie centimetres beside the
            object's surface and nearby views repeat them, so the multi-view
            votes confirm them. Such pixels stay open to negative votes and
            to Stage 3. Cost: true positives on an object's own rim become
            unknown too, so the confidence model sees fewer positive edges.
            Measured on four frames per scene (seed 1, with a first band of
            16 / 3 px): positive precision street 98.1 -> 99.1 %, orbit
            96.7 -> 99.0 %, for 6 % and 5 % of the coverage.
        stage2_edge_below_px: for positives the band also reaches this many
            rows straight below a pixel (``stage2_edge_other_px`` columns
            either side), pixels; the band's other uses (negative voters,
            occlusion votes, free-space band, the forest's band cue and
            prior) keep ``stage2_edge_other_px``. Default 24; a value not
            above ``stage2_edge_other_px`` (4) is the symmetric band,
            ``stage2_edge_jump_px`` 0 the paper. Deviation, for the query
            algorithm's direction: OpenCV's single-pass SGBM (``sgbm``,
            ``sgbm_3way``) aggregates along paths that run sideways or
            downward, so it carries an object's disparity down onto a weakly
            textured background under its lower edge (a shelf board onto the
            back panel, 3.5-7 px too near, every nearby view alike) and
            never up (a strip above a drop instead took 30 % of the room's
            positives and lowered their precision). Tuning seeds 1-10 at
            1226x370, 4 -> 24 px (positive precision mean, worst; coverage;
            %): street 99.42, 98.68; 41.72 -> 99.45, 98.75; 41.58; orbit
            99.31, 98.96; 74.72 -> 99.37, 99.04; 74.30; room 99.61, 99.16;
            38.33 -> 99.67, 99.39; 38.05; negatives within 0.03. 12 / 16 / 24
            / 28 px would take the room's worst to 99.23 / 99.27 / 99.39 /
            99.40 % for 0.4 / 0.6 / 1.2 / 1.6 % of its positives (estimated
            by taking the positives out of the 4-px labels; the labelling
            at 24 px gave the same 99.39). A matcher with paths from below
            too (``hh``, 8 paths) has no such direction: not measured, the
            symmetric band (4) may suit it better.
        min_positive_votes: +1 votes an augmented-depth candidate needs (paper: 3).
        stage3_min_free_space_views: a Stage-3 negative (query depth in
            front of the augmented depth) is kept only where at least this
            many references see through the query point: it projects onto
            a valid measurement of theirs lying behind it by more than the
            Stage-3 candidate tolerance
            (:func:`~selfcontra_ros.stages.outliers.free_space_witnesses`).
            0 = the paper. Default 2. Deviation: the augmented depth is the
            nearest depth three views confirm, and a farther hypothesis is
            never contradicted by a nearer measurement (occlusion) while a
            nearer one is by a farther one. Where the views split between
            two depths (a near, weakly textured surface that some views
            match and others carry too far), Stage 3 therefore picks the
            farther and calls a right query depth an outlier. Per pixel on
            the tuning seeds (1-10 at 613x185), half of street's Stage-3
            negatives with a true disparity above 20 px were wrong (the
            query's median error under 0.2 px, the augmented depth's 9-16 px
            too far); on the hardest sequences a wrong Stage-3 negative had
            a view seeing through its point in 1-62 % of cases, a right one
            in 50-97 %. Label benchmark (accuracy / coverage /
            positive precision / negative precision / bad recall, %, means;
            worst accuracy), 0 -> 1 -> 2 -> 3: street 98.00 / 31.93 / 99.68 /
            72.9 / 17.4; 94.34 -> 98.54 / 31.76 / 99.66 / 78.0 / 16.1; 95.87
            -> 98.79 / 31.65 / 99.64 / 78.8 / 14.9; 96.59 -> 98.94 / 31.52 /
            99.63 / 79.1 / 13.5; 96.95, orbit 98.30 / 65.60 / 98.46 / 86.0 /
            10.3 -> 98.35 / 65.59 / 98.45 / 86.9 / 9.6 -> 98.35 / 65.59 /
            98.45 / 86.7 / 9.5 -> 98.35 / 65.59 / 98.45 / 86.6 / 9.4 (worst
            97.21 throughout), room 97.90 / 32.26 / 99.24 / 96.5 / 39.4;
            95.41 -> 98.32 / 31.94 / 99.23 / 97.3 / 38.7; 95.70 -> 98.54 /
            31.46 / 99.23 / 97.7 / 37.6; 96.01 -> 98.74 / 30.78 / 99.23 /
            98.0 / 36.1; 96.18. At 1226x370 (seeds 1-5) 0 -> 1 -> 2: street
            96.58 / 29.41 / 15.9 -> 97.23 / 29.15 / 15.0 -> 97.72 / 28.92 /
            14.0 (accuracy / coverage / bad recall), room 95.88 / 32.83 /
            39.8 -> 96.05 / 32.60 / 39.4 -> 96.33 / 32.11 / 38.6. Each step
            buys accuracy with a point of bad recall (negatives the forest
            learns from); 3 was not taken for that reason (``docs/label_quality.md``).
            What it costs the forest trained on the labels, held out at
            1226x370 (seeds 11-20; Ensemble trained on 11-15, scored on
            16-20; self / ground-truth AUSC ratio), 0 -> 2: orbit 1.994 ->
            2.200 (bad recall 8.65 -> 7.75 %), street 1.316 -> 1.255
            (accuracy 97.27 -> 98.06 %).
            The count is absolute, so a short window (few references) keeps
            fewer Stage-3 negatives: on 6-frame test inputs (window of 6)
            too few were left to train a forest, and their tests use 0.
        stage3_min_depth_ratio: a Stage-3 negative also needs the augmented
            depth to lie this many times farther than the query depth
            (``z_aug >= ratio * z_q``; 1 = the paper, only the uncertainty
            margin). Default 1. Where the references carry a textureless
            surface a little too far and the query's match is right, the
            augmented depth lies a little behind the query point; where the
            query is grossly too near (a fattened foreground, a disparity at
            the end of the range), far behind: z_aug / z_q at the median
            1.51 for wrong and 2.18 for right Stage-3 negatives on room
            seed 17 at 1226x370, 1.50 / 3.00 on room and 1.38 / 3.12 on
            street (tuning seeds 1-10 at 613x185), 1.89 / 1.91 on orbit.
            1.5 on seeds 1-10 at 613x185 (accuracy / coverage / bad recall,
            %): street 98.95 / 40.50 / 15.6 -> 99.10 / 40.41 / 14.9, room
            98.63 / 35.49 / 38.0 -> 98.84 / 34.19 / 34.7, orbit unchanged;
            self / ground-truth AUSC ratio street 1.342 -> 1.353, orbit
            2.689 -> 2.658, room 1.038 -> 1.040. Held out (seeds 21-30 at
            1226x370): street 97.74 / 35.22 / 19.0 -> 98.37 / 34.55 / 15.6,
            room 97.80 / 36.10 / 40.6 -> 98.55 / 33.13 / 34.4. Not the
            default: the forest does not gain, street's coverage falls under
            35 % and the right negatives it drops are the kind the forest
            lacks; for filtering depth with the negatives themselves, 1.5.
        cross_check_matcher: ``none`` (the paper, default) or
            ``census_sgm``: a second matcher labelled over the same window by
            a second labeler of these parameters; an unknown query pixel
            becomes negative where the second matcher's depth is a positive
            of its own labels and differs from the query's by more than
            ``cross_check_min_difference_px``
            (:mod:`selfcontra_ros.cross_check`). Beyond the paper: it gives
            negatives on errors every view of the query algorithm repeats,
            which the forest lacks most. It needs the stereo images (not
            with ``matcher.algorithm: external``) and costs a census SGM run
            and a second labeling per view, and held out at 1226x370 the
            forest did not gain (orbit seeds 21-30: ratio 1.968 -> 1.939,
            bad recall 7.2 -> 12.0 %; figures in ``docs/label_quality.md``), so it is off
            by default.
        cross_check_min_difference_px: pixels; see ``cross_check_matcher``.
            Default 4. Tuning seeds 1-10 at 613x185, 3 / 4 / 5 / 7 px (share
            of the new negatives on wrong query depth; Ensemble self /
            ground-truth AUSC ratio, trained on seeds 1-5, scored on 6-10,
            against 2.689 / 1.342 / 1.038 without the check): orbit 57 / 85
            / 93 % at 3 / 4 / 5 px, ratio 2.281 / 1.898 / 2.069 / 2.625;
            street 37 / 52 / 54 %, ratio 1.356 / 1.329 / 1.304 / 1.340; room
            59 / 69 % at 4 / 5 px (4126 and 3144 pixels beside 2.5 million
            negatives), ratio 1.034 / 1.037. 4 px has the lowest mean ratio
            over the three scenes. The threshold is in pixels of disparity,
            so it means a larger depth error at a smaller image size.
        range_abstain: whether a view casts no vote on a point its matcher
            could not have measured: a query point whose disparity in a
            reference would exceed that reference's searched range
            (``Labeler.add_view(max_disparity=...)``, the built-in matcher's
            ``min_disparity + num_disparities - 1``) less ``range_margin_px``.
            Such a reference neither confirms nor contradicts the point in
            Stage 2, neither validates nor rejects it as an augmented-depth
            candidate, and is no Stage-3 witness against it. False = the paper.
            A surface nearer than the range comes out at some farther
            disparity (or none) in every view that close to it, so those views
            agree on the wrong surface behind it and "see through" the right
            depth of a view standing farther back: on the room, where the MAV
            flies close to furniture (up to 20 % of a view's ground truth
            beyond 128 px on held-out seed 72), half of the wrong negatives
            lay above 96 px of disparity. The range of an external disparity is unknown
            (a DisparityImage's ``max_disparity`` is the searched range for
            stereo_image_proc but the largest value found for others), so the
            rule is off for it. Default true. Measured with
            ``bench/label_quality.py`` (30 frames, 1226x370; accuracy /
            coverage / positive / negative precision, %, mean, in brackets the
            worst accuracy), false -> true: tuning seeds 1-10 room 97.25 /
            38.65 / 99.61 / 95.38 (95.62) -> 97.30 / 38.33 / 99.61 / 95.44
            (96.03), street 98.65 / 41.72 / 99.43 / 85.41 (96.64) -> 98.68 /
            41.72 / 99.42 / 85.57 (96.68), orbit the same but for a few
            negatives (bad recall 8.53 -> 8.48 %); room seeds 71-80, the set that showed the
            failure, 97.32 / 37.47 / 99.60 / 95.03 (91.86) -> 97.83 / 36.78 /
            99.59 / 95.79 (95.04): on seed 72 41 % of the wrong negatives go,
            and 10 % of the right ones. The room's forest (Ensemble trained
            on seeds 1-5, AUSC / optimal on 6-10, mean) 1.130 -> 1.131; KITTI
            06's label shares 32.39 / 5.47 -> 32.39 / 5.46 %. Fresh held-out
            seeds: ``docs/label_quality.md``.
        range_margin_px: pixels below the searched range from which a view
            abstains (``range_abstain``). Default 2, about the query point's own
            disparity noise; 0 / 2 / 8 px on room seeds 1-10: accuracy 97.30 /
            97.30 / 97.31, coverage 38.36 / 38.33 / 38.23, bad recall 38.23 /
            38.17 / 37.97 %.
        stage3_reliable_witnesses: whether only a reference's reliable
            measurements (not ambiguous, ``View.reliable``, as for Stage-2
            votes) may witness a Stage-3 negative. False = the paper, the
            default: on the room, whose walls are textureless, it takes nearly
            all Stage-3 negatives away. Tuning seeds 1-10 at 1226x370 with
            ``range_abstain`` (accuracy / coverage / positive precision / bad
            recall, %, mean; worst accuracy and positive precision): street
            98.68 / 41.72 / 99.42 / 18.24 (96.68, 98.68) -> 99.21 / 40.31 /
            99.36 / 9.85 (98.39, 98.54); room 97.30 / 38.33 / 99.61 / 38.17
            (96.03, 99.16) -> 99.13 / 21.94 / 99.55 / 5.34 (97.11, 99.05).
            Right labels, but half of street's and seven eighths of the room's
            negatives gone, and the forest learns the errors from them.
        keyframe_min_translation: metres; a view closer than this to the
            newest kept view (left camera centres) and rotated less than
            ``keyframe_min_rotation_deg`` from it is skipped. Default 0.05 m.
        keyframe_min_rotation_deg: degrees, see above. Default 1.
        flush_incomplete: whether :meth:`Labeler.flush` (end of a sequence or
            bag, node shutdown) labels the views that never got
            ``label_delay`` newer views, with the views there are. Default
            false: they are dropped, like the paper, which labels only the
            middle view of a full 21-view window. Measured (street, 30
            frames, seed 1, defaults otherwise; accuracy / coverage /
            positive precision, %): the 20 views labelled with a full delay
            96.99 / 35.16 / 98.49, the 10 flushed ones 91.94 / 28.96 / 94.86:
            on forward motion the newer views are the closer, more accurate
            ones, and only more accurate references vote in Stage 2.
        ambiguity_min_texture: grey levels; a pixel whose left-image
            standard deviation in an ``ambiguity_texture_window`` square is
            below this is *ambiguous* (:func:`~selfcontra_ros.window.ambiguous_pixels`):
            as a reference it casts no Stage-2 vote (with ``ambiguity_abstain``
            it is never labelled positive itself either). Default 1.8 grey
            levels, 1.2 times the synthetic scenes' sensor noise (1.5; a patch
            of noise alone reads about 1.53 with the 8-bit rounding): set it
            from your camera's noise. A textureless patch
            matches equally well at many disparities, SGM fills it from its
            surroundings and nearby views repeat the guess, so their agreement
            proves nothing, and their disagreement with a correct neighbour
            view proves nothing either. 0 = the paper. Needs the left image
            (``Labeler.add_view(image=...)``; the session, the node and the
            bag labeler pass it; without it, e.g. external disparities with
            no images, the cue is off). Measured with ``bench/label_quality.py``
            (30 frames; accuracy / coverage / positive / negative precision,
            %, mean over sequences), paper votes -> default (texture 2,
            edge 4 px, no abstention). Tuning seeds 1-10 at 613x185: street
            93.83 / 41.70 / 98.50 / 49.0 -> 97.75 / 33.26 / 99.26 / 68.8,
            orbit 97.45 / 72.91 / 98.25 / 38.7 -> 97.70 / 68.43 / 98.31 / 45.5,
            room 86.13 / 51.20 / 94.80 / 76.4 -> 97.48 / 34.34 / 98.26 / 95.9.
            Held-out seeds 11-13 at 1226x370: street 91.76 / 40.89 / 97.24 /
            70.5 -> 96.25 / 30.67 / 98.64 / 82.5, orbit 98.20 / 71.30 / 99.12
            / 41.3 -> 98.47 / 63.53 / 99.09 / 49.9, room 88.94 / 49.86 / 94.53
            / 86.1 -> 95.12 / 35.46 / 96.48 / 94.4. The cost is coverage.
            2 -> 1.8 (the default since; 1226x370, the other defaults of the
            time, one run each): tuning seeds 1-10, street 98.27 / 37.16 /
            99.39 / 80.3 -> 98.25 / 40.03 / 99.37 / 79.7, orbit 99.05 / 64.33
            / 99.22 / 79.9 -> 99.08 / 67.75 / 99.25 / 79.6, room 96.84 / 34.73
            / 99.60 / 95.1 -> 96.88 / 38.15 / 99.55 / 94.9; held out (street
            and orbit 31-50, never used to choose anything), street 97.79 /
            34.19 / 99.38 / 79.6 -> 97.84 / 37.53 / 99.40 / 79.0 (worst
            sequence's accuracy 95.22 -> 95.50, positive precision 98.70 ->
            98.73), orbit 98.99 / 63.10 / 99.16 / 77.6 -> 99.03 / 66.93 /
            99.19 / 77.3. Patches between 1.8 and 2 are mostly faint road and
            facade texture that every view matches right. 1.6 is too near the
            noise: street seed 7's positive precision fell to 96.94 % (98.62
            at 1.8), its wrong positives on a plain facade whose own patches
            read 1.53, pure noise, while the nearer views see faint texture
            above the threshold and repeat SGBM's wrong depth.
        ambiguity_texture_window: odd window size of that standard deviation, pixels.
        ambiguity_texture_measure: ``std`` (grey-level standard deviation) or
            ``gradient_x`` (RMS of the horizontal derivative, the only
            direction that constrains a horizontal disparity).
        ambiguity_abstain: whether an ambiguous query pixel abstains from a
            positive label (true), or only ambiguous reference pixels are
            kept from voting (false, the default). Seeds 1-3 at 1226x370,
            texture 2 and edge 4 px, true -> false: coverage street 30.9 ->
            33.6, orbit 60.5 -> 65.9, room 35.5 -> 38.6 %, accuracy unchanged
            (97.49 / 98.73 / 96.57 -> 97.51 / 98.74 / 96.58 %), positive
            precision -0.14 / -0.04 / -0.26 points.
        ambiguity_saturation: grey level (8-bit left image) at or above which
            a pixel is *clipped* (:func:`~selfcontra_ros.window.saturated_pixels`):
            it is never labelled positive, whatever the votes, and as a
            reference it casts no vote. Default 255, the sensor's full scale;
            0 = off (the paper). A clipped pixel's value says nothing about
            the scene but "bright": beside a window onto a bright outside, the
            query algorithm gives the white pixels next to the frame the wall's
            disparity (the frame's edge is the only texture in their matching
            window), the window's white inside is too flat for a disparity drop,
            so no fattening band forms, and every view repeats the same depth.
            Measured with ``bench/label_quality.py`` (30 frames, 1226x370;
            accuracy / coverage / positive / negative precision, %, mean, in
            brackets the worst sequence's positive precision), 0 -> 255:
            held-out room 61-70 97.65 / 37.70 / 99.12 / 96.0 (95.54) ->
            97.79 / 37.65 / 99.60 / 96.0 (99.10), where 99.8 % of the
            positives at 255 were wrong; tuning room 1-10 97.24 / 38.65 /
            99.59 -> 97.25 / 38.65 / 99.61; orbit 1-10 the same but for
            seed 4's coverage and negative precision (-0.01 point each);
            street has no pixel at 255.
            Cost on real data: KITTI 06's positive share 33.17 -> 32.39 %,
            and the Ensemble forest trained on those labels 1.2 % (KITTI
            2015) and 1.9 % (Middlebury) worse (AUSC, mean of three forest
            seeds). See ``docs/label_quality.md``.
        ambiguity_edge_px: pixels; a pixel whose disparity varies by more than
            this within its 3x3 neighbourhood (a depth edge, where a lookup
            hits foreground or background by a fraction of a pixel) is
            ambiguous too. 0 = the paper. Default 4 (seeds 1-3 at 1226x370,
            with texture 2 and abstention, 0 -> 4 -> 2 px: accuracy street
            97.19 -> 97.49 -> 97.48, orbit 98.51 -> 98.73 -> 98.87, coverage
            street 31.3 -> 30.9 -> 28.9, orbit 61.2 -> 60.5 -> 55.8 %).
    """

    window_size: int = 20
    label_delay: int = 10
    alpha_min_deg: float = 7.0
    sigma_max: float = 2.0
    sigma_px: float = 1.0
    stage1_tolerance: str = "sum"
    stage2_tolerance: str = "sum"
    stage3_tolerance: str = "std"
    stage2_min_angle_deg: float = 0.0
    stage2_min_query_support: int = 0
    stage2_negative_voters: str = "band"
    stage2_occlusion_votes: str = "band"
    stage2_free_space_votes: bool = True
    stage2_free_space_neighbourhood: int = 2
    stage2_positive_sigma: float = 1.25
    stage2_negative_sigma: float = 3.0
    stage2_edge_jump_px: float = 4.0
    stage2_edge_occluded_side_px: int = 20
    stage2_edge_other_px: int = 4
    min_positive_votes: int = 3
    stage3_min_free_space_views: int = 2
    stage3_min_depth_ratio: float = 1.0
    keyframe_min_translation: float = 0.05
    keyframe_min_rotation_deg: float = 1.0
    flush_incomplete: bool = False
    ambiguity_min_texture: float = 1.8
    ambiguity_texture_window: int = 7
    ambiguity_edge_px: float = 4.0
    ambiguity_texture_measure: str = "std"
    ambiguity_abstain: bool = False
    ambiguity_saturation: float = 255.0
    stage2_free_space_band: bool = True
    stage2_hole_margin_px: float = 4.0
    stage2_free_space_min_views: int = 3
    stage2_band_min_negative_views: int = 2
    contradicted_share: float = 0.1
    contradicted_radius_deg: float = 2.6
    stage2_positive_accuracy_ratio: float = 1.0
    stage2_fallback_accuracy_ratio: float = 2.0
    stage2_fallback_min_views: int = 2
    cross_check_matcher: str = "none"
    cross_check_min_difference_px: float = 4.0
    range_abstain: bool = True
    range_margin_px: float = 2.0
    stage3_reliable_witnesses: bool = False
    stage2_edge_below_px: int = 24

    def __post_init__(self) -> None:
        for name in (
            "window_size",
            "label_delay",
            "min_positive_votes",
            "stage2_fallback_min_views",
            "stage3_min_free_space_views",
            "stage2_min_query_support",
            "stage2_free_space_neighbourhood",
            "stage2_free_space_min_views",
            "stage2_band_min_negative_views",
            "stage2_edge_occluded_side_px",
            "stage2_edge_other_px",
            "stage2_edge_below_px",
            "ambiguity_texture_window",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"LabelerParams.{name} must be an integer, got {value!r}")
        for name in (
            "alpha_min_deg",
            "sigma_max",
            "sigma_px",
            "stage2_min_angle_deg",
            "stage2_positive_sigma",
            "stage2_negative_sigma",
            "stage2_edge_jump_px",
            "keyframe_min_translation",
            "keyframe_min_rotation_deg",
            "ambiguity_min_texture",
            "ambiguity_edge_px",
            "ambiguity_saturation",
            "stage2_hole_margin_px",
            "contradicted_share",
            "contradicted_radius_deg",
            "stage2_positive_accuracy_ratio",
            "stage2_fallback_accuracy_ratio",
            "stage3_min_depth_ratio",
            "cross_check_min_difference_px",
            "range_margin_px",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise ValueError(f"LabelerParams.{name} must be a number, got {value!r}")
            if not np.isfinite(value):
                raise ValueError(f"LabelerParams.{name} must be finite, got {value!r}")
        for name in (
            "stage2_free_space_votes",
            "flush_incomplete",
            "ambiguity_abstain",
            "stage2_free_space_band",
            "range_abstain",
            "stage3_reliable_witnesses",
        ):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"LabelerParams.{name} must be true or false, got {getattr(self, name)!r}")
        if self.window_size < 2:
            raise ValueError(f"LabelerParams.window_size must be >= 2 (views need references), got {self.window_size}")
        if not 0 <= self.label_delay < self.window_size:
            raise ValueError(
                f"LabelerParams.label_delay must be in [0, window_size - 1] = [0, {self.window_size - 1}], "
                f"got {self.label_delay}"
            )
        if not 180.0 / (MAX_BINS - 1) < self.alpha_min_deg < 180.0:
            raise ValueError(
                f"LabelerParams.alpha_min_deg must be in ({180.0 / (MAX_BINS - 1):.3f}, 180) degrees, "
                f"got {self.alpha_min_deg}"
            )
        for name in ("sigma_max", "sigma_px", "stage2_positive_sigma", "stage2_negative_sigma"):
            if getattr(self, name) <= 0:
                raise ValueError(f"LabelerParams.{name} must be > 0, got {getattr(self, name)}")
        for name in (
            "keyframe_min_translation",
            "keyframe_min_rotation_deg",
            "stage2_min_query_support",
            "stage2_free_space_neighbourhood",
            "stage2_edge_jump_px",
            "stage2_edge_occluded_side_px",
            "stage2_edge_other_px",
            "stage2_edge_below_px",
            "ambiguity_min_texture",
            "ambiguity_edge_px",
            "stage2_hole_margin_px",
            "range_margin_px",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"LabelerParams.{name} must be >= 0, got {getattr(self, name)}")
        if self.stage2_negative_sigma < self.stage2_positive_sigma:
            raise ValueError(
                f"LabelerParams.stage2_negative_sigma ({self.stage2_negative_sigma}) must be >= "
                f"stage2_positive_sigma ({self.stage2_positive_sigma}): nothing may both confirm and contradict"
            )
        if not 0 <= self.stage2_min_angle_deg < 180:
            raise ValueError(
                f"LabelerParams.stage2_min_angle_deg must be in [0, 180) degrees, got {self.stage2_min_angle_deg}"
            )
        if not 0 <= self.ambiguity_saturation <= 255:
            raise ValueError(
                "LabelerParams.ambiguity_saturation must be in [0, 255] grey levels (0: off), "
                f"got {self.ambiguity_saturation}"
            )
        if self.ambiguity_texture_window < 1 or self.ambiguity_texture_window % 2 == 0:
            raise ValueError(
                f"LabelerParams.ambiguity_texture_window must be odd and >= 1, got {self.ambiguity_texture_window}"
            )
        if self.stage2_positive_accuracy_ratio < 1:
            raise ValueError(
                "LabelerParams.stage2_positive_accuracy_ratio must be >= 1 (1: only more accurate references "
                f"confirm), got {self.stage2_positive_accuracy_ratio}"
            )
        if self.stage2_fallback_accuracy_ratio < 1:
            raise ValueError(
                "LabelerParams.stage2_fallback_accuracy_ratio must be >= 1 (1: off, the paper), "
                f"got {self.stage2_fallback_accuracy_ratio}"
            )
        if self.stage2_fallback_min_views < 1:
            raise ValueError(
                f"LabelerParams.stage2_fallback_min_views must be >= 1, got {self.stage2_fallback_min_views}"
            )
        if self.stage2_band_min_negative_views < 1:
            raise ValueError(
                f"LabelerParams.stage2_band_min_negative_views must be >= 1, got {self.stage2_band_min_negative_views}"
            )
        if self.stage2_free_space_min_views < 1:
            raise ValueError(
                f"LabelerParams.stage2_free_space_min_views must be >= 1, got {self.stage2_free_space_min_views}"
            )
        if not 0 <= self.contradicted_share <= 1:
            raise ValueError(f"LabelerParams.contradicted_share must be in [0, 1], got {self.contradicted_share}")
        if not 0 < self.contradicted_radius_deg < 45:
            raise ValueError(
                f"LabelerParams.contradicted_radius_deg must be in (0, 45) degrees, got {self.contradicted_radius_deg}"
            )
        if self.min_positive_votes < 1:
            raise ValueError(f"LabelerParams.min_positive_votes must be >= 1, got {self.min_positive_votes}")
        if not self.stage3_min_depth_ratio >= 1:
            raise ValueError(
                "LabelerParams.stage3_min_depth_ratio must be >= 1 (1: any margin beyond the tolerance), "
                f"got {self.stage3_min_depth_ratio}"
            )
        if not self.cross_check_min_difference_px > 0:
            raise ValueError(
                f"LabelerParams.cross_check_min_difference_px must be > 0, got {self.cross_check_min_difference_px}"
            )
        if self.stage3_min_free_space_views < 0:
            raise ValueError(
                f"LabelerParams.stage3_min_free_space_views must be >= 0, got {self.stage3_min_free_space_views}"
            )
        for name, choices in (
            ("ambiguity_texture_measure", TEXTURE_MEASURES),
            ("stage1_tolerance", TOLERANCES),
            ("stage2_tolerance", TOLERANCES),
            ("stage2_negative_voters", NEGATIVE_VOTERS),
            ("stage2_occlusion_votes", OCCLUSION_VOTES),
            ("stage3_tolerance", READINGS),
            ("cross_check_matcher", CROSS_CHECK_MATCHERS),
        ):
            if getattr(self, name) not in choices:
                raise ValueError(f"LabelerParams.{name} must be one of {choices}, got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> LabelerParams:
        """Parameters from a mapping (e.g. a YAML section); missing keys keep their defaults.

        Raises:
            ValueError: naming unknown keys, or any invalid value.
        """
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown labeler parameter(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(values))


@dataclass
class LabelResult:
    """Labels of one view and the intermediate maps that produced them (all HxW).

    Attributes:
        key: what the caller passed with the view.
        stamp: the labelled view's own stamp, seconds.
        labels: final labels (0 unknown, 1 positive, 2 negative).
        stage2_labels: labels after Stage 2 alone.
        support: Stage-1 support (distinct angle bins) of the view.
        vote_sum: Stage-2 vote sum (0 where no vote).
        augmented_depth: Stage-3 augmented depth, metres (NaN where none or not computed).
        uncertainty: ``u``, largest covariance eigenvalue per pixel, m^2 (NaN invalid).
    """

    key: Hashable
    stamp: float
    labels: NDArray[np.uint8]
    stage2_labels: NDArray[np.uint8]
    support: NDArray[np.uint8]
    vote_sum: NDArray[np.float32]
    augmented_depth: NDArray[np.float32]
    uncertainty: NDArray[np.float32]


class Labeler:
    """Online self-contradiction labeler over a sliding window of views."""

    def __init__(self, camera: StereoCamera, params: LabelerParams | None = None) -> None:
        """Create a labeler for one rectified stereo camera."""
        self.camera = camera
        self.params = params if params is not None else LabelerParams()
        self.window = ViewWindow(
            self.params.window_size, self.params.keyframe_min_translation, self.params.keyframe_min_rotation_deg
        )
        self.skipped_views = 0
        #: views dropped unlabelled by :meth:`flush` (``flush_incomplete`` false).
        self.dropped_views = 0
        self._calls = 0
        self._kept = 0

    def add_view(
        self,
        disparity: NDArray[np.floating],
        pose: NDArray[np.floating],
        *,
        stamp: float,
        key: Hashable = None,
        image: NDArray[np.uint8] | None = None,
        max_disparity: float | None = None,
    ) -> list[LabelResult]:
        """Add one view; returns the labels of the views that became ready (``label_delay`` views back).

        Args:
            disparity: HxW left disparity, pixels; NaN, inf or <= 0 is invalid.
            pose: 4x4 ``T_world_left`` (metres).
            stamp: the view's stamp, seconds; the label image carries it.
            key: returned with the labels; defaults to the running number of ``add_view`` calls.
            image: the view's left image (HxW grey or HxWx3 RGB), for ``ambiguity_min_texture``; without
                it that cue is off for this view.
            max_disparity: the largest disparity the view's matcher searched, pixels (``range_abstain``);
                None: unknown, the view then speaks about every point.

        Raises:
            SelfContraError: naming the disparity shape, the pose or ``max_disparity`` when malformed.
        """
        call = self._calls
        self._calls += 1
        disp = np.asarray(disparity)
        shape = (self.camera.height, self.camera.width)
        if disp.shape != shape:
            raise SelfContraError(f"disparity has shape {disp.shape}; expected {shape} (camera height x width)")
        pose64 = _checked_pose(pose)
        searched = math.inf if max_disparity is None else _checked_range(max_disparity)
        if not self.window.is_keyframe(pose64):
            self.skipped_views += 1
            return []
        p = self.params
        if image is not None and np.asarray(image).shape[:2] != shape:
            raise SelfContraError(f"image has shape {np.asarray(image).shape}; expected {shape} (as the disparity)")
        grey = None if image is None else to_grey(image)  # once for both cues
        reliable = None
        if p.ambiguity_min_texture > 0 or p.ambiguity_edge_px > 0:
            reliable = ~ambiguous_pixels(
                disp,
                grey,
                min_texture=p.ambiguity_min_texture,
                texture_window=p.ambiguity_texture_window,
                edge_px=p.ambiguity_edge_px,
                texture_measure=p.ambiguity_texture_measure,
            )
        clipped = None
        if grey is not None and p.ambiguity_saturation > 0:
            clipped = saturated_pixels(grey, p.ambiguity_saturation)
            reliable = ~clipped if reliable is None else reliable & ~clipped
        view = make_view(
            self.camera,
            disp,
            pose64,
            index=self._kept,
            key=call if key is None else key,
            stamp=stamp,
            sigma_px=p.sigma_px,
            reliable=reliable,
            clipped=clipped,
            max_disparity=searched,
        )
        self._kept += 1
        update_support(
            view,
            list(self.window),
            self.camera,
            alpha_min_deg=p.alpha_min_deg,
            sigma_max=p.sigma_max,
            sigma_px=p.sigma_px,
            tolerance=p.stage1_tolerance,
        )
        self.window.push(view)
        ready = [v for v in self.window if not v.labelled and v.index <= view.index - p.label_delay]
        return [self._label(v) for v in ready]

    def flush(self) -> list[LabelResult]:
        """End of a sequence: empty the window for a new one.

        Views still waiting for ``label_delay`` newer views are labelled with
        the views available if ``params.flush_incomplete``, else dropped
        (counted in :attr:`dropped_views`).
        """
        waiting = [v for v in self.window if not v.labelled]
        results = [self._label(v) for v in waiting] if self.params.flush_incomplete else []
        self.dropped_views += len(waiting) - len(results)
        self.window.clear()
        return results

    def _label(self, view: View) -> LabelResult:
        """Stages 2 and 3 for one view against every other view in the window."""
        p = self.params
        cam = self.camera
        refs = self.window.others(view)
        margin = p.range_margin_px if p.range_abstain else None
        voting = consistency_voting(
            view,
            refs,
            cam,
            sigma_max=p.sigma_max,
            sigma_px=p.sigma_px,
            tolerance=p.stage2_tolerance,
            min_angle_deg=p.stage2_min_angle_deg,
            min_query_support=p.stage2_min_query_support,
            negative_voters=p.stage2_negative_voters,
            free_space_votes=p.stage2_free_space_votes,
            free_space_neighbourhood=p.stage2_free_space_neighbourhood,
            edge_jump_px=p.stage2_edge_jump_px,
            edge_occluded_side_px=p.stage2_edge_occluded_side_px,
            edge_other_px=p.stage2_edge_other_px,
            positive_sigma=p.stage2_positive_sigma,
            negative_sigma=p.stage2_negative_sigma,
            abstain_ambiguous=p.ambiguity_abstain,
            free_space_band=p.stage2_free_space_band,
            hole_margin_px=p.stage2_hole_margin_px,
            free_space_min_views=p.stage2_free_space_min_views,
            positive_accuracy_ratio=p.stage2_positive_accuracy_ratio,
            occlusion_votes=p.stage2_occlusion_votes,
            band_min_negative_views=p.stage2_band_min_negative_views,
            fallback_accuracy_ratio=p.stage2_fallback_accuracy_ratio,
            fallback_min_views=p.stage2_fallback_min_views,
            range_margin_px=margin,
            edge_below_px=p.stage2_edge_below_px,
        )
        labels = voting.labels.copy()
        unknown = labels == UNKNOWN
        trivial = trivial_outliers(view, cam) & unknown
        pending = view.valid & unknown & ~trivial
        z_aug = augmented_depth(
            view,
            refs,
            pending,
            cam,
            sigma_max=p.sigma_max,
            sigma_px=p.sigma_px,
            reading=p.stage3_tolerance,
            min_positive_votes=p.min_positive_votes,
            range_margin_px=margin,
        )
        negatives = outlier_negatives(
            view,
            z_aug,
            pending,
            cam,
            sigma_max=p.sigma_max,
            sigma_px=p.sigma_px,
            reading=p.stage3_tolerance,
            refs=refs,
            min_free_space_views=p.stage3_min_free_space_views,
            min_depth_ratio=p.stage3_min_depth_ratio,
            range_margin_px=margin,
            reliable_witnesses=p.stage3_reliable_witnesses,
        )
        labels[trivial | negatives] = NEGATIVE
        shape = (cam.height, cam.width)
        if p.contradicted_share < 1:
            radius = round(cam.fx * np.tan(np.radians(p.contradicted_radius_deg)))
            # Trivial outliers are geometry (a match outside the right image), not views' contradictions.
            # The band's negatives held back for too few views (stage2_band_min_negative_views) still count.
            withheld = voting.voted & (voting.vote_sum < 0)
            contradicted = np.where(trivial, UNKNOWN, np.where(withheld, NEGATIVE, labels)).reshape(shape)
            labels[contradicted_positives(contradicted, radius, p.contradicted_share).ravel()] = UNKNOWN
        view.labelled = True
        return LabelResult(
            key=view.key,
            stamp=view.stamp,
            labels=labels.reshape(shape),
            stage2_labels=voting.labels.reshape(shape),
            support=support_count(view.support_bits).reshape(shape),
            vote_sum=voting.vote_sum.astype(np.float32).reshape(shape),
            augmented_depth=z_aug.astype(np.float32).reshape(shape),
            uncertainty=view.u.reshape(shape),
        )


def _checked_range(max_disparity: float) -> float:
    """The matcher's largest searched disparity as a float; raises SelfContraError unless finite and > 0."""
    value = float(max_disparity)
    if not (math.isfinite(value) and value > 0):
        raise SelfContraError(f"max_disparity must be a finite disparity > 0 pixels, got {max_disparity!r}")
    return value


def _checked_pose(pose: NDArray[np.floating]) -> NDArray[np.float64]:
    """The pose as a float64 4x4 rigid transform; raises SelfContraError naming what is wrong."""
    t = np.asarray(pose, dtype=np.float64)
    if t.shape != (4, 4):
        raise SelfContraError(f"pose has shape {t.shape}; expected a 4x4 T_world_left matrix")
    if not np.all(np.isfinite(t)):
        raise SelfContraError("pose holds non-finite values; expected a finite 4x4 T_world_left matrix")
    rotation = t[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) <= 0:
        raise SelfContraError("pose rotation block is not a proper rotation (R R^T != I or det(R) <= 0)")
    if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0]):
        raise SelfContraError(f"pose last row is {t[3].tolist()}; expected [0, 0, 0, 1]")
    return t
