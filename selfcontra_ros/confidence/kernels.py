"""Compiled kernels of the confidence measures and the forest (numba, parallel over the valid pixels).

Every kernel computes features only at the valid pixels ``(rows, cols)``
of a :class:`~selfcontra_ros.confidence.features.FeatureContext` (the window
kernel passes over the window's pixels but writes only at valid ones; the
right-image minimum and the census window sums read the image rows that hold
a valid pixel), so the work grows with the number of valid disparities, not
with the image. Each computation exists once, here (the census window sum in
:mod:`selfcontra_ros.matching.census`); the tests hold slow, obviously
correct references. Kernels are compiled on first use and cached on disk
(``cache=True``): the first call in a fresh environment takes a few seconds.

Cost volumes are ``costs[v, u, k]`` (any real dtype), normalised cost
``c = float32(costs) / float32(scale)`` as in the measures' notation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from selfcontra_ros.matching.census import WindowedCensusCosts, window_band_advance, window_band_start, window_row

__all__ = [
    "CurveRequest",
    "CurveStatistics",
    "ForestLayout",
    "band_look",
    "curve_statistics",
    "disparity_entropy",
    "forest_layout",
    "forest_predict",
    "strip_costs",
    "window_costs",
]

I64 = NDArray[np.int64]
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


# ==================================================================== cost curves

#: Rows of the float32 statistics of :func:`_row_statistics`.
_C1, _C2, _CQ, _BELOW, _ABOVE, _C2M, _RIGHT = range(7)
_N_F32 = 7


@njit(cache=True)
def _row_statistics(
    row: NDArray[np.generic],
    cols: I64,
    dq: I64,
    lo: int,
    hi: int,
    scale: float,
    local: bool,
    rates: F64,
    powers: I64,
    weight: F64,
    moment: F64,
    moments: NDArray[np.bool_],
    right: bool,
    min_disparity: int,
    best: NDArray[np.generic],
    index: I64,
    f32: F32,
    f64: F64,
    sums: F64,
) -> None:  # pragma: no cover - compiled
    """Every requested statistic of the cost curves ``row[u]`` (W x D) of pixels ``lo .. hi - 1`` of one image row.

    The one implementation of the cost-curve statistics: the volume pass
    hands it a row of a stored volume, the census pass a row it has just
    summed. Writes ``index[:, i] = (d1, d2m)``, ``f32[:, i]`` (rows ``_C1`` ..
    ``_RIGHT``, normalised costs), ``f64[:, i] = (spread, total)`` and
    ``sums[e, :, i] = (S0, S1)`` of exponential term ``e``. Plain element
    indexing and selects rather than branches where the data decide.
    """
    depth = row.shape[1]
    s = np.float32(scale)
    n_terms = rates.size
    tabled = weight.shape[1] > 0
    last = weight.shape[1] - 1
    for i in range(lo, hi):
        # The pixel's curve as a contiguous slice: plain, unaliased runs that the compiler vectorises.
        curve = row[cols[i]]
        c_min = curve[0]
        top = curve[0]
        for k in range(1, depth):
            c_min = min(c_min, curve[k])
            top = max(top, curve[k])
        arg = 0
        # Bounded: a NaN cost (invalid input) must not walk past the curve.
        while arg < depth - 1 and curve[arg] != c_min:
            arg += 1
        # Second smallest: the minimum again when it occurs twice, else the smallest value above it.
        ties = 0
        second = top
        for k in range(depth):
            value = curve[k]
            ties += value == c_min
            second = min(second, value if value > c_min else top)
        if ties > 1 or depth < 2:
            second = c_min
        below = max(arg - 1, 0)
        above = min(arg + 1, depth - 1)
        # At a range end the one neighbour counts twice.
        c_lo = np.float32(curve[above if arg == 0 else below]) / s
        c_hi = np.float32(curve[above]) / s if arg < depth - 1 else c_lo
        index[0, i] = arg
        f32[_C1, i] = np.float32(c_min) / s
        f32[_C2, i] = np.float32(second) / s
        f32[_CQ, i] = np.float32(curve[dq[i]]) / s
        f32[_BELOW, i] = c_lo
        f32[_ABOVE, i] = c_hi
        f64[0, i] = np.float64(top) - np.float64(c_min)
        if local:
            found = False
            value2 = curve[0]
            arg2 = arg
            acc = 0.0
            for k in range(depth):
                here = curve[k]
                acc += np.float32(here) / s
                # A local minimum is strictly below its left and not above its right neighbour: a flat valley
                # counts once. Selects instead of branches: a noisy curve defeats branch prediction.
                left_value = curve[max(k - 1, 0)]
                right_value = curve[min(k + 1, depth - 1)]
                is_local = ((k == 0) | (here < left_value)) & ((k == depth - 1) | (here <= right_value)) & (k != arg)
                better = is_local & (~found | (here < value2))
                value2 = here if better else value2
                arg2 = k if better else arg2
                found = found | better
            f32[_C2M, i] = np.float32(value2 if found else top) / s
            index[1, i] = arg2
            f64[1, i] = acc
        c_best = np.float32(c_min) / s
        for e in range(n_terms):
            a0 = 0.0
            a1 = 0.0
            with_moment = moments[e]
            if tabled:
                # Integer costs: the difference to the minimum indexes the precomputed terms.
                base = np.int64(c_min)
                a0 = _table_sum(curve, base, weight[e], last)
                if with_moment:
                    a1 = _table_sum(curve, base, moment[e], last)
            else:
                for k in range(depth):
                    x = _exponent(np.float64(np.float32(curve[k]) / s - c_best), rates[e], powers[e])
                    w = math.exp(-x)
                    a0 += w
                    a1 += w * x
            sums[e, 0, i] = a0
            sums[e, 1, i] = a1 if with_moment else 0.0
    if right:
        # Best right-image cost of every right column x of the row, min over k of row[x + d(k), k]: one
        # contiguous pass over the row's curves instead of a strided diagonal walk per pixel, in the costs' own
        # type, on slices (so that the compiler sees contiguous, unaliased runs: the widest vectors). Slot
        # j = (width - 1 - min_disparity) - x holds column x, so that consecutive k are consecutive slots. Each
        # of the width + depth - 1 columns x_min .. width - 1 - min_disparity, x_min = -(min_disparity +
        # depth - 1), has at least one entry: starting from the row's maximum leaves no slot at its start
        # value unless that is its minimum.
        width = row.shape[0]
        start = row[0, 0]
        for x_left in range(width):
            curve = row[x_left]
            for k in range(depth):
                start = max(start, curve[k])
        best[:] = start
        for x_left in range(width):
            curve = row[x_left]
            slots = best[width - 1 - x_left : width - 1 - x_left + depth]
            for k in range(depth):
                slots[k] = min(slots[k], curve[k])
        for i in range(lo, hi):
            at = width - 1 - cols[i] + index[0, i]
            # No right-image entry at all (the right pixel is outside the image): the left minimum stands in.
            f32[_RIGHT, i] = np.float32(best[at]) / s if 0 <= at < best.size else f32[_C1, i]


@njit(cache=True, fastmath={"reassoc"})
def _table_sum(curve: NDArray[np.generic], base: np.int64, table: F64, last: int) -> float:  # pragma: no cover
    """``sum_k table[min(curve[k] - base, last)]``, float64, in any order (``reassoc``: vector gathers, partial sums).

    The sum then differs from the sequential one by float64 rounding only
    (far below the float32 the features are stored in). Clamped so that a
    too small table is never read outside.
    """
    acc = 0.0
    for k in range(curve.size):
        acc += table[min(np.int64(curve[k]) - base, last)]
    return acc


def _outputs(n: int, n_terms: int) -> tuple[I64, F32, F64, F64]:
    # One contiguous row per statistic: the results are views, no copies. Every valid pixel's entries of
    # the requested statistics are written, so no zero-filling pass either.
    return (
        np.empty((2, n), np.int64),
        np.empty((_N_F32, n), np.float32),
        np.empty((2, n), np.float64),
        np.empty((n_terms, 2, n), np.float64),
    )


@njit(cache=True, parallel=True)
def _volume_statistics(
    costs: NDArray[np.generic],
    rows: I64,
    cols: I64,
    dq: I64,
    scale: float,
    local: bool,
    rates: F64,
    powers: I64,
    weight: F64,
    moment: F64,
    moments: NDArray[np.bool_],
    right: bool,
    min_disparity: int,
    index: I64,
    f32: F32,
    f64: F64,
    sums: F64,
) -> None:  # pragma: no cover - compiled
    """:func:`_row_statistics` over the rows of a stored H x W x D volume, one image row per task."""
    height, width, depth = costs.shape
    # Valid pixels come in row-major order: pixels of row r are first[r] .. first[r + 1] - 1.
    first = np.searchsorted(rows, np.arange(height + 1))
    for r in prange(height):
        if first[r] == first[r + 1]:
            continue
        best = np.empty(width + depth - 1 if right else 0, costs.dtype)
        _row_statistics(
            costs[r], cols, dq, first[r], first[r + 1], scale, local, rates, powers, weight, moment, moments,
            right, min_disparity, best, index, f32, f64, sums,
        )  # fmt: skip


@njit(cache=True, parallel=True)
def _census_statistics(
    census_left: NDArray[np.uint64],
    right_reversed: NDArray[np.uint64],
    depth: int,
    worst: int,
    radius: int,
    bands: int,
    rows: I64,
    cols: I64,
    dq: I64,
    scale: float,
    local: bool,
    rates: F64,
    powers: I64,
    weight: F64,
    moment: F64,
    moments: NDArray[np.bool_],
    right: bool,
    min_disparity: int,
    index: I64,
    f32: F32,
    f64: F64,
    sums: F64,
) -> None:  # pragma: no cover - compiled
    """:func:`_row_statistics` over window-summed census rows made on the fly, a band of rows per task.

    Each band keeps the column sums of its window's raw Hamming rows and one
    summed row (W x D), reduced at once: the H x W x D volume never exists.
    Rows without a valid pixel are slid past without being summed.
    """
    height, width = census_left.shape
    first = np.searchsorted(rows, np.arange(height + 1))
    for band in prange(bands):
        v0 = band * height // bands
        v1 = (band + 1) * height // bands
        if v0 >= v1 or first[v0] == first[v1]:
            continue
        scratch = np.empty((width, depth), dtype=np.uint8)
        column = np.empty((width, depth), dtype=np.uint16)
        summed = np.empty((width, depth), dtype=np.uint16)
        best = np.empty(width + depth - 1 if right else 0, np.uint16)
        window_band_start(census_left, right_reversed, v0, radius, min_disparity, worst, scratch, column)
        for v in range(v0, v1):
            if first[v] < first[v + 1]:
                window_row(column, radius, summed)
                _row_statistics(
                    summed, cols, dq, first[v], first[v + 1], scale, local, rates, powers, weight, moment, moments,
                    right, min_disparity, best, index, f32, f64, sums,
                )  # fmt: skip
            if v + 1 < v1:
                window_band_advance(census_left, right_reversed, v, radius, min_disparity, worst, scratch, column)


@dataclass(frozen=True)
class CurveRequest:
    """Which cost-curve statistics a pass computes beyond the minima (always computed).

    Attributes:
        local: the second local minimum and the curve sum.
        exp_terms: ``(rate, power, moment)`` of each exponential sum wanted (see :class:`CurveStatistics`).
        right_minimum: the right image's best cost at the matched pixel.
    """

    local: bool = False
    exp_terms: tuple[tuple[float, int, bool], ...] = ()
    right_minimum: bool = False

    def __or__(self, other: CurveRequest) -> CurveRequest:
        """Everything either request asks for (moments merged per ``(rate, power)``)."""
        terms: dict[tuple[float, int], bool] = {}
        for rate, power, with_moment in (*self.exp_terms, *other.exp_terms):
            terms[(rate, power)] = terms.get((rate, power), False) or with_moment
        return CurveRequest(
            local=self.local or other.local,
            exp_terms=tuple((rate, power, m) for (rate, power), m in terms.items()),
            right_minimum=self.right_minimum or other.right_minimum,
        )


@dataclass
class CurveStatistics:
    """Statistics of the normalised cost curves ``c(k) = costs[v, u, k] / scale`` of N pixels, (N,) arrays.

    Attributes:
        d1: int64 index of the minimum (first on ties).
        c1: float32 minimum.
        c2: float32 second smallest value (``c1`` when it occurs twice or ``D = 1``).
        cq: float32 cost at the query index ``dq``.
        below: float32 cost at ``d1 - 1`` (at a range end the existing neighbour).
        above: float32 cost at ``d1 + 1`` (likewise).
        spread: float64 curve maximum minus minimum, in the volume's own units.
        c2m: float32 smallest local minimum other than ``d1`` (the curve maximum when none); None unless requested.
        d2m: int64 index of ``c2m`` (``d1`` when none); None unless requested.
        total: float64 sum of the normalised curve; None unless requested.
        exp: ``(rate, power) -> (S0, S1)``, float64: ``S0 = sum_k exp(-e(k))``, ``S1 = sum_k e(k) exp(-e(k))``
            with ``e(k) = rate (c(k) - c1)^power`` (``S1`` None unless its moment was requested).
        right_minimum: float32 ``min_k c_R(u - d(d1), k)``, ``c_R(x, k) = c(x + d(k), k)`` the volume
            re-indexed for the right image, ``d(k) = min_disparity + k``; entries whose left pixel leaves
            the image are skipped, ``c1`` when none is left; None unless requested.
    """

    d1: I64
    c1: F32
    c2: F32
    cq: F32
    below: F32
    above: F32
    spread: F64
    c2m: F32 | None = None
    d2m: I64 | None = None
    total: F64 | None = None
    exp: dict[tuple[float, int], tuple[F64, F64 | None]] = field(default_factory=dict)
    right_minimum: F32 | None = None


def curve_statistics(
    costs: NDArray[np.generic] | WindowedCensusCosts,
    rows: I64,
    cols: I64,
    dq: I64,
    scale: float,
    *,
    min_disparity: int = 0,
    request: CurveRequest | None = None,
) -> CurveStatistics:
    """Every requested statistic of the cost curves of pixels ``(rows, cols)`` in one compiled pass.

    Reads each valid pixel's curve once; only image rows holding a valid
    pixel are read (the right-image minimum reads all of such a row). A
    :class:`~selfcontra_ros.matching.census.WindowedCensusCosts` is summed a
    row at a time and reduced at once, never stored. For uint8/uint16 costs
    the exponential terms depend only on the integer difference to the
    minimum, so they are tabulated once.

    Args:
        costs: HxWxD cost volume (any real dtype), or windowed census costs.
        rows: (N,) pixel rows, sorted (row-major pixel order, as ``np.nonzero`` gives).
        cols: (N,) pixel columns.
        dq: (N,) query disparity as a volume index (``0 <= dq < D``).
        scale: divisor of the normalised cost.
        min_disparity: disparity of ``costs[..., 0]``, pixels (right-image minimum).
        request: what to compute beyond the minima (default: nothing more).

    Returns:
        The statistics (:class:`CurveStatistics`).
    """
    request = request if request is not None else CurveRequest()
    for rate, power, _ in request.exp_terms:
        if power not in (1, 2):
            raise ValueError(f"curve_statistics: exponential power must be 1 or 2, got {power} (rate {rate})")
    n = int(np.size(rows))
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    if n and np.any(rows[1:] < rows[:-1]):
        # The passes find each row's pixels by binary search.
        raise ValueError("curve_statistics: rows must be sorted (row-major pixel order, as np.nonzero gives)")
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    dq = np.ascontiguousarray(dq, dtype=np.int64)
    rates = np.array([t[0] for t in request.exp_terms], dtype=np.float64)
    powers = np.array([t[1] for t in request.exp_terms], dtype=np.int64)
    moments = np.array([t[2] for t in request.exp_terms], dtype=np.bool_)
    if isinstance(costs, WindowedCensusCosts):
        size = costs.max_cost + 1
    elif costs.dtype in (np.uint8, np.uint16):
        # Differences to the minimum are at most the dtype's range; only the entries in use reach the cache.
        size = 256 if costs.dtype == np.uint8 else 65536
    else:
        size = 0
    weight, moment = _exp_tables(size if n and rates.size else 0, 1.0 / float(np.float32(scale)), rates, powers)
    index, f32, f64, sums = _outputs(n, rates.size)
    flags = (float(scale), bool(request.local), rates, powers, weight, moment, moments, bool(request.right_minimum))
    if n and isinstance(costs, WindowedCensusCosts):
        _census_statistics(
            costs.census_left, costs.right_reversed, costs.num_disparities, costs.worst, costs.radius,
            costs.bands(), rows, cols, dq, *flags, int(min_disparity), index, f32, f64, sums,
        )  # fmt: skip
    elif n:
        _volume_statistics(np.asarray(costs), rows, cols, dq, *flags, int(min_disparity), index, f32, f64, sums)
    stats = CurveStatistics(
        d1=index[0],
        c1=f32[_C1],
        c2=f32[_C2],
        cq=f32[_CQ],
        below=f32[_BELOW],
        above=f32[_ABOVE],
        spread=f64[0],
    )
    if request.local:
        stats.c2m = f32[_C2M]
        stats.d2m = index[1]
        stats.total = f64[1]
    for e, (rate, power, with_moment) in enumerate(request.exp_terms):
        stats.exp[(rate, power)] = (
            sums[e, 0],
            sums[e, 1] if with_moment else None,
        )
    if request.right_minimum:
        stats.right_minimum = f32[_RIGHT]
    return stats


@njit(cache=True, inline="always")
def _exponent(delta: float, rate: float, power: int) -> float:  # pragma: no cover - compiled
    """``rate * delta ** power`` for a normalised cost difference ``delta >= 0``."""
    return rate * delta if power == 1 else rate * delta * delta


@njit(cache=True)
def _exp_tables(size: int, inv_scale: float, rates: F64, powers: I64) -> tuple[F64, F64]:  # pragma: no cover
    """``exp(-e)`` and ``e exp(-e)`` of each term for integer cost differences ``0 .. size - 1``."""
    weight = np.empty((rates.size, size), np.float64)
    moment = np.empty((rates.size, size), np.float64)
    for t in range(rates.size):
        for j in range(size):
            e = _exponent(j * inv_scale, rates[t], powers[t])
            weight[t, j] = math.exp(-e)
            moment[t, j] = weight[t, j] * e
    return weight, moment


# ==================================================================== disparity-map windows


@njit(cache=True, parallel=True)
def _disparity_entropy(bins: NDArray[np.int32], valid: NDArray[np.bool_], n_bins: int, window: int) -> F32:
    height, width = bins.shape
    radius = window // 2
    area = window * window
    # n ln n for every possible count of one bin in a window.
    nlogn = np.zeros(area + 1, np.float64)
    for m in range(2, area + 1):
        nlogn[m] = m * math.log(m)
    out = np.zeros((height, width), np.float32)
    for v in prange(height):
        y0, y1 = max(v - radius, 0), min(v + radius + 1, height)
        counts = np.zeros(n_bins, np.int64)
        total = 0
        acc = 0.0  # sum over bins of n ln n
        # Columns enter at u + radius and leave after u - radius: a sliding histogram along the row.
        for x in range(min(radius, width)):
            for y in range(y0, y1):
                if valid[y, x]:
                    b = bins[y, x]
                    acc += nlogn[counts[b] + 1] - nlogn[counts[b]]
                    counts[b] += 1
                    total += 1
        for u in range(width):
            x = u + radius
            if x < width:
                for y in range(y0, y1):
                    if valid[y, x]:
                        b = bins[y, x]
                        acc += nlogn[counts[b] + 1] - nlogn[counts[b]]
                        counts[b] += 1
                        total += 1
            if valid[v, u]:
                # -sum q ln q with q = n / T equals ln T - sum(n ln n) / T; a window with two or more
                # bins has entropy above ln(T) / T > 1e-3, so anything below 1e-9 is rounding of a single bin.
                entropy = math.log(total) - acc / total
                out[v, u] = entropy if entropy > 1e-9 else 0.0
            x = u - radius
            if x >= 0:
                for y in range(y0, y1):
                    if valid[y, x]:
                        b = bins[y, x]
                        acc += nlogn[counts[b] - 1] - nlogn[counts[b]]
                        counts[b] -= 1
                        total -= 1
    return out


def disparity_entropy(bins: NDArray[np.int32], valid: NDArray[np.bool_], window: int) -> F32:
    """Entropy (nats) of the bin histogram of the valid pixels in each ``window``-square, HxW float32.

    Args:
        bins: HxW non-negative bin index of each pixel (read only where valid).
        valid: HxW valid-pixel mask; pixels outside the image or invalid do not count.
        window: odd window side, pixels.

    Returns:
        HxW float32 ``-sum_b q_b ln q_b`` at valid pixels (``q_b`` the share
        of the window's valid pixels in bin ``b``), 0 elsewhere.
    """
    n_bins = int(bins[valid].max()) + 1 if valid.any() else 1
    return np.asarray(_disparity_entropy(np.ascontiguousarray(bins), np.ascontiguousarray(valid), n_bins, int(window)))


@njit(cache=True, parallel=True)
def _band_look(
    grey: F32,
    disparity: F32,
    band: NDArray[np.bool_],
    rows: I64,
    cols: I64,
    jump: float,
    half_height: int,
    half_width: int,
    min_count: int,
) -> F32:  # pragma: no cover - compiled
    height, width = grey.shape
    out = np.full(rows.size, np.nan, np.float32)
    for k in prange(rows.size):
        r, c = rows[k], cols[k]
        own = disparity[r, c]
        value = grey[r, c]
        # Sums, sums of squares and counts of the background (0) and the object's interior (1).
        s0 = q0 = s1 = q1 = 0.0
        n0 = n1 = 0
        for y in range(max(r - half_height, 0), min(r + half_height + 1, height)):
            for x in range(max(c - half_width, 0), min(c + half_width + 1, width)):
                d = disparity[y, x]
                if not 0 < d < math.inf:  # NaN, infinite or invalid
                    continue
                v = grey[y, x]
                if d < own - jump:
                    s0 += v
                    q0 += v * v
                    n0 += 1
                elif abs(d - own) <= 1.0 and not band[y, x]:
                    s1 += v
                    q1 += v * v
                    n1 += 1
        if n0 >= min_count and n1 >= min_count:
            m0, m1 = s0 / n0, s1 / n1
            # A flat set's spread is floored at one grey level, so that a pixel a level off is not infinitely far.
            sd0 = math.sqrt(max(q0 / n0 - m0 * m0, 1.0))
            sd1 = math.sqrt(max(q1 / n1 - m1 * m1, 1.0))
            out[k] = abs(value - m0) / sd0 - abs(value - m1) / sd1
    return out


def band_look(
    grey: NDArray[np.floating],
    disparity: NDArray[np.floating],
    band: NDArray[np.bool_],
    rows: NDArray[np.integer],
    cols: NDArray[np.integer],
    *,
    jump: float,
    window: tuple[int, int],
    min_count: int,
) -> F32:
    """How much more pixel ``(rows[k], cols[k])`` looks like the object at its disparity than the background beyond.

    Over a ``window`` (height, width; odd) around the pixel, the *background* is the valid pixels more
    than ``jump`` below the pixel's disparity and the *interior* those within 1 px of it and outside
    ``band``. The look is the pixel's grey value as a z-score against the background minus its z-score
    against the interior (each set's standard deviation floored at 1 grey level): positive where the
    pixel resembles the interior, negative where it resembles the background.

    Args:
        grey: HxW float grey image (smoothed by the caller as it sees fit).
        disparity: HxW disparity; non-finite or <= 0 is invalid.
        band: HxW mask of the pixels never counted as interior (the fattening band).
        rows, cols: (N,) pixels to score; each must hold a valid disparity.
        jump: disparity drop to the background, pixels.
        window: (height, width) of the window, odd, pixels.
        min_count: fewest pixels each set needs; fewer gives NaN.

    Returns:
        (N,) float32 look; NaN where a set is too small.

    Raises:
        ValueError: images of different shapes, or a pixel outside them (the kernel does not check bounds).
    """
    shape = np.shape(grey)
    if np.shape(disparity) != shape or np.shape(band) != shape:
        raise ValueError(f"band_look: grey {shape}, disparity {np.shape(disparity)} and band {np.shape(band)} differ")
    r: I64 = np.ascontiguousarray(rows, dtype=np.int64)
    c: I64 = np.ascontiguousarray(cols, dtype=np.int64)
    if r.shape != c.shape or (r.size and (r.min() < 0 or r.max() >= shape[0] or c.min() < 0 or c.max() >= shape[1])):
        raise ValueError(f"band_look: pixels must be pairs inside the {shape} image")
    return np.asarray(
        _band_look(
            np.ascontiguousarray(grey, dtype=np.float32),
            np.ascontiguousarray(disparity, dtype=np.float32),
            np.ascontiguousarray(band, dtype=np.bool_),
            r,
            c,
            float(jump),
            int(window[0]) // 2,
            int(window[1]) // 2,
            int(min_count),
        )
    )


@njit(cache=True)
def _strip_cost(
    right: F32, r: int, c: int, disparity: float, half: int, centred: F32, n: int
) -> float:  # pragma: no cover - compiled
    """Zero-mean mean absolute difference of the left strip ``centred`` and the right one ``disparity`` left of it."""
    height, width = right.shape
    # A strip matched beyond the image border reads its edge column; the caller guarantees width >= 2.
    x = min(max(c - disparity, 0.0), width - 1.0)
    x0 = min(math.floor(x), width - 2)
    t = x - x0
    x1 = x0 + 1
    mean = 0.0
    for i in range(n):
        y = min(max(r - half + i, 0), height - 1)
        mean += (1.0 - t) * right[y, x0] + t * right[y, x1]
    mean /= n
    total = 0.0
    for i in range(n):
        y = min(max(r - half + i, 0), height - 1)
        total += abs(centred[i] - ((1.0 - t) * right[y, x0] + t * right[y, x1] - mean))
    return total / n


@njit(cache=True, parallel=True)
def _strip_costs(
    left: F32, right: F32, rows: I64, cols: I64, own: F32, background: F32, max_disparity: int, half: int
) -> F32:  # pragma: no cover - compiled
    height = left.shape[0]
    n = 2 * half + 1
    out = np.empty((rows.size, 4), np.float32)
    for k in prange(rows.size):
        r, c = rows[k], cols[k]
        strip = np.empty(n, np.float32)
        mean = 0.0
        for i in range(n):
            strip[i] = left[min(max(r - half + i, 0), height - 1), c]
            mean += strip[i]
        mean /= n
        texture = 0.0
        for i in range(n):
            strip[i] -= mean
            texture += abs(strip[i])
        best = math.inf
        for d in range(0, min(max_disparity, c) + 1):
            best = min(best, _strip_cost(right, r, c, float(d), half, strip, n))
        out[k, 0] = _strip_cost(right, r, c, own[k], half, strip, n)
        out[k, 1] = _strip_cost(right, r, c, background[k], half, strip, n)
        out[k, 2] = best
        out[k, 3] = texture / n
    return out


def strip_costs(
    left: NDArray[np.floating],
    right: NDArray[np.floating],
    rows: NDArray[np.integer],
    cols: NDArray[np.integer],
    own: NDArray[np.floating],
    background: NDArray[np.floating],
    *,
    max_disparity: int,
    half_height: int,
) -> F32:
    """Matching costs of the thin vertical strip through each pixel ``(rows[k], cols[k])`` of the left image.

    The strip is the pixel's column from ``half_height`` rows above to as many below (rows clipped at the
    image border), its mean removed. Its cost at a disparity ``d`` is the mean absolute difference to the
    right image's strip ``d`` columns to the left (linearly interpolated between columns, the column clamped
    to the image), that strip's mean removed too. A strip one pixel wide does not straddle an object's
    vertical outline the way a square window does, so it tells which side of an edge a pixel belongs to.

    Args:
        left, right: HxW float grey images of the rectified pair.
        rows, cols: (N,) pixels to score.
        own, background: (N,) two disparities per pixel to cost (e.g. its own and its background's).
        max_disparity: the whole-pixel disparities 0 .. this (at most the pixel's column) are searched for the
            smallest cost.
        half_height: rows above and below the pixel in the strip.

    Returns:
        (N, 4) float32: cost at ``own``, cost at ``background``, smallest cost over the searched disparities,
        and the strip's texture (mean absolute deviation from its mean), grey levels.

    Raises:
        ValueError: images of different shapes, or pixels and disparities that do not match or lie outside.
    """
    grey_left, grey_right, r, c = _pair_and_pixels("strip_costs", left, right, rows, cols)
    d0: F32 = np.ascontiguousarray(own, dtype=np.float32)
    d1: F32 = np.ascontiguousarray(background, dtype=np.float32)
    if not r.shape == d0.shape == d1.shape:
        raise ValueError("strip_costs: both disparities must be (N,) arrays, one per pixel")
    if not (np.isfinite(d0).all() and np.isfinite(d1).all()):
        raise ValueError("strip_costs: disparities must be finite")
    return np.asarray(_strip_costs(grey_left, grey_right, r, c, d0, d1, int(max_disparity), int(half_height)))


def _pair_and_pixels(
    name: str,
    left: NDArray[np.floating],
    right: NDArray[np.floating],
    rows: NDArray[np.integer],
    cols: NDArray[np.integer],
) -> tuple[F32, F32, I64, I64]:
    """The pair as float32 and the pixels as int64 for the window kernel ``name``; ValueError where they do not fit."""
    shape = np.shape(left)
    if np.shape(right) != shape or len(shape) != 2 or shape[1] < 2:
        raise ValueError(f"{name}: left {shape} and right {np.shape(right)} must be one HxW shape, W >= 2")
    r: I64 = np.ascontiguousarray(rows, dtype=np.int64)
    c: I64 = np.ascontiguousarray(cols, dtype=np.int64)
    if r.ndim != 1 or r.shape != c.shape:
        raise ValueError(f"{name}: rows and cols must be (N,) arrays of one length")
    if r.size and (r.min() < 0 or r.max() >= shape[0] or c.min() < 0 or c.max() >= shape[1]):
        raise ValueError(f"{name}: pixels must lie inside the {shape} image")
    return np.ascontiguousarray(left, dtype=np.float32), np.ascontiguousarray(right, dtype=np.float32), r, c


@njit(cache=True)
def _window_cost(
    left: F32, right: F32, r: int, c: int, disparity: float, half: int, before: int, after: int
) -> tuple[float, float]:  # pragma: no cover - compiled
    """Zero-mean mean absolute difference of a left window and the right one ``disparity`` left of it, and the
    left window's mean absolute deviation (rows ``r +- half``, columns ``c - before .. c + after``, clamped)."""
    height, width = right.shape
    mean_left = 0.0
    mean_right = 0.0
    for i in range(-half, half + 1):
        y = min(max(r + i, 0), height - 1)
        for j in range(-before, after + 1):
            u = min(max(c + j, 0), width - 1)
            x = min(max(u - disparity, 0.0), width - 1.0)
            x0 = min(math.floor(x), width - 2)
            t = x - x0
            mean_left += left[y, u]
            mean_right += (1.0 - t) * right[y, x0] + t * right[y, x0 + 1]
    n = (2 * half + 1) * (before + after + 1)
    mean_left /= n
    mean_right /= n
    cost = 0.0
    texture = 0.0
    for i in range(-half, half + 1):
        y = min(max(r + i, 0), height - 1)
        for j in range(-before, after + 1):
            u = min(max(c + j, 0), width - 1)
            x = min(max(u - disparity, 0.0), width - 1.0)
            x0 = min(math.floor(x), width - 2)
            t = x - x0
            a = left[y, u] - mean_left
            cost += abs(a - ((1.0 - t) * right[y, x0] + t * right[y, x0 + 1] - mean_right))
            texture += abs(a)
    return cost / n, texture / n


@njit(cache=True, parallel=True)
def _window_costs(
    left: F32, right: F32, rows: I64, cols: I64, disparities: F32, half: int, before: int, after: int
) -> F32:  # pragma: no cover - compiled
    n_disparities = disparities.shape[1]
    out = np.empty((rows.size, n_disparities + 1), np.float32)
    for k in prange(rows.size):
        texture = 0.0
        for j in range(n_disparities):
            out[k, j], texture = _window_cost(left, right, rows[k], cols[k], disparities[k, j], half, before, after)
        out[k, n_disparities] = texture
    return out


def window_costs(
    left: NDArray[np.floating],
    right: NDArray[np.floating],
    rows: NDArray[np.integer],
    cols: NDArray[np.integer],
    disparities: NDArray[np.floating],
    *,
    half_height: int,
    before: int,
    after: int,
) -> F32:
    """Matching costs of a window at each pixel ``(rows[k], cols[k])`` of the left image, at given disparities.

    The window covers rows ``half_height`` above to as many below and columns ``before`` left of the pixel to
    ``after`` right of it (clamped to the image), so it can lie on one side of the pixel: a window that ends at
    the pixel sees what lies left of it, one that starts there what lies right of it. Its cost at a disparity
    ``d`` is :func:`strip_costs`' (zero-mean mean absolute difference to the right image ``d`` columns to the
    left, linearly interpolated, the column clamped to the image); ``before = after = 0`` is that strip.

    Args:
        left, right: HxW float grey images of the rectified pair.
        rows, cols: (N,) pixels to score.
        disparities: (N, K) disparities to cost each pixel's window at (K >= 1).
        half_height, before, after: the window's reach, pixels (each >= 0).

    Returns:
        (N, K + 1) float32: the cost at each of the K disparities, then the window's texture (mean absolute
        deviation of the left window from its mean), grey levels.

    Raises:
        ValueError: images of different shapes, pixels and disparities that do not match or lie outside, a
            negative reach or a non-finite disparity.
    """
    grey_left, grey_right, r, c = _pair_and_pixels("window_costs", left, right, rows, cols)
    d: F32 = np.ascontiguousarray(disparities, dtype=np.float32)
    if d.ndim != 2 or d.shape[0] != r.size or d.shape[1] < 1:
        raise ValueError("window_costs: disparities must be an (N, K) array, K >= 1, a row per pixel")
    if min(half_height, before, after) < 0:
        raise ValueError(f"window_costs: the window's reach must be >= 0, got {half_height}, {before}, {after}")
    if not np.isfinite(d).all():
        raise ValueError("window_costs: disparities must be finite")
    return np.asarray(_window_costs(grey_left, grey_right, r, c, d, int(half_height), int(before), int(after)))


# ==================================================================== forest


#: Samples traversing a tree together: their independent paths overlap in the CPU's pipeline.
_FOREST_BLOCK = 256


@njit(cache=True)
def _forest_layout(
    tree_offsets: I64,
    children_left: NDArray[np.int32],
    children_right: NDArray[np.int32],
    feature: NDArray[np.int32],
    threshold: F64,
) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.int32], F32, I64]:  # pragma: no cover - compiled
    """Compact node arrays: global children (a leaf is its own child), tested column, float32 threshold, tree depths.

    The float32 threshold is the largest float32 not above the float64 one,
    so that for a float32 feature ``x``, ``x <= threshold32`` exactly when
    ``x <= threshold`` (scikit-learn's test in float64).
    """
    n_trees = tree_offsets.size - 1
    m = children_left.size
    left = np.empty(m, np.int32)
    right = np.empty(m, np.int32)
    column = np.zeros(m, np.int32)
    threshold32 = np.zeros(m, np.float32)
    level = np.zeros(m, np.int64)
    depth = np.zeros(n_trees, np.int64)
    for t in range(n_trees):
        root = tree_offsets[t]
        for j in range(root, tree_offsets[t + 1]):
            if children_left[j] >= 0:
                left[j] = root + children_left[j]
                right[j] = root + children_right[j]
                column[j] = feature[j]
                value = np.float32(threshold[j])
                if np.float64(value) > threshold[j]:
                    value = np.nextafter(value, np.float32(-np.inf))
                threshold32[j] = value
                # Children follow their parent (checked when a model is built or loaded).
                level[left[j]] = level[j] + 1
                level[right[j]] = level[j] + 1
            else:
                left[j] = j
                right[j] = j
            depth[t] = max(depth[t], level[j])
    return left, right, column, threshold32, depth


