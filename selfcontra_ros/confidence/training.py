"""Training samples for the confidence forest: balanced per image, from self-generated or ground-truth labels.

Each image contributes as many positive as negative samples (DESIGN section
5): ``n = min(#positives, #negatives, max_per_class)`` of each, drawn without
replacement from its labelled pixels that have a valid query disparity. An
image with only one class contributes nothing.

:func:`train` is a pure function of its samples and parameters.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.features import FeatureContext, compute_features, feature_names
from selfcontra_ros.confidence.forest import ForestModel, fit_forest
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labels import NEGATIVE, POSITIVE

__all__ = ["Samples", "TrainParams", "balanced_indices", "frame_samples", "merge_samples", "train"]


@dataclass
class Samples:
    """Training samples of one feature set.

    Attributes:
        feature_set: name of the feature set (``ensemble``, ``gcp``, ``park``).
        features: (N, F) float32 features.
        labels: (N,) bool, True = positive (correct disparity).
        frames: number of images that contributed.
    """

    feature_set: str
    features: NDArray[np.float32]
    labels: NDArray[np.bool_]
    frames: int = 0


@dataclass(frozen=True)
class TrainParams:
    """Forest and metadata of a training run.

    Attributes:
        forest: overrides of :data:`~selfcontra_ros.confidence.constants.FOREST`.
        n_jobs: scikit-learn worker count.
        metadata: extra JSON-serialisable facts stored with the model (sources, query algorithm).
    """

    forest: dict[str, Any] = field(default_factory=dict)
    n_jobs: int | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


def balanced_indices(labels: NDArray[np.integer], max_per_class: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices of an equal number of POSITIVE and NEGATIVE entries of ``labels`` (others ignored).

    ``n = min(#positive, #negative, max_per_class)`` of each class, drawn
    without replacement; sorted. Empty when a class is missing.
    """
    labels = np.asarray(labels)
    positive = np.flatnonzero(labels == POSITIVE)
    negative = np.flatnonzero(labels == NEGATIVE)
    n = min(positive.size, negative.size, int(max_per_class))
    if n <= 0:
        return np.zeros(0, dtype=np.int64)
    chosen = np.concatenate([rng.choice(positive, n, replace=False), rng.choice(negative, n, replace=False)])
    return np.sort(chosen).astype(np.int64)


def frame_samples(
    feature_set: str,
    ctx: FeatureContext,
    label_image: NDArray[np.integer],
    rng: np.random.Generator,
    *,
    max_per_class: int = int(constants.TRAINING["max_per_class"]),
) -> Samples:
    """Balanced samples of one image: features only for the chosen pixels' image, labels from ``label_image``.

    Args:
        feature_set: feature set to compute.
        ctx: feature context of the image's query disparity.
        label_image: HxW codes (0 unknown, 1 positive, 2 negative).
        rng: random generator of the draw.
        max_per_class: cap on the samples per class.
    """
    label_image = np.asarray(label_image)
    if label_image.shape != ctx.shape:
        raise SelfContraError(f"label image {label_image.shape} does not match the disparity map {ctx.shape}")
    at_valid = label_image[ctx.rows, ctx.cols]
    chosen = balanced_indices(at_valid, max_per_class, rng)
    width = len(feature_names(feature_set))
    if chosen.size == 0:
        return Samples(feature_set, np.zeros((0, width), np.float32), np.zeros(0, bool), frames=0)
    features, _ = compute_features(feature_set, ctx)
    return Samples(feature_set, features[chosen], at_valid[chosen] == POSITIVE, frames=1)


def merge_samples(parts: Iterable[Samples]) -> Samples:
    """Concatenate samples of one feature set."""
    parts = list(parts)
    if not parts:
        raise SelfContraError("no training samples")
    names = {p.feature_set for p in parts}
    if len(names) != 1:
        raise SelfContraError(f"cannot merge samples of different feature sets {sorted(names)}")
    return Samples(
        feature_set=parts[0].feature_set,
        features=np.concatenate([p.features for p in parts]).astype(np.float32),
        labels=np.concatenate([p.labels for p in parts]).astype(bool),
        frames=sum(p.frames for p in parts),
    )


def train(samples: Samples, params: TrainParams | None = None) -> ForestModel:
    """Train the confidence forest on ``samples`` (pure: same samples and parameters give the same model).

    Raises:
        SelfContraError: without samples of both classes.
    """
    params = params if params is not None else TrainParams()
    if samples.labels.size == 0:
        raise SelfContraError(f"no labelled training samples for feature set {samples.feature_set!r}")
    metadata = {
        **params.metadata,
        "feature_set": samples.feature_set,
        "feature_names": feature_names(samples.feature_set),
        "constants_version": constants.VERSION,
        "training_samples": int(samples.labels.size),
        "training_frames": int(samples.frames),
        "training_positive_share": float(samples.labels.mean()),
    }
    return fit_forest(samples.features, samples.labels, metadata, n_jobs=params.n_jobs, forest=params.forest)
