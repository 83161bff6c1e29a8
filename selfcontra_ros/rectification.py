"""Stereo rectification from two ``sensor_msgs/CameraInfo``, as stereo_image_proc does it, without ROS.

Many drivers publish ``image_raw`` with the calibration of the raw cameras:
``K`` (3x3 intrinsics), ``D`` (distortion, ``plumb_bob``: k1 k2 p1 p2 k3, or
``rational_polynomial``: k1 k2 p1 p2 k3 k4 k5 k6), ``R`` (the rotation from
the raw camera to the rectified one, ``X_rect = R X_raw``) and ``P`` (the
rectified 3x4 projection; the right one carries ``P[0,3] = -fx' * baseline``).
:class:`Rectifier` builds OpenCV's remap tables once per calibration
(``cv2.initUndistortRectifyMap``, fixed-point maps) and rectifies each pair
with ``cv2.remap`` (bilinear); the rectified images keep the camera_info's
size, as in ROS. :attr:`Rectifier.camera` is the rectified
:class:`~selfcontra_ros.geometry.StereoCamera` (from the two ``P``), the one
the labeler uses, and :attr:`Rectifier.raw_from_rectified` the pose of the
rectified left camera in the raw left camera's frame (``R_left^T``): a pose of
the raw optical frame from TF times it is the pose of the rectified view.

``equidistant`` (fisheye) calibrations are refused, naming the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.errors import CalibrationError, ConversionError
from selfcontra_ros.geometry import StereoCamera

__all__ = ["DISTORTION_MODELS", "Rectifier", "calibration_key", "raw_from_rectified"]

#: Distortion models rectified -> the numbers of coefficients ``D`` may have.
DISTORTION_MODELS: dict[str, tuple[int, ...]] = {
    "plumb_bob": (4, 5),
    "rational_polynomial": (8, 12, 14),
    "": (0, 4, 5, 8),  # unset (some drivers): OpenCV's own reading by length
}
#: Largest deviation of ``R`` from a rotation accepted.
_ROTATION_TOLERANCE = 1e-3


def _matrix(info: Any, field: str, shape: tuple[int, int], side: str) -> NDArray[np.float64]:
    values = np.asarray(getattr(info, field), dtype=np.float64).reshape(-1)
    if values.size != shape[0] * shape[1] or not np.all(np.isfinite(values)):
        raise CalibrationError(
            f"{side} camera_info {field.upper()} must hold {shape[0] * shape[1]} finite numbers, got {values.tolist()}"
        )
    if not np.any(values):
        raise CalibrationError(f"{side} camera_info {field.upper()} is all zeros; the camera is not calibrated")
    return values.reshape(shape)


def _calibration(info: Any, side: str) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``K``, ``D`` and ``R`` of one camera_info, checked."""
    model = str(getattr(info, "distortion_model", "")).strip()
    if model not in DISTORTION_MODELS:
        raise CalibrationError(
            f"{side} camera_info distortion_model {model!r} is not supported for rectification; expected one of "
            f"{', '.join(m for m in DISTORTION_MODELS if m)} (fisheye / equidistant cameras are not handled)"
        )
    d = np.asarray(getattr(info, "d", ()), dtype=np.float64).reshape(-1)
    if d.size not in DISTORTION_MODELS[model] or not np.all(np.isfinite(d)):
        raise CalibrationError(
            f"{side} camera_info D has {d.size} coefficients {d.tolist()}; "
            f"{model or 'an unset model'} expects {' or '.join(str(n) for n in DISTORTION_MODELS[model])} finite ones"
        )
    return _matrix(info, "k", (3, 3), side), d, _rotation(info, side)


def _rotation(info: Any, side: str) -> NDArray[np.float64]:
    """The rectification rotation ``R`` of one camera_info, checked."""
    r = _matrix(info, "r", (3, 3), side)
    if np.abs(r.T @ r - np.eye(3)).max() > _ROTATION_TOLERANCE or abs(np.linalg.det(r) - 1.0) > _ROTATION_TOLERANCE:
        raise CalibrationError(f"{side} camera_info R is not a rotation: {r.tolist()}")
    return r


