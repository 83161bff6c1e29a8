"""The offline ``selfcontra label`` run over a small synthetic sequence."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfcontra_ros.config import load_params
from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.evaluation.metrics import label_metrics, mean_metrics
from selfcontra_ros.labeler import Labeler, LabelerParams
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.matching.base import MatcherParams, make_matcher
from selfcontra_ros.pipeline import label_sequence
from selfcontra_ros.session import LabelingSession

FRAMES = 8
WIDTH, HEIGHT = 320, 96


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("street")
    write_sequence(root, scene="street", frames=FRAMES, seed=1, width=WIDTH, height=HEIGHT)
    return root


@pytest.fixture(scope="module")
def small_window(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Parameters with a window short enough for 8 frames: frames 0-4 get label_delay newer views, 5-7 not."""
    path = tmp_path_factory.mktemp("params") / "labeler.yaml"
    path.write_text("labeler:\n  ros__parameters:\n    labeler:\n      window_size: 6\n      label_delay: 3\n")
    return path


@pytest.fixture(scope="module")
def labelled(street: Path, small_window: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("labels")
    return out, label_sequence(street, out, params_file=small_window)


def test_writes_label_images_and_metrics(street: Path, labelled: tuple[Path, dict]) -> None:
    out, report = labelled
    on_disk = json.loads((out / "metrics.json").read_text())
    frames = [entry["frame"] for entry in on_disk["frames"]]
    assert frames == [0, 1, 2, 3, 4]  # the last label_delay frames are not labelled (flush_incomplete: false)
    assert on_disk["skipped_frames"] == [5, 6, 7]
    assert sorted(p.name for p in (out / "labels").iterdir()) == [f"{i:06d}.png" for i in frames]
    assert on_disk["has_ground_truth"] is True
    assert on_disk["params"]["matcher"]["algorithm"] == "sgbm"

    # Recompute each frame's figures from the written label image, a fresh SGBM run and the ground truth.
    sequence = open_sequence(street)
    matcher = make_matcher(load_params(None)[0])
    for entry in on_disk["frames"]:
        labels = cv2.imread(str(out / "labels" / f"{entry['frame']:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert labels.dtype == np.uint8 and labels.shape == (HEIGHT, WIDTH)
        colour = cv2.imread(str(out / "labels_color" / f"{entry['frame']:06d}.png"), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(colour[:, :, ::-1], colorize_labels(labels))
        frame = sequence[entry["frame"]]
        disparity = matcher.compute(frame.left, frame.right, with_right=False).left
        assert frame.gt_disparity is not None
        expected = label_metrics(labels, disparity, frame.gt_disparity)
        for key, value in expected.items():
            assert (entry[key] is None and math.isnan(value)) or entry[key] == pytest.approx(value), key
    # The mean is the mean over frames of the per-frame values, NaN (null) skipped.
    figures = [
        {k: (math.nan if v is None else v) for k, v in e.items() if k not in ("frame", "stamp")}
        for e in on_disk["frames"]
    ]
    for key, value in mean_metrics(figures).items():
        assert (on_disk["mean"][key] is None and math.isnan(value)) or on_disk["mean"][key] == pytest.approx(value)
    assert report["mean"]["coverage"] == pytest.approx(on_disk["mean"]["coverage"])
    assert 0.0 < report["mean"]["coverage"] <= 1.0


def test_labels_equal_a_direct_labeler_run(street: Path, small_window: Path, labelled: tuple[Path, dict]) -> None:
    """The pipeline adds nothing to the labels: the same Labeler fed by hand gives the same images."""
    out, _ = labelled
    matcher_params, labeler_params = load_params(small_window)
    sequence = open_sequence(street)
    matcher = make_matcher(matcher_params)
    labeler = Labeler(sequence.camera, labeler_params)
    results = []
    for frame in sequence:
        assert frame.pose is not None
        disparity = matcher.compute(frame.left, frame.right, with_right=False).left
        results += labeler.add_view(
            disparity,
            frame.pose,
            stamp=frame.stamp,
            key=frame.index,
            image=frame.left,
            max_disparity=matcher_params.max_disparity,
        )
    results += labeler.flush()
    assert results
    for result in results:
        written = cv2.imread(str(out / "labels" / f"{result.key:06d}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(written, result.labels)


def test_frame_range_and_params_file(street: Path, tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text("labeler:\n  ros__parameters:\n    matcher:\n      algorithm: bm\n      block_size: 7\n")
    report = label_sequence(street, tmp_path / "out", params_file=str(params), frames=slice(2, 6))
    assert report["params"]["matcher"]["algorithm"] == "bm"
    assert report["params"]["matcher"]["block_size"] == 7
    assert {e["frame"] for e in report["frames"]} | set(report["skipped_frames"]) == {2, 3, 4, 5}


def test_without_poses_is_a_clear_error(street: Path, tmp_path: Path) -> None:
    copy = tmp_path / "noposes"
    shutil.copytree(street, copy)
    (copy / "poses" / "00.txt").unlink()
    with pytest.raises(SelfContraError, match="no poses"):
        label_sequence(copy, tmp_path / "out")


def test_external_matcher_and_empty_range_are_rejected(street: Path, tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text("labeler:\n  ros__parameters:\n    matcher: {algorithm: external}\n")
    with pytest.raises(SelfContraError, match="external"):
        label_sequence(street, tmp_path / "out", params_file=str(params))
    with pytest.raises(SelfContraError, match="selects no frame"):
        label_sequence(street, tmp_path / "out", frames=slice(50, 60))


def test_without_ground_truth_reports_label_shares(street: Path, small_window: Path, tmp_path: Path) -> None:
    copy = tmp_path / "nogt"
    shutil.copytree(street, copy)
    shutil.rmtree(copy / "sequences" / "00" / "disp_0")
    report = label_sequence(copy, tmp_path / "out", params_file=small_window)
    assert report["has_ground_truth"] is False
    assert set(report["mean"]) == {
        "query_valid_share",
        "label_positive_share",
        "label_negative_share",
        "label_unknown_share",
    }
    for entry in report["frames"]:
        total = entry["label_positive_share"] + entry["label_negative_share"] + entry["label_unknown_share"]
        assert total == pytest.approx(1.0)


def test_the_session_tells_the_labeler_its_matchers_disparity_range(street: Path) -> None:
    sequence = open_sequence(street)
    frames = list(sequence)[:2]
    session = LabelingSession(sequence.camera, MatcherParams(num_disparities=32, min_disparity=4), LabelerParams())
    for frame in frames:
        assert frame.pose is not None
        session.process(frame.left, frame.right, frame.pose, stamp=frame.stamp, key=frame.index)
    assert [view.max_disparity for view in session.labeler.window] == [35.0, 35.0]
    external = LabelingSession(sequence.camera, MatcherParams(algorithm="external"), LabelerParams())
    disparity = make_matcher(MatcherParams()).compute(frames[0].left, frames[0].right, with_right=False).left
    assert frames[0].pose is not None
    external.process(frames[0].left, frames[0].right, frames[0].pose, stamp=0.0, key=0, external_disparity=disparity)
    assert [view.max_disparity for view in external.labeler.window] == [float("inf")]  # unknown: no limit
