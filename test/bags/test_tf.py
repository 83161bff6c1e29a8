"""The TF buffer: chains of static and dynamic transforms against hand-composed poses, and its errors (bags/tf.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.reader import default_typestore, open_bag
from selfcontra_ros.bags.tf import TFBuffer, TransformSource
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.errors import PoseError, TransformError

NS = 1_000_000_000
T0 = 1_700_000_000 * NS
RATE_HZ = 50
CAMERA, RIGHT = "camera_left_optical_frame", "camera_right_optical_frame"


def _pose(yaw: float, translation: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = translation
    return pose


def odom_base(t: float) -> np.ndarray:
    """``T_odom_base`` at ``t`` seconds: constant velocity and yaw rate, so interpolation is exact."""
    return _pose(0.3 * t, (1.5 * t, 0.2 * t, 0.01))


#: base_link -> left optical frame (REP 103: z forward = base x, x right = -base y, y down = -base z).
BASE_CAMERA = np.array([[0.0, 0.0, 1.0, 0.4], [-1.0, 0.0, 0.0, 0.06], [0.0, -1.0, 0.0, 1.2], [0, 0, 0, 1]])
BASE_RIGHT = BASE_CAMERA.copy()
BASE_RIGHT[:3, 3] += BASE_CAMERA[:3, 0] * 0.12  # 12 cm along the camera's x axis


def _stamp(t: float) -> int:
    return T0 + round(t * NS)


def _buffer(seconds: float = 2.0, *, dynamic: bool = True, static: bool = True, **kwargs: float) -> TFBuffer:
    tf = TFBuffer(**kwargs)  # type: ignore[arg-type]
    if static:
        tf.add("base_link", CAMERA, T0, BASE_CAMERA, static=True)
        tf.add("base_link", RIGHT, T0, BASE_RIGHT, static=True)
    if dynamic:
        for i in range(round(seconds * RATE_HZ) + 1):
            t = i / RATE_HZ
            assert tf.add("odom", "base_link", _stamp(t), odom_base(t))
    return tf


def test_buffer_satisfies_the_transform_source_protocol() -> None:
    source: TransformSource = _buffer(0.1)
    assert source.lookup("odom", CAMERA, _stamp(0.05)).shape == (4, 4)


@pytest.mark.parametrize("t", [0.0, 0.02, 0.013, 0.5071, 1.999])
def test_chain_equals_the_hand_composed_pose(t: float) -> None:
    """odom -> base_link (50 Hz, interpolated between samples) -> optical frame (static)."""
    tf = _buffer()
    expected = odom_base(t) @ BASE_CAMERA
    np.testing.assert_allclose(tf.lookup("odom", CAMERA, _stamp(t)), expected, atol=1e-9)
    # The other direction is the inverse; frame ids with ROS 1's leading slash are the same frames.
    np.testing.assert_allclose(tf.lookup("/" + CAMERA, "/odom", _stamp(t)) @ expected, np.eye(4), atol=1e-9)


def test_siblings_and_identity() -> None:
    tf = _buffer(0.1)
    right_in_left = tf.lookup(CAMERA, RIGHT, _stamp(0.05))
    np.testing.assert_allclose(right_in_left[:3, 3], [0.12, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(right_in_left[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(tf.lookup("odom", "odom", _stamp(0.05)), np.eye(4))
    assert tf.chain("odom", CAMERA) == [("base_link", CAMERA, True), ("odom", "base_link", False)]


def test_missing_static_link_names_the_frame() -> None:
    tf = _buffer(static=False)
    with pytest.raises(TransformError, match=f"frame '{CAMERA}' is unknown.*frames known: base_link, odom") as err:
        tf.lookup("odom", CAMERA, _stamp(0.5))
    assert err.value.reason == "tf_unknown_frame"
    assert f"no transform has child '{CAMERA}'" in str(err.value)
    assert f"missing link: base_link -> {CAMERA}" in str(err.value)  # the leaf of odom's tree
    with pytest.raises(TransformError, match=f"missing link: base_link -> {CAMERA}"):
        tf.lookup(CAMERA, "odom", _stamp(0.5))  # the unknown frame as the target: the same link


def test_missing_dynamic_link_names_the_link() -> None:
    tf = _buffer(dynamic=False)
    tf.add("map", "odom", T0, np.eye(4))  # odom is known, but nothing joins it to base_link
    with pytest.raises(TransformError, match=r"e\.g\. odom -> base_link") as err:
        tf.lookup("odom", CAMERA, _stamp(0.5))
    assert err.value.reason == "tf_not_connected"
    assert tf.newest_ns("odom", CAMERA) is None


def test_stamps_outside_the_history() -> None:
    tf = _buffer(1.0)
    # Up to max_extrapolation_s (0.05 s) past the newest transform, constant velocity continues the motion.
    np.testing.assert_allclose(tf.lookup("odom", CAMERA, _stamp(1.04)), odom_base(1.04) @ BASE_CAMERA, atol=1e-9)
    with pytest.raises(TransformError, match=r"odom -> base_link is not known at .*pose_after_buffer") as err:
        tf.lookup("odom", CAMERA, _stamp(1.2))
    assert err.value.reason == "tf_after_buffer"
    with pytest.raises(TransformError) as err:
        tf.lookup("odom", CAMERA, _stamp(-0.2))
    assert err.value.reason == "tf_before_buffer"
    assert tf.newest_ns("odom", CAMERA) == _stamp(1.0)
    assert tf.newest_ns("base_link", CAMERA) == 2**63 - 1  # static only: holds at every stamp


def test_history_is_bounded_by_the_cache_time() -> None:
    tf = _buffer(20.0, cache_time_s=10.0)
    with pytest.raises(TransformError) as err:
        tf.lookup("odom", CAMERA, _stamp(5.0))
    assert err.value.reason == "tf_before_buffer"
    np.testing.assert_allclose(tf.lookup("odom", CAMERA, _stamp(12.01)), odom_base(12.01) @ BASE_CAMERA, atol=1e-8)
    tf.discard_before(_stamp(19.0))
    with pytest.raises(TransformError):
        tf.lookup("odom", CAMERA, _stamp(18.5))


def test_refusals_are_counted() -> None:
    tf = _buffer(0.1)
    assert not tf.add("map", "base_link", _stamp(0.2), np.eye(4))  # a second parent
    assert not tf.add("odom", "base_link", _stamp(0.1), np.eye(4))  # not newer
    assert not tf.add(CAMERA, "odom", _stamp(0.1), np.eye(4))  # would close a loop
    assert not tf.add("odom", "base_link", _stamp(0.3), np.eye(4), static=True)  # dynamic link sent as static
    with pytest.raises(PoseError):
        tf.add("odom", "base_link", _stamp(0.3), np.full((4, 4), np.nan))
    assert tf.refused == {"reparented": 1, "out_of_order": 1, "loop": 1, "static_and_dynamic": 1, "bad_transform": 1}


def test_tf_messages_round_trip_through_a_bag(tmp_path: Path) -> None:
    """TFMessage is in the writer's typestore and reads back into the same chain."""
    store = default_typestore()
    assert topics.TF_TYPE in store.types
    make = MessageBuilder(store)
    bag_path = tmp_path / "tf_bag"
    with BagWriter(bag_path) as writer:
        writer.add_topic(topics.TF_STATIC, topics.TF_TYPE)
        writer.add_topic(topics.TF, topics.TF_TYPE)
        static = [("base_link", CAMERA, T0, BASE_CAMERA), ("base_link", RIGHT, T0, BASE_RIGHT)]
        writer.write(topics.TF_STATIC, T0, make.tf_message(static))
        for i in range(26):
            stamp = _stamp(i / RATE_HZ)
            writer.write(topics.TF, stamp, make.tf_message([("odom", "base_link", stamp, odom_base(i / RATE_HZ))]))
    tf = TFBuffer()
    with open_bag(bag_path) as bag:
        for message in bag.messages():
            assert tf.add_message(message.msg, static=message.topic == topics.TF_STATIC) == []
    np.testing.assert_allclose(tf.lookup("odom", CAMERA, _stamp(0.31)), odom_base(0.31) @ BASE_CAMERA, atol=1e-9)


def test_a_bad_transform_does_not_stop_the_others() -> None:
    make = MessageBuilder(default_typestore())
    msg = make.tf_message([("odom", "base_link", T0, np.eye(4)), ("base_link", CAMERA, T0, BASE_CAMERA)])
    msg.transforms[0].transform.rotation.w = 0.0  # a default-constructed quaternion
    tf = TFBuffer()
    problems = tf.add_message(msg, static=True)
    assert len(problems) == 1 and "odom -> base_link" in problems[0] and "norm" in problems[0]
    np.testing.assert_allclose(tf.lookup("base_link", CAMERA, T0), BASE_CAMERA, atol=1e-12)
