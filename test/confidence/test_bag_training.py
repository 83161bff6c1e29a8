"""Training and evaluation read bags like folders: same frames, same labels, same samples (bag_frames, commands)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import DEFAULT_STAMP_OFFSET_NS, kitti_to_mcap
from selfcontra_ros.bags.label_bag import label_bag
from selfcontra_ros.bags.reader import BagError, open_bag
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.confidence.bag_frames import BagFrame, is_bag, read_bag_labels
from selfcontra_ros.confidence.commands import (
    _label_source,
    collect_samples,
    evaluate_command,
    iter_frames,
    train_command,
)
from selfcontra_ros.confidence.forest import load_model
from selfcontra_ros.confidence.training import BAND_KEYS, Samples
from selfcontra_ros.config import load_params
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.pipeline import label_sequence

FRAMES, WIDTH, HEIGHT = 8, 320, 96
SMALL_FOREST = {"n_estimators": 3, "max_depth": 8, "min_samples_leaf": 5}
MATCHER = MatcherParams(num_disparities=32)
# A small window so that 8 frames give labelled views; no online retraining (not under test here). The
# ambiguity cues, the references' free-space band, the hole margin and the free-space view count are off (the
# paper's votes): on 8 tiny frames they leave too few views with both classes, and the test is about bag and
# folder giving the same samples, not about the labels. The fattening band reaches 24 px left, not 20: training
# must draw its band prior from the labels' own labeler, read from the bag's and the folder's metrics.json.
PARAMS = (
    "labeler:\n  ros__parameters:\n"
    "    matcher: {num_disparities: 48}\n"
    "    labeler: {window_size: 6, label_delay: 3, ambiguity_min_texture: 0.0, ambiguity_edge_px: 0.0,"
    " stage2_free_space_band: false, stage2_hole_margin_px: 0.0, stage2_free_space_min_views: 1,"
    " stage2_edge_occluded_side_px: 24}\n"
    "    confidence: {retrain_every: 1000}\n"
)


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A synthetic sequence, its bag, the bag labelled, and the sequence labelled with the same parameters."""
    from selfcontra_ros.datasets.synthetic import write_sequence

    root = tmp_path_factory.mktemp("bagtrain")
    sequence = root / "sequence"
    write_sequence(sequence, scene="street", frames=FRAMES, seed=1, width=WIDTH, height=HEIGHT)
    params = root / "params.yaml"
    params.write_text(PARAMS)
    in_bag = kitti_to_mcap(sequence, root / "in_bag", progress=False)
    labelled = root / "labelled"
    label_bag(in_bag, labelled, params_file=params, progress=False)
    folder = root / "folder_labels"
    label_sequence(sequence, folder, params_file=params)
    return {"sequence": sequence, "params": params, "in_bag": in_bag, "labelled": labelled, "folder": folder}


def _assert_same_samples(a: dict[str, Samples], b: dict[str, Samples]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name].features, b[name].features)
        np.testing.assert_array_equal(a[name].labels, b[name].labels)
        assert a[name].frames == b[name].frames


def test_bag_frames_equal_the_sequence_frames(data: dict[str, Path]) -> None:
    assert is_bag(data["in_bag"]) and not is_bag(data["sequence"])
    from_bag = list(iter_frames(data["in_bag"]))
    from_folder = list(iter_frames(data["sequence"]))
    assert [f.index for f in from_bag] == [f.index for f in from_folder] == list(range(FRAMES))
    for bag_frame, frame in zip(from_bag, from_folder, strict=True):
        assert isinstance(bag_frame, BagFrame)
        assert bag_frame.stamp_ns == DEFAULT_STAMP_OFFSET_NS + round(frame.stamp * 1e9)
        np.testing.assert_array_equal(bag_frame.left, frame.left)
        np.testing.assert_array_equal(bag_frame.right, frame.right)
        assert bag_frame.gt_disparity is not None and frame.gt_disparity is not None
        np.testing.assert_array_equal(bag_frame.gt_disparity, frame.gt_disparity)  # NaN where none, both
    # The labelled bag holds the input topics: the same frames again.
    relabelled = list(iter_frames(data["labelled"]))
    assert [f.stamp for f in relabelled] == [f.stamp for f in from_bag]


