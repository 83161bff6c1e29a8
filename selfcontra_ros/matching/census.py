"""Census matching costs and a census-cost semi-global matcher (SGM), all in vectorised numpy.

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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.matching.base import DisparityPair, MatcherError, MatcherParams, to_grey, validate_pair

__all__ = [
    "CENSUS_WINDOW",
    "SGM_DIRECTIONS",
    "SGM_P1",
    "SGM_P2",
    "CensusSGMMatcher",
    "CensusSGMResult",
    "aggregate_sgm",
    "box_cost_volume",
    "census_bits",
    "census_cost_volume",
    "census_transform",
    "hamming",
    "right_cost_volume",
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
    img = img.astype(np.float32)
    ry, rx = h_win // 2, w_win // 2
    padded = np.pad(img, ((ry, ry), (rx, rx)), mode="edge")
    height, width = img.shape
    out = np.zeros((height, width), dtype=np.uint64)
    bit = 0
    for dy in range(h_win):
        for dx in range(w_win):
            if dy == ry and dx == rx:
                continue
            darker = padded[dy : dy + height, dx : dx + width] < img
            out |= darker.astype(np.uint64) << np.uint64(bit)
            bit += 1
    return out


def hamming(a: NDArray[np.uint64], b: NDArray[np.uint64]) -> NDArray[np.uint8]:
    """Element-wise number of differing bits of two uint64 arrays."""
    x = np.bitwise_xor(a, b)
    if hasattr(np, "bitwise_count"):
        return np.asarray(np.bitwise_count(x), dtype=np.uint8)
    as_bytes = x.view(np.uint8).reshape(*x.shape, 8)
    return np.asarray(_POPCOUNT8[as_bytes].sum(axis=-1), dtype=np.uint8)


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
    height, width = census_left.shape
    volume = np.full((height, width, num_disparities), census_bits(window), dtype=np.uint8)
    for k in range(num_disparities):
        d = min_disparity + k
        lo, hi = max(d, 0), min(width, width + d)  # left columns u with 0 <= u - d < width
        if lo < hi:
            volume[:, lo:hi, k] = hamming(census_left[:, lo:hi], census_right[:, lo - d : hi - d])
    return volume


def box_cost_volume(volume: NDArray[np.integer], radius: int) -> NDArray[np.uint16]:
    """Sum a cost volume over a ``(2 radius + 1)``-square window of each disparity slice.

    Window pixels outside the image repeat the border (so every pixel sums
    the same number of costs). Used for an aggregated census cost of query
    algorithms that expose none of their own.

    Returns:
        HxWxD uint16 summed costs, same units as ``volume``.
    """
    import cv2

    if radius < 0:
        raise MatcherError(f"aggregation radius must be >= 0, got {radius}")
    vol = np.asarray(volume)
    if radius == 0:
        return vol.astype(np.uint16)
    size = 2 * radius + 1
    height, width, depth = vol.shape
    # OpenCV filters at most 512 channels at once; the disparity axis is the channel axis.
    flat = vol.astype(np.float32)
    out = np.empty(vol.shape, dtype=np.uint16)
    for start in range(0, depth, 512):
        chunk = np.ascontiguousarray(flat[:, :, start : start + 512])
        summed = cv2.boxFilter(chunk, -1, (size, size), normalize=False, borderType=cv2.BORDER_REPLICATE)
        out[:, :, start : start + 512] = np.rint(summed.reshape(height, width, -1)).astype(np.uint16)
    return out


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
