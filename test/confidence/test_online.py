"""Online confidence: LRD mapping, reservoir bound and balance, atomic model swap, model files."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.confidence.features import compute_features
from selfcontra_ros.confidence.forest import ForestModel, ModelError
from selfcontra_ros.confidence.online import (
    ConfidenceFrame,
    ConfidenceParams,
    OnlineConfidence,
    Reservoir,
    filter_depth,
    lrd_confidence_map,
)
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.evaluation.metrics import ground_truth_labels
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE, POSITIVE
from selfcontra_ros.matching.base import MatcherParams, make_matcher

MATCHER = MatcherParams(num_disparities=64)
TINY_FOREST = {"n_estimators": 3, "max_depth": 6, "min_samples_leaf": 5}
TINY = {**TINY_FOREST, "samples_per_view": 300}


@pytest.fixture(scope="module")
def labelled_frames() -> list[tuple[ConfidenceFrame, np.ndarray]]:
    """Synthetic street frames (320x96) with SGBM disparities and ground-truth labels (|d - d_gt| <= 3 px)."""
    scene = make_scene("street", 2, 320, 96, frames=4)
    matcher = make_matcher(MATCHER)
    out = []
    for k in range(4):
        rendered = scene.render(k)
        pair = matcher.compute(rendered.left, rendered.right, with_right=True)
        labels = ground_truth_labels(pair.left, rendered.disparity)
        out.append((ConfidenceFrame(rendered.left, rendered.right, pair.left, pair.right, MATCHER), labels))
    return out


def _frame(disparity: np.ndarray, right: np.ndarray | None) -> ConfidenceFrame:
    grey = np.zeros(disparity.shape, np.uint8)
    return ConfidenceFrame(grey, grey, disparity.astype(np.float32), right, MatcherParams(num_disparities=16))


def test_lrd_map_follows_the_documented_formula() -> None:
    # Row 0: left disparity 4 everywhere; the right disparity at u - 4 disagrees by u/10 pixels.
    width = 40
    disparity = np.full((2, width), 4.0, np.float32)
    disagreement = np.arange(width, dtype=np.float32) / 10.0
    right = np.full((2, width), np.nan, np.float32)
    right[0, : width - 4] = 4.0 + disagreement[4:]
    disparity[1, :] = np.nan  # invalid row
    disparity[0, 2] = 0.0  # zero disparity: invalid
    confidence = lrd_confidence_map(_frame(disparity, right), scale=2.0)
    expected = np.exp(-disagreement[4:] / 2.0)
    np.testing.assert_allclose(confidence[0, 4:], expected, rtol=1e-6)
    assert np.all(np.diff(confidence[0, 4:]) < 0), "monotone: larger disagreement, lower confidence"
    assert np.all(confidence[1] == 0) and confidence[0, 2] == 0, "invalid disparities get 0"
    # u - d < 0 (no right pixel) and a missing right disparity: 0 (up to exp(-LRC_MISSING / scale)).
    assert np.all(confidence[0, :2] < 1e-30) and np.all(confidence[0, 3] < 1e-30)
    assert lrd_confidence_map(_frame(disparity, None), scale=2.0).max() < 1e-30
    assert confidence.dtype == np.float32 and confidence.min() >= 0 and confidence.max() <= 1


def test_filter_depth_is_nan_below_the_threshold() -> None:
    depth = np.array([[1.0, 2.0, np.nan, 4.0]], np.float32)
    confidence = np.array([[0.2, 0.5, 0.9, 0.7]], np.float32)
    filtered = filter_depth(depth, confidence, 0.5)
    np.testing.assert_array_equal(filtered, np.array([[np.nan, 2.0, np.nan, 4.0]], np.float32))


def test_reservoir_is_bounded_and_uniform() -> None:
    capacity, stream, trials = 10, 100, 3000
    hits = np.zeros(stream)
    rng = np.random.default_rng(1)
    for _ in range(trials):
        reservoir = Reservoir(capacity, 1, rng)
        for start in range(0, stream, 7):  # batches of uneven size
            reservoir.add(np.arange(start, min(start + 7, stream), dtype=np.float32)[:, None])
        kept = reservoir.sample()[:, 0].astype(int)
        assert reservoir.size == capacity and len(set(kept)) == capacity, "bounded, no duplicates"
        hits[kept] += 1
    # Every stream element is kept with probability capacity / stream = 0.1 (binomial std ~ 0.0055).
    share = hits / trials
    assert np.all(np.abs(share - 0.1) < 0.03), share
    assert abs(share[:50].mean() - share[50:].mean()) < 0.01, "early and late elements equally likely"


def test_reservoir_keeps_everything_below_capacity() -> None:
    reservoir = Reservoir(50, 2, np.random.default_rng(0))
    rows = np.arange(40, dtype=np.float32).reshape(20, 2)
    reservoir.add(rows)
    np.testing.assert_array_equal(reservoir.sample(), rows)


def test_params_are_checked() -> None:
    with pytest.raises(SelfContraError, match="feature_set"):
        ConfidenceParams(feature_set="sift")
    with pytest.raises(SelfContraError, match="confidence_threshold"):
        ConfidenceParams(confidence_threshold=1.5)
    with pytest.raises(SelfContraError, match="retrain_every"):
        ConfidenceParams(retrain_every=0)
    with pytest.raises(SelfContraError, match="band_look"):
        ConfidenceParams(band_look=float("nan"))
    with pytest.raises(SelfContraError, match="band_cue"):
        ConfidenceParams(band_cue=1.5)


def test_band_look_keeps_the_objects_own_band_pixels_out_of_the_reservoir(
    fattened_edge: tuple[np.ndarray, np.ndarray],
) -> None:
    image, d = fattened_edge  # the object from column 80 on, its disparity spread 6 px left
    frame = ConfidenceFrame(image, image, d, None, MatcherParams(num_disparities=48))
    labels = np.zeros(d.shape, np.uint8)
    labels[:, 120:190] = POSITIVE
    seen = {}
    for look in (float("inf"), -1.0):
        params = ConfidenceParams(
            retrain_every=100,
            samples_per_view=5000,
            band_look=look,
            band_cue=float("inf"),
            band_texture=0.0,
            **TINY_FOREST,
        )
        online = OnlineConfidence(params, background=False, log=lambda _: None)
        online.add_labelled(frame, labels)
        seen[look] = online.reservoirs[NEGATIVE].seen
    # The band is the 20 columns from 74; its fattened 6 columns look like the background.
    assert seen[float("inf")] == 40 * 20 and seen[-1.0] == 40 * 6
    # The band is that of the labeler whose views are added: 30 columns with a wider left reach.
    params = ConfidenceParams(
        retrain_every=100,
        samples_per_view=5000,
        band_look=float("inf"),
        band_cue=float("inf"),
        band_texture=0.0,
        **TINY_FOREST,
    )
    wide = LabelerParams(stage2_edge_occluded_side_px=30)
    online = OnlineConfidence(params, background=False, log=lambda _: None, labeler=wide)
    online.add_labelled(frame, labels)
    assert online.reservoirs[NEGATIVE].seen == 40 * 30


def test_band_cue_keeps_the_objects_own_band_pixels_out_of_the_reservoir(stereo_edge: dict[str, Any]) -> None:
    left, right, query = stereo_edge["left"], stereo_edge["right"], stereo_edge["query"]
    frame = ConfidenceFrame(left, right, query, None, MatcherParams(num_disparities=48))
    labels = np.zeros(query.shape, np.uint8)
    labels[:, 150:250] = POSITIVE
    seen = {}
    for name, cue in (("off", {"band_cue": float("inf")}), ("default", {})):
        params = ConfidenceParams(retrain_every=100, samples_per_view=50000, **cue, **TINY_FOREST)
        online = OnlineConfidence(params, background=False, log=lambda _: None)
        online.add_labelled(frame, labels)
        seen[name] = online.reservoirs[NEGATIVE].seen
    # The band is the 20 columns from the fattened 8: with the cue (the default) about the 8 fattened columns
    # are drawn, the object's own 12 mostly not.
    height = query.shape[0]
    assert seen["off"] == height * 20
    assert height * 6 < seen["default"] < height * 10


def test_labelled_views_give_a_balanced_bounded_reservoir_and_a_forest(labelled_frames: list) -> None:
    messages: list[str] = []
    params = ConfidenceParams(retrain_every=3, reservoir_per_class=500, **TINY)
    online = OnlineConfidence(params, background=False, log=messages.append)
    frame0 = labelled_frames[0][0]
    np.testing.assert_array_equal(online.confidence(frame0), lrd_confidence_map(frame0, params.lrd_scale))
    assert online.source == "lrd"
    for frame, labels in labelled_frames[:3]:
        assert online.model is None
        online.add_labelled(frame, labels)
    model = online.model
    assert model is not None and online.source == "gcp" and model.n_trees == 3
    positive, negative = online.reservoirs[POSITIVE], online.reservoirs[NEGATIVE]
    assert positive.seen == negative.seen > positive.capacity, "balanced offers beyond the capacity"
    assert positive.size == negative.size == 500
    assert messages[0] == "confidence: switched from LRD to the trained gcp forest (1000 samples)"
    # The published confidence is the forest's prediction at the valid pixels, 0 elsewhere.
    frame = labelled_frames[3][0]
    features, ctx = compute_features("gcp", frame.context(with_costs=True))
    confidence = online.confidence(frame)
    np.testing.assert_allclose(confidence[ctx.rows, ctx.cols], model.predict(features), atol=1e-6)
    assert np.all(confidence[~ctx.valid] == 0)
    assert not np.allclose(confidence, online.lrd(frame)), "the forest is not the LRD mapping"
    # The forest is better than chance on the held-out frame's ground-truth labels.
    labels = labelled_frames[3][1][ctx.rows, ctx.cols]
    known = labels != 0
    good = confidence[ctx.rows, ctx.cols][known][labels[known] == POSITIVE].mean()
    bad = confidence[ctx.rows, ctx.cols][known][labels[known] == NEGATIVE].mean()
    assert good > bad


def test_background_retraining_swaps_atomically(labelled_frames: list) -> None:
    messages: list[str] = []
    online = OnlineConfidence(ConfidenceParams(retrain_every=1, **TINY), background=True, log=messages.append)
    seen: list[ForestModel | None] = []
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            seen.append(online.model)

    thread = threading.Thread(target=reader)
    thread.start()
    try:
        for frame, labels in labelled_frames:
            assert online.add_labelled(frame, labels) or online.views_dropped > 0
            assert online.wait_idle(30.0)
    finally:
        stop.set()
        thread.join()
        online.close()
    assert online.models_trained == 4 - online.views_dropped
    # Every model a reader ever saw was a whole trained forest (or none yet): it predicts.
    models = {id(m): m for m in seen if m is not None}
    assert models and None in seen
    for model in models.values():
        assert model.predict(np.zeros((2, model.n_features), np.float32)).shape == (2,)
    assert sum("switched from LRD" in m for m in messages) == 1


def test_closing_drops_the_queued_views_and_takes_no_more(labelled_frames: list) -> None:
    """close(discard_queued=True), as a node stopping: the view in progress finishes, the queued ones and any
    offered afterwards are not learnt (counted in views_dropped), and the trainer ends."""
    online = OnlineConfidence(ConfidenceParams(retrain_every=1, **TINY), background=True, log=lambda m: None)
    started, release = threading.Event(), threading.Event()
    learnt: list[int] = []

    def slow_learn(frame: ConfidenceFrame, labels: np.ndarray) -> None:
        learnt.append(len(learnt))
        started.set()
        assert release.wait(30.0)

    online._learn = slow_learn  # type: ignore[method-assign]
    trainer = online._thread
    assert trainer is not None
    frame, labels = labelled_frames[0]
    assert online.add_labelled(frame, labels)
    assert started.wait(30.0), "the trainer should take the first view"
    assert online.add_labelled(frame, labels) and online.add_labelled(frame, labels)  # TRAINER_QUEUE views wait
    online.close(timeout=0.05, discard_queued=True)  # returns while the first view is still being learnt
    assert not online.add_labelled(frame, labels)
    release.set()
    trainer.join(30.0)
    assert not trainer.is_alive(), "the trainer should end after its view"
    assert learnt == [0] and online.views_dropped == 3
    online.close()  # a second close is harmless


def test_model_out_and_model_in_round_trip(labelled_frames: list, tmp_path: Path) -> None:
    path = tmp_path / "models" / "online.npz"
    trainer = OnlineConfidence(
        ConfidenceParams(retrain_every=2, model_out=str(path), **TINY), background=False, log=lambda m: None
    )
    for frame, labels in labelled_frames[:2]:
        trainer.add_labelled(frame, labels)
    assert path.is_file() and not list(path.parent.glob("*.tmp.npz"))
    messages: list[str] = []
    loaded = OnlineConfidence(ConfidenceParams(model_in=str(path)), background=False, log=messages.append)
    assert loaded.source == "gcp" and "switched from LRD" in messages[0]
    frame = labelled_frames[3][0]
    np.testing.assert_array_equal(loaded.confidence(frame), trainer.confidence(frame))
    with pytest.raises(ModelError, match="feature set"):
        OnlineConfidence(ConfidenceParams(feature_set="park", model_in=str(path)), background=False)


def test_trainer_thread_runs_under_the_thread_cap(labelled_frames: list, monkeypatch: pytest.MonkeyPatch) -> None:
    """numba's thread count is per thread: the trainer re-applies the recorded cap before its first view."""
    import numba

    from selfcontra_ros import threads

    if numba.config.NUMBA_NUM_THREADS < 2:  # type: ignore[attr-defined]
        pytest.skip("numba runs a single thread here: a cap of 1 would change nothing")
    # The cap as limit_threads(1) records it, without changing this thread's pools.
    monkeypatch.setattr(threads, "_cap", 1)
    seen: list[tuple[str, int]] = []

    def learn(self: OnlineConfidence, frame: ConfidenceFrame, labels: np.ndarray) -> None:
        seen.append((threading.current_thread().name, numba.get_num_threads()))

    monkeypatch.setattr(OnlineConfidence, "_learn", learn)
    online = OnlineConfidence(ConfidenceParams(**TINY), background=True)
    try:
        frame, labels = labelled_frames[0]
        assert online.add_labelled(frame, labels)
        assert online.wait_idle(30.0)
    finally:
        online.close()
    assert seen == [("selfcontra_confidence_trainer", 1)]
