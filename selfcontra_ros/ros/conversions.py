"""Conversion between numpy arrays and ROS 2 messages, without cv_bridge.

Images (``sensor_msgs/Image``), disparity images (``stereo_msgs/DisparityImage``),
camera calibration (``sensor_msgs/CameraInfo`` pairs <-> :class:`StereoCamera`)
and stamps (``builtin_interfaces/Time``).

The *reading* side is duck-typed: :func:`image_to_numpy`,
:func:`disparity_from_message` and :func:`stereo_camera_from_camera_infos`
accept any object with the message's fields, so rclpy messages and messages
deserialised by ``rosbags`` work alike, and this module imports no ROS package
at import time. The *writing* side computes the message fields in pure
functions (:func:`image_fields`, :func:`camera_info_fields`) that the bag
tools can feed into ``rosbags`` message classes; only the functions returning
rclpy messages import the ROS message packages, lazily.

Arrays returned by the readers own their memory: they are copies, never views
into the message buffer, so they stay valid (and writable) after the message
is released.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.errors import CalibrationError, ConversionError
from selfcontra_ros.geometry import StereoCamera

if TYPE_CHECKING:
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import CameraInfo, Image
    from stereo_msgs.msg import DisparityImage

__all__ = [
    "ENCODINGS",
    "camera_info_fields",
    "camera_infos_from_stereo_camera",
    "disparity_from_message",
    "disparity_image",
    "disparity_image_fields",
    "image_fields",
    "image_to_numpy",
    "nanoseconds_to_stamp",
    "numpy_to_image",
    "seconds_to_stamp",
    "stamp_to_nanoseconds",
    "stamp_to_seconds",
    "stereo_camera_from_camera_infos",
]

_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class _Encoding:
    """Memory layout of one image encoding: per-channel element type and channel count."""

    dtype: np.dtype[Any]  # native byte order
    channels: int

    @property
    def pixel_size(self) -> int:
        """Bytes per pixel."""
        return self.dtype.itemsize * self.channels


# The encodings of sensor_msgs/image_encodings.hpp that the package reads and writes.
ENCODINGS: dict[str, _Encoding] = {
    "mono8": _Encoding(np.dtype(np.uint8), 1),
    "mono16": _Encoding(np.dtype(np.uint16), 1),
    "rgb8": _Encoding(np.dtype(np.uint8), 3),
    "bgr8": _Encoding(np.dtype(np.uint8), 3),
    "rgba8": _Encoding(np.dtype(np.uint8), 4),
    "bgra8": _Encoding(np.dtype(np.uint8), 4),
    "16UC1": _Encoding(np.dtype(np.uint16), 1),
    "32FC1": _Encoding(np.dtype(np.float32), 1),
}

_NATIVE_BIG_ENDIAN = sys.byteorder == "big"


def _encoding(name: str, what: str) -> _Encoding:
    try:
        return ENCODINGS[name]
    except KeyError:
        raise ConversionError(
            f"{what}.encoding {name!r} is not supported; expected one of {', '.join(ENCODINGS)}"
        ) from None


def _as_bytes_array(data: Any, what: str) -> NDArray[np.uint8]:
    """View (no copy where possible) the ``data`` field as a flat uint8 array.

    ``data`` may be ``bytes``/``bytearray``/``memoryview`` and ``array.array('B')``
    (rclpy), a numpy uint8 array (rosbags) or a list of ints.
    """
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise ConversionError(f"{what}.data must hold uint8 bytes, got a numpy array of {data.dtype}")
        return data.reshape(-1)
    if isinstance(data, (list, tuple)):
        try:
            return np.asarray(data, dtype=np.uint8)
        except (OverflowError, TypeError, ValueError) as exc:
            raise ConversionError(f"{what}.data must be a sequence of bytes (0..255): {exc}") from None
    try:
        view = memoryview(data)
    except TypeError:
        raise ConversionError(
            f"{what}.data must be bytes, array.array, a list or a numpy uint8 array, got {type(data).__name__}"
        ) from None
    if view.itemsize != 1:
        raise ConversionError(f"{what}.data must hold single bytes, got items of {view.itemsize} bytes")
    return np.frombuffer(view, dtype=np.uint8)


def image_to_numpy(msg: Any) -> NDArray[Any]:
    """Pixels of an image message as a numpy array in native byte order.

    Args:
        msg: any object with the fields of ``sensor_msgs/Image`` (``height``,
            ``width``, ``encoding``, ``is_bigendian``, ``step``, ``data``),
            e.g. an rclpy or a rosbags message.

    Returns:
        A new array (owning its memory) of shape ``(height, width)`` for
        single-channel encodings and ``(height, width, channels)`` otherwise;
        dtype uint8 (``mono8``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``),
        uint16 (``mono16``, ``16UC1``) or float32 (``32FC1``). Channel order is
        the encoding's (``bgr8`` stays BGR). Row padding (``step`` larger than
        ``width`` times the pixel size) is dropped, and big-endian data is
        byte-swapped.

    Raises:
        ConversionError: unsupported encoding, ``step`` smaller than one row,
            or ``data`` length different from ``height * step``.
    """
    what = "Image"
    enc = _encoding(str(msg.encoding), what)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height < 0 or width < 0:
        raise ConversionError(f"{what}.height/width must be >= 0, got {height}x{width}")
    row_bytes = width * enc.pixel_size
    if step < row_bytes:
        raise ConversionError(
            f"{what}.step is {step} bytes; expected >= width * pixel size = {width} * {enc.pixel_size} = {row_bytes} "
            f"for encoding {msg.encoding!r}"
        )
    raw = _as_bytes_array(msg.data, what)
    if raw.size != height * step:
        raise ConversionError(
            f"{what}.data has {raw.size} bytes; expected height * step = {height} * {step} = {height * step}"
        )
    stored = enc.dtype.newbyteorder(">" if msg.is_bigendian else "<") if enc.dtype.itemsize > 1 else enc.dtype
    shape: tuple[int, ...] = (height, width) if enc.channels == 1 else (height, width, enc.channels)
    strides: tuple[int, ...] = (step, enc.pixel_size) if enc.channels == 1 else (step, enc.pixel_size, stored.itemsize)
    # A strided view over the (possibly padded, possibly unaligned) buffer, then one copy that
    # packs the rows and converts to native byte order; the result never aliases the message.
    view = np.ndarray(shape, dtype=stored, buffer=np.ascontiguousarray(raw), strides=strides)
    return view.astype(enc.dtype, order="C", copy=True)


def image_fields(array: ArrayLike, encoding: str) -> dict[str, Any]:
    """Fields of a ``sensor_msgs/Image`` holding ``array`` (header excluded).

    Data are written packed (``step = width * pixel size``) in the machine's
    native byte order, with ``is_bigendian`` set to match (0 on x86/ARM).

    Args:
        array: ``(height, width)`` (single channel; ``(height, width, 1)`` is
            accepted too) or ``(height, width, channels)``, with exactly the
            dtype of the encoding (uint8, uint16 or float32, see
            :func:`image_to_numpy`).
        encoding: one of :data:`ENCODINGS`.

    Returns:
        ``{"height", "width", "encoding", "is_bigendian", "step", "data"}``
        with ``data`` as ``bytes``: assign it as is to an rclpy message (fast);
        a rosbags message wants ``np.frombuffer(fields["data"], np.uint8)``.

    Raises:
        ConversionError: unsupported encoding, or dtype/shape not matching it.
    """
    enc = _encoding(encoding, "numpy_to_image")
    arr = np.asarray(array)
    if arr.dtype.kind != enc.dtype.kind or arr.dtype.itemsize != enc.dtype.itemsize:
        raise ConversionError(f"array dtype is {arr.dtype}; encoding {encoding!r} expects {enc.dtype}")
    if enc.channels == 1 and arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    expected_ndim = 2 if enc.channels == 1 else 3
    if arr.ndim != expected_ndim or (enc.channels > 1 and arr.shape[2] != enc.channels):
        layout = "(height, width)" if enc.channels == 1 else f"(height, width, {enc.channels})"
        raise ConversionError(f"array shape is {arr.shape}; encoding {encoding!r} expects {layout}")
    height, width = int(arr.shape[0]), int(arr.shape[1])
    # astype to the native dtype fixes a foreign byte order; ascontiguousarray packs the rows.
    packed = np.ascontiguousarray(arr.astype(enc.dtype, copy=False))
    return {
        "height": height,
        "width": width,
        "encoding": encoding,
        "is_bigendian": int(_NATIVE_BIG_ENDIAN),
        "step": width * enc.pixel_size,
        "data": packed.tobytes(),
    }


def numpy_to_image(
    array: ArrayLike,
    encoding: str,
    *,
    stamp: Time | float | None = None,
    frame_id: str = "",
) -> Image:
    """Build an rclpy ``sensor_msgs/Image`` from an array (see :func:`image_fields`).

    Args:
        array: pixels, shape and dtype as the encoding requires.
        encoding: one of :data:`ENCODINGS`.
        stamp: header stamp, a ``builtin_interfaces/Time`` or seconds; zero when None.
        frame_id: header frame id.

    Raises:
        ConversionError: unsupported encoding, or dtype/shape not matching it.
    """
    from sensor_msgs.msg import Image

    fields = image_fields(array, encoding)
    msg = Image()
    _fill_header(msg.header, stamp, frame_id)
    msg.height = fields["height"]
    msg.width = fields["width"]
    msg.encoding = fields["encoding"]
    msg.is_bigendian = fields["is_bigendian"]
    msg.step = fields["step"]
    msg.data = fields["data"]  # bytes: rclpy copies them in one go, a numpy array element by element
    return msg


def disparity_image(
    disparity: ArrayLike,
    camera: StereoCamera,
    *,
    stamp: Time | float | None = None,
    frame_id: str = "",
    min_disparity: float = 0.0,
    max_disparity: float | None = None,
    delta_d: float = 1.0 / 16.0,
) -> DisparityImage:
    """Build a ``stereo_msgs/DisparityImage`` (conventions of stereo_image_proc).

    The image is ``32FC1`` disparity in pixels, ``f = fx`` (pixels) and
    ``t = baseline`` (metres), so that ``Z = f * t / d``; ``valid_window`` is
    the full image. stereo_msgs marks a pixel invalid by a disparity below
    ``min_disparity``: non-finite input values (NaN, inf) are written as
    ``min_disparity - 1``, as stereo_image_proc does; finite values are
    written unchanged (a finite value below ``min_disparity`` thus reads back
    as invalid).

    Args:
        disparity: ``(height, width)`` disparity map in pixels, matching the camera size.
        camera: the rectified stereo camera the disparity belongs to.
        stamp: header stamp (``builtin_interfaces/Time`` or seconds); zero when None.
        frame_id: header frame id (left optical frame), set on both headers.
        min_disparity: smallest disparity searched, pixels.
        max_disparity: largest disparity searched, pixels; None takes the
            largest finite disparity of the map (``min_disparity`` if none).
        delta_d: disparity resolution, pixels (1/16 for OpenCV SGBM).

    Raises:
        ConversionError: the disparity is not 2-D, not real, or its size differs from the camera's.
    """
    from stereo_msgs.msg import DisparityImage

    fields = disparity_image_fields(
        disparity, camera, min_disparity=min_disparity, max_disparity=max_disparity, delta_d=delta_d
    )
    msg = DisparityImage()
    _fill_header(msg.header, stamp, frame_id)
    msg.image = numpy_to_image(fields.pop("disparity"), "32FC1", stamp=stamp, frame_id=frame_id)
    for name, value in fields.pop("valid_window").items():
        setattr(msg.valid_window, name, value)
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


def disparity_image_fields(
    disparity: ArrayLike,
    camera: StereoCamera,
    *,
    min_disparity: float = 0.0,
    max_disparity: float | None = None,
    delta_d: float = 1.0 / 16.0,
) -> dict[str, Any]:
    """The fields of a ``stereo_msgs/DisparityImage`` (see :func:`disparity_image`), for any message library.

    Returns a dict with ``disparity`` (the float32 map to put in ``image`` as
    32FC1, invalid pixels already written as ``min_disparity - 1``), ``f``,
    ``t``, ``valid_window`` (a dict of the RegionOfInterest fields),
    ``min_disparity``, ``max_disparity`` and ``delta_d``.

    Raises:
        ConversionError: the disparity is not 2-D, not real, or its size differs from the camera's.
    """
    d = np.asarray(disparity)
    if d.dtype.kind not in "fiu":
        raise ConversionError(f"disparity dtype is {d.dtype}; expected a real number type")
    if d.shape != (camera.height, camera.width):
        raise ConversionError(
            f"disparity shape is {d.shape}; expected the camera size (height, width) = "
            f"({camera.height}, {camera.width})"
        )
    d32 = d.astype(np.float32)
    finite = np.isfinite(d32)
    d32[~finite] = np.float32(min_disparity - 1.0)
    if max_disparity is None:
        max_disparity = float(d32[finite].max()) if finite.any() else float(min_disparity)
    return {
        "disparity": d32,
        "f": float(camera.fx),
        "t": float(camera.baseline),
        "valid_window": {
            "x_offset": 0,
            "y_offset": 0,
            "height": camera.height,
            "width": camera.width,
            "do_rectify": False,
        },
        "min_disparity": float(min_disparity),
        "max_disparity": float(max_disparity),
        "delta_d": float(delta_d),
    }


def disparity_from_message(msg: Any) -> tuple[NDArray[np.float32], float, float]:
    """Disparity map, focal length and baseline of a ``stereo_msgs/DisparityImage``.

    Args:
        msg: any object with the fields of ``stereo_msgs/DisparityImage``
            (rclpy or rosbags); its ``image`` must be ``32FC1``.

    Returns:
        ``(disparity, f, t)``: float32 disparity in pixels with NaN where the
        message marks it invalid (below ``min_disparity``, or not finite), the
        focal length ``f`` in pixels and the baseline ``t`` in metres.

    Raises:
        ConversionError: the image is not ``32FC1`` or is malformed (see :func:`image_to_numpy`).
    """
    if str(msg.image.encoding) != "32FC1":
        raise ConversionError(f"DisparityImage.image.encoding is {msg.image.encoding!r}; expected '32FC1'")
    d = image_to_numpy(msg.image)
    d[~np.isfinite(d) | (d < np.float32(msg.min_disparity))] = np.nan
    return d, float(msg.f), float(msg.t)


def _roi_is_full(roi: Any, width: int, height: int) -> bool:
    """True when a RegionOfInterest is unset (all zero) or covers the whole image."""
    if roi is None:
        return True
    x, y, w, h = (int(getattr(roi, k, 0)) for k in ("x_offset", "y_offset", "width", "height"))
    return (x, y) == (0, 0) and (w, h) in ((0, 0), (width, height))


def stereo_camera_from_camera_infos(left_info: Any, right_info: Any) -> StereoCamera:
    """Stereo camera of a rectified pair from its two ``sensor_msgs/CameraInfo``.

    Uses the rectified projection matrices ``P`` (not ``K``): the intrinsics
    come from the left ``P`` and the baseline from
    ``(P_left[0,3] - P_right[0,3]) / fx``, so a left camera with non-zero
    ``Tx`` (KITTI colour cameras) is handled.

    Args:
        left_info: any object with the CameraInfo fields ``width``,
            ``height``, ``p`` (12 values) and optionally ``binning_x``,
            ``binning_y``, ``roi`` (rclpy or rosbags message).
        right_info: the same for the right camera.

    Raises:
        CalibrationError: naming the field: zero or differing ``width``/``height``,
            an all-zero ``P`` (uncalibrated camera), binning or a region of
            interest (not supported), or a pair that is not rectified.
    """
    sizes = {}
    for side, info in (("left", left_info), ("right", right_info)):
        w, h = int(info.width), int(info.height)
        if w <= 0 or h <= 0:
            raise CalibrationError(f"{side} camera_info width/height is {w}x{h}; expected a positive image size")
        p = np.asarray(info.p, dtype=np.float64)
        if p.size == 12 and not np.any(p):
            raise CalibrationError(
                f"{side} camera_info P is all zeros; the camera is not calibrated or the images are not rectified"
            )
        for field in ("binning_x", "binning_y"):
            if int(getattr(info, field, 0)) > 1:
                raise CalibrationError(
                    f"{side} camera_info {field} is {getattr(info, field)}; binning is not supported (expected 0 or 1)"
                )
        if not _roi_is_full(getattr(info, "roi", None), w, h):
            raise CalibrationError(f"{side} camera_info roi is set; a region of interest is not supported")
        sizes[side] = (w, h)
    if sizes["left"] != sizes["right"]:
        raise CalibrationError(
            f"camera_info width/height differ: left {sizes['left'][0]}x{sizes['left'][1]}, "
            f"right {sizes['right'][0]}x{sizes['right'][1]}; expected one rectified size"
        )
    width, height = sizes["left"]
    return StereoCamera.from_projections(left_info.p, right_info.p, width, height, source="camera_info pair")


def camera_info_fields(camera: StereoCamera, *, right: bool = False) -> dict[str, Any]:
    """Fields of the ``sensor_msgs/CameraInfo`` of one camera of a rectified pair (header excluded).

    The images are rectified, so distortion is zero (``plumb_bob``), ``R`` is
    the identity and ``K`` equals the left 3x3 of ``P``; the right ``P``
    carries ``P[0,3] = -fx * baseline``.

    Returns:
        ``{"width", "height", "distortion_model", "d", "k", "r", "p",
        "binning_x", "binning_y"}`` with float64 numpy arrays ``d`` (5), ``k``
        (9), ``r`` (9) and ``p`` (12).
    """
    p_left, p_right = camera.projection_matrices()
    return {
        "width": camera.width,
        "height": camera.height,
        "distortion_model": "plumb_bob",
        "d": np.zeros(5),
        "k": camera.K.reshape(-1),
        "r": np.eye(3).reshape(-1),
        "p": (p_right if right else p_left).reshape(-1),
        "binning_x": 0,
        "binning_y": 0,
    }


def camera_infos_from_stereo_camera(
    camera: StereoCamera,
    stamp: Time | float | None = None,
    frame_id: str = "",
    *,
    right_frame_id: str | None = None,
) -> tuple[CameraInfo, CameraInfo]:
    """The pair of rclpy ``sensor_msgs/CameraInfo`` messages of a rectified stereo camera.

    Args:
        camera: the stereo camera.
        stamp: header stamp (``builtin_interfaces/Time`` or seconds); zero when None.
        frame_id: frame id of the left camera info.
        right_frame_id: frame id of the right camera info; ``frame_id`` when None.

    Returns:
        ``(left_info, right_info)``; :func:`stereo_camera_from_camera_infos` inverts it.
    """
    from sensor_msgs.msg import CameraInfo

    infos = []
    for right, fid in ((False, frame_id), (True, frame_id if right_frame_id is None else right_frame_id)):
        fields = camera_info_fields(camera, right=right)
        msg = CameraInfo()
        _fill_header(msg.header, stamp, fid)
        msg.width = fields["width"]
        msg.height = fields["height"]
        msg.distortion_model = fields["distortion_model"]
        msg.d = fields["d"].tolist()
        msg.k = fields["k"]
        msg.r = fields["r"]
        msg.p = fields["p"]
        msg.binning_x = fields["binning_x"]
        msg.binning_y = fields["binning_y"]
        infos.append(msg)
    return infos[0], infos[1]


def stamp_to_nanoseconds(stamp: Any) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (any object with ``sec`` and ``nanosec``)."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def stamp_to_seconds(stamp: Any) -> float:
    """Seconds (float) of a ``builtin_interfaces/Time``; float64 keeps about 0.2 µs at today's epoch."""
    return stamp_to_nanoseconds(stamp) / _NS_PER_S


