"""Every constant of the confidence measures, the feature sets and the forest (DESIGN section 5).

Public implementations of the published measures differ in constants and even
signs; these are the package's own, fixed here and nowhere else. Costs are in
the units of the cost volume handed to the measures (census bits for the
package's volumes, see :mod:`selfcontra_ros.matching.census`), divided by
:data:`COST_NORMALISATION` per pixel so that the exponential measures see
costs of order 1 whatever the aggregation.

A feature set is an ordered list of ``(measure name, keyword arguments)``;
its dimension is the sum of the measures' dimensions (1 each).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

__all__ = [
    "AGGREGATION_RADIUS",
    "AML_SIGMA",
    "COST_EPS",
    "DISCONTINUITY_THRESHOLD_PX",
    "ENSEMBLE",
    "ENTROPY_BIN_PX",
    "FEATURE_SETS",
    "FOREST",
    "GCP",
    "LRC_MISSING_PX",
    "MAX_FOREST_SEED",
    "MEDIAN_STEP_PX",
    "MLM_SIGMA",
    "NEM_TEMPERATURE",
    "PARK",
    "PER_SIGMA",
    "SGM_ENERGY_P1",
    "SGM_ENERGY_P2",
    "TRAINING",
    "VERSION",
]

#: Version of the feature definitions; a model records it and refuses features of another version.
VERSION = 1

#: Radius (pixels) of the square window summing census costs for query algorithms without their own
#: cost volume (SGBM, BM, external): 5x5 window.
AGGREGATION_RADIUS = 2

#: Added to cost denominators (ratios such as the peak ratio), in normalised cost units.
COST_EPS = 1e-3

#: Scale of the maximum-likelihood measure ``exp(-c / (2 sigma^2))``, normalised cost units.
MLM_SIGMA = 0.3
#: Scale of the attainable-maximum-likelihood measure ``exp(-(c - c1)^2 / (2 sigma^2))``.
AML_SIGMA = 0.2
#: Scale of the perturbation measure ``exp(-(c1 - c)^2 / sigma^2)``.
PER_SIGMA = 0.2

#: Temperature of the negative-entropy measure ``p(d) ~ exp(-c(d) / T)``, normalised cost units.
NEM_TEMPERATURE = 0.1

#: Bin width (pixels) of the disparity histogram of the entropy-of-disparities measure.
ENTROPY_BIN_PX = 2.0

#: Median filters work on disparities quantised to this step (pixels); OpenCV's large-window median needs uint8.
MEDIAN_STEP_PX = 0.5

#: Value of the left-right consistency where the right disparity is missing or outside the image:
#: this many pixels (larger than any real disagreement of a 128-disparity search).
LRC_MISSING_PX = 256.0

#: A disparity step larger than this (pixels) between 4-neighbours is a discontinuity.
DISCONTINUITY_THRESHOLD_PX = 2.0

#: Smoothness penalties of the local SGM energy, normalised cost units per neighbour.
SGM_ENERGY_P1 = 0.1
SGM_ENERGY_P2 = 1.0

_Set = tuple[tuple[str, MappingProxyType[str, Any]], ...]


def _set(*members: tuple[str, dict[str, Any]]) -> _Set:
    return tuple((name, MappingProxyType(dict(kwargs))) for name, kwargs in members)


_SCALES = (5, 9, 15, 21)

#: Haeusler et al. 2013 ("Ensemble"), 23 dims: peak ratio, entropy of disparities (4 windows),
#: perturbation, left-right disparity difference, horizontal gradient (4 windows), disparity map
#: variance (4 windows), disparity ambiguity, zero-mean SAD (4 windows), local SGM energy (3 windows).
ENSEMBLE = _set(
    ("peak_ratio", {}),
    *(("disparity_entropy", {"window": w}) for w in _SCALES),
    ("perturbation", {}),
    ("left_right_consistency", {}),
    *(("horizontal_gradient", {"window": w}) for w in _SCALES),
    *(("disparity_variance", {"window": w}) for w in _SCALES),
    ("disparity_ambiguity", {}),
    *(("zsad", {"window": w}) for w in _SCALES),
    *(("sgm_energy", {"window": w}) for w in _SCALES[:3]),
)

#: Spyropoulos et al. 2014 ("GCP"), 8 features.
GCP = _set(
    ("matching_score", {}),
    ("distance_to_border", {}),
    ("maximum_margin", {}),
    ("attainable_maximum_likelihood", {}),
    ("left_right_consistency", {}),
    ("left_right_difference", {}),
    ("distance_to_discontinuity", {}),
    ("median_deviation", {"window": 5}),
)

#: Park & Yoon 2015, 22 dims: ten cost-curve measures, disparity-map measures at three windows,
#: left-right consistency, image gradient magnitude (three windows) and distance to border.
PARK = _set(
    ("peak_ratio", {}),
    ("naive_peak_ratio", {}),
    ("matching_score", {}),
    ("maximum_margin", {}),
    ("winner_margin", {}),
    ("maximum_likelihood", {}),
    ("perturbation", {}),
    ("negative_entropy", {}),
    ("left_right_difference", {}),
    ("curvature", {}),
    *(("disparity_variance", {"window": w}) for w in _SCALES[:3]),
    ("distance_to_discontinuity", {}),
    *(("median_deviation", {"window": w}) for w in _SCALES[:3]),
    ("left_right_consistency", {}),
    *(("gradient_magnitude", {"window": w}) for w in _SCALES[:3]),
    ("distance_to_border", {}),
)

#: Feature-set name -> members.
FEATURE_SETS: MappingProxyType[str, _Set] = MappingProxyType({"ensemble": ENSEMBLE, "gcp": GCP, "park": PARK})

#: Random forest of the paper (DESIGN section 5).
FOREST = MappingProxyType(
    {"n_estimators": 20, "max_depth": 20, "min_samples_leaf": 100, "criterion": "entropy", "random_state": 0}
)

#: Forest seeds (``random_state``) run from 0 to this (scikit-learn's limit); ``selfcontra train --forest-seed``
#: and the label benchmark's forest seeds check against it.
MAX_FOREST_SEED = 2**32 - 1

#: Training-set sampling: at most this many positives (and as many negatives) per image; ``seed`` of the draw;
#: ``band_negatives``: the share of the unlabelled pixels of the query's fattening band that self labels give
#: the draw as negatives (:func:`~selfcontra_ros.confidence.training.band_negatives`; 0 = the paper);
#: ``band_look``: of those, the ones whose look (:func:`~selfcontra_ros.confidence.training.band_look_scores`)
#: is at least this stay out of the draw (``inf``: every one is drawn, as before the look; -1 measured in
#: ``docs/label_quality.md``); ``band_cue``: of those, the ones the band cue
#: (:mod:`~selfcontra_ros.confidence.band_cue`) calls right with at least this probability stay out too
#: (``inf``: off); ``band_texture``: and so do those whose thin strip's texture (the cue's ``strip_texture``,
#: grey levels) is below this (0: off).
TRAINING = MappingProxyType(
    {
        "max_per_class": 10000,
        "seed": 0,
        "band_negatives": 1.0,
        "band_look": float("inf"),
        "band_cue": 0.5,
        "band_texture": 2.0,
    }
)

#: The look of a band pixel (:func:`~selfcontra_ros.confidence.training.band_look_scores`): windows (rows,
#: columns) tried in turn until both sets are large enough, fewest pixels in each set, and the side of the
#: Gaussian that smooths the grey image. A 17x81 window after the 9x49 one scores more pixels and gained
#: 2-3 % on the synthetic scenes but cost 3-4 % on the real pairs (``docs/label_quality.md``): one window.
BAND_LOOK_WINDOWS: tuple[tuple[int, int], ...] = ((9, 49),)
BAND_LOOK_MIN_COUNT: int = 5
BAND_LOOK_SMOOTHING: int = 3
