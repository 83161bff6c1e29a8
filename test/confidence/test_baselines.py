"""OpenCV's WLS confidence baseline: what it is fed (16x fixed point, negative right map) and what it gives.

The expected values are worked out by hand from the map's documented formula
(:mod:`selfcontra_ros.confidence.baselines`): ``min(w_L, w_R)`` where the
left-right check passes, 0 where it fails, ``w = max(1 - 0.001 var, 0)`` over
the 16x fixed-point disparities in a ``(2r + 1)^2`` box.
"""

from __future__ import annotations

import importlib.metadata

import cv2
import numpy as np
import pytest

from selfcontra_ros.confidence.baselines import (
    WLSUnavailableError,
    left_fixed_point,
    right_fixed_point,
    wls_confidence,
    wls_confidence_map,
    wls_discontinuity_radius,
)
from selfcontra_ros.confidence.features import FeatureContext
from selfcontra_ros.confidence.inputs import query_feature_input
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.matching.base import MatcherParams, make_matcher

HEIGHT, WIDTH = 64, 96
RADIUS = 3  # a 7x7 box
BOX = (2 * RADIUS + 1) ** 2


def guide() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)


def plane(d: float) -> np.ndarray:
    return np.full((HEIGHT, WIDTH), d, np.float32)


def test_opencv_is_the_contrib_build_alone() -> None:
    assert hasattr(cv2, "ximgproc"), "cv2 lacks ximgproc: opencv-contrib-python-headless is not what cv2 imports"
    try:
        importlib.metadata.distribution("opencv-contrib-python-headless")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("cv2 does not come from pip's opencv-contrib-python-headless here (a system OpenCV)")
    for plain in ("opencv-python-headless", "opencv-python"):
        with pytest.raises(importlib.metadata.PackageNotFoundError):
            importlib.metadata.distribution(plain)  # beside the contrib build it overwrites cv2


def test_fixed_point_conventions() -> None:
    d = np.array([[np.nan, 2.5, -1.0, 0.0, 12.03]], np.float32)
    assert left_fixed_point(d, 0).tolist() == [[-16, 40, -16, -16, 192]]
    assert left_fixed_point(d, 2).tolist() == [[16, 40, 16, 16, 192]]
    # The right map is negative, as OpenCV's right matcher writes it; invalid = -16 (min + num).
    assert right_fixed_point(d, 0, 64).tolist() == [[-1024, -40, -1024, -1024, -192]]
    assert right_fixed_point(d, 0, 64).dtype == np.int16
    assert wls_discontinuity_radius(MatcherParams(block_size=5)) == 3
    assert wls_discontinuity_radius(MatcherParams(algorithm="bm", block_size=9)) == 3  # ceil(0.33 * 9)


def test_correct_disparity_is_confident_and_a_corrupted_patch_is_not() -> None:
    correct = plane(12.0)
    assert np.array_equal(wls_confidence_map(guide(), correct, correct, radius=RADIUS), np.ones((HEIGHT, WIDTH)))
    corrupted = correct.copy()
    corrupted[20:30, 40:50] = 30.0  # fails the left-right check against the uncorrupted right map
    confidence = wls_confidence_map(guide(), corrupted, correct, radius=RADIUS)
    assert np.all(confidence[20:30, 40:50] == 0.0)
    ring = np.zeros((HEIGHT, WIDTH), bool)
    ring[20 - RADIUS : 30 + RADIUS, 40 - RADIUS : 50 + RADIUS] = True
    ring[20:30, 40:50] = False
    assert confidence[ring].max() < 0.05  # the variance term: 18 px steps inside the box
    far = np.ones((HEIGHT, WIDTH), bool)
    far[20 - RADIUS : 30 + RADIUS, 40 - RADIUS : 50 + RADIUS] = False
    assert np.all(confidence[far] == 1.0)


def test_variance_term_on_a_slanted_plane() -> None:
    rows = np.arange(HEIGHT, dtype=np.float32)[:, None]
    slanted = np.broadcast_to(10.0 + 0.5 * rows, (HEIGHT, WIDTH)).astype(np.float32)
    confidence = wls_confidence_map(guide(), slanted, slanted, radius=RADIUS)
    # 8 (16ths) per row, 7 rows in the box: var = 64 * (7^2 - 1) / 12 = 256, w = 1 - 0.256.
    np.testing.assert_allclose(confidence[RADIUS:-RADIUS], 0.744, atol=1e-5)


def test_left_right_threshold_is_one_and_a_half_pixels() -> None:
    right = plane(12.0)
    left = right.copy()
    left[30, 50] = 13.25  # 4/16 px short of the threshold
    left[30, 70] = 13.5  # exactly 24/16: |16 d + right| < 24 fails
    confidence = wls_confidence_map(guide(), left, right, radius=RADIUS)
    error = 16 * 1.25
    expected = 1.0 - 0.001 * error**2 * (1.0 / BOX) * (1.0 - 1.0 / BOX)  # one outlier in the box
    assert confidence[30, 50] == pytest.approx(expected, abs=1e-5)
    assert confidence[30, 70] == 0.0


def test_on_a_synthetic_pair_wrong_disparities_score_lower() -> None:
    """The room (plain walls): SGBM is wrong on a fifth of its pixels there, and WLS sees most of them."""
    scene = make_scene("room", 3, 240, 96, frames=2)
    frame = scene.render(0)
    params = MatcherParams(num_disparities=64)
    inputs = query_feature_input(make_matcher(params), frame.left, frame.right)
    ctx = FeatureContext(inputs)
    confidence = wls_confidence(ctx, params)
    assert confidence.shape == (ctx.count,) and confidence.dtype == np.float32
    assert np.all((confidence >= 0) & (confidence <= 1))
    gt = frame.disparity[ctx.rows, ctx.cols]
    known = np.isfinite(gt)
    wrong = known & (np.abs(ctx.d - gt) > 3)
    right = known & (np.abs(ctx.d - gt) <= 1)
    assert wrong.sum() > 1000 and right.sum() > 5000
    assert confidence[right].mean() > confidence[wrong].mean() + 0.3  # measured 0.50 against 0.02


def test_bad_input_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    correct = plane(12.0)
    with pytest.raises(SelfContraError, match="share one HxW size"):
        wls_confidence_map(guide(), correct, correct[:, :-1])
    with pytest.raises(SelfContraError, match="must be uint8"):
        wls_confidence_map(guide().astype(np.float32), correct, correct)
    monkeypatch.delattr(cv2, "ximgproc")
    with pytest.raises(WLSUnavailableError, match="opencv-contrib-python-headless"):
        wls_confidence_map(guide(), correct, correct)
