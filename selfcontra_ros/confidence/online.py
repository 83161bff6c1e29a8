"""Online confidence: a confidence image for every frame, a forest retrained on the labels as they come.

DESIGN section 4: each new frame gets a confidence image at once from the
current model (the LRD baseline before any model exists); the labelled views
feed a bounded, class-balanced reservoir of training samples; a background
thread retrains the forest every ``retrain_every`` labelled views and swaps
it in atomically; models are loaded (``model_in``) and saved (``model_out``)
explicitly, as the plain-array files of :mod:`selfcontra_ros.confidence.forest`.

**Confidence values** (float32 in [0, 1], 0 where the query disparity is
invalid, i.e. not finite, not > 0 or outside the search range):

* before a model exists, the LRD baseline mapped monotonically to [0, 1]:
  ``exp(-|d(u) - d_R(u - round(d(u)))| / lrd_scale)`` (``lrd_scale`` in
  pixels; 1 for perfect left-right agreement, about 0.37 at ``lrd_scale``
  pixels of disagreement, 0 where the right disparity is missing);
* with a model, the forest's predicted probability of the positive class
  (:meth:`~selfcontra_ros.confidence.forest.ForestModel.predict`).

**Cost.** LRD needs only the right disparity (a second matcher run, tens of
milliseconds at KITTI size). A forest needs the feature set's measures, hence
the census costs: they are summed a few rows at a time inside the cost-curve
statistics and never stored (:class:`~selfcontra_ros.matching.census.WindowedCensusCosts`),
and features and forest touch only the valid pixels. At KITTI size (1226x370,
128 disparities, about 380k valid pixels, ``bench/confidence_speed.py`` on 2
cores shared with other jobs, load about 3) the default ``gcp`` set takes
about 0.1-0.17 s for census and features and 0.06-0.12 s for this online
forest (10 trees, depth 12), 1.3-1.55x the time of OpenCV SGBM with its right
disparity; the paper's forest (20 trees, depth 20) 0.2-0.33 s instead;
``ensemble`` and ``park`` 0.55-0.7 s of features. A robot at 10 Hz therefore
gets forest confidences off the subscription thread (the labeler node's
confidence worker), and the sample extraction of the labelled views runs in
the trainer thread here, never on the caller's; both run numba kernels and
apply the thread cap of :func:`~selfcontra_ros.threads.limit_threads` first.

**Reservoir.** Each labelled view contributes ``n = min(#positive, #negative,
samples_per_view)`` samples of each class (:func:`~selfcontra_ros.confidence.training.balanced_indices`);
each class keeps a uniform sample of everything it was offered (reservoir
sampling, at most ``reservoir_per_class`` rows). Both classes are offered the
same number of rows, so the reservoirs stay balanced; training uses
``min`` of the two sizes of each.

**Threads.** With ``background=True`` (the ROS node) :meth:`OnlineConfidence.add_labelled`
only queues the view (at most :data:`TRAINER_QUEUE` views; a view finding the
queue full is not used and counted in ``views_dropped``); one trainer thread
extracts samples and retrains. The model is one reference replaced by a single
assignment under a lock, so a reader sees the old or the new forest, never a
mix. With ``background=False`` (the offline labelers) the same work runs in
the caller's thread, so a bag run is reproducible.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.features import (
    FeatureContext,
    FeatureInput,
    compute_features,
    feature_names,
    left_right_consistency,
)
from selfcontra_ros.confidence.forest import ForestModel, ModelError, load_model, save_model
from selfcontra_ros.confidence.inputs import census_costs
from selfcontra_ros.confidence.training import BandPrior, balanced_indices
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE, POSITIVE
from selfcontra_ros.matching.base import MatcherParams, to_grey
from selfcontra_ros.matching.census import WindowedCensusCosts
from selfcontra_ros.threads import apply_thread_limit

__all__ = [
    "LRD",
    "TRAINER_QUEUE",
    "ConfidenceFrame",
    "ConfidenceParams",
    "OnlineConfidence",
    "Reservoir",
    "filter_depth",
    "lrd_confidence_map",
]

_LOG = logging.getLogger(__name__)

#: Source name of the LRD baseline (``OnlineConfidence.source`` before a model exists).
LRD = "lrd"
#: Labelled views waiting for the background trainer.
TRAINER_QUEUE = 2


@dataclass(frozen=True)
class ConfidenceParams:
    """Parameters of the online confidence (section ``confidence`` of ``config/labeler.yaml``).

    The forest is smaller than the paper's (20 trees, depth 20, min leaf 100)
    so that a retraining on a full reservoir (2 x 20000 rows of 8 features)
    takes a few seconds on one core in the background.

    Attributes:
        feature_set: features of the forest: ``gcp`` (default: 8 features, the
            cheapest set online), ``ensemble`` or ``park``.
        confidence_threshold: ``depth/filtered`` is NaN where the confidence is
            below this, in [0, 1].
        lrd_scale: pixels of left-right disagreement at which the LRD confidence is ``exp(-1)``; > 0.
        retrain_every: retrain after this many labelled views (each view that gave samples counts).
        reservoir_per_class: capacity of each class's reservoir, samples.
        samples_per_view: at most this many samples of each class from one labelled view.
        band_negatives: the share of a labelled view's unlabelled pixels in the query's fattening band drawn
            as negatives (:func:`~selfcontra_ros.confidence.training.band_negatives`, as ``selfcontra
            train --band-negatives``; 0 = the paper).
        band_look: of those, the ones that look at least this much more like the object at their disparity
            than like the background beyond their drop stay out of the draw (as ``selfcontra train
            --band-look``; ``inf``: off, the default).
        band_cue: of those, the ones the band cue calls right with at least this probability stay out of the
            draw (as ``selfcontra train --band-cue``; ``inf``: off).
        band_texture: and so do those whose thin strip varies by less than this many grey levels (as
            ``selfcontra train --band-texture``; 0: off).
        n_estimators: trees of the online forest.
        max_depth: depth limit of each tree.
        min_samples_leaf: smallest leaf, samples.
        model_in: model file (``.npz``) to start from instead of LRD; ``""`` = none.
        model_out: model file written after every retraining; ``""`` = none.
        seed: seed of the sample draws and of the forest.
    """

    feature_set: str = "gcp"
    confidence_threshold: float = 0.5
    lrd_scale: float = 1.0
    retrain_every: int = 10
    reservoir_per_class: int = 20000
    samples_per_view: int = 2000
    band_negatives: float = float(constants.TRAINING["band_negatives"])
    band_look: float = float(constants.TRAINING["band_look"])
    band_cue: float = float(constants.TRAINING["band_cue"])
    band_texture: float = float(constants.TRAINING["band_texture"])
    n_estimators: int = 10
    max_depth: int = 12
    min_samples_leaf: int = 20
    model_in: str = ""
    model_out: str = ""
    seed: int = 0

    def __post_init__(self) -> None:
        """Check the values; raises SelfContraError naming the offending one."""
        if self.feature_set not in constants.FEATURE_SETS:
            raise SelfContraError(
                f"ConfidenceParams.feature_set is {self.feature_set!r}; expected one of "
                f"{', '.join(constants.FEATURE_SETS)}"
            )
        if not 0.0 <= self.confidence_threshold <= 1.0:
            raise SelfContraError(
                f"ConfidenceParams.confidence_threshold must be in [0, 1], got {self.confidence_threshold}"
            )
        if not (np.isfinite(self.lrd_scale) and self.lrd_scale > 0):
            raise SelfContraError(f"ConfidenceParams.lrd_scale must be > 0 pixels, got {self.lrd_scale}")
        for name in ("retrain_every", "reservoir_per_class", "samples_per_view", "n_estimators", "min_samples_leaf"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise SelfContraError(f"ConfidenceParams.{name} must be an integer >= 1, got {value!r}")
        for name in ("band_negatives", "band_look", "band_cue", "band_texture"):
            if not isinstance(getattr(self, name), float):
                raise SelfContraError(f"ConfidenceParams.{name} must be a number, got {getattr(self, name)!r}")
        try:
            self.band_prior()
        except SelfContraError as exc:
            raise SelfContraError(
                f"ConfidenceParams.band_negatives / band_look / band_cue / band_texture: {exc}"
            ) from exc
        if isinstance(self.max_depth, bool) or not isinstance(self.max_depth, int) or self.max_depth < 1:
            raise SelfContraError(f"ConfidenceParams.max_depth must be an integer >= 1, got {self.max_depth!r}")

    def band_prior(self) -> BandPrior:
        """The band prior of the labelled views (:class:`~selfcontra_ros.confidence.training.BandPrior`)."""
        return BandPrior(share=self.band_negatives, look=self.band_look, cue=self.band_cue, texture=self.band_texture)

    def forest(self) -> dict[str, Any]:
        """Forest overrides for :func:`~selfcontra_ros.confidence.forest.fit_forest`."""
        return {
            "n_estimators": self.n_estimators,
            "max_depth": self.max_depth,
            "min_samples_leaf": self.min_samples_leaf,
            "random_state": self.seed,
        }


@dataclass
class ConfidenceFrame:
    """What the confidence of one frame reads: the rectified pair and the query's two disparity maps.

    Attributes:
        left: HxW grey (or HxWx3 RGB) uint8 left image.
        right: right image, same shape.
        disparity: HxW float32 left query disparity, pixels, NaN invalid.
        disparity_right: HxW float32 right disparity, pixels, NaN invalid; None when unknown (external).
        matcher: the query algorithm's parameters (disparity search range of the cost volume).
    """

    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    disparity: NDArray[np.float32]
    disparity_right: NDArray[np.float32] | None
    matcher: MatcherParams = field(default_factory=MatcherParams)

    def context(self, *, with_costs: bool) -> FeatureContext:
        """The measures' context; without costs, a zero-strided stand-in volume (LRD reads no costs).

        The costs are the census costs summed over a small window, the cost
        input of ``selfcontra train`` for SGBM, BM and external disparities
        (for ``census_sgm`` too here, whose own aggregated costs the online
        path does not keep).
        """
        shape = self.disparity.shape
        volume: NDArray[Any] | WindowedCensusCosts
        if with_costs:
            volume, scale = census_costs(self.left, self.right, self.matcher)
        else:
            volume = np.broadcast_to(np.zeros((1, 1, 1), np.uint16), (*shape, self.matcher.num_disparities))
            scale = 1.0
        data = FeatureInput(
            left=to_grey(self.left),
            right=to_grey(self.right),
            disparity=self.disparity,
            disparity_right=self.disparity_right,
            costs=volume,
            cost_scale=scale,
            min_disparity=self.matcher.min_disparity,
        )
        return FeatureContext(data)


def lrd_confidence_map(frame: ConfidenceFrame, scale: float) -> NDArray[np.float32]:
    """LRD confidence of every pixel: ``exp(-|d - d_R(u - round(d))| / scale)``, 0 where invalid (module docstring).

    Args:
        frame: the frame's disparities (its images are not read).
        scale: pixels of disagreement giving ``exp(-1)``.

    Returns:
        HxW float32 in [0, 1].
    """
    ctx = frame.context(with_costs=False)
    out = np.zeros(ctx.shape, dtype=np.float32)
    out[ctx.rows, ctx.cols] = np.exp(-left_right_consistency(ctx) / np.float32(scale))
    return out


def filter_depth(depth: NDArray[np.float32], confidence: NDArray[np.float32], threshold: float) -> NDArray[np.float32]:
    """``depth`` with NaN where ``confidence < threshold`` (metres, float32)."""
    return np.where(confidence >= np.float32(threshold), depth, np.float32(np.nan)).astype(np.float32)


class Reservoir:
    """A uniform sample of at most ``capacity`` rows of everything offered (reservoir sampling, Algorithm R).

    Args:
        capacity: rows kept.
        width: columns of a row.
        rng: random generator of the replacements.
    """

    def __init__(self, capacity: int, width: int, rng: np.random.Generator) -> None:
        self.capacity = int(capacity)
        self.rows = np.zeros((self.capacity, width), dtype=np.float32)
        self.size = 0
        self.seen = 0
        self._rng = rng

    def add(self, rows: NDArray[np.floating]) -> None:
        """Offer ``rows`` (N x width) in order; stream row ``i`` replaces a random slot w.p. capacity/(i+1)."""
        rows = np.asarray(rows, dtype=np.float32)
        n = rows.shape[0]
        if n == 0:
            return
        index = self.seen + np.arange(n)
        self.seen += n
        fill = index < self.capacity
        self.rows[index[fill]] = rows[fill]
        self.size = min(self.seen, self.capacity)
        later = np.flatnonzero(~fill)
        if later.size == 0:
            return
        slot = (self._rng.random(later.size) * (index[later] + 1)).astype(np.int64)
        keep = slot < self.capacity
        later, slot = later[keep], slot[keep]
        # Sequential semantics: when two rows pick the same slot the later one wins.
        last = slot.size - 1 - np.unique(slot[::-1], return_index=True)[1]
        self.rows[slot[last]] = rows[later[last]]

    def sample(self) -> NDArray[np.float32]:
        """A copy of the rows kept."""
        return self.rows[: self.size].copy()


class OnlineConfidence:
    """Per-frame confidence from the current model, samples from labelled views, retraining, model files.

    Args:
        params: see :class:`ConfidenceParams`; ``model_in`` is loaded at once.
        background: run sample extraction and retraining in a trainer thread (module docstring).
        log: receives the progress messages (swaps, retrainings, failures); default: this module's logger.
        labeler: the parameters of the labeler whose views are added; the band prior (``band_negatives``) uses
            its fattening band's sizes. None: the default labeler's.

    Raises:
        ModelError: ``model_in`` cannot be read or was trained on another feature set.
    """

    def __init__(
        self,
        params: ConfidenceParams | None = None,
        *,
        background: bool = True,
        log: Callable[[str], object] | None = None,
        labeler: LabelerParams | None = None,
    ) -> None:
        self.params = params if params is not None else ConfidenceParams()
        self.labeler = labeler
        self._log = log if log is not None else _LOG.info
        self._lock = threading.Lock()
        self._model: ForestModel | None = None
        self._model_samples = 0
        rng = np.random.default_rng(self.params.seed)
        width = len(feature_names(self.params.feature_set))
        self._draw_rng, res_rng = rng.spawn(2)
        self.reservoirs = {
            POSITIVE: Reservoir(self.params.reservoir_per_class, width, res_rng),
            NEGATIVE: Reservoir(self.params.reservoir_per_class, width, res_rng),
        }
        self.views_added = 0
        self.views_dropped = 0
        self.models_trained = 0
        self.last_training_s = 0.0
        if self.params.model_in:
            self.load(self.params.model_in)
        self._queue: queue.Queue[tuple[ConfidenceFrame, NDArray[np.uint8]] | None] = queue.Queue(TRAINER_QUEUE)
        self._idle = threading.Event()
        self._idle.set()
        self._thread: threading.Thread | None = None
        self._background = background
        self._close_lock = threading.Lock()  # a view is queued before the trainer closes or not at all
        if background:
            self._thread = threading.Thread(target=self._trainer, name="selfcontra_confidence_trainer", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ model

    @property
    def model(self) -> ForestModel | None:
        """The current forest (None: LRD)."""
        with self._lock:
            return self._model

    @property
    def source(self) -> str:
        """``"lrd"`` or the current forest's feature set."""
        return LRD if self.model is None else self.params.feature_set

    def load(self, path: str | Path) -> ForestModel:
        """Load a model file and use it from now on.

        Raises:
            ModelError: unreadable, or trained on another feature set or feature version.
        """
        model = load_model(path)
        feature_set = model.metadata.get("feature_set")
        if feature_set != self.params.feature_set:
            raise ModelError(
                f"model file {path} was trained on feature set {feature_set!r}; confidence.feature_set is "
                f"{self.params.feature_set!r}"
            )
        if model.metadata.get("constants_version", constants.VERSION) != constants.VERSION:
            raise ModelError(
                f"model file {path} has feature version {model.metadata.get('constants_version')}, "
                f"the package {constants.VERSION}"
            )
        self._swap(model, int(model.metadata.get("training_samples", 0)), f"loaded from {path}")
        return model

    def save(self, path: str | Path) -> Path | None:
        """Write the current model to ``path`` atomically (see ``forest.save_model``); None without a model."""
        model = self.model
        if model is None:
            return None
        return save_model(model, path)

    def _swap(self, model: ForestModel, samples: int, how: str) -> None:
        with self._lock:
            first = self._model is None
            self._model = model
            self._model_samples = samples
        if first:
            self._log(
                f"confidence: switched from LRD to the trained {self.params.feature_set} forest ({samples} samples)"
                + ("" if how == "trained" else f", {how}")
            )
        else:
            self._log(f"confidence: {self.params.feature_set} forest {how} ({samples} samples)")

    # ------------------------------------------------------------------ per frame

    def confidence(self, frame: ConfidenceFrame, model: ForestModel | None = None) -> NDArray[np.float32]:
        """Confidence of every pixel of ``frame`` (module docstring), HxW float32 in [0, 1].

        Args:
            frame: the frame.
            model: the forest to use; default the current one (LRD without).
        """
        model = model if model is not None else self.model
        if model is None:
            return lrd_confidence_map(frame, self.params.lrd_scale)
        features, ctx = compute_features(self.params.feature_set, frame.context(with_costs=True))
        out = np.zeros(ctx.shape, dtype=np.float32)
        out[ctx.rows, ctx.cols] = model.predict(features)
        return out

    def lrd(self, frame: ConfidenceFrame) -> NDArray[np.float32]:
        """The LRD confidence of ``frame`` whatever the model (cheap)."""
        return lrd_confidence_map(frame, self.params.lrd_scale)

    # ------------------------------------------------------------------ learning

    def add_labelled(self, frame: ConfidenceFrame, labels: NDArray[np.uint8]) -> bool:
        """Feed a labelled view (its frame and HxW label codes); retrains every ``retrain_every`` views.

        In the background mode the view is queued; returns False when the
        queue was full or the trainer was closed (the view is not used,
        ``views_dropped`` counts it).
        """
        if not self._background:
            self._learn(frame, labels)
            return True
        with self._close_lock:
            if self._thread is None:  # closed
                self.views_dropped += 1
                return False
            try:
                self._idle.clear()
                self._queue.put_nowait((frame, labels))
            except queue.Full:
                self.views_dropped += 1
                return False
        return True

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until the trainer has handled every queued view (background mode); True when idle."""
        if self._thread is None:
            return True
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._queue.unfinished_tasks == 0:
                return True
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                return False
            self._idle.wait(0.05 if remaining is None else min(0.05, remaining))

    def close(self, timeout: float = 10.0, *, discard_queued: bool = False) -> None:
        """Stop the trainer thread (after the view it is working on); safe to call twice.

        A background trainer takes no views after this (:meth:`add_labelled` counts them in
        ``views_dropped``). ``discard_queued``: the views still queued are not learnt either (counted
        the same way), so that a node stopping does not wait for their samples and retrainings.
        """
        with self._close_lock:
            thread, self._thread = self._thread, None
            if thread is None:
                return
            while discard_queued:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    break
                self.views_dropped += 1
                self._queue.task_done()
            if self._queue.unfinished_tasks == 0:
                self._idle.set()
        while True:
            try:
                self._queue.put(None, timeout=timeout)
                break
            except queue.Full:  # pragma: no cover - the trainer frees a slot after each view
                continue
        thread.join(timeout)

    def _trainer(self) -> None:
        # numba's and OpenMP's thread counts are per thread: this one starts with every core otherwise.
        apply_thread_limit()
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                self._learn(*item)
            except Exception as exc:  # the trainer must survive a bad view
                self._log(f"confidence: learning from a labelled view failed: {type(exc).__name__}: {exc}")
            finally:
                self._queue.task_done()
                if self._queue.unfinished_tasks == 0:
                    self._idle.set()

    def _learn(self, frame: ConfidenceFrame, labels: NDArray[np.uint8]) -> None:
        # Also checks that the label image has the disparity map's shape.
        labels = self.params.band_prior().apply(
            labels, frame.disparity, self._draw_rng, left=frame.left, right=frame.right, labeler=self.labeler
        )
        # The cheap context first: a view without both classes costs no census volume.
        at_valid = labels[frame.context(with_costs=False).valid]
        chosen = balanced_indices(at_valid, self.params.samples_per_view, self._draw_rng)
        if chosen.size == 0:
            return
        features, _ = compute_features(self.params.feature_set, frame.context(with_costs=True))
        positive = at_valid[chosen] == POSITIVE
        with self._lock:
            self.reservoirs[POSITIVE].add(features[chosen[positive]])
            self.reservoirs[NEGATIVE].add(features[chosen[~positive]])
            self.views_added += 1
            due = self.views_added % self.params.retrain_every == 0
        if due:
            self.retrain()

    def training_set(self) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """The reservoirs' rows, balanced (``min`` of the two sizes of each class), and their labels."""
        with self._lock:
            positive = self.reservoirs[POSITIVE].sample()
            negative = self.reservoirs[NEGATIVE].sample()
        n = min(positive.shape[0], negative.shape[0])
        features = np.concatenate([positive[:n], negative[:n]])
        labels = np.concatenate([np.ones(n, bool), np.zeros(n, bool)])
        return features, labels

    def retrain(self) -> ForestModel | None:
        """Train a forest on the reservoirs now and swap it in (and save it to ``model_out``); None if impossible."""
        from selfcontra_ros.confidence.forest import fit_forest

        features, labels = self.training_set()
        if labels.size == 0:
            return None
        started = time.perf_counter()
        metadata = {
            "feature_set": self.params.feature_set,
            "feature_names": feature_names(self.params.feature_set),
            "constants_version": constants.VERSION,
            "training_samples": int(labels.size),
            "training_frames": int(self.views_added),
            "training_positive_share": 0.5,
            "source": "online",
        }
        try:
            model = fit_forest(features, labels, metadata, n_jobs=1, forest=self.params.forest())
        except SelfContraError as exc:
            self._log(f"confidence: retraining failed: {exc}")
            return None
        self.last_training_s = time.perf_counter() - started
        self.models_trained += 1
        self._swap(model, int(labels.size), "trained" if self.models_trained == 1 else "retrained")
        if self.params.model_out:
            try:
                self.save(self.params.model_out)
            except OSError as exc:
                self._log(f"confidence: cannot write model_out {self.params.model_out}: {exc}")
        return model

    def stats(self) -> dict[str, Any]:
        """Counters, JSON-ready: source, views added and dropped, reservoir sizes, models trained."""
        with self._lock:
            return {
                "source": LRD if self._model is None else self.params.feature_set,
                "model_samples": self._model_samples,
                "views_added": self.views_added,
                "views_dropped": self.views_dropped,
                "reservoir": [self.reservoirs[POSITIVE].size, self.reservoirs[NEGATIVE].size],
                "models_trained": self.models_trained,
                "last_training_s": round(self.last_training_s, 3),
            }
