"""Confidence measures behind one registry, and the feature sets built from them (DESIGN section 5).

A measure is one class: subclass :class:`Measure`, give it a ``name``,
implement :meth:`Measure.compute` and decorate it with :func:`register`. A
feature set (:data:`~selfcontra_ros.confidence.constants.FEATURE_SETS`) lists
measures by name with their keyword arguments.

Every measure returns one value per *valid* pixel of the query disparity map
(finite, > 0 and inside the cost volume's disparity range), in the row-major
order of :attr:`FeatureContext.rows` / :attr:`FeatureContext.cols`. Invalid
pixels never get features; window measures ignore them (averages over the
valid pixels of the window).

Notation (all per valid pixel ``p = (u, v)``): ``c(d)`` is the cost curve,
the cost volume at ``p`` divided by :attr:`FeatureInput.cost_scale`
(normalised cost, lower = better match); ``d1 = argmin c`` and ``c1 = c(d1)``;
``c2`` the second smallest value of the curve (the "naive" second cost);
``c2m`` the smallest *local* minimum other than ``d1`` (the curve maximum when
there is none) at disparity ``d2m``; ``dq`` the query disparity rounded to
the volume's grid, ``cq = c(dq)``; ``D`` the disparity range; ``eps`` =
:data:`~selfcontra_ros.confidence.constants.COST_EPS`. The query disparity map
is ``d``, the right one ``d_R``. Every measure is written so that the forest
can use it as is; the signs follow the usual published ones (e.g. matching
score is ``-cq``, larger = more confident for most measures, and larger =
less confident for left-right consistency, variance, deviation and energy).

Speed: every cost-curve statistic (``d1``, ``c1``, ``c2``, ``c2m``, the
exponential sums, the right-image minimum, ...) comes from one compiled pass
(:func:`~selfcontra_ros.confidence.kernels.curve_statistics`) that reads each
valid pixel's curve once and computes everything the feature set asks for
(each measure declares its :attr:`Measure.curve_request`;
:func:`compute_features` gathers them before the first is read). With the
package's window-summed census costs
(:class:`~selfcontra_ros.matching.census.WindowedCensusCosts`) that pass sums
the census costs a few image rows at a time and reduces each row at once: no
HxWxD volume is ever stored, and rows without a valid pixel are not summed.
The other maps are a few OpenCV filters over the image.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence import constants, kernels
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.matching.census import WindowedCensusCosts

__all__ = [
    "FeatureContext",
    "FeatureInput",
    "Measure",
    "compute_features",
    "feature_names",
    "feature_set",
    "lrd_confidence",
    "measure_names",
    "register",
]

F32 = NDArray[np.float32]


@dataclass
class FeatureInput:
    """What the measures read for one stereo pair.

    Attributes:
        left: HxW grey left image (uint8 or float).
        right: HxW grey right image.
        disparity: HxW float32 left query disparity, pixels, NaN invalid.
        disparity_right: HxW float32 right disparity, pixels, NaN invalid; None when unknown.
        costs: HxWxD cost volume of the left image, ``costs[v, u, k]`` the cost
            of disparity ``min_disparity + k`` (lower = better); or window-summed
            census costs, which the measures reduce without storing the volume.
        cost_scale: divisor turning costs into normalised costs (about 1 = worst match).
        min_disparity: disparity of ``costs[..., 0]``, pixels.
    """

    left: NDArray[np.generic]
    right: NDArray[np.generic]
    disparity: F32
    disparity_right: F32 | None
    costs: NDArray[np.generic] | WindowedCensusCosts
    cost_scale: float
    min_disparity: int = 0

    def __post_init__(self) -> None:
        """Check shapes; raises SelfContraError naming the mismatched input."""
        shape = np.shape(self.disparity)
        if len(shape) != 2:
            raise SelfContraError(f"FeatureInput.disparity must be HxW, got shape {shape}")
        for name in ("left", "right", "disparity_right"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != shape:
                raise SelfContraError(f"FeatureInput.{name} has shape {np.shape(value)}, the disparity {shape}")
        costs_shape = tuple(self.costs.shape)
        if len(costs_shape) != 3 or costs_shape[:2] != shape:
            raise SelfContraError(f"FeatureInput.costs must be HxWxD with HxW = {shape}, got {costs_shape}")
        if not self.cost_scale > 0:
            raise SelfContraError(f"FeatureInput.cost_scale must be > 0, got {self.cost_scale}")


_MINIMA = kernels.CurveRequest()
_LOCAL = kernels.CurveRequest(local=True)
_RIGHT_MINIMUM = kernels.CurveRequest(right_minimum=True)


def _box_mean(values: F32, weights: F32, window: int) -> F32:
    """Mean of ``values`` over the pixels with weight 1 in a ``window``-square box (NaN where none)."""
    size = (window, window)
    num = cv2.boxFilter(values * weights, cv2.CV_32F, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(weights, cv2.CV_32F, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(num / den, dtype=np.float32)


def _row_filled(disparity: F32, valid: NDArray[np.bool_]) -> F32:
    """Disparity with each invalid pixel replaced by the last valid one to its left in the row (0 before any)."""
    height, width = disparity.shape
    index = np.where(valid, np.arange(width)[None, :], 0)
    np.maximum.accumulate(index, axis=1, out=index)
    filled = disparity[np.arange(height)[:, None], index]
    filled = np.where(valid[np.arange(height)[:, None], index], filled, 0.0)
    return np.asarray(filled, dtype=np.float32)


class FeatureContext:
    """Shared intermediate results of the measures for one :class:`FeatureInput` (computed once, on demand)."""

    def __init__(self, data: FeatureInput) -> None:
        """Select the valid pixels of ``data`` (see the module docstring)."""
        self.data = data
        d = np.asarray(data.disparity, dtype=np.float32)
        self.depth = int(data.costs.shape[2])
        with np.errstate(invalid="ignore"):
            index = np.rint(d) - data.min_disparity
            self.valid = np.isfinite(d) & (d > 0) & (index >= 0) & (index <= self.depth - 1)
        self.rows, self.cols = np.nonzero(self.valid)
        self.d = d[self.rows, self.cols]
        self.dq = np.clip(np.rint(self.d) - data.min_disparity, 0, self.depth - 1).astype(np.int64)
        self._request = _MINIMA
        self._stats: kernels.CurveStatistics | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """HxW image shape."""
        return (int(self.valid.shape[0]), int(self.valid.shape[1]))

    @property
    def count(self) -> int:
        """Number of valid pixels N."""
        return int(self.rows.size)

    # ---------------------------------------------------------------- cost curve

    def prepare(self, request: kernels.CurveRequest) -> None:
        """Ask for cost-curve statistics before the first one is read, so that one pass computes them all.

        :func:`compute_features` prepares its measures' requests
        (:attr:`Measure.curve_request`). A statistic read without being
        prepared costs a further pass over the curves (with windowed census
        costs, over the census volume again).
        """
        self._request = self._request | request

    def _statistics(self, request: kernels.CurveRequest) -> kernels.CurveStatistics:
        """The statistics, computed (in one pass with everything prepared) or completed on first use."""
        # Whatever is prepared comes along: a context reused for a second feature set costs one more pass.
        wanted = self._request | request
        stats = self._stats
        if stats is None:
            stats = self._stats = self._pass(wanted)
            return stats
        missing = kernels.CurveRequest(
            local=wanted.local and stats.c2m is None,
            exp_terms=tuple(
                t for t in wanted.exp_terms if (t[0], t[1]) not in stats.exp or (t[2] and stats.exp[t[:2]][1] is None)
            ),
            right_minimum=wanted.right_minimum and stats.right_minimum is None,
        )
        if missing.local or missing.exp_terms or missing.right_minimum:
            extra = self._pass(missing)
            stats.c2m, stats.d2m, stats.total = (
                (extra.c2m, extra.d2m, extra.total) if missing.local else (stats.c2m, stats.d2m, stats.total)
            )
            stats.exp.update(extra.exp)
            stats.right_minimum = extra.right_minimum if missing.right_minimum else stats.right_minimum
        return stats

    def _pass(self, request: kernels.CurveRequest) -> kernels.CurveStatistics:
        data = self.data
        return kernels.curve_statistics(
            data.costs,
            self.rows,
            self.cols,
            self.dq,
            data.cost_scale,
            min_disparity=data.min_disparity,
            request=request,
        )

    @property
    def d1(self) -> NDArray[np.int64]:
        """(N,) index of the curve minimum (first on ties)."""
        return self._statistics(_MINIMA).d1

    @property
    def c1(self) -> F32:
        """(N,) curve minimum."""
        return self._statistics(_MINIMA).c1

    @property
    def c2(self) -> F32:
        """(N,) second smallest curve value (naive second cost)."""
        return self._statistics(_MINIMA).c2

    @property
    def c2m(self) -> F32:
        """(N,) smallest local minimum other than the global one (curve maximum when none).

        A local minimum is strictly below its left neighbour and not above its
        right one, so that a flat valley counts once.
        """
        value = self._statistics(_LOCAL).c2m
        assert value is not None
        return value

    @property
    def d2m(self) -> NDArray[np.int64]:
        """(N,) index of :attr:`c2m` (``d1`` when there is no second local minimum)."""
        value = self._statistics(_LOCAL).d2m
        assert value is not None
        return value

    @property
    def cq(self) -> F32:
        """(N,) cost at the query disparity."""
        return self._statistics(_MINIMA).cq

    @property
    def curve_sum(self) -> NDArray[np.float64]:
        """(N,) float64 sum of the normalised cost curve."""
        value = self._statistics(_LOCAL).total
        assert value is not None
        return value

    @property
    def curve_neighbours(self) -> tuple[F32, F32]:
        """(N,) costs at ``d1 - 1`` and ``d1 + 1``; at a range end the one neighbour for both."""
        stats = self._statistics(_MINIMA)
        return stats.below, stats.above

    def exp_sums(
        self, rate: float, power: int, *, moment: bool = False
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """``sum_d exp(-e(d))`` and ``sum_d e(d) exp(-e(d))``, ``e(d) = rate (c(d) - c1)^power``.

        See :class:`~selfcontra_ros.confidence.kernels.CurveStatistics`; float64 (N,) each, the second only
        with ``moment``.
        """
        stats = self._statistics(kernels.CurveRequest(exp_terms=((rate, power, moment),)))
        s0, s1 = stats.exp[(rate, power)]
        return s0, (s1 if moment else None)

    @property
    def right_minimum(self) -> F32:
        """(N,) ``min_k c_R(u - d1, k)``: best right-image cost of the right pixel the winner points at.

        ``c_R(x, k) = c_L(x + k, k)`` (same volume re-indexed); entries whose
        left pixel leaves the image are ignored (``c1`` when none is left).
        """
        value = self._statistics(_RIGHT_MINIMUM).right_minimum
        assert value is not None
        return value

    # ---------------------------------------------------------------- maps

    @cached_property
    def valid_f(self) -> F32:
        """HxW float32 1 where the disparity is valid, else 0."""
        return self.valid.astype(np.float32)

    @cached_property
    def disparity_zeroed(self) -> F32:
        """HxW disparity with invalid pixels set to 0."""
        return np.where(self.valid, np.nan_to_num(self.data.disparity, nan=0.0), 0.0).astype(np.float32)

    @cached_property
    def disparity_filled(self) -> F32:
        """HxW disparity with invalid pixels filled from the left (for filters that need every pixel)."""
        return _row_filled(self.disparity_zeroed, self.valid)

    @cached_property
    def grey_left(self) -> F32:
        """HxW float32 left grey levels."""
        return np.asarray(self.data.left, dtype=np.float32)

    @cached_property
    def grey_right(self) -> F32:
        """HxW float32 right grey levels."""
        return np.asarray(self.data.right, dtype=np.float32)

    @cached_property
    def cost_map(self) -> F32:
        """HxW cost at the query disparity, 0 at invalid pixels."""
        out = np.zeros(self.shape, dtype=np.float32)
        out[self.rows, self.cols] = self.cq
        return out

    def at_valid(self, image: NDArray[np.generic]) -> F32:
        """Values of an HxW map at the valid pixels, (N,) float32."""
        return np.asarray(np.asarray(image)[self.rows, self.cols], dtype=np.float32)


class Measure(ABC):
    """A confidence measure: one value per valid pixel.

    Subclasses set ``name`` and implement :meth:`compute`; windowed measures
    take ``window`` (odd side, pixels) as a keyword argument.
    """

    name: ClassVar[str] = ""
    #: Cost-curve statistics the measure reads beyond the minima, prepared before any is computed.
    curve_request: ClassVar[kernels.CurveRequest] = kernels.CurveRequest()

    def __init__(self, **kwargs: Any) -> None:
        """Store keyword arguments (only ``window`` is understood; others raise)."""
        unknown = set(kwargs) - {"window"}
        if unknown:
            raise SelfContraError(f"measure {self.name!r} got unknown arguments {sorted(unknown)}")
        window = kwargs.get("window")
        if window is not None and (not isinstance(window, int) or window < 3 or window % 2 == 0):
            raise SelfContraError(f"measure {self.name!r}: window must be an odd integer >= 3, got {window!r}")
        self.window: int = int(window) if window is not None else 0

    @property
    def label(self) -> str:
        """Column name: ``name`` or ``name@window``."""
        return f"{self.name}@{self.window}" if self.window else self.name

    @abstractmethod
    def compute(self, ctx: FeatureContext) -> F32:
        """Return the (N,) float32 values at the valid pixels of ``ctx``."""


_REGISTRY: dict[str, type[Measure]] = {}


def register(cls: type[Measure]) -> type[Measure]:
    """Class decorator: make a measure available to feature sets under ``cls.name``."""
    if not cls.name or cls.name in _REGISTRY:
        raise SelfContraError(f"measure class {cls.__name__} needs a new, non-empty name (got {cls.name!r})")
    _REGISTRY[cls.name] = cls
    return cls


def measure_names() -> list[str]:
    """Names of the registered measures."""
    return sorted(_REGISTRY)


def make_measure(name: str, kwargs: Mapping[str, Any] | None = None) -> Measure:
    """Instantiate registered measure ``name`` with ``kwargs``."""
    if name not in _REGISTRY:
        raise SelfContraError(f"unknown confidence measure {name!r}; known: {', '.join(measure_names())}")
    return _REGISTRY[name](**dict(kwargs or {}))


# ==================================================================== cost-curve measures

# (rate, power) of the exponential measures' terms e(d) = rate (c(d) - c1)^power.
_MLM_TERM = (1.0 / (2.0 * constants.MLM_SIGMA**2), 1)
_AML_TERM = (1.0 / (2.0 * constants.AML_SIGMA**2), 2)
_PER_TERM = (1.0 / constants.PER_SIGMA**2, 2)
_NEM_TERM = (1.0 / constants.NEM_TEMPERATURE, 1)


@register
class MatchingScore(Measure):
    """MSM: ``-cq``, minus the cost at the query disparity."""

    name = "matching_score"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return -ctx.cq


@register
class PeakRatio(Measure):
    """PKR: ``(c2m + eps) / (c1 + eps)``, second local minimum over the minimum (>= 1)."""

    name = "peak_ratio"
    curve_request = _LOCAL

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return np.asarray((ctx.c2m + constants.COST_EPS) / (ctx.c1 + constants.COST_EPS), dtype=np.float32)


@register
class NaivePeakRatio(Measure):
    """PKRN: ``(c2 + eps) / (c1 + eps)``, second smallest cost over the minimum (>= 1)."""

    name = "naive_peak_ratio"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return np.asarray((ctx.c2 + constants.COST_EPS) / (ctx.c1 + constants.COST_EPS), dtype=np.float32)


@register
class MaximumMargin(Measure):
    """MMN: ``c2 - c1``, margin between the two smallest costs (>= 0)."""

    name = "maximum_margin"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return np.asarray(ctx.c2 - ctx.c1, dtype=np.float32)


@register
class WinnerMargin(Measure):
    """WMN: ``(c2m - c1) / (sum_d c(d) + eps)``, local-minimum margin over the curve's total cost."""

    name = "winner_margin"
    curve_request = _LOCAL

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        total = ctx.curve_sum.astype(np.float32)
        return np.asarray((ctx.c2m - ctx.c1) / (total + constants.COST_EPS), dtype=np.float32)


