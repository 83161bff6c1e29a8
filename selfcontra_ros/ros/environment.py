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

from selfcontra_ros.resources import config_file

__all__ = ["FASTDDS_PROFILE", "FASTDDS_PROFILE_VARIABLE", "prepare_ros_environment"]

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