def test_bag_labels_give_the_samples_of_the_label_folder(data: dict[str, Path]) -> None:
    labels = read_bag_labels(data["labelled"])
    matcher, labeler = load_params(data["params"])
    assert labels.matcher == matcher and matcher.num_disparities == 48
    assert labels.labeler is not None and labeler.stage2_edge_occluded_side_px == 24
    assert all(getattr(labels.labeler, key) == getattr(labeler, key) for key in BAND_KEYS)
    folder_labeler = _label_source(data["folder"], data["sequence"]).labeler
    assert folder_labeler is not None and folder_labeler.stage2_edge_occluded_side_px == 24
    assert len(labels.images) >= 2, "the labeler labelled too few views for the test to mean anything"
    folder_samples, folder_params = collect_samples([(data["sequence"], data["folder"])], ["gcp", "park"])
    assert folder_params == matcher
    assert len(list((data["folder"] / "labels").glob("*.png"))) == len(labels.images)
    assert 2 <= folder_samples["gcp"].frames <= len(labels.images)  # views with one class contribute nothing
    assert folder_samples["gcp"].labels.any() and not folder_samples["gcp"].labels.all()
    for source in (data["labelled"], data["in_bag"]):  # the labelled bag itself, or the bag it was made from
        bag_samples, bag_params = collect_samples([(source, data["labelled"])], ["gcp", "park"])
        assert bag_params == matcher
        _assert_same_samples(bag_samples, folder_samples)


def test_train_command_on_bags(data: dict[str, Path], tmp_path: Path) -> None:
    summary = train_command([(data["labelled"], data["labelled"])], "gcp", tmp_path / "self", forest=SMALL_FOREST)
    model = load_model(summary["model"])
    assert model.metadata["label_source"] == "self" and model.metadata["matcher"]["num_disparities"] == 48
    assert summary["positive_share"] == pytest.approx(0.5)
    # Ground truth from /stereo/ground_truth/disparity: the folder's samples, and the folder's evaluation.
    gt_bag, _ = collect_samples([(data["in_bag"], "gt")], ["gcp"], matcher=MATCHER)
    gt_folder, _ = collect_samples([(data["sequence"], "gt")], ["gcp"], matcher=MATCHER)
    assert gt_bag["gcp"].frames == FRAMES
    _assert_same_samples(gt_bag, gt_folder)
    gt_model = train_command([(data["in_bag"], "gt")], "gcp", tmp_path / "gt", matcher=MATCHER, forest=SMALL_FOREST)
    on_bag = evaluate_command([gt_model["model"], "lrd"], data["in_bag"], tmp_path / "eval_bag")
    on_folder = evaluate_command([gt_model["model"], "lrd"], data["sequence"], tmp_path / "eval_folder")
    for name in ("gt", "lrd"):
        assert len(on_bag[name]["frames"]) == FRAMES
        assert on_bag[name]["mean"] == pytest.approx(on_folder[name]["mean"], nan_ok=True)


def test_clear_errors(data: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(SelfContraError, match="--data must be a bag"):
        collect_samples([(data["sequence"], data["labelled"])], ["gcp"])
    with pytest.raises(BagError, match="no label topic /stereo/labels"):
        collect_samples([(data["in_bag"], data["in_bag"])], ["gcp"])
    # Labels of another recording (same images, other stamps) match no frame.
    shifted = kitti_to_mcap(data["sequence"], tmp_path / "shifted", stamp_offset_ns=7 * 10**9, progress=False)
    with pytest.raises(SelfContraError, match=r"none of the \d+ label images .* matches .* 8 frames"):
        collect_samples([(shifted, data["labelled"])], ["gcp"])
    # A bag with poses but no images.
    with open_bag(data["in_bag"]) as bag, BagWriter(tmp_path / "poses_only", compress="none") as out:
        for message in bag.messages([topics.bag_topic(topics.POSE)]):
            out.write(message.topic, message.stamp_ns, message.msg)
    with pytest.raises(BagError, match=r"has no .*left/image_rect"):
        collect_samples([(tmp_path / "poses_only", "gt")], ["gcp"])
    with pytest.raises(BagError, match="does not exist"):
        list(iter_frames(tmp_path / "missing.mcap"))
