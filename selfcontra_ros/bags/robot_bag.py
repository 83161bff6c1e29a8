"""A bag recorded the way a robot's drivers record one, from a rectified sequence with ground truth.

The package's own bags (:mod:`selfcontra_ros.bags.kitti2mcap`) hold what the
labeler wants: rectified raw images under ``/stereo``, a PoseStamped of the
left camera. A robot's recording holds what its drivers publish; this module
writes such a bag from a KITTI-layout sequence (e.g. a synthetic one), so that
the offline commands and the node can be tested on it:

* driver topic names (:class:`RobotLayout`, by default
  ``/sensors/stereo/cam_left/image_raw/compressed``,
  ``/sensors/stereo/cam_left/camera_info``, the same for ``cam_right``);
* **unrectified, compressed images**: each rectified image of the sequence is
  warped into a raw camera with its own ``K``, distortion (``plumb_bob`` on
  the left, ``rational_polynomial`` on the right) and rectification rotation
  ``R`` (:func:`raw_calibration`, :func:`distort`: an inverse mapping, each raw
  pixel sampled where the calibration says it lands in the rectified image),
  then JPEG- (or PNG-) compressed as image_transport does;
* ``camera_info`` per camera, in its own optical frame, carrying that ``D``,
  ``K``, ``R`` and the rectified ``P`` (right ``P[0,3] = -fx * baseline``);
* ``/tf`` ``odom -> base_link`` at 50 Hz (interpolated between the frames'
  poses, extended at constant velocity 0.1 s beyond the first and last) and
  ``/tf_static`` ``base_link -> `` both raw optical frames;
* the right image stamped a little after the left (2 ms by default), as two
  free-running cameras are;
* ``ground_truth/disparity`` of the rectified left view (a test aid no driver
  has; stamped like the left image) when the sequence has it.

``odom`` is placed so that ``base_link`` starts at its origin; the rectified
left camera's pose in ``odom`` at each frame is then the sequence's pose up to
one fixed transform, which leaves the labels unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import DEFAULT_STAMP_OFFSET_NS, GT_DELTA_D, seconds_to_nanoseconds
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.reader import BagError
from selfcontra_ros.bags.sync import PoseBuffer
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.errors import DatasetError
from selfcontra_ros.geometry import StereoCamera, invert_pose

__all__ = ["RobotLayout", "distort", "raw_calibration", "write_robot_bag"]

_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class RobotLayout:
    """Names and timing of a driver-style recording (the defaults are one plausible robot).

    Attributes:
        namespace: the stereo driver's namespace.
        left_camera, right_camera: the per-camera sub-namespaces (``<ns>/<camera>/image_raw``, ``.../camera_info``).
        left_frame, right_frame: the raw optical frames in TF and in the camera infos' headers.
        base_frame, odom_frame: the robot's body frame and its fixed odometry frame.
        image_format: ``jpeg`` or ``png``.
        tf_rate_hz: rate of ``/tf``.
        right_delay_ns: how much later the right camera's stamps are, nanoseconds.
        base_camera: 4x4 ``T_base_rectifiedleft`` (camera 1.4 m up, looking along the base's x axis).
    """

    namespace: str = "/sensors/stereo"
    left_camera: str = "cam_left"
    right_camera: str = "cam_right"
    left_frame: str = "stereo_left_optical_frame"
    right_frame: str = "stereo_right_optical_frame"
    base_frame: str = "base_link"
    odom_frame: str = "odom"
    image_format: str = "jpeg"
    tf_rate_hz: float = 50.0
    right_delay_ns: int = 2_000_000
    base_camera: tuple[tuple[float, ...], ...] = (
        (0.0, 0.0, 1.0, 0.3),
        (-1.0, 0.0, 0.0, 0.06),
        (0.0, -1.0, 0.0, 1.4),
        (0.0, 0.0, 0.0, 1.0),
    )

    def topic(self, side: str, name: str) -> str:
        """Absolute topic of ``name`` (``image_raw``, ``camera_info``) of the ``left`` or ``right`` camera."""
        camera = self.left_camera if side == "left" else self.right_camera
        return f"{self.namespace.rstrip('/')}/{camera}/{name}"

    def remaps(self) -> list[str]:
        """The ``--remap`` rules that map the package's names onto this layout (``--namespace`` :attr:`namespace`)."""
        cameras = (("left", self.left_camera), ("right", self.right_camera))
        return [f"{side}/{name}:={camera}/{name}" for name in ("image_raw", "camera_info") for side, camera in cameras]


def _rotation(axis: tuple[float, float, float], degrees: float) -> NDArray[np.float64]:
    vector = np.asarray(axis, dtype=np.float64)
    rotation, _ = cv2.Rodrigues(vector / np.linalg.norm(vector) * math.radians(degrees))
    return np.asarray(rotation, dtype=np.float64)


def raw_calibration(camera: StereoCamera) -> tuple[dict[str, Any], dict[str, Any]]:
    """CameraInfo fields of two raw cameras that rectify to ``camera`` (fixed, mild distortion; see the module).

    Returns:
        ``(left, right)`` dicts with ``width``, ``height``, ``distortion_model``, ``d``, ``k``, ``r``, ``p``.
    """
    p_left, p_right = camera.projection_matrices()
    specs = (
        ("plumb_bob", [-0.06, 0.015, 4e-4, -3e-4, 0.0], 0.97, (2.5, -1.5), ((0.3, 1.0, 0.2), 0.6), p_left),
        (
            "rational_polynomial",
            [-0.05, 0.01, -2e-4, 3e-4, 0.0, 0.001, 0.0, 0.0],
            0.975,
            (-2.0, 1.0),
            ((-0.2, 1.0, -0.1), -0.5),
            p_right,
        ),
    )
    infos = []
    for model, d, scale, (dx, dy), (axis, degrees), p in specs:
        k = np.array([[camera.fx * scale, 0.0, camera.cx + dx], [0.0, camera.fy * scale, camera.cy + dy], [0, 0, 1]])
        infos.append(
            {
                "width": camera.width,
                "height": camera.height,
                "distortion_model": model,
                "d": np.asarray(d, dtype=np.float64),
                "k": k,
                "r": _rotation(axis, degrees),
                "p": np.asarray(p, dtype=np.float64),
            }
        )
    return infos[0], infos[1]


def distort(rectified: NDArray[np.uint8], info: dict[str, Any]) -> NDArray[np.uint8]:
    """The raw (distorted, unrotated) image of a camera whose rectified image is ``rectified``.

    Each raw pixel is sampled (bilinear) at the rectified pixel its ray maps to
    (``cv2.undistortPoints`` with ``K``, ``D``, ``R`` and ``P``, iterated to 1e-6 px);
    raw pixels that see outside the rectified image are 0.
    """
    width, height = int(info["width"]), int(info["height"])
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    raw = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6)
    k, d = np.asarray(info["k"]).reshape(3, 3), np.asarray(info["d"], dtype=np.float64)
    r, p = np.asarray(info["r"]).reshape(3, 3), np.asarray(info["p"]).reshape(3, 4)
    rect = cv2.undistortPoints(raw, k, d, R=r, P=p[:, :3], criteria=criteria).reshape(height, width, 2)
    map_x, map_y = rect[..., 0].astype(np.float32), rect[..., 1].astype(np.float32)
    return np.asarray(cv2.remap(rectified, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))