@register
class MaximumLikelihood(Measure):
    """MLM: ``exp(-c1 / (2 s^2)) / sum_d exp(-c(d) / (2 s^2))``, s = MLM_SIGMA; in (0, 1]."""

    name = "maximum_likelihood"
    curve_request = kernels.CurveRequest(exp_terms=((*_MLM_TERM, False),))

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        # Shifting every cost by c1 leaves the ratio unchanged and keeps the exponentials <= 1.
        total, _ = ctx.exp_sums(*_MLM_TERM)
        return np.asarray(1.0 / total, dtype=np.float32)


@register
class AttainableMaximumLikelihood(Measure):
    """AML: ``1 / sum_d exp(-(c(d) - c1)^2 / (2 s^2))``, s = AML_SIGMA; in (0, 1]."""

    name = "attainable_maximum_likelihood"
    curve_request = kernels.CurveRequest(exp_terms=((*_AML_TERM, False),))

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        total, _ = ctx.exp_sums(*_AML_TERM)
        return np.asarray(1.0 / total, dtype=np.float32)


@register
class Perturbation(Measure):
    """PER: ``sum_{d != d1} exp(-(c1 - c(d))^2 / s^2)``, s = PER_SIGMA; 0 for a sharp unique minimum."""

    name = "perturbation"
    curve_request = kernels.CurveRequest(exp_terms=((*_PER_TERM, False),))

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        total, _ = ctx.exp_sums(*_PER_TERM)
        # The winner's own term is exp(0) = 1.
        return np.asarray(total - 1.0, dtype=np.float32)


