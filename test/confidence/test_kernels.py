"""The compiled confidence kernels against slow, obviously correct references on small inputs."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from sklearn.ensemble import RandomForestClassifier

from selfcontra_ros.confidence import kernels
from selfcontra_ros.confidence.forest import fit_forest
from selfcontra_ros.matching.census import windowed_census_costs


def small_volume(dtype: type, depth: int, seed: int = 0, shape: tuple[int, int] = (5, 9)) -> np.ndarray:
    """Costs with few levels, so that curves have ties and flat valleys."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 6, (*shape, depth)).astype(dtype)


def pixels(shape: tuple[int, int], depth: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    valid = rng.random(shape) < 0.7
    rows, cols = np.nonzero(valid)
    return rows.astype(np.int64), cols.astype(np.int64), rng.integers(0, depth, rows.size).astype(np.int64)


def reference_statistics(curve: list[float], dq: int) -> dict[str, float]:
    """The curve statistics of the measures' notation, element by element."""
    depth = len(curve)
    d1 = min(range(depth), key=lambda k: (curve[k], k))
    ordered = sorted(curve)
    c2 = ordered[1] if depth > 1 else ordered[0]
    local = [
        k
        for k in range(depth)
        if k != d1 and (k == 0 or curve[k] < curve[k - 1]) and (k == depth - 1 or curve[k] <= curve[k + 1])
    ]
    d2m = min(local, key=lambda k: (curve[k], k)) if local else d1
    c2m = curve[d2m] if local else max(curve)
    below = curve[d1 - 1] if d1 > 0 else curve[min(d1 + 1, depth - 1)]
    above = curve[d1 + 1] if d1 < depth - 1 else below
    return {
        "d1": d1,
        "c1": curve[d1],
        "c2": c2,
        "c2m": c2m,
        "d2m": d2m,
        "cq": curve[dq],
        "total": sum(curve),
        "below": below,
        "above": above,
    }


#: Every statistic of a pass: the second local minimum, two exponential terms (one with its moment), right minimum.
FULL = kernels.CurveRequest(local=True, exp_terms=((0.7, 1, True), (2.5, 2, False)), right_minimum=True)


@pytest.mark.parametrize(("dtype", "depth"), [(np.uint16, 7), (np.uint8, 2), (np.float32, 6), (np.uint16, 1)])
def test_curve_statistics_match_the_definitions(dtype: type, depth: int) -> None:
    costs = small_volume(dtype, depth)
    rows, cols, dq = pixels(costs.shape[:2], depth)
    scale = 3.0
    stats = kernels.curve_statistics(costs, rows, cols, dq, scale, request=kernels.CurveRequest(local=True))
    got = {name: getattr(stats, name) for name in ("d1", "c1", "c2", "c2m", "d2m", "cq", "total", "below", "above")}
    for i, (r, u) in enumerate(zip(rows, cols, strict=True)):
        curve = [float(np.float32(c) / np.float32(scale)) for c in costs[r, u]]
        expected = reference_statistics(curve, int(dq[i]))
        for name, value in expected.items():
            assert got[name][i] == pytest.approx(value, rel=1e-6), (name, curve)
        assert stats.spread[i] == pytest.approx(float(costs[r, u].max()) - float(costs[r, u].min()))
    assert not stats.exp and stats.right_minimum is None


@pytest.mark.parametrize("lo", [2, 0, -1])
def test_right_minimum_reads_the_right_image_curve(lo: int) -> None:
    costs = small_volume(np.uint16, 5, seed=3, shape=(3, 12)).astype(np.uint16) + 1
    rows, cols, dq = pixels(costs.shape[:2], 5, seed=4)
    request = kernels.CurveRequest(right_minimum=True)
    stats = kernels.curve_statistics(costs, rows, cols, dq, 2.0, min_disparity=lo, request=request)
    assert stats.right_minimum is not None
    width = costs.shape[1]
    for i, (r, u) in enumerate(zip(rows, cols, strict=True)):
        x_right = u - (stats.d1[i] + lo)
        # c_R(x, k) = c_L(x + lo + k, k) wherever that left pixel exists; none left: the left minimum.
        values = [costs[r, x_right + lo + k, k] for k in range(5) if 0 <= x_right + lo + k < width]
        expected = min(values) / 2.0 if values else stats.c1[i]
        assert stats.right_minimum[i] == pytest.approx(expected)


@pytest.mark.parametrize(("dtype", "rate", "power"), [(np.uint8, 0.7, 1), (np.uint16, 2.5, 2), (np.float32, 1.3, 2)])
def test_exp_sums_match_direct_exponentials(dtype: type, rate: float, power: int) -> None:
    costs = small_volume(dtype, 8, seed=6)
    if dtype is np.float32:
        costs = costs + np.random.default_rng(7).random(costs.shape).astype(np.float32)
    rows, cols, dq = pixels(costs.shape[:2], 8, seed=8)
    scale = 4.0
    both = kernels.curve_statistics(
        costs, rows, cols, dq, scale, request=kernels.CurveRequest(exp_terms=((rate, power, True),))
    )
    alone = kernels.curve_statistics(
        costs, rows, cols, dq, scale, request=kernels.CurveRequest(exp_terms=((rate, power, False),))
    )
    s0, s1 = both.exp[(rate, power)]
    np.testing.assert_array_equal(alone.exp[(rate, power)][0], s0)
    assert alone.exp[(rate, power)][1] is None and s1 is not None
    for i, (r, u) in enumerate(zip(rows, cols, strict=True)):
        c = costs[r, u].astype(np.float64) / scale
        e = rate * (c - c.min()) ** power
        assert s0[i] == pytest.approx(np.exp(-e).sum(), rel=1e-6)
        assert s1[i] == pytest.approx((e * np.exp(-e)).sum(), rel=1e-6, abs=1e-12)


def test_curve_statistics_refuse_other_powers_and_unsorted_rows() -> None:
    costs = small_volume(np.uint8, 4)
    rows, cols, dq = pixels(costs.shape[:2], 4)
    with pytest.raises(ValueError, match="power must be 1 or 2"):
        kernels.curve_statistics(costs, rows, cols, dq, 1.0, request=kernels.CurveRequest(exp_terms=((1.0, 3, False),)))
    with pytest.raises(ValueError, match="sorted"):
        kernels.curve_statistics(costs, rows[::-1], cols[::-1], dq[::-1], 1.0)


def test_requests_merge_and_one_pass_equals_separate_passes() -> None:
    costs = small_volume(np.uint16, 9, seed=11, shape=(6, 14))
    rows, cols, dq = pixels(costs.shape[:2], 9, seed=12)
    merged = kernels.CurveRequest(local=True) | kernels.CurveRequest(exp_terms=((0.7, 1, False),))
    merged = merged | kernels.CurveRequest(exp_terms=((0.7, 1, True), (2.5, 2, False)), right_minimum=True)
    assert merged == FULL
    together = kernels.curve_statistics(costs, rows, cols, dq, 5.0, min_disparity=1, request=FULL)
    for part in (kernels.CurveRequest(local=True), kernels.CurveRequest(right_minimum=True)):
        alone = kernels.curve_statistics(costs, rows, cols, dq, 5.0, min_disparity=1, request=part)
        for name in ("d1", "c1", "c2", "cq", "below", "above", "spread", "c2m", "d2m", "total", "right_minimum"):
            if getattr(alone, name) is not None:
                np.testing.assert_array_equal(getattr(alone, name), getattr(together, name), err_msg=name)


@pytest.mark.parametrize(("radius", "lo", "shape"), [(2, 0, (9, 14)), (1, -2, (7, 10)), (0, 3, (4, 9)), (2, 1, (2, 9))])
def test_windowed_census_statistics_equal_those_of_the_stored_volume(
    radius: int, lo: int, shape: tuple[int, int]
) -> None:
    """Census costs summed and reduced row by row give exactly the statistics of the materialised volume."""
    rng = np.random.default_rng(13)
    left = rng.integers(0, 8, shape).astype(np.uint8)
    right = rng.integers(0, 8, shape).astype(np.uint8)
    costs = windowed_census_costs(left, right, 6, radius, min_disparity=lo, window=(3, 5))
    volume = costs.volume()
    # Some rows without any valid pixel: the census pass slides past them.
    valid = rng.random(shape) < 0.6
    valid[shape[0] // 2] = False
    rows, cols = np.nonzero(valid)
    dq = rng.integers(0, 6, rows.size)
    streamed = kernels.curve_statistics(costs, rows, cols, dq, 7.0, min_disparity=lo, request=FULL)
    stored = kernels.curve_statistics(volume, rows, cols, dq, 7.0, min_disparity=lo, request=FULL)
    for name in ("d1", "c1", "c2", "cq", "below", "above", "spread", "c2m", "d2m", "total", "right_minimum"):
        np.testing.assert_array_equal(getattr(streamed, name), getattr(stored, name), err_msg=name)
    assert streamed.exp.keys() == stored.exp.keys()
    for key, (s0, s1) in stored.exp.items():
        np.testing.assert_array_equal(streamed.exp[key][0], s0)
        assert (s1 is None) == (streamed.exp[key][1] is None)
        if s1 is not None:
            np.testing.assert_array_equal(streamed.exp[key][1], s1)


def test_curve_statistics_of_no_pixel() -> None:
    empty = np.zeros(0, np.int64)
    stats = kernels.curve_statistics(small_volume(np.uint16, 3), empty, empty, empty, 1.0, request=FULL)
    assert stats.d1.shape == (0,) and stats.right_minimum is not None and stats.right_minimum.shape == (0,)


@pytest.mark.parametrize("window", [3, 5])
def test_disparity_entropy_matches_a_window_histogram(window: int) -> None:
    rng = np.random.default_rng(9)
    bins = rng.integers(0, 4, (7, 11)).astype(np.int32)
    bins[:, :3] = 2  # constant region: entropy 0 there
    valid = rng.random(bins.shape) < 0.75
    got = kernels.disparity_entropy(bins, valid, window)
    r = window // 2
    height, width = bins.shape
    for v, u in itertools.product(range(height), range(width)):
        if not valid[v, u]:
            assert got[v, u] == 0.0
            continue
        window_bins = [
            bins[y, x]
            for y in range(max(v - r, 0), min(v + r + 1, height))
            for x in range(max(u - r, 0), min(u + r + 1, width))
            if valid[y, x]
        ]
        total = len(window_bins)
        expected = -sum(n / total * math.log(n / total) for n in (window_bins.count(b) for b in set(window_bins)))
        assert got[v, u] == pytest.approx(expected, abs=1e-6)


def reference_forest(model_arrays: dict[str, np.ndarray], x: np.ndarray) -> np.ndarray:
    """Walk every tree for every row, one node at a time."""
    offsets = model_arrays["tree_offsets"]
    out = []
    for row in x:
        votes = []
        for t in range(offsets.size - 1):
            root, node = int(offsets[t]), int(offsets[t])
            while model_arrays["children_left"][node] >= 0:
                go_left = float(row[model_arrays["feature"][node]]) <= model_arrays["threshold"][node]
                child = model_arrays["children_left"][node] if go_left else model_arrays["children_right"][node]
                node = root + int(child)
            votes.append(model_arrays["positive"][node])
        out.append(np.mean(votes))
    return np.asarray(out)


def test_forest_kernel_matches_scikit_learn_and_a_node_walk() -> None:
    rng = np.random.default_rng(10)
    x = rng.normal(size=(800, 4)).astype(np.float32)
    y = (x[:, 0] - 0.7 * x[:, 2] + 0.4 * rng.normal(size=800)) > 0
    small = {"n_estimators": 5, "max_depth": 7, "min_samples_leaf": 4}
    model = fit_forest(x, y, forest=small)
    reference = RandomForestClassifier(criterion="entropy", random_state=0, **small).fit(x, y.astype(np.int8))
    x_test = rng.normal(size=(700, 4)).astype(np.float32)
    # Rows exactly at split thresholds go left, as in scikit-learn's trees.
    inner = np.flatnonzero(model.children_left >= 0)[:50]
    x_test[np.arange(inner.size), model.feature[inner]] = model.threshold[inner].astype(np.float32)
    got = model.predict(x_test)
    np.testing.assert_array_equal(got, reference.predict_proba(x_test)[:, 1].astype(np.float32))
    arrays = {
        name: getattr(model, name)
        for name in ("tree_offsets", "children_left", "children_right", "feature", "threshold", "positive")
    }
    # NaN features (never produced by compute_features) fail every "<=" test and go right.
    x_test[600:610, 1] = np.nan
    np.testing.assert_allclose(model.predict(x_test), reference_forest(arrays, x_test), rtol=1e-6)


def test_forest_reads_row_and_column_major_features_alike() -> None:
    rng = np.random.default_rng(14)
    x = rng.normal(size=(600, 3)).astype(np.float32)
    y = (x[:, 1] + 0.3 * rng.normal(size=600)) > 0
    model = fit_forest(x, y, forest={"n_estimators": 4, "max_depth": 6, "min_samples_leaf": 3})
    x_test = rng.normal(size=(1000, 3)).astype(np.float32)
    expected = model.predict(np.ascontiguousarray(x_test))
    np.testing.assert_array_equal(model.predict(np.asfortranarray(x_test)), expected)
    # float64 rows are rounded to float32 first, as scikit-learn does.
    np.testing.assert_array_equal(model.predict(x_test.astype(np.float64)), expected)
