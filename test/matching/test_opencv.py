"""OpenCV query algorithms on synthetic pairs whose disparity is known by construction."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.matching.base import DisparityPair, Matcher, MatcherError, MatcherParams, make_matcher
from selfcontra_ros.matching.opencv import OpenCVMatcher, fixed_point_to_disparity

HEIGHT, WIDTH = 64, 200
NUM_DISP = 32


def _texture(rng: np.random.Generator, height: int, width: int) -> NDArray[np.uint8]:
    return rng.integers(0, 256, size=(height, width), dtype=np.uint8)


def _shifted_pair(disparity: int, seed: int = 0) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A fronto-parallel textured plane: left pixel u shows what the right image shows at u - disparity."""
    tex = _texture(np.random.default_rng(seed), HEIGHT, WIDTH + disparity)
    left = tex[:, :WIDTH].copy()
    right = tex[:, disparity : disparity + WIDTH].copy()
    assert np.array_equal(left[:, disparity:], right[:, : WIDTH - disparity])
    return left, right


@pytest.mark.parametrize("algorithm", ["sgbm", "bm"])
@pytest.mark.parametrize("rgb", [False, True])
def test_constant_shift_gives_that_disparity_left_and_right(algorithm: str, rgb: bool) -> None:
    d = 11
    left, right = _shifted_pair(d)
    if rgb:
        left, right = np.repeat(left[..., None], 3, axis=2), np.repeat(right[..., None], 3, axis=2)
    pair = make_matcher(MatcherParams(algorithm=algorithm, num_disparities=NUM_DISP, block_size=5)).compute(left, right)
    assert pair.left.dtype == np.float32 and pair.left.shape == (HEIGHT, WIDTH)
    assert pair.right is not None and pair.right.shape == (HEIGHT, WIDTH)
    margin = 4  # half a block plus one
    # Left disparity exists only where the whole search range stays inside the right image.
    inner_left = pair.left[margin:-margin, NUM_DISP + margin : -margin]
    inner_right = pair.right[margin:-margin, margin : -(NUM_DISP + margin)]
    for inner in (inner_left, inner_right):
        assert np.isfinite(inner).all()
        np.testing.assert_allclose(inner, d, atol=0.5)
    # OpenCV leaves the columns without a full search range invalid: NaN, not a number.
    assert np.isnan(pair.left[:, : NUM_DISP - 1]).all()
    assert np.isnan(pair.right[:, WIDTH - NUM_DISP + 1 :]).all()


def test_without_right_returns_none_and_same_left() -> None:
    left, right = _shifted_pair(7)
    matcher = make_matcher(MatcherParams(num_disparities=NUM_DISP))
    both = matcher.compute(left, right)
    only = matcher.compute(left, right, with_right=False)
    assert only.right is None
    np.testing.assert_array_equal(only.left, both.left)


