"""What the launch file gives each node for a robot bag (its pure part: no ROS 2 launch needed)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

LAUNCH_FILE = Path(__file__).resolve().parents[2] / "launch" / "selfcontra.launch.py"
DRIVER_REMAPS = "left/image_raw:=cam_left/image_raw, right/image_raw:=cam_right/image_raw"


@pytest.fixture(scope="module")
def launch() -> ModuleType:
    spec = importlib.util.spec_from_file_location("_selfcontra_launch", LAUNCH_FILE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # importable without launch / launch_ros (guarded import)
    return module


def test_defaults_leave_the_parameter_file_alone(launch: ModuleType) -> None:
    player, labeler, remappings = launch.node_settings({}, "/stereo")
    assert player == {"wait_for_subscribers": 5} and labeler == {} and remappings == []


def test_robot_bag_with_tf_converted_by_the_player(launch: ModuleType) -> None:
    values = {
        "image_transport": "compressed",
        "rectify": "true",
        "sync": "approximate",
        "slop": "0.005",
        "remaps": DRIVER_REMAPS,
        "pose_source": "tf",
        "world_frame": "odom",
    }
    player, labeler, remappings = launch.node_settings(values, "/sensors/stereo")
    assert labeler == {
        "image_transport": "compressed",
        "rectify": True,
        "sync": "approximate",
        "slop": 0.005,
        "pose_source": "pose",  # the player's PoseStamped
    }
    assert player == {
        "wait_for_subscribers": 5,
        "pose_source": "tf",
        "stereo_namespace": "/sensors/stereo",
        "image_transport": "compressed",
        "rectify": True,
        "world_frame": "odom",
        "camera_frame": "",
        "remaps": ["left/image_raw:=cam_left/image_raw", "right/image_raw:=cam_right/image_raw"],
    }
    assert remappings == [("left/image_raw", "cam_left/image_raw"), ("right/image_raw", "cam_right/image_raw")]


def test_tf_read_by_the_labeler(launch: ModuleType) -> None:
    values = {"pose_source": "tf", "tf_in_labeler": "true", "world_frame": "map", "camera_frame": "cam"}
    player, labeler, _ = launch.node_settings(values, "/stereo")
    assert labeler == {"pose_source": "tf", "world_frame": "map", "camera_frame": "cam"}
    assert "pose_source" not in player  # /tf played as recorded


def test_odometry_poses_estimated_by_the_labeler(launch: ModuleType) -> None:
    player, labeler, _ = launch.node_settings({"pose_source": "odometry"}, "/stereo")
    assert labeler == {"pose_source": "odometry"}
    assert player == {"wait_for_subscribers": 4}  # images and camera infos; no pose subscription


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"rectify": "yes"}, "rectify:='yes' must be true or false"),
        ({"pose_source": "gps"}, "must be pose, tf or odometry"),
        ({"remaps": "left/image_raw=cam"}, "is not FROM:=TO"),
    ],
)
def test_bad_launch_arguments_are_named(launch: ModuleType, values: dict[str, str], message: str) -> None:
    with pytest.raises(Exception, match=message):
        launch.node_settings(values, "/stereo")
