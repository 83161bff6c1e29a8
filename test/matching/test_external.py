"""The external (pass-through) query algorithm."""

from __future__ import annotations

import numpy as np
import pytest

from selfcontra_ros.matching.base import MatcherError, MatcherParams, make_matcher
from selfcontra_ros.matching.external import ExternalMatcher, normalize_disparity

IMAGES = (np.zeros((4, 5), np.uint8), np.zeros((4, 5), np.uint8))


def test_passes_disparity_through_with_invalid_as_nan() -> None:
    matcher = make_matcher(MatcherParams(algorithm="external"))
    assert isinstance(matcher, ExternalMatcher)
    given = np.arange(20, dtype=np.float64).reshape(4, 5) - 2.0  # -2 .. 17
    given[3, 4] = np.inf
    right = np.full((4, 5), 3, dtype=np.uint16)
    matcher.provide(given, right)
    pair = matcher.compute(*IMAGES)
    assert pair.left.dtype == np.float32 and pair.right is not None and pair.right.dtype == np.float32
    invalid = ~(np.isfinite(given) & (given > 0))
    assert np.array_equal(np.isnan(pair.left), invalid)
    np.testing.assert_array_equal(pair.left[~invalid], given[~invalid])
    np.testing.assert_array_equal(pair.right, 3.0)


def test_map_is_used_once_and_copied() -> None:
    matcher = ExternalMatcher()
    given = np.full((4, 5), 2.0, np.float32)
    matcher.provide(given)
    given[:] = 9.0  # the caller reusing its buffer must not change what was handed in
    pair = matcher.compute(*IMAGES, with_right=True)
    assert pair.right is None
    np.testing.assert_array_equal(pair.left, 2.0)
    with pytest.raises(MatcherError, match="no disparity was provided"):
        matcher.compute(*IMAGES)


def test_shape_is_validated() -> None:
    matcher = ExternalMatcher()
    matcher.provide(np.ones((4, 6), np.float32))
    with pytest.raises(MatcherError, match=r"shape \(4, 6\)"):
        matcher.compute(*IMAGES)
    with pytest.raises(MatcherError, match="right disparity"):
        matcher.provide(np.ones((4, 5)), np.ones((5, 4)))
    with pytest.raises(MatcherError, match="2-D"):
        normalize_disparity(np.ones((4, 5, 1)))
    with pytest.raises(MatcherError, match="2-D real"):
        normalize_disparity(np.array([["a"]]))
