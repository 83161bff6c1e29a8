"""CompressedImage decoding and encoding with image_transport's format strings (bags/compressed.py)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from selfcontra_ros.bags.compressed import compressed_image_fields, decode_compressed_image, parse_format
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.reader import default_typestore
from selfcontra_ros.errors import ConversionError


def _image(colour: bool) -> np.ndarray:
    rng = np.random.default_rng(3)
    grey = cv2.GaussianBlur(rng.integers(0, 256, (48, 64)).astype(np.uint8), (5, 5), 1.5)
    if not colour:
        return grey
    return np.dstack([grey, 255 - grey, np.full_like(grey, 40)])  # distinct channels: an order swap shows


def _msg(fmt: str, data: np.ndarray | bytes) -> SimpleNamespace:
    return SimpleNamespace(format=fmt, data=data)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("jpeg", ("jpeg", None, None)),
        ("png", ("png", None, None)),
        ("JPG", ("jpeg", None, None)),
        ("mono8; jpeg compressed mono8", ("jpeg", "mono8", "mono8")),
        ("bgr8; png compressed bgr8", ("png", "bgr8", "bgr8")),
        ("rgb8; jpeg compressed bgr8", ("jpeg", "rgb8", "bgr8")),
        ("rgb8; jpeg compressed", ("jpeg", "rgb8", None)),
    ],
)
def test_formats(text: str, expected: tuple[str, str | None, str | None]) -> None:
    assert parse_format(text) == expected


@pytest.mark.parametrize("text", ["", "webp", "16UC1; compressedDepth png", "rgb8; theora", "rgb8; jpeg packed bgr8"])
def test_unsupported_formats(text: str) -> None:
    with pytest.raises(ConversionError, match="format"):
        parse_format(text)


@pytest.mark.parametrize("encoding", ["mono8", "rgb8", "bgr8"])
def test_png_round_trip_is_exact(encoding: str) -> None:
    pixels = _image(encoding != "mono8")
    fields = compressed_image_fields(pixels, encoding, "png")
    assert fields["format"] == f"{encoding}; png compressed {'mono8' if encoding == 'mono8' else 'bgr8'}"
    decoded, decoded_encoding = decode_compressed_image(_msg(fields["format"], fields["data"]))
    # The package's convention: grey stays mono8, colour comes back as RGB.
    expected = pixels[:, :, ::-1] if encoding == "bgr8" else pixels
    assert decoded_encoding == ("mono8" if encoding == "mono8" else "rgb8")
    np.testing.assert_array_equal(decoded, expected)


def test_jpeg_round_trip_is_close() -> None:
    pixels = _image(True)
    fields = compressed_image_fields(pixels, "rgb8", "jpeg")
    decoded, encoding = decode_compressed_image(_msg(fields["format"], bytes(fields["data"])))
    assert encoding == "rgb8" and decoded.shape == pixels.shape
    # Quality 95, but JPEG keeps colour at half resolution (4:2:0), and these channels differ strongly at
    # every pixel: a few grey levels per channel (5.5 measured); a swapped channel order would be off by ~100.
    error = np.abs(decoded.astype(int) - pixels.astype(int)).mean(axis=(0, 1))
    assert np.all(error < 10.0), error


def test_plain_formats_hold_opencv_bgr_and_stored_rgb_keeps_its_order() -> None:
    pixels = _image(True)  # RGB
    _, bgr_png = cv2.imencode(".png", pixels[:, :, ::-1])
    np.testing.assert_array_equal(decode_compressed_image(_msg("png", bgr_png))[0], pixels)
    _, rgb_png = cv2.imencode(".png", pixels)  # a writer that handed RGB to OpenCV and said so
    np.testing.assert_array_equal(decode_compressed_image(_msg("rgb8; png compressed rgb8", rgb_png))[0], pixels)
    rgba = np.dstack([pixels[:, :, ::-1], np.full(pixels.shape[:2], 255, np.uint8)])
    _, png4 = cv2.imencode(".png", rgba)
    np.testing.assert_array_equal(decode_compressed_image(_msg("bgra8; png compressed bgra8", png4))[0], pixels)


def test_bad_data_is_a_conversion_error() -> None:
    with pytest.raises(ConversionError, match="does not decode as a jpeg image"):
        decode_compressed_image(_msg("jpeg", np.arange(100, dtype=np.uint8)))
    with pytest.raises(ConversionError, match="holds no data"):
        decode_compressed_image(_msg("png", b""))
    _, deep = cv2.imencode(".png", np.zeros((4, 4), np.uint16))
    with pytest.raises(ConversionError, match="expected 8-bit"):
        decode_compressed_image(_msg("mono16; png compressed mono16", deep))
    with pytest.raises(ConversionError, match="not supported"):
        compressed_image_fields(_image(False), "mono8", "webp")
    with pytest.raises(ConversionError, match="do not fit"):
        compressed_image_fields(_image(True), "mono8", "png")


def test_message_builder_writes_compressed_images() -> None:
    pixels = _image(False)
    msg = MessageBuilder(default_typestore()).compressed_image(pixels, "mono8", 5, "cam", image_format="png")
    assert msg.header.frame_id == "cam" and msg.format == "mono8; png compressed mono8"
    np.testing.assert_array_equal(decode_compressed_image(msg)[0], pixels)
