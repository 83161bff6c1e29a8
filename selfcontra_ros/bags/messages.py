"""Build rosbags messages (for writing bags) from numpy arrays and the camera.

The field conventions live in :mod:`selfcontra_ros.ros.conversions`
(``image_fields``, ``camera_info_fields``, ``disparity_image_fields``), shared
with the rclpy messages the nodes publish; this module only wraps them in the
message classes of a rosbags typestore, so bags and topics carry the same
bytes.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.typesys.store import Typestore

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.compressed import compressed_image_fields
from selfcontra_ros.geometry import StereoCamera, quaternion_from_rotation
from selfcontra_ros.ros.conversions import camera_info_fields, disparity_image_fields, image_fields

__all__ = ["MessageBuilder"]

_NS_PER_S = 1_000_000_000


class MessageBuilder:
    """Creates rosbags messages of one typestore (message classes looked up once)."""

    def __init__(self, typestore: Typestore) -> None:
        types = typestore.types
        self._time = types["builtin_interfaces/msg/Time"]
        self._header = types["std_msgs/msg/Header"]
        self._image = types[topics.IMAGE_TYPE]
        self._info = types[topics.CAMERA_INFO_TYPE]
        self._roi = types["sensor_msgs/msg/RegionOfInterest"]
        self._pose_stamped = types[topics.POSE_TYPE]
        self._pose = types["geometry_msgs/msg/Pose"]
        self._point = types["geometry_msgs/msg/Point"]
        self._quaternion = types["geometry_msgs/msg/Quaternion"]
        self._disparity = types[topics.DISPARITY_TYPE]
        self._compressed = types[topics.COMPRESSED_IMAGE_TYPE]
        self._tf_message = types[topics.TF_TYPE]
        self._transform_stamped = types["geometry_msgs/msg/TransformStamped"]
        self._transform = types["geometry_msgs/msg/Transform"]
        self._vector3 = types["geometry_msgs/msg/Vector3"]

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        """``std_msgs/Header`` with an integer-nanosecond stamp."""
        sec, nanosec = divmod(stamp_ns, _NS_PER_S)
        return self._header(stamp=self._time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    def image(self, pixels: NDArray[Any], encoding: str, stamp_ns: int, frame_id: str) -> Any:
        """``sensor_msgs/Image`` of an array in one of the encodings of ``image_fields``."""
        fields = image_fields(pixels, encoding)
        fields["data"] = np.frombuffer(fields["data"], dtype=np.uint8)
        return self._image(header=self.header(stamp_ns, frame_id), **fields)

    def camera_info(self, camera: StereoCamera, stamp_ns: int, frame_id: str, *, right: bool) -> Any:
        """``sensor_msgs/CameraInfo`` of the left or right camera of a rectified pair."""
        fields = camera_info_fields(camera, right=right)
        roi = self._roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self._info(header=self.header(stamp_ns, frame_id), roi=roi, **fields)

    def camera_info_of(self, fields: dict[str, Any], stamp_ns: int, frame_id: str) -> Any:
        """``sensor_msgs/CameraInfo`` of given fields (``width``, ``height``, ``distortion_model``, ``d``,
        ``k``, ``r``, ``p``; binning 0, full region of interest), e.g. a raw camera's distorted calibration."""
        roi = self._roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        values = {"binning_x": 0, "binning_y": 0, **fields}
        for name in "dkrp":
            values[name] = np.asarray(values[name], dtype=np.float64).reshape(-1)
        return self._info(header=self.header(stamp_ns, frame_id), roi=roi, **values)

    def pose_stamped(self, pose: NDArray[np.float64], stamp_ns: int, frame_id: str = topics.WORLD_FRAME) -> Any:
        """``geometry_msgs/PoseStamped`` of a 4x4 pose ``T_frame_left``."""
        x, y, z = (float(v) for v in pose[:3, 3])
        qx, qy, qz, qw = (float(v) for v in quaternion_from_rotation(pose[:3, :3]))
        return self._pose_stamped(
            header=self.header(stamp_ns, frame_id),
            pose=self._pose(position=self._point(x=x, y=y, z=z), orientation=self._quaternion(x=qx, y=qy, z=qz, w=qw)),
        )

    def compressed_image(
        self, pixels: NDArray[np.uint8], encoding: str, stamp_ns: int, frame_id: str, *, image_format: str = "jpeg"
    ) -> Any:
        """``sensor_msgs/CompressedImage`` of an 8-bit image as image_transport's ``compressed`` plugin writes it.

        See :func:`selfcontra_ros.bags.compressed.compressed_image_fields` (``format`` string, colour order).
        """
        fields = compressed_image_fields(pixels, encoding, image_format)
        return self._compressed(header=self.header(stamp_ns, frame_id), **fields)

    def tf_message(self, transforms: Iterable[tuple[str, str, int, NDArray[np.float64]]]) -> Any:
        """``tf2_msgs/TFMessage`` of ``(parent, child, stamp_ns, T_parent_child)`` transforms (metres)."""
        items = []
        for parent, child, stamp_ns, matrix in transforms:
            x, y, z = (float(v) for v in matrix[:3, 3])
            qx, qy, qz, qw = (float(v) for v in quaternion_from_rotation(matrix[:3, :3]))
            transform = self._transform(
                translation=self._vector3(x=x, y=y, z=z), rotation=self._quaternion(x=qx, y=qy, z=qz, w=qw)
            )
            items.append(
                self._transform_stamped(header=self.header(stamp_ns, parent), child_frame_id=child, transform=transform)
            )
        return self._tf_message(transforms=items)

    def disparity(
        self,
        disparity: NDArray[np.floating],
        camera: StereoCamera,
        stamp_ns: int,
        frame_id: str,
        *,
        min_disparity: float = 0.0,
        max_disparity: float | None = None,
        delta_d: float = 1.0 / 16.0,
    ) -> Any:
        """``stereo_msgs/DisparityImage`` with the conventions of ``conversions.disparity_image``."""
        fields = disparity_image_fields(
            disparity, camera, min_disparity=min_disparity, max_disparity=max_disparity, delta_d=delta_d
        )
        image = self.image(fields.pop("disparity"), "32FC1", stamp_ns, frame_id)
        window = self._roi(**fields.pop("valid_window"))
        return self._disparity(header=self.header(stamp_ns, frame_id), image=image, valid_window=window, **fields)
