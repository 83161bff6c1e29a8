"""Feature-based stereo visual odometry for rectified pairs: poses for sequences that have none.

The paper estimated the poses of its KITTI multiview scenes with libviso2;
this module is the package's own counterpart, built on OpenCV features:

1. **Features.** ORB corners of the left image, bucketed on a grid so that
   they cover the whole image rather than the most textured facade.
2. **Stereo matching.** Each left feature is matched to an ORB feature of the
   right image on the same row (the epipolar constraint of a rectified pair:
   ``|v_l - v_r| <= epipolar_tolerance_px``, disparity in range), with
   Lowe's ratio test; the right position is then refined to sub-pixel
   precision by Lucas-Kanade along the row. Depth ``z = fx b / d``.
3. **Frame-to-frame matching.** The features of the new frame are matched to
   those of the reference frame (the last reliable one) within a radius of
   where the constant-velocity prediction puts them (repetitive windows
   defeat an unrestricted search), then refined by Lucas-Kanade from the
   reference position.
4. **Pose.** PnP with RANSAC (seeded: ``cv2.setRNGSeed``) from the reference
   frame's 3D points to the new left image, then a robust (Huber)
   least-squares refinement of the stereo reprojection error in both
   directions (reference points into the new left and right images, new
   points into the reference images).
5. **Windowed refinement.** Features keep a track id while they are matched
   from frame to frame; a small bundle adjustment over the last
   ``window`` reliable frames (oldest pose fixed) moves poses and track
   points to minimise the stereo reprojection error of every observation.
6. **Velocity prior.** A frame whose step length cannot be trusted
   (``weak_scale``) keeps its measured rotation but takes the last reliable
   step's translation; the next reliable frame interpolates the translations
   of the unreliable frames before it (a vehicle's velocity changes little
   from frame to frame), and a reliable-looking step that jumps from the last
   reliable one by more than a vehicle can accelerate is ``weak_scale``, and
   so is a step whose length rests on one image region (leaving that
   region's matches out would change it by more than ``influence_share`` of
   the allowed error: a vehicle that the gates let through, one facade).
7. **Smoothed step lengths** (offline, :func:`smooth_step_lengths`): once
   the sequence is done, a Kalman smoother over the step lengths averages
   each step's noise with its neighbours' (a vehicle's speed changes little
   between frames), trusting reliable steps more than ``weak_scale`` ones.
   A reliable frame alone among unreliable ones is then reported
   ``isolated`` (:func:`mark_isolated`), and one whose smoothed step length
   the smoother itself knows only loosely ``uncertain``
   (:func:`step_length_spread`, :func:`mark_uncertain`).
8. **The road** (``road_steps``, :mod:`~selfcontra_ros.odometry.ground`):
   each step from the frame before is measured a second time by aligning
   the road plane under the camera between the two left images, from near
   pixels whatever the features' depth, also where the features failed (a
   truck filling the view) or were measured across a gap; the smoother
   takes its length as a second measurement (a reliable features' length
   far from it is gated out), and where two neighbouring road lengths
   agree the step takes the road's rotation and direction too
   (``road_motion``).

Every frame gets a :class:`FrameQuality`: feature, match and inlier counts,
the RMS reprojection error of the inliers and a status. A frame with too
little texture, too few matches or inliers or too large an error is flagged
unreliable: its pose is only a constant-velocity guess, it is not used as a
reference, and callers exclude it from labeling.

Poses are ``T_world_left`` 4x4 (metres), world = left camera of the first
frame, as in KITTI's pose files.
"""

from __future__ import annotations

import copy
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Generic, TypeVar, overload

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.geometry import StereoCamera, invert_pose
from selfcontra_ros.matching.census import hamming
from selfcontra_ros.odometry.ground import GroundPlane, fit_ground, road_costs, road_step

# scipy is imported where it is used: it is about 2 s of a process's start (a third of the labeler node's), and
# only a run of the odometry needs it, whereas the node and the commands import this module for its parameters.
if TYPE_CHECKING:
    import scipy.sparse

__all__ = [
    "STATUSES",
    "FrameLog",
    "FrameQuality",
    "IsolationGate",
    "OdometryError",
    "OdometryResult",
    "StereoCache",
    "StereoMatches",
    "StereoOdometry",
    "VOParams",
    "judge_spread",
    "mark_isolated",
    "mark_uncertain",
    "smooth_step_lengths",
    "step_length_spread",
]

F64 = NDArray[np.float64]
_T = TypeVar("_T")

#: Frame statuses: the first three are reliable.
STATUSES = (
    "first", "ok", "static", "weak_scale", "few_features", "few_matches", "few_inliers", "implausible", "high_error",
    "isolated", "uncertain",
)  # fmt: skip
_RELIABLE = frozenset(("first", "ok", "static"))
#: The least spread (pixels) assumed between windows' disparity-offset estimates: three windows that agree
#: by chance must not make a tiny standard error.
_OFFSET_STD_FLOOR_PX = 0.05
#: The straddle test's half windows (width, height) and how far (px) left and right of the feature they are
#: centred: each covers one side of the 19x9 stereo window.
_HALF_WINDOW = (9, 9)
_HALF_SHIFT_PX = 5.0
#: The longest run of unreliable frames that a reliable frame after it mends
#: (:meth:`StereoOdometry._interpolate_unreliable_steps`): 10 s at 10 Hz. Across a longer failure (a covered
#: lens, a night parked in the dark) a velocity interpolated between its ends means nothing, and a long-running
#: node need not keep the run's frames (``forget_before``). Every benchmark sequence is shorter: no figure
#: depends on it.
_MAX_MENDED_FRAMES = 100
#: Lengths (metres, along the measured step and straight ahead) the road searches around too while it has
#: measured no step yet: the features' first steps may rest on a vehicle moving with the camera.
_WIDE_LENGTHS_M = np.geomspace(0.1, 5.0, 28)
# Spread of the two-way refinement's step length over its normal equations' estimate (see _refine_two_way).
_SHARED = 2.0


class OdometryError(SelfContraError):
    """Visual odometry cannot estimate poses: too little texture, no motion, or bad input images."""