def _split_nanoseconds(nanoseconds: int) -> tuple[int, int]:
    """``(sec, nanosec)`` with ``0 <= nanosec < 1e9`` (floor division, also for negative times)."""
    sec, nanosec = divmod(int(nanoseconds), _NS_PER_S)
    return sec, nanosec


def nanoseconds_to_stamp(nanoseconds: int) -> Time:
    """A ``builtin_interfaces/Time`` holding exactly ``nanoseconds`` since the epoch."""
    from builtin_interfaces.msg import Time

    sec, nanosec = _split_nanoseconds(nanoseconds)
    return Time(sec=sec, nanosec=nanosec)


def seconds_to_stamp(seconds: float) -> Time:
    """A ``builtin_interfaces/Time`` of ``seconds``, rounded to the nearest nanosecond.

    The whole seconds are split off first, so the fraction is rounded without
    the precision loss of ``seconds * 1e9`` at large epoch times.

    Raises:
        ConversionError: ``seconds`` is not finite.
    """
    if not math.isfinite(seconds):
        raise ConversionError(f"stamp seconds must be finite, got {seconds!r}")
    whole = math.floor(seconds)
    return nanoseconds_to_stamp(whole * _NS_PER_S + round((seconds - whole) * _NS_PER_S))


def _fill_header(header: Any, stamp: Any, frame_id: str) -> None:
    """Set a std_msgs/Header's stamp (Time, seconds or None for zero) and frame id in place."""
    if stamp is None:
        header.stamp.sec, header.stamp.nanosec = 0, 0
    elif isinstance(stamp, (int, float)):
        t = seconds_to_stamp(float(stamp))
        header.stamp.sec, header.stamp.nanosec = t.sec, t.nanosec
    else:
        header.stamp.sec, header.stamp.nanosec = int(stamp.sec), int(stamp.nanosec)
    header.frame_id = frame_id
