"""Random forest confidence: training with scikit-learn, model files as plain arrays, compiled inference.

A model file is a NumPy ``.npz`` archive holding only numeric arrays and one
JSON text (stored as a uint8 array); it is read with
``np.load(allow_pickle=False)``, so loading a file never runs code (DESIGN
section 5: no pickle/joblib). Arrays, for ``T`` trees with ``M`` nodes in all:

==================  ============  ==================================================================
``tree_offsets``    int64 (T+1)   node ``j`` of tree ``t`` is row ``tree_offsets[t] + j``
``children_left``   int32 (M)     left child (tree-local index), -1 at a leaf
``children_right``  int32 (M)     right child (tree-local index), -1 at a leaf
``feature``         int32 (M)     feature column tested at the node (-2 at a leaf)
``threshold``       float64 (M)   go left when ``x[feature] <= threshold``
``positive``        float64 (M)   share of positive training samples reaching the node
``metadata``        uint8         UTF-8 JSON: format, feature set, feature names, constants version, ...
==================  ============  ==================================================================

A forest's confidence is the mean over trees of the leaf's positive share
(scikit-learn's ``predict_proba`` of the positive class).
"""

from __future__ import annotations

import json
import os
import threading
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros import interrupts
from selfcontra_ros.confidence import constants, kernels
from selfcontra_ros.errors import SelfContraError

__all__ = ["FORMAT", "ForestModel", "ModelError", "fit_forest", "load_model", "model_path", "save_model"]

#: Value of ``metadata["format"]`` in the package's model files.
FORMAT = "selfcontra-forest-1"

_ARRAYS = {
    "tree_offsets": np.int64,
    "children_left": np.int32,
    "children_right": np.int32,
    "feature": np.int32,
    "threshold": np.float64,
    "positive": np.float64,
}


class ModelError(SelfContraError):
    """A model file that is missing, not a package model, or inconsistent."""


