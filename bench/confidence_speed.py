"""Confidence speed against the query algorithm's own speed, at KITTI resolution.

Renders a few frames of the synthetic street (1226x370), runs OpenCV
StereoSGBM (the package's default query algorithm, with the right disparity
the left-right measures need) and then, on the same frames, the confidence
pipeline of one feature set: the census cost volume (matching costs for the
cost-curve measures), feature extraction and forest inference. The forest is
the paper's (20 trees, depth 20, min leaf 100), trained once beforehand on
ground-truth labels of a separate frame; its training is not timed.

Prints per frame the split, then one JSON line::

    {"sgbm_ms": ..., "confidence_ms": ..., "ratio": ..., "features": "ensemble",
     "costs_ms": ..., "features_ms": ..., "forest_ms": ..., "census_sgm_ms": ...}

``confidence_ms = costs_ms + features_ms + forest_ms`` per frame;
``ratio = confidence_ms / sgbm_ms``. ``census_sgm_ms`` (the census SGM query
algorithm with its right disparity, once) is given for reference.

Usage: ``python bench/confidence_speed.py [--features ensemble|gcp|park] [--frames F]``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from selfcontra_ros.confidence.features import FeatureContext, compute_features
from selfcontra_ros.confidence.inputs import feature_input
from selfcontra_ros.confidence.training import Samples, TrainParams, frame_samples, train
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.evaluation.metrics import ground_truth_labels
from selfcontra_ros.matching.base import MatcherParams, make_matcher


def main() -> None:
    """Run the benchmark and print the JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--features", default="ensemble", choices=("ensemble", "gcp", "park"))
    parser.add_argument("--frames", type=int, default=3)
    args = parser.parse_args()

    scene = make_scene("street", seed=7, frames=args.frames + 1)
    params = MatcherParams()
    sgbm = make_matcher(params)

    # A forest of the paper's shape, trained on a frame that is not timed.
    train_frame = scene.render(0)
    train_pair = sgbm.compute(train_frame.left, train_frame.right, with_right=True)
    ctx = FeatureContext(feature_input(train_frame.left, train_frame.right, train_pair, params))
    labels = ground_truth_labels(train_pair.left, train_frame.disparity)
    samples: Samples = frame_samples(args.features, ctx, labels, np.random.default_rng(0), max_per_class=20000)
    model = train(samples, TrainParams(n_jobs=2))

    sgbm_ms, costs_ms, features_ms, forest_ms = [], [], [], []
    for k in range(1, args.frames + 1):
        frame = scene.render(k)
        t0 = time.perf_counter()
        pair = sgbm.compute(frame.left, frame.right, with_right=True)
        t1 = time.perf_counter()
        data = feature_input(frame.left, frame.right, pair, params)
        t2 = time.perf_counter()
        features, ctx = compute_features(args.features, data)
        t3 = time.perf_counter()
        model.predict(features)
        t4 = time.perf_counter()
        sgbm_ms.append(1e3 * (t1 - t0))
        costs_ms.append(1e3 * (t2 - t1))
        features_ms.append(1e3 * (t3 - t2))
        forest_ms.append(1e3 * (t4 - t3))
        print(
            f"frame {k}: sgbm {sgbm_ms[-1]:.0f} ms, census costs {costs_ms[-1]:.0f} ms, "
            f"features {features_ms[-1]:.0f} ms, forest {forest_ms[-1]:.0f} ms ({ctx.count} pixels)",
            flush=True,
        )
    frame = scene.render(1)
    census = make_matcher(replace(params, algorithm="census_sgm"))
    t0 = time.perf_counter()
    census.compute(frame.left, frame.right)
    census_ms = 1e3 * (time.perf_counter() - t0)

    sgbm_mean = float(np.mean(sgbm_ms))
    confidence = float(np.mean(costs_ms) + np.mean(features_ms) + np.mean(forest_ms))
    print(
        json.dumps(
            {
                "sgbm_ms": round(sgbm_mean, 1),
                "confidence_ms": round(confidence, 1),
                "ratio": round(confidence / sgbm_mean, 2),
                "features": args.features,
                "costs_ms": round(float(np.mean(costs_ms)), 1),
                "features_ms": round(float(np.mean(features_ms)), 1),
                "forest_ms": round(float(np.mean(forest_ms)), 1),
                "census_sgm_ms": round(census_ms, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
