"""Confidence speed against the query algorithm's own speed, at KITTI resolution.

Renders a few frames of the synthetic street (1226x370), runs OpenCV
StereoSGBM (the package's default query algorithm, with the right disparity
the left-right measures need) and then, on the same frames, the confidence
of the newest frame as the labeler node computes it: the census costs
(matching costs of the cost-curve measures), feature extraction and forest
inference.

**Which forest.** By default the node's online forest, shaped by the
defaults of :class:`~selfcontra_ros.confidence.online.ConfidenceParams`
(``config/labeler.yaml``, section ``confidence``: at the time of writing 10
trees, depth 12, min leaf 20), and the node's feature set
(``ConfidenceParams().feature_set``, ``gcp``). ``--forest paper`` times the
paper's forest (:data:`~selfcontra_ros.confidence.constants.FOREST`: 20
trees, depth 20, min leaf 100) instead. The other forest is timed on the same
features too (one more prediction per frame) and reported as
``other_forest_ms`` / ``other_ratio``. Both are trained once beforehand on
ground-truth labels of a separate frame (40000 balanced samples); training is
not timed.

The compiled kernels (numba) are compiled or loaded from their on-disk cache
on first use; one untimed warm-up pass over the training frame takes that
cost, reported as ``first_call_ms``. The timed frames measure the per-frame
cost only. The machine's 1-minute load average is reported too (``load``):
on a shared 2-core machine a load above 2 slows everything, SGBM included,
but not necessarily in the same proportion.

Prints per frame the split, then one JSON line::

    {"sgbm_ms": ..., "confidence_ms": ..., "ratio": ..., "features": "gcp", "forest": "online",
     "costs_ms": ..., "features_ms": ..., "forest_ms": ..., "other_forest": "paper",
     "other_forest_ms": ..., "other_ratio": ..., "census_sgm_ms": ..., "first_call_ms": ...,
     "pixels": ..., "load": ...}

``confidence_ms = costs_ms + features_ms + forest_ms`` per frame (means over
the frames); ``ratio = confidence_ms / sgbm_ms``; ``other_ratio`` the same
with the other forest. ``costs_ms`` is the census transforms only: the
window-summed census costs are computed row by row inside the cost-curve
statistics (part of ``features_ms``), never stored as a volume.
``census_sgm_ms`` (the census SGM query algorithm with its right disparity,
once) is given for reference (``--no-census-sgm`` skips it); ``pixels`` is
the mean number of valid pixels (the only ones that get features and a
forest prediction).

Usage: ``python bench/confidence_speed.py [--features ensemble|gcp|park] [--forest online|paper] [--frames F]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from typing import Any

import numpy as np

from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.features import FeatureContext, compute_features
from selfcontra_ros.confidence.forest import ForestModel
from selfcontra_ros.confidence.inputs import feature_input
from selfcontra_ros.confidence.online import ConfidenceParams
from selfcontra_ros.confidence.training import Samples, TrainParams, frame_samples, train
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.matching.base import MatcherParams, make_matcher


def forest_shapes() -> dict[str, dict[str, Any]]:
    """Forest parameters by name: the node's online forest (``ConfidenceParams`` defaults) and the paper's."""
    return {"online": ConfidenceParams().forest(), "paper": dict(constants.FOREST)}


def main() -> None:
    """Run the benchmark and print the JSON line."""
    defaults = ConfidenceParams()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--features", default=defaults.feature_set, choices=tuple(constants.FEATURE_SETS))
    parser.add_argument("--forest", default="online", choices=("online", "paper"))
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--no-census-sgm", action="store_true", help="skip the census SGM reference timing")
    args = parser.parse_args()
    from selfcontra_ros.evaluation.metrics import ground_truth_labels

    scene = make_scene("street", seed=7, frames=args.frames + 1)
    params = MatcherParams()
    sgbm = make_matcher(params)

    # Both forests, trained on a frame that is not timed.
    train_frame = scene.render(0)
    train_pair = sgbm.compute(train_frame.left, train_frame.right, with_right=True)
    ctx = FeatureContext(feature_input(train_frame.left, train_frame.right, train_pair, params))
    labels = ground_truth_labels(train_pair.left, train_frame.disparity)
    samples: Samples = frame_samples(args.features, ctx, labels, np.random.default_rng(0), max_per_class=20000)
    models: dict[str, ForestModel] = {
        name: train(samples, TrainParams(forest=shape, n_jobs=2)) for name, shape in forest_shapes().items()
    }
    other = "paper" if args.forest == "online" else "online"
    for name, model in models.items():
        shape = model.metadata["forest"]
        print(
            f"{name} forest: {shape['n_estimators']} trees, depth {shape['max_depth']}, "
            f"min leaf {shape['min_samples_leaf']}, {model.children_left.size} nodes",
            flush=True,
        )

    # Warm-up: the first call compiles (or loads from the cache) every kernel; not per-frame time.
    t0 = time.perf_counter()
    warm, _ = compute_features(args.features, feature_input(train_frame.left, train_frame.right, train_pair, params))
    for model in models.values():
        model.predict(warm)
    first_call_ms = 1e3 * (time.perf_counter() - t0)
    print(f"first call (kernel compilation or cache load included): {first_call_ms:.0f} ms", flush=True)

    sgbm_ms, costs_ms, features_ms, forest_ms, other_ms, pixels = [], [], [], [], [], []
    for k in range(1, args.frames + 1):
        frame = scene.render(k)
        t0 = time.perf_counter()
        pair = sgbm.compute(frame.left, frame.right, with_right=True)
        t1 = time.perf_counter()
        data = feature_input(frame.left, frame.right, pair, params)
        t2 = time.perf_counter()
        features, ctx = compute_features(args.features, data)
        t3 = time.perf_counter()
        models[args.forest].predict(features)
        t4 = time.perf_counter()
        models[other].predict(features)
        t5 = time.perf_counter()
        sgbm_ms.append(1e3 * (t1 - t0))
        costs_ms.append(1e3 * (t2 - t1))
        features_ms.append(1e3 * (t3 - t2))
        forest_ms.append(1e3 * (t4 - t3))
        other_ms.append(1e3 * (t5 - t4))
        pixels.append(ctx.count)
        print(
            f"frame {k}: sgbm {sgbm_ms[-1]:.0f} ms, census {costs_ms[-1]:.0f} ms, "
            f"features {features_ms[-1]:.0f} ms, {args.forest} forest {forest_ms[-1]:.0f} ms "
            f"({other} forest {other_ms[-1]:.0f} ms), {ctx.count} pixels",
            flush=True,
        )
    census_ms = None
    if not args.no_census_sgm:
        frame = scene.render(1)
        census = make_matcher(replace(params, algorithm="census_sgm"))
        t0 = time.perf_counter()
        census.compute(frame.left, frame.right)
        census_ms = round(1e3 * (time.perf_counter() - t0), 1)

    sgbm_mean = float(np.mean(sgbm_ms))
    shared = float(np.mean(costs_ms) + np.mean(features_ms))
    confidence = shared + float(np.mean(forest_ms))
    print(
        json.dumps(
            {
                "sgbm_ms": round(sgbm_mean, 1),
                "confidence_ms": round(confidence, 1),
                "ratio": round(confidence / sgbm_mean, 2),
                "features": args.features,
                "forest": args.forest,
                "costs_ms": round(float(np.mean(costs_ms)), 1),
                "features_ms": round(float(np.mean(features_ms)), 1),
                "forest_ms": round(float(np.mean(forest_ms)), 1),
                "other_forest": other,
                "other_forest_ms": round(float(np.mean(other_ms)), 1),
                "other_ratio": round((shared + float(np.mean(other_ms))) / sgbm_mean, 2),
                "census_sgm_ms": census_ms,
                "first_call_ms": round(first_call_ms, 1),
                "pixels": round(float(np.mean(pixels))),
                "load": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
