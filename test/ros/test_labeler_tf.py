"""The labeler node's robot inputs: poses from TF, compressed images; and the player's TF -> pose conversion.

No tf2_ros here (PyPI wheels), so the node's TF path is driven through the
same :class:`~selfcontra_ros.bags.tf.TransformSource` interface with a
:class:`~selfcontra_ros.bags.tf.TFBuffer` the test fills, as tf2_ros's
``TransformListener`` would fill its ``Buffer``; the tf2_ros adapter
(:class:`Tf2Transforms`) is checked against a stand-in with tf2_ros's API.
Ground truth: a :class:`LabelingSession` run on the same frames with the poses
composed by hand (mount x odometry), and PNG (lossless) images for the
compressed transport, so the node's labels must be exactly the session's.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.stereo_input import StereoInput, TFPoses
from selfcontra_ros.bags.tf import TFBuffer
from selfcontra_ros.errors import TransformError
from selfcontra_ros.geometry import invert_pose, quaternion_from_rotation, rotation_from_quaternion

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("compiled_kernels")]

WAIT_S = 60.0
HERE = Path(__file__).resolve().parent
NODE = ["-m", "selfcontra_ros.ros.labeler_node", "--ros-args"]
MS = 1_000_000


def _load_helpers() -> ModuleType:
    """The publisher/recorder helpers and fixtures of test_labeler_node.py (test modules are not importable)."""
    spec = importlib.util.spec_from_file_location("_selfcontra_labeler_node_tests", HERE / "test_labeler_node.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


helpers = _load_helpers()
frames = helpers.frames
params_file = helpers.params_file

FRAME_ID = helpers.FRAME_ID
# T_base_camera: a camera 1.2 m up and 0.3 m forward, looking along the base's x axis, yawed by a few degrees.
_YAW = np.radians(4.0)
MOUNT = np.array(
    [
        [-np.sin(_YAW), 0.0, np.cos(_YAW), 0.3],
        [-np.cos(_YAW), 0.0, -np.sin(_YAW), 0.05],
        [0.0, -1.0, 0.0, 1.2],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def _rigid(rotation_axis: tuple[float, float, float], degrees: float, translation: tuple[float, float, float]) -> Any:
    axis = np.asarray(rotation_axis, dtype=np.float64)
    axis /= np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_quaternion([*(axis * np.sin(half)), np.cos(half)])
    pose[:3, 3] = translation
    return pose


def _odom_base(frames: Any, k: int) -> NDArray[np.float64]:
    """``T_odom_base`` at frame ``k``: such that ``T_odom_base @ MOUNT`` is the sequence's ``T_world_left``."""
    return np.asarray(frames.poses[k] @ invert_pose(MOUNT))


def _node(rclpy_context: Any, params_file: Path, source: Any, **overrides: Any) -> Any:
    from rclpy.parameter import Parameter

    from selfcontra_ros.config import load_params, to_ros_parameters
    from selfcontra_ros.ros.labeler_node import LabelerNode

    values = to_ros_parameters(*load_params(params_file))
    values.update({"input_qos": "reliable", "stats_period": 0.1, "label_queue_size": 16})
    values.update(overrides)
    cli_args = values.pop("cli_args", None)
    return LabelerNode(
        transform_source=source,
        context=rclpy_context,
        cli_args=cli_args,
        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
    )


@pytest.fixture
def nodes(rclpy_context: Any) -> Iterator[list[Any]]:
    """Labeler nodes created by a test, destroyed at teardown."""
    created: list[Any] = []
    yield created
    for node in created:
        node.destroy_node()


# --------------------------------------------------------------------------- the decision, without a node


def _tf_poses(static: bool = True) -> tuple[TFBuffer, TFPoses]:
    buffer = TFBuffer()
    if static:
        buffer.add("base_link", "cam", 0, MOUNT, static=True)
    return buffer, TFPoses(buffer, "odom", "cam")