@register
class NegativeEntropy(Measure):
    """NEM: ``sum_d p(d) ln p(d)`` with ``p(d) = exp(-c(d)/T) / sum_k exp(-c(k)/T)``, T = NEM_TEMPERATURE.

    Minus the entropy of the curve read as a distribution: 0 for a single
    peak, ``-ln D`` for a flat curve.
    """

    name = "negative_entropy"
    curve_request = kernels.CurveRequest(exp_terms=((*_NEM_TERM, True),))

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        # With e(d) = (c(d) - c1) / T and Z = sum_d exp(-e(d)): ln p(d) = -e(d) - ln Z, so
        # sum_d p ln p = -sum_d e exp(-e) / Z - ln Z (costs shifted by c1 keep every exponential <= 1).
        norm, moment = ctx.exp_sums(*_NEM_TERM, moment=True)
        assert moment is not None
        return np.asarray(-moment / norm - np.log(norm), dtype=np.float32)


@register
class LeftRightDifference(Measure):
    """LRD (Hu & Mordohai): ``(c2 - c1) / (|c1 - min_k c_R(u - d1, k)| + eps)``.

    Large when the minimum is distinct and the right image's best cost at the
    matched pixel agrees with it.
    """

    name = "left_right_difference"
    curve_request = _RIGHT_MINIMUM

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return np.asarray(
            (ctx.c2 - ctx.c1) / (np.abs(ctx.c1 - ctx.right_minimum) + constants.COST_EPS), dtype=np.float32
        )


