"""The labeler node over a real ROS 2 graph: depth of every frame, labels of the labelled views, parameters, shutdown.

The reference is a :class:`LabelingSession` run in the test on the same frames
with the same parameters: the node must give exactly its depth and labels.
"""

from __future__ import annotations

import json
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.config import load_params
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.geometry import StereoCamera, quaternion_from_rotation
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.session import LabelingSession

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("compiled_kernels")]

# Upper bound (s) of the waits for a node: a passing run never waits it out, but a loaded 2-core machine needs the
# slack (a node process takes seconds to import and to load its kernels from numba's cache, more when others run).
WAIT_S = 60.0

FRAMES = 8
DELAY = 3
FRAME_ID = "cam_left_optical"
STAMP0_NS = 1_700_000_000 * 1_000_000_000
PERIOD_NS = 100_000_000
NODE = ["-m", "selfcontra_ros.ros.labeler_node", "--ros-args"]
# Small and fast: each labeling takes well under 0.1 s at 320x96.
PARAMS_YAML = f"""\
labeler:
  ros__parameters:
    matcher:
      num_disparities: 64
    labeler:
      window_size: 6
      label_delay: {DELAY}
      flush_incomplete: true  # flush_on_shutdown labels the last label_delay views too
"""


@dataclass
class Frames:
    """A short synthetic stereo sequence with its camera and poses (T_world_left)."""

    camera: StereoCamera
    left: list[NDArray[np.uint8]]
    right: list[NDArray[np.uint8]]
    poses: list[NDArray[np.float64]]

    def stamp_ns(self, k: int) -> int:
        return STAMP0_NS + k * PERIOD_NS


@pytest.fixture(scope="module")
def frames() -> Frames:
    scene = make_scene("street", 2, 320, 96, frames=FRAMES)
    rendered = [scene.render(k) for k in range(FRAMES)]
    return Frames(
        scene.camera, [f.left for f in rendered], [f.right for f in rendered], [scene.pose(k) for k in range(FRAMES)]
    )


@pytest.fixture(scope="module")
def params_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("labeler_params") / "labeler.yaml"
    path.write_text(PARAMS_YAML)
    return path


def reference(
    frames: Frames, params_file: Path, *, images: bool = True
) -> tuple[list[NDArray[np.float32]], dict[Any, Any]]:
    """Depth of every frame and label results by frame index, from a session run directly on the frames.

    ``images=False``: the labeler sees disparities only, as the node in external mode (no texture cue).
    """
    matcher, labeler = load_params(params_file)
    session = LabelingSession(frames.camera, matcher, labeler)
    depths, results = [], {}
    for k in range(len(frames.left)):
        stamp = frames.stamp_ns(k) / 1e9
        if images:
            out = session.process(frames.left[k], frames.right[k], frames.poses[k], stamp=stamp, key=k)
            depths.append(out.depth)
            labelled = out.labelled
        else:
            disparity, depth = session.match(frames.left[k], frames.right[k])
            depths.append(depth)
            labelled, _ = session.label(disparity, frames.poses[k], stamp=stamp, key=k)
        results.update({r.key: r for r in labelled})
    results.update({r.key: r for r in session.flush()})
    return depths, results


# --------------------------------------------------------------------------- test-side publisher and recorder


