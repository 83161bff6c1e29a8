"""Bag player node: replays a rosbag2 bag onto the ROS 2 graph with its recorded timing.

Run::

    python -m selfcontra_ros.ros.player_node --ros-args -p bag:=/data/seq06 -p rate:=2.0
    ros2 run selfcontra_ros player --ros-args -p bag:=/data/seq06 -r /stereo/left/image_rect:=/cam/left

Each message is published as it is stored (raw CDR, bit-exact, header stamps
as recorded) when its turn comes: message ``k`` with log time ``t_k`` goes
out ``(t_k - t_start) / rate`` seconds of steady (monotonic) time after
playback began. Topics keep the bag's names, but as names relative to the
node's namespace (``stereo/left/image_rect``), so remap rules and
``__ns:=/robot`` apply as to any node.

Parameters (all read once at start):

``bag`` (string, required)
    bag folder or ``.mcap`` file.
``rate`` (double, 1.0, 0.001..1000)
    playback speed factor.
``loop`` (bool, false)
    start over after the last message, until shut down; the next pass begins
    one mean stamp period (0.1 s for a single-instant bag) after the last
    message, scaled by ``rate``.
``start_offset`` (double, 0.0 s)
    skip the first seconds of the bag.
``publish_clock`` (bool, false)
    publish ``/clock`` (rosgraph_msgs/Clock) with the bag time of each
    message just before it, for nodes running with ``use_sim_time``.
``wait_for_subscribers`` (int, 0)
    before playing, wait until the bag's topics together have at least this
    many matched subscriptions (0: play at once). With reliable QoS and
    volatile durability a subscriber that appears late misses the first
    messages; tests and pipelines that need every message set this to the
    number of subscriptions they create.
``qos_reliability`` (string, ``reliable``), ``qos_depth`` (int, 10)
    publisher QoS (history keep-last, volatile). ``reliable`` is the default
    because a reliable publisher serves both reliable and best-effort
    subscribers, while a best-effort one serves only best-effort ones.
``pose_source`` (string, ``none``: publish the bag as recorded; ``tf``)
    turn the bag's ``/tf`` and ``/tf_static`` into the pose of the left camera
    (see below).
``world_frame`` (string), ``camera_frame`` (string, ``""``: the left camera_info's frame id)
    the TF frames of ``pose_source: tf`` (``world_frame`` required there, e.g. ``odom``).
``stereo_namespace`` (string, ``""``: found from the left image topic), ``remaps`` (string array),
``image_transport`` (``raw`` or ``compressed``), ``rectify`` (bool, false)
    where the bag's left image, left camera_info and TF topics are, in the
    terms of the offline commands (``selfcontra label BAG --namespace NS
    --remap FROM:=TO --image-transport ... --rectify``,
    :class:`~selfcontra_ros.bags.stereo_input.StereoInput`): ``remaps`` holds
    the same ``FROM:=TO`` rules, e.g. ``-p remaps:='["left/image_raw:=cam_left/image_raw"]'``
    (each rule in double quotes) or a params file; used with ``pose_source: tf`` only.

**TF to pose** (``pose_source: tf``). A robot's bag has its poses in TF
(``odom -> base_link`` on ``/tf``, ``base_link -> <camera>_optical_frame`` on
``/tf_static``), as ``tf2_msgs/TFMessage``, which the PyPI ROS wheels cannot
publish (the player skips such topics), and a labeler without ``tf2_ros``
cannot read. The player composes them itself instead
(:class:`BagTFPoses`: the package's :class:`~selfcontra_ros.bags.tf.TFBuffer`,
interpolated at the stamp) and publishes ``geometry_msgs/PoseStamped`` of the
left camera (``camera_frame`` in ``world_frame``, header frame id
``world_frame``) at each left image's header stamp, on the labeler's pose
topic: the relative ``pose`` resolved in the stereo namespace like the bag's
topics (``/sensors/stereo/pose`` for ``/sensors/stereo/cam_left/...``,
remappable with ``remaps`` ``pose:=...`` or the player's own ``-r``). With
``rectify`` the rotation ``R`` of the left camera_info is applied
(``T_world_camera @ R^T``, as
:attr:`~selfcontra_ros.rectification.Rectifier.raw_from_rectified`), so the
pose is that of the rectified left view, the one a labeler with ``rectify:
true`` labels: that labeler then runs with ``pose_source: pose``. A pose goes
out as soon as TF covers its stamp (the next ``/tf`` message after it), or,
when TF stops, once the bag is ``0.5`` s past the stamp (extrapolating at
most ``0.05`` s), as the offline bag labeler decides; a stamp TF cannot
answer is counted in :attr:`PlayerNode.pose_misses` by the reason of
:class:`~selfcontra_ros.errors.TransformError` and logged (naming the missing
link). On a robot whose ROS install has ``tf2_ros`` none of this is needed:
play ``/tf`` as recorded and run the labeler with ``pose_source: tf``.

Without ``loop`` the node logs a summary after the last message, waits (at
most 1 s) until reliable subscribers acknowledged everything, and the process
exits with code 0. Exit codes: 0 done or stopped by SIGINT/SIGTERM,
1 the bag cannot be read, 2 invalid parameters.
"""