@dataclass
class ForestModel:
    """A trained forest as flat node arrays (see the module docstring) and its metadata.

    Attributes:
        tree_offsets: (T+1,) start of each tree's nodes.
        children_left: (M,) tree-local left child, -1 at leaves.
        children_right: (M,) tree-local right child, -1 at leaves.
        feature: (M,) tested feature column.
        threshold: (M,) split threshold.
        positive: (M,) positive share at each node.
        metadata: JSON-serialisable description (``feature_set``, ``feature_names``, ...).
    """

    tree_offsets: NDArray[np.int64]
    children_left: NDArray[np.int32]
    children_right: NDArray[np.int32]
    feature: NDArray[np.int32]
    threshold: NDArray[np.float64]
    positive: NDArray[np.float64]
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def n_trees(self) -> int:
        """Number of trees."""
        return int(self.tree_offsets.size - 1)

    @property
    def n_features(self) -> int:
        """Number of feature columns the model expects."""
        return int(self.metadata.get("n_features", int(self.feature.max(initial=-1)) + 1))

    def predict(self, features: NDArray[np.floating]) -> NDArray[np.float32]:
        """Confidence of each sample: mean over trees of the reached leaf's positive share, in [0, 1].

        A compiled traversal of the node arrays (:func:`kernels.forest_predict`,
        parallel over samples); equal to scikit-learn's ``predict_proba`` of the
        positive class for the same forest.

        Args:
            features: (N, n_features) feature rows (cast to float32 like scikit-learn).

        Returns:
            (N,) float32 confidences.
        """
        # Not made C-contiguous: the kernel reads columns, so compute_features' column-major rows pass as they are.
        x = np.asarray(features, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.n_features:
            raise ModelError(f"features must be (N, {self.n_features}), got shape {x.shape}")
        if x.shape[0] == 0:
            return np.zeros(0, dtype=np.float32)
        return kernels.forest_predict(x, self.tree_offsets, self.positive, self._layout)

    @cached_property
    def _layout(self) -> kernels.ForestLayout:
        """The traversal's node arrays, built on the first prediction (the node arrays are not changed after)."""
        return kernels.forest_layout(
            self.tree_offsets, self.children_left, self.children_right, self.feature, self.threshold
        )


def fit_forest(
    features: NDArray[np.floating],
    labels: NDArray[np.bool_],
    metadata: dict[str, Any] | None = None,
    *,
    n_jobs: int | None = None,
    forest: Mapping[str, Any] | None = None,
) -> ForestModel:
    """Train scikit-learn's random forest and export it as a :class:`ForestModel`.

    Args:
        features: (N, F) training features.
        labels: (N,) True for positive (correct disparity) samples.
        metadata: stored with the model (feature set, sources, ...).
        n_jobs: parallel jobs of scikit-learn (None = 1).
        forest: overrides of :data:`~selfcontra_ros.confidence.constants.FOREST`.

    Raises:
        SelfContraError: if the samples hold only one class.
    """
    from sklearn.ensemble import RandomForestClassifier

    x = np.asarray(features, dtype=np.float32)
    y = np.asarray(labels, dtype=bool)
    if x.ndim != 2 or y.shape != (x.shape[0],):
        raise SelfContraError(f"training features {x.shape} and labels {y.shape} do not match")
    if y.all() or not y.any():
        raise SelfContraError("training samples must hold both positive and negative labels")
    params = {**constants.FOREST, **(forest or {})}
    clf = RandomForestClassifier(n_jobs=n_jobs, **params)
    with interrupts.immediate():  # minutes inside scikit-learn with no safe point of ours
        clf.fit(x, y.astype(np.int8))
    positive_class = int(np.flatnonzero(clf.classes_ == 1)[0])
    offsets = [0]
    parts: dict[str, list[NDArray[Any]]] = {name: [] for name in _ARRAYS if name != "tree_offsets"}
    for estimator in clf.estimators_:
        tree = estimator.tree_
        value = np.asarray(tree.value[:, 0, :], dtype=np.float64)
        share = value[:, positive_class] / np.maximum(value.sum(axis=1), 1e-300)
        parts["children_left"].append(tree.children_left)
        parts["children_right"].append(tree.children_right)
        parts["feature"].append(tree.feature)
        parts["threshold"].append(tree.threshold)
        parts["positive"].append(share)
        offsets.append(offsets[-1] + int(tree.node_count))
    meta = {**(metadata or {}), "n_features": int(x.shape[1]), "forest": {k: params[k] for k in sorted(params)}}
    model = ForestModel(
        tree_offsets=np.asarray(offsets, dtype=np.int64),
        metadata=meta,
        **{name: np.concatenate(chunks).astype(_ARRAYS[name]) for name, chunks in parts.items()},
    )
    _check(model, "trained model")
    return model


def model_path(path: Path | str) -> Path:
    """Where :func:`save_model` writes ``path``: the path as given, with ``.npz`` added only when it has no suffix."""
    path = Path(path)
    return path if path.suffix else path.with_name(path.name + ".npz")


def save_model(model: ForestModel, path: Path | str) -> Path:
    """Write ``model`` as a ``.npz`` of plain arrays (see the module docstring); returns the path written.

    The file is :func:`model_path` of ``path`` (``park.model`` stays
    ``park.model``; ``park`` becomes ``park.npz``), written atomically: a
    temporary file beside it, then a rename, so that a reader (the node
    loading ``model_in``, an interrupted run) never sees half a model.
    """
    path = model_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {**model.metadata, "format": FORMAT}
    arrays = {name: np.asarray(getattr(model, name), dtype=dtype) for name, dtype in _ARRAYS.items()}
    text = json.dumps(meta, sort_keys=True).encode("utf-8")
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.partial")
    try:
        with temporary.open("wb") as handle:  # a file object: numpy would append .npz to a name
            np.savez_compressed(handle, metadata=np.frombuffer(text, dtype=np.uint8), **arrays)  # type: ignore[arg-type]
        temporary.replace(path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def load_model(path: Path | str) -> ForestModel:
    """Read a model file written by :func:`save_model`; never unpickles (object arrays are refused).

    Raises:
        ModelError: naming the file when it is missing, not an ``.npz`` of the
            expected numeric arrays, holds object arrays, or is inconsistent.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"model file {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as archive:
            missing = sorted({*_ARRAYS, "metadata"} - set(archive.files))
            if missing:
                raise ModelError(f"model file {path} lacks arrays {missing}; is it a selfcontra model?")
            arrays = {name: archive[name] for name in (*_ARRAYS, "metadata")}
    except ModelError:
        raise
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        # np.load raises ValueError for pickled (object) content when allow_pickle=False.
        raise ModelError(f"model file {path} is not a plain-array .npz model: {exc}") from exc
    for name, dtype in _ARRAYS.items():
        if arrays[name].dtype.kind not in "iuf" or arrays[name].ndim != 1:
            raise ModelError(f"model file {path}: array {name} must be 1-D numeric, got {arrays[name].dtype}")
        arrays[name] = arrays[name].astype(dtype)
    if arrays["metadata"].dtype != np.uint8:
        raise ModelError(f"model file {path}: metadata must be uint8 JSON text")
    try:
        meta = json.loads(arrays["metadata"].tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"model file {path}: metadata is not JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelError(f"model file {path}: metadata format is not {FORMAT!r}")
    model = ForestModel(
        tree_offsets=arrays["tree_offsets"],
        children_left=arrays["children_left"],
        children_right=arrays["children_right"],
        feature=arrays["feature"],
        threshold=arrays["threshold"],
        positive=arrays["positive"],
        metadata=meta,
    )
    _check(model, f"model file {path}")
    return model


def _check(model: ForestModel, what: str) -> None:
    """Check that every child index stays inside its tree and inner nodes test a real column."""
    offsets = model.tree_offsets
    m = model.children_left.size
    sizes = {a.size for a in (model.children_right, model.feature, model.threshold, model.positive)}
    if sizes != {m} or offsets.size < 2 or offsets[0] != 0 or offsets[-1] != m or np.any(np.diff(offsets) < 1):
        raise ModelError(f"{what}: node arrays and tree offsets are inconsistent")
    tree_size = np.repeat(np.diff(offsets), np.diff(offsets))
    local = np.arange(m) - np.repeat(offsets[:-1], np.diff(offsets))
    inner = model.children_left >= 0
    for child in (model.children_left, model.children_right):
        # Children come after their parent (scikit-learn's depth-first order), which also rules out cycles.
        if np.any(inner & ((child <= local) | (child >= tree_size))):
            raise ModelError(f"{what}: a child index points outside its tree")
    if np.any(inner != (model.children_right >= 0)):
        raise ModelError(f"{what}: a node has exactly one child")
    n_features = model.n_features
    if np.any(inner & ((model.feature < 0) | (model.feature >= n_features))):
        raise ModelError(f"{what}: a split tests a feature outside 0..{n_features - 1}")
    if not np.all(np.isfinite(model.positive)) or np.any((model.positive < 0) | (model.positive > 1)):
        raise ModelError(f"{what}: positive shares must lie in [0, 1]")
