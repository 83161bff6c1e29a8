"""Census transform, Hamming cost volume and census SGM against direct references."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from selfcontra_ros.matching.base import MatcherError, MatcherParams, make_matcher
from selfcontra_ros.matching.census import (
    CensusSGMMatcher,
    aggregate_sgm,
    box_cost_volume,
    census_bits,
    census_cost_volume,
    census_transform,
    census_window_cost_volume,
    hamming,
    popcount,
    right_cost_volume,
)


def test_census_transform_matches_a_direct_loop() -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 6, (6, 7)).astype(np.uint8)  # few levels: many ties (not darker)
    window = (3, 5)
    census = census_transform(image, window)
    padded = np.pad(image, ((1, 1), (2, 2)), mode="edge")
    for v, u in itertools.product(range(6), range(7)):
        bits = [int(padded[v + dy, u + dx] < image[v, u]) for dy in range(3) for dx in range(5) if (dy, dx) != (1, 2)]
        assert int(census[v, u]) == sum(b << k for k, b in enumerate(bits))
    assert census_bits(window) == 14


def test_hamming_counts_differing_bits() -> None:
    a = np.array([0, 0b1011, 2**63], dtype=np.uint64)
    b = np.array([0, 0b0110, 0], dtype=np.uint64)
    np.testing.assert_array_equal(hamming(a, b), [0, 3, 1])


def test_popcount_without_numpy_bitwise_count(monkeypatch: pytest.MonkeyPatch) -> None:
    """numpy < 2.0 has no ``bitwise_count`` (``setup.py`` allows numpy >= 1.24): the byte table gives the same."""
    rng = np.random.default_rng(4)
    x = rng.integers(0, 2**63, (5, 7), dtype=np.uint64)[:, ::2]  # not contiguous
    expected = np.unpackbits(np.ascontiguousarray(x).view(np.uint8), axis=1).reshape(5, 4, 64).sum(axis=2)
    np.testing.assert_array_equal(popcount(x), expected)
    monkeypatch.delattr(np, "bitwise_count", raising=False)
    got = popcount(x)
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, expected)


def shifted_pair(disparity: int, shape: tuple[int, int] = (30, 60), seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    right = rng.integers(0, 256, shape).astype(np.uint8)
    left = np.empty_like(right)
    left[:, disparity:] = right[:, : shape[1] - disparity]
    left[:, :disparity] = right[:, :1]
    return left, right


def test_cost_volume_is_zero_at_the_true_disparity() -> None:
    left, right = shifted_pair(5)
    volume = census_cost_volume(left, right, 16)
    inner = volume[5:-5, 15:-5]
    assert np.all(inner[:, :, 5] == 0)
    # Elsewhere costs are large (a pixel darkest in its window has the all-zero string, so a few ties remain).
    assert np.mean(np.delete(inner, 5, axis=2)) > 20
    assert np.all(volume[:, :3, 4] == census_bits())  # u - d < 0: worst cost
    # With min_disparity 3, slice k holds disparity 3 + k.
    shifted = census_cost_volume(left, right, 8, min_disparity=3)
    np.testing.assert_array_equal(shifted[:, 10:, :], volume[:, 10:, 3:11])


def test_right_cost_volume_reindexes() -> None:
    volume = np.arange(2 * 6 * 3).reshape(2, 6, 3)
    right = right_cost_volume(volume)
    assert right[1, 2, 2] == volume[1, 4, 2]
    assert right[0, 5, 1] == volume.max()  # u + d = 6 leaves the image


def reference_sgm(cost: np.ndarray, p1: int, p2: int, directions: int) -> np.ndarray:
    """Hirschmüller's recursion pixel by pixel (slow; tiny volumes only)."""
    h, w, depth = cost.shape
    steps = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    if directions == 8:
        steps += [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    total = np.zeros(cost.shape, dtype=np.int64)
    for dv, du in steps:
        path = np.zeros(cost.shape, dtype=np.int64)
        rows = range(h) if dv >= 0 else range(h - 1, -1, -1)
        cols = range(w) if du >= 0 else range(w - 1, -1, -1)
        order = [(v, u) for v in rows for u in cols] if dv != 0 else [(v, u) for u in cols for v in rows]
        for v, u in order:
            pv, pu = v - dv, u - du
            if not (0 <= pv < h and 0 <= pu < w):
                path[v, u] = cost[v, u]
                continue
            prev = path[pv, pu]
            low = prev.min()
            for d in range(depth):
                options = [prev[d], low + p2]
                if d > 0:
                    options.append(prev[d - 1] + p1)
                if d < depth - 1:
                    options.append(prev[d + 1] + p1)
                path[v, u, d] = cost[v, u, d] + min(options) - low
        total += path
    return total


@pytest.mark.parametrize("directions", [4, 8])
def test_sgm_aggregation_matches_the_pixelwise_recursion(directions: int) -> None:
    rng = np.random.default_rng(2)
    cost = rng.integers(0, 30, (5, 6, 4))
    expected = reference_sgm(cost, 3, 11, directions)
    np.testing.assert_array_equal(aggregate_sgm(cost, p1=3, p2=11, directions=directions), expected)


def test_census_sgm_recovers_a_constant_shift_both_ways() -> None:
    left, right = shifted_pair(7, (40, 80))
    matcher = make_matcher(MatcherParams(algorithm="census_sgm", num_disparities=16))
    assert isinstance(matcher, CensusSGMMatcher)
    result = matcher.compute_costs(left, right)
    assert result.costs.shape == (40, 80, 16)
    assert np.all(result.pair.left[:, 20:] == 7)
    assert result.pair.right is not None
    # Ties at the border column (all-zero census strings) may pick another disparity there.
    assert np.all(result.pair.right[:, 1:60] == 7)
    only_left = matcher.compute(left, right, with_right=False)
    assert only_left.right is None


def reference_cost_volume(
    left: np.ndarray, right: np.ndarray, depth: int, lo: int, window: tuple[int, int]
) -> np.ndarray:
    """Hamming distances of census strings built bit by bit, pixel by pixel."""
    cl, cr = census_transform(left, window), census_transform(right, window)
    height, width = left.shape
    out = np.full((height, width, depth), census_bits(window), dtype=np.uint8)
    for v, u, k in itertools.product(range(height), range(width), range(depth)):
        x = u - (lo + k)
        if 0 <= x < width:
            out[v, u, k] = bin(int(cl[v, u]) ^ int(cr[v, x])).count("1")
    return out


@pytest.mark.parametrize(("depth", "lo"), [(6, 0), (5, -2), (4, 3), (3, 12)])
def test_cost_volume_kernel_matches_the_direct_definition(depth: int, lo: int) -> None:
    rng = np.random.default_rng(3)
    left = rng.integers(0, 8, (5, 10)).astype(np.uint8)
    right = rng.integers(0, 8, (5, 10)).astype(np.uint8)
    window = (3, 5)
    np.testing.assert_array_equal(
        census_cost_volume(left, right, depth, min_disparity=lo, window=window),
        reference_cost_volume(left, right, depth, lo, window),
    )


@pytest.mark.parametrize(("dtype", "radius"), [(np.uint8, 1), (np.uint8, 2), (np.uint16, 2), (np.int32, 1)])
def test_box_cost_volume_sums_the_edge_padded_window(dtype: type, radius: int) -> None:
    rng = np.random.default_rng(4)
    volume = rng.integers(0, 63, (4, 7, 3)).astype(dtype)
    padded = np.pad(volume.astype(np.int64), ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    side = 2 * radius + 1
    expected = np.zeros(volume.shape, np.int64)
    for v, u in itertools.product(range(4), range(7)):
        expected[v, u] = padded[v : v + side, u : u + side].sum(axis=(0, 1))
    got = box_cost_volume(volume, radius)
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, expected)


def test_box_cost_volume_refuses_sums_that_overflow() -> None:
    with pytest.raises(MatcherError, match="fit uint16"):
        box_cost_volume(np.full((3, 3, 2), 60000, np.uint16), 1)
    with pytest.raises(MatcherError, match="radius"):
        box_cost_volume(np.zeros((3, 3, 2), np.uint8), -1)


@pytest.mark.parametrize(("radius", "lo", "shape"), [(2, 0, (9, 14)), (1, -2, (5, 8)), (0, 3, (4, 9)), (2, 1, (2, 9))])
def test_windowed_census_costs_equal_the_box_sum_of_the_raw_volume(
    radius: int, lo: int, shape: tuple[int, int]
) -> None:
    rng = np.random.default_rng(5)
    left = rng.integers(0, 8, shape).astype(np.uint8)
    right = rng.integers(0, 8, shape).astype(np.uint8)
    window = (3, 5)
    raw = reference_cost_volume(left, right, 6, lo, window).astype(np.int64)
    padded = np.pad(raw, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    side = 2 * radius + 1
    expected = np.zeros(raw.shape, np.int64)
    for v, u in itertools.product(range(shape[0]), range(shape[1])):
        expected[v, u] = padded[v : v + side, u : u + side].sum(axis=(0, 1))
    got = census_window_cost_volume(left, right, 6, radius, min_disparity=lo, window=window)
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, expected)