@register
class Curvature(Measure):
    """CUR: ``c(d1 - 1) + c(d1 + 1) - 2 c1``; at a range end the one neighbour counts twice."""

    name = "curvature"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        below, above = ctx.curve_neighbours
        return np.asarray(below + above - 2.0 * ctx.c1, dtype=np.float32)


@register
class DisparityAmbiguity(Measure):
    """DA: ``|d1 - d2m|``, pixels between the best and the second-best local minimum (0 when unique)."""

    name = "disparity_ambiguity"
    curve_request = _LOCAL

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return np.abs(ctx.d1 - ctx.d2m).astype(np.float32)


# ==================================================================== disparity-map measures


@register
class LeftRightConsistency(Measure):
    """LRC: ``|d(u) - d_R(u - round(d(u)))|``, pixels; LRC_MISSING_PX where ``d_R`` is missing there."""

    name = "left_right_consistency"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        return left_right_consistency(ctx)


def left_right_consistency(ctx: FeatureContext) -> F32:
    """The LRC values of the valid pixels (see :class:`LeftRightConsistency`)."""
    right = ctx.data.disparity_right
    if right is None:
        return np.full(ctx.count, constants.LRC_MISSING_PX, dtype=np.float32)
    x = ctx.cols - np.rint(ctx.d).astype(np.int64)
    inside = x >= 0
    d_right = np.full(ctx.count, np.nan, dtype=np.float32)
    d_right[inside] = np.asarray(right)[ctx.rows[inside], x[inside]]
    diff = np.abs(ctx.d - d_right)
    return np.asarray(np.where(np.isfinite(diff), diff, constants.LRC_MISSING_PX), dtype=np.float32)


