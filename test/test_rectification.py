"""Rectification from distorted camera infos: a known calibration undone (rectification.py, bags/robot_bag.distort)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest

from selfcontra_ros.bags.robot_bag import distort, raw_calibration
from selfcontra_ros.errors import CalibrationError, ConversionError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.rectification import Rectifier, calibration_key

CAMERA = StereoCamera(fx=300.0, fy=300.0, cx=161.5, cy=59.0, baseline=0.12, width=320, height=120)
MARGIN = 12  # pixels: the rim where the raw cameras see past the rectified images


def _info(fields: dict[str, Any], frame: str = "cam") -> SimpleNamespace:
    return SimpleNamespace(header=SimpleNamespace(frame_id=frame), **fields)


def _texture(seed: int) -> np.ndarray:
    """A smooth random texture (blurred noise), so that two bilinear resamplings change it little."""
    noise = np.random.default_rng(seed).integers(0, 256, (CAMERA.height, CAMERA.width)).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 3.0)
    return np.clip((blurred - blurred.mean()) * 6.0 + 128.0, 0, 255).astype(np.uint8)


def test_rectifying_a_distorted_pair_gives_back_the_original() -> None:
    left_fields, right_fields = raw_calibration(CAMERA)
    assert left_fields["distortion_model"] == "plumb_bob" and right_fields["distortion_model"] == "rational_polynomial"
    rectifier = Rectifier.from_camera_infos(_info(left_fields), _info(right_fields))
    # From the two P matrices: intrinsics, and the baseline from P_right[0,3] = -fx * b (to rounding).
    assert dataclasses.replace(rectifier.camera, baseline=CAMERA.baseline) == CAMERA
    assert rectifier.camera.baseline == pytest.approx(CAMERA.baseline, rel=1e-12)
    np.testing.assert_allclose(rectifier.raw_from_rectified[:3, :3], np.asarray(left_fields["r"]).T)
    for right, fields, seed in ((False, left_fields, 1), (True, right_fields, 2)):
        original = _texture(seed)
        raw = distort(original, fields)
        inner = np.s_[MARGIN:-MARGIN, MARGIN:-MARGIN]
        before = np.abs(raw.astype(float) - original)[inner].mean()
        after = np.abs(rectifier.rectify(raw, right=right).astype(float) - original)[inner].mean()
        # Two bilinear resamplings (the second with OpenCV's 1/32-px fixed-point maps) of a texture whose
        # gradient is about 8 grey levels per pixel leave about 1 level (0.95 measured); the distortion
        # itself (pixels displaced by up to several px) leaves over 20.
        assert after < 2.0, after
        assert before > 10 * after, (before, after)


def test_colour_images_and_sizes() -> None:
    left_fields, right_fields = raw_calibration(CAMERA)
    rectifier = Rectifier.from_camera_infos(_info(left_fields), _info(right_fields))
    colour = np.dstack([_texture(3)] * 3)
    assert rectifier.rectify(colour, right=False).shape == colour.shape
    with pytest.raises(ConversionError, match="raw image is 100x50"):
        rectifier.rectify(np.zeros((50, 100), np.uint8), right=True)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"distortion_model": "equidistant"}, "fisheye / equidistant"),
        ({"d": np.zeros(6)}, "D has 6 coefficients"),
        ({"k": np.zeros(9)}, "K is all zeros"),
        ({"r": np.diag([1.0, 1.0, -1.0])}, "R is not a rotation"),
        ({"width": 64}, "sizes differ"),
    ],
)
def test_bad_calibrations_name_the_field(change: dict[str, Any], message: str) -> None:
    left_fields, right_fields = raw_calibration(CAMERA)
    with pytest.raises(CalibrationError, match=message):
        Rectifier.from_camera_infos(_info({**left_fields, **change}), _info(right_fields))


def test_calibration_key_changes_with_the_calibration() -> None:
    left_fields, _ = raw_calibration(CAMERA)
    same = calibration_key(_info(left_fields)) == calibration_key(_info(dict(left_fields)))
    other = calibration_key(_info({**left_fields, "d": np.zeros(5)}))
    assert same and other != calibration_key(_info(left_fields))
