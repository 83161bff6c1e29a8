"""Two real rclpy processes on loopback: full-size best-effort images through the packaged Fast DDS profile."""

from __future__ import annotations

import importlib.util
import os
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.resources import config_file

HERE = Path(__file__).resolve().parent
PUBLISHER = HERE / "_image_publisher.py"
NS = {"dds": "http://www.eprosima.com"}


def _load_publisher_module() -> ModuleType:
    # --import-mode=importlib keeps test/ros off sys.path, so load the helper by file name.
    spec = importlib.util.spec_from_file_location("_selfcontra_image_publisher", PUBLISHER)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


publisher_module = _load_publisher_module()


def test_profile_declares_large_shm_and_loopback_udp() -> None:
    root = ET.parse(config_file("fastdds_profile.xml")).getroot()
    descriptors = {
        d.findtext("dds:transport_id", namespaces=NS): d for d in root.iterfind(".//dds:transport_descriptor", NS)
    }
    participant = root.find(".//dds:participant", NS)
    assert participant is not None and participant.get("is_default_profile") == "true"
    used = [t.text for t in participant.iterfind("dds:rtps/dds:userTransports/dds:transport_id", NS)]
    assert participant.findtext("dds:rtps/dds:useBuiltinTransports", namespaces=NS) == "false"
    kinds = {descriptors[name].findtext("dds:type", namespaces=NS): descriptors[name] for name in used}
    assert set(kinds) == {"SHM", "UDPv4"}
    assert int(kinds["SHM"].findtext("dds:segment_size", namespaces=NS) or 0) == 16 * 1024 * 1024
    whitelist = [a.text for a in kinds["UDPv4"].iterfind("dds:interfaceWhiteList/dds:address", NS)]
    assert whitelist == ["127.0.0.1"]


def test_prepare_ros_environment_defaults_to_the_packaged_profile(monkeypatch: pytest.MonkeyPatch) -> None:
    from selfcontra_ros.ros.environment import prepare_ros_environment

    variable = "FASTDDS_DEFAULT_PROFILES_FILE"
    monkeypatch.delenv(variable, raising=False)
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    prepare_ros_environment()
    assert os.environ[variable] == str(config_file("fastdds_profile.xml"))
    assert Path(os.environ[variable]).is_file()
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in os.environ  # left to the user: graphs may span machines

    monkeypatch.setenv(variable, "/robot/own_profile.xml")
    prepare_ros_environment()
    assert os.environ[variable] == "/robot/own_profile.xml"

    monkeypatch.setenv(variable, "")  # "no profile": removed, so Fast DDS does not try to open ""
    prepare_ros_environment()
    assert variable not in os.environ


@pytest.mark.ros
def test_fastdds_xml_errors_would_show_on_stderr(
    ros_process: Callable[..., Any], ros_environment: dict[str, str], tmp_path: Path
) -> None:
    """Negative control for the 'no XML errors' check below: a broken profile is reported on stderr."""
    broken = tmp_path / "broken.xml"
    broken.write_text('<dds xmlns="http://www.eprosima.com"><profiles><participant>')
    code = "import rclpy; rclpy.init(); rclpy.create_node('probe').destroy_node(); rclpy.shutdown()"
    proc = ros_process(["-c", code], extra_env={"FASTDDS_DEFAULT_PROFILES_FILE": str(broken)}, name="probe")
    assert proc.popen.wait(timeout=20) == 0
    assert "XMLPARSER" in proc.stderr()


@pytest.mark.ros
def test_large_best_effort_images_cross_processes(
    capfd: pytest.CaptureFixture[str],  # first, so that it also sees what rclpy.init in ros_node prints
    ros_process: Callable[..., Any],
    ros_node: Any,
    spin_until: Callable[[Any, Callable[[], bool], float], bool],
    ros_environment: dict[str, str],
) -> None:
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from selfcontra_ros.ros.conversions import image_to_numpy
    from selfcontra_ros.ros.environment import prepare_ros_environment

    prepare_ros_environment()  # what every executable does; the fixture already chose the packaged profile
    assert os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] == str(config_file("fastdds_profile.xml"))
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"

    topic = f"selfcontra_test_images_{os.getpid()}"
    good: list[int] = []
    bad: list[str] = []

    def on_image(msg: Image) -> None:
        try:
            index = publisher_module.frame_index(msg.header.frame_id)
            pixels = image_to_numpy(msg)
            if pixels.shape != (publisher_module.HEIGHT, publisher_module.WIDTH, 3):
                bad.append(f"frame {index}: shape {pixels.shape}")
            elif not np.array_equal(pixels, publisher_module.expected_frame(index)):
                bad.append(f"frame {index}: pixels differ")
            else:
                good.append(index)
        except Exception as exc:  # recorded, so that the assertion below shows it
            bad.append(repr(exc))

    ros_node.create_subscription(Image, topic, on_image, qos_profile_sensor_data)
    publisher = ros_process([str(PUBLISHER), "--topic", topic, "--rate", "10", "--duration", "20"], name="publisher")

    arrived = spin_until(ros_node, lambda: len(good) >= 10 or bool(bad), 15.0)
    exit_code = publisher.stop()

    assert not bad, bad
    assert arrived, f"only {len(good)} correct frames within 15 s; publisher stderr:\n{publisher.stderr()}"
    assert good == sorted(set(good)), "frames arrived duplicated or out of order"
    # Best effort may lose a frame now and then, but Fast DDS's builtin transports lose most
    # frames of this size (about 60 % measured); the profile's 16 MiB shared memory loses none.
    span = good[-1] - good[0] + 1
    assert len(good) >= 0.9 * span, f"lost {span - len(good)} of {span} frames: {good}"
    assert exit_code == 0, publisher.stderr()
    assert "published" in publisher.stdout()
    # The packaged profile parses: neither process reported an XML (or any other Fast DDS) error.
    assert "XMLPARSER" not in publisher.stderr() and "Error" not in publisher.stderr(), publisher.stderr()
    captured = capfd.readouterr()
    assert "XMLPARSER" not in captured.err, captured.err
    print(f"received {len(good)} correct 1242x375 rgb8 frames: {good}", file=sys.stderr)