class Feeder:
    """Publishes frames to the labeler's input topics (reliable QoS, deep history: nothing lost in the test)."""

    def __init__(self, node: Any, *, odom: bool = False) -> None:
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image

        qos = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
        self.odom = odom
        self.left = node.create_publisher(Image, topics.LEFT_IMAGE, qos)
        self.right = node.create_publisher(Image, topics.RIGHT_IMAGE, qos)
        self.left_info = node.create_publisher(CameraInfo, topics.LEFT_INFO, qos)
        self.right_info = node.create_publisher(CameraInfo, topics.RIGHT_INFO, qos)
        self._pose_type = Odometry if odom else PoseStamped
        self.pose = node.create_publisher(self._pose_type, "odom" if odom else topics.POSE, qos)

    def matched(self) -> bool:
        """Whether the labeler subscribed to every input."""
        publishers = (self.left, self.right, self.left_info, self.right_info, self.pose)
        return all(p.get_subscription_count() >= 1 for p in publishers)

    def infos(self, camera: StereoCamera, stamp_ns: int, *, mangle: Callable[[Any], None] | None = None) -> None:
        from selfcontra_ros.ros.conversions import camera_infos_from_stereo_camera, nanoseconds_to_stamp

        left, right = camera_infos_from_stereo_camera(camera, nanoseconds_to_stamp(stamp_ns), FRAME_ID)
        if mangle is not None:
            mangle(left)
        self.left_info.publish(left)
        self.right_info.publish(right)

    def images(
        self,
        left: NDArray[Any],
        right: NDArray[Any],
        stamp_ns: int,
        *,
        encoding: str = "mono8",
        right_stamp_ns: int | None = None,
    ) -> None:
        from selfcontra_ros.ros.conversions import nanoseconds_to_stamp, numpy_to_image

        stamp = nanoseconds_to_stamp(stamp_ns)
        self.left.publish(numpy_to_image(left, encoding, stamp=stamp, frame_id=FRAME_ID))
        rstamp = stamp if right_stamp_ns is None else nanoseconds_to_stamp(right_stamp_ns)
        self.right.publish(numpy_to_image(right, encoding, stamp=rstamp, frame_id=FRAME_ID))

    def send_pose(self, pose: NDArray[np.float64], stamp_ns: int, *, quaternion: Any = None) -> None:
        """Publish ``pose`` (its rotation as a quaternion, or ``quaternion`` as given) stamped ``stamp_ns``."""
        from selfcontra_ros.ros.conversions import nanoseconds_to_stamp

        msg = self._pose_type()
        msg.header.stamp = nanoseconds_to_stamp(stamp_ns)
        msg.header.frame_id = topics.WORLD_FRAME
        target = msg.pose.pose if self.odom else msg.pose
        if self.odom:
            msg.child_frame_id = FRAME_ID
        target.position.x, target.position.y, target.position.z = (float(v) for v in pose[:3, 3])
        q = quaternion_from_rotation(pose[:3, :3]) if quaternion is None else quaternion
        o = target.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in q)
        self.pose.publish(msg)

    def frame(self, frames: Frames, k: int, *, pose_first: bool = False, stamp_ns: int | None = None) -> None:
        """Frame ``k``: infos, images and pose (the pose before or after the images)."""
        stamp = frames.stamp_ns(k) if stamp_ns is None else stamp_ns
        if pose_first:
            self.send_pose(frames.poses[k], stamp)
        self.infos(frames.camera, stamp)
        self.images(frames.left[k], frames.right[k], stamp)
        if not pose_first:
            self.send_pose(frames.poses[k], stamp)


