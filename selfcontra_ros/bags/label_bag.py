"""Offline labeling of a rosbag2 bag: the labeler node's work without DDS.

:func:`label_bag` reads a stereo bag (MCAP or SQLite), runs the same
:class:`~selfcontra_ros.session.LabelingSession` as the ROS labeler node and
the sequence labeler, and writes a new MCAP bag that opens in Foxglove.

**Inputs** (names of :mod:`selfcontra_ros.bags.topics` under a namespace ``NS``):
``NS/left/image_rect`` and ``NS/right/image_rect`` (``mono8``, ``rgb8`` or
``bgr8``), ``NS/left/camera_info`` and ``NS/right/camera_info``, and the pose
of the left camera ``T_world_left`` on ``NS/pose`` as
``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry`` (another topic with
``pose_topic``; an Odometry's child frame must be the left camera). Optional:
``NS/ground_truth/disparity`` (``stereo_msgs/DisparityImage``), which turns on
the label metrics, and an external disparity topic (``disparity_topic``) when
the parameter file sets ``matcher.algorithm: external``.

**Choosing the namespace.** ``namespace`` when given; else ``/stereo``
(:data:`~selfcontra_ros.bags.topics.STEREO_NAMESPACE`, what the package's own
bags use) if the bag has ``/stereo/left/image_rect``; else the prefix of the
one topic ending in ``/left/image_rect``. Several candidates: pass ``namespace``.

**Synchronisation.** Left and right images (and the external disparity) are
paired by header stamp with :class:`~selfcontra_ros.bags.sync.StampSynchronizer`
(``sync="exact"``, or ``"approximate"`` within ``slop`` seconds); the frame's
stamp is the left image's. The pose comes from
:class:`~selfcontra_ros.bags.sync.PoseBuffer`, interpolated at that stamp. A
frame waits (in memory) until the bag has moved past its stamp and a pose at
or after it arrived, or ``max_pose_gap`` seconds passed without one, so poses
and ground truth logged a little after the images are still used. Frames are
numbered in the order they are synchronised: frame ``N`` of a bag written by
:func:`~selfcontra_ros.bags.kitti2mcap.kitti_to_mcap` is frame ``N`` of the
sequence.

**Output bag** (rosbag2 folder, MCAP storage, zstd): every input message,
copied bit-exact with its log time, plus under ``NS`` what the node publishes:

=====================  ============================  =========================================================
topic                  type                          content, header (stamp, frame id); log time = stamp
=====================  ============================  =========================================================
``NS/labels``          sensor_msgs/Image ``mono8``   0 unknown / 1 positive / 2 negative; the *labelled* view's
                                                     stamp (``label_delay`` frames back) and left frame id
``NS/labels/color``    sensor_msgs/Image ``rgb8``    green / red / blue; as ``labels``
``NS/depth``           sensor_msgs/Image ``32FC1``   depth, metres, NaN invalid (REP 118); the frame's stamp
``NS/disparity``       stereo_msgs/DisparityImage    query disparity (stereo_image_proc conventions); as ``depth``
``NS/confidence``      sensor_msgs/Image ``32FC1``   confidence in [0, 1] (LRD until the first forest); as ``depth``
``NS/depth/filtered``  sensor_msgs/Image ``32FC1``   depth, NaN where confidence < threshold; as ``depth``
=====================  ============================  =========================================================

**Confidence** is the node's online confidence
(:class:`~selfcontra_ros.confidence.online.OnlineConfidence`, section
``confidence`` of the parameter file), run in the bag labeler's own thread so
that a run is reproducible: each frame gets the confidence of the model
current when it is matched; the labelled views fill the reservoir and the
forest is retrained every ``retrain_every`` labelled views. ``model_out``
(argument, else the file's ``confidence.model_out``) receives the last
model, so a bag run yields a trained model. Not in external mode (no images).

**Metrics** are written to ``<out_bag>/metrics.json`` (inside the bag folder,
so one path holds a run's whole output; rosbag2 tools ignore the extra file),
with the schema of :func:`selfcontra_ros.pipeline.label_sequence` (frames
keyed by their index in the bag; label metrics with ground truth, label
shares without) plus ``output``, ``namespace``, ``status``
(``complete`` / ``interrupted`` / ``failed``), ``dropped`` (reason -> count),
``dropped_frames``, ``sync`` (synchroniser counters), ``confidence_params``,
``confidence`` (:meth:`OnlineConfidence.stats`: source, samples, models trained)
and ``recovered`` (:attr:`~selfcontra_ros.bags.reader.Bag.recovery`: what a
truncated input, or one without ``metadata.yaml``, still held; None when intact).

**Failures.** A missing or corrupt input bag, or a truncated one without a
complete message, raises :class:`~selfcontra_ros.bags.reader.BagError` (a
truncated bag is labelled up to its last complete chunk, see
:func:`~selfcontra_ros.bags.reader.open_bag`); an existing output is never
overwritten. Bad messages (undecodable, unsupported encoding, size not
matching the camera info, NaN or non-rigid pose, stamps going backwards, ...)
are counted in ``dropped`` and skipped with one warning per reason. Ctrl-C
(``KeyboardInterrupt``; under the ``selfcontra`` command, SIGINT and SIGTERM
stop between two messages, see :mod:`selfcontra_ros.interrupts`) or an error
part way closes the output bag properly: it stays readable and indexed with
everything written so far, and ``metrics.json`` records the ``status``; the
exception is then re-raised.

Like :func:`~selfcontra_ros.pipeline.label_sequence`, :func:`label_bag` is a
pure function of its arguments (DESIGN section 9): it reads ``in_bag`` and the
parameter file and writes only ``out_bag``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray
from rosbags.typesys.store import Typestore
from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.bags import topics
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.reader import Bag, BagError, open_bag
from selfcontra_ros.bags.stereo_input import (
    CUSTOM_DATA_KEY,
    IMAGE_ENCODINGS,
    NAMESPACE_KEY,
    SYNC_KEY,
    ImageError,
    StereoImages,
    StereoInput,
    TFPoses,
    TopicPoses,
)
from selfcontra_ros.bags.sync import StampSynchronizer
from selfcontra_ros.bags.tf import TFBuffer
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.confidence.online import OnlineConfidence
from selfcontra_ros.config import load_confidence_params, load_params, params_to_dict
from selfcontra_ros.errors import CalibrationError, ConversionError, PoseError, SelfContraError
from selfcontra_ros.evaluation.metrics import mean_metrics
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import LabelerParams, LabelResult
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.matching.base import MatcherError, MatcherParams
from selfcontra_ros.reports import METRICS_FILE, PendingView, evaluate_view, write_json
from selfcontra_ros.ros.conversions import (
    disparity_from_message,
    stamp_to_nanoseconds,
)
from selfcontra_ros.session import LabelingSession

__all__ = ["IMAGE_ENCODINGS", "ODOMETRY_TYPE", "POSE_TYPES", "label_bag", "metrics_path", "resolve_namespace"]

_LOG = logging.getLogger(__name__)
_NS_PER_S = 1_000_000_000

ODOMETRY_TYPE = topics.ODOMETRY_TYPE
#: Message types accepted on the pose topic.
POSE_TYPES = topics.POSE_TYPES
#: Output topics (relative) that the input bag must not hold already.
_OUTPUTS = topics.OUTPUT_TOPICS
#: Disparity resolution of OpenCV's block matchers (4 fractional bits), pixels.
_OPENCV_DELTA_D = 1.0 / 16.0

_LEFT, _RIGHT, _EXTERNAL = "left", "right", "disparity"


def metrics_path(out_bag: Path | str) -> Path:
    """Where :func:`label_bag` writes the metrics of ``out_bag``: ``<out_bag>/metrics.json``."""
    return Path(out_bag) / METRICS_FILE


def resolve_namespace(topic_names: set[str] | list[str], namespace: str | None = None) -> str:
    """The namespace of a bag's stereo topics (see "Choosing the namespace" in the module docstring).

    Raises:
        BagError: no ``.../left/image_rect`` topic, or several and ``namespace`` not given.
    """
    if namespace is not None:
        return "/" + namespace.strip("/") if namespace.strip("/") else ""
    names = set(topic_names)
    if topics.bag_topic(topics.LEFT_IMAGE) in names:
        return topics.STEREO_NAMESPACE
    suffix = "/" + topics.LEFT_IMAGE
    candidates = sorted(name[: -len(suffix)] for name in names if name.endswith(suffix))
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise BagError(f"the bag has no <namespace>{suffix} topic (topics: {', '.join(sorted(names)) or 'none'})")
    raise BagError(f"the bag has several stereo namespaces {candidates}; choose one with namespace=")


@dataclass
class _Frame:
    """A synchronised stereo frame waiting for its pose (and ground truth)."""

    index: int
    stamp_ns: int
    left: Any
    right: Any
    external: Any | None


class _Messages(MessageBuilder):
    """The output messages; disparities report the built-in matcher's search range, as stereo_image_proc does."""

    def __init__(self, typestore: Typestore, camera_delta_d: float, matcher: MatcherParams) -> None:
        super().__init__(typestore)
        self._delta_d = camera_delta_d
        self._matcher = matcher

    def matcher_disparity(
        self, disparity: NDArray[np.float32], camera: StereoCamera, stamp_ns: int, frame_id: str
    ) -> Any:
        """A DisparityImage with the conventions of :func:`selfcontra_ros.ros.conversions.disparity_image`."""
        if self._matcher.algorithm == "external":
            min_disparity, max_disparity = 0.0, None
        else:
            min_disparity = float(self._matcher.min_disparity)
            max_disparity = self._matcher.max_disparity
        return self.disparity(
            disparity,
            camera,
            stamp_ns,
            frame_id,
            min_disparity=min_disparity,
            max_disparity=max_disparity,
            delta_d=self._delta_d,
        )


