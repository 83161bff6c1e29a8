"""Label quality against ground-truth disparity (DESIGN section 8, paper section 4).

A query pixel is *evaluable* when it has both a valid query disparity
(finite and > 0, DESIGN section 2) and ground truth (finite and > 0). It is
*correct* when ``|d - d_gt| <= threshold`` (3 px, the KITTI rule). The
ground-truth label image labels every evaluable pixel: positive if correct,
negative if not. Our labels are compared with it on the evaluable pixels only.

Keys of :func:`label_metrics` (all floats; NaN where a share has an empty
denominator, e.g. ``positive_precision`` of a frame without positives):

==========================  ================================================================
``accuracy``                share of our labelled evaluable pixels whose label agrees with GT
``coverage``                share of the evaluable pixels that we labelled (positive or negative)
``positive_precision``      share of our evaluable positives that are correct
``negative_precision``      share of our evaluable negatives that are not correct (bad depth)
``bad_recall``              share of the query algorithm's bad evaluable pixels we labelled negative
``positive_share``          our positives / evaluable pixels
``negative_share``          our negatives / evaluable pixels
``query_bad_rate``          bad (not correct) evaluable pixels / evaluable pixels
``evaluable_pixels``        number of evaluable pixels (as a float)
``stage2_<name>``           the first seven figures above for the Stage-2-alone labels
==========================  ================================================================

Keys of :func:`label_shares` (no ground truth needed; also part of
:func:`label_metrics`):

==========================  ================================================================
``query_valid_share``       pixels with a valid query disparity / all pixels
``label_positive_share``    our positives / valid query pixels
``label_negative_share``    our negatives / valid query pixels
``label_unknown_share``     valid query pixels we left unknown / valid query pixels
==========================  ================================================================
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN

__all__ = [
    "DEFAULT_THRESHOLD_PX",
    "ground_truth_labels",
    "label_metrics",
    "label_shares",
    "mean_metrics",
]

#: Disparity error (pixels) up to which a query disparity counts as correct (KITTI's 3 px rule).
DEFAULT_THRESHOLD_PX = 3.0

#: The figures computed per label image; :func:`label_metrics` also reports them for Stage 2 alone.
_LABEL_FIGURES = (
    "accuracy",
    "coverage",
    "positive_precision",
    "negative_precision",
    "bad_recall",
    "positive_share",
    "negative_share",
)


def _valid(disparity: NDArray[np.floating]) -> NDArray[np.bool_]:
    with np.errstate(invalid="ignore"):
        return np.isfinite(disparity) & (disparity > 0)


def _ratio(numerator: int, denominator: int) -> float:
    return float(numerator) / float(denominator) if denominator else math.nan


def _as_labels(labels: ArrayLike, shape: tuple[int, ...], name: str) -> NDArray[np.uint8]:
    array = np.asarray(labels)
    if array.shape != shape:
        raise ValueError(f"{name} has shape {array.shape}, the query disparity {shape}")
    if array.size and (int(array.min()) < UNKNOWN or int(array.max()) > NEGATIVE):
        raise ValueError(f"{name} holds codes outside {UNKNOWN}, {POSITIVE}, {NEGATIVE}")
    return array.astype(np.uint8, copy=False)


def ground_truth_labels(
    disparity: ArrayLike, gt_disparity: ArrayLike, *, threshold: float = DEFAULT_THRESHOLD_PX
) -> NDArray[np.uint8]:
    """Return the ground-truth label image of a query disparity map.

    Args:
        disparity: HxW query disparity, pixels (NaN, inf or <= 0 invalid).
        gt_disparity: HxW ground-truth disparity, pixels (NaN or <= 0 = none).
        threshold: largest ``|d - d_gt|`` (pixels) of a correct disparity.

    Returns:
        HxW uint8: POSITIVE where both exist and ``|d - d_gt| <= threshold``,
        NEGATIVE where both exist and the error is larger, UNKNOWN elsewhere.

    Raises:
        ValueError: if the two maps differ in shape or the threshold is not positive.
    """
    d = np.asarray(disparity, dtype=np.float64)
    gt = np.asarray(gt_disparity, dtype=np.float64)
    if d.shape != gt.shape or d.ndim != 2:
        raise ValueError(f"query disparity {d.shape} and ground truth {gt.shape} must be HxW of one shape")
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0 pixels, got {threshold}")
    evaluable = _valid(d) & _valid(gt)
    out = np.full(d.shape, UNKNOWN, dtype=np.uint8)
    correct = np.zeros(d.shape, dtype=bool)
    correct[evaluable] = np.abs(d[evaluable] - gt[evaluable]) <= threshold
    out[evaluable & correct] = POSITIVE
    out[evaluable & ~correct] = NEGATIVE
    return out


def _figures(labels: NDArray[np.uint8], gt_labels: NDArray[np.uint8]) -> dict[str, float]:
    evaluable = gt_labels != UNKNOWN
    correct = gt_labels == POSITIVE
    bad = gt_labels == NEGATIVE
    ours_pos = (labels == POSITIVE) & evaluable
    ours_neg = (labels == NEGATIVE) & evaluable
    n_eval = int(evaluable.sum())
    n_pos, n_neg = int(ours_pos.sum()), int(ours_neg.sum())
    n_true_pos = int((ours_pos & correct).sum())
    n_true_neg = int((ours_neg & bad).sum())
    return {
        "accuracy": _ratio(n_true_pos + n_true_neg, n_pos + n_neg),
        "coverage": _ratio(n_pos + n_neg, n_eval),
        "positive_precision": _ratio(n_true_pos, n_pos),
        "negative_precision": _ratio(n_true_neg, n_neg),
        "bad_recall": _ratio(n_true_neg, int(bad.sum())),
        "positive_share": _ratio(n_pos, n_eval),
        "negative_share": _ratio(n_neg, n_eval),
    }


def label_shares(labels: ArrayLike, disparity: ArrayLike) -> dict[str, float]:
    """Return the label figures that need no ground truth (keys in the module docstring).

    Args:
        labels: HxW label image (0 unknown, 1 positive, 2 negative).
        disparity: HxW query disparity, pixels (NaN, inf or <= 0 invalid).

    Raises:
        ValueError: if the shapes differ or the labels hold other codes.
    """
    d = np.asarray(disparity, dtype=np.float64)
    ours = _as_labels(labels, d.shape, "labels")
    valid = _valid(d)
    n_valid = int(valid.sum())
    return {
        "query_valid_share": _ratio(n_valid, d.size),
        "label_positive_share": _ratio(int((valid & (ours == POSITIVE)).sum()), n_valid),
        "label_negative_share": _ratio(int((valid & (ours == NEGATIVE)).sum()), n_valid),
        "label_unknown_share": _ratio(int((valid & (ours == UNKNOWN)).sum()), n_valid),
    }


def label_metrics(
    labels: ArrayLike,
    disparity: ArrayLike,
    gt_disparity: ArrayLike,
    *,
    stage2_labels: ArrayLike | None = None,
    threshold: float = DEFAULT_THRESHOLD_PX,
) -> dict[str, float]:
    """Return the quality figures of one label image against ground truth (keys in the module docstring).

    Args:
        labels: HxW final labels (0 unknown, 1 positive, 2 negative).
        disparity: HxW query disparity the labels are for, pixels.
        gt_disparity: HxW ground-truth disparity, pixels (NaN or <= 0 = none).
        stage2_labels: HxW labels after Stage 2 alone; when given, the
            ``stage2_*`` figures are added.
        threshold: largest ``|d - d_gt|`` (pixels) of a correct disparity.

    Returns:
        Figure name -> value; shares in [0, 1], NaN where undefined.

    Raises:
        ValueError: if the shapes differ or the labels hold other codes.
    """
    gt_labels = ground_truth_labels(disparity, gt_disparity, threshold=threshold)
    ours = _as_labels(labels, gt_labels.shape, "labels")
    result = _figures(ours, gt_labels)
    n_eval = int((gt_labels != UNKNOWN).sum())
    result["query_bad_rate"] = _ratio(int((gt_labels == NEGATIVE).sum()), n_eval)
    result["evaluable_pixels"] = float(n_eval)
    if stage2_labels is not None:
        stage2 = _figures(_as_labels(stage2_labels, gt_labels.shape, "stage2_labels"), gt_labels)
        result.update({f"stage2_{name}": value for name, value in stage2.items()})
    result.update(label_shares(ours, disparity))
    return result


def mean_metrics(frames: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Average per-frame figure dictionaries key by key.

    Each key's result is the plain mean over frames of the per-frame values
    (every frame weighs the same, whatever its number of pixels), skipping
    frames where the value is NaN or the key is absent; NaN when no frame has
    a value. Keys appear in the order first seen.
    """
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for frame in frames:
        for key, value in frame.items():
            sums.setdefault(key, 0.0)
            counts.setdefault(key, 0)
            if value is not None and math.isfinite(value):
                sums[key] += float(value)
                counts[key] += 1
    return {key: (sums[key] / counts[key] if counts[key] else math.nan) for key in sums}
