"""Compile the package's numba kernels ahead of time, before anything is timed.

Every kernel of :mod:`selfcontra_ros.stages.kernels`,
:mod:`selfcontra_ros.confidence.kernels` and :mod:`selfcontra_ros.matching.census`
is compiled lazily by numba at its first call, for the argument types of
that call, which takes seconds per kernel (about a minute for the labeler's
whole set on a slow or busy machine). The kernels use ``cache=True``, so the
machine code is written to numba's on-disk cache (``__pycache__`` beside the
modules, or ``NUMBA_CACHE_DIR``) and later processes load it instead of
compiling again, as long as they see the same cache folder and CPU settings.

:func:`warm_up` runs the labeling pipeline a node runs with the package
defaults (SGBM query, the three stages, online confidence with its forest)
on a tiny synthetic sequence, so that every kernel gets compiled for the
argument types the node, the bag labeler and the sequence labeler use. A
test suite calls it before it starts labeler processes whose first frames
would otherwise wait for the compiler; a deployment may call it once after
installing, so that the first frames a robot sees are labelled at speed.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

__all__ = ["warm_up"]

# Small, but large enough that the labeler finds positives and negatives to train the forest on.
_WIDTH, _HEIGHT, _FRAMES = 320, 96, 6


def warm_up(feature_sets: Sequence[str] = ("gcp",)) -> float:
    """Compile (or load from numba's on-disk cache) the kernels of labeling and online confidence.

    Runs a :class:`~selfcontra_ros.session.LabelingSession` with an online
    confidence of each feature set over a few synthetic frames (matching,
    Stages 1-3, the LRD map, sample extraction and a retraining), then the
    features and the compiled forest traversal of one frame. The results are
    discarded. Calling it again in the same process costs a few tenths of a
    second; in a new process with a warm on-disk cache, about a second.

    Args:
        feature_sets: confidence feature sets whose measures to compile
            (``gcp`` is the labeler node's default; ``ensemble`` and ``park``
            compile further cost-curve statistics).

    Returns:
        Seconds it took.
    """
    from selfcontra_ros.confidence.features import compute_features
    from selfcontra_ros.confidence.forest import fit_forest
    from selfcontra_ros.confidence.online import ConfidenceParams, OnlineConfidence
    from selfcontra_ros.datasets.synthetic import make_scene
    from selfcontra_ros.labeler import LabelerParams
    from selfcontra_ros.matching.base import MatcherParams
    from selfcontra_ros.session import LabelingSession

    start = time.monotonic()
    scene = make_scene("street", 2, _WIDTH, _HEIGHT, frames=_FRAMES)
    rendered = [scene.render(k) for k in range(_FRAMES)]
    matcher = MatcherParams(num_disparities=64)
    labeler = LabelerParams(window_size=_FRAMES, label_delay=2, flush_incomplete=True)
    for feature_set in feature_sets:
        params = ConfidenceParams(
            feature_set=feature_set, retrain_every=1, samples_per_view=200, n_estimators=2, max_depth=4
        )
        online = OnlineConfidence(params, background=False, log=lambda message: None)
        session = LabelingSession(scene.camera, matcher, labeler, online)
        for k, frame in enumerate(rendered):
            # The first call also compiles the forest path once a view was labelled and a model trained.
            session.process(frame.left, frame.right, scene.pose(k), stamp=0.1 * k, key=k)
        session.flush()
        # The features and the forest of one frame, whether or not the labels above gave a model.
        matched = session.match_frame(rendered[-1].left, rendered[-1].right).frame
        features, _ = compute_features(feature_set, matched.context(with_costs=True))
        labels = np.arange(features.shape[0]) % 2 == 0
        model = fit_forest(features, labels, forest={"n_estimators": 1, "max_depth": 3})
        model.predict(features)
        online.confidence(matched, model)
    return time.monotonic() - start
