"""Fit the band cue (:mod:`selfcontra_ros.confidence.band_cue`) on synthetic sequences and report how well it ranks.

For every ``--scenes`` x ``--seeds`` sequence (rendered into ``--cache`` as the label benchmark does) and
every ``--frame-step``-th frame, the query (the package's default matcher) is matched, and the pixels of its
fattening band (the default labeler's) that hold a ground-truth disparity become samples: the band cue's
features, and whether the query's disparity is right (the package's 3 px error rule). The random forest
(:func:`~selfcontra_ros.confidence.forest.fit_forest`, ``--trees`` trees, leaves of at least ``--min-leaf``
samples) is fitted on them and written as a model file (plain arrays, never pickle).

The ``--test-seeds`` sequences are scored and not fitted on (and the ``--real`` pairs, every frame): per set
the rank AUC (wrong pixels against right ones; 0.5 = chance) of the cue and of the look alone (where it is
computed), and the share of band pixels the cue calls right at the training default's threshold and how many
of those are right. ``--score MODEL`` scores a model file instead of fitting one. Examples::

    # the shipped model
    python bench/fit_band_cue.py --scenes orbit street room --seeds 1-5 --test-seeds 6-7 --cache /tmp/lq
    # the shipped model on held-out seeds and the real pairs
    python bench/fit_band_cue.py --score selfcontra_ros/confidence/models/band_cue.npz --test-seeds 61-62 \\
        --cache /tmp/lq --real ../shared/data/kitti_stereo_2015 ../shared/data/middlebury2003
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from selfcontra_ros.cli import parse_seeds, parse_size
from selfcontra_ros.confidence.band_cue import FEATURES, MODEL_FILE, band_cue_features
from selfcontra_ros.confidence.constants import TRAINING
from selfcontra_ros.confidence.forest import ForestModel, fit_forest, load_model, save_model
from selfcontra_ros.confidence.training import band_look_scores, prior_band
from selfcontra_ros.datasets import SCENES
from selfcontra_ros.evaluation.metrics import ground_truth_labels
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE
from selfcontra_ros.matching.base import MatcherParams, make_matcher
from selfcontra_ros.threads import limit_threads

sys.path.insert(0, str(Path(__file__).resolve().parent))
from label_quality import _sequence  # the label benchmark's render cache


def rank_auc(score: NDArray[np.floating], wrong: NDArray[np.bool_]) -> float:
    """Probability that a random wrong pixel scores higher than a random right one (ties count half)."""
    from scipy.stats import rankdata

    ranks = rankdata(score)
    n_wrong, n_right = int(wrong.sum()), int((~wrong).sum())
    if not n_wrong or not n_right:
        return float("nan")
    return float((ranks[wrong].sum() - n_wrong * (n_wrong + 1) / 2) / (n_wrong * n_right))


def band_samples(
    data: Path, frame_step: int, per_frame: int, rng: np.random.Generator
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Band cue features and 'wrong' flags of the band pixels of every ``frame_step``-th frame of ``data``.

    ``data`` is anything ``selfcontra train`` reads with ground truth (a synthetic sequence, a KITTI stereo
    split, a Middlebury folder); with ``frame_step`` 1 every frame counts.
    """
    from selfcontra_ros.confidence.commands import iter_frames

    matcher = make_matcher(MatcherParams())
    labeler = LabelerParams()
    features, wrong = [], []
    for frame in iter_frames(data):
        if (frame_step > 1 and frame.index % frame_step != frame_step // 2) or frame.gt_disparity is None:
            continue
        disparity = matcher.compute(frame.left, frame.right, with_right=False).left
        gt = np.asarray(frame.gt_disparity, dtype=np.float32)
        band = prior_band(disparity, labeler)
        rows, cols = np.nonzero(band & np.isfinite(gt) & (gt > 0))
        if rows.size > per_frame:
            pick = np.sort(rng.choice(rows.size, per_frame, replace=False))
            rows, cols = rows[pick], cols[pick]
        look = band_look_scores(frame.left, disparity, band, rows, cols, jump_px=labeler.stage2_edge_jump_px)
        features.append(band_cue_features(frame.left, frame.right, disparity, rows, cols, look, labeler))
        wrong.append(ground_truth_labels(disparity, gt)[rows, cols] == NEGATIVE)
    if not features:
        return np.zeros((0, len(FEATURES)), np.float32), np.zeros(0, bool)
    return np.concatenate(features), np.concatenate(wrong)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=["orbit", "street", "room"])
    parser.add_argument("--seeds", type=parse_seeds, default=parse_seeds("1-5"), help="sequences fitted on")
    parser.add_argument("--test-seeds", type=parse_seeds, default=parse_seeds("6-7"), help="sequences scored")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--size", type=parse_size, default=(1226, 370))
    parser.add_argument("--frame-step", type=int, default=10, help="every this many frames (the middle one)")
    parser.add_argument("--per-frame", type=int, default=30000, help="band pixels drawn per frame at most")
    parser.add_argument("--trees", type=int, default=24)
    parser.add_argument("--min-leaf", type=int, default=500)
    parser.add_argument("--max-depth", type=int, default=16)
    parser.add_argument(
        "--real",
        nargs="*",
        default=[],
        help="real pairs with ground truth scored too, every frame (e.g. ../shared/data/kitti_stereo_2015)",
    )
    parser.add_argument("--cache", required=True, help="rendered sequences (the label benchmark's --cache)")
    parser.add_argument("--out", default=str(MODEL_FILE), help="model file to write (default: the package's)")
    parser.add_argument("--score", default=None, metavar="MODEL", help="score this model instead of fitting one")
    parser.add_argument("--threads", type=int, default=0)
    args = parser.parse_args(argv)
    if args.threads:
        limit_threads(args.threads)
    started = time.perf_counter()
    rng = np.random.default_rng(0)
    seeds = [] if args.score else args.seeds
    sets: dict[tuple[str, int], tuple[NDArray[np.float32], NDArray[np.bool_]]] = {}
    jobs = [(scene, seed) for scene in args.scenes for seed in sorted(set(seeds) | set(args.test_seeds))]
    for scene, seed in tqdm(jobs, desc="band pixels", unit="sequence", file=sys.stderr):
        data = _sequence(Path(args.cache), scene, seed, args.frames, args.size)
        sets[scene, seed] = band_samples(data, args.frame_step, args.per_frame, rng)
    if args.score:
        model = load_model(args.score)
        print(f"scoring {args.score} (fitted on {json.dumps(model.metadata.get('fitted_on'))})")
    else:
        model = _fit(args, [sets[scene, seed] for scene in args.scenes for seed in args.seeds])
    scored = {scene: [sets[scene, s] for s in args.test_seeds] for scene in args.scenes}
    for path in tqdm(args.real, desc="real pairs", unit="set", file=sys.stderr):
        scored[f"real:{Path(path).name}"] = [band_samples(Path(path), 1, args.per_frame, rng)]
    test = {name: _score(model, parts) for name, parts in scored.items()}
    heads = f"{'pixels':>8} {'wrong':>6} {'AUC cue':>8} {'AUC look':>9} {'called right':>13} {'of them right':>14}"
    print(f"{'set':<24} {heads}")
    for name, t in test.items():
        print(
            f"{name:<24} {t['pixels']:>8} {t['wrong_share']:>6.1%} {t['auc_cue']:>8.3f} "
            f"{t['auc_look_where_scored']:>9.3f} {t['called_right_share']:>13.1%} {t['called_right_precision']:>14.1%}"
        )
    if not args.score:
        model.metadata["test"] = {"seeds": args.test_seeds, **test}
        print(f"written {save_model(model, args.out)}")
    print(f"{time.perf_counter() - started:.0f} s")
    print(json.dumps({"model": args.score or args.out, "fitted_on": model.metadata.get("fitted_on"), "test": test}))
    return 0


