"""KITTI odometry metrics against trajectories whose errors are known in closed form."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.odometry.metrics import evaluate_odometry, path_lengths


def _straight(n: int, step: float = 1.0) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = step * np.arange(n)
    return poses


def _chain(steps: list[np.ndarray]) -> np.ndarray:
    poses = [np.eye(4)]
    for s in steps:
        poses.append(poses[-1] @ s)
    return np.stack(poses)


def test_perfect_estimate_has_no_error() -> None:
    rng = np.random.default_rng(0)
    steps = []
    for _ in range(40):
        s = np.eye(4)
        s[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix()
        s[:3, 3] = np.array([0.1, 0.0, 1.2]) + rng.normal(0, 0.05, 3)
        steps.append(s)
    gt = _chain(steps)
    m = evaluate_odometry(gt, gt)
    assert m.pairs > 0
    assert m.translation_error_pct == pytest.approx(0.0, abs=1e-9)
    assert m.rotation_error_deg_per_m == pytest.approx(0.0, abs=1e-6)


def test_scale_error_gives_its_percentage() -> None:
    gt = _straight(60)
    est = gt.copy()
    est[:, :3, 3] *= 1.02  # 2 % too long everywhere
    m = evaluate_odometry(est, gt, lengths=(5.0, 10.0, 20.0))
    assert m.translation_error_pct == pytest.approx(2.0, rel=1e-9)
    assert m.rotation_error_deg_per_m == pytest.approx(0.0, abs=1e-9)
    # Pairs: first frames whose L-th successor exists, every frame a start (step 1).
    assert m.per_length[5.0][2] == 60 - 5
    assert m.per_length[20.0][2] == 60 - 20


def test_constant_yaw_drift_gives_its_rate() -> None:
    drift = np.radians(0.05)  # per frame of 1 m: 0.05 deg/m
    gt_step = np.eye(4)
    gt_step[2, 3] = 1.0
    est_step = gt_step.copy()
    est_step[:3, :3] = Rotation.from_rotvec([0.0, drift, 0.0]).as_matrix()
    gt = _chain([gt_step] * 50)
    est = _chain([est_step] * 50)
    m = evaluate_odometry(est, gt, lengths=(10.0, 20.0))
    assert m.rotation_error_deg_per_m == pytest.approx(0.05, rel=1e-6)
    assert m.translation_error_pct > 0


def test_devkit_last_frame_rule_and_step() -> None:
    # Steps of 0.4 m: 5 m is first reached after 13 frames (5.2 m), so the pair (0, 13) and so on.
    gt = _straight(30, step=0.4)
    est = gt.copy()
    est[13, 0, 3] = 0.26  # frame 13 alone is 0.26 m off
    m = evaluate_odometry(est, gt, lengths=(5.0,), step=10)
    # First frames 0, 10 (20 + 13 > 29 is out): pairs (0, 13), off by 0.26 m, and (10, 23), exact.
    assert m.pairs == 2
    assert m.translation_error_pct == pytest.approx(100.0 * 0.26 / 5.0 / 2.0)


def test_unreached_lengths_and_mask() -> None:
    gt = _straight(11)  # 10 m path
    est = gt.copy()
    est[5, 2, 3] += 1.0
    m = evaluate_odometry(est, gt, lengths=(5.0, 50.0))
    assert list(m.per_length) == [5.0]
    assert m.path_length_m == pytest.approx(10.0)
    masked = evaluate_odometry(est, gt, lengths=(5.0,), mask=np.arange(11) != 5)
    # Pairs touching frame 5 ((0, 5) and (5, 10)) are left out; the others are exact.
    assert masked.pairs == m.pairs - 2
    assert masked.translation_error_pct == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(path_lengths(gt), np.arange(11.0))


def test_bad_input_is_refused() -> None:
    with pytest.raises(SelfContraError, match="estimated poses"):
        evaluate_odometry(np.zeros((3, 2, 2)), _straight(3))
    with pytest.raises(SelfContraError, match="3 estimated poses for 4"):
        evaluate_odometry(_straight(3), _straight(4))
    three_by_four = _straight(8)[:, :3, :]
    assert evaluate_odometry(three_by_four, _straight(8), lengths=(2.0,)).pairs == 6
