"""Labeler node: self-contradiction labels (and the query algorithm's depth) of a live stereo stream.

Run::

    ros2 run selfcontra_ros labeler --ros-args --params-file config/labeler.yaml -r __ns:=/stereo
    python -m selfcontra_ros.ros.labeler_node --ros-args --params-file config/labeler.yaml -r __ns:=/stereo

The node drives one :class:`~selfcontra_ros.session.LabelingSession`, the
object the offline bag and sequence labelers use too, so the same frames give
the same labels whichever way they arrive.

**Inputs** (relative names, :mod:`selfcontra_ros.bags.topics`): ``left/image_rect``
and ``right/image_rect`` (``mono8``, ``rgb8`` or ``bgr8``), ``left/camera_info``
and ``right/camera_info``, and the pose ``T_world_left``: ``pose``
(geometry_msgs/PoseStamped) or ``odom`` (nav_msgs/Odometry, its child frame
must be the left optical frame), chosen by ``pose_source``. With
``matcher.algorithm: external`` the images are not subscribed: each
``disparity`` (stereo_msgs/DisparityImage) message of an external stereo
algorithm is one view.

**A robot's own topics** (the same choices as the offline commands,
:class:`~selfcontra_ros.bags.stereo_input.StereoInput`):

* ``image_transport: compressed`` subscribes to ``<image topic>/compressed``
  (sensor_msgs/CompressedImage, JPEG or PNG, ``format`` as image_transport
  writes it), decoded by :mod:`selfcontra_ros.bags.compressed`. A remap of
  the base name (``-r left/image_raw:=cam_left/image_raw``) moves the
  ``/compressed`` topic with it, as image_transport's subscribers do.
* ``rectify: true`` subscribes to ``left/image_raw`` and ``right/image_raw``
  and rectifies them with their (distorted) camera infos
  (:class:`~selfcontra_ros.rectification.Rectifier`: ``plumb_bob`` or
  ``rational_polynomial`` D, K, R, P; the OpenCV maps are built once per
  calibration and rebuilt when it changes); the rectified camera (from the
  two P) is the one labelled, and the outputs keep the left image's frame id.
* ``pose_source: tf`` takes the pose of ``camera_frame`` (default: the left
  camera_info's ``header.frame_id``) in ``world_frame`` from TF at the left
  image's stamp, times the rectification rotation ``R_left^T`` with
  ``rectify`` (the pose of the rectified view). It needs ``tf2_ros`` (a
  ``Buffer`` with a ``TransformListener`` on ``/tf`` and ``/tf_static``,
  adapted by :class:`Tf2Transforms`); where it is missing, as in the PyPI
  wheels, the node stops at start with a message naming the alternatives:
  ``pose_source: pose`` fed by the player's TF conversion (``player -p
  pose_source:=tf``, which composes a bag's TF itself), ``pose``/``odom``
  from the robot's own pose topic, or ``odometry``. The decision when a frame
  has its pose is :func:`tf_pose_decision`; a frame waits while TF may still
  reach its stamp, like a frame waiting for a pose topic.
* ``pose_source: odometry`` estimates the poses with the package's stereo
  odometry (:class:`~selfcontra_ros.odometry.run.OnlineOdometry`, on the
  subscription thread): a frame has its pose once
  ``VOParams.smoothing_lag_frames`` (5) more frames have arrived, its step
  length smoothed with them, a reliable frame alone among unreliable
  ones is reported ``isolated`` and one whose smoothed step length the
  frames around it pin down too loosely ``uncertain``, as the offline
  ``estimate_poses`` does. A
  frame without a reliable pose keeps its depth, disparity and confidence
  and is not labelled (``odometry_unreliable``). Should the odometry raise,
  the frame is published unlabelled (``odometry_error``) and the node starts
  over with a new odometry and labeling session, as after a time jump.

**Synchronisation.** Images and camera infos are grouped by header stamp
(left image first; ``sync: exact`` needs equal stamps, ``approximate`` accepts
``slop`` seconds) by :class:`~selfcontra_ros.bags.sync.StampSynchronizer`, as
stereo_image_proc does, so a frame is processed whatever order its four
messages arrive in. The pose at the left image's stamp comes from
:class:`~selfcontra_ros.bags.sync.PoseBuffer` (linear translation, slerp
rotation between the bracketing poses, at most ``max_pose_gap`` s apart). A
frame newer than the newest pose waits for it; it is given up (and counted)
once a frame more than ``max_pose_gap`` s newer has arrived without the pose
stream reaching it (the stream stopped).

**Outputs** (the left image's frame id on all of them):

* ``depth`` (32FC1 metres, NaN invalid, REP 118) and ``disparity``
  (stereo_msgs/DisparityImage; not in external mode, where it is the input), published from the subscription callback as
  soon as a frame is matched, with the frame's stamp;
* ``confidence`` (32FC1 in [0, 1], 0 where the disparity is invalid) and
  ``depth/filtered`` (32FC1 metres, NaN where the confidence is below
  ``confidence.confidence_threshold``), for every frame with the frame's stamp
  (not in external mode, which has no images): the LRD baseline
  ``exp(-|d_L - d_R| / confidence.lrd_scale)``, published from the
  subscription callback, until a forest exists; then the forest's
  probability, computed by the confidence worker (see below);
* ``labels`` (mono8: 0 unknown, 1 positive, 2 negative) and ``labels/color``
  (rgb8), published by the labeling worker ``label_delay`` views later, with
  the *labelled view's* stamp;
* with ``publish_debug``: ``debug/support`` (mono8, distinct angle bins of
  Stage 1), ``debug/vote_sum`` (32FC1, Stage-2 vote sum, 0 where no vote) and
  ``debug/uncertainty`` (32FC1, largest covariance eigenvalue, m^2, NaN invalid);
* ``~/stats`` (std_msgs/String, JSON, transient-local): drop counters per
  reason and progress counters, every ``stats_period`` s and at shutdown.

**Threads and queues.** The executor thread runs the subscriptions: it
synchronises, converts, runs :meth:`LabelingSession.match` (milliseconds at
VGA size) and publishes the depth at once; it never waits for labeling. A
view with its pose goes to a labeling worker thread through a bounded queue
of ``label_queue_size`` views. **Policy when labeling falls behind:** a view
that finds the queue full is skipped (never labelled, its depth was already
published) and counted as ``label_queue_full``; the views already queued are
kept, so the labeler's window sees the stream thinned, not reordered. Memory
is bounded in the node: ``queue_size`` messages per synchronised topic, as many
frames waiting for their pose, 1000 poses, ``label_queue_size`` views, and the
labeler's own window. **When the executor falls behind** (matching, and the
odometry with ``pose_source: odometry``, take longer than the camera's period
on a busy computer), ``input_qos`` decides: ``sensor_data`` keeps the newest
``max(queue_size, 5)`` messages per topic in the middleware and overwrites
older unread ones, which DDS does not report, so they appear in no counter;
``reliable`` keeps every message until the node takes it (keep-all history):
nothing is lost, and the unread messages' memory grows while the node is
behind.

**Online confidence** (:class:`~selfcontra_ros.confidence.online.OnlineConfidence`,
DESIGN section 4). The labelled views (frame and labels) go from the labeling
worker to the confidence's trainer thread (at most 2 waiting; more are counted
in ``~/stats`` ``confidence.views_dropped``), which adds balanced samples to
the reservoir and retrains the forest every ``confidence.retrain_every``
views, swapping it in atomically; the first swap logs "confidence: switched
from LRD to the trained <set> forest (N samples)". Forest confidences need
the census cost volume and the feature set (about 2.8 s a frame at KITTI size
for ``gcp``, 30 ms at 320x96), so they are computed by a confidence worker
thread fed through a queue of ``confidence_queue_size`` frames; a frame that
finds it full gets the LRD confidence from the callback at once (counted as
``confidence_lrd_fallback``), so every frame still gets its confidence.
Forest confidences may therefore arrive after later frames' messages.

**Robustness.** A message that cannot be used is dropped, counted under a
reason in ``~/stats`` (``drops``) and logged at most every 5 s per reason:
``bad_image`` (unsupported encoding or malformed data), ``bad_camera_info``
(a camera info pair that does not describe one rectified camera),
``size_mismatch`` (image and camera info sizes differ), ``bad_pose`` (NaN or
non-rigid pose), ``pose_backwards`` / ``stamp_backwards`` (stamps not
increasing), ``unsynced`` (no partner within the slop, or a queue overflow,
e.g. a topic that stopped), ``pose_none_yet`` / ``pose_before_buffer`` /
``pose_after_buffer`` / ``pose_gap`` (no pose within ``max_pose_gap`` of the
image stamp), ``bad_compressed_image`` (a CompressedImage that does not
decode or has an unsupported ``format``), the TF reasons of
:class:`~selfcontra_ros.errors.TransformError` with ``pose_source: tf``
(``tf_unknown_frame``, ``tf_not_connected``, ``tf_none_yet``,
``tf_before_buffer``, ``tf_after_buffer``, ``tf_gap``, ``tf_lookup_failed``,
``no_camera_frame``; the warning names the missing link),
``pose_wait_overflow``, ``label_queue_full``, ``session_reset``
(views of the old session dropped at a camera change or a time jump),
``bad_disparity`` and
``error`` (anything unexpected, logged with the reason; the node carries on).
A camera change (camera infos describing another calibration) starts a new
session (logged, counted in ``camera_resets``): views of the old session still
waiting for their pose or in the label queue are dropped (``session_reset``),
and the old window goes with its session, so its last ``label_delay`` views
are never labelled. Image stamps jumping back by more than ``time_jump_reset``
s (a bag played in a loop, a restarted driver) reset the synchroniser, the
poses and the session the same way (counted in ``time_jumps``).

**Parameters** (read once at start; invalid values stop the node with exit code 2):

``matcher.*``, ``labeler.*``
    the core's parameters (:class:`~selfcontra_ros.matching.base.MatcherParams`,
    :class:`~selfcontra_ros.labeler.LabelerParams`), defaults and meaning as in
    ``config/labeler.yaml``; ``--params-file`` sets them.
``pose_source`` (``pose``: ``pose``, ``odom``, ``odometry`` or ``tf``), ``sync`` (``exact``), ``slop`` (0.0 s, 0..1)
    see above; ``slop`` needs ``sync: approximate``.
``world_frame`` (``""``), ``camera_frame`` (``""``: the left camera_info's frame id)
    the TF frames of ``pose_source: tf`` (``world_frame`` is required there, e.g. ``odom`` or ``map``).
``image_transport`` (``raw``: sensor_msgs/Image, or ``compressed``), ``rectify`` (false)
    see "A robot's own topics" above.
``queue_size`` (10, 1..1000)
    messages per synchronised topic, frames waiting for their pose, and the
    subscriptions' history depth.
``label_queue_size`` (4, 1..1000)
    views waiting for the labeling worker.
``max_pose_gap`` (0.5 s), ``max_pose_extrapolation`` (0.05 s)
    pose interpolation limits (see above).
``time_jump_reset`` (1.0 s, 0 = never)
    image stamps jumping back by more than this reset the node's state.
``input_qos`` (``sensor_data``)
    ``sensor_data`` (best effort, the newest ``max(queue_size, 5)`` messages
    per topic: serves best-effort and reliable publishers) or ``reliable``
    (reliable, keep-all: nothing lost between reliable nodes, e.g. the player
    replaying a bag faster than the node labels it; see above).
``confidence.*``
    :class:`~selfcontra_ros.confidence.online.ConfidenceParams`: feature set,
    threshold, LRD scale, ``retrain_every``, reservoir and forest sizes,
    ``model_in`` (a model file to start from) and ``model_out`` (written after
    every retraining), as in ``config/labeler.yaml``.
``confidence_queue_size`` (2, 1..100)
    frames waiting for a forest confidence.
``publish_debug`` (false), ``stats_period`` (1.0 s), ``flush_on_shutdown`` (false).
``threads`` (0 = every core the process may run on)
    cap on every thread pool (numba kernels, OpenCV's StereoSGBM, BLAS/OpenMP,
    scikit-learn), applied at start by :func:`selfcontra_ros.threads.limit_threads`
    and by each worker thread for its own numba/OpenMP count; a value above
    the cores available is lowered to them. The cap applied is logged at
    start and reported as ``threads`` in ``~/stats``.

**Shutdown.** SIGINT and SIGTERM stop the node cleanly (exit code 0). By
default the views still queued or waiting in the window are *not* labelled
(shutdown stays fast; they are counted as ``shutdown_discarded``); with
``flush_on_shutdown`` the worker labels the queued views and then flushes the
session's window (:meth:`LabelingSession.flush`) before the node exits, which
takes one labeling per waiting view; the node waits for that however long it
takes (logging what is left every 10 s; a second Ctrl-C cuts it short). The
confidence threads stop first either way: frames waiting for a forest
confidence and views waiting for the trainer are dropped (``~/stats``
``confidence.views_dropped``), and the views labelled while stopping do not
train the forest. Exit codes: 0 stopped, 2 invalid parameters.
"""