@register
class DisparityVariance(Measure):
    """VAR: variance of the valid disparities in a ``window`` square, pixels^2."""

    name = "disparity_variance"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        mean = _box_mean(ctx.disparity_zeroed, ctx.valid_f, self.window)
        mean_sq = _box_mean(ctx.disparity_zeroed**2, ctx.valid_f, self.window)
        return np.maximum(ctx.at_valid(mean_sq - mean**2), 0.0).astype(np.float32)


@register
class MedianDeviation(Measure):
    """MDD: ``|d - median_window(d)|``, pixels.

    The median runs on disparities quantised to MEDIAN_STEP_PX with invalid
    pixels filled from their left neighbour (OpenCV's median needs every
    pixel; uint8 beyond 5x5 windows).
    """

    name = "median_deviation"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        quantised = np.clip(np.rint(ctx.disparity_filled / constants.MEDIAN_STEP_PX), 0, 255).astype(np.uint8)
        median = cv2.medianBlur(quantised, self.window).astype(np.float32) * np.float32(constants.MEDIAN_STEP_PX)
        return np.abs(ctx.d - ctx.at_valid(median)).astype(np.float32)


@register
class DistanceToDiscontinuity(Measure):
    """DDS: Euclidean distance (pixels) to the nearest disparity discontinuity.

    A pixel lies on a discontinuity when a valid 4-neighbour's disparity
    differs by more than DISCONTINUITY_THRESHOLD_PX. Without any discontinuity
    the distance is the image diagonal.
    """

    name = "distance_to_discontinuity"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        d, valid = ctx.disparity_zeroed, ctx.valid
        edge = np.zeros(ctx.shape, dtype=bool)
        jump_x = valid[:, 1:] & valid[:, :-1] & (np.abs(d[:, 1:] - d[:, :-1]) > constants.DISCONTINUITY_THRESHOLD_PX)
        jump_y = valid[1:, :] & valid[:-1, :] & (np.abs(d[1:, :] - d[:-1, :]) > constants.DISCONTINUITY_THRESHOLD_PX)
        edge[:, 1:] |= jump_x
        edge[:, :-1] |= jump_x
        edge[1:, :] |= jump_y
        edge[:-1, :] |= jump_y
        if not edge.any():
            return np.full(ctx.count, float(np.hypot(*ctx.shape)), dtype=np.float32)
        distance = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        # The exact transform's squared distances are integers, but OpenCV's single-threaded path returns some
        # square roots one float32 ulp low, depending on the buffer's alignment. Rounding the square and taking
        # the root again gives the same bits on every machine and thread count.
        squared = np.rint(distance.astype(np.float64) ** 2)
        return ctx.at_valid(np.sqrt(squared).astype(np.float32))


