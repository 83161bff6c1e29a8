"""Negatives from a second, independent matcher (``LabelerParams.cross_check_matcher``).

The self-contradiction test cannot mark an error that every view repeats:
the references come from the same query algorithm, and where its matching
fails alike in every view (orbit's far ground at the horizon, matched 3-6 px
too near in every frame), the depths agree and confirm each other. A second
matcher with a different cost and a different aggregation fails elsewhere.
:class:`CrossCheck` runs one (census-transform SGM,
:class:`~selfcontra_ros.matching.census.CensusSGMMatcher`) on the same stereo
pairs, labels *its* depth maps with a second labeler of the same parameters
over the same window, and turns an unknown query pixel into a negative where

* the second matcher's depth there is a positive of its own labels (its
  depth is confirmed by the window), and
* the two disparities differ by more than ``cross_check_min_difference_px``.

A confirmed depth that disagrees by that much is evidence the query's depth
is wrong; the multi-view confirmation is what makes it evidence (on orbit
the census matcher's raw output is more than 3 px from 2.0 % of the query's
right positives, more than the 1.8 % of its positives that are wrong, and
from only 18 % of the wrong ones). Positive and negative
query labels are never changed: the paper's labels stay as they are and the
check only adds negatives where the paper's stages were silent.

Measured on the label benchmark's tuning seeds 1-10 at 613x185 (forests
trained on the self labels of seeds 1-5, scored on 6-10; figures in
``LabelerParams.cross_check_min_difference_px`` and ``docs/label_quality.md``): at the
default 4 px, 85 % of the new negatives are on wrong query depth on
``orbit`` and 52 % on ``street``, and the Ensemble forest's self /
ground-truth AUSC ratio went from 2.69 to 1.90 on orbit and from 1.34 to
1.33 on street (room 1.04, unchanged). Held out at 1226x370 (seeds 21-30)
the forest did not gain (orbit 1.968 -> 1.939), though the check still found
more of the query's errors (orbit's bad recall 7.2 -> 12.0 %, the new
negatives 79.5 % right against 72 % for the paper's own).

The cost: a census SGM run per frame (numba, on one core: about 1 s at
613x185 and 5 s at 1226x370, against SGBM's 0.06 s there) and a second
labeling of every view, so the check
is off by default and meant for offline labelling (``selfcontra label``,
``label-bag``); the node accepts it too.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import CROSS_CHECK_MATCHERS, Labeler, LabelerParams, LabelResult
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.matching.base import MatcherParams, make_matcher

__all__ = ["CROSS_CHECK_MATCHERS", "CrossCheck", "check_supported", "cross_negatives"]


def check_supported(matcher_params: MatcherParams, labeler_params: LabelerParams) -> None:
    """Refuse a cross check the query algorithm cannot feed (the parameter files and every session call it).

    Raises:
        SelfContraError: the cross check is on and ``matcher.algorithm`` is ``external`` (no stereo images).
    """
    if matcher_params.algorithm == "external" and labeler_params.cross_check_matcher != "none":
        raise SelfContraError(
            "labeler.cross_check_matcher needs the stereo images, which matcher.algorithm 'external' "
            "does not give; set it to 'none'"
        )


def cross_negatives(
    labels: NDArray[np.uint8],
    disparity: NDArray[np.floating],
    other_labels: NDArray[np.uint8],
    other_disparity: NDArray[np.floating],
    min_difference_px: float,
) -> NDArray[np.bool_]:
    """Pixels the cross check makes negative (HxW bool).

    Args:
        labels: the query's labels from the paper's stages.
        disparity: the query's disparity, pixels (NaN or <= 0 invalid).
        other_labels: the second matcher's labels of the same view.
        other_disparity: the second matcher's disparity, pixels.
        min_difference_px: a larger ``|d_other - d|`` contradicts.
    """
    d = np.asarray(disparity, dtype=np.float64)
    o = np.asarray(other_disparity, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0) & np.isfinite(o) & (o > 0)
        far_apart = np.abs(o - d) > min_difference_px
    return (labels == UNKNOWN) & (other_labels == POSITIVE) & valid & far_apart


class CrossCheck:
    """The second matcher and its labeler beside one labeling session.

    Feed it every view the session's labeler gets (:meth:`add_view`) before
    the labeler, then pass the labeler's results through :meth:`apply`: both
    labelers keep the same views (the keyframe rule depends on the poses
    alone) and label each view with the same number of newer views, so the
    second labels of a view are ready when the query's are.
    """

    def __init__(self, camera: StereoCamera, matcher_params: MatcherParams, labeler_params: LabelerParams) -> None:
        self.min_difference_px = float(labeler_params.cross_check_min_difference_px)
        # Only the disparity range of the query: the census matcher's penalties are on its own (Hamming) scale.
        self._matcher = make_matcher(
            MatcherParams(
                algorithm=labeler_params.cross_check_matcher,
                num_disparities=matcher_params.num_disparities,
                min_disparity=matcher_params.min_disparity,
            )
        )
        self._labeler = Labeler(camera, dataclasses.replace(labeler_params, cross_check_matcher="none"))
        self._window = labeler_params.window_size
        # Per kept view (key, stamp): (query disparity, second disparity); then the second labels when ready.
        self._views: dict[tuple[Hashable, float], tuple[NDArray[np.float32], NDArray[np.float32]]] = {}
        self._ready: dict[tuple[Hashable, float], NDArray[np.uint8]] = {}
        #: labelled views the second labeler had no labels for (left as the paper's stages gave them).
        self.unmatched_views = 0
        #: query pixels the check made negative, over all views.
        self.negatives = 0

    def add_view(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        disparity: NDArray[np.float32],
        pose: NDArray[np.float64],
        *,
        stamp: float,
        key: Hashable,
    ) -> None:
        """Match the pair with the second matcher and add the view to the second labeler."""
        skipped = self._labeler.skipped_views
        other = self._matcher.compute(left, right, with_right=False).left
        results = self._labeler.add_view(
            other, pose, stamp=stamp, key=key, image=left, max_disparity=self._matcher.params.max_disparity
        )
        if self._labeler.skipped_views == skipped:
            self._views[(key, stamp)] = (np.asarray(disparity, dtype=np.float32), other)
        self._keep(results)

    def _keep(self, results: list[LabelResult]) -> None:
        for result in results:
            self._ready[(result.key, result.stamp)] = result.labels
        # Bounded whatever the caller does: never more than a window of views of either kind.
        for store in (self._views, self._ready):
            while len(store) > self._window:
                store.pop(next(iter(store)))

    def flush(self) -> None:
        """End of a sequence: the second labeler labels what it still holds (call before the query's flush)."""
        self._keep(self._labeler.flush())

    def apply(self, result: LabelResult) -> LabelResult:
        """The query's result with the cross-check negatives added (a copy; the Stage-2 map is left as it was)."""
        name = (result.key, result.stamp)
        other_labels = self._ready.pop(name, None)
        views = self._views.pop(name, None)
        if other_labels is None or views is None:
            self.unmatched_views += 1
            return result
        disparity, other = views
        add = cross_negatives(result.labels, disparity, other_labels, other, self.min_difference_px)
        self.negatives += int(add.sum())
        return dataclasses.replace(result, labels=np.where(add, np.uint8(NEGATIVE), result.labels).astype(np.uint8))

    def clear(self) -> None:
        """Forget every waiting view (after the query's flush)."""
        self._views.clear()
        self._ready.clear()