class Recorder:
    """Collects the labeler's outputs (deserialised) and its latest stats."""

    def __init__(self, node: Any) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image
        from std_msgs.msg import String
        from stereo_msgs.msg import DisparityImage

        qos = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
        outputs = {
            topics.DEPTH: Image,
            topics.DISPARITY: DisparityImage,
            topics.LABELS: Image,
            topics.LABELS_COLOR: Image,
            "debug/support": Image,
            "debug/vote_sum": Image,
            "debug/uncertainty": Image,
        }
        self.received: dict[str, list[Any]] = {name: [] for name in outputs}
        self.subscriptions = {
            name: node.create_subscription(msg_type, name, self.received[name].append, qos)
            for name, msg_type in outputs.items()
        }
        self.stats: dict[str, Any] | None = None
        stats_qos = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        self.subscriptions["stats"] = node.create_subscription(String, "/labeler/stats", self._on_stats, stats_qos)

    def _on_stats(self, msg: Any) -> None:
        self.stats = json.loads(msg.data)

    def count(self, name: str) -> int:
        return len(self.received[name])

    def matched(self) -> bool:
        """Whether the labeler's depth and label publishers reach this recorder."""
        return all(self.subscriptions[n].get_publisher_count() >= 1 for n in (topics.DEPTH, topics.LABELS))


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def check_outputs(
    recorder: Recorder, frames: Frames, params_file: Path, *, flushed: bool, external: bool = False
) -> None:
    """Depth of every frame and labels of the labelled views equal the reference session's, with the right headers."""
    from selfcontra_ros.ros.conversions import disparity_from_message, image_to_numpy

    depths, results = reference(frames, params_file, images=not external)
    matcher, _ = load_params(params_file)
    max_disparity = matcher.min_disparity + matcher.num_disparities - 1
    n_frames = len(frames.left)
    depth_msgs = recorder.received[topics.DEPTH]
    assert [stamp_ns(m) for m in depth_msgs] == [frames.stamp_ns(k) for k in range(n_frames)]
    for k, msg in enumerate(depth_msgs):
        assert msg.header.frame_id == FRAME_ID and msg.encoding == "32FC1"
        depth = image_to_numpy(msg)
        assert np.array_equal(depth, depths[k], equal_nan=True), f"depth of frame {k} differs from the session's"
        # The depth is the camera's disparity_to_depth of the published disparity.
        disparity_msg = recorder.received[topics.DISPARITY][k]
        disparity, f, t = disparity_from_message(disparity_msg)
        assert (f, t) == pytest.approx((frames.camera.fx, frames.camera.baseline))
        if not external:  # else DISPARITY carries the test's own input
            # The search range as the offline labeler reports it (stereo_image_proc: min + num - 1).
            assert (disparity_msg.min_disparity, disparity_msg.max_disparity) == (matcher.min_disparity, max_disparity)
        assert np.array_equal(frames.camera.disparity_to_depth(disparity).astype(np.float32), depth, equal_nan=True)
    labelled = n_frames if flushed else n_frames - DELAY
    label_msgs = recorder.received[topics.LABELS]
    assert [stamp_ns(m) for m in label_msgs] == [frames.stamp_ns(k) for k in range(labelled)]
    for k, msg in enumerate(label_msgs):
        assert msg.header.frame_id == FRAME_ID and msg.encoding == "mono8"
        labels = image_to_numpy(msg)
        assert np.array_equal(labels, results[k].labels), f"labels of frame {k} differ from the session's"
        color = recorder.received[topics.LABELS_COLOR][k]
        assert stamp_ns(color) == stamp_ns(msg) and color.encoding == "rgb8"
        assert np.array_equal(image_to_numpy(color), colorize_labels(labels))
    assert any((image_to_numpy(m) == 1).any() for m in label_msgs), "no positive label at all"


def spin_nodes(nodes: list[Any], predicate: Callable[[], bool], timeout: float) -> bool:
    """Spin several nodes of one context in one executor until ``predicate()`` holds or ``timeout`` s pass."""
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=nodes[0].context)
    for node in nodes:
        executor.add_node(node)
    deadline = time.monotonic() + timeout
    try:
        while not predicate() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
    finally:
        for node in nodes:
            executor.remove_node(node)
        executor.shutdown()
    return predicate()


def refused_node(context: Any, argument: str, message: str) -> None:
    """A labeler node given the one ``-p`` ``argument`` (``name:=value``, the value read as the CLI reads it) and
    defaults otherwise fails to start with :class:`LabelerConfigError` or rclpy's ``ParameterException`` (what
    ``main`` reports as exit code 2), saying ``message``."""
    import yaml
    from rclpy.exceptions import ParameterException
    from rclpy.parameter import Parameter

    from selfcontra_ros.ros.labeler_node import LabelerConfigError, LabelerNode

    name, _, value = argument.partition(":=")
    override = Parameter(name, value=yaml.safe_load(value))
    with pytest.raises((LabelerConfigError, ParameterException), match=re.escape(message)):
        LabelerNode(context=context, parameter_overrides=[override])


def exits_with_code_2(ros_process: Callable[..., Any], arguments: list[str], message: str) -> str:
    """The labeler executable given the ``-p`` ``arguments`` and defaults otherwise exits with code 2 and
    reports ``message`` without a traceback (the process path of :func:`refused_node`); returns its stderr."""
    node = ros_process([*NODE, *(arg for argument in arguments for arg in ("-p", argument))], name="labeler")
    assert node.popen.wait(timeout=WAIT_S) == 2, node.stderr()
    err = node.stderr()
    assert message in err
    assert "Traceback" not in err
    return str(err)


