"""Two real rclpy processes on loopback: full-size best-effort images through the packaged Fast DDS profile."""

from __future__ import annotations

import importlib.util
import os
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.resources import config_file
from selfcontra_ros.ros import environment
from selfcontra_ros.ros.environment import (
    FASTDDS_PROFILE_VARIABLES,
    fastdds_profile_variables,
    prepare_ros_environment,
)

HERE = Path(__file__).resolve().parent
PUBLISHER = HERE / "_image_publisher.py"
NS = {"dds": "http://www.eprosima.com"}
FASTDDS_3, FASTDDS_2 = FASTDDS_PROFILE_VARIABLES  # the variable Fast DDS 3.x reads, the one Fast DDS 2.x reads


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


@pytest.fixture
def profile_environment(monkeypatch: pytest.MonkeyPatch) -> Callable[[int | None], None]:
    """``given(major)``: neither profile variable set, and Fast DDS ``major`` (3, 2, None: unknown) installed."""

    def given(major: int | None) -> None:
        for name in FASTDDS_PROFILE_VARIABLES:
            monkeypatch.delenv(name, raising=False)
        monkeypatch.setattr(environment, "_fast_dds_major", lambda: major)

    return given


@pytest.mark.parametrize(
    ("major", "variables"), [(3, [FASTDDS_3]), (2, [FASTDDS_3, FASTDDS_2]), (None, [FASTDDS_3, FASTDDS_2])]
)
def test_prepare_ros_environment_defaults_to_the_packaged_profile(
    profile_environment: Callable[[int | None], None],
    monkeypatch: pytest.MonkeyPatch,
    major: int | None,
    variables: list[str],
) -> None:
    profile_environment(major)
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    prepare_ros_environment()
    set_now = {name: os.environ[name] for name in FASTDDS_PROFILE_VARIABLES if name in os.environ}
    # Fast DDS 3 gets no FASTRTPS_ variable: Kilted's rmw would read it too and warn that it is deprecated.
    assert set_now == dict.fromkeys(variables, str(config_file("fastdds_profile.xml")))
    assert Path(os.environ[FASTDDS_3]).is_file()
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in os.environ  # left to the user: graphs may span machines


@pytest.mark.parametrize("major", [3, 2])
@pytest.mark.parametrize("chosen", [FASTDDS_3, FASTDDS_2])
def test_a_profile_the_user_chose_in_either_variable_holds_for_both(
    profile_environment: Callable[[int | None], None], monkeypatch: pytest.MonkeyPatch, chosen: str, major: int
) -> None:
    own = "/robot/own_profile.xml"
    profile_environment(major)
    monkeypatch.setenv(chosen, own)
    # Copied into the variable the installed Fast DDS reads; the user's own is never changed.
    expected = {FASTDDS_3: own, FASTDDS_2: own} if major == 2 or chosen == FASTDDS_2 else {FASTDDS_3: own}
    for _ in range(2):  # idempotent
        prepare_ros_environment()
        assert {name: os.environ[name] for name in FASTDDS_PROFILE_VARIABLES if name in os.environ} == expected

    profile_environment(major)
    monkeypatch.setenv(chosen, "")  # "no profile" for both: removed, so Fast DDS does not try to open ""
    prepare_ros_environment()
    assert not set(FASTDDS_PROFILE_VARIABLES) & set(os.environ)


def test_profiles_the_user_set_in_both_variables_are_kept(
    profile_environment: Callable[[int | None], None], monkeypatch: pytest.MonkeyPatch
) -> None:
    profile_environment(2)
    monkeypatch.setenv(FASTDDS_3, "/robot/fastdds3.xml")
    monkeypatch.setenv(FASTDDS_2, "/robot/fastdds2.xml")
    prepare_ros_environment()
    assert (os.environ[FASTDDS_3], os.environ[FASTDDS_2]) == ("/robot/fastdds3.xml", "/robot/fastdds2.xml")


def test_the_installed_fast_dds_is_recognised() -> None:
    """The venvs of the Makefile hold ros-fastdds (Kilted, Fast DDS 3) or ros-fastrtps (Jazzy, Fast DDS 2)."""
    installed = {name for name in ("ros-fastdds", "ros-fastrtps") if _is_installed(name)}
    if not installed:
        pytest.skip("no Fast DDS wheel installed (a ROS installation's own Fast DDS)")
    expected = [FASTDDS_3] if installed == {"ros-fastdds"} else [FASTDDS_3, FASTDDS_2]
    assert list(fastdds_profile_variables()) == expected


def _is_installed(distribution: str) -> bool:
    try:
        metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return False
    return True


def _fastdds_output(proc: Any) -> str:
    """What a :class:`RosProcess` printed: Fast DDS 3.x logs on stderr, Fast DDS 2.14 on stdout."""
    output: str = proc.stdout() + proc.stderr()
    return output


@pytest.mark.ros
@pytest.mark.parametrize("chosen", [FASTDDS_3, FASTDDS_2])
def test_fastdds_xml_errors_would_show(
    ros_process: Callable[..., Any], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, chosen: str
) -> None:
    """Negative control for the 'no XML errors' check below, through either variable.

    A broken profile the user names in one variable reaches the installed Fast DDS, whichever
    variable that reads, and is reported on its stdout or stderr.
    """
    broken = tmp_path / "broken.xml"
    broken.write_text('<dds xmlns="http://www.eprosima.com"><profiles><participant>')
    for name in FASTDDS_PROFILE_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    code = (
        "from selfcontra_ros.ros.environment import prepare_ros_environment; prepare_ros_environment(); "
        "import rclpy; rclpy.init(); rclpy.create_node('probe').destroy_node(); rclpy.shutdown()"
    )
    proc = ros_process(["-c", code], extra_env={chosen: str(broken)}, name="probe")
    assert proc.popen.wait(timeout=20) == 0, _fastdds_output(proc)
    assert "XMLPARSER" in _fastdds_output(proc)


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

    prepare_ros_environment()  # what every executable does; the fixture already chose the packaged profile
    for name in fastdds_profile_variables():
        assert os.environ[name] == str(config_file("fastdds_profile.xml"))
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
    # The packaged profile parses: neither process reported an XML (or any other Fast DDS) error,
    # on stdout (Fast DDS 2.14) or stderr (3.x).
    output = _fastdds_output(publisher)
    assert "XMLPARSER" not in output and "Error" not in output, output
    captured = capfd.readouterr()
    assert "XMLPARSER" not in captured.out + captured.err, captured.out + captured.err
    print(f"received {len(good)} correct 1242x375 rgb8 frames: {good}", file=sys.stderr)