class _Drops:
    """Counts skipped messages and frames by reason; warns once per reason."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.frames: list[dict[str, Any]] = []

    def __call__(self, reason: str, detail: str, frame: int | None = None) -> None:
        if not self.counts[reason]:
            _LOG.warning("skipping %s (%s); further ones are only counted", detail, reason)
        self.counts[reason] += 1
        if frame is not None:
            self.frames.append({"frame": frame, "reason": reason})


class _BagLabeler:
    """The state of one :func:`label_bag` run (one input bag, one output bag)."""

    def __init__(
        self,
        bag: Bag,
        writer: BagWriter,
        *,
        namespace: str,
        pose_topic: str,
        disparity_topic: str | None,
        matcher: MatcherParams,
        labeler: LabelerParams,
        sync: StampSynchronizer,
        max_pose_gap: float,
        max_pose_extrapolation: float,
        stereo_input: StereoInput,
        confidence: OnlineConfidence | None = None,
    ) -> None:
        self.bag, self.writer, self.ns = bag, writer, namespace
        self.confidence = confidence
        self.matcher_params, self.labeler_params = matcher, labeler
        self.input = stereo_input
        self.topic = stereo_input.topics(namespace)
        self.left_topic, self.right_topic = self.topic[stereo_input.left_image], self.topic[stereo_input.right_image]
        self.pose_topic, self.disparity_topic = pose_topic, disparity_topic
        self.sync = sync
        self.images = StereoImages(stereo_input)
        self.tf: TFBuffer | None = None
        self.poses: TopicPoses | TFPoses
        if stereo_input.pose_source == "tf":
            assert stereo_input.world_frame is not None  # StereoInput checks it
            self.tf = TFBuffer(max_gap_s=max_pose_gap, max_extrapolation_s=max_pose_extrapolation)
            self.poses = TFPoses(self.tf, stereo_input.world_frame, stereo_input.camera_frame)
        else:
            self.poses = TopicPoses(max_gap_s=max_pose_gap, max_extrapolation_s=max_pose_extrapolation)
        self.pose_wait_ns = round(max_pose_gap * _NS_PER_S)
        self.make = _Messages(writer.typestore, _OPENCV_DELTA_D, matcher)
        self.drop = _Drops()
        self.infos: dict[str, Any] = {}
        self.camera: StereoCamera | None = None
        self.session: LabelingSession | None = None
        self.pending: deque[_Frame] = deque()
        self.ground_truth: dict[int, Any] = {}
        self.frames_synchronised = 0
        self.evaluation: dict[int, PendingView] = {}
        self.view_header: dict[int, tuple[int, str]] = {}
        self.skipped: list[int] = []
        self.results: list[tuple[int, float, dict[str, float]]] = []
        self.messages_read = 0

    # ------------------------------------------------------------------ reading

    def run(self, progress: bool) -> None:
        for name in self.bag.topics.values():
            if name.msgtype not in self.writer.typestore.types:
                raise BagError(
                    f"topic {name.name} of bag {self.bag.path} has type {name.msgtype}, unknown to the "
                    "ROS 2 type store; it cannot be copied"
                )
            self.writer.add_topic(name.name, name.msgtype)
        bar = tqdm(total=self.bag.message_count, desc="label bag", unit="msg", disable=not progress)
        try:
            for raw in self.bag.raw_messages():
                interrupts.check()  # between messages: the output bag stays consistent
                self.writer.write_raw(raw.topic, raw.stamp_ns, raw.data)
                self._dispatch(raw.topic, raw.stamp_ns, raw.data, raw.msgtype)
                self._release(now_ns=raw.stamp_ns)
                self.messages_read += 1
                bar.update()
        finally:
            bar.close()
        self._release(now_ns=None)
        if self.session is not None:
            self._write_labels(self.session.flush())
        for key, count in self.sync.dropped.items():
            if count:
                self.drop.counts[f"unsynchronised_{key}"] += count
        for key, count in self.sync.backwards.items():
            if count:
                self.drop.counts[f"stamp_backwards_{key}"] += count
        if isinstance(self.poses, TopicPoses) and self.poses.buffer.out_of_order:
            self.drop.counts["pose_out_of_order"] += self.poses.buffer.out_of_order
        if self.tf is not None:
            for reason, count in self.tf.refused.items():
                self.drop.counts[f"tf_{reason}"] += count

    def _decode(self, data: bytes, msgtype: str, topic: str) -> Any | None:
        try:
            return self.bag.deserialize(data, msgtype, topic=topic)
        except BagError as exc:
            self.drop("undecodable_message", str(exc))
            return None

    def _dispatch(self, topic: str, log_ns: int, data: bytes, msgtype: str) -> None:
        t = self.topic
        if topic in (self.left_topic, self.right_topic) or topic == self.disparity_topic:
            msg = self._decode(data, msgtype, topic)
            if msg is None:
                return
            key = _LEFT if topic == self.left_topic else _RIGHT if topic == self.right_topic else _EXTERNAL
            if key in self.sync.keys:
                self._synchronise(key, msg)
        elif topic in (t[topics.LEFT_INFO], t[topics.RIGHT_INFO]):
            msg = self._decode(data, msgtype, topic)
            if msg is not None:
                self._camera_info("left" if topic == t[topics.LEFT_INFO] else "right", msg)
        elif self.tf is not None and topic in (t["tf"], t["tf_static"]):
            msg = self._decode(data, msgtype, topic)
            if msg is not None:
                for problem in self.tf.add_message(msg, static=topic == t["tf_static"]):
                    self.drop("bad_transform", f"{topic} at log time {log_ns} ns: {problem}")
        elif isinstance(self.poses, TopicPoses) and topic == self.pose_topic:
            msg = self._decode(data, msgtype, topic)
            if msg is None:
                return
            try:
                self.poses.buffer.add_message(msg)
            except PoseError as exc:
                self.drop("bad_pose", f"a pose message on {topic} at log time {log_ns} ns: {exc}")
        elif topic == t[topics.GT_DISPARITY]:
            msg = self._decode(data, msgtype, topic)
            if msg is not None:
                self.ground_truth[stamp_to_nanoseconds(msg.header.stamp)] = msg

    def _synchronise(self, key: str, msg: Any) -> None:
        stamp_ns = stamp_to_nanoseconds(msg.header.stamp)
        result = self.sync.push(key, stamp_ns, msg)
        if not result.accepted:
            _LOG.debug("%s message at %d ns: stamp not newer than the previous one, dropped", key, stamp_ns)
        for match in result.matches:
            items = dict(zip(self.sync.keys, match.items, strict=True))
            frame = _Frame(self.frames_synchronised, match.stamp_ns, items[_LEFT], items[_RIGHT], items.get(_EXTERNAL))
            self.frames_synchronised += 1
            self.pending.append(frame)

    def _camera_info(self, side: str, msg: Any) -> None:
        """Keep the first valid calibration: the session, the rectification maps and the TF correction stay its own."""
        self.infos[side] = msg
        if len(self.infos) < 2:
            return
        try:
            if self.camera is not None:
                if not self.images.same_calibration(self.infos["left"], self.infos["right"]):
                    # The session's window holds views of the first calibration; a new one would mix cameras.
                    self.drop("camera_info_changed", f"a {side} camera_info differing from the first calibration")
                return
            camera = self.images.camera_from_infos(self.infos["left"], self.infos["right"])
        except CalibrationError as exc:
            self.drop("bad_camera_info", f"a {side} camera_info: {exc}")
            del self.infos[side]
            return
        self.camera = camera
        self.session = LabelingSession(camera, self.matcher_params, self.labeler_params, self.confidence)
        if isinstance(self.poses, TFPoses):
            self.poses.set_camera(str(self.infos["left"].header.frame_id), self.images.raw_from_rectified)

    # ------------------------------------------------------------------ processing

    def _release(self, now_ns: int | None) -> None:
        """Process waiting frames whose pose can be decided (all of them at the end of the bag)."""
        while self.pending:
            frame = self.pending[0]
            if now_ns is not None:
                if now_ns <= frame.stamp_ns:
                    break  # messages logged at the frame's own time (pose, ground truth) may follow
                newest = self.poses.newest_ns
                if (newest is None or newest < frame.stamp_ns) and now_ns <= frame.stamp_ns + self.pose_wait_ns:
                    break
            self.pending.popleft()
            self._process(frame)
            self.poses.discard_before(frame.stamp_ns)
            for stamp in [s for s in self.ground_truth if s <= frame.stamp_ns]:
                del self.ground_truth[stamp]

    def _image(self, msg: Any, side: str, index: int) -> NDArray[np.uint8] | None:
        try:
            return self.images.pixels(msg, side)
        except ImageError as exc:
            self.drop(exc.reason, f"frame {index}: {exc}", index)
            return None

    def _process(self, frame: _Frame) -> None:
        index = frame.index
        if self.session is None or self.camera is None:
            self.drop("no_camera_info", f"frame {index}: no valid camera_info pair yet", index)
            return
        camera = self.camera
        left = self._image(frame.left, "left", index)
        right = self._image(frame.right, "right", index) if left is not None else None
        if left is None or right is None:
            return
        if left.shape != right.shape:
            self.drop(
                "image_mismatch", f"frame {index}: left {left.shape} and right {right.shape} images differ", index
            )
            return
        if left.shape[:2] != (camera.height, camera.width):
            self.drop(
                "size_mismatch",
                f"frame {index}: images are {left.shape[1]}x{left.shape[0]}, "
                f"the camera_info {camera.width}x{camera.height}",
                index,
            )
            return
        lookup = self.poses.pose_at(frame.stamp_ns)
        if lookup.pose is None:
            reason = lookup.reason or "no_pose"
            self.drop(reason, f"frame {index}: no pose at its stamp {frame.stamp_ns} ns: {lookup.detail}", index)
            return
        external = None
        if frame.external is not None:
            try:
                external, _, _ = disparity_from_message(frame.external)
            except ConversionError as exc:
                self.drop("bad_external_disparity", f"frame {index}: {exc}", index)
                return
        gt = None
        gt_msg = self.ground_truth.get(frame.stamp_ns)
        if gt_msg is not None:
            try:
                gt, _, _ = disparity_from_message(gt_msg)
            except ConversionError as exc:
                self.drop("bad_ground_truth", f"frame {index}: ground truth: {exc}")
            if gt is not None and gt.shape != left.shape[:2]:
                self.drop("bad_ground_truth", f"frame {index}: ground truth size {gt.shape} differs from the images")
                gt = None
        stamp_s = frame.stamp_ns / _NS_PER_S
        try:
            output = self.session.process(
                left, right, lookup.pose, stamp=stamp_s, key=index, external_disparity=external
            )
        except MatcherError as exc:
            self.drop("matcher_error", f"frame {index}: {exc}", index)
            return
        frame_id = str(frame.left.header.frame_id)
        self._write_frame(output.depth, output.disparity, camera, frame.stamp_ns, frame_id)
        if output.confidence is not None and output.depth_filtered is not None:
            stamp = frame.stamp_ns
            self.writer.write(
                self.topic[topics.CONFIDENCE], stamp, self.make.image(output.confidence, "32FC1", stamp, frame_id)
            )
            self.writer.write(
                self.topic[topics.DEPTH_FILTERED],
                stamp,
                self.make.image(output.depth_filtered, "32FC1", stamp, frame_id),
            )
        if output.skipped:
            self.skipped.append(index)
        else:
            self.evaluation[index] = PendingView(disparity=output.disparity, gt_disparity=gt)
            self.view_header[index] = (frame.stamp_ns, frame_id)
        self._write_labels(output.labelled)

    def _write_frame(
        self, depth: NDArray[np.float32], disparity: NDArray[np.float32], camera: StereoCamera, stamp: int, fid: str
    ) -> None:
        self.writer.write(self.topic[topics.DEPTH], stamp, self.make.image(depth, "32FC1", stamp, fid))
        if self.disparity_topic != self.topic[topics.DISPARITY]:  # else the input already holds it
            self.writer.write(
                self.topic[topics.DISPARITY], stamp, self.make.matcher_disparity(disparity, camera, stamp, fid)
            )

    def _write_labels(self, results: list[LabelResult]) -> None:
        for result in results:
            index = cast(int, result.key)  # _process passes the frame index as the key
            stamp, fid = self.view_header.pop(index)
            labels = np.ascontiguousarray(result.labels, dtype=np.uint8)
            self.writer.write(self.topic[topics.LABELS], stamp, self.make.image(labels, "mono8", stamp, fid))
            colour = self.make.image(colorize_labels(labels), "rgb8", stamp, fid)
            self.writer.write(self.topic[topics.LABELS_COLOR], stamp, colour)
            self.results.append((index, stamp / _NS_PER_S, evaluate_view(result, self.evaluation.pop(index))))


def _pose_topic(bag: Bag, topic_map: dict[str, str], pose_topic: str | None) -> str:
    name = pose_topic if pose_topic is not None else topic_map[topics.POSE]
    summary = bag.topics.get(name)
    if summary is None:
        raise BagError(
            f"bag {bag.path} has no pose topic {name}; the labeler needs the left camera's pose "
            f"({' or '.join(POSE_TYPES)}); choose another with pose_topic=, or read TF "
            "(pose_source tf with a world frame)"
        )
    if summary.msgtype not in POSE_TYPES:
        raise BagError(
            f"pose topic {name} of bag {bag.path} carries {summary.msgtype}; expected {' or '.join(POSE_TYPES)}"
        )
    return name


def _check_topics(bag: Bag, stereo_input: StereoInput, topic_map: dict[str, str], disparity_topic: str | None) -> None:
    required = {
        stereo_input.left_image: stereo_input.image_type,
        stereo_input.right_image: stereo_input.image_type,
        topics.LEFT_INFO: topics.CAMERA_INFO_TYPE,
        topics.RIGHT_INFO: topics.CAMERA_INFO_TYPE,
    }
    if stereo_input.pose_source == "tf":
        required["tf"] = topics.TF_TYPE
    for name, msgtype in required.items():
        topic = topic_map[name]
        summary = bag.topics.get(topic)
        if summary is None:
            hint = ""
            if name == "tf" and topic_map["tf_static"] in bag.topics:
                hint = " (it has only static transforms: a moving camera needs /tf)"
            elif name in (stereo_input.left_image, stereo_input.right_image):
                other = topic + topics.COMPRESSED_SUFFIX
                if other in bag.topics:
                    hint = f" (it has {other}: use image_transport compressed)"
            raise BagError(f"bag {bag.path} has no topic {topic} ({msgtype}), which the labeler needs{hint}")
        if summary.msgtype != msgtype:
            raise BagError(f"topic {topic} of bag {bag.path} carries {summary.msgtype}; expected {msgtype}")
    if disparity_topic is not None:
        summary = bag.topics.get(disparity_topic)
        if summary is None or summary.msgtype != topics.DISPARITY_TYPE:
            raise BagError(f"bag {bag.path} has no {topics.DISPARITY_TYPE} topic {disparity_topic} (disparity_topic)")
    clashes = [topic_map[n] for n in _OUTPUTS if topic_map[n] in bag.topics]
    clashes = [c for c in clashes if c != disparity_topic]
    if clashes:
        raise BagError(
            f"bag {bag.path} already holds the labeler's output topic(s) {', '.join(clashes)}; "
            "label the original bag instead"
        )


def label_bag(
    in_bag: Path | str,
    out_bag: Path | str,
    *,
    params_file: str | Path | None = None,
    sync: str = "exact",
    slop: float = 0.0,
    progress: bool = True,
    namespace: str | None = None,
    pose_topic: str | None = None,
    disparity_topic: str | None = None,
    queue_size: int = 10,
    max_pose_gap: float = 0.5,
    max_pose_extrapolation: float = 0.05,
    model_out: str | Path | None = None,
    stereo_input: StereoInput | None = None,
) -> dict[str, Any]:
    """Label a stereo bag and write the labels, depth and disparity into a new MCAP bag (module docstring).

    Args:
        in_bag: rosbag2 folder (or ``.mcap`` file) to label.
        out_bag: bag folder to create; must not exist (missing parent folders are created).
        params_file: parameter YAML; ``None`` uses the package's ``config/labeler.yaml``.
        sync: ``"exact"`` (equal header stamps) or ``"approximate"``.
        slop: largest stamp difference of a synchronised set, seconds (``approximate`` only).
        progress: show a progress bar (messages).
        namespace: namespace of the stereo topics; chosen from the bag when None.
        pose_topic: absolute pose topic; ``<namespace>/pose`` when None.
        disparity_topic: absolute ``stereo_msgs/DisparityImage`` topic of an external
            stereo algorithm, needed with ``matcher.algorithm: external`` and only then.
        queue_size: messages queued per synchronised topic.
        max_pose_gap: largest time between the two poses interpolated, seconds.
        max_pose_extrapolation: how far past the newest (or before the oldest) pose an image may be, seconds.
        model_out: confidence model file written after every retraining; None: ``confidence.model_out``.
        stereo_input: topic remaps, image transport, rectification and pose source
            (:class:`~selfcontra_ros.bags.stereo_input.StereoInput`); None: what the bag's ``custom_data``
            records (``selfcontra.input``, e.g. from ``kitti2mcap --compress-images``), else the package's layout.

    Returns:
        The content of ``metrics.json`` (NaN, not ``null``, for undefined figures).

    Raises:
        BagError: the input is missing, truncated, corrupt, lacks a needed topic,
            or already holds output topics; the output exists already.
        SelfContraError: invalid parameters, or an external matcher without ``disparity_topic``.
        KeyboardInterrupt: re-raised after the partial output bag and metrics are written; an
            :class:`~selfcontra_ros.interrupts.Interrupted` (SIGINT, SIGTERM) says how far it got in ``done``.
    """
    started = time.perf_counter()
    in_bag, out_bag = Path(in_bag), Path(out_bag)
    if out_bag.exists() or out_bag.is_symlink():
        raise BagError(f"output bag {out_bag} exists already; remove it or choose another path (not overwriting)")
    matcher_params, labeler_params = load_params(params_file)
    confidence_params = load_confidence_params(params_file)
    if model_out is not None:
        confidence_params = dataclasses.replace(confidence_params, model_out=str(model_out))
    external = matcher_params.algorithm == "external"
    if external and disparity_topic is None:
        raise SelfContraError(
            "matcher.algorithm is 'external': give the external stereo algorithm's DisparityImage topic "
            "(disparity_topic), or use 'sgbm' or 'bm'"
        )
    if disparity_topic is not None and not external:
        raise SelfContraError(f"disparity_topic {disparity_topic} is only read with matcher.algorithm 'external'")
    keys = (_LEFT, _RIGHT, _EXTERNAL) if external else (_LEFT, _RIGHT)
    try:
        synchronizer = StampSynchronizer(keys, mode=sync, slop=slop, queue_size=queue_size)
    except ValueError as exc:
        raise SelfContraError(f"bag synchronisation: {exc}") from exc
    for name, value in (("max_pose_gap", max_pose_gap), ("max_pose_extrapolation", max_pose_extrapolation)):
        if not (math.isfinite(value) and value >= 0):
            raise SelfContraError(f"{name} must be a finite number of seconds >= 0, got {value!r}")

    with open_bag(in_bag) as bag:
        if stereo_input is None:  # as the bag says it is read (kitti2mcap --compress-images), else the package's layout
            stereo_input = StereoInput.of_bag(bag.custom_data)
        if pose_topic is not None and stereo_input.pose_source == "tf":
            raise SelfContraError(f"pose_topic {pose_topic} is read with pose_source 'pose' only, not 'tf'")
        ns = stereo_input.namespace(list(bag.topics), namespace)
        topic_map = stereo_input.topics(ns)
        _check_topics(bag, stereo_input, topic_map, disparity_topic)
        pose_name = _pose_topic(bag, topic_map, pose_topic) if stereo_input.pose_source == "pose" else ""
        out_bag.parent.mkdir(parents=True, exist_ok=True)
        custom = {
            "selfcontra.labelled_from": str(in_bag.resolve()),
            NAMESPACE_KEY: ns,
            CUSTOM_DATA_KEY: stereo_input.to_json(),
            SYNC_KEY: json.dumps({"mode": sync, "slop": slop}),
        }
        status = "failed"
        run: _BagLabeler | None = None
        confidence = (
            None
            if external
            else OnlineConfidence(confidence_params, background=False, log=_LOG.info, labeler=labeler_params)
        )
        try:
            with BagWriter(out_bag, compress="zstd", custom_data=custom) as writer:
                run = _BagLabeler(
                    bag,
                    writer,
                    namespace=ns,
                    pose_topic=pose_name,
                    disparity_topic=disparity_topic,
                    matcher=matcher_params,
                    labeler=labeler_params,
                    sync=synchronizer,
                    max_pose_gap=max_pose_gap,
                    max_pose_extrapolation=max_pose_extrapolation,
                    stereo_input=stereo_input,
                    confidence=confidence,
                )
                run.run(progress)
            status = "complete"
        except KeyboardInterrupt as exc:
            status = "interrupted"
            if isinstance(exc, interrupts.Interrupted):
                read = run.messages_read if run is not None else 0
                labelled = len(run.results) if run is not None else 0
                exc.done = (
                    f"labelled {labelled} frames from {read} of {bag.message_count} messages; "
                    f"wrote {out_bag} (readable and indexed) and its {METRICS_FILE} (status interrupted)"
                )
            raise
        finally:
            report = _report(in_bag, out_bag, ns, run, synchronizer, status, matcher_params, labeler_params, started)
            # Beside "params", whose schema stays the sequence labeler's.
            report["confidence_params"] = dataclasses.asdict(confidence_params)
            report["confidence"] = confidence.stats() if confidence is not None else None
            report["input"] = json.loads(stereo_input.to_json())
            report["recovered"] = bag.recovery  # what a damaged input still held (Bag.recovery), None if intact
            if out_bag.is_dir():
                write_json(metrics_path(out_bag), report)
    return report


def _report(
    in_bag: Path,
    out_bag: Path,
    namespace: str,
    run: _BagLabeler | None,
    synchronizer: StampSynchronizer,
    status: str,
    matcher: MatcherParams,
    labeler: LabelerParams,
    started: float,
) -> dict[str, Any]:
    per_frame = sorted(run.results if run is not None else [], key=lambda item: item[0])
    return {
        "sequence": str(in_bag),
        "output": str(out_bag),
        "namespace": namespace,
        "status": status,
        "frames": [{"frame": index, "stamp": stamp, **figures} for index, stamp, figures in per_frame],
        "mean": mean_metrics(figures for _, _, figures in per_frame),
        "params": params_to_dict(matcher, labeler),
        "skipped_frames": list(run.skipped) if run is not None else [],
        "has_ground_truth": any("accuracy" in figures for _, _, figures in per_frame),
        "frames_synchronised": run.frames_synchronised if run is not None else 0,
        "dropped": dict(sorted(run.drop.counts.items())) if run is not None else {},
        "dropped_frames": run.drop.frames if run is not None else [],
        "sync": {
            "mode": synchronizer.mode,
            "slop_s": synchronizer.slop_ns / _NS_PER_S,
            "matched": synchronizer.matched,
            "dropped": {str(k): v for k, v in synchronizer.dropped.items()},
            "backwards": {str(k): v for k, v in synchronizer.backwards.items()},
        },
        "runtime_s": time.perf_counter() - started,
    }