def calibration_key(info: Any) -> tuple[Any, ...]:
    """Hashable summary of a camera_info's calibration: rectification maps are rebuilt only when it changes."""
    fields = tuple(tuple(np.asarray(getattr(info, f, ()), dtype=np.float64).reshape(-1).tolist()) for f in "dkrp")
    return (int(info.width), int(info.height), str(getattr(info, "distortion_model", "")), *fields)


def raw_from_rectified(left_info: Any) -> NDArray[np.float64]:
    """4x4 ``T_rawleft_rectleft`` of a raw left camera_info: the rotation ``R^T`` (no translation).

    A pose of the raw optical frame (e.g. from TF) times it is the pose of the rectified left view.

    Raises:
        CalibrationError: ``R`` is not nine finite numbers forming a rotation.
    """
    pose = np.eye(4)
    pose[:3, :3] = _rotation(left_info, "left").T
    return pose


@dataclass(frozen=True)
class _Maps:
    first: NDArray[Any]
    second: NDArray[Any]


class Rectifier:
    """Rectification of one calibrated stereo pair (see the module docstring); build it with :meth:`from_camera_infos`.

    Attributes:
        camera: the rectified stereo camera (intrinsics from ``P_left``, baseline from ``P_right[0,3]``).
        raw_from_rectified: 4x4 ``T_rawleft_rectleft``: the rotation ``R_left^T``.
        key: :func:`calibration_key` of the two camera infos.
    """

    def __init__(
        self, camera: StereoCamera, maps: tuple[_Maps, _Maps], raw_from_rectified: NDArray[np.float64], key: Any
    ) -> None:
        self.camera = camera
        self._maps = maps
        self.raw_from_rectified = raw_from_rectified
        self.key = key

    @classmethod
    def from_camera_infos(cls, left_info: Any, right_info: Any) -> Rectifier:
        """The rectifier of a pair of raw-camera ``CameraInfo`` messages (duck-typed, rclpy or rosbags).

        Raises:
            CalibrationError: naming the field: an unsupported distortion model or ``D`` length,
                all-zero or non-finite ``K``/``R``/``P``, an ``R`` that is no rotation, differing
                sizes, or projections that do not describe a rectified pair.
        """
        width, height = int(left_info.width), int(left_info.height)
        if (int(right_info.width), int(right_info.height)) != (width, height) or width <= 0 or height <= 0:
            raise CalibrationError(
                f"camera_info sizes differ or are empty: left {width}x{height}, "
                f"right {int(right_info.width)}x{int(right_info.height)}"
            )
        maps = []
        projections = []
        for side, info in (("left", left_info), ("right", right_info)):
            k, d, r = _calibration(info, side)
            p = _matrix(info, "p", (3, 4), side)
            first, second = cv2.initUndistortRectifyMap(k, d, r, p[:, :3], (width, height), cv2.CV_16SC2)
            maps.append(_Maps(first, second))
            projections.append(p)
        camera = StereoCamera.from_projections(
            projections[0], projections[1], width, height, source="camera_info pair (rectified P)"
        )
        key = (calibration_key(left_info), calibration_key(right_info))
        return cls(camera, (maps[0], maps[1]), raw_from_rectified(left_info), key)

    def rectify(self, image: NDArray[np.uint8], *, right: bool) -> NDArray[np.uint8]:
        """The rectified image of the left or right raw camera (same size and channels, bilinear).

        Raises:
            ConversionError: the image size is not the calibration's.
        """
        if image.shape[:2] != (self.camera.height, self.camera.width):
            raise ConversionError(
                f"{'right' if right else 'left'} raw image is {image.shape[1]}x{image.shape[0]}; "
                f"the camera_info is {self.camera.width}x{self.camera.height}"
            )
        maps = self._maps[1 if right else 0]
        return np.asarray(cv2.remap(image, maps.first, maps.second, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
