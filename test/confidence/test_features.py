"""Each confidence measure on hand-made cost curves and disparity maps with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.features import (
    FeatureContext,
    FeatureInput,
    Measure,
    compute_features,
    feature_names,
    lrd_confidence,
    make_measure,
    register,
)
from selfcontra_ros.errors import SelfContraError

EPS = constants.COST_EPS


def curve_input(curves: list[list[float]], disparity: list[float] | None = None) -> FeatureContext:
    """A 1xN image whose pixels carry the given cost curves (cost_scale 1), disparity = argmin unless given."""
    costs = np.asarray(curves, dtype=np.float32)[None, :, :]
    n = costs.shape[1]
    d = np.asarray(disparity if disparity is not None else np.argmin(costs[0], axis=1), dtype=np.float32)
    # Disparity 0 is "no depth"; the tests use curves whose winner is not at index 0 unless they shift it.
    data = FeatureInput(
        left=np.zeros((1, n), np.uint8),
        right=np.zeros((1, n), np.uint8),
        disparity=d[None, :],
        disparity_right=None,
        costs=costs,
        cost_scale=1.0,
    )
    return FeatureContext(data)


def value(name: str, ctx: FeatureContext, **kwargs: int) -> np.ndarray:
    return make_measure(name, kwargs).compute(ctx)


CURVE = [5.0, 1.0, 4.0, 2.0, 6.0]  # minimum 1 at d=1; second local minimum 2 at d=3; second smallest 2


def test_cost_curve_measures_on_hand_made_curve() -> None:
    ctx = curve_input([CURVE])
    c = np.asarray(CURVE)
    assert value("matching_score", ctx)[0] == pytest.approx(-1.0)
    assert value("peak_ratio", ctx)[0] == pytest.approx((2 + EPS) / (1 + EPS))
    assert value("naive_peak_ratio", ctx)[0] == pytest.approx((2 + EPS) / (1 + EPS))
    assert value("maximum_margin", ctx)[0] == pytest.approx(1.0)
    assert value("winner_margin", ctx)[0] == pytest.approx(1.0 / (18.0 + EPS))
    mlm = math.exp(-1 / (2 * constants.MLM_SIGMA**2)) / np.exp(-c / (2 * constants.MLM_SIGMA**2)).sum()
    assert value("maximum_likelihood", ctx)[0] == pytest.approx(mlm, rel=1e-5)
    aml = 1.0 / np.exp(-((c - 1) ** 2) / (2 * constants.AML_SIGMA**2)).sum()
    assert value("attainable_maximum_likelihood", ctx)[0] == pytest.approx(aml, rel=1e-5)
    per = np.exp(-((c - 1) ** 2) / constants.PER_SIGMA**2).sum() - 1.0
    assert value("perturbation", ctx)[0] == pytest.approx(per, abs=1e-6)
    p = np.exp(-c / constants.NEM_TEMPERATURE) / np.exp(-c / constants.NEM_TEMPERATURE).sum()
    nem = float(np.sum(p * np.log(np.maximum(p, 1e-300))))
    assert value("negative_entropy", ctx)[0] == pytest.approx(nem, abs=1e-5)
    assert value("curvature", ctx)[0] == pytest.approx(5 + 4 - 2 * 1)
    assert value("disparity_ambiguity", ctx)[0] == pytest.approx(2.0)


def test_naive_and_local_second_minimum_differ() -> None:
    # Minimum 1 at d=2 with a neighbour 1.5 (naive second) and a distant local minimum 3 at d=5.
    ctx = curve_input([[9, 6, 1, 1.5, 7, 3, 8]])
    assert value("naive_peak_ratio", ctx)[0] == pytest.approx((1.5 + EPS) / (1 + EPS))
    assert value("peak_ratio", ctx)[0] == pytest.approx((3 + EPS) / (1 + EPS))
    assert value("maximum_margin", ctx)[0] == pytest.approx(0.5)
    assert value("disparity_ambiguity", ctx)[0] == pytest.approx(3.0)


def test_unique_minimum_and_flat_curve() -> None:
    ctx = curve_input([[9, 1, 2, 3, 4], [2, 2, 2, 2, 2]], disparity=[1, 3])
    # No second local minimum: c2m is the curve maximum, ambiguity 0.
    assert value("peak_ratio", ctx)[0] == pytest.approx((9 + EPS) / (1 + EPS))
    assert value("disparity_ambiguity", ctx)[0] == 0.0
    # A flat curve: entropy ln D, likelihood 1/D, margin 0.
    assert value("negative_entropy", ctx)[1] == pytest.approx(-math.log(5), abs=1e-5)
    assert value("maximum_likelihood", ctx)[1] == pytest.approx(0.2)
    assert value("maximum_margin", ctx)[1] == 0.0
    assert value("perturbation", ctx)[1] == pytest.approx(4.0)


def test_curvature_at_range_end_counts_one_neighbour_twice() -> None:
    ctx = curve_input([[5, 3, 7, 1]], disparity=[3])
    assert value("curvature", ctx)[0] == pytest.approx(2 * (7 - 1))


def test_matching_score_reads_the_query_disparity_not_the_winner() -> None:
    ctx = curve_input([CURVE], disparity=[3.2])  # rounds to 3, cost 2
    assert value("matching_score", ctx)[0] == pytest.approx(-2.0)
    assert value("maximum_margin", ctx)[0] == pytest.approx(1.0)  # still from the winner


def test_left_right_difference_uses_right_image_costs() -> None:
    # Pixel u=4 of a 1x6 image: winner d1=2 -> right pixel x=2, whose right curve is c_L(2 + k, k).
    depth, width = 4, 6
    costs = np.full((1, width, depth), 9.0, np.float32)
    costs[0, 4] = [6.0, 8.0, 1.0, 5.0]  # c1 = 1, c2 = 5
    costs[0, 2, 0] = 4.0  # c_R(2, 0)
    costs[0, 3, 1] = 0.5  # c_R(2, 1): the right minimum (c_R(2, 2) is the winner's own cost 1)
    costs[0, 5, 3] = 7.0  # c_R(2, 3)
    d = np.full((1, width), np.nan, np.float32)
    d[0, 4] = 2.0
    data = FeatureInput(np.zeros((1, width)), np.zeros((1, width)), d, None, costs, 1.0)
    ctx = FeatureContext(data)
    assert ctx.count == 1
    assert value("left_right_difference", ctx)[0] == pytest.approx((5 - 1) / (abs(1 - 0.5) + EPS))


def test_left_right_consistency_and_lrd_baseline() -> None:
    d_left = np.full((3, 20), 5.0, np.float32)
    d_right = np.full((3, 20), 5.0, np.float32)
    d_left[1, 12] = 8.0  # points at right x=4 whose disparity is 5
    d_right[2, 5] = np.nan  # left (2, 10) points at a missing right disparity
    d_left[0, 2] = 4.0  # points outside the right image
    data = FeatureInput(np.zeros((3, 20)), np.zeros((3, 20)), d_left, d_right, np.zeros((3, 20, 16), np.float32), 1.0)
    ctx = FeatureContext(data)
    lrc = np.full((3, 20), np.nan)
    lrc[ctx.rows, ctx.cols] = value("left_right_consistency", ctx)
    assert lrc[1, 12] == pytest.approx(3.0)
    assert lrc[2, 10] == constants.LRC_MISSING_PX
    assert lrc[0, 2] == constants.LRC_MISSING_PX
    assert lrc[1, 15] == 0.0
    np.testing.assert_array_equal(lrd_confidence(ctx), -value("left_right_consistency", ctx))


def map_context(
    disparity: np.ndarray, left: np.ndarray | None = None, right: np.ndarray | None = None
) -> FeatureContext:
    h, w = disparity.shape
    left = np.zeros((h, w), np.float32) if left is None else left
    right = np.zeros((h, w), np.float32) if right is None else right
    costs = np.zeros((h, w, 64), np.float32)
    return FeatureContext(FeatureInput(left, right, disparity.astype(np.float32), None, costs, 1.0))


def as_image(ctx: FeatureContext, values: np.ndarray) -> np.ndarray:
    out = np.full(ctx.shape, np.nan)
    out[ctx.rows, ctx.cols] = values
    return out


def test_disparity_variance_ignores_invalid_pixels() -> None:
    d = np.full((9, 9), 10.0)
    d[2, 2] = np.nan
    d[4, 6] = 13.0
    ctx = map_context(d)
    var = as_image(ctx, value("disparity_variance", ctx, window=3))
    assert np.isnan(var[2, 2])
    assert var[1, 1] == pytest.approx(0.0, abs=1e-5)  # window holds the NaN pixel, which is skipped
    window = d[3:6, 5:8].ravel()
    assert var[4, 6] == pytest.approx(np.var(window), rel=1e-4)
    assert var[4, 5] == pytest.approx(np.var(d[3:6, 4:7]), rel=1e-4)


def test_median_deviation_of_an_outlier() -> None:
    d = np.full((11, 11), 20.0)
    d[5, 5] = 31.0
    ctx = map_context(d)
    mdd = as_image(ctx, value("median_deviation", ctx, window=5))
    assert mdd[5, 5] == pytest.approx(11.0)
    assert mdd[5, 6] == pytest.approx(0.0)


def test_distance_to_discontinuity_and_border() -> None:
    d = np.full((15, 30), 10.0)
    d[:, 20:] = 30.0  # step between columns 19 and 20
    ctx = map_context(d)
    dds = as_image(ctx, value("distance_to_discontinuity", ctx))
    assert dds[7, 19] == 0.0 and dds[7, 20] == 0.0
    assert dds[7, 14] == pytest.approx(5.0, abs=0.01)
    assert dds[7, 26] == pytest.approx(6.0, abs=0.01)
    db = as_image(ctx, value("distance_to_border", ctx))
    assert db[7, 14] == 7.0 and db[2, 28] == 1.0 and db[0, 10] == 0.0


def test_disparity_entropy() -> None:
    d = np.full((9, 9), 10.0)
    d[:, 5:] = 20.0
    ctx = map_context(d)
    de = as_image(ctx, value("disparity_entropy", ctx, window=3))
    assert de[4, 1] == pytest.approx(0.0, abs=1e-6)
    # Window of (4, 5) spans columns 4..6: one column of 10, two of 20.
    q = np.array([1 / 3, 2 / 3])
    assert de[4, 5] == pytest.approx(-np.sum(q * np.log(q)), rel=1e-4)


def test_image_gradients() -> None:
    u, v = np.meshgrid(np.arange(20, dtype=np.float32), np.arange(12, dtype=np.float32))
    ctx = map_context(np.full((12, 20), 5.0), left=3 * u + 4 * v)
    grad = as_image(ctx, value("gradient_magnitude", ctx, window=3))
    assert grad[6, 10] == pytest.approx(5.0, rel=1e-5)
    hgr = as_image(ctx, value("horizontal_gradient", ctx, window=5))
    assert hgr[6, 10] == pytest.approx(3.0, rel=1e-5)


def test_zsad_zero_for_a_true_match_with_brightness_offset() -> None:
    rng = np.random.default_rng(0)
    right = rng.uniform(0, 255, (20, 40)).astype(np.float32)
    left = np.zeros_like(right)
    left[:, 6:] = right[:, :-6] + 17.0  # left (u) = right (u - 6) + offset
    d = np.full((20, 40), 6.0)
    ctx = map_context(d, left=left, right=right)
    zsad = as_image(ctx, value("zsad", ctx, window=5))
    assert np.max(zsad[4:-4, 12:-4]) < 1e-3
    wrong = map_context(np.full((20, 40), 3.0), left=left, right=right)
    assert np.min(as_image(wrong, value("zsad", wrong, window=5))[4:-4, 12:-4]) > 5.0


def test_sgm_energy_counts_costs_and_steps() -> None:
    d = np.full((7, 7), 10.0)
    d[:, 4:] = 11.0  # a 1 px step between columns 3 and 4
    ctx = map_context(d)
    energy = as_image(ctx, value("sgm_energy", ctx, window=3))
    assert energy[3, 1] == pytest.approx(0.0)
    # Window of (3, 3): columns 2..4; each of the 3 rows has two pixels touching the step (P1 each).
    assert energy[3, 3] == pytest.approx(6 * constants.SGM_ENERGY_P1 / 9)


def test_feature_sets_have_published_dimensions_and_only_valid_pixels() -> None:
    assert len(feature_names("ensemble")) == 23
    assert len(feature_names("gcp")) == 8
    assert len(feature_names("park")) == 22
    rng = np.random.default_rng(1)
    h, w, depth = 24, 48, 16
    d = rng.uniform(1, 15, (h, w)).astype(np.float32)
    d[::3, ::5] = np.nan
    data = FeatureInput(
        rng.integers(0, 255, (h, w)).astype(np.uint8),
        rng.integers(0, 255, (h, w)).astype(np.uint8),
        d,
        d.copy(),
        rng.integers(0, 600, (h, w, depth)).astype(np.uint16),
        600.0,
    )
    for name in ("ensemble", "gcp", "park"):
        features, _ = compute_features(name, data)
        assert features.shape == (int(np.isfinite(d).sum()), len(feature_names(name)))
        assert np.all(np.isfinite(features))


def test_registry_adds_a_measure_by_one_class_and_refuses_duplicates() -> None:
    @register
    class Constant(Measure):
        name = "test_constant_measure"

        def compute(self, ctx: FeatureContext) -> np.ndarray:
            return np.full(ctx.count, 7.0, np.float32)

    ctx = curve_input([CURVE])
    assert value("test_constant_measure", ctx)[0] == 7.0
    with pytest.raises(SelfContraError):
        register(Constant)
    with pytest.raises(SelfContraError):
        make_measure("no_such_measure")
    with pytest.raises(SelfContraError):
        make_measure("disparity_variance", {"window": 4})


def test_one_cost_pass_per_feature_set_and_census_costs_equal_their_volume(monkeypatch: pytest.MonkeyPatch) -> None:
    """A feature set reads its cost curves in one pass; a reused context adds one; census costs need no volume."""
    from dataclasses import replace

    from selfcontra_ros.confidence import kernels
    from selfcontra_ros.matching.census import windowed_census_costs

    rng = np.random.default_rng(2)
    h, w, depth = 20, 40, 12
    left = rng.integers(0, 255, (h, w)).astype(np.uint8)
    right = np.roll(left, -3, axis=1)
    d = rng.uniform(1, 11, (h, w)).astype(np.float32)
    d[::4, ::3] = np.nan
    d[7] = np.nan  # a row without a valid pixel
    census = windowed_census_costs(left, right, depth, 2, min_disparity=0)
    lazy = FeatureInput(left, right, d, d.copy(), census, 1550.0)
    stored = replace(lazy, costs=census.volume())
    passes: list[kernels.CurveRequest] = []
    real = kernels.curve_statistics

    def counted(*args: object, **kwargs: object) -> kernels.CurveStatistics:
        passes.append(kwargs["request"])  # type: ignore[arg-type]
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(kernels, "curve_statistics", counted)
    for name in ("gcp", "park", "ensemble"):
        passes.clear()
        expected, _ = compute_features(name, stored)
        assert len(passes) == 1, name
        got, ctx = compute_features(name, lazy)
        np.testing.assert_array_equal(got, expected)
        # The same context for another set: one more pass, for what the first did not compute.
        passes.clear()
        other = "ensemble" if name == "gcp" else "gcp"
        again, _ = compute_features(other, ctx)
        assert len(passes) <= 1
        np.testing.assert_array_equal(again, compute_features(other, stored)[0])
