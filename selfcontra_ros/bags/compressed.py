"""``sensor_msgs/CompressedImage`` <-> numpy, as image_transport's ``compressed`` plugin writes them, without ROS.

Robots record images compressed (``.../image_rect/compressed``,
``.../image_raw/compressed``: JPEG or PNG). The ``format`` field says how;
the spellings in use are

* ``jpeg``, ``png`` (also ``jpg``): ROS 1's plugin and many recorders; the
  data is what OpenCV writes, so colour pixels are stored in BGR order;
* ``<encoding>; <jpeg|png> compressed <stored>``, ROS 2's
  ``compressed_image_transport``, e.g. ``mono8; jpeg compressed mono8``,
  ``bgr8; png compressed bgr8``, ``rgb8; jpeg compressed bgr8``: the image of
  ``<encoding>`` was converted to ``<stored>`` before OpenCV encoded it, so
  the decoded array holds ``<stored>``'s channel order;
* ``<encoding>; compressedDepth ...``: depth images (``compressedDepth``
  transport), refused: they are no stereo input.

:func:`decode_compressed_image` returns the image the package works with:
``mono8`` (H x W) for grey images, ``rgb8`` (H x W x 3) for colour ones (an
alpha channel is dropped); only 8-bit images are accepted. It is duck-typed
(``format`` and ``data`` fields), so rclpy and rosbags messages decode alike.
:func:`compressed_image_fields` is the writing side (bags of
``kitti2mcap --compress-images``).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.bags.topics import IMAGE_ENCODINGS
from selfcontra_ros.errors import ConversionError

__all__ = ["IMAGE_FORMATS", "compressed_image_fields", "decode_compressed_image", "parse_format"]

#: Compression formats read and written.
IMAGE_FORMATS = ("jpeg", "png")
_ALIASES = {"jpeg": "jpeg", "jpg": "jpeg", "png": "png"}
#: JPEG quality written (image_transport's default is 95).
_JPEG_QUALITY = 95


def parse_format(text: str) -> tuple[str, str | None, str | None]:
    """``(compression, original encoding, stored encoding)`` of a ``CompressedImage.format`` string.

    The encodings are None where the string does not name them (``jpeg``,
    ``png``); the compression is ``jpeg`` or ``png``.

    Raises:
        ConversionError: an empty, unknown or depth (``compressedDepth``) format.
    """
    raw = str(text).strip()
    if not raw:
        raise ConversionError("CompressedImage.format is empty; expected e.g. 'jpeg' or 'mono8; jpeg compressed mono8'")
    if ";" not in raw:
        compression = _ALIASES.get(raw.lower())
        if compression is None:
            raise ConversionError(f"CompressedImage.format {raw!r} is not supported; expected jpeg or png")
        return compression, None, None
    original, _, rest = (part.strip() for part in raw.partition(";"))
    words = rest.split()
    if words and words[0] == "compressedDepth":
        raise ConversionError(f"CompressedImage.format {raw!r} is a compressedDepth image; expected a camera image")
    compression = _ALIASES.get(words[0].lower()) if words else None
    if compression is None or (len(words) > 1 and words[1] != "compressed") or len(words) > 3:
        raise ConversionError(
            f"CompressedImage.format {raw!r} is not supported; expected '<encoding>; <jpeg|png> compressed <encoding>'"
        )
    stored = words[2] if len(words) == 3 else None
    return compression, original or None, stored


def decode_compressed_image(msg: Any) -> tuple[NDArray[np.uint8], str]:
    """Pixels and encoding (``mono8`` or ``rgb8``) of a ``sensor_msgs/CompressedImage`` (module docstring).

    Raises:
        ConversionError: unsupported ``format``, data that does not decode, or an image that is not 8-bit.
    """
    compression, _, stored = parse_format(msg.format)
    data = msg.data
    buffer = data.reshape(-1) if isinstance(data, np.ndarray) else np.frombuffer(bytes(data), dtype=np.uint8)
    if buffer.dtype != np.uint8 or buffer.size == 0:
        raise ConversionError(f"CompressedImage ({msg.format!r}) holds no data")
    pixels = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise ConversionError(
            f"CompressedImage data ({buffer.size} bytes, format {msg.format!r}) "
            f"does not decode as a {compression} image"
        )
    if pixels.dtype != np.uint8:
        raise ConversionError(
            f"CompressedImage ({msg.format!r}) decodes to a {pixels.dtype} image; expected 8-bit (mono8, rgb8, bgr8)"
        )
    if pixels.ndim == 2:
        return np.ascontiguousarray(pixels), "mono8"
    if pixels.ndim != 3 or pixels.shape[2] not in (3, 4):
        raise ConversionError(
            f"CompressedImage ({msg.format!r}) decodes to shape {pixels.shape}; expected 1, 3 or 4 channels"
        )
    colour = pixels[:, :, :3]
    if stored is not None and stored.startswith("rgb"):
        return np.ascontiguousarray(colour), "rgb8"  # stored as RGB: OpenCV kept the order it was given
    return np.ascontiguousarray(colour[:, :, ::-1]), "rgb8"


def compressed_image_fields(pixels: NDArray[np.uint8], encoding: str, image_format: str = "jpeg") -> dict[str, Any]:
    """Fields ``format`` and ``data`` of a ``sensor_msgs/CompressedImage`` (header excluded), as ROS 2's plugin writes.

    ``mono8`` is stored grey (``mono8; jpeg compressed mono8``), colour as BGR
    (``rgb8; jpeg compressed bgr8``), JPEG at quality 95, PNG at OpenCV's default level.

    Raises:
        ConversionError: an unknown ``image_format`` or ``encoding``, or pixels that do not fit the encoding.
    """
    compression = _ALIASES.get(str(image_format).lower())
    if compression is None:
        raise ConversionError(
            f"image format {image_format!r} is not supported; expected one of {', '.join(IMAGE_FORMATS)}"
        )
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(
            f"encoding {encoding!r} cannot be compressed; expected one of {', '.join(IMAGE_ENCODINGS)}"
        )
    array = np.asarray(pixels)
    grey = encoding == "mono8"
    if array.dtype != np.uint8 or array.ndim != (2 if grey else 3) or (not grey and array.shape[2] != 3):
        raise ConversionError(f"pixels of shape {array.shape} ({array.dtype}) do not fit encoding {encoding!r}")
    bgr = array if grey or encoding == "bgr8" else array[:, :, ::-1]
    params = [cv2.IMWRITE_JPEG_QUALITY, _JPEG_QUALITY] if compression == "jpeg" else []
    ok, data = cv2.imencode(".jpg" if compression == "jpeg" else ".png", np.ascontiguousarray(bgr), params)
    if not ok:
        raise ConversionError(f"OpenCV could not encode a {array.shape} image as {compression}")
    stored = "mono8" if grey else "bgr8"
    return {
        "format": f"{encoding}; {compression} compressed {stored}",
        "data": np.asarray(data, dtype=np.uint8).reshape(-1),
    }