from __future__ import annotations

import json
import math
import queue
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from numpy.typing import NDArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.publisher import Publisher  # unparameterised: generic (Publisher[MsgT]) in Kilted, not in Jazzy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.stereo_input import IMAGE_TRANSPORTS, ImageError, PoseAt, StereoImages, StereoInput, TFPoses
from selfcontra_ros.bags.sync import SYNC_MODES, Match, PoseBuffer, StampSynchronizer
from selfcontra_ros.bags.tf import TransformSource, matrix_from_transform, normalize_frame
from selfcontra_ros.confidence.forest import ForestModel
from selfcontra_ros.confidence.online import ConfidenceFrame, ConfidenceParams, OnlineConfidence, filter_depth
from selfcontra_ros.config import (
    NODE_PARAMETERS,
    confidence_from_ros_parameters,
    from_ros_parameters,
    params_to_dict,
    to_ros_parameters,
)
from selfcontra_ros.errors import CalibrationError, ConversionError, PoseError, SelfContraError, TransformError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import LabelerParams, LabelResult
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.odometry.run import OnlineDecision, OnlineOdometry
from selfcontra_ros.odometry.stereo_vo import OdometryError, VOParams
from selfcontra_ros.rectification import calibration_key
from selfcontra_ros.ros.conversions import (
    disparity_from_message,
    disparity_image,
    nanoseconds_to_stamp,
    numpy_to_image,
    stamp_to_nanoseconds,
)
from selfcontra_ros.ros.environment import prepare_ros_environment
from selfcontra_ros.ros.spinning import spin_until_stopped, stop_on_signals
from selfcontra_ros.session import LabelingSession
from selfcontra_ros.threads import apply_thread_limit, available_cores, limit_threads

__all__ = [
    "DROP_REASONS",
    "TF_WAIT_REASONS",
    "LabelerConfigError",
    "LabelerNode",
    "Tf2Transforms",
    "ViewKey",
    "main",
    "tf_pose_decision",
]

NODE_NAME = "labeler"
#: Relative topic of the odometry pose source.
ODOM = "odom"
#: Relative topic of the node's statistics (JSON), in the node's private namespace.
STATS = "~/stats"
DEBUG_SUPPORT = "debug/support"
DEBUG_VOTE_SUM = "debug/vote_sum"
DEBUG_UNCERTAINTY = "debug/uncertainty"

POSE_SOURCES = ("pose", "odom", "odometry", "tf")
INPUT_QOS = ("sensor_data", "reliable")

#: Every reason a message or view can be dropped for (keys of the ``drops`` counters in ``~/stats``).
DROP_REASONS = (
    "bad_image",
    "odometry_unreliable",
    "odometry_error",
    "bad_camera_info",
    "size_mismatch",
    "bad_disparity",
    "bad_pose",
    "pose_backwards",
    "stamp_backwards",
    "unsynced",
    "pose_none_yet",
    "pose_before_buffer",
    "pose_after_buffer",
    "pose_gap",
    "bad_compressed_image",
    "tf_unknown_frame",
    "tf_not_connected",
    "tf_none_yet",
    "tf_before_buffer",
    "tf_after_buffer",
    "tf_gap",
    "tf_lookup_failed",
    "no_camera_frame",
    "pose_wait_overflow",
    "label_queue_full",
    "confidence_lrd_fallback",
    "session_reset",
    "shutdown_discarded",
    "error",
)

#: TF failures that more transforms may still cure (the frame waits for them): no data up to the stamp yet,
#: or frames / links not heard of yet (a static transform published late). Others drop the frame at once.
TF_WAIT_REASONS = frozenset(
    {"tf_none_yet", "tf_after_buffer", "tf_unknown_frame", "tf_not_connected", "no_camera_frame"}
)
#: Image-decoding reasons of :class:`~selfcontra_ros.bags.stereo_input.ImageError` -> the node's drop reason.
_IMAGE_REASONS = {"bad_encoding": "bad_image", "no_camera_info": "bad_camera_info"}
# How often frames waiting for TF are retried (tf2_ros fills its buffer without telling the node), seconds.
_TF_RETRY_PERIOD_S = 0.05
# At most one warning per drop reason in this many seconds.
_WARN_PERIOD_S = 5.0
# Poses kept: 10 s of a 100 Hz odometry.
_POSE_CAPACITY = 1000
# How long shutdown waits for a labeling in progress (one labeling at KITTI size takes ~1 s) or a confidence
# thread; with flush_on_shutdown, how often it logs while it waits for the labeling worker.
_JOIN_TIMEOUT_S = 10.0
_STATS_LOG_PERIOD_S = 30.0
# Upper bound of the wait for reliable subscribers' acknowledgements of the flushed labels at shutdown.
_ACK_TIMEOUT_S = 2.0