def test_tf_pose_decision_waits_for_tf_then_composes_the_chain() -> None:
    from selfcontra_ros.ros.labeler_node import tf_pose_decision

    buffer, poses = _tf_poses()
    a = _rigid((0.1, 1.0, 0.0), 10.0, (1.0, 0.0, 0.2))
    b = _rigid((0.1, 1.0, 0.0), 14.0, (2.0, 0.1, 0.2))
    buffer.add("odom", "base_link", 100 * MS, a)
    stamp = 150 * MS
    patience = dict(max_wait_ns=500 * MS)
    # TF has not reached the stamp: the frame waits (no extrapolation while it is patient).
    assert tf_pose_decision(poses, stamp, waited_ns=0, **patience) is None
    buffer.add("odom", "base_link", 200 * MS, b)
    found = tf_pose_decision(poses, stamp, waited_ns=0, **patience)
    assert found is not None and found.pose is not None
    # Hand-composed: odom->base_link interpolated half way (linear translation, slerp rotation), times the mount.
    half = _rigid((0.1, 1.0, 0.0), 12.0, (1.5, 0.05, 0.2))
    assert np.allclose(found.pose, half @ MOUNT, atol=1e-12)
    # Exactly at a sample: the product of the two transforms.
    at_b = tf_pose_decision(poses, 200 * MS, waited_ns=0, **patience)
    assert at_b is not None and at_b.pose is not None and np.allclose(at_b.pose, b @ MOUNT, atol=1e-12)


def test_tf_pose_decision_names_the_missing_link_once_patience_is_over() -> None:
    from selfcontra_ros.ros.labeler_node import TF_WAIT_REASONS, tf_pose_decision

    buffer, poses = _tf_poses(static=False)  # base_link -> cam never published
    buffer.add("odom", "base_link", 100 * MS, np.eye(4))
    buffer.add("odom", "base_link", 200 * MS, np.eye(4))
    assert tf_pose_decision(poses, 150 * MS, waited_ns=500 * MS, max_wait_ns=500 * MS) is None  # may still come
    found = tf_pose_decision(poses, 150 * MS, waited_ns=501 * MS, max_wait_ns=500 * MS)
    assert found is not None and found.pose is None
    assert found.reason == "tf_unknown_frame" and found.reason in TF_WAIT_REASONS
    assert "'cam' is unknown" in found.detail and "base_link, odom" in found.detail
    # A stamp older than TF's history cannot be cured by waiting: dropped at once.
    buffer.add("base_link", "cam", 0, MOUNT, static=True)
    early = tf_pose_decision(poses, 0, waited_ns=0, max_wait_ns=500 * MS)
    assert early is not None and early.pose is None and early.reason == "tf_before_buffer"


class _FakeTf2:
    """tf2_ros's exception hierarchy and a Buffer whose lookup_transform answers from a table (or raises)."""

    class TransformException(Exception):  # noqa: N818 (tf2_ros's names)
        pass

    class LookupException(TransformException):
        pass

    class ConnectivityException(TransformException):
        pass

    class ExtrapolationException(TransformException):
        pass

    def __init__(self, answers: dict[tuple[str, str], Any]) -> None:
        self.answers = answers
        self.asked: list[tuple[str, str, int]] = []

    def lookup_transform(self, target: str, source: str, time: Any) -> Any:
        self.asked.append((target, source, time.nanoseconds))
        answer = self.answers[(target, source)]
        if isinstance(answer, Exception):
            raise answer
        return answer


def _transform_stamped(pose: NDArray[np.float64]) -> Any:
    from geometry_msgs.msg import TransformStamped

    msg = TransformStamped()
    t, r = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = (float(v) for v in pose[:3, 3])
    r.x, r.y, r.z, r.w = (float(v) for v in quaternion_from_rotation(pose[:3, :3]))
    return msg