class ForestLayout(NamedTuple):
    """A forest's node arrays as the traversal reads them (:func:`forest_layout`), built once per model.

    Attributes:
        left: (M,) int32 global left child (a leaf is its own child).
        right: (M,) int32 global right child (likewise).
        column: (M,) int32 tested feature column (0 at leaves).
        threshold32: (M,) float32 threshold, the largest float32 not above the float64 one.
        depth: (T,) int64 depth of each tree, levels.
    """

    left: NDArray[np.int32]
    right: NDArray[np.int32]
    column: NDArray[np.int32]
    threshold32: F32
    depth: I64


def forest_layout(
    tree_offsets: I64,
    children_left: NDArray[np.int32],
    children_right: NDArray[np.int32],
    feature: NDArray[np.int32],
    threshold: F64,
) -> ForestLayout:
    """The traversal's node arrays of a forest given as in :mod:`selfcontra_ros.confidence.forest`.

    For a float32 feature ``x``, ``x <= threshold32`` exactly when ``x <=
    threshold`` (scikit-learn's test, in float64).
    """
    return ForestLayout(
        *_forest_layout(
            np.ascontiguousarray(tree_offsets, dtype=np.int64),
            np.ascontiguousarray(children_left, dtype=np.int32),
            np.ascontiguousarray(children_right, dtype=np.int32),
            np.ascontiguousarray(feature, dtype=np.int32),
            np.ascontiguousarray(threshold, dtype=np.float64),
        )
    )


