"""The player's ``pose_source: tf`` refuses what it cannot do (exit code 2), with a message naming what is missing."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.datasets.synthetic import write_sequence

pytestmark = pytest.mark.ros

WAIT_S = 60.0
PLAYER = ["-m", "selfcontra_ros.ros.player_node", "--ros-args"]


@pytest.fixture(scope="module")
def package_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A bag in the package's own layout: /stereo/... images and a PoseStamped, no TF."""
    root = tmp_path_factory.mktemp("player_tf")
    write_sequence(root / "data", scene="street", frames=2, seed=1, width=320, height=96)
    return kitti_to_mcap(root / "data", root / "bag", progress=False)


@pytest.mark.parametrize(
    ("parameters", "message"),
    [
        (["pose_source:=tf"], "pose_source 'tf' needs world_frame"),
        (["pose_source:=gps"], "expected one of none, tf"),
        (["pose_source:=tf", "world_frame:=odom"], "has neither /tf nor /tf_static"),
        (["pose_source:=tf", "world_frame:=odom", "rectify:=true"], "no <namespace>/left/image_raw topic"),
        (["pose_source:=tf", "world_frame:=odom", "rectify:=true"], "parameters: remaps, stereo_namespace"),
    ],
)
def test_pose_source_tf_errors_name_the_problem(
    package_bag: Path, ros_process: Callable[..., Any], parameters: list[str], message: str
) -> None:
    args = [arg for parameter in [f"bag:={package_bag}", *parameters] for arg in ("-p", parameter)]
    player = ros_process([*PLAYER, *args], name="player")
    assert player.popen.wait(timeout=WAIT_S) == 2, player.stderr()
    assert message in player.stderr() and "Traceback" not in player.stderr()
