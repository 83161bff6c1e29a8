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

Without ``loop`` the node logs a summary after the last message, waits (at
most 1 s) until reliable subscribers acknowledged everything, and the process
exits with code 0. Exit codes: 0 done or stopped by SIGINT/SIGTERM,
1 the bag cannot be read, 2 invalid parameters.
"""

from __future__ import annotations

import importlib
import sys
import time
from collections.abc import Iterator
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.publisher import Publisher  # unparameterised: generic (Publisher[MsgT]) in Kilted, not in Jazzy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.reader import Bag, RawMessage, open_bag
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.ros.environment import prepare_ros_environment

__all__ = ["PlayerConfigError", "PlayerNode", "main"]

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


class PlayerNode(Node):
    """Publishes the messages of a bag with their recorded timing scaled by ``rate`` (see the module docstring).

    Attributes:
        finished: a future that completes when playback ended (never with ``loop``).
        counts: messages published so far, per bag topic.
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
        self._clock_publisher: Publisher | None = None
        if publish_clock:
            from rosgraph_msgs.msg import Clock as ClockMsg

            self._clock_msg = ClockMsg
            self._clock_publisher = self.create_publisher(ClockMsg, topics.CLOCK, QoSProfile(depth=1))

        self.finished: Future = Future()
        self.counts: dict[str, int] = dict.fromkeys(self._publishers_by_topic, 0)
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

    # ------------------------------------------------------------------ playback

    def _subscription_count(self) -> int:
        return sum(p.get_subscription_count() for p in self._publishers_by_topic.values())

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
        if publisher is None:
            return
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

    def _log_summary(self) -> None:
        total = sum(self.counts.values())
        span = (self._last_publish_ns - (self._first_publish_ns or self._last_publish_ns)) / _NS_PER_S
        per_topic = ", ".join(f"{name} {count}" for name, count in self.counts.items())
        self.get_logger().info(f"done: published {total} messages in {span:.3f} s ({per_topic})")

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
    rclpy.init(args=args)
    logger = get_logger(NODE_NAME)
    node: PlayerNode | None = None
    code = 0
    try:
        node = PlayerNode()
        rclpy.spin_until_future_complete(node, node.finished)
        if node.finished.done() and not node.wait_for_acknowledgements():
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
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
