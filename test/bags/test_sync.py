"""Stamp synchronisation, pose interpolation and pose-message parsing (selfcontra_ros.bags.sync)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from selfcontra_ros.bags.reader import default_typestore
from selfcontra_ros.bags.sync import (
    PoseBuffer,
    PoseMiss,
    StampSynchronizer,
    matrix_from_pose,
    pose_from_message,
    validate_pose,
)
from selfcontra_ros.errors import PoseError

MS = 1_000_000  # nanoseconds per millisecond
S = 1_000_000_000


def _stamps(result_matches: list[Any]) -> list[tuple[int, ...]]:
    return [m.stamps_ns for m in result_matches]


# --------------------------------------------------------------------------- StampSynchronizer


def test_exact_pairs_equal_stamps_whichever_side_comes_first() -> None:
    sync = StampSynchronizer(("left", "right"))
    out: list[Any] = []
    out += sync.push("left", 100, "L100").matches
    assert out == []  # the right image of 100 may still come
    out += sync.push("right", 100, "R100").matches
    out += sync.push("right", 200, "R200").matches
    out += sync.push("left", 200, "L200").matches
    assert [m.items for m in out] == [("L100", "R100"), ("L200", "R200")]
    assert [m.stamp_ns for m in out] == [100, 200]
    assert sync.matched == 2 and sync.dropped == {"left": 0, "right": 0}
    assert sync.pending("left") == sync.pending("right") == 0


def test_exact_drops_a_frame_whose_partner_is_lost() -> None:
    sync = StampSynchronizer(("left", "right"))
    matches = []
    for stamp in (100, 200, 300):
        matches += sync.push("left", stamp, stamp).matches
    for stamp in (100, 300):  # the right image of 200 was lost
        matches += sync.push("right", stamp, stamp).matches
    assert _stamps(matches) == [(100, 100), (300, 300)]
    assert sync.dropped == {"left": 1, "right": 0}


def test_exact_rejects_a_slop() -> None:
    with pytest.raises(ValueError, match="exact"):
        StampSynchronizer(("left", "right"), mode="exact", slop=0.01)
    with pytest.raises(ValueError, match="mode"):
        StampSynchronizer(("left", "right"), mode="nearest")
    with pytest.raises(ValueError, match="distinct"):
        StampSynchronizer(("left", "left"))


def test_approximate_takes_the_nearest_partner_within_the_slop() -> None:
    sync = StampSynchronizer(("left", "right"), mode="approximate", slop=0.005)
    assert sync.push("left", 1000 * MS, "L").matches == []
    # 997 ms is within the slop, but a nearer partner at or after 1000 ms may still come.
    assert sync.push("right", 997 * MS, "R997").matches == []
    matches = sync.push("right", 1001 * MS, "R1001").matches
    assert [m.items for m in matches] == [("L", "R1001")]
    assert matches[0].stamp_ns == 1000 * MS  # the frame keeps the left image's stamp
    assert sync.dropped["right"] == 1  # R997 was older than the partner and is gone


def test_approximate_tie_prefers_the_earlier_and_slop_bounds_the_match() -> None:
    sync = StampSynchronizer(("left", "right"), mode="approximate", slop=0.003)
    sync.push("right", 998 * MS, "early")
    matches = sync.push("right", 1002 * MS, "late").matches
    matches += sync.push("left", 1000 * MS, "L").matches
    assert [m.items for m in matches] == [("L", "early")]
    # The next left image at 1010 ms has the 1002 ms right image 8 ms away: beyond the slop.
    matches = sync.push("left", 1010 * MS, "L2").matches
    matches += sync.push("right", 1020 * MS, "R").matches
    assert matches == []
    assert sync.dropped["left"] == 1
    # ... and three keys: all must be within the slop of the pivot.
    sync3 = StampSynchronizer(("left", "right", "disparity"), mode="approximate", slop=0.003)
    got = []
    for key, stamp in (("left", 500), ("right", 502), ("disparity", 498), ("disparity", 501)):
        got += sync3.push(key, stamp * MS, (key, stamp)).matches
    assert _stamps(got) == [(500 * MS, 502 * MS, 501 * MS)]


def test_queue_is_bounded_and_drops_are_counted() -> None:
    sync = StampSynchronizer(("left", "right"), queue_size=4)
    for k in range(10):  # the right camera is silent
        assert sync.push("left", k * 100, k).matches == []
    assert sync.pending("left") == 4
    assert sync.dropped["left"] == 6
    # The queued ones are the newest: they still match.
    matches = []
    for k in range(6, 10):
        matches += sync.push("right", k * 100, k).matches
    assert [m.items for m in matches] == [(k, k) for k in range(6, 10)]


def test_backwards_stamps_are_refused_and_counted() -> None:
    sync = StampSynchronizer(("left", "right"))
    assert sync.push("left", 200, "a").accepted
    result = sync.push("left", 100, "b")
    assert not result.accepted and result.matches == []
    assert not sync.push("left", 200, "c").accepted  # a repeated stamp as well
    assert sync.backwards == {"left": 2, "right": 0}
    assert [m.items for m in sync.push("right", 200, "r").matches] == [("a", "r")]
    # After a time jump (bag loop) the caller resets and older stamps are accepted again.
    assert sync.reset() == 0
    assert sync.push("left", 100, "again").accepted


# --------------------------------------------------------------------------- PoseBuffer


def _pose(rotvec: list[float], translation: list[float]) -> NDArray[np.float64]:
    """4x4 pose with the rotation from OpenCV's Rodrigues (independent of the package)."""
    pose = np.eye(4)
    matrix, _ = cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64))
    pose[:3, :3] = matrix
    pose[:3, 3] = translation
    return pose