@njit(cache=True, parallel=True)
def _forest_predict(
    x_columns: F32,
    tree_offsets: I64,
    left: NDArray[np.int32],
    right: NDArray[np.int32],
    column: NDArray[np.int32],
    threshold32: F32,
    depth: I64,
    positive: F64,
) -> F32:  # pragma: no cover - compiled
    n = x_columns.shape[1]
    n_trees = tree_offsets.size - 1
    out = np.empty(n, np.float32)
    n_blocks = (n + _FOREST_BLOCK - 1) // _FOREST_BLOCK
    for b in prange(n_blocks):
        start = b * _FOREST_BLOCK
        size = min(n - start, _FOREST_BLOCK)
        votes = np.zeros(size, np.float64)
        node = np.empty(size, np.int32)
        for t in range(n_trees):
            node[:] = np.int32(tree_offsets[t])
            # A leaf is its own child: the block walks the tree in lockstep for exactly its depth.
            for _ in range(depth[t]):
                # Independent samples, a select instead of a branch: the loads of many samples overlap.
                for j in range(size):
                    at = node[j]
                    # NaN fails the test and goes right, as in scikit-learn's trees.
                    node[j] = left[at] if x_columns[column[at], start + j] <= threshold32[at] else right[at]
            # Trees are summed in order in float64, as scikit-learn's predict_proba does.
            for j in range(size):
                votes[j] += positive[node[j]]
        for j in range(size):
            out[start + j] = votes[j] / n_trees
    return out


def forest_predict(x: F32, tree_offsets: I64, positive: F64, layout: ForestLayout) -> F32:
    """Mean over trees of the positive share of the leaf each row of ``x`` reaches (float64 sum, float32 result).

    At a node, a row goes left when ``x[feature] <= threshold``. A
    column-major ``x`` (as :func:`~selfcontra_ros.confidence.features.compute_features`
    returns) is read in place; any other is transposed once.

    Args:
        x: (N, F) float32 features.
        tree_offsets: (T+1,) start of each tree's nodes.
        positive: (M,) positive share of each node.
        layout: the forest's :func:`forest_layout`.

    Returns:
        (N,) float32 in [0, 1].
    """
    return np.asarray(
        _forest_predict(
            # Column-major features: a block of samples reads one contiguous run per tested column.
            np.ascontiguousarray(np.asarray(x, dtype=np.float32).T),
            np.ascontiguousarray(tree_offsets, dtype=np.int64),
            *layout,
            np.ascontiguousarray(positive, dtype=np.float64),
        )
    )