def test_tf2_adapter_gives_matrices_and_tf_reasons() -> None:
    from selfcontra_ros.ros.labeler_node import Tf2Transforms

    pose = _rigid((0.3, -1.0, 0.2), 33.0, (4.0, -1.5, 0.25))
    fake = _FakeTf2(
        {
            ("odom", "cam"): _transform_stamped(pose),
            ("odom", "nowhere"): _FakeTf2.LookupException('"nowhere" passed to lookupTransform does not exist'),
            ("map", "cam"): _FakeTf2.ConnectivityException("map and cam are not part of the same tree"),
            ("odom", "late"): _FakeTf2.ExtrapolationException("Lookup would require extrapolation into the future"),
            ("odom", "early"): _FakeTf2.ExtrapolationException("Lookup would require extrapolation into the past"),
        }
    )
    source = Tf2Transforms(fake, _FakeTf2)
    stamp = 1_700_000_000_123_456_789
    assert np.allclose(source.lookup("/odom", "cam", stamp), pose, atol=1e-12)
    assert fake.asked[-1] == ("odom", "cam", stamp)  # leading '/' dropped, the stamp to the nanosecond
    for source_frame, target, reason in [
        ("nowhere", "odom", "tf_unknown_frame"),
        ("cam", "map", "tf_not_connected"),
        ("late", "odom", "tf_after_buffer"),
        ("early", "odom", "tf_before_buffer"),
    ]:
        with pytest.raises(TransformError) as info:
            source.lookup(target, source_frame, stamp)
        assert info.value.reason == reason and source_frame in str(info.value)
    # Through TFPoses, as the node uses it: the reason reaches the drop counter.
    missing = TFPoses(source, "odom", "late").pose_at(stamp)
    assert missing.pose is None and missing.reason == "tf_after_buffer"


# --------------------------------------------------------------------------- the node


