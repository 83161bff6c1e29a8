"""Sparsification curves of a confidence measure and their area (DESIGN section 8, paper section 4).

Given the pixels with ground truth, each with a confidence and a correct/bad
flag (``|d - d_gt| <= 3 px``), the curve removes the lowest-confidence pixels
first in steps of 5 % and records the bad-pixel rate of the pixels kept.
Pixels tied in confidence are removed or kept together: at each step the
threshold keeps every pixel whose confidence is at least the confidence of the
pixel at the nominal cut, so the kept share (the *density*) can exceed the
nominal one; the curve is recorded at the densities actually reached.

AUSC is the area under the bad-rate-versus-density curve on ``[0, 1]`` by the
trapezoid rule; below the smallest density reached the curve is taken as
constant (its value there). The optimal AUSC, reached by a confidence that
ranks every correct pixel above every bad one, is
``eps + (1 - eps) ln(1 - eps)`` for the bad-pixel rate ``eps`` of all
pixels; the paper's figure of merit is the ratio AUSC / optimal (>= 1, lower
is better; NaN when ``eps = 0``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DEFAULT_STEP", "Sparsification", "optimal_ausc", "sparsification"]

#: Share of pixels removed per step.
DEFAULT_STEP = 0.05


@dataclass
class Sparsification:
    """A sparsification curve and its figures.

    Attributes:
        density: kept share of the pixels at each point, decreasing from 1.
        bad_rate: bad-pixel rate of the kept pixels at each point.
        ausc: area under the curve on [0, 1] (trapezoid rule).
        optimal: optimal AUSC for this bad-pixel rate.
        ratio: ``ausc / optimal`` (NaN when ``optimal == 0``).
        bad_rate_all: bad-pixel rate of all pixels (``eps``).
        pixels: number of pixels evaluated.
    """

    density: NDArray[np.float64]
    bad_rate: NDArray[np.float64]
    ausc: float
    optimal: float
    ratio: float
    bad_rate_all: float
    pixels: int


def optimal_ausc(bad_rate: float) -> float:
    """``eps + (1 - eps) ln(1 - eps)``: the AUSC of a perfect confidence at bad-pixel rate ``eps`` in [0, 1]."""
    eps = float(bad_rate)
    if not 0.0 <= eps <= 1.0:
        raise ValueError(f"bad-pixel rate must lie in [0, 1], got {eps}")
    if eps == 1.0:
        return 1.0
    return eps + (1.0 - eps) * math.log1p(-eps)


def sparsification(confidence: ArrayLike, correct: ArrayLike, *, step: float = DEFAULT_STEP) -> Sparsification:
    """Sparsification curve of ``confidence`` over pixels flagged ``correct`` / bad.

    Args:
        confidence: (N,) confidence per pixel, larger = more trusted (finite).
        correct: (N,) bool, True where the disparity is correct.
        step: removed share per step (default 5 %).

    Returns:
        The curve and its figures; with ``N = 0`` every figure is NaN.

    Raises:
        ValueError: on mismatched shapes, non-finite confidences or a step outside (0, 1].
    """
    conf = np.asarray(confidence, dtype=np.float64).ravel()
    ok = np.asarray(correct, dtype=bool).ravel()
    if conf.shape != ok.shape:
        raise ValueError(f"confidence {conf.shape} and correct {ok.shape} differ in size")
    if not np.all(np.isfinite(conf)):
        raise ValueError("confidence values must be finite")
    if not 0.0 < step <= 1.0:
        raise ValueError(f"step must lie in (0, 1], got {step}")
    n = conf.size
    if n == 0:
        nan = math.nan
        return Sparsification(np.zeros(0), np.zeros(0), nan, nan, nan, nan, 0)
    order = np.argsort(-conf, kind="stable")
    sorted_conf = conf[order]
    bad_cumulative = np.cumsum(~ok[order])
    steps = round(1.0 / step)
    nominal = np.unique(np.clip(np.ceil(np.arange(steps, 0, -1) * step * n - 1e-9).astype(np.int64), 1, n))[::-1]
    # Extend each cut to the end of its tie group: kept = #pixels with confidence >= that of the last kept one.
    kept = np.searchsorted(-sorted_conf, -sorted_conf[nominal - 1], side="right")
    kept = np.unique(kept)[::-1]
    density = kept / n
    bad_rate = bad_cumulative[kept - 1] / kept
    xs = np.concatenate([density, [0.0]])
    ys = np.concatenate([bad_rate, [bad_rate[-1]]])
    # xs decreases; the trapezoid sum of the reversed arrays is the area on [0, 1].
    ausc = float(np.sum(0.5 * (ys[:-1] + ys[1:]) * (xs[:-1] - xs[1:])))
    eps = float(bad_cumulative[-1] / n)
    optimal = optimal_ausc(eps)
    ratio = ausc / optimal if optimal > 0 else math.nan
    return Sparsification(density, bad_rate, ausc, optimal, ratio, eps, int(n))
