"""Stereo frames and label images of rosbag2 bags, for ``selfcontra train`` and ``evaluate-confidence``.

A **data bag** (``--data``) gives the stereo pairs under its namespace ``NS``
(chosen as :meth:`~selfcontra_ros.bags.stereo_input.StereoInput.namespace` does):
``NS/left/image_rect`` and ``NS/right/image_rect`` (``mono8``, ``rgb8``;
``bgr8`` is reordered to RGB) paired by header stamp,
``NS/left/camera_info`` and ``NS/right/camera_info`` (the first valid pair
fixes the camera; frames of another size are skipped), and, when present,
``NS/ground_truth/disparity`` matched to the left image by header stamp.
A :class:`~selfcontra_ros.bags.stereo_input.StereoInput` (``stereo_input=``)
reads a robot's own layout: remapped topic names, compressed images,
``image_raw`` rectified with its camera infos. A bag written by
``selfcontra label BAG`` records how its input was read (and its
synchronisation) in ``metadata.yaml``; without ``stereo_input`` that record
is used, so the labelled bag of a robot's recording is read as it was
labelled. Undecodable images (bad encoding, corrupt compressed data) are
skipped and counted, as the bag labeler does.
Frames are numbered in synchronisation order, as
:func:`~selfcontra_ros.bags.label_bag.label_bag` numbers them, so frame ``N``
of a bag written by :func:`~selfcontra_ros.bags.kitti2mcap.kitti_to_mcap` is
frame ``N`` of its sequence.

A **labelled bag** (``--labels``, an output of ``selfcontra label-bag``) gives
``NS/labels`` (``mono8``, codes 0/1/2), each stamped with the stamp of the left
image it labels, and ``metrics.json`` in the bag folder naming the query
algorithm's parameters (``params.matcher``). The data bag may be the labelled
bag itself: it holds every input message.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.reader import Bag, BagError, is_bag, open_bag
from selfcontra_ros.bags.stereo_input import NAMESPACE_KEY, SYNC_KEY, ImageError, StereoImages, StereoInput
from selfcontra_ros.bags.sync import StampSynchronizer
from selfcontra_ros.confidence.training import recorded_params
from selfcontra_ros.datasets.kitti import StereoFrame
from selfcontra_ros.errors import CalibrationError, ConversionError, SelfContraError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.ros.conversions import disparity_from_message, image_to_numpy, stamp_to_nanoseconds

__all__ = ["BagFrame", "BagLabels", "is_bag", "iter_bag_frames", "read_bag_labels"]

_LOG = logging.getLogger(__name__)
_NS_PER_S = 1_000_000_000
#: How long (log time) a frame waits for its ground truth after its stamp, nanoseconds; as label_bag's pose wait.
_GT_WAIT_NS = _NS_PER_S // 2


@dataclass
class BagFrame(StereoFrame):
    """A :class:`StereoFrame` of a bag, with the left image's header stamp in integer nanoseconds.

    ``stamp`` (seconds) is the same stamp as a float; labels are matched on ``stamp_ns``.
    """

    stamp_ns: int


def _namespace(bag: Bag, stereo_input: StereoInput, namespace: str | None) -> str:
    """``namespace``, else the one the bag labeler recorded, else found from the left image topic."""
    if namespace is None and NAMESPACE_KEY in bag.custom_data:
        namespace = bag.custom_data[NAMESPACE_KEY]
    return stereo_input.namespace(list(bag.topics), namespace)


def _sync(bag: Bag, slop_s: float | None = None) -> StampSynchronizer:
    """The image pairing: ``slop_s`` (approximate when > 0), else what the bag labeler recorded, else exact.

    The record is custom_data ``selfcontra.sync``: ``{"mode", "slop"}``.

    Raises:
        SelfContraError: a negative or non-finite ``slop_s``.
    """
    if slop_s is not None:
        if not (math.isfinite(slop_s) and slop_s >= 0):
            raise SelfContraError(f"slop must be a finite number of seconds >= 0, got {slop_s!r}")
        return StampSynchronizer(("left", "right"), mode="approximate" if slop_s > 0 else "exact", slop=slop_s)
    mode, slop = "exact", 0.0
    text = bag.custom_data.get(SYNC_KEY)
    if text:
        try:
            stored = json.loads(text)
            mode, slop = str(stored["mode"]), float(stored["slop"])
        except (ValueError, KeyError, TypeError) as exc:
            raise BagError(f"bag {bag.path}: custom_data {SYNC_KEY} {text!r} is unreadable: {exc}") from exc
    return StampSynchronizer(("left", "right"), mode=mode, slop=slop)


class _FrameReader:
    """Pairs the stereo images of one bag and attaches camera checks and ground truth."""

    def __init__(
        self, path: Path, topic: dict[str, str], stereo_input: StereoInput, sync: StampSynchronizer, has_gt: bool
    ) -> None:
        self.path = path
        self.topic = topic
        self.left_topic, self.right_topic = topic[stereo_input.left_image], topic[stereo_input.right_image]
        self.images = StereoImages(stereo_input)
        self.has_gt = has_gt
        self.sync = sync
        self.infos: dict[str, Any] = {}
        self.camera: StereoCamera | None = None
        self.pending: list[tuple[int, int, Any, Any]] = []  # (index, stamp_ns, left msg, right msg)
        self.ground_truth: dict[int, Any] = {}
        self.synchronised = 0
        self.skipped: dict[str, int] = {}

    def push(self, topic: str, msg: Any) -> None:
        t = self.topic
        if topic in (self.left_topic, self.right_topic):
            key = "left" if topic == self.left_topic else "right"
            for match in self.sync.push(key, stamp_to_nanoseconds(msg.header.stamp), msg).matches:
                self.pending.append((self.synchronised, match.stamp_ns, *match.items))
                self.synchronised += 1
        elif topic in (t[topics.LEFT_INFO], t[topics.RIGHT_INFO]):
            self.infos["left" if topic == t[topics.LEFT_INFO] else "right"] = msg
            if self.camera is None and len(self.infos) == 2:
                try:
                    self.camera = self.images.camera_from_infos(self.infos["left"], self.infos["right"])
                except CalibrationError as exc:
                    self._skip("bad_camera_info", f"bag {self.path}: a camera_info pair: {exc}")
        elif topic == t[topics.GT_DISPARITY]:
            self.ground_truth[stamp_to_nanoseconds(msg.header.stamp)] = msg

    def release(self, now_ns: int | None) -> Iterator[BagFrame]:
        """Frames whose ground truth has arrived or can no longer arrive (all of them when ``now_ns`` is None)."""
        while self.pending:
            index, stamp_ns, left_msg, right_msg = self.pending[0]
            waiting = self.has_gt and stamp_ns not in self.ground_truth
            # Messages logged at the frame's own time (infos, ground truth) may still follow.
            if now_ns is not None and (now_ns <= stamp_ns or (waiting and now_ns <= stamp_ns + _GT_WAIT_NS)):
                return
            self.pending.pop(0)
            gt_msg = self.ground_truth.pop(stamp_ns, None)
            for stamp in [s for s in self.ground_truth if s < stamp_ns]:
                del self.ground_truth[stamp]
            frame = self._frame(index, stamp_ns, left_msg, right_msg, gt_msg)
            if frame is not None:
                yield frame

    def _skip(self, reason: str, detail: str) -> None:
        if reason not in self.skipped:
            _LOG.warning("%s; further ones are only counted", detail)
        self.skipped[reason] = self.skipped.get(reason, 0) + 1

    def _frame(self, index: int, stamp_ns: int, left_msg: Any, right_msg: Any, gt_msg: Any | None) -> BagFrame | None:
        if self.camera is None:
            self._skip("no_camera_info", f"bag {self.path}: frame {index} has no valid camera_info pair before it")
            return None
        try:
            left = self.images.pixels(left_msg, "left")
            right = self.images.pixels(right_msg, "right")
        except ImageError as exc:
            self._skip(exc.reason, f"bag {self.path}: frame {index}: {exc}")
            return None
        size = (self.camera.height, self.camera.width)
        if left.shape != right.shape or left.shape[:2] != size:
            self._skip(
                "size_mismatch",
                f"bag {self.path}: frame {index}: images {left.shape} / {right.shape} do not match the "
                f"camera_info size {size[1]}x{size[0]}",
            )
            return None
        gt = None
        if gt_msg is not None:
            try:
                gt, _, _ = disparity_from_message(gt_msg)
            except ConversionError as exc:
                raise BagError(f"bag {self.path}: ground truth of frame {index}: {exc}") from exc
            if gt.shape != size:
                raise BagError(f"bag {self.path}: ground truth of frame {index} is {gt.shape}, the images {size}")
        return BagFrame(
            index=index,
            name=f"{index:06d}",
            stamp=stamp_ns / _NS_PER_S,
            left=left,
            right=right,
            pose=None,
            gt_disparity=gt,
            stamp_ns=stamp_ns,
        )


def iter_bag_frames(
    path: Path | str,
    *,
    namespace: str | None = None,
    stereo_input: StereoInput | None = None,
    slop: float | None = None,
) -> Iterator[BagFrame]:
    """The stereo frames of a bag in stamp order (see the module docstring); images uint8, HxW or HxWx3 RGB.

    Args:
        path: rosbag2 folder or ``.mcap`` file.
        namespace: namespace of the stereo topics; chosen from the bag when None.
        stereo_input: how to read the bag; None: as recorded by the bag labeler, else the package's layout.
        slop: pair left and right images within this many seconds (0: equal stamps); None: as
            recorded by the bag labeler, else equal stamps.

    Raises:
        BagError: the bag cannot be read, lacks an image or camera_info topic, or yields no frame.
    """
    path = Path(path)
    with open_bag(path) as bag:
        read_as = stereo_input if stereo_input is not None else StereoInput.of_bag(bag.custom_data)
        ns = _namespace(bag, read_as, namespace)
        topic = read_as.topics(ns)
        needed = {
            read_as.left_image: read_as.image_type,
            read_as.right_image: read_as.image_type,
            topics.LEFT_INFO: topics.CAMERA_INFO_TYPE,
            topics.RIGHT_INFO: topics.CAMERA_INFO_TYPE,
        }
        for name, msgtype in needed.items():
            if topic[name] not in bag.topics:
                raise BagError(f"bag {path} has no topic {topic[name]} ({msgtype}); it holds no stereo frames")
        gt_topic = topic[topics.GT_DISPARITY]
        has_gt = gt_topic in bag.topics
        reader = _FrameReader(path, topic, read_as, _sync(bag, slop), has_gt)
        wanted = [topic[n] for n in needed] + ([gt_topic] if has_gt else [])
        yielded = 0
        for message in bag.messages(wanted):
            reader.push(message.topic, message.msg)
            for frame in reader.release(message.stamp_ns):
                yielded += 1
                yield frame
        for frame in reader.release(None):
            yielded += 1
            yield frame
    if not yielded:
        detail = ", ".join(f"{k}: {v}" for k, v in sorted(reader.skipped.items())) or (
            f"no stereo pair had {'equal stamps' if reader.sync.mode == 'exact' else 'stamps within the slop'}"
        )
        raise BagError(f"bag {path} gave no stereo frame ({reader.synchronised} pairs synchronised; {detail})")


@dataclass
class BagLabels:
    """The label images of a labelled bag, keyed by the stamp of the left image they label.

    Attributes:
        path: the bag.
        images: stamp (ns) -> PNG-encoded mono8 label image (PNG keeps a long bag's labels small in memory).
        matcher: the query algorithm's parameters from the bag's ``metrics.json``, or None without them.
        labeler: the labeler's fattening band from the same file
            (:func:`~selfcontra_ros.confidence.training.band_labeler`), or None without it.
    """

    path: Path
    images: dict[int, bytes]
    matcher: MatcherParams | None
    labeler: LabelerParams | None = None

    def __contains__(self, stamp_ns: object) -> bool:
        return stamp_ns in self.images

    def at(self, stamp_ns: int) -> NDArray[np.uint8] | None:
        """The HxW label codes (0 unknown, 1 positive, 2 negative) of the view stamped ``stamp_ns``, or None."""
        data = self.images.get(stamp_ns)
        if data is None:
            return None
        return np.asarray(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), dtype=np.uint8)

    def stamp_range(self) -> str:
        """``first..last`` stamps in nanoseconds, for messages."""
        return f"{min(self.images)}..{max(self.images)} ns" if self.images else "none"


def read_bag_labels(path: Path | str, *, namespace: str | None = None) -> BagLabels:
    """Read the label images of a ``selfcontra label-bag`` output bag (see the module docstring).

    Raises:
        BagError: the bag cannot be read, has no labels topic, or a label image
            is not mono8 with codes 0/1/2; ``metrics.json`` is unreadable.
    """
    path = Path(path)
    with open_bag(path) as bag:
        read_as = StereoInput.of_bag(bag.custom_data)
        ns = _namespace(bag, read_as, namespace)
        topic = read_as.topics(ns)[topics.LABELS]
        if topic not in bag.topics:
            raise BagError(
                f"bag {path} has no label topic {topic}; "
                "--labels needs the output bag of 'selfcontra label-bag' (or 'gt')"
            )
        images: dict[int, bytes] = {}
        for message in bag.messages([topic]):
            stamp_ns = stamp_to_nanoseconds(message.msg.header.stamp)
            if str(message.msg.encoding) != "mono8":
                raise BagError(f"bag {path}: {topic} has encoding {message.msg.encoding!r}; expected 'mono8'")
            try:
                codes = image_to_numpy(message.msg)
            except ConversionError as exc:
                raise BagError(f"bag {path}: a label image on {topic} is malformed: {exc}") from exc
            if codes.size and int(codes.max()) > NEGATIVE:
                raise BagError(f"bag {path}: the label image at {stamp_ns} ns holds codes above {NEGATIVE}")
            ok, png = cv2.imencode(".png", codes)
            if not ok:
                raise BagError(f"bag {path}: the label image at {stamp_ns} ns cannot be encoded")
            images[stamp_ns] = png.tobytes()
    matcher = labeler = None
    metrics = path / "metrics.json"  # label-bag writes it inside the bag folder; a bare .mcap has none
    if path.is_dir() and metrics.is_file():
        try:
            matcher, labeler = recorded_params(json.loads(metrics.read_text()).get("params", {}))
        except (OSError, ValueError, AttributeError, SelfContraError) as exc:
            raise BagError(f"metrics file {metrics} of bag {path} is unreadable: {exc}") from exc
    return BagLabels(path=path, images=images, matcher=matcher, labeler=labeler)