def _angle(rotation: NDArray[np.float64]) -> float:
    return math.degrees(math.acos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))


def test_interpolation_midpoint_translation_and_half_angle() -> None:
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    start = _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    end = _pose(list(axis * math.radians(60.0)), [2.0, 4.0, -6.0])
    buffer = PoseBuffer()
    assert buffer.add(10 * S, start) and buffer.add(11 * S, end)
    mid = buffer.at(10 * S + S // 2, max_gap_s=1.0)
    assert mid is not None
    np.testing.assert_allclose(mid[:3, 3], [1.0, 2.0, -3.0], atol=1e-12)
    np.testing.assert_allclose(mid[:3, :3], _pose(list(axis * math.radians(30.0)), [0, 0, 0])[:3, :3], atol=1e-12)
    quarter = buffer.at(10 * S + S // 4, max_gap_s=1.0)
    assert quarter is not None
    assert _angle(quarter[:3, :3]) == pytest.approx(15.0, abs=1e-9)
    np.testing.assert_array_equal(buffer.at(11 * S), end)  # a pose at exactly the stamp is returned as is


def test_interpolation_matches_scipy_slerp_on_random_poses() -> None:
    rng = np.random.default_rng(3)
    rotations = Rotation.random(2, random_state=7)
    slerp = Slerp([0.0, 1.0], rotations)
    buffer = PoseBuffer()
    t0, t1 = rng.normal(size=3), rng.normal(size=3)
    for k, t in enumerate((t0, t1)):
        pose = np.eye(4)
        pose[:3, :3] = rotations[k].as_matrix()
        pose[:3, 3] = t
        buffer.add(k * S, pose)
    for fraction in rng.uniform(0.0, 1.0, size=5):
        got = buffer.at(round(fraction * S), max_gap_s=1.0)
        assert got is not None
        f = round(fraction * S) / S
        np.testing.assert_allclose(got[:3, :3], slerp([f]).as_matrix()[0], atol=1e-9)
        np.testing.assert_allclose(got[:3, 3], t0 + f * (t1 - t0), atol=1e-9)


def test_slerp_takes_the_shorter_arc() -> None:
    buffer = PoseBuffer()
    buffer.add(0, _pose([0.0, 0.0, math.radians(170.0)], [0, 0, 0]))
    buffer.add(S, _pose([0.0, 0.0, math.radians(-170.0)], [0, 0, 0]))
    mid = buffer.at(S // 2, max_gap_s=1.0)
    assert mid is not None
    assert _angle(mid[:3, :3]) == pytest.approx(180.0, abs=1e-6)  # through 180 deg, not through 0


def test_extrapolation_is_limited_and_reasons_are_given() -> None:
    buffer = PoseBuffer()
    assert buffer.lookup(0).reason is PoseMiss.EMPTY
    buffer.add(10 * S, _pose([0, 0, 0], [0.0, 0.0, 0.0]))
    buffer.add(11 * S, _pose([0, 0, 0], [1.0, 0.0, 0.0]))
    ahead = buffer.at(11 * S + 40 * MS, max_gap_s=1.0, max_extrapolation_s=0.05)
    assert ahead is not None
    np.testing.assert_allclose(ahead[:3, 3], [1.04, 0.0, 0.0], atol=1e-12)  # constant velocity
    stopped = buffer.lookup(11 * S + 60 * MS, max_extrapolation_s=0.05)
    assert stopped.pose is None and stopped.reason is PoseMiss.AFTER
    assert buffer.lookup(10 * S - 60 * MS, max_extrapolation_s=0.05).reason is PoseMiss.BEFORE
    gap = buffer.lookup(10 * S + S // 2)  # default max_gap_s = 0.5 s < 1 s between the poses
    assert gap.pose is None and gap.reason is PoseMiss.GAP
    assert buffer.at(10 * S + S // 2, max_gap_s=1.0) is not None


def test_bad_poses_are_rejected_with_the_problem_named() -> None:
    buffer = PoseBuffer()
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    with pytest.raises(PoseError, match="NaN"):
        buffer.add(0, nan_pose)
    with pytest.raises(PoseError, match="not rigid"):
        buffer.add(0, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(PoseError, match="not rigid"):
        buffer.add(0, np.diag([-1.0, 1.0, 1.0, 1.0]))  # a reflection
    with pytest.raises(PoseError, match="bottom row"):
        validate_pose(np.ones((4, 4)))
    with pytest.raises(PoseError, match="4x4"):
        buffer.add(0, np.eye(3))
    assert len(buffer) == 0


def test_out_of_order_poses_are_refused_and_counted() -> None:
    buffer = PoseBuffer(capacity=3)
    assert buffer.add(2 * S, np.eye(4))
    assert not buffer.add(1 * S, np.eye(4))
    assert not buffer.add(2 * S, np.eye(4))
    assert buffer.out_of_order == 2
    for k in range(3, 7):
        buffer.add(k * S, np.eye(4))
    assert len(buffer) == 3 and buffer.oldest_ns == 4 * S and buffer.newest_ns == 6 * S
    buffer.discard_before(int(5.5 * S))
    assert buffer.oldest_ns == 5 * S  # the pose just before the stamp stays for interpolation


# --------------------------------------------------------------------------- messages


def _ns_msg(stamp_ns: int, pose: NDArray[np.float64], *, odometry: bool) -> Any:
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # (x, y, z, w), scipy: independent of the package
    geometry = SimpleNamespace(
        position=SimpleNamespace(x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
        orientation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    header = SimpleNamespace(stamp=SimpleNamespace(sec=stamp_ns // S, nanosec=stamp_ns % S), frame_id="world")
    pose_field = SimpleNamespace(pose=geometry, covariance=np.zeros(36)) if odometry else geometry
    return SimpleNamespace(header=header, pose=pose_field)


@pytest.mark.parametrize("odometry", [False, True])
def test_pose_and_odometry_messages_give_stamp_and_matrix(odometry: bool) -> None:
    pose = _pose([0.3, -0.2, 1.1], [4.0, -5.0, 6.5])
    stamp, matrix = pose_from_message(_ns_msg(1_316_995_200 * S + 123_456_789, pose, odometry=odometry))
    assert stamp == 1_316_995_200 * S + 123_456_789
    np.testing.assert_allclose(matrix, pose, atol=1e-12)


def test_rosbags_messages_are_read_too() -> None:
    types = default_typestore().types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=5, nanosec=7), frame_id="w")
    geometry = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(0.25), w=math.cos(0.25)),
    )
    odom = types["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id="stereo_left_optical",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=geometry, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=np.zeros(36),
        ),
    )
    stamp, matrix = pose_from_message(odom)
    assert stamp == 5 * S + 7
    np.testing.assert_allclose(matrix, _pose([0.0, 0.0, 0.5], [1.0, 2.0, 3.0]), atol=1e-12)
    buffer = PoseBuffer()
    assert buffer.add_message(types["geometry_msgs/msg/PoseStamped"](header=header, pose=geometry))
    assert buffer.newest_ns == 5 * S + 7


def test_bad_pose_messages_raise_pose_error() -> None:
    good = _ns_msg(0, np.eye(4), odometry=False)
    good.pose.position.x = math.nan
    with pytest.raises(PoseError, match=r"position"):
        pose_from_message(good)
    zero = SimpleNamespace(
        position=SimpleNamespace(x=0.0, y=0.0, z=0.0), orientation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=0.0)
    )
    with pytest.raises(PoseError, match="norm"):
        matrix_from_pose(zero)