def test_node_with_tf_poses_labels_like_a_session_with_the_composed_poses(
    frames: Any, params_file: Path, ros_node: Any, rclpy_context: Any, nodes: list[Any]
) -> None:
    """TF fed before or after a frame's images (the frame waits; a timer retries): labels equal the session's."""
    buffer, reference = TFBuffer(), TFBuffer()  # the node forgets the history it no longer needs: keep a copy
    for tf in (buffer, reference):
        tf.add("base_link", FRAME_ID, 0, MOUNT, static=True)
        for k in range(len(frames.left)):
            if tf is reference:
                tf.add("odom", "base_link", frames.stamp_ns(k), _odom_base(frames, k))
    node = _node(rclpy_context, params_file, buffer, pose_source="tf", world_frame="odom")
    nodes.append(node)
    feeder = helpers.Feeder(ros_node)
    recorder = helpers.Recorder(ros_node)
    matched = lambda: feeder.left.get_subscription_count() >= 1 and recorder.matched()  # noqa: E731
    assert helpers.spin_nodes([node, ros_node], matched, WAIT_S)
    assert feeder.pose.get_subscription_count() == 0, "no pose topic with pose_source tf"
    n = len(frames.left)
    for k in range(n):
        stamp = frames.stamp_ns(k)
        if k % 2 == 0:
            buffer.add("odom", "base_link", stamp, _odom_base(frames, k))
        feeder.infos(frames.camera, stamp)
        feeder.images(frames.left[k], frames.right[k], stamp)
        if k % 2 == 1:
            assert helpers.spin_nodes([node, ros_node], lambda: node.stats()["awaiting_pose"] >= 1, WAIT_S)
            buffer.add("odom", "base_link", stamp, _odom_base(frames, k))
    done = helpers.spin_nodes(
        [node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= n - helpers.DELAY, WAIT_S
    )
    assert done, node.stats()
    composed = [reference.lookup("odom", FRAME_ID, frames.stamp_ns(k)) for k in range(n)]
    for k in range(n):  # the chain is the hand-made product (its rounding aside)
        assert np.allclose(composed[k], _odom_base(frames, k) @ MOUNT, atol=1e-12)
        assert np.allclose(composed[k], frames.poses[k], atol=1e-9)
    helpers.check_outputs(recorder, dataclasses.replace(frames, poses=composed), params_file, flushed=False)
    assert sum(node.stats()["drops"].values()) == 0, node.stats()["drops"]


def test_node_counts_a_missing_tf_link_and_labels_once_it_appears(
    frames: Any, params_file: Path, ros_node: Any, rclpy_context: Any, nodes: list[Any]
) -> None:
    """Without base_link -> camera, frames wait max_pose_gap of image time, then drop as tf_unknown_frame."""
    buffer = TFBuffer()
    node = _node(rclpy_context, params_file, buffer, pose_source="tf", world_frame="odom", max_pose_gap=0.15)
    nodes.append(node)
    feeder = helpers.Feeder(ros_node)
    recorder = helpers.Recorder(ros_node)
    matched = lambda: feeder.left.get_subscription_count() >= 1 and recorder.matched()  # noqa: E731
    assert helpers.spin_nodes([node, ros_node], matched, WAIT_S)
    n = len(frames.left)
    for k in range(n):
        stamp = frames.stamp_ns(k)
        buffer.add("odom", "base_link", stamp, _odom_base(frames, k))
        feeder.infos(frames.camera, stamp)
        feeder.images(frames.left[k], frames.right[k], stamp)
    # Frame k gives up once frame k + 2 arrived (0.2 s > 0.15 s newer): frames 0..n-3 are dropped, 2 still wait.
    dropped = lambda: node.stats()["counts"]["frames"] == n and node.stats()["awaiting_pose"] == 2  # noqa: E731
    assert helpers.spin_nodes([node, ros_node], dropped, WAIT_S), node.stats()
    drops = node.stats()["drops"]
    assert drops["tf_unknown_frame"] == n - 2 and sum(drops.values()) == n - 2, drops
    buffer.add("base_link", FRAME_ID, 0, MOUNT, static=True)  # the static transform comes late
    assert helpers.spin_nodes([node, ros_node], lambda: node.stats()["counts"]["views_queued"] == 2, WAIT_S)
    assert node.stats()["awaiting_pose"] == 0


def _compressed(pixels: NDArray[np.uint8], stamp_ns: int) -> Any:
    from sensor_msgs.msg import CompressedImage

    from selfcontra_ros.bags.compressed import compressed_image_fields
    from selfcontra_ros.ros.conversions import nanoseconds_to_stamp

    fields = compressed_image_fields(pixels, "mono8" if pixels.ndim == 2 else "rgb8", "png")
    msg = CompressedImage()
    msg.header.stamp = nanoseconds_to_stamp(stamp_ns)
    msg.header.frame_id = FRAME_ID
    msg.format = fields["format"]
    msg.data = fields["data"].tobytes()
    return msg


def test_node_reads_compressed_images_on_remapped_base_names_and_counts_bad_ones(
    frames: Any, params_file: Path, ros_node: Any, rclpy_context: Any, nodes: list[Any]
) -> None:
    """image_transport compressed: -r left/image_rect:=cam0/image moves the subscription to cam0/image/compressed;
    PNG frames label exactly like the session, undecodable ones are dropped as bad_compressed_image."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CompressedImage

    remaps = ["--ros-args", "-r", "left/image_rect:=cam0/image", "-r", "right/image_rect:=cam1/image"]
    # queue_size: the subscriptions' history must hold all 11 messages sent before the node spins.
    node = _node(rclpy_context, params_file, None, image_transport="compressed", queue_size=20, cli_args=remaps)
    nodes.append(node)
    feeder = helpers.Feeder(ros_node)
    recorder = helpers.Recorder(ros_node)
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    left = ros_node.create_publisher(CompressedImage, "/cam0/image/compressed", qos)
    right = ros_node.create_publisher(CompressedImage, "/cam1/image/compressed", qos)
    inputs = (left, right, feeder.left_info, feeder.right_info, feeder.pose)
    matched = lambda: all(p.get_subscription_count() >= 1 for p in inputs) and recorder.matched()  # noqa: E731
    assert helpers.spin_nodes([node, ros_node], matched, WAIT_S)
    assert feeder.left.get_subscription_count() == 0, "raw images are not subscribed with image_transport compressed"
    n = len(frames.left)
    bad = 3
    last = frames.stamp_ns(n - 1)
    for k in range(n):
        stamp = frames.stamp_ns(k)
        feeder.infos(frames.camera, stamp)
        left.publish(_compressed(frames.left[k], stamp))
        right.publish(_compressed(frames.right[k], stamp))
        feeder.send_pose(frames.poses[k], stamp)
    for i in range(bad):  # after the sequence: garbage, then a format image_transport would never write
        stamp = last + (i + 1) * 10 * MS
        feeder.infos(frames.camera, stamp)
        broken = _compressed(frames.left[0], stamp)
        broken.data = bytes(64) if i < 2 else broken.data
        broken.format = broken.format if i < 2 else "mono8; compressedDepth png"
        left.publish(broken)
        right.publish(_compressed(frames.right[0], stamp))
    counted = lambda: node.stats()["drops"]["bad_compressed_image"] >= bad  # noqa: E731
    done = lambda: recorder.count(topics.LABELS_COLOR) >= n - helpers.DELAY and counted()  # noqa: E731
    assert helpers.spin_nodes([node, ros_node], done, WAIT_S), node.stats()
    assert node.stats()["drops"]["bad_compressed_image"] == bad
    helpers.check_outputs(recorder, frames, params_file, flushed=False)


def test_invalid_robot_parameters_exit_with_code_2(ros_process: Callable[..., Any]) -> None:
    """The executable reports a combination the node refuses itself (not rclpy) in one line, exit code 2."""
    helpers.exits_with_code_2(ros_process, ["pose_source:=tf"], "'world_frame' is required with pose_source 'tf'")


@pytest.mark.parametrize(
    ("argument", "message"),
    [
        ("pose_source:=tf", "'world_frame' is required with pose_source 'tf'"),
        ("world_frame:=odom", "apply to pose_source 'tf' only"),
        ("image_transport:=theora", "expected one of raw, compressed"),
    ],
)
def test_invalid_robot_parameters_are_refused_with_their_reason(
    rclpy_context: Any, argument: str, message: str
) -> None:
    """In process, as the labeler's other invalid parameters (test_labeler_node.py)."""
    helpers.refused_node(rclpy_context, argument, message)


@pytest.mark.skipif(importlib.util.find_spec("tf2_ros") is not None, reason="this ROS install has tf2_ros")
def test_pose_source_tf_without_tf2_ros_stops_naming_the_alternatives(ros_process: Callable[..., Any]) -> None:
    err = helpers.exits_with_code_2(ros_process, ["pose_source:=tf", "world_frame:=odom"], "needs tf2_ros")
    for alternative in ("pose_source pose or odom", "player -p pose_source:=tf", "pose_source odometry"):
        assert alternative in err, err


# --------------------------------------------------------------------------- the player's conversion, without ROS


def _tf_message(parent: str, child: str, stamp_ns: int, pose: NDArray[np.float64]) -> Any:
    item = SimpleNamespace(
        header=SimpleNamespace(frame_id=parent, stamp=SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)),
        child_frame_id=child,
        transform=SimpleNamespace(
            translation=SimpleNamespace(x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
            rotation=SimpleNamespace(**dict(zip("xyzw", quaternion_from_rotation(pose[:3, :3]), strict=True))),
        ),
    )
    return SimpleNamespace(transforms=[item])


def _header(stamp_ns: int, frame_id: str = "") -> Any:
    return SimpleNamespace(frame_id=frame_id, stamp=SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9))