from __future__ import annotations

import importlib
import sys
import time
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np
import rclpy
from numpy.typing import NDArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher  # unparameterised: generic (Publisher[MsgT]) in Kilted, not in Jazzy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.reader import Bag, BagError, RawMessage, default_typestore, open_bag
from selfcontra_ros.bags.stereo_input import IMAGE_TRANSPORTS, PoseAt, StereoInput, TFPoses
from selfcontra_ros.bags.tf import TFBuffer
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.rectification import raw_from_rectified
from selfcontra_ros.ros.conversions import stamp_to_nanoseconds
from selfcontra_ros.ros.environment import prepare_ros_environment
from selfcontra_ros.ros.spinning import spin_until_stopped, stop_on_signals

__all__ = ["PLAYER_POSE_SOURCES", "BagTFPoses", "PlayerConfigError", "PlayerNode", "PoseMessages", "main"]

NODE_NAME = "player"
_NS_PER_S = 1_000_000_000
_RELIABILITIES = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}
# Polling period while waiting for subscribers, and how often the wait is logged.
_WAIT_POLL_S = 0.02
_WAIT_LOG_S = 5.0
# Upper bound of the wait for reliable subscribers' acknowledgements at the end. Fast DDS asks for them
# with its heartbeat (every 3 s by default), so a longer wait would mostly delay the exit.
_ACK_TIMEOUT_S = 1.0
# Gap between loop passes when a bag holds a single instant: the usual 10 Hz camera period.
_DEFAULT_PERIOD_NS = 100_000_000
# Timers need a positive period; a message due sooner than this goes out at once.
_MIN_PERIOD_NS = 100_000
#: Accepted ``pose_source`` values: publish as recorded, or add the left camera's pose composed from TF.
PLAYER_POSE_SOURCES = ("none", "tf")
# TF limits of the pose conversion, seconds: those of the offline bag labeler (max_pose_gap, max_pose_extrapolation).
_TF_MAX_GAP_S = 0.5
_TF_MAX_EXTRAPOLATION_S = 0.05


class PlayerConfigError(SelfContraError):
    """A parameter of the player is missing or invalid."""


def _message_class(msgtype: str) -> Any:
    """The rclpy message class of ``package/msg/Type``, or None when this ROS install lacks it."""
    package, _, name = msgtype.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def _descriptor(description: str, **kwargs: Any) -> ParameterDescriptor:
    return ParameterDescriptor(description=description, **kwargs)