@pytest.fixture
def labeler_node(rclpy_context: Any, params_file: Path) -> Iterator[Callable[..., Any]]:
    """Factory of in-process labeler nodes (parameters of the test YAML plus overrides), destroyed at teardown."""
    from rclpy.parameter import Parameter

    from selfcontra_ros.config import to_ros_parameters
    from selfcontra_ros.ros.labeler_node import LabelerNode

    created: list[Any] = []

    def make(**overrides: Any) -> Any:
        values = to_ros_parameters(*load_params(params_file))
        values.update({"input_qos": "reliable", "stats_period": 0.1, "label_queue_size": 16})
        values.update(overrides)
        node = LabelerNode(
            context=rclpy_context, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]
        )
        created.append(node)
        return node

    yield make
    for node in created:
        node.destroy_node()


def start_labeler(ros_process: Callable[..., Any], params_file: Path, *parameters: str) -> Any:
    """The labeler as a subprocess with the params file, reliable inputs, a label queue of 16 and ``parameters``."""
    extra = [arg for parameter in parameters for arg in ("-p", parameter)]
    return ros_process(
        [*NODE, "--params-file", str(params_file), "-p", "input_qos:=reliable", "-p", "label_queue_size:=16", *extra],
        name="labeler",
    )


# --------------------------------------------------------------------------- tests


def test_node_process_labels_a_sequence_like_the_session(
    frames: Frames,
    params_file: Path,
    ros_node: Any,
    ros_process: Callable[..., Any],
    spin_until: Callable[[Any, Callable[[], bool], float], bool],
) -> None:
    """Subprocess with --params-file: depth for every frame, labels label_delay frames back, debug maps, SIGINT."""
    from selfcontra_ros.ros.conversions import image_to_numpy

    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    node = start_labeler(ros_process, params_file, "publish_debug:=true")
    assert spin_until(ros_node, lambda: feeder.matched() and recorder.matched(), WAIT_S), node.stderr()
    for k in range(FRAMES):
        feeder.frame(frames, k, pose_first=k % 2 == 0)  # the pose before or after the images: both work
    expected_labels = FRAMES - DELAY
    done = spin_until(
        ros_node,
        lambda: recorder.count(topics.DEPTH) >= FRAMES and recorder.count("debug/uncertainty") >= expected_labels,
        WAIT_S,
    )
    assert done, f"{ {n: recorder.count(n) for n in recorder.received} }\n{node.stderr()}"
    assert spin_until(
        ros_node, lambda: recorder.stats is not None and recorder.stats["counts"]["views_labelled"] == FRAMES, 5.0
    ), recorder.stats
    check_outputs(recorder, frames, params_file, flushed=False)

    _, results = reference(frames, params_file)
    for k in range(expected_labels):
        assert np.array_equal(image_to_numpy(recorder.received["debug/support"][k]), results[k].support)
        assert np.array_equal(image_to_numpy(recorder.received["debug/vote_sum"][k]), results[k].vote_sum)
        uncertainty = image_to_numpy(recorder.received["debug/uncertainty"][k])
        assert np.array_equal(uncertainty, results[k].uncertainty, equal_nan=True)

    stats = recorder.stats
    assert stats is not None
    # The YAML was applied (the node reports the parameters it runs with).
    assert stats["params"]["labeler"]["window_size"] == 6
    assert stats["params"]["matcher"]["num_disparities"] == 64
    assert sum(stats["drops"].values()) == 0, stats["drops"]
    assert node.stop() == 0, node.stderr()  # SIGINT: clean exit
    assert "Traceback" not in node.stderr()
    assert "stopped:" in node.stderr() + node.stdout()


def test_sigterm_with_flush_on_shutdown_labels_the_waiting_views(
    frames: Frames,
    params_file: Path,
    ros_node: Any,
    ros_process: Callable[..., Any],
    spin_until: Callable[[Any, Callable[[], bool], float], bool],
) -> None:
    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    node = start_labeler(ros_process, params_file, "flush_on_shutdown:=true")
    assert spin_until(ros_node, lambda: feeder.matched() and recorder.matched(), WAIT_S), node.stderr()
    for k in range(FRAMES):
        feeder.frame(frames, k)
    assert spin_until(ros_node, lambda: recorder.count(topics.LABELS_COLOR) >= FRAMES - DELAY, WAIT_S), node.stderr()
    node.popen.send_signal(signal.SIGTERM)
    assert spin_until(ros_node, lambda: recorder.count(topics.LABELS_COLOR) >= FRAMES, WAIT_S), node.stderr()
    assert node.popen.wait(timeout=WAIT_S) == 0, node.stderr()
    check_outputs(recorder, frames, params_file, flushed=True)