@register
class DistanceToBorder(Measure):
    """DB: ``min(u, v, W - 1 - u, H - 1 - v)``, pixels to the nearest image border."""

    name = "distance_to_border"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        height, width = ctx.shape
        return np.minimum.reduce([ctx.cols, ctx.rows, width - 1 - ctx.cols, height - 1 - ctx.rows]).astype(np.float32)


@register
class SGMEnergy(Measure):
    """Local SGM energy: window mean over valid pixels of ``cq + sum_n P(|d - d_n|)``.

    ``n`` runs over the valid 4-neighbours; ``P`` is 0 for a step below 0.5 px,
    SGM_ENERGY_P1 up to 1.5 px, SGM_ENERGY_P2 beyond (normalised cost units).
    """

    name = "sgm_energy"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        d, valid = ctx.disparity_zeroed, ctx.valid
        energy = ctx.cost_map.copy()

        def penalty(step: F32) -> F32:
            return np.where(
                step < 0.5, 0.0, np.where(step <= 1.5, constants.SGM_ENERGY_P1, constants.SGM_ENERGY_P2)
            ).astype(np.float32)

        pairs_x = valid[:, 1:] & valid[:, :-1]
        pen_x = np.where(pairs_x, penalty(np.abs(d[:, 1:] - d[:, :-1])), 0.0)
        pairs_y = valid[1:, :] & valid[:-1, :]
        pen_y = np.where(pairs_y, penalty(np.abs(d[1:, :] - d[:-1, :])), 0.0)
        energy[:, 1:] += pen_x
        energy[:, :-1] += pen_x
        energy[1:, :] += pen_y
        energy[:-1, :] += pen_y
        return ctx.at_valid(_box_mean(energy, ctx.valid_f, self.window))


@register
class DisparityEntropy(Measure):
    """DE: entropy ``-sum_b q_b ln q_b`` of the valid disparities in a ``window`` square.

    ``q_b`` is the share of the window's valid pixels whose disparity falls in
    bin ``b`` of width ENTROPY_BIN_PX; 0 for a constant window.
    """

    name = "disparity_entropy"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        bins = np.floor(ctx.disparity_zeroed / constants.ENTROPY_BIN_PX).astype(np.int32)
        return ctx.at_valid(kernels.disparity_entropy(bins, ctx.valid, self.window))


