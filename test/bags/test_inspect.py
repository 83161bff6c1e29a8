"""selfcontra inspect: which image pair needs rectifying, judged by topic name and camera_info distortion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.inspect import inspect_bag, suggest_command
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.geometry import StereoCamera

CAMERA = StereoCamera(fx=200.0, fy=200.0, cx=80.0, cy=40.0, baseline=0.05, width=160, height=80)
#: A distortion some drivers leave in camera_info beside already-rectified images (RealSense, ZED).
DISTORTION = [0.1, -0.02, 0.0, 0.0, 0.001]


def _bag(path: Path, image: str) -> Path:
    """Two frames of ``/camera/<side>/<image>`` (mono8) with camera infos whose D is non-zero."""
    with BagWriter(path) as writer:
        make = MessageBuilder(writer.typestore)
        for side in ("infra1", "infra2"):
            writer.add_topic(f"/camera/{side}/{image}", topics.IMAGE_TYPE)
            writer.add_topic(f"/camera/{side}/camera_info", topics.CAMERA_INFO_TYPE)
        for i in range(2):
            stamp = 1_000_000_000 + i * 100_000_000
            for side, right in (("infra1", False), ("infra2", True)):
                info = make.camera_info(CAMERA, stamp, f"camera_{side}_optical_frame", right=right)
                info.distortion_model, info.d = "plumb_bob", np.asarray(DISTORTION)
                writer.write(f"/camera/{side}/camera_info", stamp, info)
                pixels = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
                writer.write(f"/camera/{side}/{image}", stamp, make.image(pixels, "mono8", stamp, info.header.frame_id))
    return path


@pytest.mark.parametrize(("image", "raw"), [("image_rect_raw", False), ("image_raw", True)])
def test_rectified_topics_named_raw_are_not_rectified_again(tmp_path: Path, image: str, raw: bool) -> None:
    """RealSense's image_rect_raw is rectified ("rect" in the name) although its camera_info has a D."""
    report = inspect_bag(_bag(tmp_path / "bag", image))
    assert [(p.left, p.raw) for p in report.pairs] == [(f"/camera/infra1/{image}", raw)]
    command = suggest_command(report)
    assert command is not None and ("--rectify" in command.split()) is raw
