"""Round trips and error reporting of selfcontra_ros.ros.conversions.

Reference layouts are built here independently of the module under test
(rows padded by hand, big-endian bytes from numpy's '>' dtypes), so a
mistake in the module cannot cancel itself out.
"""

from __future__ import annotations

import array
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.errors import CalibrationError, ConversionError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.ros.conversions import (
    ENCODINGS,
    camera_info_fields,
    camera_infos_from_stereo_camera,
    disparity_from_message,
    disparity_image,
    image_fields,
    image_to_numpy,
    nanoseconds_to_stamp,
    numpy_to_image,
    seconds_to_stamp,
    stamp_to_nanoseconds,
    stamp_to_seconds,
    stereo_camera_from_camera_infos,
)

# encoding -> (dtype, channels), written out from sensor_msgs/image_encodings.hpp, not taken from the module.
EXPECTED_LAYOUT: dict[str, tuple[np.dtype[Any], int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),
    "16UC1": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
}
MULTIBYTE = [name for name, (dtype, _) in EXPECTED_LAYOUT.items() if dtype.itemsize > 1]


def random_image(encoding: str, height: int = 5, width: int = 7, seed: int = 0) -> NDArray[Any]:
    """Random pixels covering the whole value range; floats include NaN, +-inf, -0 and subnormals."""
    dtype, channels = EXPECTED_LAYOUT[encoding]
    shape = (height, width) if channels == 1 else (height, width, channels)
    rng = np.random.default_rng(seed)
    raw = rng.integers(0, 256, size=int(np.prod(shape)) * dtype.itemsize, dtype=np.uint8)
    pixels = raw.view(dtype).reshape(shape).copy()
    if dtype == np.float32:
        pixels.flat[:5] = [np.nan, np.inf, -np.inf, -0.0, 1e-45]
    return pixels


def bits(a: NDArray[Any]) -> bytes:
    """Exact bytes in native order: equality of bits, so NaN == NaN and -0 != +0."""
    return np.ascontiguousarray(a).tobytes()


def message_like(pixels: NDArray[Any], encoding: str, *, pad: int = 0, big_endian: bool = False) -> SimpleNamespace:
    """A duck-typed Image with ``pad`` garbage bytes after each row, in the requested byte order."""
    dtype, _ = EXPECTED_LAYOUT[encoding]
    stored = pixels.astype(dtype.newbyteorder(">" if big_endian else "<"))
    rows = np.ascontiguousarray(stored).view(np.uint8).reshape(pixels.shape[0], -1)
    padded = np.full((rows.shape[0], rows.shape[1] + pad), 0xAB, dtype=np.uint8)
    padded[:, : rows.shape[1]] = rows
    return SimpleNamespace(
        height=pixels.shape[0],
        width=pixels.shape[1],
        encoding=encoding,
        is_bigendian=int(big_endian),
        step=padded.shape[1],
        data=padded.tobytes(),
    )


def test_supported_encodings_are_the_documented_ones() -> None:
    assert set(ENCODINGS) == set(EXPECTED_LAYOUT)


