"""Run a query algorithm and gather what the confidence measures read (:class:`FeatureInput`).

Cost-based measures need each pixel's cost curve whatever the query algorithm
(DESIGN section 5): the census SGM hands over its own aggregated costs; every
other algorithm (OpenCV SGBM/BM, an external disparity map) gets the
package's census costs summed over a small window
(:data:`~selfcontra_ros.confidence.constants.AGGREGATION_RADIUS`), handed
over as the two census images (:class:`~selfcontra_ros.matching.census.WindowedCensusCosts`):
the measures sum and reduce them a few rows at a time, so the HxWxD volume is
never stored.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.features import FeatureInput
from selfcontra_ros.matching.base import DisparityPair, Matcher, MatcherParams, to_grey
from selfcontra_ros.matching.census import CensusSGMMatcher, WindowedCensusCosts, census_bits, windowed_census_costs

__all__ = ["census_costs", "feature_input", "query_feature_input"]


def census_costs(
    left: NDArray[np.uint8], right: NDArray[np.uint8], params: MatcherParams
) -> tuple[WindowedCensusCosts, float]:
    """Window-summed census costs over ``params``' disparity range and their normalising scale.

    Returns:
        ``(costs, scale)``: the costs as the two census images
        (:class:`~selfcontra_ros.matching.census.WindowedCensusCosts`: the
        measures sum and reduce them a few rows at a time, so the HxWxD
        uint16 volume, bits summed over the window, is never stored; its
        ``volume()`` builds it when wanted) and the worst possible sum (bits
        x window area).
    """
    radius = constants.AGGREGATION_RADIUS
    costs = windowed_census_costs(
        to_grey(left), to_grey(right), params.num_disparities, radius, min_disparity=params.min_disparity
    )
    side = 2 * radius + 1
    return costs, float(census_bits() * side * side)


def feature_input(
    left: NDArray[np.uint8], right: NDArray[np.uint8], pair: DisparityPair, params: MatcherParams
) -> FeatureInput:
    """Feature input for a disparity pair computed elsewhere (SGBM, BM, external), with census costs."""
    costs, scale = census_costs(left, right, params)
    return FeatureInput(
        left=to_grey(left),
        right=to_grey(right),
        disparity=pair.left,
        disparity_right=pair.right,
        costs=costs,
        cost_scale=scale,
        min_disparity=params.min_disparity,
    )


def query_feature_input(matcher: Matcher, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> FeatureInput:
    """Run ``matcher`` on a rectified pair (with the right disparity) and build its feature input.

    The census SGM contributes its aggregated costs, normalised by the worst
    raw cost times its number of paths; other matchers get :func:`census_costs`.
    """
    if isinstance(matcher, CensusSGMMatcher):
        result = matcher.compute_costs(left, right)
        return FeatureInput(
            left=to_grey(left),
            right=to_grey(right),
            disparity=result.pair.left,
            disparity_right=result.pair.right,
            costs=result.costs,
            cost_scale=float(census_bits() * matcher.directions),
            min_disparity=matcher.params.min_disparity,
        )
    return feature_input(left, right, matcher.compute(left, right, with_right=True), matcher.params)
