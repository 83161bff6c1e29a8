"""Process environment that the package's ROS 2 executables need before ``rclpy.init``.

Fast DDS reads its XML profile from an environment variable once, when the
first participant is created, so the variable must be set before
``rclpy.init``. Which variable depends on the Fast DDS that rmw_fastrtps links:
Fast DDS 2.x (ROS 2 Humble to Jazzy; Jazzy's is 2.14) reads only
``FASTRTPS_DEFAULT_PROFILES_FILE``, Fast DDS 3.x (Kilted and later) reads
``FASTDDS_DEFAULT_PROFILES_FILE``, and Kilted's rmw also reads the former but
warns on every start that it is deprecated. The packaged profile
(``config/fastdds_profile.xml``, valid for both) enlarges the shared-memory
segment so that full-size best-effort images arrive and keeps UDP on the
loopback interface; see the comment in that file.

The discovery range is *not* forced here: a robot's ROS 2 graph may span
machines. Test fixtures and the Makefile set
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` themselves.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from selfcontra_ros.resources import config_file

__all__ = [
    "FASTDDS_PROFILE",
    "FASTDDS_PROFILE_VARIABLES",
    "fastdds_profile_variables",
    "prepare_ros_environment",
    "start_python",
    "stop_process",
]

# Read by Fast DDS 3.x and by Fast DDS 2.x respectively.
FASTDDS_PROFILE_VARIABLES = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")
FASTDDS_PROFILE = "fastdds_profile.xml"
# ROS 2 distributions (ROS_DISTRO, set by a ROS install's setup.bash) whose rmw_fastrtps links Fast DDS 2.x.
_FAST_DDS_2_DISTROS = frozenset({"humble", "iron", "jazzy"})


def _fast_dds_major() -> int | None:
    """The major version of the Fast DDS this environment runs, or None when nothing tells."""
    # PyPI wheels: Kilted ships Fast DDS 3 as ros-fastdds, Jazzy ships Fast DDS 2 as ros-fastrtps.
    for distribution, major in (("ros-fastdds", 3), ("ros-fastrtps", 2)):
        try:
            metadata.version(distribution)
        except metadata.PackageNotFoundError:
            continue
        return major
    distro = os.environ.get("ROS_DISTRO")
    if distro:
        return 2 if distro in _FAST_DDS_2_DISTROS else 3
    return None


def fastdds_profile_variables() -> tuple[str, ...]:
    """The profile variables that :func:`prepare_ros_environment` fills in here.

    Both of :data:`FASTDDS_PROFILE_VARIABLES`, except where Fast DDS 3 is
    known to run: there only ``FASTDDS_DEFAULT_PROFILES_FILE``, because
    Kilted's rmw would read the other one too and warn that it is deprecated.
    """
    if _fast_dds_major() == 3:
        return FASTDDS_PROFILE_VARIABLES[:1]
    return FASTDDS_PROFILE_VARIABLES


def prepare_ros_environment() -> None:
    """Point Fast DDS at the packaged profile unless the user chose one; call before ``rclpy.init``.

    With neither of :data:`FASTDDS_PROFILE_VARIABLES` set, the variables of
    :func:`fastdds_profile_variables` get the packaged profile. A value the
    user set in either variable is the choice for both: it fills in those
    variables the user left unset, and one the user set is never changed
    (where the user set both, each keeps its own). An empty value means
    "no profile": the variable is removed, so that Fast DDS keeps its builtin
    transports without complaining about an empty file name.

    Raises:
        SelfContraError: the packaged profile cannot be found (broken install).
    """
    chosen = [os.environ[name] for name in FASTDDS_PROFILE_VARIABLES if name in os.environ]
    profile = chosen[0] if chosen else str(config_file(FASTDDS_PROFILE))
    for name in fastdds_profile_variables():
        os.environ.setdefault(name, profile)
    for name in FASTDDS_PROFILE_VARIABLES:
        if os.environ.get(name) == "":
            del os.environ[name]


def start_python(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    """Start ``python args`` (e.g. ``["-m", "selfcontra_ros.ros.labeler_node", ...]``), output into ``log``.

    The child gets this process's whole environment: the ROS wheels restart
    each interpreter once with ``LD_LIBRARY_PATH`` set, and a child given
    their guard variable without it cannot import rclpy. It runs in a session
    of its own, so a Ctrl-C at the terminal reaches only the caller, which
    stops it with :func:`stop_process`.
    """
    with log.open("wb") as handle:
        return subprocess.Popen(
            [sys.executable, *args],
            env=os.environ.copy(),
            stdout=handle,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def stop_process(process: subprocess.Popen[bytes] | None, timeout: float = 10.0) -> None:
    """SIGINT (a clean shutdown of a ROS 2 node), then SIGKILL after ``timeout`` s; nothing if already gone."""
    if process is None or process.poll() is not None:
        return
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
