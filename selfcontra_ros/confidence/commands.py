"""The work behind ``selfcontra train`` and ``selfcontra evaluate-confidence``.

Data inputs (``--data``), detected from the folder's layout:

* a KITTI odometry sequence (real or the package's synthetic one, see
  :func:`~selfcontra_ros.datasets.kitti.open_sequence`); its frames carry
  ground truth when the sequence has ``disp_0``;
* a KITTI stereo 2012/2015 split (:func:`~selfcontra_ros.datasets.kitti.open_stereo_dataset`):
  the reference frame ``NNNNNN_10`` of every scene, with ground truth;
* a Middlebury scene folder (2003, 2014 / MiddEval3 or ETH3D two-view layout), or a
  folder of them (:mod:`selfcontra_ros.datasets.middlebury`);
* a rosbag2 bag (folder with ``metadata.yaml`` or ``.mcap`` file): its stereo
  pairs, with ground truth from ``NS/ground_truth/disparity`` when it has it
  (:mod:`selfcontra_ros.confidence.bag_frames`).

Label inputs (``--labels``): an output folder of ``selfcontra label``
(``labels/NNNNNN.png``, codes 0/1/2, plus ``metrics.json`` naming the query
algorithm's parameters, which training then reuses); an output bag of
``selfcontra label-bag`` (``NS/labels`` matched to the data bag's left images
by header stamp, ``metrics.json`` inside the bag folder; the data bag may be
the labelled bag itself); or ``gt``: labels from the ground-truth disparity
(``|d - d_gt| <= 3 px`` positive, else negative). Frames without labels are
skipped.

``evaluate-confidence`` writes into ``OUT``: ``metrics.json`` shaped
``{"frames": [...], "mean": {"ausc", "optimal", "ausc_ratio", "bad_rate"}}``
(with one model; with several, one ``OUT/<name>/metrics.json`` each),
``sparsification.png`` (mean curves), ``table.md`` (paper Table 1 layout:
rows = training source, columns = LRD, WLS, Ensemble, Park, GCP; cells = mean
AUSC / optimal) and ``summary.json``.

Baselines without a model file (``--model`` values): ``lrd``, the left-right
disparity difference (:func:`~selfcontra_ros.confidence.features.lrd_confidence`),
and ``wls``, OpenCV's ``DisparityWLSFilter`` confidence map computed from the
same left and right disparity maps (:mod:`selfcontra_ros.confidence.baselines`
says exactly what the filter is fed). Both are scored on the same pixels as
the forests.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros import interrupts
from selfcontra_ros.bags.stereo_input import StereoInput
from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.bag_frames import BagFrame, BagLabels, is_bag, iter_bag_frames, read_bag_labels
from selfcontra_ros.confidence.baselines import wls_confidence
from selfcontra_ros.confidence.features import FeatureContext, compute_features, feature_names, lrd_confidence
from selfcontra_ros.confidence.forest import ForestModel, ModelError, load_model, model_path, save_model
from selfcontra_ros.confidence.inputs import query_feature_input
from selfcontra_ros.confidence.training import (
    BandPrior,
    Samples,
    TrainParams,
    balanced_indices,
    frame_samples,
    merge_samples,
    recorded_params,
    train,
)
from selfcontra_ros.datasets.kitti import StereoFrame, open_sequence, open_stereo_dataset
from selfcontra_ros.datasets.middlebury import middlebury_scenes, read_middlebury
from selfcontra_ros.errors import DatasetError, SelfContraError
from selfcontra_ros.evaluation.metrics import DEFAULT_THRESHOLD_PX, ground_truth_labels
from selfcontra_ros.evaluation.plots import plot_sparsification
from selfcontra_ros.evaluation.sparsification import DEFAULT_STEP, sparsification
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE, POSITIVE
from selfcontra_ros.matching.base import MatcherParams, make_matcher

__all__ = [
    "GT",
    "LRD",
    "WLS",
    "InputSamples",
    "collect_samples",
    "confidence_table",
    "evaluate_command",
    "input_rng",
    "input_samples",
    "iter_frames",
    "merge_input_samples",
    "train_and_save",
    "train_command",
    "training_matcher",
]

#: ``--labels`` value selecting ground-truth labels.
GT = "gt"
#: ``--model`` value selecting the left-right disparity difference baseline.
LRD = "lrd"
#: ``--model`` value selecting OpenCV's WLS filter confidence baseline.
WLS = "wls"
#: Confidences without a model file: untrained, so repeated in every row of the table.
BASELINES = (LRD, WLS)

_COLUMNS = (("LRD", LRD), ("WLS", WLS), ("Ensemble", "ensemble"), ("Park", "park"), ("GCP", "gcp"))


# ------------------------------------------------------------------------------------------- inputs


def iter_frames(
    data: Path | str,
    *,
    namespace: str | None = None,
    stereo_input: StereoInput | None = None,
    slop: float | None = None,
) -> Iterator[StereoFrame]:
    """Stereo frames of a sequence, a KITTI stereo split, Middlebury scenes or a bag (see the module docstring).

    Args:
        data: the folder or bag.
        namespace: a bag's stereo namespace (default: found in the bag).
        stereo_input: how a bag is read (a robot's topic names, compressed or raw images,
            rectification); None: as a labelled bag records it, else the package's layout.
        slop: a bag's left and right images are paired within this many seconds (0: equal
            stamps); None: as a labelled bag records it, else equal stamps.

    Raises:
        DatasetError: when ``data`` is none of these.
        SelfContraError: ``stereo_input`` given for data that is not a bag.
        BagError: a bag without stereo frames, or unreadable.
    """
    path = Path(data)
    if is_bag(path):
        yield from iter_bag_frames(path, namespace=namespace, stereo_input=stereo_input, slop=slop)
        return
    if stereo_input is not None:
        raise SelfContraError(f"a stereo input (remaps, image transport, rectify) applies to bags, not to {path}")
    scenes = middlebury_scenes(path)
    if scenes:
        for i, scene in enumerate(scenes):
            yield read_middlebury(scene, index=i)
        return
    split = path / "training" if (path / "training").is_dir() else path
    if (split / "calib_cam_to_cam").is_dir() or (split / "calib").is_dir():
        for stereo_scene in open_stereo_dataset(split):
            ref = stereo_scene.reference_index
            if ref is not None:
                yield stereo_scene[ref]
        return
    yield from open_sequence(path)


@dataclass
class _LabelSource:
    """Where the training labels of one ``--data`` come from: a label folder, a labelled bag or ground truth."""

    folder: Path | None
    bag: BagLabels | None
    matcher: MatcherParams | None
    #: the labeler that made the labels, as far as its fattening band goes (None: not recorded, or ``gt``).
    labeler: LabelerParams | None = None

    def has_labels(self, frame: StereoFrame) -> bool:
        """Whether ``frame`` has labels, known before matching (ground truth: decided by :meth:`labels`)."""
        if self.bag is not None:
            return isinstance(frame, BagFrame) and frame.stamp_ns in self.bag
        if self.folder is not None:
            return (self.folder / f"{frame.index:06d}.png").is_file()
        return True

    @property
    def is_ground_truth(self) -> bool:
        """Whether the labels are the data's ground truth (``gt``) rather than self labels."""
        return self.folder is None and self.bag is None

    def labels(self, frame: StereoFrame, disparity: NDArray[np.float32]) -> NDArray[np.uint8] | None:
        if self.bag is not None:
            return self.bag.at(frame.stamp_ns) if isinstance(frame, BagFrame) else None
        if self.folder is None:
            if frame.gt_disparity is None:
                return None
            return ground_truth_labels(disparity, frame.gt_disparity, threshold=DEFAULT_THRESHOLD_PX)
        path = self.folder / f"{frame.index:06d}.png"
        if not path.is_file():
            return None
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint8 or image.ndim != 2:
            raise DatasetError(f"label image {path} must be a mono8 PNG with codes 0/1/2")
        return np.asarray(image, dtype=np.uint8)