class LabelerConfigError(SelfContraError):
    """A parameter of the labeler node is invalid."""


@dataclass(frozen=True)
class ViewKey:
    """Identity of one view, kept with it through the labeler: the header of its left image.

    Attributes:
        stamp_ns: header stamp, integer nanoseconds.
        frame_id: header frame id (the left optical frame).
    """

    stamp_ns: int
    frame_id: str


@dataclass
class _View:
    """A matched frame on its way to the labeler (waiting for its pose, then in the label queue)."""

    session: LabelingSession
    key: ViewKey
    disparity: NDArray[np.float32]
    pose: NDArray[np.float64] | None = None
    frame: ConfidenceFrame | None = None


@dataclass
class _ConfidenceJob:
    """A matched frame waiting for its forest confidence."""

    session: LabelingSession
    frame: ConfidenceFrame
    depth: NDArray[np.float32]
    model: ForestModel
    stamp_ns: int
    frame_id: str


def _descriptor(description: str, **kwargs: Any) -> ParameterDescriptor:
    # Read once at start: read-only, so that a runtime change is refused rather than silently ignored.
    return ParameterDescriptor(description=description, read_only=True, **kwargs)


def _float_range(low: float, high: float) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=low, to_value=high, step=0.0)]


def _int_range(low: int, high: int, step: int = 1) -> list[IntegerRange]:
    return [IntegerRange(from_value=low, to_value=high, step=step)]


# Ranges of the core parameters the descriptors can express; the dataclasses check everything else.
_CORE_INT_RANGES: dict[str, list[IntegerRange]] = {
    "matcher.num_disparities": _int_range(16, 1024, 16),
    "matcher.block_size": _int_range(1, 255),
    "labeler.window_size": _int_range(2, 1000),
    "labeler.label_delay": _int_range(0, 999),
    "labeler.min_positive_votes": _int_range(1, 1000),
    "labeler.stage3_min_free_space_views": _int_range(0, 1000),
    "confidence.retrain_every": _int_range(1, 1_000_000),
    "confidence.reservoir_per_class": _int_range(1, 10_000_000),
    "confidence.samples_per_view": _int_range(1, 10_000_000),
    "confidence.n_estimators": _int_range(1, 1000),
    "confidence.max_depth": _int_range(1, 100),
    "confidence.min_samples_leaf": _int_range(1, 1_000_000),
}
_CORE_FLOAT_RANGES: dict[str, list[FloatingPointRange]] = {
    "confidence.confidence_threshold": _float_range(0.0, 1.0),
}
_SECTION_CLASSES = {"matcher": "MatcherParams", "labeler": "LabelerParams", "confidence": "ConfidenceParams"}


def input_qos_profile(input_qos: str, queue_size: int) -> QoSProfile:
    """The subscriptions' QoS of ``input_qos``.

    ``sensor_data``: best effort, keep-last ``max(queue_size, 5)``: a node that
    falls behind a camera gets the newest frames; the ones it never took are
    overwritten in the reader's history, which DDS does not report (no
    ``message_lost`` event), so no drop counter can see them. ``reliable``:
    keep-all, so that nothing a reliable publisher sends is lost however far
    the node falls behind (a reliable *keep-last* reader drops unread samples
    just as silently: replaying 24 frames with three busy processes beside
    the node, it labelled 21-23 of them in 4 of 5 runs, and a lost pose made a
    frame's pose an interpolation of its neighbours'); the unread messages wait in
    the middleware, so memory grows while the node is behind (the player's
    ``rate`` paces a replay).
    """
    if input_qos == "sensor_data":
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=max(queue_size, 5),
            reliability=ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.VOLATILE,
        )
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE
    )


def _info_key(msg: Any) -> tuple[Any, ...]:
    """What identifies a rectified camera info's calibration (a change of it means another camera)."""
    return (int(msg.width), int(msg.height), tuple(float(v) for v in msg.p))


def tf_pose_decision(poses: TFPoses, stamp_ns: int, *, waited_ns: int, max_wait_ns: int) -> PoseAt | None:
    """The TF pose of a frame waiting for it: the pose, the reason it has none, or None while it should wait.

    The frame waits while it is *patient* (at most ``max_wait_ns`` of newer
    image time arrived since it, ``waited_ns``) and TF has not reached its
    stamp: the source's newest common stamp is older (a
    :class:`~selfcontra_ros.bags.tf.TFBuffer` tells it), or the lookup fails
    for a reason of :data:`TF_WAIT_REASONS`. Once impatient, the lookup's
    answer is final (the source may extrapolate a little, as it allows).

    Args:
        poses: the TF pose source (world frame, camera frame, rectification rotation).
        stamp_ns: the frame's stamp, nanoseconds.
        waited_ns: how much newer the newest frame is, nanoseconds.
        max_wait_ns: the patience, nanoseconds (``max_pose_gap``).
    """
    patient = waited_ns <= max_wait_ns
    newest = poses.newest_ns
    if patient and newest is not None and newest < stamp_ns:
        return None
    found = poses.pose_at(stamp_ns)
    if found.pose is None and patient and found.reason in TF_WAIT_REASONS:
        return None
    return found


class Tf2Transforms:
    """:class:`~selfcontra_ros.bags.tf.TransformSource` over a tf2_ros ``Buffer`` (filled by a ``TransformListener``).

    tf2_ros's exceptions become :class:`~selfcontra_ros.errors.TransformError`
    with the reasons of :class:`~selfcontra_ros.bags.tf.TFBuffer`:
    ``LookupException`` -> ``tf_unknown_frame``, ``ConnectivityException`` ->
    ``tf_not_connected``, ``ExtrapolationException`` -> ``tf_before_buffer``
    ("into the past") or ``tf_after_buffer`` (otherwise: the data may still
    come), anything else of tf2 -> ``tf_lookup_failed``.

    Args:
        buffer: a ``tf2_ros.Buffer`` (anything with its ``lookup_transform(target, source, time)``).
        tf2: the ``tf2_ros`` module (or any object with its exception classes).
    """

    def __init__(self, buffer: Any, tf2: Any) -> None:
        self.buffer = buffer
        self._tf2 = tf2

    def _reason(self, exc: BaseException) -> str:
        tf2 = self._tf2
        if isinstance(exc, tf2.LookupException):
            return "tf_unknown_frame"
        if isinstance(exc, tf2.ConnectivityException):
            return "tf_not_connected"
        if isinstance(exc, tf2.ExtrapolationException):
            return "tf_before_buffer" if "past" in str(exc).lower() else "tf_after_buffer"
        return "tf_lookup_failed"

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int) -> NDArray[np.float64]:
        """4x4 ``T_target_source`` (metres) at ``stamp_ns`` from the tf2 buffer (no waiting: timeout 0).

        Raises:
            TransformError: tf2 has no such transform at the stamp, or gave a non-rigid one.
        """
        from rclpy.time import Time

        target, source = normalize_frame(target_frame), normalize_frame(source_frame)
        try:
            msg = self.buffer.lookup_transform(target, source, Time(nanoseconds=int(stamp_ns)))
        except self._tf2.TransformException as exc:
            raise TransformError(
                f"tf2: no transform from {target} to {source} at {int(stamp_ns) / 1e9:.3f} s: {exc}", self._reason(exc)
            ) from exc
        try:
            return matrix_from_transform(msg.transform, what=f"tf2 transform {target} -> {source}")
        except PoseError as exc:
            raise TransformError(str(exc), "tf_lookup_failed") from exc