class BagTFPoses:
    """The left camera's pose at each left image of a bag, composed from the bag's ``/tf`` and ``/tf_static``.

    Plain (no ROS): the player feeds it the messages of the topics in
    :attr:`topics` as it plays them (deserialised) and publishes what
    :meth:`add` returns. A left image's stamp waits until the TF chain
    ``world_frame -> camera_frame`` reaches it (``TFBuffer.newest_ns``), or the
    bag is ``max_gap_s`` past it (then the lookup may extrapolate
    ``max_extrapolation_s``), as :func:`~selfcontra_ros.bags.label_bag.label_bag`
    decides; :meth:`finish` decides every stamp still waiting at the end of a pass.

    Args:
        stereo_input: where the left image, its camera_info and TF are (``pose_source`` tf).
        topic_map: :meth:`StereoInput.topics` of the bag's stereo namespace.
        max_gap_s: TF samples interpolated at most this far apart, and the wait for TF, seconds.
        max_extrapolation_s: how far past a link's newest transform a given-up stamp may lie, seconds.

    Attributes:
        topics: bag topics read: left image, left camera_info, ``/tf``, ``/tf_static``.
        misses: reason -> stamps without a pose (:class:`~selfcontra_ros.errors.TransformError` reasons).
    """

    def __init__(
        self,
        stereo_input: StereoInput,
        topic_map: dict[str, str],
        *,
        max_gap_s: float = _TF_MAX_GAP_S,
        max_extrapolation_s: float = _TF_MAX_EXTRAPOLATION_S,
    ) -> None:
        if stereo_input.pose_source != "tf" or stereo_input.world_frame is None:
            raise PlayerConfigError("BagTFPoses needs a stereo input with pose_source 'tf' and a world_frame")
        self.input = stereo_input
        self.left_image = topic_map[stereo_input.left_image]
        self.left_info = topic_map[topics.LEFT_INFO]
        self.tf_topic, self.tf_static_topic = topic_map["tf"], topic_map["tf_static"]
        self.topics = (self.left_image, self.left_info, self.tf_topic, self.tf_static_topic)
        self.max_gap_ns = round(max_gap_s * _NS_PER_S)
        self.max_gap_s, self.max_extrapolation_s = max_gap_s, max_extrapolation_s
        self.misses: Counter[str] = Counter()
        self.reset()

    def reset(self) -> None:
        """Start a pass over the bag: empty TF buffer, no camera frame, nothing waiting (a loop jumps back in time)."""
        self.tf = TFBuffer(max_gap_s=self.max_gap_s, max_extrapolation_s=self.max_extrapolation_s)
        assert self.input.world_frame is not None
        self.poses = TFPoses(self.tf, self.input.world_frame, self.input.camera_frame)
        self._waiting: list[int] = []

    def add(self, topic: str, log_ns: int, msg: Any) -> list[tuple[int, PoseAt]]:
        """Take one message of :attr:`topics`; return ``(stamp, pose or miss)`` of the left images now decided.

        Returns:
            Oldest first; a miss carries the TF error's reason and message.
        """
        if topic in (self.tf_topic, self.tf_static_topic):
            self.tf.add_message(msg, static=topic == self.tf_static_topic)  # refusals are counted in tf.refused
        elif topic == self.left_info:
            # The rectified left view: Rectifier.raw_from_rectified, from R alone (no maps needed here).
            correction = raw_from_rectified(msg) if self.input.rectify else np.eye(4)
            self.poses.set_camera(str(msg.header.frame_id), correction)
        elif topic == self.left_image:
            self._waiting.append(stamp_to_nanoseconds(msg.header.stamp))
        return self._decide(log_ns)

    def finish(self) -> list[tuple[int, PoseAt]]:
        """Decide every stamp still waiting (the end of a pass)."""
        return self._decide(None)

    def _decide(self, now_ns: int | None) -> list[tuple[int, PoseAt]]:
        decided = []
        while self._waiting:
            stamp = self._waiting[0]
            newest = self.poses.newest_ns
            if now_ns is not None and (newest is None or newest < stamp) and now_ns <= stamp + self.max_gap_ns:
                break  # TF may still reach the stamp
            self._waiting.pop(0)
            found = self.poses.pose_at(stamp)
            if found.pose is None:
                self.misses[found.reason or "tf_lookup_failed"] += 1
            decided.append((stamp, found))
        return decided