def _label_source(labels: str | Path, data: str | Path) -> _LabelSource:
    if str(labels) == GT:
        return _LabelSource(folder=None, bag=None, matcher=None)
    root = Path(labels)
    if is_bag(root):
        if not is_bag(data):
            raise SelfContraError(
                f"labels {root} are a bag, matched to frames by header stamp: --data must be a bag too "
                f"(the labelled bag itself will do), not {data}"
            )
        bag = read_bag_labels(root)
        if not bag.images:
            raise SelfContraError(f"labelled bag {root} holds no label image (its labeler labelled no view)")
        return _LabelSource(folder=None, bag=bag, matcher=bag.matcher, labeler=bag.labeler)
    folder = root / "labels" if (root / "labels").is_dir() else root
    if not folder.is_dir():
        raise DatasetError(
            f"label folder {root} does not exist (expected a 'selfcontra label' output folder, "
            "a 'selfcontra label-bag' output bag or 'gt')"
        )
    matcher = labeler = None
    for metrics in (root / "metrics.json", folder.parent / "metrics.json"):
        if metrics.is_file():
            matcher, labeler = recorded_params(json.loads(metrics.read_text()).get("params", {}))
            break
    return _LabelSource(folder=folder, bag=None, matcher=matcher, labeler=labeler)