@pytest.mark.ros
@pytest.mark.parametrize("encoding", list(EXPECTED_LAYOUT))
def test_rclpy_image_round_trip_is_bit_exact(encoding: str) -> None:
    pixels = random_image(encoding)
    msg = numpy_to_image(pixels, encoding, stamp=seconds_to_stamp(12.5), frame_id="cam")
    dtype, channels = EXPECTED_LAYOUT[encoding]
    assert msg.encoding == encoding
    assert msg.step == pixels.shape[1] * dtype.itemsize * channels  # packed rows
    assert msg.is_bigendian == int(np.little_endian is False)
    assert (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == ("cam", 12, 500_000_000)
    back = image_to_numpy(msg)
    assert back.dtype == dtype and back.shape == pixels.shape
    assert bits(back) == bits(pixels)


@pytest.mark.parametrize("encoding", list(EXPECTED_LAYOUT))
@pytest.mark.parametrize("pad", [1, 3, 64])
def test_padded_rows_are_dropped(encoding: str, pad: int) -> None:
    pixels = random_image(encoding, seed=pad)
    back = image_to_numpy(message_like(pixels, encoding, pad=pad))
    assert back.shape == pixels.shape and back.dtype == pixels.dtype
    assert bits(back) == bits(pixels)


@pytest.mark.parametrize("encoding", MULTIBYTE)
@pytest.mark.parametrize("pad", [0, 2])
def test_big_endian_input_is_swapped_to_native(encoding: str, pad: int) -> None:
    pixels = random_image(encoding, seed=7)
    msg = message_like(pixels, encoding, pad=pad, big_endian=True)
    if pad == 0:  # the bytes really differ from the native layout, so a missing swap would fail
        assert msg.data != np.ascontiguousarray(pixels).tobytes()
    back = image_to_numpy(msg)
    assert back.dtype.isnative
    assert bits(back) == bits(pixels)


def test_big_endian_flag_is_irrelevant_for_bytes() -> None:
    pixels = random_image("rgb8")
    assert bits(image_to_numpy(message_like(pixels, "rgb8", big_endian=True))) == bits(pixels)


@pytest.mark.parametrize("container", ["bytes", "bytearray", "array", "list", "numpy"])
def test_data_field_types(container: str) -> None:
    pixels = random_image("16UC1")
    msg = message_like(pixels, "16UC1", pad=2)
    data: Any = {
        "bytes": lambda b: b,
        "bytearray": bytearray,
        "array": lambda b: array.array("B", b),
        "list": list,
        "numpy": lambda b: np.frombuffer(b, dtype=np.uint8),
    }[container](msg.data)
    msg.data = data
    assert bits(image_to_numpy(msg)) == bits(pixels)


def test_result_owns_its_memory() -> None:
    pixels = random_image("mono8")
    msg = message_like(pixels, "mono8")
    msg.data = bytearray(msg.data)
    back = image_to_numpy(msg)
    assert back.flags.owndata and back.flags.writeable and back.flags.c_contiguous
    msg.data[:] = bytes(len(msg.data))  # clearing the message must not touch the array
    assert bits(back) == bits(pixels)


def test_rosbags_message_round_trip() -> None:
    """The reading side is duck-typed: a rosbags-serialised message converts like an rclpy one."""
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(typesys.Stores.ROS2_KILTED)
    image_type = store.types["sensor_msgs/msg/Image"]
    header_type = store.types["std_msgs/msg/Header"]
    time_type = store.types["builtin_interfaces/msg/Time"]
    pixels = random_image("32FC1", height=4, width=9)
    fields = image_fields(pixels, "32FC1")
    fields["data"] = np.frombuffer(fields["data"], dtype=np.uint8)
    msg = image_type(header=header_type(stamp=time_type(sec=3, nanosec=4), frame_id="left"), **fields)
    decoded = store.deserialize_cdr(store.serialize_cdr(msg, image_type.__msgtype__), image_type.__msgtype__)
    assert bits(image_to_numpy(decoded)) == bits(pixels)


def test_writing_converts_foreign_byte_order_and_accepts_a_channel_axis() -> None:
    pixels = random_image("mono16")
    fields = image_fields(pixels.astype(">u2"), "mono16")
    assert bits(image_to_numpy(SimpleNamespace(**fields))) == bits(pixels)
    fields = image_fields(pixels[:, :, None], "mono16")
    assert bits(image_to_numpy(SimpleNamespace(**fields))) == bits(pixels)


def test_writing_packs_non_contiguous_arrays() -> None:
    pixels = random_image("bgr8", height=6, width=8)
    view = pixels[::2, 1::2]
    fields = image_fields(view, "bgr8")
    assert fields["step"] == view.shape[1] * 3 and len(fields["data"]) == view.shape[0] * fields["step"]
    assert bits(image_to_numpy(SimpleNamespace(**fields))) == bits(view)


# ----------------------------------------------------------------------------- malformed input


def good_message() -> SimpleNamespace:
    return message_like(random_image("rgb8", height=3, width=4), "rgb8", pad=4)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"encoding": "yuv422"}, "encoding"),
        ({"encoding": "8UC3"}, "encoding"),
        ({"step": 11}, "step"),  # one row of 4 rgb8 pixels needs 12 bytes
        ({"data": bytes(3 * 16 - 1)}, "data"),
        ({"data": bytes(3 * 16 + 16)}, "data"),
        ({"height": 4}, "data"),  # data no longer height * step
        ({"data": np.zeros(48, dtype=np.float32)}, "data"),
        ({"data": 12.0}, "data"),
    ],
)
def test_malformed_message_names_the_field(change: dict[str, Any], field: str) -> None:
    msg = good_message()
    for key, value in change.items():
        setattr(msg, key, value)
    with pytest.raises(ConversionError, match=rf"Image\.{field}"):
        image_to_numpy(msg)


@pytest.mark.parametrize(
    ("array_", "encoding", "word"),
    [
        (np.zeros((2, 3), np.float64), "32FC1", "dtype"),
        (np.zeros((2, 3), np.int16), "16UC1", "dtype"),
        (np.zeros((2, 3, 3), np.uint16), "rgb8", "dtype"),
        (np.zeros((2, 3), bool), "mono8", "dtype"),
        (np.zeros((2, 3), np.uint8), "rgb8", "shape"),
        (np.zeros((2, 3, 4), np.uint8), "rgb8", "shape"),
        (np.zeros((2, 3, 3), np.uint8), "mono8", "shape"),
        (np.zeros(6, np.uint8), "mono8", "shape"),
        (np.zeros((2, 3), np.uint8), "jpeg", "encoding"),
    ],
)
def test_array_not_matching_encoding(array_: NDArray[Any], encoding: str, word: str) -> None:
    with pytest.raises(ConversionError, match=word):
        image_fields(array_, encoding)


