"""Label-quality metrics on hand-made images where every figure is known by counting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from selfcontra_ros.evaluation.metrics import ground_truth_labels, label_metrics, label_shares, mean_metrics
from selfcontra_ros.labels import NEGATIVE as N
from selfcontra_ros.labels import POSITIVE as P
from selfcontra_ros.labels import UNKNOWN as U

nan = math.nan

# Twelve pixels in one row. Column by column:
#   0-3  correct query depth (|d - gt| <= 3; column 3 exactly at the threshold)
#   4-7  bad query depth (error > 3)
#   8    no ground truth, 9 invalid query disparity (NaN), 10 zero disparity (invalid), 11 gt = 0 (none)
DISPARITY = np.array([[10.0, 20.0, 30.0, 33.0, 10.0, 20.0, 40.0, 5.0, 12.0, nan, 0.0, 7.0]], dtype=np.float32)
GT = np.array([[11.0, 18.0, 30.0, 30.0, 14.0, 10.0, 30.0, 8.5, nan, 20.0, 9.0, 0.0]], dtype=np.float32)
# Our labels: positives on 0, 1 (right) and 4 (wrong); negatives on 5, 6 (right) and 2 (wrong);
# 3 and 7 unknown; labels on the non-evaluable 8-11 must not count.
LABELS = np.array([[P, P, N, U, P, N, N, U, P, N, P, N]], dtype=np.uint8)
STAGE2 = np.array([[P, U, U, U, U, N, U, U, U, U, U, U]], dtype=np.uint8)


def test_ground_truth_labels() -> None:
    expected = np.array([[P, P, P, P, N, N, N, N, U, U, U, U]], dtype=np.uint8)
    np.testing.assert_array_equal(ground_truth_labels(DISPARITY, GT), expected)
    # A stricter threshold turns column 3 (error 3 px) and column 0 (1 px) apart.
    strict = ground_truth_labels(DISPARITY, GT, threshold=2.5)
    assert strict[0, 3] == N and strict[0, 0] == P


def test_label_metrics_by_counting() -> None:
    m = label_metrics(LABELS, DISPARITY, GT, stage2_labels=STAGE2)
    # 8 evaluable pixels (0-7); 4 correct, 4 bad. We labelled 6 of them: 4 right (0, 1, 5, 6), 2 wrong (2, 4).
    assert m["evaluable_pixels"] == 8
    assert m["accuracy"] == pytest.approx(4 / 6)
    assert m["coverage"] == pytest.approx(6 / 8)
    assert m["positive_precision"] == pytest.approx(2 / 3)
    assert m["negative_precision"] == pytest.approx(2 / 3)
    assert m["bad_recall"] == pytest.approx(2 / 4)
    assert m["positive_share"] == pytest.approx(3 / 8)
    assert m["negative_share"] == pytest.approx(3 / 8)
    assert m["query_bad_rate"] == pytest.approx(4 / 8)
    # Stage 2 alone: positive on 0 (right), negative on 5 (right).
    assert m["stage2_accuracy"] == 1.0
    assert m["stage2_coverage"] == pytest.approx(2 / 8)
    assert m["stage2_positive_precision"] == 1.0
    assert m["stage2_negative_precision"] == 1.0
    assert m["stage2_bad_recall"] == pytest.approx(1 / 4)
    assert m["stage2_positive_share"] == pytest.approx(1 / 8)
    assert m["stage2_negative_share"] == pytest.approx(1 / 8)
    # Without GT: valid query pixels are 0-8 and 11 (10 of 12); among them 4 positives (0, 1, 4, 8),
    # 4 negatives (2, 5, 6, 11) and 2 unknown (3, 7).
    assert m["query_valid_share"] == pytest.approx(10 / 12)
    assert m["label_positive_share"] == pytest.approx(4 / 10)
    assert m["label_negative_share"] == pytest.approx(4 / 10)
    assert m["label_unknown_share"] == pytest.approx(2 / 10)
    assert label_shares(LABELS, DISPARITY) == {k: m[k] for k in label_shares(LABELS, DISPARITY)}
    assert all(isinstance(v, float) for v in m.values())


def test_undefined_figures_are_nan() -> None:
    only_unknown = np.zeros_like(LABELS)
    m = label_metrics(only_unknown, DISPARITY, GT)
    assert m["coverage"] == 0.0
    for key in ("accuracy", "positive_precision", "negative_precision"):
        assert math.isnan(m[key]), key
    assert m["bad_recall"] == 0.0
    assert not any(key.startswith("stage2_") for key in m)
    no_gt = label_metrics(LABELS, DISPARITY, np.full_like(GT, nan))
    assert math.isnan(no_gt["coverage"]) and math.isnan(no_gt["query_bad_rate"])
    assert no_gt["evaluable_pixels"] == 0.0


def test_bad_input_is_rejected() -> None:
    with pytest.raises(ValueError, match="shape"):
        label_metrics(LABELS[:, :5], DISPARITY, GT)
    with pytest.raises(ValueError, match="codes"):
        label_metrics(LABELS + 1, DISPARITY, GT)
    with pytest.raises(ValueError, match="one shape"):
        ground_truth_labels(DISPARITY, GT[:, :3])
    with pytest.raises(ValueError, match="threshold"):
        ground_truth_labels(DISPARITY, GT, threshold=0.0)


def test_mean_metrics_skips_nan_and_missing() -> None:
    frames = [
        {"accuracy": 0.5, "coverage": 0.2, "positive_precision": nan},
        {"accuracy": 1.0, "coverage": 0.4, "positive_precision": 0.9},
        {"accuracy": 0.9, "coverage": 0.6},
    ]
    mean = mean_metrics(frames)
    assert list(mean) == ["accuracy", "coverage", "positive_precision"]
    assert mean["accuracy"] == pytest.approx(2.4 / 3)
    assert mean["coverage"] == pytest.approx(0.4)
    assert mean["positive_precision"] == pytest.approx(0.9)
    assert math.isnan(mean_metrics([{"x": nan}, {"x": nan}])["x"])
    assert mean_metrics([]) == {}
