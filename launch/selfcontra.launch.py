"""Launch the bag player and the self-contradiction labeler together (ROS 2 launch).

Usage, in a colcon workspace with ``launch`` and ``launch_ros`` installed::

    ros2 launch selfcontra_ros selfcontra.launch.py bag:=/data/seq06
    ros2 launch selfcontra_ros selfcontra.launch.py bag:=/data/seq06 rate:=0.5 params_file:=/my/labeler.yaml

Both nodes run in the namespace ``namespace`` (default ``/stereo``, the
namespace of the package's bags): the player publishes the bag's
``/stereo/...`` topics, the labeler subscribes to ``left/image_rect``,
``right/image_rect``, ``left/camera_info``, ``right/camera_info`` and
``pose`` in that namespace and publishes ``labels``, ``labels/color``,
``depth`` and ``disparity`` there. The player sits at the root (its topics
already carry the bag's namespace); the labeler gets the namespace.

Use a parameter file whose node key matches a namespaced node (``/**:`` or
``/stereo/labeler:``); a plain ``labeler:`` key applies only to a labeler at
the root namespace.

Without ROS 2 launch (e.g. a plain virtual environment with the rclpy
wheels), start the two processes by hand::

    python -m selfcontra_ros.ros.player_node --ros-args -p bag:=/data/seq06
    python -m selfcontra_ros.ros.labeler_node --ros-args --params-file config/labeler.yaml -r __ns:=/stereo
"""

from __future__ import annotations

from typing import Any

try:
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.substitutions import FindPackageShare

    from launch import LaunchDescription  # type: ignore[attr-defined,unused-ignore]
except ImportError as _exc:  # the file stays importable (packaging checks) where ROS 2 launch is absent
    _IMPORT_ERROR: ImportError | None = _exc
else:
    _IMPORT_ERROR = None

PACKAGE = "selfcontra_ros"


def generate_launch_description() -> Any:
    """The player (``bag``, ``rate``) and the labeler (``params_file``) in ``namespace``.

    Raises:
        ImportError: ROS 2 ``launch`` / ``launch_ros`` are not installed.
    """
    if _IMPORT_ERROR is not None:
        raise ImportError(
            f"selfcontra.launch.py needs the ROS 2 packages launch and launch_ros ({_IMPORT_ERROR}); "
            "without them start player_node and labeler_node by hand (see this file's docstring)"
        )
    default_params = [FindPackageShare(PACKAGE), "/config/labeler.yaml"]
    bag = LaunchConfiguration("bag")
    rate = LaunchConfiguration("rate")
    namespace = LaunchConfiguration("namespace")
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription(
        [
            DeclareLaunchArgument("bag", description="bag folder or .mcap file to play"),
            DeclareLaunchArgument("rate", default_value="1.0", description="playback speed factor"),
            DeclareLaunchArgument("namespace", default_value="/stereo", description="namespace of the stereo topics"),
            DeclareLaunchArgument(
                "params_file", default_value=default_params, description="labeler parameter file (YAML)"
            ),
            Node(
                package=PACKAGE,
                executable="player",
                name="player",
                output="screen",
                parameters=[{"bag": bag, "rate": rate, "wait_for_subscribers": 5}],
            ),
            Node(
                package=PACKAGE,
                executable="labeler",
                name="labeler",
                namespace=namespace,
                output="screen",
                parameters=[params_file],
            ),
        ]
    )
