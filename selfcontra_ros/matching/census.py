"""Census matching costs and a census-cost semi-global matcher (SGM).

* :func:`census_transform`: each pixel becomes a bit string, one bit per
  window neighbour, set where the neighbour is darker than the centre.
* :func:`census_cost_volume`: the Hamming distance between the left census
  string at ``(u, v)`` and the right one at ``(u - d, v)``, an HxWxD uint8
  volume; :func:`right_cost_volume` re-indexes it for the right image.
* :class:`CensusSGMMatcher` (query algorithm ``"census_sgm"``, the paper's
  query algorithm): Hirschmüller's SGM on the census costs along 4 or 8 scan
  directions, winner-takes-all, and the right disparity from the same
  aggregated volume. :meth:`CensusSGMMatcher.compute_costs` also returns the
  aggregated costs, which the cost-based confidence measures read.

Cost units are bits (Hamming distance). Columns where ``u - d < 0`` have no
right pixel to compare with; they get the largest possible cost (the number of
census bits), i.e. "worst match", rather than an invalid marker, so that every
cost curve is complete.

Memory at KITTI size (1241x376, 128 disparities): the raw volume is 60 MB
(uint8), the aggregated one 120 MB (uint16); SGM keeps one image line of
int32 working costs per scan.

The census transform, the Hamming volume and the window sum are compiled
kernels (numba, parallel over image rows or bands of rows, cached on disk
after the first call); SGM aggregation is vectorised numpy. The window-summed
costs of the confidence measures (query algorithms without costs of their
own) are :class:`WindowedCensusCosts`: the two census images, from which the
window sums are made a band of rows at a time (:func:`window_band_start`,
:func:`window_row`, :func:`window_band_advance`, the one implementation of
that sum), either into a stored volume (:meth:`WindowedCensusCosts.volume`,
:func:`census_window_cost_volume`) or straight into the confidence
statistics, which never store it
(:func:`selfcontra_ros.confidence.kernels.curve_statistics`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from selfcontra_ros.matching.base import DisparityPair, MatcherError, MatcherParams, to_grey, validate_pair

__all__ = [
    "CENSUS_WINDOW",
    "SGM_DIRECTIONS",
    "SGM_P1",
    "SGM_P2",
    "CensusSGMMatcher",
    "CensusSGMResult",
    "WindowedCensusCosts",
    "aggregate_sgm",
    "box_cost_volume",
    "census_bits",
    "census_cost_volume",
    "census_transform",
    "census_window_cost_volume",
    "hamming",
    "right_cost_volume",
    "window_band_advance",
    "window_band_start",
    "window_row",
    "windowed_census_costs",
    "winner_takes_all",
]

#: Census window (height, width), pixels: 7 x 9 = 62 neighbour bits, fits a uint64.
CENSUS_WINDOW = (7, 9)
#: SGM penalty for a disparity change of 1 px between path neighbours, bits.
SGM_P1 = 10
#: SGM penalty for larger disparity changes, bits.
SGM_P2 = 120
#: Number of SGM scan directions (4: horizontal and vertical; 8: plus the diagonals).
SGM_DIRECTIONS = 8

# Per-byte popcount table, for numpy versions without np.bitwise_count (< 2.0).
_POPCOUNT8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)

# Bit masks of the branch-free 64-bit popcount (uint64 so that numba keeps the arithmetic unsigned).
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


@njit(cache=True, inline="always")
def _popcount64(x: np.uint64) -> np.uint64:  # pragma: no cover - compiled
    """Number of set bits of a uint64 (SWAR sum; LLVM turns it into the popcnt instruction)."""
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return (x * _H01) >> np.uint64(56)


@njit(cache=True, parallel=True)
def _census_kernel(padded: NDArray[np.float32], h_win: int, w_win: int) -> NDArray[np.uint64]:  # pragma: no cover
    """Census strings of the centre of every ``h_win x w_win`` window of an edge-padded float32 image."""
    height = padded.shape[0] - (h_win - 1)
    width = padded.shape[1] - (w_win - 1)
    ry, rx = h_win // 2, w_win // 2
    out = np.empty((height, width), dtype=np.uint64)
    for v in prange(height):
        bits = np.zeros(width, np.uint64)
        centre = padded[v + ry, rx : rx + width]
        bit = np.uint64(0)
        # One neighbour at a time over the whole row: the inner loop over pixels is a vector compare, shift
        # and or on contiguous slices (no branch: the bits of natural images are unpredictable).
        for dy in range(h_win):
            for dx in range(w_win):
                if dy == ry and dx == rx:
                    continue
                neighbour = padded[v + dy, dx : dx + width]
                for u in range(width):
                    bits[u] |= np.uint64(neighbour[u] < centre[u]) << bit
                bit += np.uint64(1)
        out[v] = bits
    return out


@njit(cache=True, inline="always")
def _hamming_row(
    census_left: NDArray[np.uint64],
    right_reversed: NDArray[np.uint64],
    v: int,
    min_disparity: int,
    worst: int,
    out: NDArray[np.uint8],
) -> None:  # pragma: no cover - compiled
    """Row ``v`` of the Hamming volume into ``out`` (W x D): ``popcount(L[v, u] ^ R[v, u - min_disparity - k])``.

    ``right_reversed`` is the right census image mirrored left-right, so that
    the right strings of consecutive ``k`` are consecutive in memory;
    ``worst`` where ``u - d`` leaves the image.
    """
    width, depth = out.shape
    fill = np.uint8(worst)
    right_row = right_reversed[v]
    for u in range(width):
        # Slices k with 0 <= u - min_disparity - k < width, split off so that the inner loop has no branch;
        # contiguous, unaliased slices let the compiler vectorise the popcounts.
        k_lo = min(max(u - min_disparity - width + 1, 0), depth)
        k_hi = min(max(u - min_disparity + 1, k_lo), depth)
        a = census_left[v, u]
        base = width - 1 - u + min_disparity  # mirrored column of u - min_disparity - k, minus k
        curve = out[u]
        curve[:k_lo] = fill
        strings = right_row[base + k_lo : base + k_hi]
        inside = curve[k_lo:k_hi]
        for k in range(k_hi - k_lo):
            inside[k] = np.uint8(_popcount64(a ^ strings[k]))
        curve[k_hi:] = fill


@njit(cache=True, parallel=True)
def _hamming_volume_kernel(
    census_left: NDArray[np.uint64],
    right_reversed: NDArray[np.uint64],
    num_disparities: int,
    min_disparity: int,
    worst: int,
) -> NDArray[np.uint8]:  # pragma: no cover - compiled
    """The Hamming volume (H x W x D uint8 bits), one image row per task (:func:`_hamming_row`)."""
    height, width = census_left.shape
    out = np.empty((height, width, num_disparities), dtype=np.uint8)
    for v in prange(height):
        _hamming_row(census_left, right_reversed, v, min_disparity, worst, out[v])
    return out


@njit(cache=True, inline="always")
def _add_row(column: NDArray[np.uint16], raw: NDArray[np.uint8], sign: int) -> None:  # pragma: no cover - compiled
    """``column += sign * raw`` (W x D, sign +1 or -1), exact in uint16 arithmetic, row slice by row slice."""
    width, depth = column.shape
    for u in range(width):
        target = column[u]
        source = raw[u]
        if sign > 0:
            for k in range(depth):
                target[k] += source[k]
        else:
            for k in range(depth):
                target[k] -= source[k]


@njit(cache=True)
def window_band_start(
    census_left: NDArray[np.uint64],
    right_reversed: NDArray[np.uint64],
    v0: int,
    radius: int,
    min_disparity: int,
    worst: int,
    scratch: NDArray[np.uint8],
    column: NDArray[np.uint16],
) -> None:  # pragma: no cover - compiled
    """Start a band of windowed census rows at row ``v0`` (kernel building block).

    ``column`` (W x D uint16) receives the sum of the raw Hamming rows ``v0 -
    radius .. v0 + radius`` (clipped to the image: the border row repeats),
    bits; ``scratch`` (W x D uint8) is working space.
    """
    height = census_left.shape[0]
    column[:] = 0
    for i in range(-radius, radius + 1):
        _hamming_row(census_left, right_reversed, min(max(v0 + i, 0), height - 1), min_disparity, worst, scratch)
        _add_row(column, scratch, 1)


@njit(cache=True)
def window_row(column: NDArray[np.uint16], radius: int, out: NDArray[np.uint16]) -> None:  # pragma: no cover
    """Windowed costs of the current row into ``out`` (W x D uint16): ``column`` summed over ``2 radius + 1`` columns.

    Columns outside the image repeat the border one. A running sum: column
    ``u`` adds ``column[u + radius]`` and drops ``column[u - radius - 1]``
    (both clipped), exact in integers, so each cost costs two additions
    whatever the radius.
    """
    width, depth = column.shape
    for k in range(depth):
        out[0, k] = 0
    for dx in range(-radius, radius + 1):
        x = min(max(dx, 0), width - 1)
        for k in range(depth):
            out[0, k] += column[x, k]
    for u in range(1, width):
        # Row slices: contiguous, unaliased runs that the compiler vectorises.
        here = out[u]
        previous = out[u - 1]
        entering = column[min(u + radius, width - 1)]
        leaving = column[max(u - radius - 1, 0)]
        for k in range(depth):
            here[k] = previous[k] + entering[k] - leaving[k]


@njit(cache=True)
def window_band_advance(
    census_left: NDArray[np.uint64],
    right_reversed: NDArray[np.uint64],
    v: int,
    radius: int,
    min_disparity: int,
    worst: int,
    scratch: NDArray[np.uint8],
    column: NDArray[np.uint16],
) -> None:  # pragma: no cover - compiled
    """Slide a band's ``column`` from row ``v`` to ``v + 1``: row ``v - radius`` leaves, ``v + radius + 1`` enters.

    The leaving row's raw costs are computed again rather than kept: a
    Hamming row costs less than keeping ``2 radius + 1`` of them, whose
    footprint would push the band's working rows out of the core's cache.
    """
    height = census_left.shape[0]
    _hamming_row(census_left, right_reversed, min(max(v - radius, 0), height - 1), min_disparity, worst, scratch)
    _add_row(column, scratch, -1)
    _hamming_row(census_left, right_reversed, min(v + radius + 1, height - 1), min_disparity, worst, scratch)
    _add_row(column, scratch, 1)


@njit(cache=True, parallel=True)
def _windowed_hamming_kernel(
    census_left: NDArray[np.uint64],
    right_reversed: NDArray[np.uint64],
    num_disparities: int,
    min_disparity: int,
    worst: int,
    radius: int,
    bands: int,
) -> NDArray[np.uint16]:  # pragma: no cover - compiled
    """The Hamming volume summed over ``(2 radius + 1)``-square windows (border replicated), H x W x D uint16.

    Each task owns a band of output rows and keeps the column sums of its
    window's raw rows, so that the H x W x D raw volume never exists.
    """
    height, width = census_left.shape
    out = np.empty((height, width, num_disparities), dtype=np.uint16)
    for band in prange(bands):
        v0 = band * height // bands
        v1 = (band + 1) * height // bands
        if v0 >= v1:
            continue
        scratch = np.empty((width, num_disparities), dtype=np.uint8)
        column = np.empty((width, num_disparities), dtype=np.uint16)
        window_band_start(census_left, right_reversed, v0, radius, min_disparity, worst, scratch, column)
        for v in range(v0, v1):
            window_row(column, radius, out[v])
            if v + 1 < v1:
                window_band_advance(census_left, right_reversed, v, radius, min_disparity, worst, scratch, column)
    return out


@njit(cache=True, parallel=True)
def _box_sum_kernel(volume: NDArray[np.unsignedinteger], radius: int) -> NDArray[np.uint16]:  # pragma: no cover
    """Sum of each disparity slice over the ``(2 radius + 1)``-square window, border pixels replicated."""
    height, width, depth = volume.shape
    out = np.empty((height, width, depth), dtype=np.uint16)
    for v in prange(height):
        # Column sums over the window's rows first (each row of the output is independent: one per thread).
        column = np.zeros((width, depth), dtype=np.uint16)
        for dy in range(-radius, radius + 1):
            y = min(max(v + dy, 0), height - 1)
            for u in range(width):
                for k in range(depth):
                    column[u, k] += np.uint16(volume[y, u, k])
        for u in range(width):
            for k in range(depth):
                out[v, u, k] = 0
            for dx in range(-radius, radius + 1):
                x = min(max(u + dx, 0), width - 1)
                for k in range(depth):
                    out[v, u, k] += column[x, k]
    return out


def census_bits(window: tuple[int, int] = CENSUS_WINDOW) -> int:
    """Number of bits of a census string over an odd ``(height, width)`` window (the centre is not compared)."""
    return window[0] * window[1] - 1


def census_transform(image: NDArray[np.generic], window: tuple[int, int] = CENSUS_WINDOW) -> NDArray[np.uint64]:
    """Census transform of a grey image.

    Bit ``k`` of pixel ``(u, v)`` is set when the ``k``-th window neighbour
    (row-major order, centre skipped) is strictly darker than ``(u, v)``.
    Neighbours outside the image replicate the border pixel.

    Args:
        image: HxW grey image (any real dtype) or HxWx3 uint8 RGB.
        window: odd ``(height, width)``; at most 64 neighbours.

    Returns:
        HxW uint64 census strings.

    Raises:
        MatcherError: if the window is not odd or has more than 64 neighbours.
    """
    h_win, w_win = window
    if h_win % 2 == 0 or w_win % 2 == 0 or h_win < 1 or w_win < 1:
        raise MatcherError(f"census window must be odd (height, width), got {window}")
    if census_bits(window) > 64:
        raise MatcherError(f"census window {window} has {census_bits(window)} neighbours; at most 64 fit a uint64")
    img = np.asarray(image)
    if img.ndim == 3:
        img = to_grey(img.astype(np.uint8))
    if img.ndim != 2:
        raise MatcherError(f"census image must be HxW grey or HxWx3 RGB, got shape {img.shape}")
    ry, rx = h_win // 2, w_win // 2
    padded = np.pad(img.astype(np.float32), ((ry, ry), (rx, rx)), mode="edge")
    return np.asarray(_census_kernel(padded, h_win, w_win))


def popcount(x: NDArray[np.uint64]) -> NDArray[np.uint8]:
    """Element-wise number of set bits of a uint64 array (``np.bitwise_count`` where numpy has it, >= 2.0)."""
    if hasattr(np, "bitwise_count"):
        return np.asarray(np.bitwise_count(x), dtype=np.uint8)
    as_bytes = np.ascontiguousarray(x).view(np.uint8).reshape(*np.shape(x), 8)
    return np.asarray(_POPCOUNT8[as_bytes].sum(axis=-1), dtype=np.uint8)


def hamming(a: NDArray[np.uint64], b: NDArray[np.uint64]) -> NDArray[np.uint8]:
    """Element-wise number of differing bits of two uint64 arrays."""
    return popcount(np.bitwise_xor(a, b))


def census_cost_volume(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    num_disparities: int,
    *,
    min_disparity: int = 0,
    window: tuple[int, int] = CENSUS_WINDOW,
) -> NDArray[np.uint8]:
    """Census (Hamming) matching cost of the left image against the right one.

    ``C[v, u, k]`` is the Hamming distance between the census strings of
    left ``(u, v)`` and right ``(u - d, v)`` with ``d = min_disparity + k``,
    bits; ``census_bits(window)`` where ``u - d`` is outside the image.

    Args:
        left: HxW grey (or HxWx3 RGB uint8) left image.
        right: right image of the same shape.
        num_disparities: number of disparities ``D``.
        min_disparity: disparity of ``k = 0``, pixels.
        window: census window ``(height, width)``.

    Returns:
        HxWxD uint8 costs, bits.
    """
    if num_disparities < 1:
        raise MatcherError(f"num_disparities must be >= 1, got {num_disparities}")
    census_left = census_transform(left, window)
    census_right = census_transform(right, window)
    if census_left.shape != census_right.shape:
        raise MatcherError(f"left image {census_left.shape} and right image {census_right.shape} differ in size")
    return np.asarray(
        _hamming_volume_kernel(
            census_left,
            np.ascontiguousarray(census_right[:, ::-1]),
            int(num_disparities),
            int(min_disparity),
            census_bits(window),
        )
    )


@dataclass(frozen=True, eq=False)
class WindowedCensusCosts:
    """Census costs summed over a square window, kept as the two census images (the volume is never stored).

    ``costs[v, u, k]`` is the sum over the ``(2 radius + 1)``-square window
    around ``(u, v)`` (border pixels repeated) of the Hamming distance of
    left ``(x, y)`` and right ``(x - min_disparity - k, y)``; ``worst`` bits
    where that right pixel leaves the image. :meth:`volume` materialises it
    (H x W x D uint16, bits); the confidence kernels instead compute it a few
    rows at a time and reduce each row at once
    (:func:`selfcontra_ros.confidence.kernels.curve_statistics`), so that
    no H x W x D array exists at all.

    Attributes:
        census_left: HxW uint64 left census strings.
        right_reversed: HxW uint64 right census strings, mirrored left-right (the kernels' layout).
        num_disparities: ``D``.
        min_disparity: disparity of ``k = 0``, pixels.
        radius: window radius, pixels (0..7).
        worst: cost of one pixel pair without a right pixel, bits (the census string length).
    """

    census_left: NDArray[np.uint64]
    right_reversed: NDArray[np.uint64]
    num_disparities: int
    min_disparity: int
    radius: int
    worst: int

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(H, W, D)`` of the volume."""
        height, width = self.census_left.shape
        return (int(height), int(width), int(self.num_disparities))

    @property
    def dtype(self) -> np.dtype[np.uint16]:
        """The volume's dtype (uint16)."""
        return np.dtype(np.uint16)

    @property
    def max_cost(self) -> int:
        """Largest possible summed cost, bits: ``worst`` times the window area."""
        return int(self.worst * (2 * self.radius + 1) ** 2)

    def bands(self) -> int:
        """Number of row bands of the compiled passes: a few per numba thread, to balance the work."""
        return max(1, min(self.shape[0], 4 * numba.get_num_threads()))

    def volume(self) -> NDArray[np.uint16]:
        """The H x W x D uint16 summed costs, bits (one compiled pass, bands of rows, no raw volume)."""
        return np.asarray(
            _windowed_hamming_kernel(
                self.census_left,
                self.right_reversed,
                int(self.num_disparities),
                int(self.min_disparity),
                int(self.worst),
                int(self.radius),
                self.bands(),
            )
        )


def windowed_census_costs(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    num_disparities: int,
    radius: int,
    *,
    min_disparity: int = 0,
    window: tuple[int, int] = CENSUS_WINDOW,
) -> WindowedCensusCosts:
    """Census transforms of a pair, ready for window-summed costs (:class:`WindowedCensusCosts`).

    Args:
        left: HxW grey (or HxWx3 RGB uint8) left image.
        right: right image of the same shape.
        num_disparities: number of disparities ``D``.
        radius: window radius, pixels, 0 to 7 (sums must fit uint16).
        min_disparity: disparity of ``k = 0``, pixels.
        window: census window ``(height, width)``.

    Raises:
        MatcherError: no disparity, a radius outside 0..7 or images of different sizes.
    """
    if num_disparities < 1:
        raise MatcherError(f"num_disparities must be >= 1, got {num_disparities}")
    if not 0 <= radius <= 7:
        raise MatcherError(f"aggregation radius must be 0..7 (uint16 sums of census bits), got {radius}")
    census_left = census_transform(left, window)
    census_right = census_transform(right, window)
    if census_left.shape != census_right.shape:
        raise MatcherError(f"left image {census_left.shape} and right image {census_right.shape} differ in size")
    return WindowedCensusCosts(
        census_left=census_left,
        right_reversed=np.ascontiguousarray(census_right[:, ::-1]),
        num_disparities=int(num_disparities),
        min_disparity=int(min_disparity),
        radius=int(radius),
        worst=census_bits(window),
    )


def census_window_cost_volume(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    num_disparities: int,
    radius: int,
    *,
    min_disparity: int = 0,
    window: tuple[int, int] = CENSUS_WINDOW,
) -> NDArray[np.uint16]:
    """Census costs summed over a ``(2 radius + 1)``-square window (``box_cost_volume`` of ``census_cost_volume``).

    Computed in one compiled pass (bands of rows, each keeping its window's
    raw rows), without the intermediate HxWxD raw volume; arguments as
    :func:`windowed_census_costs`.

    Returns:
        HxWxD uint16 summed costs, bits.
    """
    return windowed_census_costs(
        left, right, num_disparities, radius, min_disparity=min_disparity, window=window
    ).volume()


def box_cost_volume(volume: NDArray[np.integer], radius: int) -> NDArray[np.uint16]:
    """Sum a cost volume over a ``(2 radius + 1)``-square window of each disparity slice.

    Window pixels outside the image repeat the border (so every pixel sums
    the same number of costs). Used for an aggregated census cost of query
    algorithms that expose none of their own.

    Args:
        volume: HxWxD non-negative integer costs (uint8 census bits, or any
            integer type whose window sums fit uint16).
        radius: window radius, pixels (0 = no sum).

    Returns:
        HxWxD uint16 summed costs, same units as ``volume``.

    Raises:
        MatcherError: negative radius, not HxWxD, or sums that could overflow uint16.
    """
    if radius < 0:
        raise MatcherError(f"aggregation radius must be >= 0, got {radius}")
    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise MatcherError(f"cost volume must be HxWxD, got shape {vol.shape}")
    if radius == 0:
        return vol.astype(np.uint16)
    area = (2 * radius + 1) ** 2
    if vol.dtype != np.uint8:
        # Other integer volumes are summed as uint16 when every window sum fits.
        if vol.dtype.kind not in "iu" or (vol.size and (vol.min() < 0 or int(vol.max()) * area > 65535)):
            raise MatcherError(
                f"box_cost_volume needs non-negative integer costs whose {area}-pixel sums fit uint16, "
                f"got {vol.dtype} up to {vol.max() if vol.size else 0}"
            )
        vol = vol.astype(np.uint16)
    elif area * 255 > 65535:
        raise MatcherError(f"aggregation radius {radius} could overflow uint16 sums of uint8 costs; at most 7")
    return np.asarray(_box_sum_kernel(np.ascontiguousarray(vol), int(radius)))


def right_cost_volume(volume: NDArray[np.generic], min_disparity: int = 0) -> NDArray[np.generic]:
    """Re-index a left cost volume for the right image: ``C_R[v, u, k] = C_L[v, u + d, k]``, ``d = min_disparity + k``.

    Right pixel ``(u, v)`` with disparity ``d`` matches left ``(u + d, v)``.
    Where ``u + d`` leaves the image the cost is the volume's maximum.

    Returns:
        HxWxD array of the same dtype.
    """
    vol = np.asarray(volume)
    _, width, depth = vol.shape
    out = np.full(vol.shape, vol.max() if vol.size else 0, dtype=vol.dtype)
    for k in range(depth):
        d = min_disparity + k
        lo, hi = max(-d, 0), min(width, width - d)  # right columns u with 0 <= u + d < width
        if lo < hi:
            out[:, lo:hi, k] = vol[:, lo + d : hi + d, k]
    return out


def _scan_rows(cost: NDArray[np.int32], dx: int, reverse: bool, p1: int, p2: int, out: NDArray[np.int32]) -> None:
    """Add one SGM path cost ``L_r`` to ``out``: rows scanned top to bottom (or bottom up), predecessor ``u - dx``.

    ``L_r(p, d) = C(p, d) + min(L(q, d), L(q, d +- 1) + P1, min_k L(q, k) + P2) - min_k L(q, k)``
    with ``q = p - r`` the previous pixel on the path; pixels whose
    predecessor is outside the image start the path (``L_r = C``).
    """
    height, width, depth = cost.shape
    rows = range(height - 1, -1, -1) if reverse else range(height)
    previous: NDArray[np.int32] | None = None
    big = np.int32(1 << 28)
    for v in rows:
        row_cost = cost[v]
        if previous is None:
            current = row_cost.copy()
        else:
            shifted = np.zeros((width, depth), dtype=np.int32)
            if dx > 0:
                shifted[dx:] = previous[:-dx]
            elif dx < 0:
                shifted[:dx] = previous[-dx:]
            else:
                shifted[:] = previous
            # A zero predecessor row gives L = C: the path starts there.
            low = shifted.min(axis=1, keepdims=True)
            best = np.minimum(shifted, low + p2)
            step = np.full((width, depth + 2), big, dtype=np.int32)
            step[:, 1:-1] = shifted + p1
            np.minimum(best, step[:, :-2], out=best)
            np.minimum(best, step[:, 2:], out=best)
            current = row_cost + best - low
        out[v] += current
        previous = current


def aggregate_sgm(
    volume: NDArray[np.integer], *, p1: int = SGM_P1, p2: int = SGM_P2, directions: int = SGM_DIRECTIONS
) -> NDArray[np.uint16]:
    """Semi-global aggregation of a cost volume (Hirschmüller 2008): the sum of the path costs ``L_r``.

    Args:
        volume: HxWxD matching costs (non-negative integers, e.g. census bits).
        p1: penalty of a 1 px disparity change between path neighbours.
        p2: penalty of a larger change; must exceed ``p1``.
        directions: 4 (left/right/up/down) or 8 (plus diagonals).

    Returns:
        HxWxD uint16 aggregated costs ``S = sum_r L_r`` (clipped at 65535).
    """
    if directions not in (4, 8):
        raise MatcherError(f"SGM directions must be 4 or 8, got {directions}")
    if not 0 <= p1 < p2:
        raise MatcherError(f"SGM penalties must satisfy 0 <= P1 < P2, got P1={p1}, P2={p2}")
    cost = np.asarray(volume).astype(np.int32)
    total = np.zeros(cost.shape, dtype=np.int32)
    # Vertical and diagonal paths scan rows; horizontal paths scan rows of the transposed volume.
    row_paths = [(0, False), (0, True)]
    if directions == 8:
        row_paths += [(1, False), (-1, False), (1, True), (-1, True)]
    for dx, reverse in row_paths:
        _scan_rows(cost, dx, reverse, p1, p2, total)
    cost_t = np.ascontiguousarray(cost.transpose(1, 0, 2))
    total_t = np.zeros(cost_t.shape, dtype=np.int32)
    for reverse in (False, True):
        _scan_rows(cost_t, 0, reverse, p1, p2, total_t)
    total += total_t.transpose(1, 0, 2)
    return np.minimum(total, 65535).astype(np.uint16)


def winner_takes_all(volume: NDArray[np.generic], min_disparity: int = 0) -> NDArray[np.float32]:
    """Disparity of the lowest cost per pixel, float32 pixels; 0 (no depth) becomes NaN."""
    disparity = np.argmin(np.asarray(volume), axis=2).astype(np.float32) + np.float32(min_disparity)
    disparity[disparity <= 0] = np.nan
    return disparity


@dataclass
class CensusSGMResult:
    """Census SGM output with its costs.

    Attributes:
        pair: left and right disparity, float32 pixels, NaN invalid.
        costs: HxWxD uint16 aggregated left cost volume ``S[v, u, d]``
            (disparity ``min_disparity + d``), bits summed over the paths.
    """

    pair: DisparityPair
    costs: NDArray[np.uint16]


class CensusSGMMatcher:
    """Census-cost SGM (query algorithm ``"census_sgm"``), the paper's kind of query algorithm.

    Uses ``params.num_disparities`` and ``params.min_disparity``; the
    penalties ``params.p1``/``p2`` when non-zero, else :data:`SGM_P1` /
    :data:`SGM_P2` (bits). Other SGBM fields are ignored. The disparity is
    integer (no sub-pixel refinement) and unfiltered, like the OpenCV
    matchers' raw output. Time at KITTI size with 128 disparities and 8 paths:
    see the package's benchmark (about 15-25 s in numpy on one core).
    """

    def __init__(self, params: MatcherParams | None = None, *, directions: int = SGM_DIRECTIONS) -> None:
        """Create the matcher for ``params`` (default parameters with ``algorithm="census_sgm"`` when ``None``)."""
        self.params = params if params is not None else MatcherParams(algorithm="census_sgm")
        self.directions = directions
        self.p1 = self.params.p1 or SGM_P1
        self.p2 = self.params.p2 or SGM_P2
        if self.p2 <= self.p1:
            raise MatcherError(f"census SGM penalty P2 ({self.p2}) must exceed P1 ({self.p1})")

    def compute_costs(self, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> CensusSGMResult:
        """Match a rectified pair and return both disparities and the aggregated left cost volume.

        The right disparity is the winner of the same aggregated costs
        re-indexed for the right image (:func:`right_cost_volume`).
        """
        validate_pair(left, right)
        lo = self.params.min_disparity
        raw = census_cost_volume(to_grey(left), to_grey(right), self.params.num_disparities, min_disparity=lo)
        costs = aggregate_sgm(raw, p1=self.p1, p2=self.p2, directions=self.directions)
        left_disparity = winner_takes_all(costs, lo)
        right_disparity = winner_takes_all(right_cost_volume(costs, lo), lo)
        return CensusSGMResult(pair=DisparityPair(left=left_disparity, right=right_disparity), costs=costs)

    def compute(self, left: NDArray[np.uint8], right: NDArray[np.uint8], *, with_right: bool = True) -> DisparityPair:
        """Match a rectified pair; see :meth:`selfcontra_ros.matching.base.Matcher.compute`."""
        pair = self.compute_costs(left, right).pair
        return pair if with_right else DisparityPair(left=pair.left)
