"""How the offline commands read a robot's own stereo bag: topic names, image transport, rectification, poses.

One :class:`StereoInput` describes it, for ``selfcontra label BAG``,
``train``/``evaluate-confidence`` on bags and ``odometry BAG`` alike:

* **Topic names** (:func:`topic_map`): the relative names of
  :mod:`selfcontra_ros.bags.topics` (``left/image_rect``, ``left/camera_info``,
  ``pose``, ...) resolved in a namespace, after ROS-style remaps
  ``FROM:=TO`` (:func:`parse_remaps`; ``TO`` absolute, or relative to the
  namespace), the same rules as a node's ``-r``. ``tf`` and ``tf_static``
  (``/tf``, ``/tf_static``) remap too.
* **Image transport**: ``raw`` (``sensor_msgs/Image``) or ``compressed``
  (``sensor_msgs/CompressedImage`` on ``<image topic>/compressed``, as
  image_transport names it: the remap applies to the base topic).
* **Rectification** (``rectify``): read ``left/image_raw`` and
  ``right/image_raw`` with their distorted camera infos and rectify them
  (:class:`~selfcontra_ros.rectification.Rectifier`) before matching.
* **Poses** (``pose_source``): ``pose`` (``geometry_msgs/PoseStamped`` or
  ``nav_msgs/Odometry`` of the left camera on ``pose``) or ``tf``: the pose of
  ``camera_frame`` (default: the left camera_info's ``header.frame_id``) in
  ``world_frame`` from ``/tf`` and ``/tf_static``
  (:class:`~selfcontra_ros.bags.tf.TFBuffer`); with ``rectify`` the rotation
  ``R_left`` of the calibration is applied, so the pose is the one of the
  *rectified* left view.

:class:`StereoImages` turns messages into the images and camera the labeler
uses; :class:`TopicPoses` and :class:`TFPoses` give the pose at an image
stamp behind one interface (:class:`PoseSource`). None of this imports ROS.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.compressed import decode_compressed_image
from selfcontra_ros.bags.reader import BagError
from selfcontra_ros.bags.sync import PoseBuffer
from selfcontra_ros.bags.tf import TFBuffer, TransformSource, normalize_frame
from selfcontra_ros.errors import ConversionError, SelfContraError, TransformError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.rectification import Rectifier, calibration_key
from selfcontra_ros.ros.conversions import image_to_numpy, stereo_camera_from_camera_infos

__all__ = [
    "CUSTOM_DATA_KEY",
    "IMAGE_ENCODINGS",
    "IMAGE_TRANSPORTS",
    "NAMESPACE_KEY",
    "POSE_SOURCES",
    "REMAPPABLE",
    "SYNC_KEY",
    "ImageError",
    "PoseAt",
    "PoseSource",
    "StereoImages",
    "StereoInput",
    "TFPoses",
    "TopicPoses",
    "parse_remaps",
    "topic_map",
]

#: Accepted ``image_transport`` values.
IMAGE_TRANSPORTS = ("raw", "compressed")
#: Accepted ``pose_source`` values.
POSE_SOURCES = ("pose", "tf")
#: Relative names that remaps may rename (inputs and the labeler's outputs), plus the TF topics.
REMAPPABLE = (
    topics.LEFT_IMAGE,
    topics.RIGHT_IMAGE,
    topics.LEFT_RAW,
    topics.RIGHT_RAW,
    topics.LEFT_INFO,
    topics.RIGHT_INFO,
    topics.POSE,
    topics.GT_DISPARITY,
    *topics.OUTPUT_TOPICS,
    "tf",
    "tf_static",
)
_TF_NAMES = {"tf": topics.TF, "tf_static": topics.TF_STATIC}
#: Raw image encodings read (``bgr8`` is reordered to RGB).
IMAGE_ENCODINGS = topics.IMAGE_ENCODINGS
#: ``metadata.yaml`` custom_data key of the input description in bags written by the bag labeler.
CUSTOM_DATA_KEY = "selfcontra.input"
#: custom_data key of the stereo namespace the bag labeler read.
NAMESPACE_KEY = "selfcontra.namespace"
#: custom_data key of the bag labeler's image pairing, JSON ``{"mode", "slop"}``.
SYNC_KEY = "selfcontra.sync"


def parse_remaps(remaps: Iterable[str]) -> dict[str, str]:
    """``{relative name: target}`` of ``FROM:=TO`` rules (later rules win; ``/tf`` may be written for ``tf``).

    Raises:
        SelfContraError: a rule without ``:=``, an empty side, or a ``FROM`` that is not
            one of :data:`REMAPPABLE`.
    """
    out: dict[str, str] = {}
    for rule in remaps:
        source, sep, target = (part.strip() for part in str(rule).partition(":="))
        if not sep or not source or not target:
            raise SelfContraError(f"remap {rule!r} is not FROM:=TO, e.g. left/image_rect:=/zed/left/image_rect_color")
        name = source.lstrip("/") if source.lstrip("/") in _TF_NAMES else source
        if name not in REMAPPABLE:
            raise SelfContraError(
                f"remap {rule!r}: {source!r} is not a name the package reads or writes; "
                f"expected one of {', '.join(REMAPPABLE)}"
            )
        out[name] = target
    return out


def _resolve(name: str, namespace: str) -> str:
    return name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"


def topic_map(
    namespace: str, remaps: Mapping[str, str] | Iterable[str] = (), *, image_transport: str = "raw"
) -> dict[str, str]:
    """Absolute topic of every name of :data:`REMAPPABLE` (image topics with ``/compressed`` when compressed).

    Args:
        namespace: where relative names (and relative remap targets) live, e.g. ``/stereo``.
        remaps: ``{name: target}`` or ``FROM:=TO`` rules.
        image_transport: ``raw`` or ``compressed``.
    """
    rules = dict(remaps) if isinstance(remaps, Mapping) else parse_remaps(remaps)
    suffix = topics.COMPRESSED_SUFFIX if image_transport == "compressed" else ""
    images = (topics.LEFT_IMAGE, topics.RIGHT_IMAGE, topics.LEFT_RAW, topics.RIGHT_RAW)
    out = {}
    for name in REMAPPABLE:
        default = _TF_NAMES.get(name, name)
        out[name] = _resolve(rules.get(name, default), namespace) + (suffix if name in images else "")
    return out


@dataclass(frozen=True)
class StereoInput:
    """How to read a stereo bag (module docstring); the defaults read the package's own bags.

    Attributes:
        image_transport: ``raw`` or ``compressed``.
        rectify: read ``image_raw`` and rectify it with the camera infos' calibration.
        remaps: ``FROM:=TO`` rules.
        pose_source: ``pose`` (a pose topic) or ``tf``.
        world_frame: the fixed frame of the poses (``pose_source: tf`` only; needed there).
        camera_frame: the left camera's frame in TF; None: the left camera_info's ``header.frame_id``.
    """

    image_transport: str = "raw"
    rectify: bool = False
    remaps: tuple[str, ...] = ()
    pose_source: str = "pose"
    world_frame: str | None = None
    camera_frame: str | None = None
    rules: dict[str, str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.image_transport not in IMAGE_TRANSPORTS:
            raise SelfContraError(
                f"image_transport is {self.image_transport!r}; expected one of {', '.join(IMAGE_TRANSPORTS)}"
            )
        if self.pose_source not in POSE_SOURCES:
            raise SelfContraError(f"pose_source is {self.pose_source!r}; expected one of {', '.join(POSE_SOURCES)}")
        if self.pose_source == "tf" and not (self.world_frame and normalize_frame(self.world_frame)):
            raise SelfContraError("pose_source 'tf' needs world_frame (the fixed frame, e.g. odom or map)")
        if self.pose_source != "tf" and (self.world_frame or self.camera_frame):
            raise SelfContraError("world_frame and camera_frame apply to pose_source 'tf' only")
        object.__setattr__(self, "remaps", tuple(self.remaps))
        object.__setattr__(self, "rules", parse_remaps(self.remaps))

    @property
    def left_image(self) -> str:
        """Relative name of the left image read: ``left/image_raw`` when rectifying, else ``left/image_rect``."""
        return topics.LEFT_RAW if self.rectify else topics.LEFT_IMAGE

    @property
    def right_image(self) -> str:
        """Relative name of the right image read."""
        return topics.RIGHT_RAW if self.rectify else topics.RIGHT_IMAGE

    @property
    def image_type(self) -> str:
        """Message type of the image topics."""
        return topics.COMPRESSED_IMAGE_TYPE if self.image_transport == "compressed" else topics.IMAGE_TYPE

    def topics(self, namespace: str) -> dict[str, str]:
        """:func:`topic_map` of this input in ``namespace``."""
        return topic_map(namespace, self.rules, image_transport=self.image_transport)

    def namespace(self, topic_names: Iterable[str], namespace: str | None = None) -> str:
        """The namespace of a bag's stereo topics: ``namespace`` when given, else found from the left image topic.

        ``/stereo`` (the package's own) if the bag has the left image there; else the
        prefix of the one topic ending in the left image's (remapped) relative name;
        ``/stereo`` when that name is remapped to an absolute topic.

        Raises:
            BagError: no such topic, or several and ``namespace`` not given.
        """
        if namespace is not None:
            return "/" + namespace.strip("/") if namespace.strip("/") else ""
        target = self.rules.get(self.left_image, self.left_image)
        if target.startswith("/"):
            return topics.STEREO_NAMESPACE
        suffix = "/" + target + (topics.COMPRESSED_SUFFIX if self.image_transport == "compressed" else "")
        names = set(topic_names)
        if topics.STEREO_NAMESPACE + suffix in names:
            return topics.STEREO_NAMESPACE
        candidates = sorted(name[: -len(suffix)] for name in names if name.endswith(suffix))
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            hint = (
                "; its images look compressed: try --image-transport compressed"
                if any(n.endswith(suffix + topics.COMPRESSED_SUFFIX) for n in names)
                else ""
            )
            raise BagError(
                f"the bag has no <namespace>{suffix} topic (topics: {', '.join(sorted(names)) or 'none'}){hint}; "
                "name the left image with --remap or the namespace with --namespace "
                "('selfcontra inspect BAG' suggests both)"
            )
        raise BagError(f"the bag has several stereo namespaces {candidates}; choose one with --namespace (namespace=)")

    def to_json(self) -> str:
        """This input as JSON (stored in the bag labeler's output, so that training reads the bag alike)."""
        return json.dumps({k: v for k, v in asdict(self).items() if k != "rules"}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> StereoInput:
        """The inverse of :meth:`to_json`.

        Raises:
            SelfContraError: not such a JSON object.
        """
        try:
            values = json.loads(text)
            return cls(**{**values, "remaps": tuple(values.get("remaps", ()))})
        except (TypeError, ValueError) as exc:
            raise SelfContraError(f"stored stereo input {text!r} is unreadable: {exc}") from exc

    @classmethod
    def of_bag(cls, custom_data: Mapping[str, str]) -> StereoInput:
        """The input stored in a labelled bag's ``custom_data`` (the defaults for other bags)."""
        text = custom_data.get(CUSTOM_DATA_KEY)
        return cls() if not text else cls.from_json(text)

    def with_options(self, **options: Any) -> StereoInput:
        """This input with the given fields replaced (the options a user gave over a bag's stored input).

        ``remaps`` given are added after the stored ones (later rules win). A
        ``pose_source`` other than ``tf`` clears the stored ``world_frame`` and
        ``camera_frame`` unless they are given too.

        Raises:
            SelfContraError: an unknown field, or a combination :class:`StereoInput` refuses.
        """
        unknown = sorted(set(options) - {f for f in self.__dataclass_fields__ if f != "rules"})
        if unknown:
            raise SelfContraError(f"stereo input options {unknown} do not exist")
        values = {k: v for k, v in asdict(self).items() if k != "rules"}
        if "remaps" in options:
            options["remaps"] = (*self.remaps, *options["remaps"])
        if options.get("pose_source", self.pose_source) != "tf":
            values.update(world_frame=None, camera_frame=None)
        return StereoInput(**{**values, **options, "remaps": tuple(options.get("remaps", self.remaps))})


class ImageError(ConversionError):
    """An image message that cannot be used; ``reason`` is the drop counter's key."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class StereoImages:
    """Camera and images of a stereo bag as the labeler needs them: decoded, RGB or grey, rectified when asked.

    Args:
        stereo_input: how the bag is read.
    """

    def __init__(self, stereo_input: StereoInput) -> None:
        self.input = stereo_input
        self.rectifier: Rectifier | None = None
        self.camera: StereoCamera | None = None

    @property
    def raw_from_rectified(self) -> NDArray[np.float64]:
        """``T_rawleft_rectleft`` (identity without rectification): the pose correction for TF poses."""
        return self.rectifier.raw_from_rectified if self.rectifier is not None else np.eye(4)

    def camera_from_infos(self, left_info: Any, right_info: Any) -> StereoCamera:
        """The (rectified) stereo camera of a camera_info pair; the rectification maps are built once per calibration.

        A pair with the calibration in use (:meth:`same_calibration`) returns the
        current camera without building anything; another calibration replaces it.

        Raises:
            CalibrationError: the infos do not describe a (rectifiable) pair.
        """
        if self.input.rectify:
            if self.rectifier is None or not self.same_calibration(left_info, right_info):
                self.rectifier = Rectifier.from_camera_infos(left_info, right_info)
            camera = self.rectifier.camera
        else:
            # A D left non-zero on image_rect topics is ignored, as stereo_image_proc's consumers do: P describes them.
            camera = stereo_camera_from_camera_infos(left_info, right_info)
        self.camera = camera
        return camera

    def same_calibration(self, left_info: Any, right_info: Any) -> bool:
        """Whether a camera_info pair describes the calibration in use (nothing is built or replaced).

        With ``rectify`` the whole calibration counts (:func:`~selfcontra_ros.rectification.calibration_key`:
        size, D, K, R, P); without, the rectified camera of the two ``P``.

        Raises:
            CalibrationError: without ``rectify``, infos that describe no rectified pair.
        """
        if self.input.rectify:
            key = (calibration_key(left_info), calibration_key(right_info))
            return self.rectifier is not None and key == self.rectifier.key
        return self.camera is not None and stereo_camera_from_camera_infos(left_info, right_info) == self.camera

    def pixels(self, msg: Any, side: str) -> NDArray[np.uint8]:
        """The image of one message: uint8 HxW (grey) or HxWx3 RGB, rectified with ``rectify``.

        Raises:
            ImageError: reasons ``bad_encoding``, ``bad_image``, ``bad_compressed_image``,
                ``no_camera_info`` (rectification before a calibration), ``size_mismatch``.
        """
        if self.input.image_transport == "compressed":
            try:
                pixels, _ = decode_compressed_image(msg)
            except ConversionError as exc:
                raise ImageError(f"{side} image: {exc}", "bad_compressed_image") from exc
        else:
            encoding = str(msg.encoding)
            if encoding not in IMAGE_ENCODINGS:
                raise ImageError(
                    f"{side} image encoding {encoding!r} (expected {', '.join(IMAGE_ENCODINGS)})", "bad_encoding"
                )
            try:
                pixels = image_to_numpy(msg)
            except ConversionError as exc:
                raise ImageError(f"{side} image: {exc}", "bad_image") from exc
            if encoding == "bgr8":
                pixels = np.ascontiguousarray(pixels[:, :, ::-1])
        if self.input.rectify:
            if self.rectifier is None:
                raise ImageError(f"{side} image before a valid camera_info pair", "no_camera_info")
            try:
                pixels = self.rectifier.rectify(pixels, right=side == "right")
            except ConversionError as exc:
                raise ImageError(str(exc), "size_mismatch") from exc
        return pixels


# --------------------------------------------------------------------------- poses


class PoseAt(NamedTuple):
    """The pose at a stamp, or why there is none (``reason``: a drop counter's key; ``detail``: for the log)."""

    pose: NDArray[np.float64] | None
    reason: str | None = None
    detail: str = ""


class PoseSource(Protocol):
    """The pose ``T_world_left`` (rectified left view) at an image stamp, from whatever the bag provides."""

    @property
    def newest_ns(self) -> int | None:
        """The newest stamp the source can answer for without extrapolating (None: nothing yet)."""
        ...

    def pose_at(self, stamp_ns: int) -> PoseAt:
        """The pose at ``stamp_ns`` or the reason for none."""
        ...

    def discard_before(self, stamp_ns: int) -> None:
        """Forget what stamps before ``stamp_ns`` need."""
        ...


class TopicPoses:
    """:class:`PoseSource` of a PoseStamped / Odometry topic (a :class:`~selfcontra_ros.bags.sync.PoseBuffer`)."""

    def __init__(self, *, max_gap_s: float = 0.5, max_extrapolation_s: float = 0.05) -> None:
        self.buffer = PoseBuffer()
        self.max_gap_s, self.max_extrapolation_s = max_gap_s, max_extrapolation_s

    @property
    def newest_ns(self) -> int | None:
        """Stamp of the newest pose."""
        return self.buffer.newest_ns

    def pose_at(self, stamp_ns: int) -> PoseAt:
        """The interpolated pose (see :meth:`PoseBuffer.lookup`)."""
        found = self.buffer.lookup(stamp_ns, max_gap_s=self.max_gap_s, max_extrapolation_s=self.max_extrapolation_s)
        if found.pose is not None:
            return PoseAt(found.pose)
        reason = found.reason.value if found.reason is not None else "no_pose"
        return PoseAt(None, reason, f"no pose at {stamp_ns} ns ({reason})")

    def discard_before(self, stamp_ns: int) -> None:
        """See :meth:`PoseBuffer.discard_before`."""
        self.buffer.discard_before(stamp_ns)


class TFPoses:
    """:class:`PoseSource` of TF: ``T_world_camera @ T_camera_rectified`` at a stamp.

    Args:
        source: a :class:`~selfcontra_ros.bags.tf.TFBuffer`, or any :class:`TransformSource` (tf2_ros adapter).
        world_frame: the fixed frame.
        camera_frame: the left camera's frame; None until :meth:`set_camera` names it (from the camera_info).
        raw_from_rectified: ``T_camera_rectified`` (the rectification rotation; identity for rectified input).
    """

    def __init__(
        self,
        source: TransformSource,
        world_frame: str,
        camera_frame: str | None = None,
        raw_from_rectified: NDArray[np.float64] | None = None,
    ) -> None:
        self.source = source
        self.world_frame = normalize_frame(world_frame)
        self.camera_frame = normalize_frame(camera_frame) if camera_frame else None
        self.raw_from_rectified = np.eye(4) if raw_from_rectified is None else raw_from_rectified

    def set_camera(self, camera_frame: str, raw_from_rectified: NDArray[np.float64]) -> None:
        """Name the camera frame (when none was given) and the rectification rotation, from the calibration."""
        if self.camera_frame is None:
            self.camera_frame = normalize_frame(camera_frame)
        self.raw_from_rectified = raw_from_rectified

    @property
    def newest_ns(self) -> int | None:
        """The latest stamp every dynamic link of the chain has (None before the chain is connected)."""
        if self.camera_frame is None or not isinstance(self.source, TFBuffer):
            return None
        return self.source.newest_ns(self.world_frame, self.camera_frame)

    def pose_at(self, stamp_ns: int) -> PoseAt:
        """The pose of the (rectified) left camera in the world frame, or the TF error's reason."""
        if self.camera_frame is None:
            return PoseAt(None, "no_camera_frame", "no camera frame yet (no camera_info before the image)")
        try:
            pose = self.source.lookup(self.world_frame, self.camera_frame, stamp_ns)
        except TransformError as exc:
            return PoseAt(None, exc.reason, str(exc))
        return PoseAt(pose @ self.raw_from_rectified)

    def discard_before(self, stamp_ns: int) -> None:
        """Forget TF history no longer needed (a TFBuffer source only)."""
        if isinstance(self.source, TFBuffer):
            self.source.discard_before(stamp_ns)
