"""config/foxglove_layout.json: a Foxglove layout whose panels show the package's own topics of a labelled bag."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.label_bag import resolve_namespace
from selfcontra_ros.resources import config_file

LAYOUT = Path(__file__).resolve().parents[1] / "config" / "foxglove_layout.json"

#: What the layout must show (relative names of selfcontra_ros.bags.topics).
SHOWN = (topics.LEFT_IMAGE, topics.LABELS_COLOR, topics.CONFIDENCE, topics.DEPTH, topics.DEPTH_FILTERED)


def _leaves(node: Any) -> list[str]:
    """Panel ids of a Foxglove mosaic tree (a panel id, or {first, second, direction, splitPercentage})."""
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"first", "second", "direction", "splitPercentage"}, node
    assert node["direction"] in ("row", "column")
    assert 0 < float(node.get("splitPercentage", 50)) < 100
    return _leaves(node["first"]) + _leaves(node["second"])


def _package_topics() -> set[str]:
    """Every topic name topics.py defines, as a bag written by the package stores it (under /stereo)."""
    names = {
        value
        for key, value in vars(topics).items()
        if key.isupper() and isinstance(value, str) and not key.endswith(("_TYPE", "_FRAME", "_NAMESPACE", "_SUFFIX"))
    }
    return {topics.bag_topic(n) for n in names if not n.startswith("/")}


def test_layout_is_foxglove_json_with_one_image_panel_per_topic() -> None:
    layout = json.loads(LAYOUT.read_text())
    assert {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"} <= set(layout)
    panels = _leaves(layout["layout"])
    assert sorted(panels) == sorted(layout["configById"]) and len(set(panels)) == len(panels)
    shown = []
    for panel_id in panels:
        kind, _, suffix = panel_id.partition("!")
        assert kind == "Image" and suffix, f"panel id {panel_id!r} is not of the form 'Image!<id>'"
        mode = layout["configById"][panel_id]["imageMode"]
        shown.append(mode["imageTopic"])
        if "minValue" in mode:
            assert mode["minValue"] < mode["maxValue"]
    assert shown == [topics.bag_topic(name) for name in SHOWN]  # in reading order: row by row


def test_every_topic_of_the_layout_exists_in_topics_py() -> None:
    layout = json.loads(LAYOUT.read_text())
    known = _package_topics()
    named = [
        value
        for config in layout["configById"].values()
        for key, value in config["imageMode"].items()
        if key.endswith("Topic")
    ]
    assert named and all(name in known for name in named), sorted(set(named) - known)
    # The labelled bag of a package bag keeps the /stereo namespace the layout names.
    assert resolve_namespace({topics.bag_topic(topics.LEFT_IMAGE)}) == topics.STEREO_NAMESPACE == "/stereo"


def test_layout_is_installed_with_the_config_files() -> None:
    assert config_file("foxglove_layout.json").read_text() == LAYOUT.read_text()
