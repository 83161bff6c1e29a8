"""``selfcontra batch train``: per-input training samples as Ray tasks, gathered into one forest.

Each ``--data`` input (expanded as :func:`~selfcontra_ros.batch.inputs.expand_inputs`
does for ``batch label``) pairs with the label result ``LABELS_FROM/<name>`` of
``selfcontra batch label`` (a label folder or a labelled bag). One task per
pair runs :func:`~selfcontra_ros.confidence.commands.input_samples`: matching,
features and the draw balanced per image (``max_per_class`` per class and
image), with the pair's own generator
:func:`~selfcontra_ros.confidence.commands.input_rng` ``(seed, position)``,
optionally capped at ``max_per_input`` samples per input. The samples come
back through Ray's object store, are concatenated in the inputs' order and
train one forest (:func:`~selfcontra_ros.confidence.commands.train_and_save`).

That is what ``selfcontra train --data D1 --labels LABELS_FROM/<name1> --data D2
...`` does in one process, so both give the same model file (identical
arrays) for the same inputs and seed. Inputs without a complete label result
(failed or not yet labelled) are left out and listed; none left is an error.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from selfcontra_ros.batch.engine import Engine, TaskLostError, open_engine
from selfcontra_ros.batch.inputs import BatchInput, expand_inputs
from selfcontra_ros.batch.label import complete_result
from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.commands import (
    InputSamples,
    input_rng,
    input_samples,
    merge_input_samples,
    train_and_save,
    training_matcher,
)
from selfcontra_ros.confidence.training import BandPrior, Samples
from selfcontra_ros.errors import BatchError
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.threads import limit_threads

__all__ = ["batch_train", "sample_one"]


def sample_one(
    position: int,
    data: str,
    labels: str,
    feature_set: str,
    matcher: dict[str, Any],
    seed: int,
    max_per_class: int,
    max_per_input: int | None,
    threads: int | None,
    band: BandPrior | None = None,
) -> dict[str, Any]:
    """The samples of one ``(data, labels)`` pair as plain arrays; the body of one batch-train task.

    Returns:
        ``features`` (N, F) float32, ``labels`` (N,) bool, ``frames`` (images that gave samples),
        ``read`` (frames read), ``labelled`` (frames with labels); or ``error`` when sampling raised.
    """
    if threads is not None:  # a Ray task's CPUs; None: this process's own cap
        limit_threads(threads)
    try:
        part = input_samples(
            data,
            labels,
            [feature_set],
            MatcherParams(**matcher),
            input_rng(seed, position),
            max_per_class=max_per_class,
            max_per_input=max_per_input,
            band=band,
        )
    except Exception as exc:  # reported with its input by the driver
        return {"error": f"{type(exc).__name__}: {exc}"}
    samples = part.samples[feature_set]
    return {
        "features": samples.features,
        "labels": samples.labels,
        "frames": samples.frames,
        "read": part.frames,
        "labelled": part.labelled,
    }


def batch_train(
    features: str,
    labels_from: str | Path,
    data: Sequence[str | Path],
    out: str | Path,
    *,
    address: str | None = None,
    cpus_per_task: int = 1,
    matcher: MatcherParams | None = None,
    max_per_class: int = int(constants.TRAINING["max_per_class"]),
    max_per_input: int | None = None,
    seed: int = int(constants.TRAINING["seed"]),
    band: BandPrior | None = None,
    n_jobs: int | None = None,
    forest: Mapping[str, Any] | None = None,
    progress: bool = True,
    echo: Callable[[str], None] | None = print,
    engine: Engine | None = None,
) -> dict[str, Any]:
    """Train a ``features`` forest on the batch-labelled ``data`` (module docstring) and write it to ``out``.

    Args:
        features: ``ensemble``, ``gcp`` or ``park``.
        labels_from: the output folder of ``selfcontra batch label`` on (at least) these inputs.
        data: bags, sequence folders, odometry roots or globs.
        out: model file (``.npz``).
        address, cpus_per_task, engine: where the tasks run (:func:`~selfcontra_ros.batch.label.batch_label`).
        matcher: query algorithm if the label results name none.
        max_per_class: per-image cap on samples of each class.
        max_per_input: cap on one input's samples (None: no cap beyond the per-image one).
        seed: seed of the draws.
        band: how the unknown pixels of the query's fattening band are drawn as negatives
            (:class:`~selfcontra_ros.confidence.training.BandPrior`; None: the defaults; share 0: the paper).
        n_jobs: scikit-learn workers of the final training.
        forest: overrides of the forest constants.
        progress: a progress bar over the finished inputs.
        echo: where notes go (None: silent).

    Returns:
        :func:`~selfcontra_ros.confidence.commands.train_and_save`'s summary plus ``inputs`` (used),
        ``left_out`` (inputs without a complete label result) and ``engine``.

    Raises:
        BatchError: bad inputs, no input with a complete label result, an input whose sampling failed.
        SelfContraError: label results of different query algorithms, no labelled sample.
    """
    started = time.perf_counter()
    root = Path(labels_from)
    items = expand_inputs(data)
    used: list[BatchInput] = []
    left_out: list[BatchInput] = []
    for item in items:
        (used if complete_result(root, item) is not None else left_out).append(item)
    if left_out and echo is not None:
        echo(f"left out (no complete label result in {root}): {', '.join(item.name for item in left_out)}")
    if not used:
        raise BatchError(f"none of the {len(items)} inputs has a complete label result in {root}")
    pairs = [(str(item.path), str(root / item.name)) for item in used]
    params = training_matcher(pairs, matcher)
    own_engine = engine is None
    if engine is None:
        engine = open_engine(address, cpus_per_task=cpus_per_task, inputs=len(pairs), echo=echo)
    threads = cpus_per_task if engine.remote else None
    calls = [
        (position, d, lab, features, asdict(params), seed, max_per_class, max_per_input, threads, band)
        for position, (d, lab) in enumerate(pairs)
    ]
    results: dict[int, dict[str, Any]] = {}
    try:
        if echo is not None:
            echo(f"sampling {len(calls)} input(s) on {engine.description}")
        with tqdm(total=len(calls), desc="batch samples", unit="input", disable=not progress) as bar:
            for position, result in engine.run(sample_one, calls):
                results[position] = (
                    {"error": f"the task was lost: {result}"} if isinstance(result, TaskLostError) else result
                )
                bar.update(1)
    finally:
        if own_engine:
            engine.close()
    failed = [f"{used[p].name}: {r['error']}" for p, r in sorted(results.items()) if "error" in r]
    if failed:
        raise BatchError("sampling failed for " + "; ".join(failed))
    parts = [_input_samples(features, results[p]) for p in range(len(calls))]
    samples = merge_input_samples(parts, [features])[features]
    summary = train_and_save(
        samples,
        params,
        pairs,
        out,
        n_jobs=n_jobs,
        forest=forest,
        started=started,
        sampling=(band if band is not None else BandPrior()).metadata(),
    )
    summary.update(
        inputs=[item.name for item in used], left_out=[item.name for item in left_out], engine=engine.description
    )
    return summary


def _input_samples(feature_set: str, result: dict[str, Any]) -> InputSamples:
    samples = Samples(
        feature_set,
        np.asarray(result["features"], dtype=np.float32),
        np.asarray(result["labels"], dtype=bool),
        frames=int(result["frames"]),
    )
    return InputSamples(samples={feature_set: samples}, frames=int(result["read"]), labelled=int(result["labelled"]))
