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
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import Labeler, LabelerParams, LabelResult
from selfcontra_ros.matching.base import Matcher, MatcherError, MatcherParams, make_matcher
from selfcontra_ros.matching.external import normalize_disparity

__all__ = ["FrameOutput", "LabelingSession"]


@dataclass
class FrameOutput:
    """What one processed stereo frame gives.

    Attributes:
        disparity: left disparity of the query algorithm, float32 pixels, NaN invalid.
        depth: left depth, float32 metres (REP 118), NaN where the disparity is invalid.
        labelled: label results of views that became ready with this frame (older views).
        skipped: whether the labeler's keyframe rule rejected this view.
    """

    disparity: NDArray[np.float32]
    depth: NDArray[np.float32]
    labelled: list[LabelResult] = field(default_factory=list)
    skipped: bool = False


class LabelingSession:
    """Query algorithm plus sliding-window labeler for one rectified stereo camera.

    Args:
        camera: the rectified stereo camera; every frame must match its size.
        matcher_params: the query algorithm; ``algorithm: external`` takes
            the disparity from the caller (``external_disparity``).
        labeler_params: the self-contradiction labeler's parameters.
    """

    def __init__(
        self,
        camera: StereoCamera,
        matcher_params: MatcherParams | None = None,
        labeler_params: LabelerParams | None = None,
    ) -> None:
        self.camera = camera
        self.matcher_params = matcher_params if matcher_params is not None else MatcherParams()
        self.labeler_params = labeler_params if labeler_params is not None else LabelerParams()
        self._matcher: Matcher | None = (
            None if self.matcher_params.algorithm == "external" else make_matcher(self.matcher_params)
        )
        self.labeler = Labeler(camera, self.labeler_params)

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
        expected = (self.camera.height, self.camera.width)
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
            disparity = self._matcher.compute(left, right, with_right=False).left
        depth = self.camera.disparity_to_depth(disparity).astype(np.float32)
        return disparity, depth

    def label(
        self, disparity: NDArray[np.float32], pose: NDArray[np.float64], *, stamp: float, key: Hashable = None
    ) -> tuple[list[LabelResult], bool]:
        """Add one view to the labeler; returns ``(ready label results, skipped)``.

        ``skipped`` is true when the keyframe rule rejected the view (too
        little motion since the last kept view); such a view is never labelled.
        """
        skipped_before = self.labeler.skipped_views
        results = self.labeler.add_view(disparity, pose, stamp=stamp, key=key)
        return results, self.labeler.skipped_views > skipped_before

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
        """:meth:`match` then :meth:`label` for one frame."""
        disparity, depth = self.match(left, right, external_disparity=external_disparity)
        labelled, skipped = self.label(disparity, pose, stamp=stamp, key=key)
        return FrameOutput(disparity=disparity, depth=depth, labelled=labelled, skipped=skipped)

    def flush(self) -> list[LabelResult]:
        """End of stream: label every view still waiting, with the views available."""
        return self.labeler.flush()