@dataclass(frozen=True)
class VOParams:
    """Parameters of :class:`StereoOdometry` (pixels unless stated otherwise).

    Attributes:
        features: left features kept per frame after bucketing.
        grid_rows: bucketing grid rows (each cell keeps ``features / cells`` corners).
        grid_cols: bucketing grid columns.
        fast_threshold: FAST threshold of the ORB detector (grey levels); low
            so that weakly textured surfaces still give corners.
        min_disparity: smallest stereo disparity kept; far points fix rotation
            but their depth is noise, so 1 px (about 380 m on KITTI) is the floor.
        max_disparity: largest disparity searched.
        epipolar_tolerance_px: largest row difference of a stereo match after
            sub-pixel refinement.
        ratio: Lowe's ratio of best to second-best descriptor distance.
        max_descriptor_distance: largest Hamming distance of an accepted ORB match (of 256 bits).
        search_radius_px: frame-to-frame search radius around the predicted position.
        first_search_radius_px: the same when no motion prediction exists (second frame, after a failure).
        lk_window: Lucas-Kanade window side of the frame-to-frame tracking (and
            of the ``parabola`` refinement's SAD window).
        stereo_window: Lucas-Kanade window (width, height) of the stereo
            refinement (``subpixel`` ``lk``). Wider than tall (19x9; 11x11
            before): Lucas-Kanade takes one disparity for the whole window,
            and a road's disparity changes by row (about 0.3 px per row in
            the bottom third of a KITTI-size image, +-1.5 px over 11 rows),
            so a square window measures road features up to a pixel off;
            fewer rows keep it nearer the feature's own row, more columns
            keep the texture. On a synthetic road plane the median disparity
            error falls from 0.43 px (11x11) to 0.28 (19x9) and 0.21 (19x7;
            a test). Highway seeds 1-30 (tuning; translation mean, 90th
            percentile, worst, bad reliable / reliable frames): 11x11 0.93 %
            (1.87, 3.23), 14 / 497; 19x9 0.79 % (1.29, 3.00), 3 / 514,
            seeds 1-5 below 1 %; 19x7 0.79 % (1.09, 4.27), 5 / 528 but seed 3
            2.07 % and, held out, seed 59 90 %; 21x5 0.79 % (1.15, 4.06),
            4 / 534 but street 0.26 -> 0.33 % (worst 0.86); 7x7 1.28 %
            (2.91, 7.20), 13 / 487. Held out (seeds 41-100, KITTI 06, street,
            orbit): docs/visual_odometry.md, fifth round.
        length_gate_sigmas: a ``weak_scale`` step whose length lies further
            than this many standard deviations (of the innovation) from the
            smoother's prediction is left out of :func:`smooth_step_lengths`
            (0: off). A ``weak_length_factor`` times larger noise is not
            enough when a truck moving with the camera is measured for
            several frames: its lengths are 13-68 % of the truth, and their
            noise, relative to those lengths, is small in metres (highway
            seed 78: 8.59 % -> 3.81 %; 6.98 -> 1.00 % with a 19x7 window).
            Reliable steps are never left out. Of highway seeds 1-30 and
            41-100 it changes seed 78 only.
        disparity_offset_px: added to every measured disparity, pixels: a
            rectification's known offset (rectified images shifted against
            each other by a fraction of a pixel make every disparity wrong by
            that much, and the depth wrong by a share that grows with it:
            0.3 px is 3 % at 10 px, 10 % at 3 px, so a highway's far points
            suffer most). With ``estimate_disparity_offset`` the value the
            estimate must differ from to be applied.
        estimate_disparity_offset: estimate the offset from the windowed
            adjustment (:meth:`StereoOdometry._estimate_offset`) and apply it
            once it differs significantly from ``disparity_offset_px``
            (offline, :func:`~selfcontra_ros.odometry.run.estimate_poses`
            then runs the sequence again, estimating around it, and a third
            time with that estimate fixed). On the KITTI 06 sample it
            finds about +0.2 px (disparities too small), which took the
            translation error from 1.37 to 0.83 % and the scale error from
            +1.05 to +0.30 %; on the synthetic scenes, whose disparities have
            no offset, it stays at 0 on most sequences, not all (docs/visual_odometry.md).
        offset_inlier_px: tracks with a residual above this after the
            adjustment are left out of the offset estimate.
        offset_step_px: the disparity shift ``h`` of the estimate's parabola.
        offset_min_windows: windows (sharing no frame) needed before the
            estimate may be applied.
        offset_sigmas: the mean of the windows' estimates is applied when it
            differs from ``disparity_offset_px`` by more than this many
            standard errors.
        offset_straddle_px: a feature whose stereo window straddles a depth
            edge is left out of the offset estimate: its disparity measured
            with the window's left and right halves alone (9x9, centred 5 px
            either side) differs by more than this (0: every feature counts).
            Such a window takes part of its disparity from the nearer side (a
            far corner beside a vehicle or a pole reads +0.5 px too large at
            0-2 px of disparity on the synthetic highway, against +0.07 px
            for the others), which the estimate read as a negative offset.
            With 1 px, held-out highway seeds 66 and 70 no longer take a false
            offset (-0.13 px; 0.95 -> 1.72 % and 1.10 -> 2.44 % with it), and
            a simulated 0.3 px offset is estimated a little closer (highway
            1-10: +0.19 -> +0.20 px on average, 1.37 -> 1.25 %); KITTI 06 and
            the synthetic sequences without offset are unchanged (docs/visual_odometry.md).
            0.5 and 2 px did worse on the shifted tuning highways 1-30
            (1.53 and 1.61 % against 1.45 % without seed 12).
        offset_window_std_px: a window's estimate counts only when the
            window itself pins the offset down to within this standard
            deviation (pixels): ``sigma h / sqrt(c)`` from its parabola, ``c``
            the cost's second difference and ``sigma`` the re-solved window's
            residual per degree of freedom (0: every window counts). Where the
            disparities are large (orbit: 30-60 px), an offset barely bends the
            window's cost (one window there pins it to 0.05-0.2 px; on KITTI 06
            and the highway to 0.015-0.05 px), and the features' own
            systematic errors of a tenth of a pixel, the same in every window,
            read as a significant offset (orbit seed 4: -0.48 px, 0.42 ->
            0.63 %). With 0.1 px orbit seeds 1-25 take no offset (4 did
            before); KITTI 06, street and the shifted highways 1-30 are
            unchanged, the highways 1-30, 41-100 and 101-130 but for seeds 11
            (1.55 -> 1.54 %) and 87 (2.26 -> 1.43 %). 0.05 px lost shifted
            highways (2.69 -> 2.77 %), 0.2 px let seed 4's offset back
            (docs/visual_odometry.md).
        offset_max_windows: the estimate is the mean of the latest this many
            windows (0: of every window since the start). A mean over all of
            them gets an ever smaller standard error the longer the node
            runs, until a systematic lean of a few hundredths of a pixel
            (the features' own, not the rig's) passes ``offset_sigmas`` and
            is applied; nor could it follow a rig whose offset drifts (heat).
            60 windows are about 300 frames of driving: on 300-frame
            highways (seeds 1, 13, 45; 58-59 windows) the estimate stayed
            unapplied, and no benchmark sequence (at most 10 windows) changes.
        ransac_threshold_px: PnP RANSAC inlier threshold.
        ransac_iterations: PnP RANSAC iterations.
        min_features: fewer left features than this: ``few_features``.
        min_matches: fewer frame-to-frame matches than this: ``few_matches``.
        min_inliers: fewer PnP inliers than this after refinement: ``few_inliers``.
        max_reprojection_error_px: RMS reprojection error of the inliers above
            this: ``high_error``.
        static_flow_px: median image motion of the inliers below this: the frame is ``static``.
        window: frames of the windowed bundle adjustment (<= 1 switches it off).
        seed: RANSAC seed (``cv2.setRNGSeed``) for reproducible poses.
        consistent_tracks: matched features move to the tracked position of
            the reference's point and their stereo is re-measured there.
        max_step_change_m: a motion whose translation differs from the
            constant-velocity prediction by more than this (metres) plus
            ``max_step_change_ratio`` times the predicted step is implausible:
            the largest rigid group is then taken to be a moving object, and
            the next largest is tried (status ``implausible`` if it fails too).
        max_step_change_ratio: see ``max_step_change_m``.
        subpixel: the sub-pixel refinement of stereo matches: ``lk``
            (Lucas-Kanade from the left feature), ``parabola`` (SAD at integer
            disparities and a parabola) or ``none`` (the right ORB corner).
        prior_gate: before RANSAC, drop matches whose point moved in the world
            under the constant-velocity prediction by more than its error and
            the depth noise explain (see ``max_step_change_m``,
            ``prior_rotation_deg``): vehicles, mostly.
        track_outlier_px: a track with a residual above this (pixels) in the
            windowed adjustment is not a static point: it is dropped, the
            window solved again, and it takes no further part (0: off, the
            default: on the benchmark it gained nothing and cost a second solve).
        prior_rotation_deg: the prediction's rotation error allowed by ``prior_gate``.
        disparity_threshold_px: largest difference between a match's disparity
            in the new frame and the one the motion predicts from the
            reference (grown by the squared ratio of the two disparities);
            0 switches the gate off. 0.5 px (1.0 before): vehicles far ahead
            that drive about as fast as the camera fit its motion in the left
            image and differ from the static scene by a few tenths of a pixel
            of disparity change; LK's disparity noise is about 0.15 px at the
            highway's disparities (see ``bench/odometry_accuracy.py
            --stereo-bias``). Highway seeds 1-10 with ``influence_share``
            0.75: 0.75 +- 0.21 % (worst 1.05), 7 bad reliable frames,
            against 0.85 +- 0.41 % (1.67), 11 bad, at 1.0 px; 0.3 px was
            worse (1.31 +- 0.95 %, worst 3.21, before ``influence_share``).
        depth_weighting: the frame-to-frame refinement weights each residual
            by the depth uncertainty of its triangulated point.
        check_scale: frames whose step length is not trustworthy to
            ``max_step_error_pct`` are flagged ``weak_scale`` (unreliable,
            but their measured motion is kept and tracked from).
        max_step_error_pct: the step-length error (percent of the step) a
            reliable frame must stay within: its ``scale_sigmas``-sigma
            uncertainty must not exceed it, its sensitivity to a ``disparity_bias_px`` disparity
            bias not ``bias_share`` of it, and the windowed adjustment's change
            of the step not ``adjustment_share`` of it.
        disparity_bias_px: the systematic disparity error the scale check
            guards against (pixels).
        scale_sigmas: see ``max_step_error_pct``. 4 (3 before) together with
            ``follow_unmatched``: see there.
        reference_focal_baseline: ``fx * b`` (pixel metres) that
            ``max_step_error_pct`` holds for, KITTI's; a camera with a smaller
            ``fx * b`` measures depth more coarsely, the labeler's tolerances
            grow with its depth noise, and the limit grows by this over its ``fx * b``.
        bias_share: see ``max_step_error_pct``.
        adjustment_share: see ``max_step_error_pct``.
        reanchor_after: a frame that gets no pose this many frames after the
            reference (which its features are leaving) becomes the reference
            itself, at its constant-velocity guess (0: never).
        interpolate_speed: a ``weak_scale`` frame's step keeps its measured
            rotation but takes the translation of the last reliable step, and
            when a reliable measured frame follows unreliable ones, their steps
            take translations interpolated between the reliable steps on both
            sides (a vehicle's velocity changes little from frame to frame);
            ``poses`` change, ``FrameQuality.translation_m`` stays the measured step.
        influence_grid: rows and columns of the image regions that
            ``influence_share`` leaves out one at a time ((1, 1): off).
        influence_share: a measured step whose length changes by more than
            this share of ``max_step_error_pct`` when the matches of one
            ``influence_grid`` region are left out (linearised, see
            :meth:`StereoOdometry._region_influence`) is ``weak_scale``; 0:
            off. Highway seeds 1-10 (with ``disparity_threshold_px`` 0.5):
            0.5 left seed 3 with 2 reliable frames of 30 and 15.2 %
            translation error; 0.75 gave 0.75 +- 0.21 % (worst 1.05), 7 bad
            reliable frames, 144 of 300 unreliable; 1.0 0.76 +- 0.29 % (worst
            1.43), 7 bad, 139 unreliable; off 0.88 +- 0.44 % (worst 1.94), 9
            bad, 133 unreliable. KITTI 06: 1.55 % (one frame flagged) against 1.58 %.
        smooth_lengths: after the whole sequence (:func:`smooth_step_lengths`,
            which :func:`~selfcontra_ros.odometry.run.estimate_poses` calls;
            the node's online odometry over the frames up to
            ``smoothing_lag_frames`` after each, and not at all, without
            delay, when this is off), the step lengths
            are smoothed by a Kalman filter and Rauch-Tung-Striebel smoother
            with a constant-velocity model of the step length: every step
            measured from the frame before (reliable or ``weak_scale``) is a
            measurement, weighted by its uncertainty; the steps keep their
            directions and rotations. Per-frame steps are noisier than
            their normal equations say (on the synthetic highway the
            frame-to-frame length error has a median of 1.5-2 standard
            deviations and a 95th percentile of 7.5), and a car's speed
            changes little between two frames, so neighbouring steps
            average the noise out.
        isolated_frames: a reliable frame with no other reliable frame
            within this many frames before and after it is reported
            unreliable (``isolated``); its pose is kept (0: off). A frame
            that passes every check amid frames whose step length the
            inliers could not pin down (a highway's far texture) has the
            same weak geometry and passed by chance: on the synthetic
            highway, tuning seeds 1-30 with and without a simulated 0.3 px
            offset, 2 frames take 42 of 965 reliable frames and 9 of their
            40 bad ones (more than 2 % off); held-out seeds 41-100, 53 of 860
            and 17 of 23 (docs/visual_odometry.md). Offline :func:`mark_isolated` applies it
            (:func:`~selfcontra_ros.odometry.run.estimate_poses`, after the
            smoother); the node's
            :class:`~selfcontra_ros.odometry.run.OnlineOdometry` applies it as
            frames arrive (:class:`IsolationGate`), deciding a frame that
            follows unreliable ones up to this many frames late.
        max_length_spread_pct: an ``ok`` frame whose smoothed step length
            the sequence pins down only to more than this (percent of the
            step; :func:`step_length_spread`, the smoother's own standard
            deviation with each step's reported noise) is reported
            unreliable (``uncertain``); its pose is kept (0: off). The
            smoother averages a step's noise with its neighbours'; where
            they are weak, missing, or on one side only (a sequence's first
            and last frames), it cannot. On the synthetic highway most bad
            reliable frames (more than 2 % off) sat there: 11 of 15 within
            four frames of a 30-frame sequence's ends, which hold a quarter
            of the reliable frames. Chosen as the largest limit that leaves
            no bad reliable frame on the tuning seeds 1-30 (their two at
            0.91 and 1.05 %). Bad / reliable frames, off -> 0.9: tuning
            seeds 1-30 2 / 496 -> 0 / 475; held out 41-100 9 / 799 -> 6 / 755
            and 101-130 4 / 440 -> 3 / 414, with a 0.3 px offset 63 / 777
            -> 49 / 726; the node (``--online``) 1-30 5 / 466 -> 2 / 442,
            41-100 9 / 738 -> 3 / 687; street and orbit seeds 1-10
            and KITTI 06 unchanged (no frame flagged); offline poses and
            translation errors unchanged (the node's poses chain from the
            last reliable frame, so they may move slightly: its mean
            translation errors read the same to 0.01 %, single sequences
            within 0.1 point). 0.8 would have left 3 and 2 held-out bad frames, for 11 %
            and 14 % of the reliable ones.
        road_steps: measure each step's length a second time on the road
            (:mod:`~selfcontra_ros.odometry.ground`: the plane under the
            camera found by stereo, the earlier image's road pixels aligned
            with the later image; ``FrameQuality.road_length_m``) and give it
            to the step-length smoother as a second measurement of the step
            (:func:`smooth_step_lengths`, :func:`step_length_spread`). The
            road is near (15-65 px of disparity on a KITTI-like rig) where
            a highway's corners are far (1-3 px), so a tenth of a pixel of
            disparity bias, which moves a feature step by several percent,
            moves the road's by a fraction of one. The features' checks
            decide as without it; the smoothed lengths change, and with
            the spread the frames reported ``uncertain`` (fewer). See
            docs/visual_odometry.md, fourteenth round.
        road_noise_pct: standard deviation of a road step length, percent of
            the step (measured mean absolute errors, per sequence: 0.15-0.7 %
            on highway seeds 78, 97 and 12, 0.3-0.4 % on orbit seeds 1 and
            8, 0.43 % on KITTI 06; set, not swept).
        road_agreement_pct: a road length is used only where a neighbouring
            frame's road length agrees with it within this (percent): an
            alignment started far off (a step measured on a truck) can settle
            on a wrong length that still looks well aligned, and two
            neighbours rarely settle on the same wrong one.
        road_motion: where the road's length of a step is used (agreed by a
            neighbour), the step also takes the road's rotation and
            translation direction (``FrameQuality.road_motion``) in place of
            the features' (:func:`smooth_step_lengths`). Against the exact
            poses, per step (medians; the windowed adjustment's steps
            against the road's on the same frames): rotation 17.3 -> 4.9
            mdeg and direction 0.24 -> 0.02 degrees on highway seeds 1-10,
            8.3 -> 1.4 mdeg and 0.18 -> 0.01 degrees on street 1-5, 21.9 ->
            18.8 mdeg and 0.24 -> 0.14 degrees on orbit 1-5 (a drone's
            ground is farther); on real KITTI 06 the rotations are as good
            as the features' (30 mdeg against GPS/INS), the directions a
            little better. Where the features failed (a truck filling the
            view) the road's motion replaces a constant-velocity guess.
            Translation errors, off -> on (docs/visual_odometry.md, fifteenth round):
            highway 1-30 0.40 -> 0.14 %, 41-100 0.46 -> 0.21 % (with every
            change of that round 0.18 %), street 0.14 -> 0.05 %, orbit
            0.36 -> 0.18 %, KITTI 06 0.77 -> 0.73 % (its rotation error
            0.0185 -> 0.0194 deg/m).
        smoothing_lag_frames: the node's
            :class:`~selfcontra_ros.odometry.run.OnlineOdometry` gives a
            frame its pose once this many frames after it have arrived, its
            step length smoothed (:func:`smooth_step_lengths`) over the
            frames up to then: a fixed-lag form of the offline smoother
            (``smooth_lengths`` off: the measured lengths, without delay).
            Chosen on the synthetic highway's tuning seeds 1-30 (bad
            reliable frames, more than 2 % off, of 463, and translation
            mean, replayed from one run's poses): lag 0 (the filter alone)
            16, 1.01 %; 1: 10; 2: 5; 3: 3, 0.86 %; 5: 3, 0.83 %; 10: 2,
            0.81 %; the whole sequence (offline) 2, 0.80 %. The node itself
            with 5 (docs/visual_odometry.md, ninth round): 5 of 463, 0.83 %, against 20 of
            484 and 1.25 % before (no smoothing, no ``isolated``); held-out
            seeds 41-100 8 of 750 (48 of 800 before). Each frame of lag
            delays the node's labels by one frame.
        length_acceleration_m: the smoother's process noise: standard
            deviation of the change of the step length from one frame to the
            next, metres per frame (0.02: 2 m/s^2 at 10 Hz).
        length_sigmas: a measured step's length noise is this many of its
            ``scale_std_pct``, at least ``length_floor_pct`` of it.
        length_floor_pct: see ``length_sigmas``.
        weak_length_factor: a ``weak_scale`` step's length noise is this
            many times a reliable one's. Highway seeds 1-10 (the tuning
            seeds; translation error, worst, bad reliable frames): no
            smoothing 0.75 +- 0.21 % (1.05), 7; factor 4 0.80 +- 0.50 %
            (2.19), 3; 8 0.71 +- 0.27 % (1.28), 3; 16 0.72 +- 0.29 % (1.43),
            3; weak steps left out 0.74 +- 0.36 % (1.71), 3 (all with
            ``length_acceleration_m`` 0.02; 0.01 and 0.04 with factor 8:
            0.66 % (1.41), 2 and 0.81 % (1.45), 4). Weighting a weak step
            by its own bias and region sensitivities instead of a factor
            was worse (factor 1: 0.99 +- 1.10 %, worst 4.24): the weak
            steps are off by more than their uncertainty says, vehicles
            among their matches. KITTI 06: 1.55 -> 1.48 %, bad reliable
            frames 15 -> 6; street and orbit seeds 1-3 unchanged (0.22 %).
        follow_unmatched: reference features the descriptors did not match
            are followed by Lucas-Kanade from their predicted position and
            matched to the new frame's corner where they went
            (:meth:`StereoOdometry._follow_unmatched`; on the highway about
            60 % of the reference features with a corner in reach fail the
            descriptor or ratio test). Measured with ``scale_sigmas`` 4 (3
            alone left the bad share among reliable frames as it was), one
            run each, translation mean +- std (worst), bad reliable /
            unreliable frames, before -> after: highway seeds 1-10 (tuning)
            0.71 +- 0.27 (1.28) 3 / 144 -> 0.78 +- 0.34 (1.40) 2 / 119;
            11-30 (tuning) 1.11 +- 0.75 (3.33) 10 / 308 -> 1.02 +- 0.80
            (2.79) 10 / 271; 31-40 0.89 +- 0.72 (2.85) 9 / 142 -> 0.68 +-
            0.23 (1.10) 4 / 125; 41-50 (rendered after the choice) 1.50 +-
            0.94 (3.58, 4 above 2 %) 6 / 180 -> 1.24 +- 0.73 (2.97, 1) 10 /
            167. KITTI 06 1.48 -> 1.44 %, bad reliable 6 -> 9; street
            seeds 1-10 0.23 (0.35) -> 0.26 (0.48) %, orbit 0.33 (0.56) ->
            0.31 (0.54) %.
        untrusted_override: when the constant-velocity prediction comes from
            a frame that failed a check (``weak_scale``), two consecutive
            frames whose largest rigid groups are implausible against it but
            agree with each other overrule it (the second is measured; see
            :meth:`StereoOdometry._confirms_untrusted_override`).
        max_velocity_change_m: a measured step whose translation differs from
            the last reliable step's by more than this per frame between them
            (metres; 0.1 is 10 m/s^2 at 10 Hz) is ``weak_scale``, unless the
            next measured step confirms it (0: off).
        stale_velocity_frames: a constant-velocity prediction older than
            this (frames since a frame measured the velocity) is dropped: the
            frame is measured as without one, as the second frame of a
            sequence is (the largest rigid group, the wide first search
            radius; 0: never). Without it, a failure during which the camera
            started to move locked the odometry for good, every later frame
            ``implausible`` against the old velocity (a car pulling away
            while a bus crosses in front; street and orbit seeds 1-10
            stopped for 8 frames, then 2 blank frames: 17 of 20 never
            measured a frame again). A tolerance that grows with the
            prediction's age instead let a vehicle moving slower than the
            camera through first (street seed 7: a reliable step 130 %
            off). See docs/visual_odometry.md.
    """

    features: int = 2000
    grid_rows: int = 4
    grid_cols: int = 12
    fast_threshold: int = 7
    min_disparity: float = 1.0
    max_disparity: float = 250.0
    epipolar_tolerance_px: float = 1.0
    ratio: float = 0.85
    max_descriptor_distance: int = 70
    search_radius_px: float = 30.0
    first_search_radius_px: float = 150.0
    lk_window: int = 11
    ransac_threshold_px: float = 1.5
    ransac_iterations: int = 300
    min_features: int = 60
    min_matches: int = 40
    min_inliers: int = 25
    max_reprojection_error_px: float = 1.5
    static_flow_px: float = 0.3
    window: int = 5
    seed: int = 0
    consistent_tracks: bool = True
    subpixel: str = "lk"
    prior_gate: bool = True
    track_outlier_px: float = 0.0
    prior_rotation_deg: float = 1.0
    disparity_threshold_px: float = 0.5
    depth_weighting: bool = True
    check_scale: bool = True
    max_step_error_pct: float = 2.0
    disparity_bias_px: float = 0.1
    scale_sigmas: float = 4.0
    bias_share: float = 0.5
    reference_focal_baseline: float = 379.8
    adjustment_share: float = 0.5
    reanchor_after: int = 2
    interpolate_speed: bool = True
    max_velocity_change_m: float = 0.1
    max_step_change_m: float = 0.3
    max_step_change_ratio: float = 0.25
    stale_velocity_frames: int = 10
    influence_grid: tuple[int, int] = (3, 8)
    influence_share: float = 0.75
    smooth_lengths: bool = True
    length_acceleration_m: float = 0.02
    length_sigmas: float = 3.0
    length_floor_pct: float = 1.0
    weak_length_factor: float = 8.0
    follow_unmatched: bool = True
    untrusted_override: bool = True
    stereo_window: tuple[int, int] = (19, 9)
    length_gate_sigmas: float = 3.0
    isolated_frames: int = 2
    smoothing_lag_frames: int = 5
    disparity_offset_px: float = 0.0
    estimate_disparity_offset: bool = True
    offset_inlier_px: float = 0.6
    offset_step_px: float = 0.25
    offset_min_windows: int = 3
    offset_sigmas: float = 3.0
    offset_straddle_px: float = 1.0
    offset_window_std_px: float = 0.1
    offset_max_windows: int = 60
    max_length_spread_pct: float = 0.9
    road_steps: bool = True
    road_noise_pct: float = 0.5
    road_agreement_pct: float = 3.0
    road_motion: bool = True

    def __post_init__(self) -> None:
        positive = ("features", "grid_rows", "grid_cols", "lk_window", "ransac_iterations", "min_inliers")
        for name in positive:
            if int(getattr(self, name)) < 1:
                raise OdometryError(f"VOParams.{name} must be >= 1, got {getattr(self, name)!r}")
        if not np.isfinite(self.disparity_offset_px) or abs(self.disparity_offset_px) > 5.0:
            raise OdometryError(
                f"VOParams.disparity_offset_px must be finite and within +-5 px, got {self.disparity_offset_px!r}"
            )
        for name in ("offset_inlier_px", "offset_step_px", "offset_sigmas"):
            if not float(getattr(self, name)) > 0:
                raise OdometryError(f"VOParams.{name} must be > 0, got {getattr(self, name)!r}")
        if int(self.offset_min_windows) < 2:
            raise OdometryError(f"VOParams.offset_min_windows must be >= 2, got {self.offset_min_windows!r}")
        if 0 < int(self.offset_max_windows) < int(self.offset_min_windows):
            raise OdometryError(
                f"VOParams.offset_max_windows must be 0 (every window) or >= offset_min_windows "
                f"({self.offset_min_windows}), got {self.offset_max_windows!r}"
            )
        for name in (
            "offset_straddle_px", "offset_window_std_px", "length_gate_sigmas", "isolated_frames",
            "smoothing_lag_frames", "stale_velocity_frames", "offset_max_windows", "max_length_spread_pct",
        ):  # fmt: skip
            if not float(getattr(self, name)) >= 0:
                raise OdometryError(f"VOParams.{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("road_noise_pct", "road_agreement_pct"):
            if not float(getattr(self, name)) > 0:
                raise OdometryError(f"VOParams.{name} must be > 0, got {getattr(self, name)!r}")
        if len(self.stereo_window) != 2 or min(int(v) for v in self.stereo_window) < 3:
            raise OdometryError(
                f"VOParams.stereo_window must be (width, height), each >= 3, got {self.stereo_window!r}"
            )
        if not 0 < self.min_disparity < self.max_disparity:
            raise OdometryError(
                f"VOParams needs 0 < min_disparity < max_disparity, got {self.min_disparity}, {self.max_disparity}"
            )
        if self.subpixel not in ("lk", "parabola", "none"):
            raise OdometryError(f"VOParams.subpixel must be lk, parabola or none, got {self.subpixel!r}")
        if not 0 < self.ratio <= 1:
            raise OdometryError(f"VOParams.ratio must be in (0, 1], got {self.ratio}")


@dataclass(frozen=True)
class FrameQuality:
    """How far the pose of one frame can be trusted.

    Attributes:
        index: frame number (order of :meth:`StereoOdometry.add` calls, from 0).
        stamp: the caller's stamp (seconds or nanoseconds, as given).
        status: one of :data:`STATUSES`.
        reliable: the pose is an estimate, not a guess (status first, ok or static).
        features: left features detected.
        stereo_matches: left features with a stereo match (a 3D point).
        temporal_matches: matches with the reference frame.
        inliers: matches consistent with the final pose.
        reprojection_error_px: RMS stereo reprojection error of the inliers (NaN without a pose).
        translation_m: distance moved since the previous frame, metres.
        rotation_deg: rotation since the previous frame, degrees.
        reference: the frame the pose was estimated from (-1 for the first frame).
        message: why the frame is unreliable (empty when reliable).
        scale_std_pct: standard deviation of the frame-to-frame step length, percent of it (NaN without a pose).
        scale_bias_pct: change of the step length, percent, if every disparity were
            ``VOParams.disparity_bias_px`` smaller (NaN without a pose).
        adjustment_change_pct: change of the step length by the windowed adjustment, percent (NaN without one).
        scale_influence_pct: the largest change of the frame-to-frame step
            length, percent, when the matches of one image region are left
            out (``VOParams.influence_grid``; NaN without a pose).
        disparity_offset_px: the offset added to this frame's measured
            disparities (``VOParams.disparity_offset_px``, or the running
            estimate: :attr:`StereoOdometry.disparity_offset`).
        road_length_m: the step's length measured on the road
            (:func:`~selfcontra_ros.odometry.ground.road_step`, ``VOParams.road_steps``), metres: the step
            from the frame before, whatever frame the features were measured from; NaN where the road did
            not give it.
        road_pixels: road pixels that measured it (0: none).
        road_motion: the step ``T_prev_cur`` the road measured, as a rotation vector (radians) and a
            translation (metres) in the previous frame's camera frame; empty where ``road_length_m`` is NaN.
    """

    index: int
    stamp: float
    status: str
    reliable: bool
    features: int
    stereo_matches: int
    temporal_matches: int = 0
    inliers: int = 0
    reprojection_error_px: float = float("nan")
    translation_m: float = 0.0
    rotation_deg: float = 0.0
    reference: int = -1
    message: str = ""
    scale_std_pct: float = float("nan")
    scale_bias_pct: float = float("nan")
    adjustment_change_pct: float = float("nan")
    scale_influence_pct: float = float("nan")
    disparity_offset_px: float = 0.0
    road_length_m: float = float("nan")
    road_pixels: int = 0
    road_motion: tuple[float, ...] = ()


@dataclass(frozen=True)
class OdometryResult:
    """The outcome of one frame: ``pose`` (4x4 ``T_world_left``, metres) and its quality."""

    pose: F64
    quality: FrameQuality


@dataclass
class _Features:
    """Stereo features of one frame; row ``i`` of each array describes feature ``i``."""

    uv: F64  # (N, 2) left pixel positions
    disparity: F64  # (N,) pixels; u_right = u_left - disparity
    descriptors: NDArray[np.uint8]  # (N, 32) ORB
    points: F64  # (N, 3) left-camera frame, metres
    track_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    # (N,) stereo window across a depth edge (:meth:`StereoOdometry._straddles`); empty when not measured.
    straddle: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    # The road plane with this run's disparity offset (``VOParams.road_steps``), or None.
    ground: GroundPlane | None = None


@dataclass(frozen=True)
class StereoMatches:
    """One pair's stereo matches before the disparity offset: what a later pass over the same images reuses.

    Row ``i`` of each array is candidate ``i``: a left ORB feature matched to
    a right corner on its row whose sub-pixel right position stayed on the
    row. The gates the offset moves (disparity range, refinement distance)
    are applied by :meth:`StereoOdometry._stereo` with the offset of its run.
    """

    uv: F64  # (M, 2) left pixel positions
    descriptors: NDArray[np.uint8]  # (M, 32) ORB
    guess_u: F64  # (M,) the matched right corner's column
    found_u: F64  # (M,) the refined right column, as the images show it (no offset)
    detected: int  # left features detected (bucketed), matched or not
    # (M,) the straddle test (StereoOdometry._straddles) on the raw disparities, measured when the offset is
    # estimated; None otherwise.
    straddle: NDArray[np.bool_] | None = None
    # The road plane of the pair, as the images show it (no offset; :func:`fit_ground`), when ``road_steps``.
    ground: GroundPlane | None = None

    @classmethod
    def empty(cls, detected: int) -> StereoMatches:
        """No match (no corner in one of the images); ``detected`` left features."""
        return cls(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0), np.zeros(0), detected)

    @property
    def nbytes(self) -> int:
        """Memory held by the arrays, bytes."""
        arrays = (self.uv, self.descriptors, self.guess_u, self.found_u)
        total = sum(a.nbytes for a in arrays) + (0 if self.straddle is None else self.straddle.nbytes)
        return total + (0 if self.ground is None else self.ground.nbytes)