def _fit(args: argparse.Namespace, fit: list[tuple[NDArray[np.float32], NDArray[np.bool_]]]) -> ForestModel:
    """The band cue fitted on the band pixels ``fit`` (features, wrong) with the arguments' forest."""
    x = np.concatenate([f for f, _ in fit])
    right = ~np.concatenate([w for _, w in fit])
    metadata = {
        "kind": "band_cue",
        "feature_set": "band_cue",
        "feature_names": list(FEATURES),
        "fitted_on": {"scenes": args.scenes, "seeds": args.seeds, "frame_step": args.frame_step},
        "training_samples": int(right.size),
        "training_right_share": float(right.mean()),
    }
    forest = {"n_estimators": args.trees, "min_samples_leaf": args.min_leaf, "max_depth": args.max_depth}
    model = fit_forest(x, right, metadata, n_jobs=-1, forest=forest)
    nodes = model.feature.size
    print(f"fitted on {right.size} band pixels ({right.mean():.1%} right): {model.n_trees} trees, {nodes} nodes")
    return model


def _score(model: ForestModel, parts: list[tuple[NDArray[np.float32], NDArray[np.bool_]]]) -> dict[str, Any]:
    """How ``model`` ranks band pixels ``parts`` (features, wrong), and what the training's threshold calls right."""
    xs = np.concatenate([f for f, _ in parts])
    wrong = np.concatenate([w for _, w in parts])
    p_right = model.predict(xs)
    look = np.where(xs[:, FEATURES.index("look_missing")] > 0, np.nan, xs[:, FEATURES.index("look")])
    has_look = np.isfinite(look)
    called = p_right >= float(TRAINING["band_cue"])
    return {
        "pixels": int(wrong.size),
        "wrong_share": float(wrong.mean()),
        "auc_cue": rank_auc(-p_right, wrong),
        "auc_look_where_scored": rank_auc(-look[has_look], wrong[has_look]),
        "called_right_share": float(called.mean()),
        "called_right_precision": float((~wrong[called]).mean()) if called.any() else float("nan"),
    }


if __name__ == "__main__":
    raise SystemExit(main())
