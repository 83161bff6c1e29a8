"""Stereo frames and label images of rosbag2 bags, for ``selfcontra train`` and ``evaluate-confidence``.

A **data bag** (``--data``) gives the stereo pairs under its namespace ``NS``
(chosen as :func:`~selfcontra_ros.bags.label_bag.resolve_namespace` does):
``NS/left/image_rect`` and ``NS/right/image_rect`` (``mono8``, ``rgb8``;
``bgr8`` is reordered to RGB) paired by equal header stamp,
``NS/left/camera_info`` and ``NS/right/camera_info`` (the first valid pair
fixes the camera; frames of another size are skipped), and, when present,
``NS/ground_truth/disparity`` matched to the left image by header stamp.
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
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.label_bag import resolve_namespace
from selfcontra_ros.bags.reader import BagError, is_bag, open_bag
from selfcontra_ros.bags.sync import StampSynchronizer
from selfcontra_ros.datasets.kitti import StereoFrame
from selfcontra_ros.errors import CalibrationError, ConversionError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.ros.conversions import (
    disparity_from_message,
    image_to_numpy,
    stamp_to_nanoseconds,
    stereo_camera_from_camera_infos,
)

__all__ = ["BagFrame", "BagLabels", "is_bag", "iter_bag_frames", "read_bag_labels"]

_LOG = logging.getLogger(__name__)
_NS_PER_S = 1_000_000_000
#: How long (log time) a frame waits for its ground truth after its stamp, nanoseconds; as label_bag's pose wait.
_GT_WAIT_NS = _NS_PER_S // 2
_ENCODINGS = ("mono8", "rgb8", "bgr8")


@dataclass
class BagFrame(StereoFrame):
    """A :class:`StereoFrame` of a bag, with the left image's header stamp in integer nanoseconds.

    ``stamp`` (seconds) is the same stamp as a float; labels are matched on ``stamp_ns``.
    """

    stamp_ns: int


def _pixels(msg: Any, topic: str, bag: Path) -> NDArray[np.uint8]:
    encoding = str(msg.encoding)
    if encoding not in _ENCODINGS:
        raise BagError(f"bag {bag}: {topic} has encoding {encoding!r}; expected one of {', '.join(_ENCODINGS)}")
    try:
        pixels = image_to_numpy(msg)
    except ConversionError as exc:
        raise BagError(f"bag {bag}: an image on {topic} is malformed: {exc}") from exc
    return np.ascontiguousarray(pixels[:, :, ::-1]) if encoding == "bgr8" else pixels


class _FrameReader:
    """Pairs the stereo images of one bag and attaches camera checks and ground truth."""

    def __init__(self, path: Path, namespace: str, has_gt: bool) -> None:
        self.path = path
        self.topic = {name: topics.bag_topic(name, namespace) for name in topics.INPUT_TOPICS}
        self.has_gt = has_gt
        self.sync = StampSynchronizer(("left", "right"), mode="exact")
        self.infos: dict[str, Any] = {}
        self.camera: StereoCamera | None = None
        self.pending: list[tuple[int, int, Any, Any]] = []  # (index, stamp_ns, left msg, right msg)
        self.ground_truth: dict[int, Any] = {}
        self.synchronised = 0
        self.skipped: dict[str, int] = {}

    def push(self, topic: str, msg: Any) -> None:
        t = self.topic
        if topic in (t[topics.LEFT_IMAGE], t[topics.RIGHT_IMAGE]):
            key = "left" if topic == t[topics.LEFT_IMAGE] else "right"
            for match in self.sync.push(key, stamp_to_nanoseconds(msg.header.stamp), msg).matches:
                self.pending.append((self.synchronised, match.stamp_ns, *match.items))
                self.synchronised += 1
        elif topic in (t[topics.LEFT_INFO], t[topics.RIGHT_INFO]):
            self.infos["left" if topic == t[topics.LEFT_INFO] else "right"] = msg
            if self.camera is None and len(self.infos) == 2:
                try:
                    self.camera = stereo_camera_from_camera_infos(self.infos["left"], self.infos["right"])
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
        left = _pixels(left_msg, self.topic[topics.LEFT_IMAGE], self.path)
        right = _pixels(right_msg, self.topic[topics.RIGHT_IMAGE], self.path)
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


def iter_bag_frames(path: Path | str, *, namespace: str | None = None) -> Iterator[BagFrame]:
    """The stereo frames of a bag in stamp order (see the module docstring); images uint8, HxW or HxWx3 RGB.

    Args:
        path: rosbag2 folder or ``.mcap`` file.
        namespace: namespace of the stereo topics; chosen from the bag when None.

    Raises:
        BagError: the bag cannot be read, lacks an image or camera_info topic,
            holds images of an unsupported encoding, or yields no frame.
    """
    path = Path(path)
    with open_bag(path) as bag:
        ns = resolve_namespace(list(bag.topics), namespace)
        needed = (topics.LEFT_IMAGE, topics.RIGHT_IMAGE, topics.LEFT_INFO, topics.RIGHT_INFO)
        for name in needed:
            topic = topics.bag_topic(name, ns)
            if topic not in bag.topics:
                raise BagError(
                    f"bag {path} has no topic {topic} ({topics.INPUT_TOPICS[name]}); it holds no stereo frames"
                )
        gt_topic = topics.bag_topic(topics.GT_DISPARITY, ns)
        has_gt = gt_topic in bag.topics
        reader = _FrameReader(path, ns, has_gt)
        wanted = [topics.bag_topic(n, ns) for n in needed] + ([gt_topic] if has_gt else [])
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
        detail = ", ".join(f"{k}: {v}" for k, v in sorted(reader.skipped.items())) or "no stereo pair had equal stamps"
        raise BagError(f"bag {path} gave no stereo frame ({reader.synchronised} pairs synchronised; {detail})")


@dataclass
class BagLabels:
    """The label images of a labelled bag, keyed by the stamp of the left image they label.

    Attributes:
        path: the bag.
        images: stamp (ns) -> PNG-encoded mono8 label image (PNG keeps a long bag's labels small in memory).
        matcher: the query algorithm's parameters from the bag's ``metrics.json``, or None without them.
    """

    path: Path
    images: dict[int, bytes]
    matcher: MatcherParams | None

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
        ns = resolve_namespace(list(bag.topics), namespace)
        topic = topics.bag_topic(topics.LABELS, ns)
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
    matcher = None
    metrics = path / "metrics.json"  # label-bag writes it inside the bag folder; a bare .mcap has none
    if path.is_dir() and metrics.is_file():
        try:
            params = json.loads(metrics.read_text()).get("params", {}).get("matcher")
        except (OSError, ValueError, AttributeError) as exc:
            raise BagError(f"metrics file {metrics} of bag {path} is unreadable: {exc}") from exc
        if isinstance(params, dict):
            matcher = MatcherParams(**params)
    return BagLabels(path=path, images=images, matcher=matcher)