class LabelerNode(Node):
    """Matches every synchronised stereo frame and labels its views off the subscription thread.

    See the module docstring for topics, parameters, threads and drop reasons.

    Attributes:
        drops: drop reason -> count (also published on ``~/stats``).
        counts: progress counters (frames matched, views labelled, ...).
    """

    def __init__(self, *, transform_source: TransformSource | None = None, **kwargs: Any) -> None:
        """Declare and read the parameters, create publishers, subscriptions, timers and the labeling worker.

        Args:
            transform_source: with ``pose_source: tf``, the TF to read instead of a tf2_ros
                ``Buffer`` + ``TransformListener`` (e.g. a :class:`~selfcontra_ros.bags.tf.TFBuffer`
                that its owner fills: tests, or a program embedding the node). The node discards
                the transforms older than the frames it has its poses for.
            kwargs: passed to ``rclpy.node.Node`` (``context``, ``parameter_overrides``, ...).

        Raises:
            LabelerConfigError: a parameter is invalid, or ``pose_source: tf`` without tf2_ros
                and without ``transform_source``.
        """
        super().__init__(NODE_NAME, **kwargs)
        self._transform_source = transform_source
        self._tf_listener: Any = None
        self._lock = threading.Lock()
        self.drops: dict[str, int] = dict.fromkeys(DROP_REASONS, 0)
        self.counts: dict[str, int] = {
            "frames": 0,
            "depth_published": 0,
            "views_queued": 0,
            "views_labelled": 0,
            "keyframe_skipped": 0,
            "labels_published": 0,
            "confidence_published": 0,
            "confidence_forest": 0,
            "camera_resets": 0,
            "time_jumps": 0,
        }
        self._warned: dict[str, float] = {}
        self._worker: threading.Thread | None = None
        self._confidence_worker: threading.Thread | None = None
        self._confidence: OnlineConfidence | None = None
        self._stop = threading.Event()
        try:
            self._declare_parameters()
            self._read_parameters()
            self._create_io()
        except BaseException:
            super().destroy_node()
            raise
        self._worker = threading.Thread(target=self._label_worker, name="selfcontra_labeling", daemon=True)
        self._worker.start()
        if self._confidence_pub is not None:
            self._confidence_worker = threading.Thread(
                target=self._confidence_loop, name="selfcontra_confidence", daemon=True
            )
            self._confidence_worker.start()

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        for name, default in to_ros_parameters(MatcherParams(), LabelerParams(), ConfidenceParams()).items():
            section, _, key = name.partition(".")
            cls = _SECTION_CLASSES[section]
            extra: dict[str, Any] = {}
            if name in _CORE_INT_RANGES:
                extra["integer_range"] = _CORE_INT_RANGES[name]
            if name in _CORE_FLOAT_RANGES:
                extra["floating_point_range"] = _CORE_FLOAT_RANGES[name]
            if isinstance(default, float):
                # A YAML "10" for a float parameter would otherwise be refused as an integer.
                extra["dynamic_typing"] = True
            self.declare_parameter(name, default, _descriptor(f"see selfcontra_ros {cls}.{key}", **extra))
        self.declare_parameter(
            "pose_source",
            "pose",
            _descriptor(
                "pose topic: 'pose' (geometry_msgs/PoseStamped) or 'odom' (nav_msgs/Odometry), T_world_left; "
                "'odometry': no pose topic, the package's stereo visual odometry estimates the poses; "
                "'tf': camera_frame in world_frame from /tf and /tf_static (needs tf2_ros)",
                additional_constraints="pose, odom, odometry or tf",
            ),
        )
        self.declare_parameter(
            "odometry_disparity_offset_px",
            0.0,
            _descriptor(
                "pose_source odometry: the rig's disparity offset, added to every disparity the odometry measures "
                "(pixels, within +-5; e.g. what `selfcontra odometry` prints for a recording of the rig)",
                dynamic_typing=True,
            ),
        )
        self.declare_parameter(
            "odometry_estimate_offset",
            True,
            _descriptor(
                "pose_source odometry: estimate the disparity offset while running and apply it once it differs "
                "significantly from odometry_disparity_offset_px (false: keep that value)"
            ),
        )
        self.declare_parameter(
            "odometry_road_steps",
            True,
            _descriptor(
                "pose_source odometry: measure each step a second time on the road ahead (the ground plane below "
                "the camera: its length, and where neighbouring frames' road steps agree its rotation and "
                "direction too); false for a camera that never sees one"
            ),
        )
        self.declare_parameter(
            "world_frame",
            "",
            _descriptor("pose_source tf: the fixed frame of the poses, e.g. odom or map (required there)"),
        )
        self.declare_parameter(
            "camera_frame",
            "",
            _descriptor("pose_source tf: the left camera's TF frame; empty: the left camera_info's header.frame_id"),
        )
        self.declare_parameter(
            "image_transport",
            "raw",
            _descriptor(
                "raw: sensor_msgs/Image; compressed: sensor_msgs/CompressedImage on <image topic>/compressed",
                additional_constraints="raw or compressed",
            ),
        )
        self.declare_parameter(
            "rectify",
            False,
            _descriptor(
                "subscribe to left/right image_raw and rectify them with their (distorted) camera_info "
                "(plumb_bob or rational_polynomial D, K, R, P)"
            ),
        )
        self.declare_parameter(
            "sync",
            "exact",
            _descriptor("image/camera-info synchronisation", additional_constraints="exact or approximate"),
        )
        self.declare_parameter(
            "slop",
            0.0,
            _descriptor(
                "largest stamp difference to the left image, seconds (approximate sync)",
                floating_point_range=_float_range(0.0, 1.0),
            ),
        )
        self.declare_parameter(
            "queue_size",
            10,
            _descriptor(
                "messages queued per synchronised topic, and frames waiting for their pose",
                integer_range=_int_range(1, 1000),
            ),
        )
        self.declare_parameter(
            "label_queue_size",
            4,
            _descriptor(
                "views waiting for the labeling worker; a view finding it full is skipped (label_queue_full)",
                integer_range=_int_range(1, 1000),
            ),
        )
        self.declare_parameter(
            "max_pose_gap",
            0.5,
            _descriptor(
                "seconds: poses interpolated at an image stamp may be at most this far apart, and a frame waits "
                "at most this much newer image time for its pose",
                floating_point_range=_float_range(0.0, 60.0),
            ),
        )
        self.declare_parameter(
            "max_pose_extrapolation",
            0.05,
            _descriptor(
                "seconds past the newest pose a given-up frame may still be extrapolated (0: never)",
                floating_point_range=_float_range(0.0, 1.0),
            ),
        )
        self.declare_parameter(
            "time_jump_reset",
            1.0,
            _descriptor(
                "image stamps going back by more than this many seconds reset the node's state (0: never)",
                floating_point_range=_float_range(0.0, 1.0e6),
            ),
        )
        self.declare_parameter(
            "confidence_queue_size",
            2,
            _descriptor(
                "frames waiting for a forest confidence; a frame finding it full gets LRD (confidence_lrd_fallback)",
                integer_range=_int_range(1, 100),
            ),
        )
        self.declare_parameter("publish_debug", False, _descriptor("publish debug/support, vote_sum, uncertainty"))
        self.declare_parameter(
            "input_qos",
            "sensor_data",
            _descriptor(
                "subscription QoS: sensor_data (best effort, keep-last) or reliable (keep-all: nothing lost)",
                additional_constraints="sensor_data or reliable",
            ),
        )
        self.declare_parameter(
            "stats_period",
            1.0,
            _descriptor("seconds between ~/stats messages", floating_point_range=_float_range(0.01, 3600.0)),
        )
        self.declare_parameter(
            "threads",
            NODE_PARAMETERS["threads"],
            _descriptor(
                "threads per pool (numba, OpenCV, BLAS/OpenMP, scikit-learn); 0 = every core the process may use",
                integer_range=_int_range(0, 4096),
            ),
        )
        self.declare_parameter(
            "flush_on_shutdown",
            False,
            _descriptor("at shutdown, label the queued views and flush the window before exiting"),
        )

    def _read_parameters(self) -> None:
        names = list(to_ros_parameters(MatcherParams(), LabelerParams(), ConfidenceParams()))
        values = {name: self.get_parameter(name).value for name in names}
        try:
            self.matcher_params, self.labeler_params = from_ros_parameters(values)
            self.confidence_params = confidence_from_ros_parameters(values)
        except SelfContraError as exc:
            raise LabelerConfigError(str(exc)) from exc
        p = self.get_parameter
        self._pose_source = str(p("pose_source").value)
        try:
            self._odometry_params = VOParams(
                disparity_offset_px=float(p("odometry_disparity_offset_px").value),
                estimate_disparity_offset=bool(p("odometry_estimate_offset").value),
                road_steps=bool(p("odometry_road_steps").value),
            )
        except (OdometryError, TypeError, ValueError) as exc:
            raise LabelerConfigError(f"parameter 'odometry_disparity_offset_px': {exc}") from exc
        self._world_frame = normalize_frame(str(p("world_frame").value))
        self._camera_frame = normalize_frame(str(p("camera_frame").value))
        self._image_transport = str(p("image_transport").value)
        self._rectify = bool(p("rectify").value)
        self._sync_mode = str(p("sync").value)
        self._slop = float(p("slop").value)
        self._queue_size = int(p("queue_size").value)
        self._label_queue_size = int(p("label_queue_size").value)
        self._max_pose_gap = float(p("max_pose_gap").value)
        self._max_extrapolation = float(p("max_pose_extrapolation").value)
        self._time_jump_ns = round(float(p("time_jump_reset").value) * 1e9)
        self._publish_debug = bool(p("publish_debug").value)
        self._input_qos = str(p("input_qos").value)
        self._stats_period = float(p("stats_period").value)
        self._flush_on_shutdown = bool(p("flush_on_shutdown").value)
        self._confidence_queue_size = int(p("confidence_queue_size").value)
        try:
            # Before the first kernel runs: the cap must hold from the first frame on.
            self._threads = limit_threads(int(p("threads").value))
        except SelfContraError as exc:
            raise LabelerConfigError(str(exc)) from exc
        self.get_logger().info(f"threads: {self._threads} per pool (of {available_cores()} cores available)")
        for name, value, choices in (
            ("pose_source", self._pose_source, POSE_SOURCES),
            ("sync", self._sync_mode, SYNC_MODES),
            ("input_qos", self._input_qos, INPUT_QOS),
            ("image_transport", self._image_transport, IMAGE_TRANSPORTS),
        ):
            if value not in choices:
                raise LabelerConfigError(f"parameter {name!r} is {value!r}; expected one of {', '.join(choices)}")
        if self._pose_source == "tf" and not self._world_frame:
            raise LabelerConfigError(
                "parameter 'world_frame' is required with pose_source 'tf': the fixed frame, e.g. odom or map"
            )
        if self._pose_source != "tf" and (self._world_frame or self._camera_frame):
            raise LabelerConfigError(
                f"parameters 'world_frame' and 'camera_frame' apply to pose_source 'tf' only "
                f"(pose_source is {self._pose_source!r})"
            )
        # Before any thread starts: a missing tf2_ros stops the node at once.
        self._tf2: Any = self._import_tf2() if self._pose_source == "tf" and self._transform_source is None else None
        if self._sync_mode == "exact" and self._slop != 0.0:
            raise LabelerConfigError(f"parameter 'slop' is {self._slop:g} s with sync 'exact'; use sync:=approximate")
        self._external = self.matcher_params.algorithm == "external"
        if not self._external:
            try:
                self._confidence = OnlineConfidence(
                    self.confidence_params,
                    background=True,
                    log=self.get_logger().info,
                    labeler=self.labeler_params,
                )
            except SelfContraError as exc:  # model_in unreadable or of another feature set
                raise LabelerConfigError(f"confidence.model_in: {exc}") from exc

    # ------------------------------------------------------------------ topics

    def _create_io(self) -> None:
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image
        from std_msgs.msg import String
        from stereo_msgs.msg import DisparityImage

        qos_in = input_qos_profile(self._input_qos, self._queue_size)
        qos_out = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        qos_stats = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )

        self._depth_pub: Publisher = self.create_publisher(Image, topics.DEPTH, qos_out)
        # In external mode ``disparity`` is the input: the node does not publish on it.
        self._disparity_pub: Publisher | None = (
            None if self._external else self.create_publisher(DisparityImage, topics.DISPARITY, qos_out)
        )
        # Confidence needs images: none in external mode.
        self._confidence_pub: Publisher | None = None
        self._filtered_pub: Publisher | None = None
        if self._confidence is not None:
            self._confidence_pub = self.create_publisher(Image, topics.CONFIDENCE, qos_out)
            self._filtered_pub = self.create_publisher(Image, topics.DEPTH_FILTERED, qos_out)
        self._confidence_queue: queue.Queue[_ConfidenceJob | None] = queue.Queue(maxsize=self._confidence_queue_size)
        self._labels_pub: Publisher = self.create_publisher(Image, topics.LABELS, qos_out)
        self._color_pub: Publisher = self.create_publisher(Image, topics.LABELS_COLOR, qos_out)
        self._debug_pubs: dict[str, Publisher] = {}
        if self._publish_debug:
            for name in (DEBUG_SUPPORT, DEBUG_VOTE_SUM, DEBUG_UNCERTAINTY):
                self._debug_pubs[name] = self.create_publisher(Image, name, qos_out)
        self._stats_pub: Publisher = self.create_publisher(String, STATS, qos_stats)
        self._string_type = String

        # The pivot (first key) gives the frame's stamp: the left image, or the external disparity.
        pivot = "disparity" if self._external else "left"
        keys = (pivot, "left_info", "right_info") if self._external else ("left", "right", "left_info", "right_info")
        self._keys = keys
        self._sync = StampSynchronizer(keys, mode=self._sync_mode, slop=self._slop, queue_size=self._queue_size)
        self._poses = PoseBuffer(_POSE_CAPACITY)
        self._awaiting_pose: list[_View] = []
        self._newest_frame_ns: int | None = None
        self._camera_key: tuple[Any, ...] | None = None
        self._camera: StereoCamera | None = None
        self._session: LabelingSession | None = None
        self._odometry: OnlineOdometry | None = None  # pose_source "odometry": one per session
        self._label_queue: queue.Queue[_View | None] = queue.Queue(maxsize=self._label_queue_size)
        stereo_input = StereoInput(image_transport=self._image_transport, rectify=self._rectify)
        self._images = StereoImages(stereo_input)
        self._tf_poses: TFPoses | None = None
        if self._pose_source == "tf":
            source = self._transform_source if self._transform_source is not None else self._tf2_source()
            self._tf_poses = TFPoses(source, self._world_frame, self._camera_frame or None)
            self._tf_timer = self.create_timer(_TF_RETRY_PERIOD_S, self._retry_tf)

        if self._external:
            self.create_subscription(DisparityImage, topics.DISPARITY, self._callback("disparity"), qos_in)
        elif self._image_transport == "compressed":
            for key, name in (("left", stereo_input.left_image), ("right", stereo_input.right_image)):
                # The base name resolved (and remapped) first, as image_transport does: -r left/image_raw:=X
                # moves the subscription to X/compressed.
                topic = self.resolve_topic_name(name) + topics.COMPRESSED_SUFFIX
                self.create_subscription(CompressedImage, topic, self._callback(key), qos_in)
        else:
            self.create_subscription(Image, stereo_input.left_image, self._callback("left"), qos_in)
            self.create_subscription(Image, stereo_input.right_image, self._callback("right"), qos_in)
        self.create_subscription(CameraInfo, topics.LEFT_INFO, self._callback("left_info"), qos_in)
        self.create_subscription(CameraInfo, topics.RIGHT_INFO, self._callback("right_info"), qos_in)
        if self._pose_source == "pose":
            self.create_subscription(PoseStamped, topics.POSE, self._on_pose, qos_in)
        elif self._pose_source == "odom":
            self.create_subscription(Odometry, ODOM, self._on_pose, qos_in)
        self._stats_timer = self.create_timer(self._stats_period, self.publish_stats)
        self._last_stats_log = time.monotonic()
        self._last_logged_stats: str | None = None
        self.get_logger().info(
            f"labeling {'external disparities' if self._external else 'stereo images'} "
            f"({self.matcher_params.algorithm}"
            + ("" if self._external else f", {self._image_transport}{', rectified here' if self._rectify else ''}")
            + f"), pose from '{self._pose_source}'"
            + (
                f" ({self._camera_frame or 'the left camera_info frame'} in {self._world_frame})"
                if self._tf_poses
                else ""
            )
            + f", sync {self._sync_mode}"
            + (f" (slop {self._slop:g} s)" if self._sync_mode == "approximate" else "")
            + f", window {self.labeler_params.window_size}, delay {self.labeler_params.label_delay}"
        )

    def _tf2_source(self) -> Tf2Transforms:
        """A tf2_ros ``Buffer`` filled by a ``TransformListener`` on this node (``/tf``, ``/tf_static``)."""
        tf2_ros = self._tf2
        buffer = tf2_ros.Buffer(node=self)
        self._tf_listener = tf2_ros.TransformListener(buffer, self)
        return Tf2Transforms(buffer, tf2_ros)

    @staticmethod
    def _import_tf2() -> Any:
        """The ``tf2_ros`` module.

        Raises:
            LabelerConfigError: tf2_ros is not installed (naming the alternatives).
        """
        try:
            import tf2_ros
        except ImportError as exc:
            raise LabelerConfigError(
                f"pose_source 'tf' needs tf2_ros, ROS 2's Python TF library, which this installation lacks ({exc}); "
                "the PyPI ROS wheels have none. Alternatives: run the node from a ROS 2 install that has tf2_ros "
                "(ros-<distro>-tf2-ros); or give the labeler a pose topic (pose_source pose or odom), e.g. from "
                "the player, which composes a bag's /tf and /tf_static itself (player -p pose_source:=tf "
                "-p world_frame:=odom publishes the left camera's PoseStamped on 'pose'); or let the package "
                "estimate the poses (pose_source odometry); offline, 'selfcontra label BAG --pose-source tf' "
                "needs no ROS at all"
            ) from exc
        return tf2_ros

    def _retry_tf(self) -> None:
        """Timer: frames waiting for TF get another lookup (tf2_ros fills its buffer without telling the node)."""
        if not self._awaiting_pose:
            return
        try:
            self._release_views()
        except Exception as exc:  # never die on input
            self._drop("error", f"TF pose lookup: unexpected {type(exc).__name__}: {exc}")

    # ------------------------------------------------------------------ counters and logs

    def _drop(self, reason: str, message: str, count: int = 1) -> None:
        """Count ``count`` drops under ``reason`` and warn, at most once per reason every few seconds."""
        with self._lock:
            self.drops[reason] = self.drops.get(reason, 0) + count
        now = time.monotonic()
        if now - self._warned.get(reason, -math.inf) >= _WARN_PERIOD_S:
            self._warned[reason] = now
            self.get_logger().warning(f"dropped ({reason}): {message}")

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] = self.counts.get(name, 0) + n

    def stats(self) -> dict[str, Any]:
        """Drop counters (own reasons plus the synchroniser's), progress counters and queue fill, JSON-ready."""
        with self._lock:
            drops = dict(self.drops)
            counts = dict(self.counts)
        sync_dropped = {str(k): int(v) for k, v in self._sync.dropped.items()}
        sync_backwards = {str(k): int(v) for k, v in self._sync.backwards.items()}
        drops["unsynced"] += sum(sync_dropped.values())
        drops["stamp_backwards"] += sum(sync_backwards.values())
        drops["pose_backwards"] += self._poses.out_of_order
        return {
            "drops": drops,
            "counts": counts,
            "sync_dropped": sync_dropped,
            "sync_backwards": sync_backwards,
            "label_queue": self._label_queue.qsize(),
            "threads": self._threads,
            "awaiting_pose": len(self._awaiting_pose),
            "params": params_to_dict(self.matcher_params, self.labeler_params, self.confidence_params),
            "confidence": self._confidence.stats() if self._confidence is not None else None,
        }

    def publish_stats(self) -> None:
        """Publish :meth:`stats` on ``~/stats``; log them now and then when they changed."""
        text = json.dumps(self.stats(), sort_keys=True)
        msg = self._string_type()
        msg.data = text
        try:
            self._stats_pub.publish(msg)
        except Exception:  # the context may be shutting down
            return
        now = time.monotonic()
        if now - self._last_stats_log >= _STATS_LOG_PERIOD_S and text != self._last_logged_stats:
            self._last_stats_log = now
            self._last_logged_stats = text
            self.get_logger().info(f"stats: {self._summary()}")

    def _summary(self) -> str:
        stats = self.stats()
        drops = {k: v for k, v in stats["drops"].items() if v}
        return f"{json.dumps(stats['counts'], sort_keys=True)}, drops {json.dumps(drops, sort_keys=True)}"

    # ------------------------------------------------------------------ subscription side

    def _callback(self, key: str) -> Any:
        def on_message(msg: Any) -> None:
            try:
                self._on_synced_message(key, msg)
            except SelfContraError as exc:
                self._drop("error", f"{key}: {exc}")
            except Exception as exc:  # never die on input: log and carry on
                self._drop("error", f"{key}: unexpected {type(exc).__name__}: {exc}")

        return on_message

    def _on_synced_message(self, key: str, msg: Any) -> None:
        stamp_ns = stamp_to_nanoseconds(msg.header.stamp)
        newest = self._newest_frame_ns
        if key == self._keys[0] and newest is not None and 0 < self._time_jump_ns < newest - stamp_ns:
            self._reset_stream(stamp_ns)
        result = self._sync.push(key, stamp_ns, msg)
        if not result.accepted:
            self._warn_once("stamp_backwards", f"{key} stamp {stamp_ns} ns is not newer than the previous one")
        for match in result.matches:
            self._on_frame(match)

    def _warn_once(self, reason: str, message: str) -> None:
        """Rate-limited warning for drops counted elsewhere (synchroniser, pose buffer)."""
        now = time.monotonic()
        if now - self._warned.get(reason, -math.inf) >= _WARN_PERIOD_S:
            self._warned[reason] = now
            self.get_logger().warning(f"dropped ({reason}): {message}")

    def _reset_stream(self, stamp_ns: int) -> None:
        """Time went back (bag loop, restarted driver): start over with empty queues, poses and session."""
        self.get_logger().warning(
            f"image stamps jumped back by {(self._newest_frame_ns or 0) - stamp_ns:,} ns: resetting synchroniser, "
            "poses and labeling session"
        )
        self._count("time_jumps")
        self._sync.reset()
        out_of_order = self._poses.out_of_order
        self._poses = PoseBuffer(_POSE_CAPACITY)
        self._poses.out_of_order = out_of_order  # keep the counter running
        self._newest_frame_ns = None
        self._end_session("time jump", keep_camera=False)

    def _end_session(self, reason: str, *, keep_camera: bool) -> None:
        """Drop the views waiting for a pose (``session_reset``) and the session; the next frame starts a new
        one (and, with ``pose_source: odometry``, a new odometry). ``keep_camera`` False: the camera line is
        logged again."""
        if self._awaiting_pose:
            self._drop("session_reset", reason, len(self._awaiting_pose))
            self._awaiting_pose.clear()
        with self._lock:
            self._session = None
            self._camera_key = None
            if not keep_camera:
                self._camera = None

    def _on_frame(self, match: Match) -> None:
        """One synchronised frame: convert, match, publish depth and disparity, queue the view for its pose."""
        items = dict(zip(self._keys, match.items, strict=True))
        session = self._session_for(items["left_info"], items["right_info"])
        if session is None:
            return
        camera = session.camera
        pivot = items[self._keys[0]]
        frame_id = str(pivot.header.frame_id)
        posed = True  # False: the odometry found the frame's pose unreliable; its outputs go out, it is not labelled
        try:
            if self._external:
                disparity_in, _, _ = disparity_from_message(pivot)
                if disparity_in.shape != (camera.height, camera.width):
                    self._drop(
                        "size_mismatch",
                        f"disparity is {disparity_in.shape[1]}x{disparity_in.shape[0]}, "
                        f"camera_info says {camera.width}x{camera.height}",
                    )
                    return
                left = right = np.zeros((camera.height, camera.width), np.uint8)
                disparity, depth = session.match(left, right, external_disparity=disparity_in)
                frame = None
            else:
                left, right = self._images.pixels(items["left"], "left"), self._images.pixels(items["right"], "right")
                for side, image in (("left", left), ("right", right)):
                    if image.shape[:2] != (camera.height, camera.width):
                        self._drop(
                            "size_mismatch",
                            f"{side} image is {image.shape[1]}x{image.shape[0]}, "
                            f"camera_info says {camera.width}x{camera.height}",
                        )
                        return
                if left.shape != right.shape:
                    self._drop("bad_image", f"left image {left.shape} and right image {right.shape} differ")
                    return
                matched = session.match_frame(left, right)
                disparity, depth, frame = matched.disparity, matched.depth, matched.frame
                if self._odometry is not None:
                    posed = self._odometry_pose(match.stamp_ns, left, right)
        except ImageError as exc:
            self._drop(_IMAGE_REASONS.get(exc.reason, exc.reason), str(exc))
            return
        except ConversionError as exc:
            self._drop("bad_disparity" if self._external else "bad_image", str(exc))
            return
        self._count("frames")
        stamp = nanoseconds_to_stamp(match.stamp_ns)
        self._depth_pub.publish(numpy_to_image(depth, "32FC1", stamp=stamp, frame_id=frame_id))
        if frame is not None:
            self._confidence_for(session, frame, depth, match.stamp_ns, frame_id)
        p = self.matcher_params
        if self._disparity_pub is not None:
            self._disparity_pub.publish(
                disparity_image(
                    disparity,
                    camera,
                    stamp=stamp,
                    frame_id=frame_id,
                    min_disparity=float(p.min_disparity),
                    max_disparity=p.max_disparity,
                )
            )
        self._after_match(session, match.stamp_ns, frame_id, disparity, frame, label=posed)

    def _after_match(
        self,
        session: LabelingSession,
        stamp_ns: int,
        frame_id: str,
        disparity: NDArray[np.float32],
        frame: ConfidenceFrame | None = None,
        *,
        label: bool = True,
    ) -> None:
        """Queue a matched view until its pose is known (``label`` False: its outputs are out, it is not labelled)."""
        self._count("depth_published")
        self._newest_frame_ns = stamp_ns
        if not label:
            self._release_views()
            return
        self._awaiting_pose.append(_View(session, ViewKey(stamp_ns, frame_id), disparity, frame=frame))
        hold = self._odometry.max_hold if self._odometry is not None else 0  # views wait for the odometry's lag
        if len(self._awaiting_pose) > self._queue_size + hold:
            dropped = self._awaiting_pose.pop(0)
            self._drop("pose_wait_overflow", f"frame at {dropped.key.stamp_ns} ns waited too long for its pose")
        self._release_views()

    # ------------------------------------------------------------------ confidence

    def _confidence_for(
        self,
        session: LabelingSession,
        frame: ConfidenceFrame,
        depth: NDArray[np.float32],
        stamp_ns: int,
        frame_id: str,
    ) -> None:
        """LRD confidence now, or the frame queued for the confidence worker once a forest exists."""
        assert self._confidence is not None
        model = self._confidence.model
        if model is not None:
            try:
                self._confidence_queue.put_nowait(_ConfidenceJob(session, frame, depth, model, stamp_ns, frame_id))
                return
            except queue.Full:
                self._drop(
                    "confidence_lrd_fallback", f"forest confidence is behind; LRD for the frame at {stamp_ns} ns"
                )
        self._publish_confidence(self._confidence.lrd(frame), depth, stamp_ns, frame_id)

    def _publish_confidence(
        self, confidence: NDArray[np.float32], depth: NDArray[np.float32], stamp_ns: int, frame_id: str
    ) -> None:
        assert self._confidence is not None and self._confidence_pub is not None and self._filtered_pub is not None
        stamp = nanoseconds_to_stamp(stamp_ns)
        filtered = filter_depth(depth, confidence, self.confidence_params.confidence_threshold)
        self._confidence_pub.publish(numpy_to_image(confidence, "32FC1", stamp=stamp, frame_id=frame_id))
        self._filtered_pub.publish(numpy_to_image(filtered, "32FC1", stamp=stamp, frame_id=frame_id))
        self._count("confidence_published")

    def _confidence_loop(self) -> None:
        """Forest confidences of the queued frames (runs on its own thread)."""
        assert self._confidence is not None
        apply_thread_limit()  # numba's and OpenMP's thread counts are per thread
        while True:
            job = self._confidence_queue.get()
            if job is None:
                return
            try:
                confidence = self._confidence.confidence(job.frame, job.model)
                self._publish_confidence(confidence, job.depth, job.stamp_ns, job.frame_id)
                self._count("confidence_forest")
            except Exception as exc:
                self._drop("error", f"confidence of the frame at {job.stamp_ns} ns: {type(exc).__name__}: {exc}")

    def _odometry_pose(self, stamp_ns: int, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> bool:
        """``pose_source: odometry``: estimate the frame's pose into the pose buffer; False: the frame is not labelled.

        Runs on the subscription thread, as every frame must reach the
        odometry in order (about 150 ms a frame at KITTI size on 2 cores). A
        frame whose pose is unreliable is never labelled (it would make false
        labels, counted as the drop ``odometry_unreliable``); its depth,
        disparity and confidence do not depend on the pose and are published.
        A frame's decision comes ``VOParams.smoothing_lag_frames`` frames
        later (its step length smoothed with the frames after it; up to
        ``isolated_frames`` after unreliable ones: ``OnlineOdometry``): its
        view waits in ``_awaiting_pose`` for it however long that takes, and
        leaves it when the decision is no.

        Should the odometry raise (a defect, or an input it cannot take),
        its state is unknown: the frame is counted as the drop
        ``odometry_error`` and published but not labelled, and the node
        starts over as after a time jump, with a new odometry and labeling
        session on the next frame (the new odometry's poses are in a frame
        of their own, which must not meet the old views'); the old views
        still waiting for the odometry's decisions, or in the label queue,
        are dropped (``session_reset``).
        """
        assert self._odometry is not None
        try:
            decisions = self._odometry.add(stamp_ns, left, right)
        except Exception as exc:
            self._drop("odometry_error", f"frame at {stamp_ns} ns: {type(exc).__name__}: {exc}; starting over")
            self._odometry = None
            self._end_session("odometry error", keep_camera=True)
            return False
        return self._apply_decisions(decisions, stamp_ns)

    def _apply_decisions(self, decisions: list[OnlineDecision], current_ns: int | None = None) -> bool:
        """Poses of the odometry's decisions into the pose buffer; views decided unreliable leave the queue.

        Returns False when the frame at ``current_ns`` (not queued yet) was decided unreliable.
        """
        labelled = True
        for decision in decisions:
            if decision.pose is not None:
                self._poses.add(decision.stamp_ns, decision.pose)
                continue
            self._drop("odometry_unreliable", decision.quality.message or "unreliable pose")
            if decision.stamp_ns == current_ns:
                labelled = False
            else:  # an earlier frame, whose view waits for this decision
                self._awaiting_pose[:] = [v for v in self._awaiting_pose if v.key.stamp_ns != decision.stamp_ns]
        return labelled

    def _session_for(self, left_info: Any, right_info: Any) -> LabelingSession | None:
        """The session of the camera the infos describe; a new one (logged) when the calibration changed.

        With ``rectify`` the whole calibration (D, K, R, P) is the key: a change rebuilds the
        rectification maps, and starts a new session only if the rectified camera changed too.
        """
        if self._rectify:
            key = (calibration_key(left_info), calibration_key(right_info))
        else:
            key = (_info_key(left_info), _info_key(right_info))
        if key == self._camera_key and self._session is not None:
            return self._session
        try:
            camera = self._images.camera_from_infos(left_info, right_info)
        except CalibrationError as exc:
            self._drop("bad_camera_info", str(exc))
            return None
        self._camera_key = key
        if self._tf_poses is not None:
            self._tf_poses.set_camera(str(left_info.header.frame_id), self._images.raw_from_rectified)
        if self._session is not None and camera == self._camera:
            return self._session  # same calibration, e.g. only the stamps or the K of the infos differ
        session = LabelingSession(camera, self.matcher_params, self.labeler_params, self._confidence)
        if self._session is not None:
            self._count("camera_resets")
            self.get_logger().warning(
                f"camera changed ({self._camera.width}x{self._camera.height} -> {camera.width}x{camera.height}, "
                f"fx {self._camera.fx:g} -> {camera.fx:g}, baseline {self._camera.baseline:g} -> "
                f"{camera.baseline:g} m): starting a new labeling session"
                if self._camera is not None
                else "camera changed: starting a new labeling session"
            )
            if self._awaiting_pose:
                self._drop("session_reset", "views of the previous camera", len(self._awaiting_pose))
                self._awaiting_pose.clear()
        elif camera != self._camera:  # not after an odometry error, which keeps the camera (once a frame, perhaps)
            self.get_logger().info(
                f"camera: {camera.width}x{camera.height}, fx {camera.fx:g} px, baseline {camera.baseline:g} m"
            )
        with self._lock:
            self._camera = camera
            self._session = session
        if self._pose_source == "odometry" and not self._external:
            self._odometry = OnlineOdometry(camera, self._odometry_params)
        return session

    def _on_pose(self, msg: Any) -> None:
        try:
            if not self._poses.add_message(msg):
                self._warn_once("pose_backwards", "pose stamp is not newer than the previous pose")
                return
            self._release_views()
        except PoseError as exc:
            self._drop("bad_pose", str(exc))
        except SelfContraError as exc:
            self._drop("error", f"pose: {exc}")
        except Exception as exc:
            self._drop("error", f"pose: unexpected {type(exc).__name__}: {exc}")

    def _release_views(self, *, block: bool = False) -> None:
        """Give their pose to the waiting frames (oldest first) and queue them for labeling.

        A frame whose stamp the pose stream has not reached waits, unless a
        frame more than ``max_pose_gap`` s newer has arrived already (the pose
        stream stopped or lags too far): then it is looked up one last time
        (extrapolating at most ``max_pose_extrapolation`` s) and dropped when
        that fails. With ``pose_source: odometry`` a frame waits for the
        odometry's decision instead, which comes ``max_hold`` frames later or
        at shutdown (``_odometry_pose``, ``stop``); ``block``: wait for room
        in the label queue instead of dropping the view (shutdown).
        """
        max_wait_ns = round(self._max_pose_gap * 1e9)
        while self._awaiting_pose:
            view = self._awaiting_pose[0]
            stamp = view.key.stamp_ns
            waited_ns = (self._newest_frame_ns or stamp) - stamp
            if self._tf_poses is not None:
                found = tf_pose_decision(self._tf_poses, stamp, waited_ns=waited_ns, max_wait_ns=max_wait_ns)
                if found is None:
                    return  # TF may still reach the stamp
                self._awaiting_pose.pop(0)
                if found.pose is None:
                    self._drop(found.reason or "tf_lookup_failed", f"frame at {stamp} ns: {found.detail}")
                    continue
                view.pose = found.pose
                self._tf_poses.discard_before(stamp)
            else:
                if self._odometry is not None and stamp in self._odometry.undecided():
                    return  # decided a few frames later, whatever the time between frames
                newest_pose = self._poses.newest_ns
                if newest_pose is None or newest_pose < stamp:
                    if waited_ns <= max_wait_ns:
                        return  # the pose may still come
                    extrapolation = self._max_extrapolation
                else:
                    extrapolation = 0.0
                lookup = self._poses.lookup(stamp, max_gap_s=self._max_pose_gap, max_extrapolation_s=extrapolation)
                self._awaiting_pose.pop(0)
                if lookup.pose is None:
                    reason = lookup.reason.value if lookup.reason is not None else "pose_none_yet"
                    self._drop(reason, f"no pose within {self._max_pose_gap:g} s of the frame at {stamp} ns")
                    continue
                view.pose = lookup.pose
                self._poses.discard_before(stamp)
            try:
                if block:  # at shutdown: wait for the worker rather than drop
                    self._label_queue.put(view, timeout=_JOIN_TIMEOUT_S)
                else:
                    self._label_queue.put_nowait(view)
            except queue.Full:
                self._drop("label_queue_full", f"labeling is behind; view at {stamp} ns skipped")
                continue
            self._count("views_queued")

    # ------------------------------------------------------------------ labeling worker

    def _label_worker(self) -> None:
        """Label the queued views in order and publish their labels (runs on its own thread)."""
        apply_thread_limit()  # numba's and OpenMP's thread counts are per thread
        while True:
            view = self._label_queue.get()
            if view is None:
                return
            if self._stop.is_set() and not self._flush_on_shutdown:
                self._drop("shutdown_discarded", "node stopping", 1)
                continue
            try:
                self._label_view(view)
            except SelfContraError as exc:
                self._drop("error", f"labeling the view at {view.key.stamp_ns} ns: {exc}")
            except Exception as exc:
                self._drop(
                    "error", f"labeling the view at {view.key.stamp_ns} ns: unexpected {type(exc).__name__}: {exc}"
                )

    def _label_view(self, view: _View) -> None:
        with self._lock:
            current = self._session
        if view.session is not current:
            self._drop("session_reset", f"view at {view.key.stamp_ns} ns belongs to the previous camera")
            return
        assert view.pose is not None
        results, skipped = view.session.label(
            view.disparity, view.pose, stamp=view.key.stamp_ns / 1e9, key=view.key, frame=view.frame
        )
        self._count("views_labelled")
        if skipped:
            self._count("keyframe_skipped")
        for result in results:
            self._publish_labels(result)

    def _publish_labels(self, result: LabelResult) -> None:
        """Publish the labels (and debug maps) of one view with its own header."""
        key = result.key
        assert isinstance(key, ViewKey)
        stamp = nanoseconds_to_stamp(key.stamp_ns)
        frame_id = key.frame_id
        self._labels_pub.publish(numpy_to_image(result.labels, "mono8", stamp=stamp, frame_id=frame_id))
        self._color_pub.publish(numpy_to_image(colorize_labels(result.labels), "rgb8", stamp=stamp, frame_id=frame_id))
        if self._debug_pubs:
            maps = (
                (DEBUG_SUPPORT, result.support, "mono8"),
                (DEBUG_VOTE_SUM, result.vote_sum.astype(np.float32), "32FC1"),
                (DEBUG_UNCERTAINTY, result.uncertainty.astype(np.float32), "32FC1"),
            )
            for name, image, encoding in maps:
                self._debug_pubs[name].publish(numpy_to_image(image, encoding, stamp=stamp, frame_id=frame_id))
        self._count("labels_published")

    # ------------------------------------------------------------------ shutdown

    def stop(self) -> None:
        """Stop the labeling worker; with ``flush_on_shutdown`` label what is queued and flush the window first.

        Safe to call more than once. The confidence threads stop first (module docstring). Frames still
        waiting for their pose are discarded; with ``flush_on_shutdown`` and ``pose_source: odometry`` the
        odometry first decides the frames it still holds (``OnlineOdometry.finish``, the end of the
        sequence), and those with a pose are labelled.
        """
        if self._worker is None:
            return
        worker, self._worker = self._worker, None
        if self._flush_on_shutdown and self._odometry is not None:
            try:
                self._apply_decisions(self._odometry.finish())
                self._release_views(block=True)
            except Exception as exc:
                self._drop("error", f"the odometry's last frames: {type(exc).__name__}: {exc}")
        self._stop.set()
        if self._awaiting_pose:
            self._drop("shutdown_discarded", "node stopping", len(self._awaiting_pose))
            self._awaiting_pose.clear()
        # The confidence threads first: nothing needs them any more, and the trainer (0.8 s of band cue and
        # features per KITTI view, retrainings) would take the cores from the labeling worker's last views.
        self._stop_confidence()
        if self._flush_on_shutdown:
            self._finish_labeling(worker)
        else:
            try:
                # Waits only while the queue is full: the worker frees a slot after the view it is labeling.
                self._label_queue.put(None, timeout=_JOIN_TIMEOUT_S)
            except queue.Full:
                self.get_logger().error("the labeling worker does not take views any more; exiting without it")
            worker.join(timeout=_JOIN_TIMEOUT_S)
        if self._flush_on_shutdown and not worker.is_alive():
            with self._lock:
                session = self._session
            if session is not None:
                try:
                    for result in session.flush():
                        self._publish_labels(result)
                except Exception as exc:
                    self.get_logger().error(f"flushing the labeling window failed: {type(exc).__name__}: {exc}")
        self.publish_stats()
        if self._flush_on_shutdown:
            self._wait_for_acknowledgements()
        self.get_logger().info(f"stopped: {self._summary()}")

    def _finish_labeling(self, worker: threading.Thread) -> None:
        """``flush_on_shutdown``: wait for the worker to label every queued view, however long that takes.

        Its labels are the ones asked for; a bound here lost them on a loaded machine (the window's
        flush was skipped). A second Ctrl-C interrupts the wait (``ros.spinning``).
        """
        while worker.is_alive():
            try:
                self._label_queue.put(None, timeout=_JOIN_TIMEOUT_S)
                break
            except queue.Full:
                self.get_logger().info(f"stopping: labeling the {self._label_queue.qsize()} queued views first")
        while worker.is_alive():
            worker.join(timeout=_JOIN_TIMEOUT_S)
            if worker.is_alive():
                self.get_logger().info(
                    f"stopping: still labeling ({self._label_queue.qsize()} views queued), then the window's flush"
                )

    def _stop_confidence(self) -> None:
        """Stop the confidence worker (dropping waiting frames) and the trainer thread."""
        thread, self._confidence_worker = self._confidence_worker, None
        if thread is not None:
            while True:
                try:
                    self._confidence_queue.get_nowait()
                except queue.Empty:
                    break
            self._confidence_queue.put(None)
            thread.join(timeout=_JOIN_TIMEOUT_S)
        if self._confidence is not None:
            self._confidence.close(timeout=_JOIN_TIMEOUT_S, discard_queued=True)

    def _wait_for_acknowledgements(self, timeout_s: float = _ACK_TIMEOUT_S) -> None:
        """Give reliable subscribers up to ``timeout_s`` in all to acknowledge the last labels before the node goes."""
        deadline = time.monotonic() + timeout_s
        for publisher in (self._labels_pub, self._color_pub, self._stats_pub, *self._debug_pubs.values()):
            remaining = max(deadline - time.monotonic(), 0.0)
            try:
                publisher.wait_for_all_acked(Duration(nanoseconds=round(remaining * 1e9)))
            except Exception:  # best effort: the context may be going down
                return

    def destroy_node(self) -> None:
        """Stop the worker, then destroy the node."""
        self.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Run the labeler until SIGINT or SIGTERM; return the process exit code (0 stopped, 2 bad parameters)."""
    prepare_ros_environment()
    # Own signal handling (ros/spinning.py): the context must stay up after Ctrl-C so that the worker can
    # publish while stopping.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    logger = get_logger(NODE_NAME)
    node: LabelerNode | None = None
    code = 0
    executor = SingleThreadedExecutor()
    # The handlers stay for the shutdown too: SIGTERM must not cut a flush short, a second Ctrl-C may.
    with stop_on_signals() as stop:
        try:
            node = LabelerNode()
            executor.add_node(node)
            spin_until_stopped(executor, stop)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except (LabelerConfigError, ParameterException) as exc:
            logger.error(f"invalid parameters: {exc}")
            code = 2
        finally:
            if node is not None:
                executor.remove_node(node)
                node.destroy_node()
            executor.shutdown()
            rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
