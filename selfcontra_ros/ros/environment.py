"""Process environment that the package's ROS 2 executables need before ``rclpy.init``.

Fast DDS reads its XML profile from ``FASTDDS_DEFAULT_PROFILES_FILE`` once,
when the first participant is created, so the variable must be set before
``rclpy.init``. The packaged profile (``config/fastdds_profile.xml``) enlarges
the shared-memory segment so that full-size best-effort images arrive and
keeps UDP on the loopback interface; see the comment in that file.

The discovery range is *not* forced here: a robot's ROS 2 graph may span
machines. Test fixtures and the Makefile set
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` themselves.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from selfcontra_ros.resources import config_file

__all__ = ["FASTDDS_PROFILE", "FASTDDS_PROFILE_VARIABLE", "prepare_ros_environment", "start_python", "stop_process"]

FASTDDS_PROFILE_VARIABLE = "FASTDDS_DEFAULT_PROFILES_FILE"
FASTDDS_PROFILE = "fastdds_profile.xml"


def prepare_ros_environment() -> None:
    """Point Fast DDS at the packaged profile unless the user chose one; call before ``rclpy.init``.

    A non-empty value the user already set is left untouched. An empty value
    means "no profile": the variable is removed, so that Fast DDS keeps its
    builtin transports without complaining about an empty file name.

    Raises:
        SelfContraError: the packaged profile cannot be found (broken install).
    """
    if FASTDDS_PROFILE_VARIABLE in os.environ:
        if not os.environ[FASTDDS_PROFILE_VARIABLE]:
            del os.environ[FASTDDS_PROFILE_VARIABLE]
        return
    os.environ[FASTDDS_PROFILE_VARIABLE] = str(config_file(FASTDDS_PROFILE))


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
