"""Training and evaluation commands end to end on a tiny synthetic sequence, and the data readers."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfcontra_ros.confidence.commands import confidence_table, evaluate_command, iter_frames, train_command
from selfcontra_ros.confidence.features import FeatureContext
from selfcontra_ros.confidence.forest import load_model
from selfcontra_ros.confidence.inputs import query_feature_input
from selfcontra_ros.confidence.training import balanced_indices
from selfcontra_ros.datasets.middlebury import read_middlebury
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.evaluation.metrics import ground_truth_labels
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.matching.base import MatcherParams, make_matcher

SMALL_FOREST = {"n_estimators": 3, "max_depth": 8, "min_samples_leaf": 5}
MATCHER = MatcherParams(num_disparities=32)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("synthetic")
    write_sequence(root, scene="street", frames=2, seed=5, width=240, height=96)
    return root


def test_balanced_indices() -> None:
    labels = np.array([POSITIVE] * 7 + [NEGATIVE] * 3 + [UNKNOWN] * 5)
    rng = np.random.default_rng(0)
    chosen = balanced_indices(labels, 100, rng)
    assert np.sum(labels[chosen] == POSITIVE) == 3 and np.sum(labels[chosen] == NEGATIVE) == 3
    assert balanced_indices(labels, 2, rng).size == 4
    assert balanced_indices(np.full(4, POSITIVE), 10, rng).size == 0


def test_train_on_ground_truth_and_evaluate(sequence: Path, tmp_path: Path) -> None:
    summary = train_command([(sequence, "gt")], "gcp", tmp_path / "gcp", matcher=MATCHER, forest=SMALL_FOREST)
    model = load_model(summary["model"])
    assert model.metadata["feature_set"] == "gcp" and model.metadata["label_source"] == "gt"
    assert model.metadata["matcher"]["num_disparities"] == 32
    assert summary["positive_share"] == pytest.approx(0.5)
    results = evaluate_command([summary["model"], "lrd"], sequence, tmp_path / "eval")
    for name in ("gcp", "lrd"):
        record = json.loads((tmp_path / "eval" / name / "metrics.json").read_text())
        assert len(record["frames"]) == 2
        assert set(record["mean"]) == {"ausc", "optimal", "ausc_ratio", "bad_rate"}
        assert record["mean"]["ausc_ratio"] >= 1.0 - 1e-9
        assert record["mean"]["ausc"] == pytest.approx(np.mean([f["ausc"] for f in record["frames"]]))
    assert results["gcp"]["mean"]["bad_rate"] == results["lrd"]["mean"]["bad_rate"]
    assert (tmp_path / "eval" / "sparsification.png").stat().st_size > 1000
    assert "| ground truth |" in (tmp_path / "eval" / "table.md").read_text()
    single = evaluate_command("lrd", sequence, tmp_path / "single")
    assert (tmp_path / "single" / "metrics.json").is_file() and "lrd" in single


def test_wls_baseline_is_scored_on_the_same_pixels_as_lrd(sequence: Path, tmp_path: Path) -> None:
    results = evaluate_command(["lrd", "wls", "wls"], sequence, tmp_path / "eval", matcher=MATCHER)
    assert sorted(n for n in results if n != "table") == ["lrd", "wls"]  # a repeated baseline counts once
    for lrd_frame, wls_frame in zip(results["lrd"]["frames"], results["wls"]["frames"], strict=True):
        assert wls_frame["frame"] == lrd_frame["frame"]
        assert wls_frame["pixels"] == lrd_frame["pixels"] and wls_frame["bad_rate"] == lrd_frame["bad_rate"]
        assert wls_frame["ausc"] >= wls_frame["optimal"] - 1e-12
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["models"]["wls"]["feature_set"] == "wls" and summary["models"]["wls"]["source"] == "none"
    lines = (tmp_path / "eval" / "table.md").read_text().splitlines()
    assert lines[0] == "| training source | LRD | WLS | Ensemble | Park | GCP |"
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    assert cells[0] == "-" and cells[3:] == ["-", "-", "-"]
    assert float(cells[1]) == pytest.approx(results["lrd"]["mean"]["ausc_ratio"], abs=5e-4)
    assert float(cells[2]) == pytest.approx(results["wls"]["mean"]["ausc_ratio"], abs=5e-4)


def test_train_on_label_folder_uses_its_query_algorithm(sequence: Path, tmp_path: Path) -> None:
    labels_out = tmp_path / "labels_run"
    (labels_out / "labels").mkdir(parents=True)
    matcher = make_matcher(MATCHER)
    for frame in iter_frames(sequence):
        ctx = FeatureContext(query_feature_input(matcher, frame.left, frame.right))
        assert frame.gt_disparity is not None
        labels = ground_truth_labels(ctx.data.disparity, frame.gt_disparity)
        cv2.imwrite(str(labels_out / "labels" / f"{frame.index:06d}.png"), labels)
    (labels_out / "metrics.json").write_text(json.dumps({"params": {"matcher": asdict(MATCHER)}}))
    summary = train_command([(sequence, labels_out)], "park", tmp_path / "park.npz", forest=SMALL_FOREST)
    model = load_model(summary["model"])
    assert model.metadata["label_source"] == "self"
    assert model.metadata["matcher"] == asdict(MATCHER)
    assert summary["frames"] == 2


def test_confidence_table_layout() -> None:
    rows = [
        {"feature_set": "lrd", "source": "none", "ausc_ratio": 2.8},
        {"feature_set": "wls", "source": "none", "ausc_ratio": 2.6},
        {"feature_set": "ensemble", "source": "gt", "ausc_ratio": 1.97},
        {"feature_set": "ensemble", "source": "self", "ausc_ratio": 1.95},
        {"feature_set": "gcp", "source": "self", "ausc_ratio": 2.45},
    ]
    lines = confidence_table(rows).splitlines()
    assert lines[0] == "| training source | LRD | WLS | Ensemble | Park | GCP |"
    assert lines[1] == "|---|---|---|---|---|---|"
    assert lines[2] == "| ground truth | 2.800 | 2.600 | 1.970 | - | - |"
    assert lines[3] == "| self-generated labels | 2.800 | 2.600 | 1.950 | - | 2.450 |"
    # Baselines alone: one row, the forest columns empty.
    only = confidence_table(rows[:2]).splitlines()
    assert only[2] == "| - | 2.800 | 2.600 | - | - | - |"


def test_middlebury_reader(shared_data: Path) -> None:
    frame = read_middlebury(shared_data / "middlebury2003" / "cones")
    assert frame.left.shape == (375, 450, 3) and frame.right.shape == frame.left.shape
    assert frame.gt_disparity is not None
    valid = np.isfinite(frame.gt_disparity)
    assert valid.mean() > 0.5
    # Cones' disparities lie within the published 0..59 px (quarter-pixel steps).
    assert np.nanmin(frame.gt_disparity) > 0 and np.nanmax(frame.gt_disparity) < 64
    np.testing.assert_array_equal(frame.gt_disparity[valid] * 4, np.rint(frame.gt_disparity[valid] * 4))
    frames = list(iter_frames(shared_data / "middlebury2003"))
    assert [f.name for f in frames] == ["cones", "teddy"]


def test_kitti_stereo_split_gives_its_reference_frame(shared_data: Path) -> None:
    frames = list(iter_frames(shared_data / "kitti_stereo_2015"))
    assert [f.name for f in frames] == ["000000_10"]
    assert frames[0].gt_disparity is not None and np.isfinite(frames[0].gt_disparity).any()