def _matcher_params(sources: Sequence[_LabelSource], matcher: MatcherParams | None) -> MatcherParams:
    """The one query algorithm of a training run: the labels' own, else ``matcher``, else the default."""
    found = {json.dumps(asdict(s.matcher), sort_keys=True) for s in sources if s.matcher is not None}
    if len(found) > 1:
        raise SelfContraError(
            "the label folders were made with different query algorithms; train one model per algorithm"
        )
    if found:
        params = MatcherParams(**json.loads(found.pop()))
        if matcher is not None and matcher != params:
            raise SelfContraError("the labels were made with other matcher parameters than the ones given")
        return params
    return matcher if matcher is not None else MatcherParams()


# ------------------------------------------------------------------------------------------- training


def input_rng(seed: int, position: int) -> np.random.Generator:
    """The generator of the sample draw of the ``position``-th ``(data, labels)`` pair of a run seeded ``seed``.

    Each input draws from its own generator, so that its samples do not depend on the inputs before it:
    ``selfcontra batch train`` samples the inputs apart (in parallel) and gets what :func:`collect_samples` gets.
    """
    return np.random.default_rng([int(seed), int(position)])


@dataclass
class InputSamples:
    """The training samples of one ``(data, labels)`` pair.

    Attributes:
        samples: feature set -> the input's samples, its labelled frames in order (empty when none).
        frames: frames read from the data.
        labelled: frames that had a label image (each gave samples, possibly none of one class).
    """

    samples: dict[str, Samples]
    frames: int
    labelled: int


