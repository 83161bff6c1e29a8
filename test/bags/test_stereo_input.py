"""Remaps, topic map, namespaces and the stored input description (bags/stereo_input.py)."""

from __future__ import annotations

import pytest

from selfcontra_ros.bags.reader import BagError
from selfcontra_ros.bags.stereo_input import StereoInput, parse_remaps, topic_map
from selfcontra_ros.errors import SelfContraError


def test_topic_map_applies_remaps_like_a_node() -> None:
    rules = ["left/image_rect:=/zed/zed_node/left/image_rect_color", "right/image_rect:=right/image_rect_color"]
    names = topic_map("/zed/zed_node", rules, image_transport="compressed")
    # image_transport appends /compressed to the (remapped) base topic; relative targets live in the namespace.
    assert names["left/image_rect"] == "/zed/zed_node/left/image_rect_color/compressed"
    assert names["right/image_rect"] == "/zed/zed_node/right/image_rect_color/compressed"
    assert names["left/camera_info"] == "/zed/zed_node/left/camera_info"
    assert names["labels"] == "/zed/zed_node/labels"
    assert names["tf"] == "/tf" and names["tf_static"] == "/tf_static"
    assert topic_map("/s", ["/tf:=/robot/tf"])["tf"] == "/robot/tf"
    assert topic_map("/s")["left/image_raw"] == "/s/left/image_raw"


@pytest.mark.parametrize(
    ("rule", "message"),
    [("left/image_rect", "not FROM:=TO"), ("left/image:=/x", "not a name the package reads"), (":=/x", "FROM:=TO")],
)
def test_bad_remaps(rule: str, message: str) -> None:
    with pytest.raises(SelfContraError, match=message):
        parse_remaps([rule])


def test_input_validation() -> None:
    with pytest.raises(SelfContraError, match="needs world_frame"):
        StereoInput(pose_source="tf")
    with pytest.raises(SelfContraError, match="pose_source 'tf' only"):
        StereoInput(world_frame="odom")
    with pytest.raises(SelfContraError, match="image_transport"):
        StereoInput(image_transport="theora")
    stored = StereoInput(image_transport="compressed", rectify=True, remaps=("left/image_raw:=a/b",), pose_source="tf",
                         world_frame="map")  # fmt: skip
    assert StereoInput.from_json(stored.to_json()) == stored
    assert StereoInput.of_bag({"selfcontra.input": stored.to_json()}) == stored
    assert StereoInput.of_bag({}) == StereoInput()


def test_namespace_detection() -> None:
    names = ["/cam/left/image_raw/compressed", "/cam/right/image_raw/compressed", "/cam/left/camera_info"]
    assert StereoInput(rectify=True, image_transport="compressed").namespace(names) == "/cam"
    with pytest.raises(BagError, match="try --image-transport compressed"):
        StereoInput(rectify=True).namespace(names)
    assert StereoInput(remaps=("left/image_rect:=/abs/left",)).namespace(names) == "/stereo"
    assert StereoInput().namespace(names, "robot/") == "/robot"