# ----------------------------------------------------------------------------- disparity


@pytest.fixture
def camera() -> StereoCamera:
    return StereoCamera(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854, baseline=0.5327, width=40, height=30)


@pytest.mark.ros
def test_disparity_image_round_trip(camera: StereoCamera) -> None:
    rng = np.random.default_rng(3)
    disparity = rng.uniform(0.5, 120.0, size=(camera.height, camera.width)).astype(np.float32)
    invalid = rng.random(disparity.shape) < 0.2
    disparity[invalid] = np.nan
    disparity[0, 0] = np.inf  # also invalid
    invalid[0, 0] = True

    msg = disparity_image(disparity, camera, stamp=seconds_to_stamp(7.25), frame_id="left", delta_d=0.25)

    # stereo_msgs conventions, checked on the message itself.
    assert msg.image.encoding == "32FC1"
    assert msg.header.frame_id == msg.image.header.frame_id == "left"
    assert msg.header.stamp == msg.image.header.stamp == seconds_to_stamp(7.25)
    assert (msg.valid_window.x_offset, msg.valid_window.y_offset) == (0, 0)
    assert (msg.valid_window.width, msg.valid_window.height) == (camera.width, camera.height)
    raw = image_to_numpy(msg.image)
    assert np.all(np.isfinite(raw))  # invalid pixels are encoded below min_disparity, not as NaN
    assert np.all(raw[invalid] < msg.min_disparity)
    assert msg.min_disparity == 0.0
    assert msg.max_disparity == pytest.approx(float(np.nanmax(disparity[~invalid])))
    assert msg.delta_d == 0.25

    back, f, t = disparity_from_message(msg)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(back), invalid)
    np.testing.assert_array_equal(back[~invalid], disparity[~invalid])
    assert f == pytest.approx(camera.fx, rel=1e-7) and t == pytest.approx(camera.baseline, rel=1e-7)
    # Z = f * T / d as stereo_msgs defines it agrees with the camera model.
    np.testing.assert_allclose(f * t / back[~invalid], camera.disparity_to_depth(disparity)[~invalid], rtol=1e-6)


@pytest.mark.ros
def test_disparity_below_min_disparity_reads_as_invalid(camera: StereoCamera) -> None:
    disparity = np.full((camera.height, camera.width), 20.0, dtype=np.float32)
    disparity[5, 5] = 3.0
    msg = disparity_image(disparity, camera, min_disparity=4.0, max_disparity=96.0)
    back, _, _ = disparity_from_message(msg)
    assert np.isnan(back[5, 5]) and np.count_nonzero(np.isnan(back)) == 1
    assert msg.max_disparity == 96.0


@pytest.mark.ros
def test_disparity_errors(camera: StereoCamera) -> None:
    with pytest.raises(ConversionError, match="shape"):
        disparity_image(np.zeros((camera.width, camera.height), np.float32), camera)
    msg = disparity_image(np.zeros((camera.height, camera.width), np.float32), camera)
    msg.image = numpy_to_image(np.zeros((camera.height, camera.width), np.uint16), "16UC1")
    with pytest.raises(ConversionError, match=r"DisparityImage\.image\.encoding"):
        disparity_from_message(msg)


# ----------------------------------------------------------------------------- camera info