def input_samples(
    data: str | Path,
    labels: str | Path,
    feature_sets: Sequence[str],
    params: MatcherParams,
    rng: np.random.Generator,
    *,
    max_per_class: int = int(constants.TRAINING["max_per_class"]),
    max_per_input: int | None = None,
    namespace: str | None = None,
    stereo_input: StereoInput | None = None,
    slop: float | None = None,
    band: BandPrior | None = None,
) -> InputSamples:
    """Balanced samples of one ``(data, labels)`` pair with query algorithm ``params`` (see :func:`collect_samples`).

    Args:
        data, labels: one pair as :func:`collect_samples` takes them.
        feature_sets: feature sets to sample; matching runs once per frame.
        params: the run's query algorithm (:func:`training_matcher`).
        rng: the pair's generator (:func:`input_rng`).
        max_per_class: per-image cap on samples of each class.
        max_per_input: cap on the pair's samples of each feature set (both classes together); an
            input above it keeps a balanced draw of ``max_per_input // 2`` per class. None: no cap.
        namespace, stereo_input, slop: how a data bag is read (:func:`iter_frames`).
        band: self labels only (not ``gt``): how the unknown pixels of the query's fattening band are drawn as
            negatives (:class:`~selfcontra_ros.confidence.training.BandPrior`; None: the defaults).

    Raises:
        SelfContraError: labels of a bag that match no frame of its data (or with data that is not a bag).
        BagError: a bag that cannot be read or holds no stereo frames or no labels.
    """
    source = _label_source(labels, data)
    query = make_matcher(params)
    parts: dict[str, list[Samples]] = {name: [] for name in feature_sets}
    frames = matched = labelled = 0
    for frame in iter_frames(data, namespace=namespace, stereo_input=stereo_input, slop=slop):
        interrupts.check()
        frames += 1
        if not source.has_labels(frame):
            continue
        matched += 1
        inputs = query_feature_input(query, frame.left, frame.right)
        label_image = source.labels(frame, inputs.disparity)
        if label_image is None:
            continue
        if not source.is_ground_truth:
            prior = band if band is not None else BandPrior()
            label_image = prior.apply(
                label_image, inputs.disparity, rng, left=frame.left, right=frame.right, labeler=source.labeler
            )
        labelled += 1
        ctx = FeatureContext(inputs)
        for name in feature_sets:
            parts[name].append(frame_samples(name, ctx, label_image, rng, max_per_class=max_per_class))
    if source.bag is not None and not matched:
        raise SelfContraError(
            f"none of the {len(source.bag.images)} label images of {labels} (stamps {source.bag.stamp_range()}) "
            f"matches the left image stamp of one of the {frames} frames of {data}; "
            "were the labels made from this bag?"
        )
    merged: dict[str, Samples] = {}
    for name in feature_sets:
        width = len(feature_names(name))
        empty = Samples(name, np.zeros((0, width), np.float32), np.zeros(0, bool), frames=0)
        samples = merge_samples(parts[name]) if parts[name] else empty
        if max_per_input is not None and samples.labels.size > max_per_input:
            codes = np.where(samples.labels, POSITIVE, NEGATIVE)
            keep = balanced_indices(codes, max(int(max_per_input) // 2, 0), rng)
            samples = Samples(name, samples.features[keep], samples.labels[keep], frames=samples.frames)
        merged[name] = samples
    return InputSamples(samples=merged, frames=frames, labelled=labelled)


def training_matcher(
    pairs: Sequence[tuple[str | Path, str | Path]], matcher: MatcherParams | None = None
) -> MatcherParams:
    """The one query algorithm of a training run on ``pairs``: the labels' own, else ``matcher``, else the default.

    Raises:
        SelfContraError: label sources of different query algorithms, or other than ``matcher``.
        DatasetError: a label folder that does not exist.
    """
    return _matcher_params([_label_source(labels, data) for data, labels in pairs], matcher)


def merge_input_samples(
    parts: Sequence[InputSamples], feature_sets: Sequence[str], data: Sequence[str | Path] | None = None
) -> dict[str, Samples]:
    """The samples of a run: each feature set's samples of the pairs concatenated in the pairs' order.

    ``data`` (the pairs' data, for the error message) defaults to "the inputs".

    Raises:
        SelfContraError: no pair had a labelled frame.
    """
    if not any(part.labelled for part in parts):
        what = "the inputs" if data is None else str([str(d) for d in data])
        raise SelfContraError(f"no frame of {what} has labels to train on")
    return {name: merge_samples([part.samples[name] for part in parts]) for name in feature_sets}


def collect_samples(
    pairs: Sequence[tuple[str | Path, str | Path]],
    feature_sets: Sequence[str],
    *,
    matcher: MatcherParams | None = None,
    max_per_class: int = int(constants.TRAINING["max_per_class"]),
    seed: int = int(constants.TRAINING["seed"]),
    namespace: str | None = None,
    stereo_inputs: Sequence[StereoInput | None] | None = None,
    slop: float | None = None,
    max_per_input: int | None = None,
    band: BandPrior | None = None,
) -> tuple[dict[str, Samples], MatcherParams]:
    """Balanced training samples of several feature sets from ``(data, labels)`` pairs; matching runs once per frame.

    ``namespace``, ``stereo_inputs`` (one per pair, None for a bag's own record) and ``slop``
    say how data bags are read (:func:`iter_frames`). Pair ``i`` draws its samples with
    :func:`input_rng` ``(seed, i)`` (:func:`input_samples`); ``max_per_input`` caps each pair's samples;
    ``band`` as in :func:`input_samples`.

    Returns:
        ``({feature set: samples}, query algorithm parameters)``.

    Raises:
        SelfContraError: no labelled frame at all, labels of a bag that match no frame of its data
            (or with data that is not a bag), label sources of different query algorithms.
        BagError: a bag that cannot be read or holds no stereo frames or no labels.
    """
    bag_inputs: list[StereoInput | None] = list(stereo_inputs) if stereo_inputs is not None else [None] * len(pairs)
    if len(bag_inputs) != len(pairs):
        raise SelfContraError(
            f"{len(bag_inputs)} stereo inputs for {len(pairs)} --data/--labels pairs; give one per pair"
        )
    params = training_matcher(pairs, matcher)
    parts = [
        input_samples(
            data,
            labels,
            feature_sets,
            params,
            input_rng(seed, position),
            max_per_class=max_per_class,
            max_per_input=max_per_input,
            namespace=namespace,
            stereo_input=stereo_input,
            slop=slop,
            band=band,
        )
        for position, ((data, labels), stereo_input) in enumerate(zip(pairs, bag_inputs, strict=True))
    ]
    return merge_input_samples(parts, feature_sets, [d for d, _ in pairs]), params


def train_command(
    pairs: Sequence[tuple[str | Path, str | Path]],
    features: str,
    out: str | Path,
    *,
    matcher: MatcherParams | None = None,
    n_jobs: int | None = None,
    max_per_class: int = int(constants.TRAINING["max_per_class"]),
    forest: Mapping[str, Any] | None = None,
    namespace: str | None = None,
    stereo_inputs: Sequence[StereoInput | None] | None = None,
    slop: float | None = None,
    band: BandPrior | None = None,
) -> dict[str, Any]:
    """Train a confidence forest of feature set ``features`` and write it to ``out`` (``.npz``).

    Args:
        pairs: ``(data, labels)`` pairs; ``data`` a sequence, stereo split, Middlebury folder or bag;
            ``labels`` a ``selfcontra label`` output folder, a ``selfcontra label-bag`` output bag
            (``data`` then a bag: the labelled bag itself or the bag it was made from) or ``"gt"``.
        features: ``ensemble``, ``gcp`` or ``park``.
        out: model file, written as given (``.npz`` added only to a name without suffix:
            :func:`~selfcontra_ros.confidence.forest.model_path`).
        matcher: query algorithm for ``gt`` labels (label folders and bags bring their own).
        n_jobs: scikit-learn workers.
        max_per_class: per-image cap on samples of each class.
        forest: overrides of the forest constants (tests use smaller forests).
        namespace: stereo namespace of the data bags (default: found in each bag).
        stereo_inputs: how each data bag is read, one per pair (None: its own record, else the
            package's layout): a robot's topic names, compressed images, rectification.
        slop: data bags' left and right images paired within this many seconds; None: as recorded.
        band: self labels only: how the unknown pixels of the query's fattening band are drawn as negatives
            (:class:`~selfcontra_ros.confidence.training.BandPrior`; None: the defaults; share 0: the paper).

    Returns:
        Summary: ``model`` path, ``samples``, ``frames``, ``positive_share``, ``seconds``.
    """
    if not pairs:
        raise SelfContraError("train needs at least one --data/--labels pair")
    start = time.perf_counter()
    samples, params = collect_samples(
        pairs,
        [features],
        matcher=matcher,
        max_per_class=max_per_class,
        namespace=namespace,
        stereo_inputs=stereo_inputs,
        slop=slop,
        band=band,
    )
    return train_and_save(
        samples[features],
        params,
        pairs,
        out,
        n_jobs=n_jobs,
        forest=forest,
        started=start,
        sampling=(band if band is not None else BandPrior()).metadata(),
    )


def train_and_save(
    samples: Samples,
    params: MatcherParams,
    pairs: Sequence[tuple[str | Path, str | Path]],
    out: str | Path,
    *,
    n_jobs: int | None = None,
    forest: Mapping[str, Any] | None = None,
    started: float | None = None,
    sampling: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Train the forest on a run's gathered samples and write it to ``out``: the end of :func:`train_command`.

    Args:
        samples: the run's samples of one feature set (:func:`collect_samples`).
        params: the query algorithm they were computed with (stored in the model).
        pairs: the ``(data, labels)`` pairs they came from (stored in the model).
        out: model file (:func:`~selfcontra_ros.confidence.forest.model_path`).
        n_jobs: scikit-learn workers.
        forest: overrides of the forest constants.
        started: ``time.perf_counter()`` at the run's start, for ``seconds`` (None: now).
        sampling: how self labels were sampled (:meth:`~selfcontra_ros.confidence.training.BandPrior.metadata`),
            stored in the model as ``sampling`` when a pair has self labels (ground truth is used as it is).

    Returns:
        Summary: ``model`` path, ``feature_set``, ``samples``, ``frames``, ``positive_share``, ``seconds``.
    """
    start = time.perf_counter() if started is None else started
    kinds = {GT if str(labels) == GT else "self" for _, labels in pairs}
    metadata = {
        "matcher": asdict(params),
        "label_source": kinds.pop() if len(kinds) == 1 else "mixed",
        "sources": [{"data": str(d), "labels": str(lab)} for d, lab in pairs],
    }
    if sampling is not None and any(str(labels) != GT for _, labels in pairs):
        metadata["sampling"] = dict(sampling)
    model = train(samples, TrainParams(forest=dict(forest or {}), n_jobs=n_jobs, metadata=metadata))
    path = save_model(model, out)
    return {
        "model": str(path),
        "feature_set": samples.feature_set,
        "samples": int(samples.labels.size),
        "frames": samples.frames,
        "positive_share": float(samples.labels.mean()),
        "seconds": time.perf_counter() - start,
    }


# ------------------------------------------------------------------------------------------- evaluation


@dataclass
class _Entry:
    name: str
    feature_set: str  # "lrd" or "wls" for the baselines
    source: str
    model: ForestModel | None


def _load_entries(models: Sequence[str | Path]) -> list[_Entry]:
    entries: list[_Entry] = []
    for spec in models:
        if str(spec) in BASELINES:
            if any(e.model is None and e.feature_set == str(spec) for e in entries):
                continue  # a baseline asked for twice is scored once
            entry = _Entry(str(spec), str(spec), "none", None)
        else:
            path = Path(spec)
            if not path.exists() and model_path(path).is_file():
                path = model_path(path)  # the name given to 'train --out' without suffix: train wrote NAME.npz
            model = load_model(path)
            if int(model.metadata.get("constants_version", -1)) != constants.VERSION:
                raise ModelError(
                    f"model {spec} was trained with feature version {model.metadata.get('constants_version')}"
                )
            feature_set = str(model.metadata.get("feature_set", ""))
            entry = _Entry(path.stem, feature_set, str(model.metadata.get("label_source", "?")), model)
        if any(e.name == entry.name for e in entries):
            entry.name = f"{entry.name}_{len(entries)}"
        entries.append(entry)
    return entries


def _frame_figures(curve_result: Any) -> dict[str, Any]:
    return {
        "ausc": curve_result.ausc,
        "optimal": curve_result.optimal,
        "ausc_ratio": curve_result.ratio,
        "bad_rate": curve_result.bad_rate_all,
        "pixels": curve_result.pixels,
        "density": [float(x) for x in curve_result.density],
        "curve_bad_rate": [float(x) for x in curve_result.bad_rate],
    }


def _mean(frames: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    out: dict[str, float] = {}
    for key in ("ausc", "optimal", "ausc_ratio", "bad_rate"):
        values = [float(f[key]) for f in frames if f[key] is not None and math.isfinite(float(f[key]))]
        out[key] = float(np.mean(values)) if values else math.nan
    return out


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def confidence_table(results: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table in the layout of the paper's Table 1: mean AUSC / optimal.

    Args:
        results: one mapping per evaluated model with ``feature_set``
            (``lrd``, ``ensemble``, ``park``, ``gcp``), ``source`` (training
            labels: ``gt``, ``self``, ...) and ``ausc_ratio``.

    Returns:
        Rows = training source (the baselines LRD and WLS, untrained, repeated
        in every row); columns = LRD, WLS, Ensemble, Park, GCP; ``-`` where
        nothing was evaluated.
    """
    baselines = {key: [r["ausc_ratio"] for r in results if r["feature_set"] == key] for key in BASELINES}
    sources = sorted({str(r["source"]) for r in results if r["feature_set"] not in BASELINES}) or ["-"]
    names = {GT: "ground truth", "self": "self-generated labels"}
    lines = ["| training source | " + " | ".join(c for c, _ in _COLUMNS) + " |", "|---" * (len(_COLUMNS) + 1) + "|"]
    for source in sources:
        cells = []
        for _, key in _COLUMNS:
            values = (
                baselines[key]
                if key in baselines
                else [r["ausc_ratio"] for r in results if r["feature_set"] == key and r["source"] == source]
            )
            cells.append(f"{values[0]:.3f}" if values and values[0] is not None and math.isfinite(values[0]) else "-")
        lines.append(f"| {names.get(source, source)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def evaluate_command(
    models: Sequence[str | Path] | str | Path,
    data: str | Path,
    out: str | Path,
    *,
    matcher: MatcherParams | None = None,
    step: float = DEFAULT_STEP,
    namespace: str | None = None,
    stereo_input: StereoInput | None = None,
    slop: float | None = None,
) -> dict[str, Any]:
    """Evaluate confidence models (or the baselines ``"lrd"``, ``"wls"``) by sparsification on frames with ground truth.

    The query algorithm is the one the models were trained for (all must
    agree); with only baselines, ``matcher`` or the default. Matching and each
    feature set are computed once per frame for all models. ``namespace``,
    ``stereo_input`` and ``slop`` say how a bag ``data`` is read (:func:`iter_frames`).

    Returns:
        ``{model name: {"frames": [...], "mean": {...}}}`` plus ``"table"`` (the Markdown table).

    Raises:
        SelfContraError: models of different query algorithms, or no frame with ground truth.
    """
    specs = [models] if isinstance(models, (str, Path)) else list(models)
    if not specs:
        raise SelfContraError("evaluate-confidence needs at least one --model (a model file, 'lrd' or 'wls')")
    entries = _load_entries(specs)
    algorithms = {json.dumps(e.model.metadata.get("matcher"), sort_keys=True) for e in entries if e.model is not None}
    if len(algorithms) > 1:
        raise SelfContraError("the models were trained for different query algorithms; evaluate them separately")
    params = matcher if matcher is not None else MatcherParams()
    if algorithms:
        stored: dict[str, Any] | None = json.loads(algorithms.pop())
        if stored:
            params = MatcherParams(**stored)
    query = make_matcher(params)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    frames: dict[str, list[dict[str, Any]]] = {e.name: [] for e in entries}
    for frame in iter_frames(data, namespace=namespace, stereo_input=stereo_input, slop=slop):
        interrupts.check()
        if frame.gt_disparity is None:
            continue
        ctx = FeatureContext(query_feature_input(query, frame.left, frame.right))
        gt = frame.gt_disparity[ctx.rows, ctx.cols]
        has_gt = np.isfinite(gt) & (gt > 0)
        if not has_gt.any():
            continue
        correct = np.abs(ctx.d[has_gt] - gt[has_gt]) <= DEFAULT_THRESHOLD_PX
        cache: dict[str, NDArray[np.float32]] = {}
        for entry in entries:
            if entry.model is None:
                if entry.feature_set not in cache:
                    cache[entry.feature_set] = (
                        wls_confidence(ctx, params) if entry.feature_set == WLS else lrd_confidence(ctx)
                    )
                confidence = cache[entry.feature_set]
            else:
                if entry.feature_set not in cache:
                    cache[entry.feature_set] = compute_features(entry.feature_set, ctx)[0]
                confidence = entry.model.predict(cache[entry.feature_set])
            result = sparsification(confidence[has_gt], correct, step=step)
            frames[entry.name].append({"frame": frame.name, **_frame_figures(result)})
    if not any(frames.values()):
        raise SelfContraError(f"no frame of {data} has ground-truth disparity to evaluate against")
    results: dict[str, Any] = {}
    table_rows: list[dict[str, Any]] = []
    curves = {}
    legend = {}
    grid = np.arange(1.0, 0.0, -step)
    for entry in entries:
        mean = _mean(frames[entry.name])
        record = {"frames": frames[entry.name], "mean": mean}
        results[entry.name] = record
        table_rows.append({"feature_set": entry.feature_set, "source": entry.source, **mean})
        mean_curve = np.mean(
            [np.interp(grid, f["density"][::-1], f["curve_bad_rate"][::-1]) for f in frames[entry.name]], axis=0
        )
        curves[entry.name] = (grid, mean_curve)
        legend[entry.name] = f"AUSC/opt {mean['ausc_ratio']:.2f}"
        target = out / "metrics.json" if len(entries) == 1 else out / entry.name / "metrics.json"
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(json.dumps(_json_safe(record), indent=1))
    bad_rate = float(np.mean([f["bad_rate"] for f in next(iter(frames.values()))]))
    plot_sparsification(curves, out / "sparsification.png", bad_rate=bad_rate, legend_extra=legend)
    table = confidence_table(table_rows)
    (out / "table.md").write_text(table)
    summary = {
        "data": str(data),
        "matcher": asdict(params),
        "models": {
            e.name: {"feature_set": e.feature_set, "source": e.source, **results[e.name]["mean"]} for e in entries
        },
    }
    (out / "summary.json").write_text(json.dumps(_json_safe(summary), indent=1))
    return {**results, "table": table}