@pytest.mark.parametrize("rectify", [False, True])
def test_player_tf_poses_compose_tf_at_each_left_image_stamp(rectify: bool) -> None:
    """Poses decided once TF passes the stamp, the rectification rotation applied, a missing link counted."""
    from selfcontra_ros.ros.player_node import BagTFPoses

    stereo_input = StereoInput(
        image_transport="compressed",
        rectify=rectify,
        pose_source="tf",
        world_frame="odom",
        remaps=("pose:=/robot/pose",),
    )
    topic_map = stereo_input.topics("/cam")
    poses = BagTFPoses(stereo_input, topic_map)
    assert poses.left_image == ("/cam/left/image_raw/compressed" if rectify else "/cam/left/image_rect/compressed")
    assert topic_map["pose"] == "/robot/pose"
    r_left = _rigid((0.2, 1.0, -0.1), 0.7, (0.0, 0.0, 0.0))[:3, :3]  # X_rect = R X_raw
    info = SimpleNamespace(header=_header(0, "cam_left_raw"), r=r_left.reshape(-1))
    a = _rigid((0.0, 0.0, 1.0), 5.0, (0.0, 0.0, 0.0))
    b = _rigid((0.0, 0.0, 1.0), 7.0, (1.0, 0.0, 0.0))

    assert poses.add("/tf_static", 0, _tf_message("base_link", "cam_left_raw", 0, MOUNT)) == []
    assert poses.add("/tf", 80 * MS, _tf_message("odom", "base_link", 80 * MS, a)) == []
    assert poses.add(topic_map["left/camera_info"], 100 * MS, info) == []
    image = SimpleNamespace(header=_header(100 * MS, "cam_left_raw"))
    assert poses.add(poses.left_image, 100 * MS, image) == []  # TF is at 80 ms: wait
    decided = poses.add("/tf", 120 * MS, _tf_message("odom", "base_link", 120 * MS, b))
    assert [stamp for stamp, _ in decided] == [100 * MS]
    found = decided[0][1].pose
    assert found is not None
    raw_from_rectified = np.eye(4)
    if rectify:
        raw_from_rectified[:3, :3] = r_left.T
    expected = _rigid((0.0, 0.0, 1.0), 6.0, (0.5, 0.0, 0.0)) @ MOUNT @ raw_from_rectified
    assert np.allclose(found, expected, atol=1e-12)

    # TF stops: a later image is given up 0.5 s of bag time after its stamp (0.05 s extrapolation allowed: none).
    late = SimpleNamespace(header=_header(400 * MS, "cam_left_raw"))
    assert poses.add(poses.left_image, 400 * MS, late) == []
    assert poses.finish()[0][1].reason == "tf_after_buffer"
    assert poses.misses == {"tf_after_buffer": 1}
    poses.reset()  # a new pass (loop): the old TF is gone, so the camera frame is unknown until its camera_info
    assert poses.add(poses.left_image, 100 * MS, image) == []
    assert poses.finish()[0][1].reason == "no_camera_frame"


def test_player_pose_messages_are_the_bags_pose_stamped_in_cdr() -> None:
    """The player's TF poses go out as the CDR of MessageBuilder's PoseStamped: they read back as the pose."""
    from selfcontra_ros.bags import topics
    from selfcontra_ros.bags.reader import default_typestore
    from selfcontra_ros.bags.sync import matrix_from_pose
    from selfcontra_ros.ros.player_node import PoseMessages

    pose = _rigid((0.3, -1.0, 0.2), 40.0, (1.5, -2.0, 0.25))
    data = PoseMessages().pose_stamped(pose, 1_700_000_000_123_456_789, "odom")
    assert isinstance(data, bytes)
    msg = default_typestore().deserialize_cdr(data, topics.POSE_TYPE)
    assert msg.header.frame_id == "odom"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    np.testing.assert_allclose(matrix_from_pose(msg.pose), pose, atol=1e-12)