def kitti_colour_like_infos() -> tuple[SimpleNamespace, SimpleNamespace]:
    """Rectified colour cameras 2/3 of KITTI: both offset from the reference camera 0 (left Tx != 0)."""
    fx, cx, cy = 721.5377, 609.5593, 172.854
    tx_left, tx_right = 44.85728, -339.5242  # P[0,3] = fx * t_x of cameras 2 and 3
    infos = []
    for tx in (tx_left, tx_right):
        p = [fx, 0.0, cx, tx, 0.0, fx, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        infos.append(SimpleNamespace(width=1242, height=375, p=np.array(p), binning_x=0, binning_y=0, roi=None))
    return infos[0], infos[1]


def test_kitti_colour_pair_baseline() -> None:
    left, right = kitti_colour_like_infos()
    camera = stereo_camera_from_camera_infos(left, right)
    # Camera 2 sits 6 cm left of camera 0 and camera 3 47 cm right of it: about 0.53 m apart.
    assert camera.baseline == pytest.approx((44.85728 + 339.5242) / 721.5377, rel=1e-12)
    assert 0.52 < camera.baseline < 0.54
    assert (camera.width, camera.height, camera.fx, camera.cx) == (1242, 375, 721.5377, 609.5593)


@pytest.mark.ros
def test_camera_info_round_trip(camera: StereoCamera) -> None:
    left, right = camera_infos_from_stereo_camera(camera, seconds_to_stamp(1.5), "left_optical")
    assert left.header.frame_id == right.header.frame_id == "left_optical"
    assert left.header.stamp == seconds_to_stamp(1.5)
    assert left.p[3] == 0.0 and right.p[3] == pytest.approx(-camera.fx * camera.baseline)
    np.testing.assert_array_equal(np.asarray(left.k).reshape(3, 3), camera.K)
    back = stereo_camera_from_camera_infos(left, right)
    for name in ("fx", "fy", "cx", "cy", "baseline"):
        assert getattr(back, name) == pytest.approx(getattr(camera, name), rel=1e-12)
    assert (back.width, back.height) == (camera.width, camera.height)
    again = camera_infos_from_stereo_camera(back, seconds_to_stamp(1.5), "left_optical", right_frame_id="right")
    assert again[1].header.frame_id == "right"
    for a, b in zip((left, right), again, strict=True):
        np.testing.assert_allclose(a.p, b.p, rtol=1e-12)
        assert (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model)


def bad_info_pair(**changes: Any) -> tuple[SimpleNamespace, SimpleNamespace]:
    camera = StereoCamera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, baseline=0.1, width=640, height=480)
    left = SimpleNamespace(**camera_info_fields(camera), roi=None)
    right = SimpleNamespace(**camera_info_fields(camera, right=True), roi=None)
    for key, value in changes.items():
        side, field = key.split("__")
        setattr(left if side == "left" else right, field, value)
    return left, right


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"right__width": 320}, "width/height differ"),
        ({"left__height": 0}, "left camera_info width/height"),
        ({"right__p": np.zeros(12)}, "right camera_info P is all zeros"),
        ({"left__p": np.zeros(12)}, "left camera_info P is all zeros"),
        ({"right__p": np.array([510.0, 0, 320, -50, 0, 510, 240, 0, 0, 0, 1, 0])}, "not rectified"),
        ({"right__p": np.array([500.0, 0, 320, 50, 0, 500, 240, 0, 0, 0, 1, 0])}, "baseline"),
        ({"left__binning_x": 2}, "binning_x"),
        ({"right__roi": SimpleNamespace(x_offset=10, y_offset=0, width=100, height=100)}, "roi"),
    ],
)
def test_bad_camera_infos(changes: dict[str, Any], pattern: str) -> None:
    left, right = bad_info_pair(**changes)
    with pytest.raises(CalibrationError, match=pattern):
        stereo_camera_from_camera_infos(left, right)


def test_full_image_roi_is_accepted() -> None:
    left, right = bad_info_pair(left__roi=SimpleNamespace(x_offset=0, y_offset=0, width=640, height=480))
    assert stereo_camera_from_camera_infos(left, right).baseline == pytest.approx(0.1)


# ----------------------------------------------------------------------------- stamps


@pytest.mark.ros
@pytest.mark.parametrize(
    "nanoseconds", [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_500_000_000]
)
def test_stamp_nanoseconds_are_exact(nanoseconds: int) -> None:
    stamp = nanoseconds_to_stamp(nanoseconds)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert stamp.sec * 1_000_000_000 + stamp.nanosec == nanoseconds
    assert stamp_to_nanoseconds(stamp) == nanoseconds


@pytest.mark.ros
def test_seconds_to_stamp_rounds_to_the_nearest_nanosecond() -> None:
    assert stamp_to_nanoseconds(seconds_to_stamp(12.5)) == 12_500_000_000
    assert stamp_to_nanoseconds(seconds_to_stamp(-0.25)) == -250_000_000
    assert stamp_to_nanoseconds(seconds_to_stamp(0.9999999999)) == 1_000_000_000  # carries into the seconds
    # At today's epoch a float64 holds about 0.24 us: the stamp is the float's value to the nanosecond.
    t = 1_700_000_000.123456
    stamp = seconds_to_stamp(t)
    exact = (1_700_000_000, round((t - 1_700_000_000) * 1e9))
    assert (stamp.sec, stamp.nanosec) == exact
    assert stamp_to_seconds(stamp) == pytest.approx(t, abs=1e-9)
    with pytest.raises(ConversionError, match="finite"):
        seconds_to_stamp(float("nan"))


def test_stamp_to_seconds_is_duck_typed() -> None:
    assert stamp_to_seconds(SimpleNamespace(sec=2, nanosec=250_000_000)) == 2.25