class StereoCache:
    """Stereo matches of one sequence's frames by frame index, for later passes over the same images.

    The offline odometry runs a sequence again when its disparity offset
    estimate becomes significant (:func:`~selfcontra_ros.odometry.run.estimate_poses`);
    a later pass differs only in the offset, which moves every right
    position by the same amount after the matching. Its stereo matching
    (ORB on both images, row matching, the sub-pixel step: half of a pass's
    time) is therefore the first pass's, taken from here, and the poses are
    the same as when measured again (a test checks it). Entries are valid
    only for the same frames in the same order and for parameters that
    differ at most in ``disparity_offset_px`` and ``estimate_disparity_offset``;
    other parameters miss. At most ``max_bytes`` of matches are kept (about
    50 kB a KITTI-size frame, up to 40 kB more with the road's plane); frames beyond it are measured
    again.
    """

    def __init__(self, max_bytes: int = 512 * 2**20) -> None:
        self.max_bytes = int(max_bytes)
        self.nbytes = 0
        self.hits = 0
        self._matches: dict[int, StereoMatches] = {}
        self._params: VOParams | None = None

    def __len__(self) -> int:
        return len(self._matches)

    @staticmethod
    def _front_end(params: VOParams) -> VOParams:
        return replace(params, disparity_offset_px=0.0, estimate_disparity_offset=False)

    def get(self, index: int, params: VOParams) -> StereoMatches | None:
        """The matches stored for frame ``index`` under ``params`` (see the class), or None."""
        if self._params is None or self._front_end(params) != self._params:
            return None
        matches = self._matches.get(index)
        self.hits += matches is not None
        return matches

    def put(self, index: int, params: VOParams, matches: StereoMatches) -> None:
        """Store frame ``index``'s matches measured under ``params``, unless the cache is full or holds
        another parameter set's."""
        front_end = self._front_end(params)
        if self._params is None:
            self._params = front_end
        if front_end != self._params or self.nbytes + matches.nbytes > self.max_bytes:
            return
        previous = self._matches.get(index)
        self.nbytes += matches.nbytes - (previous.nbytes if previous is not None else 0)
        self._matches[index] = matches


@dataclass
class _WindowFrame:
    """A reliable frame kept for the windowed bundle adjustment."""

    index: int
    pose: F64  # T_world_left
    track_ids: NDArray[np.int64]
    uv: F64
    u_right: F64
    straddle: NDArray[np.bool_]  # per feature (all False where not measured): see _Features.straddle

    @classmethod
    def of(cls, index: int, pose: F64, features: _Features) -> _WindowFrame:
        """The window frame of frame ``index`` at ``pose`` (``T_world_left``, copied by the caller if shared)
        with ``features`` (their track ids set)."""
        straddle = features.straddle.copy() if features.straddle.size else np.zeros(len(features.uv), bool)
        right = features.uv[:, 0] - features.disparity
        return cls(index, pose, features.track_ids, features.uv.copy(), right, straddle)


def _grey(image: NDArray[np.uint8], what: str) -> NDArray[np.uint8]:
    array = np.asarray(image)
    if array.dtype != np.uint8:
        raise OdometryError(f"{what} image must be uint8, got {array.dtype}")
    if array.ndim == 3 and array.shape[2] == 3:
        return np.ascontiguousarray(cv2.cvtColor(array, cv2.COLOR_RGB2GRAY))
    if array.ndim != 2:
        raise OdometryError(f"{what} image must be HxW grey or HxWx3 RGB, got shape {array.shape}")
    return np.ascontiguousarray(array)


def _rotation_deg(rotation: F64) -> float:
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def _pose_from_vector(x: F64) -> F64:
    """4x4 transform of a 6-vector (rotation vector, translation)."""
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    pose[:3, 3] = x[3:6]
    return pose


def _vector_from_pose(pose: F64) -> F64:
    from scipy.spatial.transform import Rotation

    return np.concatenate([Rotation.from_matrix(pose[:3, :3]).as_rotvec(), pose[:3, 3]])


class FrameLog(Generic[_T]):
    """Per-frame values by frame index, like a list that can forget its oldest entries.

    ``len`` is the number of frames ever appended, so indices stay the
    frames' own after forgetting; reading a forgotten frame raises
    :class:`IndexError` naming it. A node that runs for hours keeps only
    what the odometry still reads (:meth:`StereoOdometry.forget_before`).
    """

    def __init__(self) -> None:
        self._items: dict[int, _T] = {}
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def __bool__(self) -> bool:
        return self._count > 0

    def append(self, value: _T) -> None:
        self._items[self._count] = value
        self._count += 1

    def _index(self, index: int) -> int:
        k = index + self._count if index < 0 else index
        if not 0 <= k < self._count:
            raise IndexError(f"frame {index} out of range ({self._count} frames)")
        return k

    @overload
    def __getitem__(self, index: int) -> _T: ...
    @overload
    def __getitem__(self, index: slice) -> list[_T]: ...
    def __getitem__(self, index: int | slice) -> _T | list[_T]:
        if isinstance(index, slice):
            return [self[k] for k in range(*index.indices(self._count))]
        k = self._index(index)
        try:
            return self._items[k]
        except KeyError:
            raise IndexError(f"frame {k} was forgotten (forget_before)") from None

    def __setitem__(self, index: int, value: _T) -> None:
        k = self._index(index)
        if k not in self._items:
            raise IndexError(f"frame {k} was forgotten (forget_before)")
        self._items[k] = value

    def __iter__(self) -> Iterator[_T]:
        return iter(self[:])

    def holds(self, index: int) -> bool:
        """Whether frame ``index`` is still held (appended and not forgotten)."""
        return index in self._items

    def forget(self, indices: Iterable[int]) -> int:
        """Forget these frames (those still held); returns how many."""
        gone = [k for k in indices if k in self._items]
        for k in gone:
            del self._items[k]
        return len(gone)

    def held(self) -> list[int]:
        """The indices still held, oldest first."""
        return sorted(self._items)