class PoseMessages:
    """Serialised ``geometry_msgs/PoseStamped`` of 4x4 poses, built by the bags' own MessageBuilder.

    The player publishes them as raw CDR, as it publishes the bag's messages.
    """

    def __init__(self) -> None:
        self._typestore = default_typestore()
        self._make = MessageBuilder(self._typestore)

    def pose_stamped(self, pose: NDArray[np.float64], stamp_ns: int, frame_id: str) -> bytes:
        """CDR bytes of the PoseStamped of ``pose`` (metres; rotation as a unit quaternion x, y, z, w)."""
        msg = self._make.pose_stamped(pose, stamp_ns, frame_id)
        return bytes(self._typestore.serialize_cdr(msg, topics.POSE_TYPE))


class PlayerNode(Node):
    """Publishes the messages of a bag with their recorded timing scaled by ``rate`` (see the module docstring).

    Attributes:
        finished: a future that completes when playback ended (never with ``loop``).
        counts: messages published so far, per bag topic (and the pose topic with ``pose_source: tf``).
        pose_misses: ``pose_source: tf``: left image stamps without a pose, per TF reason.
    """

    def __init__(self, **kwargs: Any) -> None:
        """Declare the parameters, open the bag and create the publishers and the playback timer.

        Raises:
            PlayerConfigError: a parameter is missing or invalid.
            BagError: the bag cannot be opened.
        """
        super().__init__(NODE_NAME, **kwargs)
        self._bag: Bag | None = None
        try:
            self._setup()
        except BaseException:
            self.destroy_node()  # closes the bag if it was opened
            raise

    def _setup(self) -> None:
        self._declare_parameters()
        bag_path = str(self.get_parameter("bag").value)
        self._rate = float(self.get_parameter("rate").value)
        self._loop = bool(self.get_parameter("loop").value)
        start_offset = float(self.get_parameter("start_offset").value)
        publish_clock = bool(self.get_parameter("publish_clock").value)
        self._wait_for = int(self.get_parameter("wait_for_subscribers").value)
        reliability = str(self.get_parameter("qos_reliability").value)
        depth = int(self.get_parameter("qos_depth").value)
        if not bag_path:
            raise PlayerConfigError("parameter 'bag' is required: --ros-args -p bag:=/path/to/bag")
        if reliability not in _RELIABILITIES:
            raise PlayerConfigError(
                f"parameter 'qos_reliability' is {reliability!r}; expected one of {', '.join(_RELIABILITIES)}"
            )
        pose_input = self._pose_input()

        bag = self._bag = open_bag(bag_path)
        offset_ns = round(start_offset * _NS_PER_S)
        if bag.message_count and offset_ns > bag.duration_ns:
            raise PlayerConfigError(
                f"parameter 'start_offset' is {start_offset:g} s; the bag {bag_path} lasts "
                f"{bag.duration_ns / _NS_PER_S:g} s"
            )
        # A full read (no offset) lets the reader check the message counts against the bag's index.
        self._start_ns: int | None = bag.start_ns + offset_ns if offset_ns > 0 else None

        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=depth,
            reliability=_RELIABILITIES[reliability],
            durability=DurabilityPolicy.VOLATILE,
        )
        self._publishers_by_topic: dict[str, Publisher] = {}
        for name, info in bag.topics.items():
            msg_class = _message_class(info.msgtype)
            if msg_class is None:
                self.get_logger().warning(f"skipping {name}: message type {info.msgtype} is not installed")
                continue
            # Relative name: resolved in the node's namespace, remappable like any topic.
            self._publishers_by_topic[name] = self.create_publisher(msg_class, name.lstrip("/"), qos)
        if not self._publishers_by_topic:
            raise PlayerConfigError(f"bag {bag_path} has no topic this ROS installation can publish")
        self._tf_poses: BagTFPoses | None = None
        self._pose_messages: PoseMessages | None = None
        self._pose_publisher: Publisher | None = None
        self._pose_topic = ""
        self.pose_misses: Counter[str] = Counter()
        self._warned: set[str] = set()
        if pose_input is not None:
            self._setup_tf_poses(bag, pose_input, qos)
        self._clock_publisher: Publisher | None = None
        if publish_clock:
            from rosgraph_msgs.msg import Clock as ClockMsg

            self._clock_msg = ClockMsg
            self._clock_publisher = self.create_publisher(ClockMsg, topics.CLOCK, QoSProfile(depth=1))

        self.finished: Future = Future()
        self.counts: dict[str, int] = dict.fromkeys(self._publishers_by_topic, 0)
        if self._pose_publisher is not None:
            self.counts[self._pose_topic] = 0
        self._iterator: Iterator[RawMessage] | None = None
        self._pending: RawMessage | None = None
        self._wall_start_ns = 0
        self._bag_start_ns = 0
        self._first_publish_ns: int | None = None
        self._last_publish_ns = 0
        self._loops = 0
        self._pass_instants = 0
        self._last_stamp_ns = 0
        self._last_wait_log = time.monotonic()
        # Steady time: playback follows wall time even when the node itself uses sim time.
        self._timer = self.create_timer(_WAIT_POLL_S, self._on_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._playing = False
        self.get_logger().info(
            f"playing {bag_path}: {bag.message_count} messages on {len(self._publishers_by_topic)} topics over "
            f"{bag.duration_ns / _NS_PER_S:.3f} s at rate {self._rate:g}"
            + (f", waiting for {self._wait_for} subscriptions" if self._wait_for else "")
        )

    def _declare_parameters(self) -> None:
        self.declare_parameter("bag", "", _descriptor("bag folder or .mcap file to play (required)"))
        self.declare_parameter(
            "rate",
            1.0,
            _descriptor(
                "playback speed factor (2.0 plays twice as fast)",
                floating_point_range=[FloatingPointRange(from_value=0.001, to_value=1000.0, step=0.0)],
            ),
        )
        self.declare_parameter("loop", False, _descriptor("start over after the last message"))
        self.declare_parameter(
            "start_offset",
            0.0,
            _descriptor(
                "seconds of the bag to skip at the start",
                floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0e9, step=0.0)],
            ),
        )
        self.declare_parameter("publish_clock", False, _descriptor("publish /clock with the bag time"))
        self.declare_parameter(
            "wait_for_subscribers",
            0,
            _descriptor(
                "play once the bag's topics together have this many matched subscriptions (0: at once)",
                integer_range=[IntegerRange(from_value=0, to_value=10000, step=1)],
            ),
        )
        self.declare_parameter(
            "qos_reliability",
            "reliable",
            _descriptor("publisher reliability", additional_constraints="reliable or best_effort"),
        )
        self.declare_parameter(
            "qos_depth",
            10,
            _descriptor("publisher history depth", integer_range=[IntegerRange(from_value=1, to_value=1000, step=1)]),
        )
        self.declare_parameter(
            "pose_source",
            "none",
            _descriptor(
                "none: publish the bag as recorded; tf: also publish the left camera's PoseStamped composed from "
                "the bag's /tf and /tf_static at each left image stamp",
                additional_constraints="none or tf",
            ),
        )
        self.declare_parameter("world_frame", "", _descriptor("pose_source tf: the fixed frame, e.g. odom or map"))
        self.declare_parameter(
            "camera_frame", "", _descriptor("pose_source tf: the left camera's frame; empty: the left camera_info's")
        )
        self.declare_parameter(
            "stereo_namespace",
            "",
            _descriptor("pose_source tf: namespace of the bag's stereo topics; empty: found from the left image"),
        )
        self.declare_parameter(
            "remaps",
            Parameter.Type.STRING_ARRAY,
            _descriptor("pose_source tf: FROM:=TO rules naming the bag's topics, as selfcontra label --remap"),
        )
        self.declare_parameter(
            "image_transport",
            "raw",
            _descriptor(
                "pose_source tf: the bag's images are raw or compressed", additional_constraints="raw or compressed"
            ),
        )
        self.declare_parameter(
            "rectify", False, _descriptor("pose_source tf: the bag has image_raw; the pose is the rectified view's")
        )

    def _pose_input(self) -> StereoInput | None:
        """The stereo input of ``pose_source: tf`` (None for ``none``).

        Raises:
            PlayerConfigError: an invalid pose_source, image_transport, remap rule or missing world_frame.
        """
        p = self.get_parameter
        source = str(p("pose_source").value)
        if source not in PLAYER_POSE_SOURCES:
            raise PlayerConfigError(
                f"parameter 'pose_source' is {source!r}; expected one of {', '.join(PLAYER_POSE_SOURCES)}"
            )
        transport = str(p("image_transport").value)
        if transport not in IMAGE_TRANSPORTS:
            raise PlayerConfigError(
                f"parameter 'image_transport' is {transport!r}; expected one of {', '.join(IMAGE_TRANSPORTS)}"
            )
        try:
            remaps = tuple(str(rule) for rule in p("remaps").value)
        except ParameterUninitializedException:
            remaps = ()
        if source == "none":
            return None
        camera_frame = str(p("camera_frame").value)
        try:
            return StereoInput(
                image_transport=transport,
                rectify=bool(p("rectify").value),
                remaps=remaps,
                pose_source="tf",
                world_frame=str(p("world_frame").value),
                camera_frame=camera_frame or None,
            )
        except SelfContraError as exc:
            raise PlayerConfigError(f"pose_source tf: {exc} (parameters world_frame, remaps, ...)") from exc

    def _setup_tf_poses(self, bag: Bag, stereo_input: StereoInput, qos: QoSProfile) -> None:
        """Find the bag's left image, left camera_info and TF topics; create the pose publisher.

        Raises:
            PlayerConfigError: the bag lacks them (or the stereo namespace cannot be found), or already
                has the pose topic.
        """
        from geometry_msgs.msg import PoseStamped

        namespace = str(self.get_parameter("stereo_namespace").value)
        try:
            ns = stereo_input.namespace(list(bag.topics), namespace or None)
        except BagError as exc:  # worded for the command line: name the player's parameters too
            raise PlayerConfigError(
                f"pose_source tf: {exc} (the player's parameters: remaps, stereo_namespace)"
            ) from exc
        topic_map = stereo_input.topics(ns)
        tf_poses = BagTFPoses(stereo_input, topic_map)
        missing = [t for t in (tf_poses.left_image, tf_poses.left_info) if t not in bag.topics]
        if missing:
            raise PlayerConfigError(
                f"pose_source tf: the bag has no {' and no '.join(missing)} (topics: {', '.join(bag.topics)}); "
                "set stereo_namespace, remaps, image_transport and rectify as for 'selfcontra label BAG' "
                "('selfcontra inspect BAG' suggests them)"
            )
        if tf_poses.tf_topic not in bag.topics and tf_poses.tf_static_topic not in bag.topics:
            raise PlayerConfigError(
                f"pose_source tf: the bag has neither {tf_poses.tf_topic} nor {tf_poses.tf_static_topic}"
            )
        self._pose_topic = topic_map[topics.POSE]
        if self._pose_topic in bag.topics:
            raise PlayerConfigError(
                f"pose_source tf: the bag has its own pose topic {self._pose_topic}; play it as recorded "
                "(pose_source none) or move the TF pose elsewhere (remaps pose:=...)"
            )
        self._tf_poses = tf_poses
        self._pose_messages = PoseMessages()
        self._pose_publisher = self.create_publisher(PoseStamped, self._pose_topic.lstrip("/"), qos)
        self.get_logger().info(
            f"TF to pose: {stereo_input.camera_frame or 'the left camera_info frame'} in {stereo_input.world_frame} "
            f"at each {tf_poses.left_image} stamp, published on {self._pose_publisher.topic_name}"
        )

    # ------------------------------------------------------------------ playback

    def _subscription_count(self) -> int:
        publishers = [*self._publishers_by_topic.values(), *([self._pose_publisher] if self._pose_publisher else [])]
        return sum(p.get_subscription_count() for p in publishers)

    def _on_timer(self) -> None:
        if not self._playing:
            if not self._ready_to_play():
                return
            self._playing = True
            self._restart()
        self._publish_due()

    def _ready_to_play(self) -> bool:
        if self._wait_for <= 0:
            return True
        have = self._subscription_count()
        if have >= self._wait_for:
            return True
        now = time.monotonic()
        if now - self._last_wait_log >= _WAIT_LOG_S:
            self._last_wait_log = now
            self.get_logger().info(f"waiting for subscribers: {have} of {self._wait_for} matched")
        return False

    def _restart(self, delay_ns: int = 0) -> None:
        """Start (or, looping, restart) reading the bag; its first message is due ``delay_ns`` from now."""
        assert self._bag is not None
        self._iterator = self._bag.raw_messages(start_ns=self._start_ns)
        self._pending = next(self._iterator, None)
        self._wall_start_ns = time.monotonic_ns() + delay_ns
        self._bag_start_ns = self._pending.stamp_ns if self._pending is not None else 0
        self._pass_instants = 0  # distinct stamps published in this pass
        if self._tf_poses is not None:
            self._tf_poses.reset()
            static = self._tf_poses.tf_static_topic
            if self._start_ns is not None and static in self._bag.topics:
                # Static transforms are latched: those recorded before start_offset still hold.
                for raw in self._bag.raw_messages([static], stop_ns=self._start_ns):
                    self._tf_message(raw)

    def _loop_gap_ns(self) -> int:
        """Wall time between the last message of a pass and the first of the next: one mean stamp period."""
        span = self._last_stamp_ns - self._bag_start_ns
        period = span // (self._pass_instants - 1) if self._pass_instants > 1 else _DEFAULT_PERIOD_NS
        return round(period / self._rate)

    def _due_ns(self, message: RawMessage) -> int:
        """Monotonic time (ns) at which ``message`` is to be published."""
        return self._wall_start_ns + round((message.stamp_ns - self._bag_start_ns) / self._rate)

    def _publish_due(self) -> None:
        """Publish every message whose time has come, then arm the timer for the next one."""
        assert self._iterator is not None
        while self._pending is not None:
            now = time.monotonic_ns()
            due = self._due_ns(self._pending)
            if due > now:
                self._timer.timer_period_ns = max(due - now, _MIN_PERIOD_NS)
                self._timer.reset()
                return
            if self._pass_instants == 0 or self._pending.stamp_ns != self._last_stamp_ns:
                self._pass_instants += 1
            self._last_stamp_ns = self._pending.stamp_ns
            self._publish(self._pending)
            self._pending = next(self._iterator, None)
            if self._pending is None and self._tf_poses is not None:
                self._publish_poses(self._tf_poses.finish())
            if self._pending is None and self._loop:
                self._loops += 1
                self.get_logger().debug(f"loop: starting pass {self._loops + 1}")
                # The next pass continues at the bag's own pace, so a bag of one instant cannot spin in a busy loop.
                self._restart(self._loop_gap_ns())
        self._timer.cancel()
        self._log_summary()
        self.finished.set_result(True)

    def _publish(self, message: RawMessage) -> None:
        publisher = self._publishers_by_topic.get(message.topic)
        if publisher is not None:
            if self._clock_publisher is not None:
                clock = self._clock_msg()
                clock.clock.sec, clock.clock.nanosec = divmod(message.stamp_ns, _NS_PER_S)
                self._clock_publisher.publish(clock)
            publisher.publish(message.data)  # raw CDR as stored: bit-exact, no deserialisation
            now = time.monotonic_ns()
            if self._first_publish_ns is None:
                self._first_publish_ns = now
            self._last_publish_ns = now
            self.counts[message.topic] += 1
        if self._tf_poses is not None and message.topic in self._tf_poses.topics:
            self._tf_message(message)

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def _tf_message(self, message: RawMessage) -> None:
        """Feed a TF, left image or left camera_info message to the TF conversion; publish the poses it decides."""
        assert self._tf_poses is not None and self._bag is not None
        try:
            msg = self._bag.deserialize(message.data, message.msgtype, topic=message.topic)
            decided = self._tf_poses.add(message.topic, message.stamp_ns, msg)
        except SelfContraError as exc:  # a bad message costs its pose(s), never the playback
            self.pose_misses["bad_message"] += 1
            self._warn_once("bad_message", f"TF to pose: {exc} (further bad messages are only counted)")
            return
        self._publish_poses(decided)

    def _publish_poses(self, decided: list[tuple[int, PoseAt]]) -> None:
        assert self._tf_poses is not None and self._pose_publisher is not None and self._pose_messages is not None
        world = self._tf_poses.poses.world_frame
        for stamp_ns, found in decided:
            if found.pose is None:
                reason = found.reason or "tf_lookup_failed"
                self.pose_misses[reason] += 1
                self._warn_once(
                    reason, f"no pose for the left image at {stamp_ns} ns ({reason}): {found.detail} (further: counted)"
                )
                continue
            self._pose_publisher.publish(self._pose_messages.pose_stamped(found.pose, stamp_ns, world))
            self.counts[self._pose_topic] += 1

    def _log_summary(self) -> None:
        total = sum(self.counts.values())
        span = (self._last_publish_ns - (self._first_publish_ns or self._last_publish_ns)) / _NS_PER_S
        per_topic = ", ".join(f"{name} {count}" for name, count in self.counts.items())
        misses = f"; left images without a TF pose: {dict(self.pose_misses)}" if self.pose_misses else ""
        self.get_logger().info(f"done: published {total} messages in {span:.3f} s ({per_topic}){misses}")

    def wait_for_acknowledgements(self, timeout_s: float = _ACK_TIMEOUT_S) -> bool:
        """Wait until reliable subscribers acknowledged every published message, at most ``timeout_s`` in all.

        Returns:
            True when everything was acknowledged in time (always, for best-effort publishers).
        """
        deadline = time.monotonic() + timeout_s
        acked = True
        for publisher in self._publishers_by_topic.values():
            remaining = max(deadline - time.monotonic(), 0.0)
            acked = publisher.wait_for_all_acked(Duration(nanoseconds=round(remaining * _NS_PER_S))) and acked
        return acked

    def destroy_node(self) -> None:
        """Close the bag and destroy the node."""
        bag, self._bag = self._bag, None
        if bag is not None:
            bag.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Run the player until the bag is played (or forever with ``loop``); return the process exit code."""
    prepare_ros_environment()
    # Own signal handling (ros/spinning.py): with rclpy's, a Ctrl-C landing in a __del__ left the executor
    # on a shut-down context and the player exited with an RCLError.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    logger = get_logger(NODE_NAME)
    node: PlayerNode | None = None
    code = 0
    executor = SingleThreadedExecutor()
    with stop_on_signals() as stop:
        try:
            node = PlayerNode()
            executor.add_node(node)
            if spin_until_stopped(executor, stop, node.finished.done) and not node.wait_for_acknowledgements():
                # Usual with Fast DDS (acknowledgements follow its 3 s heartbeat): the wait was a short linger.
                logger.debug("not every message was acknowledged by reliable subscribers before exiting")
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except (PlayerConfigError, ParameterException) as exc:
            logger.error(f"invalid parameters: {exc}")
            code = 2
        except SelfContraError as exc:
            logger.error(str(exc))
            code = 1
        finally:
            if node is not None:
                executor.remove_node(node)
                node.destroy_node()
            executor.shutdown()
            rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