def test_flush_on_shutdown_waits_for_a_slow_labeling_worker(
    frames: Frames,
    params_file: Path,
    ros_node: Any,
    labeler_node: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """flush_on_shutdown: stopping waits for the labeling worker however long its queued views take (here
    the worker is held for many times the node's join timeout, as on a loaded machine), then flushes the
    window. No label is lost; a bounded wait skipped the flush and lost the window's last labels."""
    from selfcontra_ros.ros import labeler_node as node_module

    monkeypatch.setattr(node_module, "_JOIN_TIMEOUT_S", 0.05)
    label = LabelingSession.label
    release = threading.Event()

    def held_label(self: LabelingSession, *args: Any, **kwargs: Any) -> Any:
        if threading.current_thread().name == "selfcontra_labeling":  # the node's worker, not the reference
            assert release.wait(WAIT_S)
        return label(self, *args, **kwargs)

    monkeypatch.setattr(LabelingSession, "label", held_label)
    node = labeler_node(flush_on_shutdown=True)
    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    assert spin_nodes([node, ros_node], lambda: feeder.matched() and recorder.matched(), WAIT_S)
    for k in range(FRAMES):
        feeder.frame(frames, k)
    queued = lambda: node.stats()["counts"].get("views_queued", 0) >= FRAMES  # noqa: E731
    assert spin_nodes([node, ros_node], queued, WAIT_S), node.stats()
    assert node.stats()["counts"].get("views_labelled", 0) == 0
    timer = threading.Timer(0.5, release.set)  # ten join timeouts into the stop
    timer.start()
    try:
        node.stop()
    finally:
        release.set()
        timer.join()
    assert node.stats()["counts"]["views_labelled"] == FRAMES
    assert spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= FRAMES, WAIT_S), node.stats()
    check_outputs(recorder, frames, params_file, flushed=True)
    assert node.stats()["drops"].get("shutdown_discarded", 0) == 0


def test_reliable_input_keeps_every_message_while_the_node_is_behind(
    frames: Frames, params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    """input_qos reliable: a node that takes no message while a whole sequence is published (an executor
    far behind, as on a loaded machine) still gets every frame and pose, and labels as the session does. The
    subscriptions keep every unread message; with a keep-last history of 5 (queue_size 2) the reader would
    silently overwrite the first frames, and the missing poses would make others' poses interpolations."""
    node = labeler_node(queue_size=2)
    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    assert spin_nodes([node, ros_node], lambda: feeder.matched() and recorder.matched(), WAIT_S)
    for k in range(FRAMES):
        feeder.frame(frames, k)
    time.sleep(1.0)  # every message reaches the node's reader before it takes one
    done = spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= FRAMES - DELAY, WAIT_S)
    assert done, (recorder.stats, node.stats())
    assert node.stats()["counts"]["frames"] == FRAMES
    check_outputs(recorder, frames, params_file, flushed=False)


def test_odometry_pose_source(
    frames: Frames, params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    node = labeler_node(pose_source="odom")
    feeder = Feeder(ros_node, odom=True)
    recorder = Recorder(ros_node)
    assert spin_nodes([node, ros_node], lambda: feeder.matched() and recorder.matched(), WAIT_S)
    for k in range(FRAMES):
        feeder.frame(frames, k)
    done = spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= FRAMES - DELAY, WAIT_S)
    assert done, (recorder.stats, node.stats())
    check_outputs(recorder, frames, params_file, flushed=False)


def test_invalid_parameter_exits_with_code_2(ros_process: Callable[..., Any]) -> None:
    """The executable reports a parameter rclpy refuses (outside its declared range) in one line, exit code 2."""
    exits_with_code_2(ros_process, ["labeler.window_size:=1"], "out of range")