def _mounts(layout: RobotLayout, camera: StereoCamera, infos: tuple[dict[str, Any], dict[str, Any]]) -> list[Any]:
    """``T_base_rawleft`` and ``T_base_rawright``: the rectified frames rotated back by their ``R``."""
    base_rect_left = np.asarray(layout.base_camera, dtype=np.float64)
    base_rect_right = base_rect_left.copy()
    base_rect_right[:3, 3] += base_rect_left[:3, 0] * camera.baseline
    mounts = []
    for base_rect, info in ((base_rect_left, infos[0]), (base_rect_right, infos[1])):
        rect_from_raw = np.eye(4)
        rect_from_raw[:3, :3] = np.asarray(info["r"]).reshape(3, 3)  # X_rect = R X_raw
        mounts.append(base_rect @ rect_from_raw)
    return mounts


def write_robot_bag(
    sequence: Path | str,
    out: Path | str,
    *,
    layout: RobotLayout | None = None,
    frames: slice | None = None,
    stamp_offset_ns: int = DEFAULT_STAMP_OFFSET_NS,
    ground_truth: bool = True,
) -> Path:
    """Write a KITTI-layout sequence with poses as a driver-style bag (see the module docstring).

    Returns:
        The bag folder ``out``.

    Raises:
        DatasetError: the sequence has no poses, or ``frames`` selects none.
        BagError: ``out`` exists.
    """
    layout = layout if layout is not None else RobotLayout()
    out = Path(out)
    if out.exists():
        raise BagError(f"output bag {out} exists already (not overwriting)")
    seq = open_sequence(sequence)
    if seq.poses is None:
        raise DatasetError(f"sequence {seq.folder} has no poses; a robot bag needs them for /tf")
    indices = range(len(seq))[frames if frames is not None else slice(None)]
    if not indices:
        raise DatasetError(f"frames {frames} selects no frame of {seq.folder}")
    camera = seq.camera
    infos = raw_calibration(camera)
    mount_left, mount_right = _mounts(layout, camera, infos)
    base_rect_left = np.asarray(layout.base_camera, dtype=np.float64)
    stamps = [int(stamp_offset_ns) + seconds_to_nanoseconds(float(seq.stamps[i])) for i in indices]
    # T_odom_base at each frame: odom = base_link at the first frame.
    odom_world = base_rect_left @ invert_pose(seq.poses[indices[0]])
    base_poses = PoseBuffer(capacity=len(indices) + 1)
    for i, stamp in zip(indices, stamps, strict=True):
        base_poses.add(stamp, odom_world @ seq.poses[i] @ invert_pose(base_rect_left))

    out.parent.mkdir(parents=True, exist_ok=True)
    period_ns = round(_NS_PER_S / layout.tf_rate_hz)
    margin_ns = _NS_PER_S // 10
    with BagWriter(out, atomic=True, custom_data={"selfcontra.robot_bag_of": str(seq.folder.resolve())}) as bag:
        make = MessageBuilder(bag.typestore)
        left_image, right_image = (layout.topic(s, "image_raw") + topics.COMPRESSED_SUFFIX for s in ("left", "right"))
        left_info, right_info = layout.topic("left", "camera_info"), layout.topic("right", "camera_info")
        gt_topic = f"{layout.namespace.rstrip('/')}/{topics.GT_DISPARITY}"
        for topic, msgtype in (
            (topics.TF_STATIC, topics.TF_TYPE),
            (topics.TF, topics.TF_TYPE),
            (left_image, topics.COMPRESSED_IMAGE_TYPE),
            (right_image, topics.COMPRESSED_IMAGE_TYPE),
            (left_info, topics.CAMERA_INFO_TYPE),
            (right_info, topics.CAMERA_INFO_TYPE),
        ):
            bag.add_topic(topic, msgtype)
        start = stamps[0] - margin_ns
        static = [
            (layout.base_frame, layout.left_frame, start, mount_left),
            (layout.base_frame, layout.right_frame, start, mount_right),
        ]
        bag.write(topics.TF_STATIC, start, make.tf_message(static))
        tf_stamps = list(range(start, stamps[-1] + margin_ns + 1, period_ns))
        frame_at = dict(zip(stamps, indices, strict=True))
        # One stream in log-time order: TF samples and frames (a frame's messages at its left stamp).
        events = sorted([(t, 0) for t in tf_stamps] + [(t, 1) for t in stamps])
        for stamp, kind in events:
            if kind == 0:
                pose = base_poses.at(stamp, max_gap_s=1.0, max_extrapolation_s=2.0 * margin_ns / _NS_PER_S)
                assert pose is not None  # within the extended span by construction
                bag.write(topics.TF, stamp, make.tf_message([(layout.odom_frame, layout.base_frame, stamp, pose)]))
                continue
            frame = seq[frame_at[stamp]]
            right_stamp = stamp + layout.right_delay_ns
            encoding = "rgb8" if frame.left.ndim == 3 else "mono8"
            left_raw, right_raw = distort(frame.left, infos[0]), distort(frame.right, infos[1])
            fmt = layout.image_format
            bag.write(left_info, stamp, make.camera_info_of(infos[0], stamp, layout.left_frame))
            bag.write(
                left_image, stamp, make.compressed_image(left_raw, encoding, stamp, layout.left_frame, image_format=fmt)
            )
            bag.write(right_info, right_stamp, make.camera_info_of(infos[1], right_stamp, layout.right_frame))
            bag.write(
                right_image,
                right_stamp,
                make.compressed_image(right_raw, encoding, right_stamp, layout.right_frame, image_format=fmt),
            )
            if ground_truth and frame.gt_disparity is not None:
                gt = make.disparity(frame.gt_disparity, camera, stamp, layout.left_frame, delta_d=GT_DELTA_D)
                bag.write(gt_topic, stamp, gt)
    return out
