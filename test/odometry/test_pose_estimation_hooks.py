"""``--estimate-poses``: the labelers and kitti2mcap use visual odometry where a sequence has no poses."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.bags.sync import pose_from_message
from selfcontra_ros.datasets.kitti import read_poses, write_poses
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.pipeline import label_sequence

FRAMES = 10
PARAMS = """\
labeler:
  ros__parameters:
    labeler:
      window_size: 8
      label_delay: 4
"""


@pytest.fixture(scope="module")
def poseless(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A synthetic street without its poses file, and the true poses."""
    root = tmp_path_factory.mktemp("poseless")
    write_sequence(root, scene="street", frames=FRAMES, seed=3, width=640, height=192)
    truth = read_poses(root / "poses" / "00.txt")
    shutil.rmtree(root / "poses")
    return root, truth


def test_label_needs_poses_or_the_flag(poseless: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    root, _ = poseless
    with pytest.raises(SelfContraError, match="--estimate-poses"):
        label_sequence(root, tmp_path / "out")


def test_label_with_estimated_poses_matches_true_poses(poseless: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    root, truth = poseless
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS)
    report = label_sequence(root, tmp_path / "estimated", params_file=params, estimate_poses=True)
    assert report["pose_source"] == "stereo visual odometry"
    assert report["unreliable_pose_frames"] == []
    assert len(report["frames"]) == FRAMES - 4  # the last label_delay frames have no full window

    with_truth = tmp_path / "with_truth"
    shutil.copytree(root, with_truth)
    write_poses(with_truth / "poses" / "00.txt", truth)
    reference = label_sequence(with_truth, tmp_path / "true", params_file=params)
    assert reference["pose_source"] == "ground truth file"
    # Labels hinge on sub-pixel agreement, so single pixels flip with centimetre pose errors at this small
    # size; the figures against ground truth must stay those of the true poses.
    est, ref = report["mean"], reference["mean"]
    assert ref["coverage"] > 0.02
    assert abs(est["accuracy"] - ref["accuracy"]) < 0.03
    assert 0.7 * ref["coverage"] < est["coverage"] < 1.3 * ref["coverage"]


def test_kitti2mcap_writes_estimated_poses(poseless: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    root, truth = poseless
    bag = kitti_to_mcap(root, tmp_path / "bag", estimate_poses=True, progress=False)
    with open_bag(bag) as reader:
        poses = [pose_from_message(m.msg)[1] for m in reader.messages(["/stereo/pose"])]
        assert reader.custom_data.get("selfcontra.pose_source") == "odometry"
    assert len(poses) == FRAMES
    # The synthetic car drives about 1 m per frame: the estimated path must follow the true one.
    error = np.linalg.norm(np.stack(poses)[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert error.max() < 0.05 * max(np.linalg.norm(truth[-1, :3, 3]), 1.0)