# ==================================================================== image measures


def _central_difference_x(image: F32) -> F32:
    grad = np.zeros_like(image)
    grad[:, 1:-1] = 0.5 * (image[:, 2:] - image[:, :-2])
    return grad


def _central_difference_y(image: F32) -> F32:
    grad = np.zeros_like(image)
    grad[1:-1, :] = 0.5 * (image[2:, :] - image[:-2, :])
    return grad


@register
class HorizontalGradient(Measure):
    """HGR: window mean of ``|dI/du|`` of the left image (central difference), grey levels per pixel."""

    name = "horizontal_gradient"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        grad = np.abs(_central_difference_x(ctx.grey_left))
        return ctx.at_valid(cv2.blur(grad, (self.window, self.window), borderType=cv2.BORDER_REFLECT))


@register
class GradientMagnitude(Measure):
    """GRM: window mean of ``sqrt((dI/du)^2 + (dI/dv)^2)`` of the left image, grey levels per pixel."""

    name = "gradient_magnitude"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        grad = np.hypot(_central_difference_x(ctx.grey_left), _central_difference_y(ctx.grey_left))
        return ctx.at_valid(cv2.blur(grad.astype(np.float32), (self.window, self.window)))


@register
class ZeroMeanSAD(Measure):
    """ZSAD: window mean of ``|(I_L - mean I_L) - (I_W - mean I_W)|``, grey levels.

    ``I_W(u, v) = I_R(u - d(u, v), v)`` is the right image warped by the query
    disparity (linear interpolation; invalid pixels take their left valid
    neighbour's disparity), so each window compares the left patch with its
    match under the local disparity field. 0 for a perfect match up to an
    intensity offset.
    """

    name = "zsad"

    def compute(self, ctx: FeatureContext) -> F32:
        """See the class docstring."""
        height, width = ctx.shape
        map_x = (np.arange(width, dtype=np.float32)[None, :] - ctx.disparity_filled).astype(np.float32)
        map_y = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
        warped = cv2.remap(ctx.grey_right, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        size = (self.window, self.window)
        left_zero = ctx.grey_left - cv2.blur(ctx.grey_left, size)
        warped_zero = warped - cv2.blur(warped, size)
        return ctx.at_valid(cv2.blur(np.abs(left_zero - warped_zero).astype(np.float32), size))


# ==================================================================== feature sets


def feature_set(name: str) -> list[Measure]:
    """The measures of feature set ``name`` (``ensemble``, ``gcp`` or ``park``), in column order."""
    if name not in constants.FEATURE_SETS:
        raise SelfContraError(f"unknown feature set {name!r}; expected one of {', '.join(constants.FEATURE_SETS)}")
    return [make_measure(measure, kwargs) for measure, kwargs in constants.FEATURE_SETS[name]]


def feature_names(name: str) -> list[str]:
    """Column names of feature set ``name`` (``measure`` or ``measure@window``)."""
    return [m.label for m in feature_set(name)]


def compute_features(name: str, data: FeatureInput | FeatureContext) -> tuple[F32, FeatureContext]:
    """Compute feature set ``name`` for one stereo pair.

    Returns:
        ``(features, ctx)``: (N, dims) float32 features of the N valid pixels
        ``(ctx.rows, ctx.cols)``, and the context (reusable for other sets).
    """
    ctx = data if isinstance(data, FeatureContext) else FeatureContext(data)
    measures = feature_set(name)
    for measure in measures:
        ctx.prepare(measure.curve_request)
    # Column-major: each measure fills one contiguous column, and the forest reads columns.
    out = np.empty((ctx.count, len(measures)), dtype=np.float32, order="F")
    for j, measure in enumerate(measures):
        out[:, j] = measure.compute(ctx)
    # A non-finite feature would make the forest's comparisons arbitrary; clamp to large finite values.
    np.nan_to_num(out, copy=False, nan=0.0, posinf=1e30, neginf=-1e30)
    return out, ctx


def lrd_confidence(ctx: FeatureContext) -> F32:
    """LRD baseline (no learning): ``-|d(u) - d_R(u - d(u))|`` at the valid pixels (larger = more confident)."""
    return -left_right_consistency(ctx)
