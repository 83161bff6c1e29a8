"""The labeler node's ``threads`` parameter over a real ROS 2 graph: applied at start, logged, in ``~/stats``."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from typing import Any

import pytest

from selfcontra_ros.resources import config_file

pytestmark = pytest.mark.ros

# Upper bound (s) of the waits for a node: a passing run never waits it out, but a loaded 2-core machine needs the
# slack (a node process takes seconds to import and to load its kernels from numba's cache, more when others run).
WAIT_S = 60.0

NODE = ["-m", "selfcontra_ros.ros.labeler_node", "--ros-args"]


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@pytest.mark.parametrize(("value", "expected"), [("1", lambda: 1), ("0", _cores)], ids=["one", "all"])
def test_node_applies_and_reports_its_thread_cap(
    ros_process: Callable[..., Any],
    ros_node: Any,
    spin_until: Callable[..., bool],
    value: str,
    expected: Callable[[], int],
) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    received: list[dict[str, Any]] = []
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros_node.create_subscription(String, "/labeler/stats", lambda msg: received.append(json.loads(msg.data)), qos)
    # The package's YAML (with its own threads: 0) first, so the command line must override it.
    node = ros_process(
        [
            *NODE,
            "--params-file",
            str(config_file("labeler.yaml")),
            "-p",
            f"threads:={value}",
            "-p",
            "stats_period:=0.1",
        ],
        name="labeler",
    )
    assert spin_until(ros_node, lambda: bool(received) or node.popen.poll() is not None, WAIT_S), node.stderr()
    assert received, node.stderr()
    assert received[-1]["threads"] == expected()
    assert node.stop() == 0
    assert f"threads: {expected()} per pool" in node.stderr()


def test_negative_threads_stop_the_node_with_code_2(ros_process: Callable[..., Any]) -> None:
    node = ros_process([*NODE, "-p", "threads:=-1"], name="labeler")
    assert node.popen.wait(timeout=WAIT_S) == 2, node.stderr()
    assert "threads" in node.stderr() and "Traceback" not in node.stderr()