class StereoOdometry:
    """Stereo visual odometry fed one rectified pair at a time, online or offline.

    Example::

        vo = StereoOdometry(camera)
        for frame in sequence:
            result = vo.add(frame.left, frame.right, stamp=frame.stamp)
            if result.quality.reliable:
                use(result.pose)

    :meth:`add` returns the pose at once (for a ROS node); the windowed
    refinement keeps improving the last ``window`` poses, and
    :attr:`poses` holds the final values (what offline runs write).
    """

    def __init__(
        self, camera: StereoCamera, params: VOParams | None = None, *, stereo_cache: StereoCache | None = None
    ) -> None:
        self.camera = camera
        self.params = params or VOParams()
        #: The stereo matches of earlier passes over the same frames (frame index = the frame's position in
        #: this run), reused instead of measured; filled with this run's when set (see :class:`StereoCache`).
        self.stereo_cache = stereo_cache
        p = self.params
        # Many more corners than kept: bucketing then picks the strongest per cell.
        self._orb = cv2.ORB.create(
            nfeatures=4 * p.features, scaleFactor=1.2, nlevels=4, edgeThreshold=19, patchSize=19,
            fastThreshold=p.fast_threshold,
        )  # fmt: skip
        self._lk_criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        self.poses: FrameLog[F64] = FrameLog()
        self.qualities: FrameLog[FrameQuality] = FrameLog()
        self._reference: tuple[int, NDArray[np.uint8], _Features] | None = None
        self._velocity: F64 | None = None  # T_ref_cur per frame of the last reliable step
        self._next_track = 0
        self._window: deque[_WindowFrame] = deque(maxlen=max(self.params.window, 1))
        self._bad_tracks: set[int] = set()  # tracks the windowed adjustment found moving
        self._reliable_step: F64 | None = None  # translation of the last reliable measured step, metres
        self._reliable_index = 0  # its frame
        self._velocity_index = 0  # the frame that measured _velocity
        self._jump_candidate: F64 | None = None  # the last step flagged by _check_velocity_change
        self._velocity_trusted = False  # the velocity comes from a frame that passed every check
        self._implausible_candidate: F64 | None = None  # T_ref_cur per frame of the last implausible frame's group
        #: Left pixel positions (N, 2) of the last frame's inliers (empty when it got no pose): diagnostics.
        self.last_inliers: F64 = np.zeros((0, 2))
        #: Disparities (N,) of the last frame's inliers in the new frame, pixels: diagnostics.
        self.last_inlier_disparity: F64 = np.zeros(0)
        #: Left pixel positions (N, 2) of the last frame's stereo features: diagnostics.
        self.last_features: F64 = np.zeros((0, 2))
        self._offset = float(p.disparity_offset_px)  # added to every measured disparity, pixels
        # One window's estimate of the whole offset each, the latest ``offset_max_windows``.
        self._offset_windows: deque[float] = deque(maxlen=int(self.params.offset_max_windows) or None)
        self._adjustments = 0
        self._road_translation = np.full(3, np.nan)  # the last step the road measured (T_cur_ref), metres
        # The frame before's index, left image and road plane: the road measures every step from it.
        self._previous: tuple[int, NDArray[np.uint8], GroundPlane | None] | None = None

    @property
    def disparity_offset(self) -> float:
        """The offset (pixels) now added to every measured disparity: ``VOParams.disparity_offset_px`` until
        the windows' estimates (:meth:`offset_estimate`) differ from it significantly, then their mean."""
        return self._offset

    def offset_estimate(self) -> tuple[float, float, int]:
        """The windows' estimate of the disparity offset: mean, its standard error (pixels; NaN before
        ``VOParams.offset_min_windows`` windows) and the number of windows, the latest
        ``VOParams.offset_max_windows`` of them."""
        n = len(self._offset_windows)
        if n == 0:
            return float("nan"), float("nan"), 0
        values = np.asarray(self._offset_windows)
        if n < self.params.offset_min_windows:
            return float(values.mean()), float("nan"), n
        return float(values.mean()), max(float(values.std(ddof=1)), _OFFSET_STD_FLOOR_PX) / np.sqrt(n), n

    # ------------------------------------------------------------------ features and stereo

    def _detect(self, image: NDArray[np.uint8]) -> tuple[F64, NDArray[np.uint8], NDArray[np.int64]]:
        """ORB corners bucketed over the grid: positions (N, 2), descriptors (N, 32), pyramid octaves (N,)."""
        p = self.params
        keypoints = self._orb.detect(image, None)
        if not keypoints:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
        uv = np.array([k.pt for k in keypoints], dtype=np.float64)
        response = np.array([k.response for k in keypoints])
        h, w = image.shape
        cell = (np.minimum(uv[:, 1] * p.grid_rows // h, p.grid_rows - 1) * p.grid_cols
                + np.minimum(uv[:, 0] * p.grid_cols // w, p.grid_cols - 1)).astype(np.int64)  # fmt: skip
        order = np.lexsort((-response, cell))
        sorted_cells = cell[order]
        first_of_cell = np.searchsorted(sorted_cells, sorted_cells, side="left")
        rank = np.arange(order.size) - first_of_cell
        per_cell = max(p.features // (p.grid_rows * p.grid_cols), 1)
        keep = order[rank < per_cell]
        kept, descriptors = self._orb.compute(image, [keypoints[i] for i in keep])
        if descriptors is None or not kept:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
        uv = np.array([k.pt for k in kept], dtype=np.float64)
        octave = np.array([k.octave for k in kept], dtype=np.int64)
        return uv, np.asarray(descriptors, dtype=np.uint8), octave

    def _all_corners(self, image: NDArray[np.uint8]) -> tuple[F64, NDArray[np.uint8]]:
        """Every ORB corner of an image (no bucketing): the right image's candidates."""
        keypoints, descriptors = self._orb.detectAndCompute(image, None)
        if descriptors is None or not keypoints:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        return np.array([k.pt for k in keypoints], dtype=np.float64), np.asarray(descriptors, dtype=np.uint8)

    def _ratio_matches(
        self,
        query: NDArray[np.uint8],
        train: NDArray[np.uint8],
        qi: NDArray[np.int64],
        ti: NDArray[np.int64],
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Query/train index pairs among the candidate pairs ``(qi, ti)`` passing the distance bound, the ratio
        test and uniqueness.

        Each query's best and second-best train feature are taken among its
        candidates only (Hamming distance of the 256-bit ORB descriptors), as
        a masked brute-force k=2 search would take them; a query with one
        candidate has no second, and passes the ratio test.
        """
        if qi.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        distance = _hamming(query[qi], train[ti])
        at, second = _best_two(qi, distance)
        q, t, b = qi[at], ti[at], distance[at].astype(np.float64)
        ok = (b <= self.params.max_descriptor_distance) & (b < self.params.ratio * second)
        q, t, b = q[ok], t[ok], b[ok]
        # One query per train feature: the closest wins, ties and the rest are dropped.
        order = np.lexsort((b, t))
        t_sorted = t[order]
        first = np.ones(order.size, dtype=bool)
        first[1:] = t_sorted[1:] != t_sorted[:-1]
        keep = order[first]
        return q[keep], t[keep]

    def _lk(
        self,
        source: NDArray[np.uint8],
        target: NDArray[np.uint8],
        points: F64,
        guess: F64,
        window: tuple[int, int] | None = None,
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Lucas-Kanade positions in ``target`` of ``points`` of ``source``, started at ``guess``; ``window``
        (width, height) defaults to the square ``lk_window``."""
        if points.shape[0] == 0:
            return np.zeros((0, 2)), np.zeros(0, bool)
        size = (int(window[0]), int(window[1])) if window else (self.params.lk_window, self.params.lk_window)
        found, status, _ = cv2.calcOpticalFlowPyrLK(
            source, target, points.astype(np.float32).reshape(-1, 1, 2), guess.astype(np.float32).reshape(-1, 1, 2),
            winSize=size, maxLevel=1, criteria=self._lk_criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )  # fmt: skip
        return found.reshape(-1, 2).astype(np.float64), status.reshape(-1).astype(bool)

    def _stereo(self, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> tuple[_Features, int]:
        """Stereo features of a pair and the number of left features detected.

        The matches before the disparity offset (:class:`StereoMatches`) come
        from :attr:`stereo_cache` when it holds this frame (a later pass over
        the same images), else they are measured (and stored there when a
        cache is set); the offset and the gates it moves are applied here.
        """
        p = self.params
        index = len(self.poses)
        cache = self.stereo_cache
        matches = cache.get(index, p) if cache is not None else None
        if matches is None:
            matches = self._stereo_matches(left, right)
            if cache is not None:
                cache.put(index, p, matches)
        right_u = matches.found_u - self._offset  # u_left - u_right + offset is the disparity
        d = matches.uv[:, 0] - right_u
        ok = (np.abs(right_u - matches.guess_u) <= 3.0) & (d >= p.min_disparity) & (d <= p.max_disparity)
        uv, d = matches.uv[ok], d[ok]
        if matches.straddle is not None and self._measures_straddle:
            straddle = matches.straddle[ok]  # measured on the raw disparities: the same in every pass
        else:
            straddle = self._straddles(left, right, uv, d)
        ground = None if matches.ground is None else matches.ground.shifted(self._offset, self.camera)
        features = _Features(uv, d, matches.descriptors[ok], self._triangulate(uv, d), straddle=straddle, ground=ground)
        return features, matches.detected

    def _stereo_matches(self, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> StereoMatches:
        """A pair's stereo matches before the disparity offset: ORB on both images, matched along the rows,
        the right positions refined (``params.subpixel``) and kept where the refinement stayed on the row."""
        p = self.params
        uv, descriptors, octave = self._detect(left)
        ruv, rdesc = self._all_corners(right)
        if uv.shape[0] == 0 or ruv.shape[0] == 0:
            return StereoMatches.empty(len(uv))
        # Epipolar band: ORB positions of coarser octaves are coarser, so the band widens with the octave.
        band = 2.0 * 1.2 ** octave.astype(np.float64) + p.epipolar_tolerance_px
        qi, ti = _row_candidates(uv[:, 1], ruv[:, 1], band)
        disparity = uv[qi, 0] - ruv[ti, 0]
        inside = (disparity >= p.min_disparity - 2.0) & (disparity <= p.max_disparity)
        inside &= np.abs(uv[qi, 1] - ruv[ti, 1]) <= band[qi]
        qi, ti = self._ratio_matches(descriptors, rdesc, qi[inside], ti[inside])
        guess = np.column_stack([ruv[ti, 0], uv[qi, 1]])
        found, ok = self._refine_right_raw(left, right, uv[qi], guess)
        ok &= np.abs(found[:, 1] - uv[qi, 1]) <= p.epipolar_tolerance_px
        qi = qi[ok]
        straddle = None
        if self._measures_straddle:
            straddle = self._straddles_raw(left, right, uv[qi], uv[qi, 0] - found[ok, 0])
        ground = fit_ground(left, right, self.camera, seed=p.seed) if p.road_steps else None
        return StereoMatches(uv[qi], descriptors[qi], guess[ok, 0], found[ok, 0], len(uv), straddle, ground)

    def _straddles(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv: F64, disparity: F64
    ) -> NDArray[np.bool_]:
        """Which stereo features (left ``uv``, measured ``disparity``) straddle a depth edge (``offset_straddle_px``).

        Each feature's disparity is measured again, by Lucas-Kanade from its
        measured one, in a 9x9 window 5 px to its left and in one 5 px to its
        right: the two halves of its stereo window. Where they differ by more
        than ``offset_straddle_px``, or either fails, the window saw two
        depths. Only measured while the offset is estimated (empty otherwise).
        """
        if not (self._measures_straddle and len(uv)):
            return np.zeros(0, bool)
        # The offset moved the right positions; the halves are measured raw.
        return self._straddles_raw(left, right, uv, disparity - self._offset)

    @property
    def _measures_straddle(self) -> bool:
        """Whether the straddle test runs: only while the offset is estimated, and when it is on."""
        return self.params.estimate_disparity_offset and self.params.offset_straddle_px > 0

    def _straddles_raw(self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv: F64, raw: F64) -> NDArray[np.bool_]:
        """:meth:`_straddles` of features whose disparities ``raw`` are as the images show them (no offset)."""
        if not len(uv):
            return np.zeros(0, bool)
        found_both = np.ones(len(uv), dtype=bool)
        halves = []
        for side in (-_HALF_SHIFT_PX, _HALF_SHIFT_PX):
            points = uv + np.array([side, 0.0])
            guess = points - np.column_stack([raw, np.zeros(len(uv))])
            found, ok = self._lk(left, right, points, guess, _HALF_WINDOW)
            halves.append(points[:, 0] - found[:, 0])
            found_both &= ok
        return ~found_both | (np.abs(halves[0] - halves[1]) > self.params.offset_straddle_px)

    def _refine_right(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv: F64, guess: F64
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Sub-pixel right positions (N, 2) of left features ``uv`` started at ``guess``, by ``params.subpixel``,
        moved by the disparity offset (:attr:`disparity_offset`)."""
        found, ok = self._refine_right_raw(left, right, uv, guess)
        # The disparity offset (u_left - u_right + offset is the disparity): the right position moves left.
        found[:, 0] -= self._offset
        return found, ok

    def _refine_right_raw(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv: F64, guess: F64
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Sub-pixel right positions (N, 2) of left features ``uv`` started at ``guess``, by ``params.subpixel``,
        as the images show them (no offset)."""
        method = self.params.subpixel
        if method == "lk":
            return self._lk(left, right, uv, guess, self.params.stereo_window)
        if method == "none":
            return guess.copy(), np.ones(len(uv), dtype=bool)
        return self._parabola(left, right, uv, guess)

    def _parabola(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv: F64, guess: F64
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Right positions by SAD block matching at integer disparities and a parabola through the best three.

        The classic sub-pixel step of block matchers, kept to measure its
        bias against Lucas-Kanade (pixel locking: estimates pulled towards
        integer disparities).
        """
        n, half, reach = len(uv), self.params.lk_window // 2, 3
        if n == 0:
            return np.zeros((0, 2)), np.zeros(0, bool)
        offsets = np.arange(-half, half + 1, dtype=np.float32)
        dx, dy = np.meshgrid(offsets, offsets)
        rows = (uv[:, 1, None, None] + dy).astype(np.float32)
        left_patch = cv2.remap(left, (uv[:, 0, None, None] + dx).astype(np.float32).reshape(n * dx.shape[0], -1),
                               rows.reshape(n * dx.shape[0], -1), cv2.INTER_LINEAR).astype(np.float32)  # fmt: skip
        base = np.rint(uv[:, 0] - guess[:, 0])
        costs = np.empty((n, 2 * reach + 1))
        for k, shift in enumerate(range(-reach, reach + 1)):
            cols = (uv[:, 0, None, None] - (base + shift)[:, None, None] + dx).astype(np.float32)
            patch = cv2.remap(right, cols.reshape(n * dx.shape[0], -1), rows.reshape(n * dx.shape[0], -1),
                              cv2.INTER_LINEAR).astype(np.float32)  # fmt: skip
            costs[:, k] = np.abs(patch - left_patch).reshape(n, -1).sum(axis=1)
        best = np.clip(np.argmin(costs, axis=1), 1, 2 * reach - 1)
        c0, c1, c2 = (costs[np.arange(n), best + j] for j in (-1, 0, 1))
        curvature = c0 - 2.0 * c1 + c2
        ok = curvature > 0
        offset = np.where(ok, 0.5 * (c0 - c2) / np.where(ok, curvature, 1.0), 0.0)
        disparity = base + (best - reach) + offset
        return np.column_stack([uv[:, 0] - disparity, uv[:, 1]]), ok

    def _move_features(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        cur: _Features,
        ri: NDArray[np.int64],
        ci: NDArray[np.int64],
        cur_uv: F64,
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], F64]:
        """Move matched features of the new frame to where the reference's point was tracked; re-measure stereo there.

        The ORB corner a reference feature is matched to lies up to 3 px from
        the tracked position of the same surface point; keeping the corner
        would let a track slide over the surface from frame to frame (noise
        the windowed adjustment reads as motion). Matches whose stereo fails
        at the tracked position are dropped.
        """
        p = self.params
        guess = cur_uv - np.column_stack([cur.disparity[ci], np.zeros(len(ci))])
        refined, ok = self._refine_right(left, right, cur_uv, guess)
        d = cur_uv[:, 0] - refined[:, 0]
        ok &= np.abs(refined[:, 1] - cur_uv[:, 1]) <= p.epipolar_tolerance_px
        ok &= np.abs(refined[:, 0] - guess[:, 0]) <= 1.5
        ok &= (d >= p.min_disparity) & (d <= p.max_disparity)
        ri, ci, cur_uv, d = ri[ok], ci[ok], cur_uv[ok], d[ok]
        if cur.straddle.size:
            cur.straddle[ci] = self._straddles(left, right, cur_uv, d)
        cur.uv[ci] = cur_uv
        cur.disparity[ci] = d
        cur.points[ci] = self._triangulate(cur_uv, d)
        return ri, ci, cur_uv

    def _follow_unmatched(
        self,
        ref_image: NDArray[np.uint8],
        image: NDArray[np.uint8],
        ref: _Features,
        cur: _Features,
        pred_uv: F64,
        seen: NDArray[np.int64],
        radius: float,
        ri: NDArray[np.int64],
        ci: NDArray[np.int64],
        cur_uv: F64,
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], F64]:
        """Add matches for reference features the descriptors did not match, by following them with Lucas-Kanade.

        Each unmatched reference feature predicted into the view (``seen``,
        at ``pred_uv``) is followed from its prediction into ``image``; it
        must come back within 0.5 px (forward-backward) and stay within the
        search ``radius``. It is then matched to the new frame's corner
        within 3 px of where it went (the nearest; not added when that corner
        is already matched; each corner once), like a descriptor match after
        its sub-pixel step.
        Returns the matches (reference, new) and the followed positions,
        the new ones appended.
        """
        rest = np.setdiff1d(seen, ri)
        if rest.size == 0 or len(cur.uv) == 0:
            return ri, ci, cur_uv
        went, found = self._lk(ref_image, image, ref.uv[rest], pred_uv[rest])
        back, returned = self._lk(image, ref_image, went, ref.uv[rest])
        found &= returned & (np.linalg.norm(back - ref.uv[rest], axis=1) <= 0.5)
        found &= np.linalg.norm(went - pred_uv[rest], axis=1) <= radius
        rest, went = rest[found], went[found]
        q, t = _row_candidates(went[:, 1], cur.uv[:, 1], np.full(len(went), 3.0))
        distance = np.linalg.norm(went[q] - cur.uv[t], axis=1)
        close = distance <= 3.0
        q, t, distance = q[close], t[close], distance[close]
        nearest, _ = _best_two(q, distance)  # per followed feature, its nearest corner
        q, t = q[nearest], t[nearest]
        free = ~np.isin(t, ci)  # nearest corner already matched by its descriptor: the feature is not added
        q, t = q[free], t[free]
        _, once = np.unique(t, return_index=True)  # a corner claimed twice goes to one of them
        q, t = q[once], t[once]
        return np.concatenate([ri, rest[q]]), np.concatenate([ci, t]), np.concatenate([cur_uv, went[q]])

    def _triangulate(self, uv: F64, disparity: F64) -> F64:
        """Left-camera 3D points (N, 3), metres, of left pixels (N, 2) with their disparities (N,)."""
        cam = self.camera
        z = cam.focal_baseline / disparity
        return np.column_stack([(uv[:, 0] - cam.cx) * z / cam.fx, (uv[:, 1] - cam.cy) * z / cam.fy, z])

    # ------------------------------------------------------------------ projection and refinement

    def _project(self, points: F64, pose: F64) -> tuple[F64, F64]:
        """Left pixels (N, 2) and right column (N,) of points (N, 3) moved by ``pose`` into the camera."""
        cam = self.camera
        x = points @ pose[:3, :3].T + pose[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = np.where(x[:, 2] > 1e-6, 1.0 / x[:, 2], np.nan)
        u = cam.fx * x[:, 0] * inv_z + cam.cx
        v = cam.fy * x[:, 1] * inv_z + cam.cy
        return np.column_stack([u, v]), u - cam.focal_baseline * inv_z

    def _stereo_residuals(self, points: F64, pose: F64, uv: F64, u_right: F64) -> F64:
        """(N, 3) reprojection residuals (u_left, v_left, u_right) in pixels; large where behind the camera."""
        proj, proj_right = self._project(points, pose)
        res = np.column_stack([proj - uv, proj_right - u_right])
        return np.nan_to_num(res, nan=1e3)

    def _static_under_prediction(
        self, ref: _Features, cur: _Features, ri: NDArray[np.int64], ci: NDArray[np.int64], predicted: F64
    ) -> NDArray[np.bool_]:
        """Matches whose two triangulations agree in the reference frame under the predicted motion ``T_ref_cur``.

        Allowed: the prediction's error (``max_step_change_m`` plus
        ``max_step_change_ratio`` of the step, and ``prior_rotation_deg`` of
        rotation at the point's range) and three standard deviations of both
        depths (``z^2 / (fx b)`` times 0.3 px of disparity noise).
        """
        p = self.params
        ref_points = ref.points[ri]
        cur_points = cur.points[ci] @ predicted[:3, :3].T + predicted[:3, 3]
        distance = np.linalg.norm(ref_points - cur_points, axis=1)
        fb = self.camera.focal_baseline
        sigma = 0.3 * np.hypot(ref_points[:, 2] ** 2, cur.points[ci, 2] ** 2) / fb
        reach = np.linalg.norm(ref_points, axis=1)
        allowed = (
            p.max_step_change_m
            + p.max_step_change_ratio * float(np.linalg.norm(predicted[:3, 3]))
            + np.deg2rad(p.prior_rotation_deg) * reach
            + 3.0 * sigma
        )
        return distance <= allowed

    def _disparity_consistent(
        self, t_cur_ref: F64, ref: _Features, cur: _Features, ri: NDArray[np.int64], ci: NDArray[np.int64], cur_uv: F64
    ) -> NDArray[np.bool_]:
        """Matches whose disparity in the new frame is what the motion ``T_cur_ref`` predicts from the reference's.

        The reference disparity's error grows by ``(d_cur / d_ref)^2`` on the
        way, so the threshold ``disparity_threshold_px`` grows with it.
        """
        p = self.params
        if p.disparity_threshold_px <= 0:
            return np.ones(len(ri), dtype=bool)
        x = ref.points[ri] @ t_cur_ref[:3, :3].T + t_cur_ref[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            predicted = self.camera.focal_baseline / x[:, 2]
        observed = cur.disparity[ci]
        growth = np.maximum(1.0, (observed / ref.disparity[ri]) ** 2)
        return np.nan_to_num(np.abs(predicted - observed), nan=np.inf) <= p.disparity_threshold_px * growth

    def _depth_weights(self, points: F64, pose: F64) -> F64:
        """Per residual (N, 3) weights ``1 / sqrt(1 + (J_z sigma_z / sigma_px)^2)`` of points (N, 3) moved by ``pose``.

        A point triangulated from one stereo pair is uncertain along its depth,
        ``sigma_z = z^2 / (fx b) sigma_d``; ``J_z`` is how far its projection
        (left u, v and right u) in the other frame moves per metre of depth,
        so the residual's noise is ``sigma_px`` plus the propagated depth
        noise (the disparity and the image positions taken as equally noisy,
        ``sigma_d = sigma_px``). The weights fall where the motion is large
        against the point's range: a point ahead at ``z`` seen after a step
        ``t`` towards it has a right-image weight ``1 / sqrt(1 + (z / (z - t))^4)``;
        at the image edges its left weights fall with the step too.
        """
        cam = self.camera
        eps = 1e-4
        base_uv, base_right = self._project(points, pose)
        moved_uv, moved_right = self._project(points * (1.0 + eps), pose)
        z = np.maximum(points[:, 2], 1e-6)
        dz = eps * z
        jac = np.column_stack([moved_uv - base_uv, moved_right - base_right]) / dz[:, None]
        spread = jac * (z * z / cam.focal_baseline)[:, None]
        return np.nan_to_num(1.0 / np.sqrt(1.0 + spread**2), nan=0.0)

    def _refine_two_way(
        self, pose: F64, ref: _Features, cur: _Features, ri: NDArray[np.int64], ci: NDArray[np.int64], cur_uv: F64
    ) -> tuple[F64, float, float, float]:
        """Refine ``T_cur_ref`` by robust least squares on the stereo reprojection error both ways.

        Returns:
            The refined ``T_cur_ref``; the standard deviation of its step
            length from the normal equations (percent of the step); and how
            much the step length would change (percent) if every disparity
            were ``params.disparity_bias_px`` smaller, which is how strongly
            the scale rests on far points.
        """
        from scipy.optimize import least_squares

        p = self.params
        cur_disparity, ref_disparity = cur.disparity[ci], ref.disparity[ri]
        ref_points, cur_points = ref.points[ri], cur.points[ci]
        if p.depth_weighting:
            w_forward, w_backward = (
                self._depth_weights(ref_points, pose),
                self._depth_weights(cur_points, invert_pose(pose)),
            )
        else:
            w_forward = w_backward = np.ones((len(ri), 3))

        def residuals_of(x: F64, bias: float) -> F64:
            t = _pose_from_vector(x)
            rp = ref_points if bias == 0 else self._triangulate(ref.uv[ri], ref_disparity - bias)
            cp = cur_points if bias == 0 else self._triangulate(cur.uv[ci], cur_disparity - bias)
            forward = self._stereo_residuals(rp, t, cur_uv, cur_uv[:, 0] - (cur_disparity - bias))
            backward = self._stereo_residuals(cp, invert_pose(t), ref.uv[ri], ref.uv[ri, 0] - (ref_disparity - bias))
            return np.concatenate([(forward * w_forward).ravel(), (backward * w_backward).ravel()])

        fit = least_squares(
            residuals_of, _vector_from_pose(pose), args=(0.0,), loss="huber", f_scale=1.0, method="trf", max_nfev=30
        )
        refined = _pose_from_vector(fit.x)
        # The step's uncertainty and bias sensitivity, linearised at the solution with the Huber weights.
        jac = np.asarray(fit.jac)
        robust = np.sqrt(np.minimum(1.0, 1.0 / np.maximum(np.abs(fit.fun), 1e-12)))
        step = fit.x[3:6]
        length = float(np.linalg.norm(step))
        if length < 1e-6:
            return refined, float("nan"), float("nan"), float("nan")
        direction = step / length
        try:
            covariance = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            return refined, float("inf"), float("inf"), float("inf")
        sigma = 1.4826 * float(np.median(np.abs(fit.fun[fit.fun != 0]))) if np.any(fit.fun != 0) else 0.0
        # Each measurement enters twice (as an observation one way and in a triangulated point the other):
        # the normal equations take the two for independent and halve the spread (measured on synthetic points).
        std_pct = (
            _SHARED * 100.0 * sigma * float(np.sqrt(max(direction @ covariance[3:, 3:] @ direction, 0.0))) / length
        )
        change = (residuals_of(fit.x, p.disparity_bias_px) - fit.fun) * robust
        dx = -covariance @ (jac.T @ change)
        bias_pct = 100.0 * abs(float(np.linalg.norm(step + dx[3:6])) - length) / length
        influence_pct = self._region_influence(cur_uv, lambda x: residuals_of(x, 0.0), fit.x, fit.fun, robust)
        return refined, std_pct, bias_pct, influence_pct

    def _region_influence(self, uv: F64, residuals: Callable[[F64], F64], x: F64, fun: F64, robust: F64) -> float:
        """Largest change of the step length (percent) when the matches of one image region are left out.

        ``uv``: the matches' positions (N, 2), in the order of the residuals
        (3 per match forward, then 3 per match backward); ``residuals`` and
        its solution ``x`` (with ``fun`` there and the Huber weights'
        square roots ``robust``). Linearised at the solution as one
        reweighted least-squares step, with the Huber weights fixed: without
        the rows ``g`` of one region the normal equations lose ``J_g^T J_g``
        and the gradient ``J_g^T r_g`` (weighted Jacobian and residuals), so
        the parameters move by ``(J^T J - J_g^T J_g)^-1 J_g^T r_g``. A scale
        that rests on one region (a vehicle that moved with the camera, one
        far facade) changes a lot. The Jacobian is the residuals' own (central
        differences), not least_squares' Huber-modified one, whose rows of
        outlying residuals are zero and would hide the regions that pull most.
        """
        rows, cols = self.params.influence_grid
        cell = (np.clip((uv[:, 1] * rows / self.camera.height).astype(np.int64), 0, rows - 1) * cols
                + np.clip((uv[:, 0] * cols / self.camera.width).astype(np.int64), 0, cols - 1))  # fmt: skip
        groups = np.unique(cell)
        if len(groups) < 2:  # one region (or the check off): leaving it out leaves nothing
            return 0.0
        per_residual = np.concatenate([np.repeat(cell, 3), np.repeat(cell, 3)])
        eps = 1e-6
        jac = np.empty((len(fun), len(x)))
        for k in range(len(x)):
            dx = np.zeros_like(x)
            dx[k] = eps
            jac[:, k] = (residuals(x + dx) - residuals(x - dx)) / (2.0 * eps)
        jac *= robust[:, None]
        weighted = fun * robust
        hessian = jac.T @ jac
        step = x[3:6]
        length = float(np.linalg.norm(step))
        worst = 0.0
        for group in groups:
            rows_g = per_residual == group
            jg = jac[rows_g]
            try:
                dx = np.linalg.solve(hessian - jg.T @ jg, jg.T @ weighted[rows_g])
            except np.linalg.LinAlgError:
                return float("inf")
            worst = max(worst, 100.0 * abs(float(np.linalg.norm(step + dx[3:6])) - length) / length)
        return worst

    # ------------------------------------------------------------------ the frame step

    def add(self, left: NDArray[np.uint8], right: NDArray[np.uint8], stamp: float = 0.0) -> OdometryResult:
        """Estimate the pose of a new rectified pair.

        Args:
            left: left image, HxW grey or HxWx3 RGB uint8, the camera's size.
            right: right image, same shape.
            stamp: the caller's time stamp, kept in the quality record.

        Returns:
            The pose ``T_world_left`` (world = left camera of the first frame)
            and the frame's quality. An unreliable frame gets the
            constant-velocity guess as its pose.

        Raises:
            OdometryError: images of the wrong type or size.
        """
        p = self.params
        index = len(self.poses)
        self.last_inliers = np.zeros((0, 2))
        self.last_inlier_disparity = np.zeros(0)
        gl, gr = _grey(left, "left"), _grey(right, "right")
        expected = (self.camera.height, self.camera.width)
        if gl.shape != expected or gr.shape != expected:
            raise OdometryError(
                f"frame {index}: images are {gl.shape[::-1]} (left) and {gr.shape[::-1]} (right), "
                f"expected {expected[::-1]} from the camera calibration"
            )
        cur, n_features = self._stereo(gl, gr)
        self.last_features = cur.uv
        previous, self._previous = self._previous, (index, gl, cur.ground)
        if previous is not None and previous[0] != index - 1:
            previous = None
        common: dict[str, Any] = {
            "index": index,
            "stamp": float(stamp),
            "features": n_features,
            "stereo_matches": len(cur.uv),
        }

        if self._reference is None:
            return self._first_or_fail(gl, cur, common)
        ref_index, ref_image, ref = self._reference
        ref_pose = self.poses[ref_index]
        gap = index - ref_index
        velocity = self._velocity
        predicted = np.eye(4) if velocity is None else np.linalg.matrix_power(velocity, gap)  # T_ref_cur
        guess_pose = ref_pose @ predicted  # a failed frame's pose: constant velocity, however old
        if 0 < p.stale_velocity_frames < index - self._velocity_index:
            velocity, predicted = None, np.eye(4)  # too old to predict by: measured as without a prediction

        def fail(status: str, message: str, **extra: Any) -> OdometryResult:
            if velocity is not None and "road_length_m" not in extra:
                # The road may still give the step's length where the features do not (a truck filling
                # the view): measured from the constant-velocity guess.
                extra.update(self._road(previous, gl, invert_pose(velocity), velocity))
            quality = FrameQuality(
                status=status, reliable=False, reference=ref_index, message=message, **common, **extra
            )
            result = self._record(guess_pose, quality)
            if status != "few_features" and gap >= p.reanchor_after:
                self._reanchor(index, gl, cur, guess_pose)
            return result

        if n_features < p.min_features or len(cur.uv) < p.min_features // 2:
            return fail("few_features", f"too little texture: {n_features} features, {len(cur.uv)} with a stereo match")

        # Frame-to-frame matching within a radius of the predicted position.
        pred_uv, _ = self._project(ref.points, invert_pose(predicted))
        radius = p.search_radius_px * gap if velocity is not None else p.first_search_radius_px
        seen = np.flatnonzero(np.isfinite(pred_uv).all(axis=1))
        ri, ci = _row_candidates(pred_uv[seen, 1], cur.uv[:, 1], np.full(seen.size, float(radius)))
        ri = seen[ri]
        near = ((pred_uv[ri] - cur.uv[ci]) ** 2).sum(axis=1) <= radius**2
        ri, ci = self._ratio_matches(ref.descriptors, cur.descriptors, ri[near], ci[near])
        # Sub-pixel: follow each reference feature into the new image, started at its matched corner.
        cur_uv, ok = self._lk(ref_image, gl, ref.uv[ri], cur.uv[ci])
        ok &= np.linalg.norm(cur_uv - cur.uv[ci], axis=1) <= 3.0
        ri, ci, cur_uv = ri[ok], ci[ok], cur_uv[ok]
        if p.follow_unmatched and velocity is not None:
            ri, ci, cur_uv = self._follow_unmatched(ref_image, gl, ref, cur, pred_uv, seen, radius, ri, ci, cur_uv)
        if p.consistent_tracks:
            ri, ci, cur_uv = self._move_features(gl, gr, cur, ri, ci, cur_uv)
        if len(ri) < p.min_matches:
            return fail("few_matches", f"only {len(ri)} matches with frame {ref_index} (need {p.min_matches})",
                        temporal_matches=len(ri))  # fmt: skip

        everything = np.arange(len(ri))
        if self._bad_tracks:
            fine = everything[~np.isin(ref.track_ids[ri], np.fromiter(self._bad_tracks, np.int64))]
            everything = fine if len(fine) >= p.min_inliers else everything
        if velocity is not None and p.prior_gate:
            # Points that moved in the world since the reference (vehicles) beyond what the prediction's error
            # and their depth noise explain do not enter RANSAC, unless too few are left.
            still = everything[self._static_under_prediction(ref, cur, ri[everything], ci[everything], predicted)]
            everything = still if len(still) >= p.min_inliers else everything
        t_cur_ref, keep = self._pnp_ransac(ref.points[ri], cur_uv, predicted, velocity is not None, everything)
        candidate, self._implausible_candidate = self._implausible_candidate, None
        if (
            velocity is not None
            and len(keep) >= p.min_inliers
            and not self._plausible(t_cur_ref, predicted)
            and not self._confirms_untrusted_override(t_cur_ref, candidate, gap)
        ):
            # The largest rigid group moves unlike the camera can (a vehicle filling the view, say): the
            # static scene is the largest group among the rest, if it moves as the camera can.
            first, largest = len(keep), (t_cur_ref, keep)
            self._implausible_candidate = _step_of(invert_pose(t_cur_ref), gap)
            t_cur_ref, keep = self._pnp_ransac(ref.points[ri], cur_uv, predicted, True, np.setdiff1d(everything, keep))
            flow = np.linalg.norm(cur_uv[largest[1]] - ref.uv[ri[largest[1]]], axis=1)
            if (len(keep) < p.min_inliers or not self._plausible(t_cur_ref, predicted)) and (
                np.median(flow) < p.static_flow_px
            ):
                t_cur_ref, keep = largest  # no other group, and the image stands still: the camera stopped
            elif len(keep) < p.min_inliers or not self._plausible(t_cur_ref, predicted):
                return fail("implausible", f"the largest rigid group of matches ({first}) moves unlike the "
                            "constant-velocity prediction, and no other group does", temporal_matches=len(ri),
                            inliers=first)  # fmt: skip
        if len(keep) < p.min_inliers:
            return fail("few_inliers", f"PnP RANSAC found {len(keep)} inliers of {len(ri)} matches "
                        f"(need {p.min_inliers})", temporal_matches=len(ri), inliers=len(keep))  # fmt: skip
        # PnP sees only the left image: a vehicle ahead, near the focus of expansion, fits the camera's motion
        # there; its disparity changes as its own speed says. Gate the stereo (disparity) residual too.
        keep = keep[self._disparity_consistent(t_cur_ref, ref, cur, ri[keep], ci[keep], cur_uv[keep])]
        if len(keep) < p.min_inliers:
            return fail("few_inliers", f"{len(keep)} PnP inliers of {len(ri)} matches agree with their disparity "
                        f"(need {p.min_inliers})", temporal_matches=len(ri), inliers=len(keep))  # fmt: skip
        t_cur_ref, scale_std, scale_bias, influence = self._refine_two_way(
            t_cur_ref, ref, cur, ri[keep], ci[keep], cur_uv[keep]
        )
        # Inliers of the refined pose among all matches: both directions within the RANSAC threshold.
        forward = self._stereo_residuals(ref.points[ri], t_cur_ref, cur_uv, cur_uv[:, 0] - cur.disparity[ci])
        backward = self._stereo_residuals(
            cur.points[ci], invert_pose(t_cur_ref), ref.uv[ri], ref.uv[ri, 0] - ref.disparity[ri]
        )
        err = np.maximum(np.abs(forward).max(axis=1), np.abs(backward).max(axis=1))
        inlier = err <= p.ransac_threshold_px * 1.5
        inlier &= self._disparity_consistent(t_cur_ref, ref, cur, ri, ci, cur_uv)
        n_in = int(inlier.sum())
        self.last_inliers = cur_uv[inlier]
        self.last_inlier_disparity = cur.disparity[ci[inlier]]
        rms = float(np.sqrt(np.mean(forward[inlier] ** 2))) if n_in else float("nan")
        t_ref_cur = invert_pose(t_cur_ref)
        extra = {"temporal_matches": len(ri), "inliers": n_in, "reprojection_error_px": rms,
                 "scale_std_pct": scale_std, "scale_bias_pct": scale_bias,
                 "scale_influence_pct": influence}  # fmt: skip
        step = t_ref_cur if gap == 1 else _step_of(t_ref_cur, gap)  # the road measures the step from the frame before
        extra.update(self._road(previous, gl, invert_pose(step), velocity if velocity is not None else step))
        if n_in < p.min_inliers:
            return fail("few_inliers", f"{n_in} inliers after refinement (need {p.min_inliers})", **extra)
        if not rms <= p.max_reprojection_error_px:
            return fail("high_error", f"RMS reprojection error {rms:.2f} px > {p.max_reprojection_error_px}", **extra)

        flow = float(np.median(np.linalg.norm(cur_uv[inlier] - ref.uv[ri[inlier]], axis=1)))
        status = "static" if flow < p.static_flow_px else "ok"
        if status == "static":
            t_ref_cur = np.eye(4)  # below the noise: no motion rather than a random jitter
        pose = ref_pose @ t_ref_cur
        # Tracks: inlier matches inherit the reference's id, everything else starts a new track.
        ids = np.arange(self._next_track, self._next_track + len(cur.uv), dtype=np.int64)
        ids[ci[inlier]] = ref.track_ids[ri[inlier]]
        self._next_track += len(cur.uv)
        cur.track_ids = ids
        quality = FrameQuality(status=status, reliable=True, reference=ref_index, **common, **extra)  # type: ignore[arg-type]
        result = self._record(pose, quality)
        self._velocity = np.linalg.matrix_power(t_ref_cur, 1) if gap == 1 else _step_of(t_ref_cur, gap)
        self._velocity_index = index
        self._velocity_trusted = True  # until the checks below say otherwise
        if status == "ok" or self._reference is None:
            self._reference = (index, gl, cur)
        if status == "ok":
            self._window.append(_WindowFrame.of(index, pose, cur))
            self._bundle_adjust()
            adjusted = invert_pose(self.poses[index - 1]) @ self.poses[index]
            before = float(np.linalg.norm((invert_pose(self.poses[index - 1]) @ pose)[:3, 3]))
            change = 100.0 * abs(float(np.linalg.norm(adjusted[:3, 3])) - before) / max(before, 1e-9)
            quality = self._check_scale(replace(result.quality, adjustment_change_pct=change))
            if quality.reliable:
                quality = self._check_velocity_change(index, quality)
            self.qualities[index] = quality
            self._velocity_trusted = quality.reliable
            if p.interpolate_speed:
                self._step_prior(index, quality.reliable)
            return OdometryResult(self.poses[index].copy(), quality)
        return result

    def smoothed_poses(self) -> F64:
        """The poses so far with their step lengths smoothed (:func:`smooth_step_lengths`), (N, 4, 4)."""
        poses = np.stack(self.poses[:]) if self.poses else np.zeros((0, 4, 4))
        return smooth_step_lengths(poses, self.qualities[:], self.params)

    def forget_before(self, index: int) -> int:
        """Forget the poses and qualities of the frames before ``index`` that the odometry no longer reads;
        returns how many were forgotten.

        For a long-running node (about 0.9 kB a frame otherwise, 30 MiB an
        hour at 10 Hz): :class:`~selfcontra_ros.odometry.run.OnlineOdometry`
        forgets what its smoother no longer reads. Kept whatever ``index``,
        so that the frames to come are measured and mended exactly as
        without forgetting: the last ``_MAX_MENDED_FRAMES`` frames (what a
        reliable frame after a failure mends and walks back over), the
        reference frame, the windowed adjustment's frames and the reference
        of the last reliable frame; the frames between them are forgotten
        during a long stop or failure, so memory stays bounded then too.
        The tracks found moving are forgotten once no frame that can be
        matched or adjusted has them (nothing else reads them).
        :attr:`poses` and :attr:`qualities` keep their indices; reading a
        forgotten frame raises :class:`IndexError`, so :meth:`smoothed_poses`
        needs every frame.
        """
        newest = len(self.poses) - 1
        keep = {frame.index for frame in self._window}
        if self._reference is not None:
            keep.add(self._reference[0])
        recent = max(0, newest - _MAX_MENDED_FRAMES)
        for k in range(newest, recent - 1, -1):  # the frame a reliable one would mend from, and its reference
            if self.qualities[k].reliable:  # (the last _MAX_MENDED_FRAMES frames are never forgotten)
                keep.add(self.qualities[k].reference)
                break
        drop = [k for k in self.poses.held() if k < min(index, recent) and k not in keep]
        self.qualities.forget(drop)
        if self._bad_tracks:  # only the reference's tracks are matched again, and the window's adjusted
            alive = [frame.track_ids for frame in self._window]
            if self._reference is not None:
                alive.append(self._reference[2].track_ids)
            self._bad_tracks.intersection_update(np.concatenate(alive).tolist() if alive else ())
        return self.poses.forget(drop)

    def _road(
        self, previous: tuple[int, NDArray[np.uint8], GroundPlane | None] | None, image: NDArray[np.uint8],
        t_cur_prev: F64, predicted: F64,
    ) -> dict[str, Any]:  # fmt: skip
        """The step from the frame before measured on the road (``road_length_m``, ``road_pixels``,
        ``road_motion`` for the quality; empty when ``road_steps`` is off, ``previous`` (its index, left
        image and road plane) is not the frame before or has no road, or the road does not say).

        The step is the one from the frame before whatever frame the
        features were measured from (a reference further back, after a
        failure). A frame that fails after its measured step found no road
        length is searched again from the prediction (in ``fail``). Started
        from ``t_cur_prev``, the predicted step (``predicted``,
        ``T_prev_cur``) and the last translation the road measured (a
        vehicle's velocity changes little from one frame to the next): a
        step measured on a vehicle or on far texture alone may be further
        off, in length and direction, than the road's search reaches. Until
        the road has measured a step, it also searches around
        :data:`_WIDE_LENGTHS_M` along the measured step: on a new highway
        (seed 158) a truck moving with the camera made the features' first
        seventeen steps 70-86 % short, and the prediction with them; and,
        in a search of its own, straight ahead (seed 191: such steps 4-6
        degrees aside), keeping the result that aligns the pixels both keep
        in view better (:func:`~selfcontra_ros.odometry.ground.road_costs`).
        """
        if not self.params.road_steps or previous is None or previous[2] is None:
            return {}
        plane, earlier = previous[2], previous[1]
        others: tuple[F64 | float, ...] = (invert_pose(predicted)[:3, 3], self._road_translation)
        wide = not np.all(np.isfinite(self._road_translation))
        if wide:
            others += tuple(_WIDE_LENGTHS_M)
        road = road_step(plane, earlier, image, self.camera, t_cur_prev, other_starts=others)
        if wide:
            # Straight ahead (the optical axis) too: a step measured on a vehicle may point several degrees
            # off (highway seed 191: 4-6 degrees, 0.2 m aside at the true length). A search of its own (the
            # pixels a search compares are those every start keeps in view, and a sideways camera's road
            # leaves the view ahead); the two results compared on the pixels both keep.
            ahead = t_cur_prev.copy()
            ahead[:3, 3] = (0.0, 0.0, -1.0)
            forward = road_step(plane, earlier, image, self.camera, ahead,
                                other_starts=tuple(np.array([0.0, 0.0, -x]) for x in _WIDE_LENGTHS_M))  # fmt: skip
            if forward is not None and (
                road is None
                or np.argmin(road_costs(plane, earlier, image, self.camera, [road.t_cur_ref, forward.t_cur_ref])) == 1
            ):
                road = forward
        if road is None:
            return {}
        if road.length_m > 0.01:  # a standing camera's step is no start for the next one
            self._road_translation = road.t_cur_ref[:3, 3].copy()
        motion = tuple(float(x) for x in _vector_from_pose(invert_pose(road.t_cur_ref)))
        return {"road_length_m": road.length_m, "road_pixels": road.pixels, "road_motion": motion}

    def _frame_step(self, index: int) -> F64:
        """The measured frame ``index``'s motion per frame since its reference (``T_prev_cur``, 4x4)."""
        reference = self.qualities[index].reference
        return _step_of(invert_pose(self.poses[reference]) @ self.poses[index], index - reference)

    def _check_velocity_change(self, index: int, quality: FrameQuality) -> FrameQuality:
        """Flag a measured step ``weak_scale`` when it differs from the last reliable step by more than
        ``max_velocity_change_m`` per frame between them (translations per frame, in the camera frame).

        A vehicle accelerating or braking at 10 m/s^2 changes its step at
        10 Hz by 0.1 m per frame; a larger jump is the estimate's, mostly
        vehicles that pass the per-frame tests (far oncoming cars). A jump
        that the next measured frame confirms (within the same limit of the
        flagged step) is taken as real: the prior was the stale one.
        """
        p = self.params
        if p.max_velocity_change_m <= 0 or self._reliable_step is None:
            return quality
        step = self._frame_step(index)[:3, 3]
        limit = p.max_velocity_change_m * (index - self._reliable_index)
        jump = float(np.linalg.norm(step - self._reliable_step))
        candidate, self._jump_candidate = self._jump_candidate, None
        if jump <= limit:
            return quality
        if candidate is not None and float(np.linalg.norm(step - candidate)) <= p.max_velocity_change_m:
            return quality
        self._jump_candidate = step.copy()
        return replace(quality, status="weak_scale", reliable=False,
                       message=f"the step changed by {jump:.2f} m from the last reliable one "
                       f"{index - self._reliable_index} frame(s) before (limit {limit:.2f} m)")  # fmt: skip

    def _step_prior(self, index: int, reliable: bool) -> None:
        """After the measured frame ``index``: a reliable one sets the velocity prior and mends the unreliable
        frames before it (:meth:`_interpolate_unreliable_steps`); a ``weak_scale`` one keeps its measured
        rotation (per frame, when measured from a reference further back) but takes the last reliable step's
        translation from the frame before (in the camera frame: a vehicle's velocity changes little from one
        frame to the next)."""
        if reliable:
            self._interpolate_unreliable_steps(index)
            self._reliable_step = self._frame_step(index)[:3, 3].copy()
            self._reliable_index = index
            return
        reference = self.qualities[index].reference
        if self._reliable_step is None or not 0 <= reference < index:
            return
        # Measured across a failed frame (a truck's rigid group was rejected there), the motion's rotation per
        # frame; the frame before holds a constant-velocity guess.
        step = invert_pose(self.poses[reference]) @ self.poses[index]
        if reference < index - 1:
            step = _step_of(step, index - reference)
        step[:3, 3] = self._reliable_step
        self.poses[index] = self.poses[index - 1] @ step
        for frame in self._window:
            if frame.index == index:
                frame.pose = self.poses[index].copy()

    def _interpolate_unreliable_steps(self, index: int) -> None:
        """Give the unreliable frames just before the reliable measured frame ``index`` interpolated translations.

        The frames since the last reliable one have either a measured motion
        whose translation could not be trusted (``weak_scale``: on the
        synthetic highway such steps were 5-15 % off, in length and
        direction) or a constant-velocity guess. A vehicle's velocity in its
        own frame changes little from one frame to the next, so each of their
        steps up to the reference of ``index`` keeps its rotation and takes
        the translation (``T_prev_cur``, metres) interpolated linearly in
        frame numbers between the reliable steps per frame on both sides (the
        one after only, when the reliable frame before is the first); they are
        chained again from the reliable frame before, ``index`` keeps its
        measured motion from its reference, and frames between the two (no
        pose of their own) lie on the screw motion between them. The windowed
        adjustment's copies follow. A run of more than ``_MAX_MENDED_FRAMES``
        unreliable frames keeps its guesses.
        """
        start = index - 1
        while start >= 0 and not self.qualities[start].reliable:
            if index - start > _MAX_MENDED_FRAMES:
                return  # too long a failure to interpolate across (its frames may be forgotten: forget_before)
            start -= 1
        if start < 0 or start == index - 1:
            return
        reference = self.qualities[index].reference
        measured = invert_pose(self.poses[reference]) @ self.poses[index]
        per_frame = _step_of(measured, index - reference)
        end = per_frame[:3, 3]
        begin = end
        if start >= 1 and self.qualities[start].status in ("ok", "static"):
            begin = self._frame_step(start)[:3, 3]
        gap = index - start
        steps = [invert_pose(self.poses[k - 1]) @ self.poses[k] for k in range(start + 1, reference + 1)]
        pose = self.poses[start]
        for k, step in zip(range(start + 1, reference + 1), steps, strict=True):
            step[:3, 3] = begin + (end - begin) * (k - start) / gap
            pose = pose @ step
            self.poses[k] = pose
        for k in range(reference + 1, index):
            self.poses[k] = self.poses[reference] @ np.linalg.matrix_power(per_frame, k - reference)
        self.poses[index] = self.poses[reference] @ measured
        for frame in self._window:
            frame.pose = self.poses[frame.index].copy()

    def _check_scale(self, quality: FrameQuality) -> FrameQuality:
        """Flag a measured frame ``weak_scale`` when its step length cannot be trusted to ``max_step_error_pct``.

        Four signs: the step's statistical uncertainty (``scale_sigmas``), its
        sensitivity to a ``disparity_bias_px`` bias of every disparity (a
        scale resting on far points), its sensitivity to one image region's
        matches (``influence_share``: a scale resting on one object), and how
        far the windowed adjustment moved the step from the frame-to-frame
        estimate.
        """
        p = self.params
        reasons = []
        limit = p.max_step_error_pct * _coarseness(p, self.camera.focal_baseline)
        if not p.scale_sigmas * quality.scale_std_pct <= limit:
            reasons.append(f"{p.scale_sigmas:g}-sigma step uncertainty {p.scale_sigmas * quality.scale_std_pct:.2f} %")
        if not quality.scale_bias_pct <= limit * p.bias_share:
            reasons.append(
                f"a {p.disparity_bias_px:g} px disparity bias changes the step by {quality.scale_bias_pct:.2f} %"
            )
        if p.influence_share > 0 and not quality.scale_influence_pct <= limit * p.influence_share:
            reasons.append(
                f"leaving one image region's matches out changes the step by {quality.scale_influence_pct:.2f} %"
            )
        if not quality.adjustment_change_pct <= limit * p.adjustment_share:
            reasons.append(f"the window adjustment changed the step by {quality.adjustment_change_pct:.2f} %")
        if not reasons or not p.check_scale:
            return quality
        return replace(quality, status="weak_scale", reliable=False,
                       message="scale not constrained well enough: " + "; ".join(reasons))  # fmt: skip

    def _first_or_fail(self, image: NDArray[np.uint8], cur: _Features, common: dict[str, Any]) -> OdometryResult:
        """The first frame with enough stereo features anchors the world frame."""
        p = self.params
        if common["features"] < p.min_features or len(cur.uv) < p.min_features // 2:
            quality = FrameQuality(status="few_features", reliable=False,
                                   message=f"too little texture: {common['features']} features, "
                                   f"{len(cur.uv)} with a stereo match", **common)  # fmt: skip
            return self._record(np.eye(4), quality)
        index = int(common["index"])
        cur.track_ids = np.arange(self._next_track, self._next_track + len(cur.uv), dtype=np.int64)
        self._next_track += len(cur.uv)
        self._reference = (index, image, cur)
        self._window.append(_WindowFrame.of(index, np.eye(4), cur))
        return self._record(np.eye(4), FrameQuality(status="first", reliable=True, **common))

    def _pnp_ransac(
        self, points: F64, uv: F64, predicted: F64, use_guess: bool, subset: NDArray[np.int64]
    ) -> tuple[F64, NDArray[np.int64]]:
        """PnP RANSAC on the matches ``subset``: ``T_cur_ref`` and its inliers (indices into all matches)."""
        p = self.params
        none = (np.eye(4), np.zeros(0, np.int64))
        if len(subset) < 6:
            return none
        cv2.setRNGSeed(p.seed)
        guess = invert_pose(predicted)
        rvec0, _ = cv2.Rodrigues(guess[:3, :3])
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            points[subset].astype(np.float64), uv[subset].astype(np.float64), self.camera.K, None,
            rvec=rvec0.copy(), tvec=guess[:3, 3].reshape(3, 1).copy(), useExtrinsicGuess=use_guess,
            iterationsCount=p.ransac_iterations, reprojectionError=p.ransac_threshold_px, confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )  # fmt: skip
        if not found or inliers is None:
            return none
        t_cur_ref = np.eye(4)
        t_cur_ref[:3, :3] = cv2.Rodrigues(rvec)[0]
        t_cur_ref[:3, 3] = tvec.ravel()
        return t_cur_ref, subset[inliers.ravel()]

    def _confirms_untrusted_override(self, t_cur_ref: F64, candidate: F64 | None, gap: int) -> bool:
        """Whether an implausible motion overrules the constant-velocity prediction: the prediction comes
        from a frame that failed a check (``weak_scale``, never confirmed), and the last implausible
        frame's largest group moved as this one does (``candidate``, per frame; ``untrusted_override``).

        Without it a wrong first step locks the odometry: on highway seed 3
        (``fast_threshold`` 5) frame 1 measured 0.26 m on a truck moving
        with the camera (true 2.53 m, flagged ``weak_scale``), and every
        later frame's static scene, 2.6 m, was ``implausible`` against it:
        29 of 30 frames unreliable and the path 91 % short.
        """
        if not self.params.untrusted_override or self._velocity_trusted or candidate is None:
            return False
        return self._plausible(t_cur_ref, np.linalg.matrix_power(candidate, gap))

    def _plausible(self, t_cur_ref: F64, predicted: F64) -> bool:
        """Whether motion ``T_cur_ref`` is within what a camera can change from the prediction ``T_ref_cur``."""
        p = self.params
        step = invert_pose(t_cur_ref)[:3, 3]
        expected = predicted[:3, 3]
        limit = p.max_step_change_m + p.max_step_change_ratio * float(np.linalg.norm(expected))
        return float(np.linalg.norm(step - expected)) <= limit

    def _reanchor(self, index: int, image: NDArray[np.uint8], cur: _Features, pose: F64) -> None:
        """Make a frame without a measured pose the reference, at its guessed pose, with new tracks.

        The reference it replaces is ``reanchor_after`` frames old: its
        features leave the view, so matching against it would keep failing.
        The next frames' motion is measured from here; only this frame's
        absolute pose is a guess. The windowed adjustment starts over with it
        as its fixed frame.
        """
        cur.track_ids = np.arange(self._next_track, self._next_track + len(cur.uv), dtype=np.int64)
        self._next_track += len(cur.uv)
        self._reference = (index, image, cur)
        self._window.clear()
        self._window.append(_WindowFrame.of(index, pose.copy(), cur))

    def _record(self, pose: F64, quality: FrameQuality) -> OdometryResult:
        previous = self.poses[-1] if self.poses else pose
        step = invert_pose(previous) @ pose
        quality = replace(
            quality,
            translation_m=float(np.linalg.norm(step[:3, 3])),
            rotation_deg=_rotation_deg(step[:3, :3]),
            disparity_offset_px=self._offset,
        )
        self.poses.append(pose.copy())
        self.qualities.append(quality)
        return OdometryResult(pose.copy(), quality)

    # ------------------------------------------------------------------ windowed bundle adjustment

    def _bundle_adjust(self) -> None:
        """Refine the window's poses (all but the oldest) and its tracks' points; update :attr:`poses`."""
        from scipy.optimize import least_squares

        frames = list(self._window)
        if len(frames) < 3:
            return
        cam = self.camera
        all_ids = np.concatenate([f.track_ids for f in frames])
        unique, counts = np.unique(all_ids, return_counts=True)
        shared = unique[counts >= 2]
        if shared.size < self.params.min_inliers:
            return
        obs_frame, obs_point, obs_uv, obs_ur, obs_straddle = [], [], [], [], []
        world_points = np.zeros((shared.size, 3))
        weight = np.zeros(shared.size)
        for k, f in enumerate(frames):
            sel = np.isin(f.track_ids, shared)
            idx = np.searchsorted(shared, f.track_ids[sel])
            obs_frame.append(np.full(idx.size, k))
            obs_point.append(idx)
            obs_uv.append(f.uv[sel])
            obs_ur.append(f.u_right[sel])
            obs_straddle.append(f.straddle[sel])
            d = f.uv[sel, 0] - f.u_right[sel]
            local = self._triangulate(f.uv[sel], d)
            # Initial point: disparity-weighted mean of the triangulations (near views are more precise).
            np.add.at(world_points, idx, (local @ f.pose[:3, :3].T + f.pose[:3, 3]) * d[:, None] ** 2)
            np.add.at(weight, idx, d**2)
        world_points /= weight[:, None]
        fi = np.concatenate(obs_frame)
        pi = np.concatenate(obs_point)
        uv = np.concatenate(obs_uv)
        ur = np.concatenate(obs_ur)
        n_free = len(frames) - 1
        x0 = np.concatenate([np.concatenate([_vector_from_pose(invert_pose(f.pose)) for f in frames[1:]]),
                             world_points.ravel()])  # fmt: skip
        problem = _WindowProblem(cam, invert_pose(frames[0].pose), n_free, shared.size, fi, pi, uv, ur)
        fit = least_squares(
            problem.residuals, x0, jac=problem.jacobian, loss="huber", f_scale=1.0, method="trf", x_scale="jac",
            max_nfev=15, tr_solver="lsmr",
        )  # fmt: skip
        if self.params.track_outlier_px > 0:
            # A track the window cannot explain as one static point (a vehicle far ahead, whose per-frame
            # motion hides in the noise) is dropped here and kept out of later matching.
            error = np.abs(fit.fun.reshape(-1, 3)).max(axis=1)
            bad = np.unique(pi[error > self.params.track_outlier_px])
            if 0 < bad.size <= shared.size - self.params.min_inliers:
                self._bad_tracks.update(int(t) for t in shared[bad])
                problem.weight = (~np.isin(pi, bad)).astype(np.float64)
                fit = least_squares(
                    problem.residuals, fit.x, jac=problem.jacobian, loss="huber", f_scale=1.0, method="trf",
                    x_scale="jac", max_nfev=10, tr_solver="lsmr",
                )  # fmt: skip
        self._adjustments += 1
        if self.params.estimate_disparity_offset and self._adjustments % max(self.params.window, 1) == 0:
            self._estimate_offset(problem, fit.fun, x0, np.concatenate(obs_straddle))
        cams = fit.x[: 6 * n_free].reshape(n_free, 6)
        for f, vec in zip(frames[1:], cams, strict=True):
            f.pose = invert_pose(_pose_from_vector(vec))
            self.poses[f.index] = f.pose.copy()
        # Keep the reference frame's 3D points as they are (its own stereo): only poses move.

    def _estimate_offset(self, problem: _WindowProblem, fun: F64, x0: F64, straddle: NDArray[np.bool_]) -> None:
        """Estimate from the window the disparity offset its measurements still carry; update the applied one.

        A constant error ``e`` of every disparity (a rectification whose
        images are shifted against each other by a fraction of a pixel) makes
        the depths ``fb / d`` wrong by a share that grows with the depth, so
        no rigid motion fits near and far points together: the window's
        reprojection error is smallest at the disparity shift that undoes
        ``e``. It is found by a parabola through the adjusted window's cost
        (tracks whose residual exceeds ``offset_inlier_px`` left out, plain
        least squares; tracks seen once with a window across a depth edge,
        ``straddle`` per observation, too) with every disparity shifted by ``-h, 0, +h``
        (``h = offset_step_px``), each solved from the same start. Every
        ``window``-th adjustment (windows that share no frame) adds one
        estimate, when the parabola's own standard deviation is within
        ``offset_window_std_px``; once ``offset_min_windows`` exist, the mean of the latest
        ``offset_max_windows`` replaces ``disparity_offset_px`` when it differs from it by more than
        ``offset_sigmas`` standard errors (the windows' spread, at least
        :data:`_OFFSET_STD_FLOOR_PX`).
        """
        p = self.params
        worst = np.abs(fun.reshape(-1, 3)).max(axis=1)
        outliers = np.unique(problem.pi[(worst > p.offset_inlier_px) | straddle])
        weight = problem.weight * ~np.isin(problem.pi, outliers)
        if np.unique(problem.pi[weight > 0]).size < p.min_inliers:
            return
        step, std = self._window_offset(problem, weight, x0)
        if not (np.isfinite(step) and (p.offset_window_std_px <= 0 or std <= p.offset_window_std_px)):
            return
        self._add_offset_window(self._offset + step)

    def _add_offset_window(self, estimate: float) -> None:
        """Count one window's estimate of the whole offset (pixels); apply the windows' mean when significant."""
        p = self.params
        self._offset_windows.append(estimate)
        mean, error, n = self.offset_estimate()
        if n >= p.offset_min_windows:
            significant = abs(mean - p.disparity_offset_px) > p.offset_sigmas * error
            self._offset = mean if significant else float(p.disparity_offset_px)

    def _window_offset(self, problem: _WindowProblem, weight: F64, x0: F64) -> tuple[float, float]:
        """The disparity shift (pixels) that minimises the window's cost, and its standard deviation.

        The cost (plain least squares, observations of ``weight`` 0 left out)
        is solved from ``x0`` (:meth:`_WindowProblem.solve`, Levenberg-Marquardt
        on the reduced camera system: the estimates of scipy's trust region
        solver to 4 decimals on KITTI 06, 5-10 times faster) with every disparity shifted by ``-h, 0, +h``
        (``h = VOParams.offset_step_px``); the parabola through the three
        gives the minimum (clipped to ``+-2 h``) and, with the residual
        variance per degree of freedom ``sigma^2`` (3 per observation; 6 per
        free frame and 3 per point), its standard deviation ``sigma h /
        sqrt(c)``, ``c`` the cost's second difference (cost ~ ``c (s -
        s*)^2 / (2 h^2)``). NaN, NaN when the cost does not curve upwards.
        """
        h = self.params.offset_step_px
        costs = []
        for shift in (-h, 0.0, h):
            _, fun = problem.with_right(problem.u_right - shift, weight).solve(x0)
            costs.append(0.5 * float(np.sum(fun**2)))
        lower, middle, upper = costs
        curvature = lower + upper - 2.0 * middle
        if not curvature > 0:
            return math.nan, math.nan
        used = weight > 0
        dof = 3 * int(used.sum()) - 6 * problem.n_free - 3 * np.unique(problem.pi[used]).size
        std = h * math.sqrt(2.0 * middle / max(dof, 1) / curvature)
        return float(np.clip(0.5 * h * (lower - upper) / curvature, -2.0 * h, 2.0 * h)), std


class _WindowProblem:
    """The windowed adjustment's stereo reprojection residuals and their analytic Jacobian.

    Unknowns ``x``: per free frame (``n_free``, all but the fixed oldest, whose
    ``T_cam_world`` is ``fixed``) the rotation vector and translation of its
    ``T_cam_world`` (6 each), then every track's world point (``n_points``,
    3 each, metres). Observation ``n`` of point ``pi[n]`` in frame ``fi[n]``
    (0 = the fixed one) gives three residuals, pixels times ``weight[n]``:
    left u, left v and right u of the projection minus the measured
    ``uv[n]``, ``u_right[n]``.
    """

    def __init__(
        self,
        camera: StereoCamera,
        fixed: F64,
        n_free: int,
        n_points: int,
        fi: NDArray[np.int64],
        pi: NDArray[np.int64],
        uv: F64,
        u_right: F64,
    ) -> None:
        import scipy.sparse

        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy
        self.fb = camera.focal_baseline
        self.fixed, self.fi, self.pi, self.uv, self.u_right = fixed, fi, pi, uv, u_right
        self.n_free, self.n_points = n_free, n_points
        #: Per observation (N,): 1, or 0 for tracks left out.
        self.weight = np.ones(fi.size)
        # The Jacobian's structure, fixed: 3 rows per observation, each with the 6 columns of its frame (when
        # free) and the 3 of its point. ``_order`` puts the (n, 3, 9) blocks' values into CSR order.
        n = fi.size
        free = fi > 0
        cols = np.empty((n, 3, 9), dtype=np.int64)
        cols[:, :, :6] = (6 * (fi[:, None] - 1) + np.arange(6))[:, None, :]
        cols[:, :, 6:] = (6 * self.n_free + 3 * pi[:, None] + np.arange(3))[:, None, :]
        rows = np.broadcast_to(np.arange(3 * n).reshape(n, 3, 1), (n, 3, 9))
        present = np.concatenate([np.repeat(free[:, None], 6, axis=1), np.ones((n, 3), bool)], axis=1)
        self._present = np.broadcast_to(present[:, None, :], (n, 3, 9))
        structure = scipy.sparse.coo_matrix(
            (np.arange(1, int(self._present.sum()) + 1, dtype=np.float64),
             (rows[self._present], cols[self._present])),
            shape=(3 * n, 6 * self.n_free + 3 * self.n_points),
        ).tocsr()  # fmt: skip
        self._order = structure.data.astype(np.int64) - 1
        self._indices, self._indptr, self._shape = structure.indices, structure.indptr, structure.shape

    def with_right(self, u_right: F64, weight: F64) -> _WindowProblem:
        """The same problem (its Jacobian structure shared) with other right-image measurements and weights."""
        other = copy.copy(self)
        other.u_right, other.weight = u_right, weight
        return other

    def _camera_points(self, x: F64) -> tuple[F64, F64, F64, F64]:
        """The free frames' rotation vectors (F, 3); every frame's rotation (F+1, 3, 3) and translation (F+1, 3);
        the observed points in their camera (N, 3)."""
        from scipy.spatial.transform import Rotation

        cams = x[: 6 * self.n_free].reshape(self.n_free, 6)
        pts = x[6 * self.n_free :].reshape(-1, 3)
        rot = np.concatenate([self.fixed[None, :3, :3], Rotation.from_rotvec(cams[:, :3]).as_matrix()])
        trans = np.concatenate([self.fixed[None, :3, 3], cams[:, 3:]])
        xc = np.einsum("nij,nj->ni", rot[self.fi], pts[self.pi]) + trans[self.fi]
        return cams[:, :3], rot, trans, xc

    def residuals(self, x: F64) -> F64:
        """(3 N,) weighted residuals, pixels."""
        _, _, _, xc = self._camera_points(x)
        z = np.where(xc[:, 2] > 1e-3, xc[:, 2], 1e-3)
        u = self.fx * xc[:, 0] / z + self.cx
        v = self.fy * xc[:, 1] / z + self.cy
        res = np.column_stack([u - self.uv[:, 0], v - self.uv[:, 1], u - self.fb / z - self.u_right])
        return (res * self.weight[:, None]).ravel()

    def jacobian(self, x: F64) -> scipy.sparse.csr_matrix:
        """The residuals' derivatives (3 N, len(x)), sparse (:meth:`blocks` in scipy's layout)."""
        import scipy.sparse

        data = self.blocks(x)[self._present][self._order]
        return scipy.sparse.csr_matrix((data, self._indices, self._indptr), shape=self._shape)

    def blocks(self, x: F64) -> F64:
        """The residuals' derivatives as one (3, 9) block per observation (N, 3, 9): by its frame's 6
        unknowns (zero for the fixed frame) and by its point's 3.

        With ``X_c = R X + t``: the projection's derivative ``A`` by ``X_c``
        (zero along depth where the depth is clamped at 1 mm), times ``R`` for
        the point, the identity for the translation and ``-[R X]_x J_l(r)``
        for the rotation vector ``r`` (``J_l``: SO(3)'s left Jacobian, since
        ``R(r + dr) = Exp(J_l(r) dr) R(r)`` to first order).
        """
        rotvec, rot, trans, xc = self._camera_points(x)
        n = self.fi.size
        ahead = xc[:, 2] > 1e-3
        z = np.where(ahead, xc[:, 2], 1e-3)
        inv_z = 1.0 / z
        dz = np.where(ahead, inv_z * inv_z, 0.0)  # d(1/z)/dz, negated
        a = np.zeros((n, 3, 3))
        a[:, 0, 0] = a[:, 2, 0] = self.fx * inv_z
        a[:, 1, 1] = self.fy * inv_z
        a[:, 0, 2] = -self.fx * xc[:, 0] * dz
        a[:, 1, 2] = -self.fy * xc[:, 1] * dz
        a[:, 2, 2] = a[:, 0, 2] + self.fb * dz
        a *= self.weight[:, None, None]
        blocks = np.empty((n, 3, 9))
        blocks[:, :, 6:] = a @ rot[self.fi]
        blocks[:, :, 3:6] = a
        rotated = xc - trans[self.fi]  # R X
        left = np.concatenate([np.zeros((1, 3, 3)), _left_jacobian(rotvec)])[self.fi]
        blocks[:, :, :3] = -a @ _skew(rotated) @ left
        blocks[self.fi == 0, :, :6] = 0.0
        return blocks

    def solve(self, x0: F64, max_iterations: int = 30, tolerance: float = 1e-10) -> tuple[F64, F64]:
        """Plain least squares from ``x0`` by Levenberg-Marquardt on the reduced camera system.

        The points are eliminated per iteration (the Schur complement of
        their 3x3 blocks), leaving a dense system of the free frames' 6
        unknowns each, as bundle adjusters do; a window of a few hundred
        tracks takes a few milliseconds an iteration. Stops when a step
        lowers the cost by less than ``tolerance`` of it, or after
        ``max_iterations`` accepted or refused steps.

        Returns:
            The solution and its residuals (3 N,).
        """
        import scipy.linalg

        x = np.array(x0, dtype=np.float64, copy=True)
        res = self.residuals(x)
        cost = float(res @ res)
        damping = 1e-4
        nc, npts = 6 * self.n_free, self.n_points
        free = self.fi > 0
        cam_index = np.where(free, self.fi - 1, 0)
        steps_left = max_iterations  # accepted and refused steps alike
        while steps_left > 0:
            b = self.blocks(x)
            r = res.reshape(-1, 3, 1)
            jc, jp = b[free, :, :6], b[:, :, 6:]
            jp_t, jc_t = jp.transpose(0, 2, 1), jc.transpose(0, 2, 1)
            v = np.zeros((npts, 3, 3))
            np.add.at(v, self.pi, jp_t @ jp)
            v[np.trace(v, axis1=1, axis2=2) <= 0] = np.eye(3)  # a point whose every observation weighs 0: stays
            gp = np.zeros((npts, 3))
            np.add.at(gp, self.pi, (jp_t @ r)[:, :, 0])
            u = np.zeros((self.n_free, 6, 6))
            np.add.at(u, cam_index[free], jc_t @ jc)
            gc = np.zeros((self.n_free, 6))
            np.add.at(gc, cam_index[free], (jc_t @ r[free])[:, :, 0])
            cross = np.zeros((npts, self.n_free, 6, 3))  # per point, its cross terms with each free frame
            cross[self.pi[free], cam_index[free]] = jc_t @ jp[free]
            w = cross.reshape(npts, nc, 3)
            while True:
                vd = v + damping * (np.einsum("pii->pi", v)[:, :, None] * np.eye(3))
                ud = u + damping * (np.einsum("fii->fi", u)[:, :, None] * np.eye(6))
                v_inv = np.linalg.inv(vd)
                y = w @ v_inv  # (P, 6F, 3)
                reduced = (
                    scipy.linalg.block_diag(*ud)
                    - y.transpose(1, 0, 2).reshape(nc, -1) @ w.transpose(1, 0, 2).reshape(nc, -1).T
                )
                rhs = -gc.ravel() + (y @ gp[:, :, None]).sum(axis=0)[:, 0]
                try:
                    dc = np.linalg.solve(reduced, rhs)
                except np.linalg.LinAlgError:
                    dc = np.linalg.lstsq(reduced, rhs, rcond=None)[0]
                dp = (v_inv @ (-gp - (w.transpose(0, 2, 1) @ dc))[:, :, None])[:, :, 0]
                candidate = x + np.concatenate([dc, dp.ravel()])
                new_res = self.residuals(candidate)
                new_cost = float(new_res @ new_res)
                steps_left -= 1
                if new_cost < cost or steps_left <= 0:
                    break
                damping *= 10.0
            if not new_cost < cost:
                break
            converged = cost - new_cost <= tolerance * cost
            x, res, cost = candidate, new_res, new_cost
            damping = max(damping / 10.0, 1e-9)
            if converged:
                break
        return x, res


def _skew(v: F64) -> F64:
    """Cross-product matrices (N, 3, 3) of vectors (N, 3): ``_skew(a) @ b = a x b``."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _left_jacobian(rotvec: F64) -> F64:
    """SO(3)'s left Jacobians (N, 3, 3) of rotation vectors (N, 3), radians (series below 1e-4 rad)."""
    theta = np.linalg.norm(rotvec, axis=1)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    k = _skew(rotvec)
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def _best_two(group: NDArray[np.int64], value: NDArray[np.int64] | F64) -> tuple[NDArray[np.int64], F64]:
    """Per group (sorted by group): the index of its smallest value, and its second smallest value (inf if none).

    Ties between the smallest go to the earlier entry; its second smallest is then equal to it.
    """
    order = np.lexsort((value, group))
    g = group[order]
    first = np.ones(g.size, dtype=bool)
    first[1:] = g[1:] != g[:-1]
    at = np.flatnonzero(first)
    has_second = at + 1 < g.size
    has_second[has_second] = ~first[at[has_second] + 1]
    second = np.full(at.size, np.inf)
    second[has_second] = value[order[at[has_second] + 1]]
    return order[at], second


def _hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.int64]:
    """Hamming distances (N,) between the rows of two (N, 32) uint8 descriptor arrays."""
    words = hamming(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))
    return words.sum(axis=1, dtype=np.int64)


def _row_candidates(query_rows: F64, train_rows: F64, reach: F64) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Every pair ``(q, t)`` with ``|train_rows[t] - query_rows[q]| <= reach[q]``, grouped by ``q``.

    The train rows are sorted once and each query takes the slice within its
    reach (a binary search each way), so the cost grows with the pairs found,
    not with queries times train features. The slice is 1e-6 px wider than
    the reach, against rounding: callers apply their exact test to the pairs.
    """
    order = np.argsort(train_rows, kind="stable")
    rows = train_rows[order]
    start = np.searchsorted(rows, query_rows - reach - 1e-6, side="left")
    stop = np.searchsorted(rows, query_rows + reach + 1e-6, side="right")
    count = np.maximum(stop - start, 0)
    qi = np.repeat(np.arange(query_rows.size, dtype=np.int64), count)
    offset = np.arange(qi.size, dtype=np.int64) - np.repeat(np.cumsum(count) - count, count)
    ti = order[np.repeat(start, count) + offset].astype(np.int64)
    return qi, ti


def _step_of(motion: F64, steps: int) -> F64:
    """The per-frame motion whose ``steps``-th power is ``motion``: the rotation vector divided by ``steps``,
    and the translation ``t`` with ``(I + R + ... + R^(steps-1)) t`` = the motion's."""
    from scipy.spatial.transform import Rotation

    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(motion[:3, :3]).as_rotvec() / steps).as_matrix()
    powers = np.eye(3)
    total = np.zeros((3, 3))
    for _ in range(steps):
        total += powers
        powers = powers @ step[:3, :3]
    step[:3, 3] = np.linalg.solve(total, motion[:3, 3])
    return step


def mark_isolated(qualities: Iterable[FrameQuality], params: VOParams | None = None) -> list[FrameQuality]:
    """The qualities with every reliable frame that has no other reliable frame within
    ``params.isolated_frames`` frames before and after it reported unreliable (status ``isolated``).

    The first frame (the world's origin, exact) is never marked but counts as
    a reliable neighbour. Unchanged when ``isolated_frames`` is 0. The whole
    sequence through :class:`IsolationGate`, which decides as frames arrive.
    """
    gate = IsolationGate(params)
    out = [decided for quality in qualities for decided in gate.add(quality)]
    return out + gate.finish()


def _isolated(quality: FrameQuality, reach: int) -> FrameQuality:
    """``quality`` reported unreliable as a reliable frame with no reliable neighbour within ``reach`` frames."""
    return replace(
        quality,
        status="isolated",
        reliable=False,
        message=f"no other reliable frame within {reach} frames before or after: its step length is in doubt",
    )


@dataclass
class _Pending:
    """A frame in :class:`IsolationGate`: its quality and what the frames after it showed so far."""

    quality: FrameQuality
    waiting: bool  # reliable, but no reliable frame within reach before it: the frames after it decide
    after: int = 0  # frames seen after it


class IsolationGate:
    """:func:`mark_isolated` as frames arrive: each frame's final reliability, in order, as soon as it is known.

    A reliable frame with a reliable frame among the ``isolated_frames``
    frames before it is decided at once; one without waits for up to as
    many frames after it (the first reliable one decides it reliable;
    none marks it ``isolated``). Frames behind a waiting one wait with it,
    so that decisions come out in frame order. On a sequence of reliable
    frames nothing waits; after a run of unreliable ones a frame waits at
    most ``isolated_frames`` frames. :meth:`finish` decides the rest as
    :func:`mark_isolated` does at a sequence's end.
    """

    def __init__(self, params: VOParams | None = None) -> None:
        self._reach = max(int((params or VOParams()).isolated_frames), 0)
        self._recent: deque[bool] = deque(maxlen=max(self._reach, 1))
        self._queue: deque[_Pending] = deque()

    def add(self, quality: FrameQuality) -> list[FrameQuality]:
        """Take the next frame's quality; return the final qualities of the frames now decided, oldest first."""
        reliable = quality.reliable
        for pending in self._queue:
            if pending.waiting:
                pending.after += 1
                if reliable:
                    pending.waiting = False
                elif pending.after >= self._reach:
                    pending.waiting = False
                    pending.quality = _isolated(pending.quality, self._reach)
        waits = reliable and self._reach > 0 and quality.status != "first" and not any(self._recent)
        self._recent.append(reliable)
        self._queue.append(_Pending(quality, waits))
        return self._decided()

    def finish(self) -> list[FrameQuality]:
        """The end of the sequence: every frame still waiting had no reliable frame after it."""
        for pending in self._queue:
            if pending.waiting:
                pending.waiting = False
                pending.quality = _isolated(pending.quality, self._reach)
        return self._decided()

    def undecided(self) -> list[int]:
        """Indices (:attr:`FrameQuality.index`) of the frames still waiting, or queued behind one."""
        return [pending.quality.index for pending in self._queue]

    def _decided(self) -> list[FrameQuality]:
        out = []
        while self._queue and not self._queue[0].waiting:
            out.append(self._queue.popleft().quality)
        return out


def smooth_step_lengths(poses: F64, qualities: list[FrameQuality], params: VOParams | None = None) -> F64:
    """Poses (N, 4, 4) whose step lengths are smoothed over the sequence; directions and rotations are kept,
    but where the road's length is used, with ``road_motion``, the step is the road's (then its length smoothed).

    A Kalman filter and Rauch-Tung-Striebel smoother over the frames with
    the state (step length, its change per frame) and the process noise
    ``params.length_acceleration_m``. Measurements are the lengths of the
    steps measured from the frame before (``FrameQuality.translation_m``
    of an ``ok`` or ``weak_scale`` frame whose reference is the frame
    before), with the noise ``length_sigmas`` times ``scale_std_pct``, at
    least ``length_floor_pct`` of the length, ``weak_length_factor`` times
    more for ``weak_scale``; a ``weak_scale`` length further than
    ``length_gate_sigmas`` from the filter's prediction is left out. With
    ``road_steps``, the road's length of the step (always measured from
    the frame before) is a second measurement (noise ``road_noise_pct``,
    open to the gate, only where a neighbour's agrees:
    :func:`_agreed_road_lengths`), also where the features failed or were
    measured across a gap. Frames without a measurement take the smoothed prediction; ``static``
    frames stay still. Unchanged when ``params.smooth_lengths`` is off; the
    lengths unchanged when fewer than two steps are measured.
    """
    p = params or VOParams()
    out = np.array(poses, dtype=np.float64, copy=True)
    n = len(out) - 1
    if not p.smooth_lengths or n < 2:
        return out
    steps = np.linalg.inv(out[:-1]) @ out[1:]
    value, measured, noise, gated = _length_measurements(qualities[1 : n + 1], p, p.length_floor_pct)
    if p.road_motion:  # where the road's length is a measurement, the step is the road's
        for j in np.flatnonzero(measured[:, 0]):
            motion = qualities[j + 1].road_motion
            if len(motion) == 6:
                steps[j] = _pose_from_vector(np.asarray(motion, dtype=np.float64))
    length = np.linalg.norm(steps[:, :3, 3], axis=1)
    if measured.any(axis=1).sum() >= 2:
        smoothed, _ = _rts_constant_velocity(value, measured, noise, p.length_acceleration_m, p.length_gate_sigmas,
                                             gated)  # fmt: skip
        moving = length > 1e-9
        moving &= np.array([q.status != "static" for q in qualities[1 : n + 1]])
        steps[moving, :3, 3] *= (np.maximum(smoothed[moving], 0.0) / length[moving])[:, None]
    for k in range(n):
        out[k + 1] = out[k] @ steps[k]
    return out


def step_length_spread(qualities: list[FrameQuality], params: VOParams | None = None) -> F64:
    """Per frame (N,), how well the sequence's measured step lengths pin down the frame's step: percent.

    The smoother of :func:`smooth_step_lengths` (same model and
    measurements) run with each measurement's noise its own reported one
    (``length_sigmas`` times ``scale_std_pct``, ``weak_length_factor`` times
    more for a ``weak_scale`` step; the road's ``road_noise_pct``) and no
    ``length_floor_pct`` (its gate judged with these noises); the standard deviation of each smoothed step
    length, as a percent of that smoother's length (inf where it is not
    positive). Small where the step and its neighbours were measured well;
    large where the step was not measured, its neighbours were weak, or at
    a sequence's ends, where only one side can average its noise out. The
    process noise is an absolute ``length_acceleration_m``, so for the same
    per-step noise a slower camera's spread is larger (at 0.3 % per step:
    0.49 % for 3 m steps, 0.62 % for 1 m, 0.75 % for 0.3 m). NaN for the
    first frame, when fewer than two steps were measured, or when smoothing
    is off.
    """
    p = params or VOParams()
    n = len(qualities) - 1
    spread = np.full(n + 1, np.nan)
    if not p.smooth_lengths or n < 2:
        return spread
    value, measured, noise, gated = _length_measurements(qualities[1:], p, 0.0)
    if measured.any(axis=1).sum() < 2:
        return spread
    smoothed, std = _rts_constant_velocity(value, measured, noise, p.length_acceleration_m, p.length_gate_sigmas, gated)
    with np.errstate(divide="ignore", invalid="ignore"):
        spread[1:] = np.where(smoothed > 0, 100.0 * std / smoothed, np.inf)
    return spread


def mark_uncertain(
    qualities: Iterable[FrameQuality], spread: F64, params: VOParams | None = None, focal_baseline: float = 0.0
) -> list[FrameQuality]:
    """The qualities with every frame :func:`judge_spread` finds too loosely pinned down reported
    ``uncertain``; ``spread`` is per frame, as :func:`step_length_spread` returns it."""
    return [
        judge_spread(q, float(spread[k]) if k < len(spread) else math.nan, params, focal_baseline)
        for k, q in enumerate(qualities)
    ]


def judge_spread(
    quality: FrameQuality, spread: float, params: VOParams | None = None, focal_baseline: float = 0.0
) -> FrameQuality:
    """``quality`` reported unreliable (status ``uncertain``; its pose is kept) when it is ``ok`` and its
    :func:`step_length_spread` ``spread`` exceeds ``params.max_length_spread_pct``; else as it is.

    Only frames measured from the frame before: one measured across a gap
    (its reference further back) has no step of its own for the smoother,
    and its pose is as good as the check that passed it. A camera's
    ``focal_baseline`` (``fx * b``) below ``params.reference_focal_baseline``
    raises the limit by their ratio, as the scale check's (0: KITTI's).
    Never when ``max_length_spread_pct`` is 0.
    """
    p = params or VOParams()
    if p.max_length_spread_pct <= 0 or quality.status != "ok" or quality.reference != quality.index - 1:
        return quality
    limit = p.max_length_spread_pct * _coarseness(p, focal_baseline)
    if not spread > limit:
        return quality
    return replace(
        quality,
        status="uncertain",
        reliable=False,
        message=f"the smoothed step length is known to {spread:.2f} % (more than {limit:.2f} %): too few well "
        "measured steps around it",
    )


def _coarseness(p: VOParams, focal_baseline: float) -> float:
    """How much a camera's step-length limits grow over KITTI's: ``reference_focal_baseline`` over its
    ``fx * b``, at least 1 (``focal_baseline`` 0: KITTI's)."""
    return max(1.0, p.reference_focal_baseline / focal_baseline) if focal_baseline > 0 else 1.0


def _length_measurements(
    qualities: list[FrameQuality], p: VOParams, floor_pct: float
) -> tuple[F64, NDArray[np.bool_], F64, NDArray[np.bool_]]:
    """The smoother's measurements of steps 1..N (``qualities`` of frames 1..N), two per step (N, 2): the
    road's (column 0: ``road_length_m``, noise ``road_noise_pct``; always open to the gate) and the
    features' (column 1). Lengths, which are measured, their noise (metres; the features' at least
    ``floor_pct`` of the length) and which the gate may leave out (the road's, unreliable frames', and
    reliable frames' where the road measured the step too).
    The road's (always the step from the frame before) counts for any frame but ``static`` ones, failed ones
    and ones measured across a gap too."""
    n = len(qualities)
    measured = np.zeros((n, 2), dtype=bool)
    value = np.zeros((n, 2))
    noise = np.ones((n, 2))
    gated = np.ones((n, 2), dtype=bool)
    road = _agreed_road_lengths(qualities, p)
    for k, q in enumerate(qualities):
        if q.status == "static":
            continue
        if np.isfinite(road[k]):  # also where the features failed: the road may see past a truck
            measured[k, 0] = True
            value[k, 0] = road[k]
            noise[k, 0] = max(road[k] * p.road_noise_pct / 100.0, 1e-6)
        if q.reference != k:
            continue
        std = q.scale_std_pct
        if q.status not in ("ok", "weak_scale") or q.translation_m <= 0 or not np.isfinite(std):
            continue
        measured[k, 1] = True
        value[k, 1] = q.translation_m
        pct = max(p.length_sigmas * std, floor_pct) * (1.0 if q.reliable else p.weak_length_factor)
        noise[k, 1] = max(q.translation_m * pct / 100.0, 1e-6)
        # A reliable step is gated too where the road measured it: a step far from the road's agreed length
        # rests on something that moved (highway seed 191: a frame measured on a truck passed every check).
        gated[k, 1] = not q.reliable or bool(measured[k, 0])
    return value, measured, noise, gated


def _agreed_road_lengths(qualities: list[FrameQuality], p: VOParams) -> F64:
    """Per frame, the road's step length where a neighbouring frame's road length agrees with it within
    ``road_agreement_pct`` (a vehicle's speed changes little from one frame to the next); NaN elsewhere.

    A road alignment started far from the truth (a step measured on a
    truck, the first steps without a velocity) can settle on a wrong length
    that still looks well aligned; two neighbours rarely settle on the same
    wrong one.
    """
    n = len(qualities)
    out = np.full(n, np.nan)
    if not p.road_steps:
        return out
    length = np.array([q.road_length_m if q.road_length_m > 0 else np.nan for q in qualities], dtype=np.float64)
    for k in range(n):
        if not np.isfinite(length[k]):
            continue
        near = [length[j] for j in (k - 1, k + 1) if 0 <= j < n and np.isfinite(length[j])]
        if any(abs(other / length[k] - 1.0) * 100.0 <= p.road_agreement_pct for other in near):
            out[k] = length[k]
    return out


def _rts_constant_velocity(
    value: F64,
    measured: NDArray[np.bool_],
    noise: F64,
    acceleration: float,
    gate: float = 0.0,
    gated: NDArray[np.bool_] | None = None,
) -> tuple[F64, F64]:
    """Smoothed ``value`` under x_{k+1} = x_k + v_k, v random-walking by ``acceleration`` per step, and
    its standard deviation (N,).

    ``value`` is (N,) or (N, M): M measurements of each step, taken in
    column order. ``measured`` marks the entries observed, with standard
    deviations ``noise``; steps with none are predicted (before the first
    measurement too, by the smoother's backward pass). The filter starts
    from a vague prior (ten times the first measured value, or 10, as the
    spread of both). With ``gate`` > 0, a measurement marked in ``gated``
    (default: every one) that lies further than ``gate`` standard
    deviations of its innovation (prediction and measurement spread
    together) from the filter's prediction is left out, as if it had not
    been measured.
    """
    value = np.asarray(value, dtype=np.float64).reshape(len(value), -1)
    measured = np.asarray(measured, dtype=bool).reshape(value.shape)
    noise = np.asarray(noise, dtype=np.float64).reshape(value.shape)
    gated = np.ones(value.shape, bool) if gated is None else np.asarray(gated, dtype=bool).reshape(value.shape)
    n = len(value)
    f = np.array([[1.0, 1.0], [0.0, 1.0]])
    q = acceleration**2 * np.array([[0.25, 0.5], [0.5, 1.0]])
    first = value[measured][0]
    vague = 10.0 * max(abs(float(first)), 1.0)
    x = np.array([first, 0.0])
    cov = np.diag([vague**2, vague**2])
    filtered, filtered_cov = np.zeros((n, 2)), np.zeros((n, 2, 2))
    predicted, predicted_cov = np.zeros((n, 2)), np.zeros((n, 2, 2))
    for k in range(n):
        if k > 0:
            x, cov = f @ x, f @ cov @ f.T + q
        predicted[k], predicted_cov[k] = x, cov
        for j in np.flatnonzero(measured[k]):
            spread = cov[0, 0] + noise[k, j] ** 2
            outlier = gate > 0 and (value[k, j] - x[0]) ** 2 > gate**2 * spread
            if not (outlier and gated[k, j]):
                gain = cov[:, 0] / spread
                x = x + gain * (value[k, j] - x[0])
                cov = cov - np.outer(gain, cov[0, :])
        filtered[k], filtered_cov[k] = x, cov
    smoothed, smoothed_cov = filtered.copy(), filtered_cov.copy()
    for k in range(n - 2, -1, -1):
        back = filtered_cov[k] @ f.T @ np.linalg.inv(predicted_cov[k + 1])
        smoothed[k] = filtered[k] + back @ (smoothed[k + 1] - predicted[k + 1])
        smoothed_cov[k] = filtered_cov[k] + back @ (smoothed_cov[k + 1] - predicted_cov[k + 1]) @ back.T
    return smoothed[:, 0], np.sqrt(np.maximum(smoothed_cov[:, 0, 0], 0.0))