def _pair_with_small_patch(
    background: int, patch: int, box: tuple[int, int, int, int]
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Background plane at one disparity with a small rectangle (y0, y1, x0, x1 in the left image) at another."""
    rng = np.random.default_rng(3)
    left = _texture(rng, HEIGHT, WIDTH)
    # right(u) = left(u + d(u)) with d the disparity of the surface visible there.
    right = np.zeros_like(left)
    right[:, : WIDTH - background] = left[:, background:]
    y0, y1, x0, x1 = box
    # Where the background copy of the patch would land, the right camera sees background the patch hides in
    # the left image: fresh texture, so that the patch matches at its own disparity only.
    right[y0:y1, x0 - background : x1 - background] = _texture(rng, y1 - y0, x1 - x0)
    right[y0:y1, x0 - patch : x1 - patch] = left[y0:y1, x0:x1]
    return left, right


def test_raw_sgbm_keeps_speckles_and_the_filter_is_configurable() -> None:
    box = (28, 38, 100, 110)  # 10x10 patch: a speckle for a 400-pixel window
    left, right = _pair_with_small_patch(background=8, patch=24, box=box)
    centre = (slice(31, 35), slice(103, 107))
    raw = make_matcher(MatcherParams(num_disparities=NUM_DISP)).compute(left, right, with_right=False).left
    np.testing.assert_allclose(raw[centre], 24, atol=0.5)
    np.testing.assert_allclose(raw[10:20, 60:80], 8, atol=0.5)
    filtered_params = MatcherParams(num_disparities=NUM_DISP, speckle_window_size=400, speckle_range=2)
    filtered = make_matcher(filtered_params).compute(left, right, with_right=False).left
    assert np.isnan(filtered[centre]).all()
    np.testing.assert_allclose(filtered[10:20, 60:80], 8, atol=0.5)


def test_default_sgbm_is_raw() -> None:
    matcher = OpenCVMatcher(MatcherParams())
    engine = matcher._engine(1)
    assert engine.getUniquenessRatio() == 0
    assert engine.getSpeckleWindowSize() == 0
    assert engine.getDisp12MaxDiff() == -1
    assert (engine.getP1(), engine.getP2()) == (8 * 25, 32 * 25)
    assert (matcher._engine(3).getP1(), matcher._engine(3).getP2()) == (8 * 3 * 25, 32 * 3 * 25)


def test_fixed_point_conversion() -> None:
    raw = np.array([[-16, 0, 16, 40, 2047 * 16]], dtype=np.int16)
    out = fixed_point_to_disparity(raw, min_disparity=0)
    assert np.isnan(out[0, 0]) and np.isnan(out[0, 1])  # invalid marker and zero disparity
    np.testing.assert_array_equal(out[0, 2:], [1.0, 2.5, 2047.0])
    # With min_disparity 2 the invalid marker is 16 and 1.0 px lies below the search range.
    assert np.isnan(fixed_point_to_disparity(np.array([[16, 32]], dtype=np.int16), 2)[0, 0])


def test_make_matcher_satisfies_protocol() -> None:
    for algorithm in ("sgbm", "bm", "external"):
        matcher = make_matcher(MatcherParams(algorithm=algorithm))
        assert isinstance(matcher, Matcher)
        assert matcher.params.algorithm == algorithm
    assert isinstance(make_matcher(), OpenCVMatcher)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"algorithm": "census"}, "algorithm"),
        ({"num_disparities": 100}, "multiple of 16"),
        ({"num_disparities": 0}, "multiple of 16"),
        ({"block_size": 4}, "block_size"),
        ({"algorithm": "bm", "block_size": 3}, "block_size"),
        ({"p1": 100, "p2": 50}, "p2"),
        ({"mode": "fast"}, "mode"),
        ({"disp12_max_diff": -2}, "disp12_max_diff"),
        ({"uniqueness_ratio": 101}, "uniqueness_ratio"),
        ({"block_size": 5.0}, "integer"),
        ({"speckle_range": True}, "integer"),
    ],
)
def test_params_validation_names_the_field(fields: dict[str, object], message: str) -> None:
    with pytest.raises(MatcherError, match=message):
        MatcherParams(**fields)  # type: ignore[arg-type]
    with pytest.raises(ValueError):  # MatcherError is also a ValueError
        MatcherParams(**fields)  # type: ignore[arg-type]


def test_bad_images_are_rejected() -> None:
    matcher = make_matcher()
    left, right = _shifted_pair(5)
    with pytest.raises(MatcherError, match="differ in shape"):
        matcher.compute(left, right[:, :-1])
    with pytest.raises(MatcherError, match="uint8"):
        matcher.compute(left.astype(np.float32), right)  # type: ignore[arg-type]
    with pytest.raises(MatcherError, match="grey or HxWx3"):
        matcher.compute(left[..., None], right[..., None])


def test_disparity_pair_default_right_is_none() -> None:
    assert DisparityPair(left=np.zeros((2, 2), np.float32)).right is None