@pytest.mark.parametrize(
    ("argument", "message"),
    [
        ("sync:=fuzzy", "expected one of exact, approximate"),
        ("labeler.window_size:=1", "out of range"),
        ("matcher.num_disparities:=100", "not a valid step"),
        ("matcher.mode:=fast", "MatcherParams.mode must be one of"),
    ],
)
def test_invalid_parameter_is_refused_with_its_reason(rclpy_context: Any, argument: str, message: str) -> None:
    """Each invalid parameter (defaults otherwise) raises one of the errors ``main`` turns into exit code 2, naming
    what is wrong. In process: the executable's path is the test above, and each node process costs seconds."""
    refused_node(rclpy_context, argument, message)


def test_external_disparity_mode_labels_the_given_disparities(
    frames: Frames, params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    """matcher.algorithm external: each DisparityImage is a view; given SGBM's disparities, the labels are SGBM's."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from stereo_msgs.msg import DisparityImage

    from selfcontra_ros.ros.conversions import disparity_image, nanoseconds_to_stamp

    node = labeler_node(**{"matcher.algorithm": "external"})
    feeder = Feeder(ros_node)
    # The recorder's "disparity" subscription receives these input messages (the node publishes none in this mode).
    recorder = Recorder(ros_node)
    disparity_pub = ros_node.create_publisher(
        DisparityImage, topics.DISPARITY, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    )
    matched = lambda: disparity_pub.get_subscription_count() >= 2 and recorder.matched()  # noqa: E731
    assert spin_nodes([node, ros_node], matched, WAIT_S)
    matcher, _ = load_params(params_file)
    session = LabelingSession(frames.camera, matcher)
    for k in range(FRAMES):
        stamp = frames.stamp_ns(k)
        disparity, _ = session.match(frames.left[k], frames.right[k])
        feeder.infos(frames.camera, stamp)
        disparity_pub.publish(
            disparity_image(disparity, frames.camera, stamp=nanoseconds_to_stamp(stamp), frame_id=FRAME_ID)
        )
        feeder.send_pose(frames.poses[k], stamp)
    done = spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= FRAMES - DELAY, WAIT_S)
    assert done, (recorder.stats, node.stats())
    check_outputs(recorder, frames, params_file, flushed=False, external=True)


@pytest.mark.parametrize(
    ("blank", "posed"),
    [
        (set(), range(11)),  # every frame reliable: each comes out smoothing_lag_frames (5) frames later
        ({3, 4, 6, 7}, [0, 1, 2, *range(8, 11)]),  # frame 5: isolated, decided at frame 7
        ({3, 4, 6}, [0, 1, 2, 5, *range(7, 11)]),  # frame 5: reliable, frame 6 behind it
    ],
)
def test_odometry_pose_source_labels_the_frames_the_odometry_poses(
    blank: set[int], posed: Sequence[int], params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    """pose_source odometry: no pose topic; frames come out 5 frames late (their step lengths smoothed over
    the frames after them). Blank frames (a lens cap) have no reliable pose: their depth and disparity go out
    and they are not labelled. Frame 5, after two blank frames, is ``isolated`` when two more blank frames
    follow, reliable when a reliable one does. At 1 Hz the views wait 5 s for their decision, beyond
    ``max_pose_gap``. The labels equal a session fed the frames the odometry decided reliable, in order; at
    shutdown (``flush_on_shutdown``) the frames the odometry still held are decided and labelled too."""
    from selfcontra_ros.odometry.run import OnlineOdometry
    from selfcontra_ros.ros.conversions import image_to_numpy

    n = 16
    scene = make_scene("street", 2, 320, 96, frames=n)
    rendered = [scene.render(k) for k in range(n)]
    grey = np.full_like(rendered[0].left, 128)
    left = [grey if k in blank else f.left for k, f in enumerate(rendered)]
    right = [grey if k in blank else f.right for k, f in enumerate(rendered)]
    stamps = [STAMP0_NS + k * 10 * PERIOD_NS for k in range(n)]  # 1 Hz: a decision 2 frames late is 2 s late
    odometry = OnlineOdometry(scene.camera)
    decisions = [d for k in range(n) for d in odometry.add(stamps[k], left[k], right[k])]
    status = {stamps.index(d.stamp_ns): d.quality.status for d in decisions}
    assert len(decisions) == n - odometry.max_hold == 11
    isolated = [k for k, st in status.items() if st == "isolated"]
    if [stamps.index(d.stamp_ns) for d in decisions if d.pose is not None] != list(posed) or isolated != (
        [5] if 7 in blank else []
    ):  # the odometry's own outcome (ORB, RANSAC) on this machine; the node's plumbing is what is tested
        pytest.skip(f"the odometry decided {status} here, not the scenario this case needs")
    matcher, labeler = load_params(params_file)
    session = LabelingSession(scene.camera, matcher, labeler)
    expected = []
    for d in decisions:
        if d.pose is not None:
            k = stamps.index(d.stamp_ns)
            expected += session.process(left[k], right[k], d.pose, stamp=stamps[k] / 1e9, key=k).labelled
    assert expected, "some views should be labelled"

    node = labeler_node(pose_source="odometry", flush_on_shutdown=True)
    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    subscribed = lambda: feeder.left.get_subscription_count() >= 1 and recorder.matched()  # noqa: E731
    assert spin_nodes([node, ros_node], subscribed, WAIT_S)
    assert feeder.pose.get_subscription_count() == 0, "no pose topic with pose_source odometry"
    for k in range(n):  # one frame at a time, as a camera sends them (12 at once overflow queue_size 10)
        feeder.infos(scene.camera, stamps[k])
        feeder.images(left[k], right[k], stamps[k])
        assert spin_nodes([node, ros_node], lambda k=k: recorder.count(topics.DEPTH) > k, WAIT_S), k
    done = spin_nodes(
        [node, ros_node],
        lambda: recorder.count(topics.LABELS) >= len(expected) and recorder.count(topics.DEPTH) >= n,
        WAIT_S,
    )
    assert done, (recorder.stats, node.stats())
    assert [stamp_ns(m) for m in recorder.received[topics.DEPTH]] == stamps
    assert [stamp_ns(m) for m in recorder.received[topics.DISPARITY]] == stamps
    received = recorder.received[topics.LABELS]
    assert [stamp_ns(m) for m in received] == [stamps[r.key] for r in expected]
    for msg, result in zip(received, expected, strict=True):
        assert np.array_equal(image_to_numpy(msg), result.labels)
    assert node.stats()["drops"].get("odometry_unreliable", 0) == len(blank) + len(isolated)
    # Shutdown with flush_on_shutdown: the odometry decides the frames it still holds (the end of the
    # sequence) and those with a pose are labelled, then the window is flushed, as the session does.
    for d in odometry.finish():
        if d.pose is not None:
            k = stamps.index(d.stamp_ns)
            expected += session.process(left[k], right[k], d.pose, stamp=stamps[k] / 1e9, key=k).labelled
    expected += session.flush()
    node.stop()
    assert spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS) >= len(expected), WAIT_S)
    received = recorder.received[topics.LABELS]
    assert [stamp_ns(m) for m in received] == [stamps[r.key] for r in expected]
    for msg, result in zip(received, expected, strict=True):
        assert np.array_equal(image_to_numpy(msg), result.labels)
    assert node.stats()["drops"].get("shutdown_discarded", 0) == 0


def test_the_odometry_takes_the_rigs_disparity_offset(
    params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    """pose_source odometry with a known disparity offset: the node's odometry adds it to every disparity
    from its first frame on and, with estimation off, keeps it; an offset beyond +-5 px is refused."""
    from selfcontra_ros.ros.labeler_node import LabelerConfigError

    scene = make_scene("street", 2, 320, 96, frames=3)
    node = labeler_node(pose_source="odometry", odometry_disparity_offset_px=0.3, odometry_estimate_offset=False)
    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    subscribed = lambda: feeder.left.get_subscription_count() >= 1 and recorder.matched()  # noqa: E731
    assert spin_nodes([node, ros_node], subscribed, WAIT_S)
    for k in range(3):
        frame = scene.render(k)
        feeder.infos(scene.camera, STAMP0_NS + k * PERIOD_NS)
        feeder.images(frame.left, frame.right, STAMP0_NS + k * PERIOD_NS)
        assert spin_nodes([node, ros_node], lambda k=k: recorder.count(topics.DEPTH) > k, WAIT_S), k
    odometry = node._odometry
    assert odometry is not None and odometry.last_quality is not None
    assert odometry.last_quality.disparity_offset_px == 0.3
    assert odometry.last_quality.status != "first"  # a measured frame, not only the first one
    with pytest.raises(LabelerConfigError, match="disparity_offset_px"):
        labeler_node(pose_source="odometry", odometry_disparity_offset_px=7.0)
    # The road's second measure of each step: on by default, off for a camera that never sees the ground.
    assert node._odometry_params.road_steps
    assert not labeler_node(pose_source="odometry", odometry_road_steps=False)._odometry_params.road_steps


def test_an_odometry_error_publishes_the_frame_and_starts_over(
    params_file: Path, ros_node: Any, labeler_node: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """pose_source odometry: an exception in the odometry (frame 10 here) does not cost the frame its depth or
    stop the node. Its state is unknown, so the node starts over as after a time jump: the views waiting for
    the old odometry's decisions are dropped, and frames 11-15 are labelled by a new session from a new
    odometry's poses (which must not meet the old views'). The labels equal two sessions fed that way."""
    from selfcontra_ros.odometry.run import OnlineOdometry
    from selfcontra_ros.ros.conversions import image_to_numpy

    n, failing = 16, 10
    scene = make_scene("street", 2, 320, 96, frames=n)
    rendered = [scene.render(k) for k in range(n)]
    stamps = [STAMP0_NS + k * 10 * PERIOD_NS for k in range(n)]
    matcher, labeler = load_params(params_file)

    def labelled(frames: range, *, finish: bool) -> tuple[list[Any], list[int]]:
        """A fresh odometry and session fed ``frames``: the labels, and the frames still undecided at the end."""
        odometry = OnlineOdometry(scene.camera)
        session = LabelingSession(scene.camera, matcher, labeler)
        decisions = [d for k in frames for d in odometry.add(stamps[k], rendered[k].left, rendered[k].right)]
        waiting = [stamps.index(s) for s in odometry.undecided()]
        if finish:
            decisions += odometry.finish()
        out = []
        for d in decisions:
            if d.pose is not None:
                k = stamps.index(d.stamp_ns)
                out += session.process(
                    rendered[k].left, rendered[k].right, d.pose, stamp=stamps[k] / 1e9, key=k
                ).labelled
        return out + (session.flush() if finish else []), waiting

    before, waiting = labelled(range(failing), finish=False)
    after, _ = labelled(range(failing + 1, n), finish=True)
    assert before and after, "both sessions should label views"

    add = OnlineOdometry.add

    def failing_add(self: Any, stamp: int, left: Any, right: Any) -> Any:
        if stamp == stamps[failing]:
            raise ValueError("injected odometry defect")
        return add(self, stamp, left, right)

    monkeypatch.setattr(OnlineOdometry, "add", failing_add)
    node = labeler_node(pose_source="odometry", flush_on_shutdown=True)
    feeder = Feeder(ros_node)
    recorder = Recorder(ros_node)
    subscribed = lambda: feeder.left.get_subscription_count() >= 1 and recorder.matched()  # noqa: E731
    assert spin_nodes([node, ros_node], subscribed, WAIT_S)
    for k in range(n):
        if k == failing:  # the old session's posed views are labelled before it ends (else dropped: a race)
            assert spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS) >= len(before), WAIT_S)
        feeder.infos(scene.camera, stamps[k])
        feeder.images(rendered[k].left, rendered[k].right, stamps[k])
        assert spin_nodes([node, ros_node], lambda k=k: recorder.count(topics.DEPTH) > k, WAIT_S), k
    node.stop()
    expected = before + after
    assert spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS) >= len(expected), WAIT_S), (
        recorder.stats,
        node.stats(),
    )
    assert [stamp_ns(m) for m in recorder.received[topics.DEPTH]] == stamps, "every frame keeps its depth"
    received = recorder.received[topics.LABELS]
    assert [stamp_ns(m) for m in received] == [stamps[r.key] for r in expected]
    for msg, result in zip(received, expected, strict=True):
        assert np.array_equal(image_to_numpy(msg), result.labels)
    drops = node.stats()["drops"]
    assert drops["odometry_error"] == 1
    assert drops["session_reset"] == len(waiting) > 0
