"""One stereo camera's labeling session: the object every front end shares.

The ROS labeler node, the offline bag labeler and the sequence labeler
(``selfcontra label``) all drive a :class:`LabelingSession`, so the same input
gives the same labels whichever way it arrives. A session splits the work in
the two parts a robot needs at different rates:

* :meth:`LabelingSession.match` runs the query algorithm on one stereo pair
  (fast, once per frame: depth and disparity come out at once);
* :meth:`LabelingSession.label` feeds the view to the sliding-window labeler
  (slow: a node runs it off the subscription thread) and returns the labels
  of views that became ready, ``label_delay`` views back.

:meth:`LabelingSession.process` does both in sequence, for offline use.

With an :class:`~selfcontra_ros.confidence.online.OnlineConfidence` attached
(``confidence=``), :meth:`LabelingSession.match_frame` also computes the
right disparity (for the LRD baseline and the left-right features) and
returns the frame's :class:`~selfcontra_ros.confidence.online.ConfidenceFrame`;
:meth:`LabelingSession.label` keeps each view's frame until the view is
labelled and then hands frame and labels to the confidence's reservoir;
:meth:`LabelingSession.process` adds the frame's ``confidence`` and
``depth_filtered`` to its output.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence.online import ConfidenceFrame, OnlineConfidence, filter_depth
from selfcontra_ros.cross_check import CrossCheck, check_supported
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import Labeler, LabelerParams, LabelResult
from selfcontra_ros.matching.base import Matcher, MatcherError, MatcherParams, make_matcher
from selfcontra_ros.matching.external import normalize_disparity

__all__ = ["FrameOutput", "LabelingSession", "MatchOutput"]


@dataclass
class FrameOutput:
    """What one processed stereo frame gives.

    Attributes:
        disparity: left disparity of the query algorithm, float32 pixels, NaN invalid.
        depth: left depth, float32 metres (REP 118), NaN where the disparity is invalid.
        labelled: label results of views that became ready with this frame (older views).
        skipped: whether the labeler's keyframe rule rejected this view.
        confidence: HxW float32 confidence in [0, 1] (None without an attached confidence).
        depth_filtered: ``depth`` with NaN where ``confidence`` is below the threshold (None without).
        confidence_source: ``"lrd"`` or the forest's feature set that gave ``confidence`` ("" without).
    """

    disparity: NDArray[np.float32]
    depth: NDArray[np.float32]
    labelled: list[LabelResult] = field(default_factory=list)
    skipped: bool = False
    confidence: NDArray[np.float32] | None = None
    depth_filtered: NDArray[np.float32] | None = None
    confidence_source: str = ""


@dataclass
class MatchOutput:
    """One matched frame: its depth and what its confidence reads.

    Attributes:
        disparity: left disparity, float32 pixels, NaN invalid.
        depth: left depth, float32 metres, NaN invalid.
        frame: images and both disparities for the confidence (right disparity None in external mode).
    """

    disparity: NDArray[np.float32]
    depth: NDArray[np.float32]
    frame: ConfidenceFrame


class LabelingSession:
    """Query algorithm plus sliding-window labeler for one rectified stereo camera.

    Args:
        camera: the rectified stereo camera; every frame must match its size.
        matcher_params: the query algorithm; ``algorithm: external`` takes
            the disparity from the caller (``external_disparity``).
        labeler_params: the self-contradiction labeler's parameters.
        confidence: online confidence fed by this session's labelled views
            (may be shared by several sessions, e.g. across camera changes).
    """

    def __init__(
        self,
        camera: StereoCamera,
        matcher_params: MatcherParams | None = None,
        labeler_params: LabelerParams | None = None,
        confidence: OnlineConfidence | None = None,
    ) -> None:
        self.camera = camera
        self.matcher_params = matcher_params if matcher_params is not None else MatcherParams()
        self.labeler_params = labeler_params if labeler_params is not None else LabelerParams()
        self._matcher: Matcher | None = (
            None if self.matcher_params.algorithm == "external" else make_matcher(self.matcher_params)
        )
        self.labeler = Labeler(camera, self.labeler_params)
        #: the second matcher of ``labeler_params.cross_check_matcher`` (None when ``none``).
        self.cross_check: CrossCheck | None = None
        if self.labeler_params.cross_check_matcher != "none":
            check_supported(self.matcher_params, self.labeler_params)
            self.cross_check = CrossCheck(camera, self.matcher_params, self.labeler_params)
        self.confidence = confidence
        # Frames of the views in the labeler's window, until labelled: keyed by (key, stamp).
        self._frames: dict[tuple[Hashable, float], ConfidenceFrame] = {}

    @property
    def external(self) -> bool:
        """Whether disparities come from the caller instead of a built-in matcher."""
        return self._matcher is None

    def match(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        *,
        external_disparity: NDArray[np.floating] | None = None,
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Disparity (pixels) and depth (metres) of the left image, float32 with NaN invalid.

        Raises:
            SelfContraError: the images do not match the camera or each other,
                or an external disparity is missing or of the wrong size.
        """
        out = self._match(left, right, external_disparity=external_disparity, with_right=False)
        return out.disparity, out.depth

    def match_frame(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        *,
        external_disparity: NDArray[np.floating] | None = None,
    ) -> MatchOutput:
        """:meth:`match` plus the right disparity (built-in matchers), packed for the confidence.

        The left disparity is the one :meth:`match` gives (the right one is a second, independent run).

        Raises:
            SelfContraError: as :meth:`match`.
        """
        return self._match(left, right, external_disparity=external_disparity, with_right=True)

    def _match(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        *,
        external_disparity: NDArray[np.floating] | None,
        with_right: bool,
    ) -> MatchOutput:
        expected = (self.camera.height, self.camera.width)
        disparity_right: NDArray[np.float32] | None = None
        if self._matcher is None:
            if external_disparity is None:
                raise MatcherError("matcher.algorithm is 'external' but no external disparity was given")
            disparity = normalize_disparity(external_disparity, name="external disparity")
            if disparity.shape != expected:
                raise MatcherError(
                    f"external disparity is {disparity.shape[1]}x{disparity.shape[0]}, "
                    f"the camera is {expected[1]}x{expected[0]}"
                )
        else:
            if left.shape[:2] != expected:
                raise MatcherError(
                    f"left image is {left.shape[1]}x{left.shape[0]}, the camera is {expected[1]}x{expected[0]}"
                )
            pair = self._matcher.compute(left, right, with_right=with_right)
            disparity, disparity_right = pair.left, pair.right
        depth = self.camera.disparity_to_depth(disparity).astype(np.float32)
        frame = ConfidenceFrame(left, right, disparity, disparity_right, self.matcher_params)
        return MatchOutput(disparity=disparity, depth=depth, frame=frame)

    def confidence_of(self, frame: ConfidenceFrame) -> tuple[NDArray[np.float32], NDArray[np.float32], str]:
        """``(confidence, depth_filtered, source)`` of a matched frame with the attached confidence's current model.

        Raises:
            SelfContraError: no confidence is attached.
        """
        if self.confidence is None:
            raise SelfContraError("this labeling session has no confidence attached")
        model = self.confidence.model
        confidence = self.confidence.confidence(frame, model)
        depth = self.camera.disparity_to_depth(frame.disparity).astype(np.float32)
        filtered = filter_depth(depth, confidence, self.confidence.params.confidence_threshold)
        return confidence, filtered, self.confidence.source if model is not None else "lrd"

    def label(
        self,
        disparity: NDArray[np.float32],
        pose: NDArray[np.float64],
        *,
        stamp: float,
        key: Hashable = None,
        frame: ConfidenceFrame | None = None,
        image: NDArray[np.uint8] | None = None,
        right: NDArray[np.uint8] | None = None,
    ) -> tuple[list[LabelResult], bool]:
        """Add one view to the labeler; returns ``(ready label results, skipped)``.

        ``skipped`` is true when the keyframe rule rejected the view (too
        little motion since the last kept view); such a view is never labelled.
        With a confidence attached and the view's ``frame`` given, the frame
        waits here until the view is labelled, then frame and labels go to
        :meth:`OnlineConfidence.add_labelled`. With a cross check
        (``labeler_params.cross_check_matcher``) the stereo pair comes from
        ``frame`` or from ``image`` and ``right``. The labeler learns the built-in matcher's disparity range
        (``labeler_params.range_abstain``); in external mode the range is unknown and every view speaks about
        every point.

        Raises:
            SelfContraError: as :meth:`Labeler.add_view`; with a cross check, when the stereo pair is missing.
        """
        skipped_before = self.labeler.skipped_views
        if self.confidence is not None and frame is not None:
            self._frames[(key, stamp)] = frame
        if image is None and frame is not None:
            image = frame.left
        if right is None and frame is not None:
            right = frame.right
        if self.cross_check is not None:
            if image is None or right is None:
                raise SelfContraError("labeler.cross_check_matcher needs the view's left and right images")
            self.cross_check.add_view(image, right, disparity, pose, stamp=stamp, key=key)
        searched = None if self._matcher is None else self.matcher_params.max_disparity
        results = self.labeler.add_view(disparity, pose, stamp=stamp, key=key, image=image, max_disparity=searched)
        if self.cross_check is not None:
            results = [self.cross_check.apply(result) for result in results]
        skipped = self.labeler.skipped_views > skipped_before
        if skipped:
            self._frames.pop((key, stamp), None)
        self._learn(results)
        return results, skipped

    def _learn(self, results: list[LabelResult]) -> None:
        """Hand the labelled views' frames to the confidence; forget frames that left the window unlabelled."""
        if self.confidence is None:
            return
        for result in results:
            frame = self._frames.pop((result.key, result.stamp), None)
            if frame is not None:
                self.confidence.add_labelled(frame, result.labels)
        # Bounded whatever happens in the labeler: at most a window of frames waits.
        while len(self._frames) > self.labeler_params.window_size:
            self._frames.pop(next(iter(self._frames)))

    def process(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        pose: NDArray[np.float64],
        *,
        stamp: float,
        key: Hashable = None,
        external_disparity: NDArray[np.floating] | None = None,
    ) -> FrameOutput:
        """:meth:`match` then :meth:`label` for one frame (and its confidence when one is attached).

        The confidence uses the model current *before* this frame's labelled
        views are learnt from, as a live node would.
        """
        if self.confidence is None:
            disparity, depth = self.match(left, right, external_disparity=external_disparity)
            labelled, skipped = self.label(disparity, pose, stamp=stamp, key=key, image=left, right=right)
            return FrameOutput(disparity=disparity, depth=depth, labelled=labelled, skipped=skipped)
        matched = self.match_frame(left, right, external_disparity=external_disparity)
        confidence, filtered, source = self.confidence_of(matched.frame)
        labelled, skipped = self.label(matched.disparity, pose, stamp=stamp, key=key, frame=matched.frame)
        return FrameOutput(
            disparity=matched.disparity,
            depth=matched.depth,
            labelled=labelled,
            skipped=skipped,
            confidence=confidence,
            depth_filtered=filtered,
            confidence_source=source,
        )

    def flush(self) -> list[LabelResult]:
        """End of stream: label every view still waiting, with the views available (and learn from them)."""
        if self.cross_check is not None:
            self.cross_check.flush()
        results = self.labeler.flush()
        if self.cross_check is not None:
            results = [self.cross_check.apply(result) for result in results]
            self.cross_check.clear()
        self._learn(results)
        self._frames.clear()
        return results
