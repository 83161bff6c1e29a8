"""Sparsification curves, AUSC and the optimal AUSC against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from selfcontra_ros.evaluation.sparsification import optimal_ausc, sparsification


def test_optimal_ausc_matches_the_integral_of_the_optimal_curve() -> None:
    for eps in (0.05, 0.2, 0.6):
        density = np.linspace(1e-6, 1.0, 200001)
        curve = np.maximum(0.0, 1.0 - (1.0 - eps) / density)
        assert optimal_ausc(eps) == pytest.approx(np.trapezoid(curve, density), abs=1e-5)
    assert optimal_ausc(0.0) == 0.0


def test_perfect_confidence_reaches_the_optimum_up_to_the_step_grid() -> None:
    n, bad = 100000, 20000
    correct = np.arange(n) >= bad
    confidence = np.arange(n, dtype=float)  # every correct pixel above every bad one
    result = sparsification(confidence, correct)
    assert result.bad_rate_all == pytest.approx(0.2)
    assert result.bad_rate[-1] == 0.0
    assert result.ratio == pytest.approx(1.0, abs=0.02)
    assert result.density[0] == 1.0 and len(result.density) == 20


def test_uninformative_and_inverted_confidence() -> None:
    rng = np.random.default_rng(0)
    correct = rng.random(200000) > 0.1
    random = sparsification(rng.random(correct.size), correct)
    assert random.ausc == pytest.approx(random.bad_rate_all, rel=0.05)
    inverted = sparsification(np.where(correct, 0.0, 1.0) + rng.random(correct.size) * 1e-3, correct)
    assert inverted.ausc > 2 * random.ausc


def test_tied_pixels_are_removed_or_kept_together() -> None:
    # 10 pixels: 6 tied at confidence 1 (2 bad), 4 at confidence 0 (all correct).
    confidence = np.array([1, 1, 1, 1, 1, 1, 0, 0, 0, 0], dtype=float)
    correct = np.array([1, 1, 1, 1, 0, 0, 1, 1, 1, 1], dtype=bool)
    result = sparsification(confidence, correct)
    np.testing.assert_allclose(result.density, [1.0, 0.6])
    np.testing.assert_allclose(result.bad_rate, [0.2, 2 / 6])
    # Trapezoid on [0.6, 1] plus the constant extension on [0, 0.6].
    assert result.ausc == pytest.approx(0.4 * (0.2 + 2 / 6) / 2 + 0.6 * 2 / 6)
    all_tied = sparsification(np.ones(10), correct)
    assert all_tied.ausc == pytest.approx(all_tied.bad_rate_all)


def test_empty_and_invalid_input() -> None:
    assert math.isnan(sparsification(np.zeros(0), np.zeros(0, bool)).ausc)
    assert math.isnan(sparsification(np.ones(5), np.ones(5, bool)).ratio)
    with pytest.raises(ValueError):
        sparsification(np.array([np.nan]), np.array([True]))
    with pytest.raises(ValueError):
        sparsification(np.ones(3), np.ones(4, bool))
