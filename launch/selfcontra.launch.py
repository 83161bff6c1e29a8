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

**A robot's own bag** (driver topic names, compressed distorted
``image_raw``, poses in TF) takes the labeler's robot parameters as launch
arguments; each one left empty keeps what the parameter file (or the node's
default) says::

    ros2 launch selfcontra_ros selfcontra.launch.py bag:=robot namespace:=/sensors/stereo \
        image_transport:=compressed rectify:=true sync:=approximate slop:=0.005 \
        pose_source:=tf world_frame:=odom \
        remaps:=left/image_raw:=cam_left/image_raw,right/image_raw:=cam_right/image_raw,\
    left/camera_info:=cam_left/camera_info,right/camera_info:=cam_right/camera_info

``image_transport`` (``raw`` / ``compressed``), ``rectify``, ``sync``, ``slop``
    the labeler's parameters of the same names.
``remaps``
    comma-separated ``FROM:=TO`` rules, the relative names of ``selfcontra
    label BAG --remap``: the labeler's remappings (a compressed topic follows
    its base name), and where the player finds the left camera.
``pose_source`` (``""``: the parameter file's; ``pose``; ``tf``; ``odometry``), ``world_frame``, ``camera_frame``
    with ``tf`` the poses come from the bag's ``/tf`` and ``/tf_static``. By
    default (``tf_in_labeler:=false``) the player composes them itself and
    publishes the left camera's PoseStamped on ``<namespace>/pose``, which the
    labeler reads with ``pose_source: pose``: nothing of tf2 is needed (the
    PyPI wheels have neither ``tf2_msgs`` nor ``tf2_ros``). With
    ``tf_in_labeler:=true`` the player publishes ``/tf`` as recorded and the
    labeler reads it through tf2_ros (``pose_source: tf``): a ROS 2 install
    with both. With ``odometry`` the labeler estimates the poses from the
    stereo images itself (a bag without poses; the labeler node's
    ``pose_source: odometry``).

Without ROS 2 launch (e.g. a plain virtual environment with the rclpy
wheels), start the two processes by hand::

    python -m selfcontra_ros.ros.player_node --ros-args -p bag:=/data/seq06
    python -m selfcontra_ros.ros.labeler_node --ros-args --params-file config/labeler.yaml -r __ns:=/stereo

(for a robot bag, the player with ``-p pose_source:=tf -p world_frame:=odom``
and the ``stereo_namespace``/``remaps``/``image_transport``/``rectify`` of the
bag, the labeler with ``-r`` remaps and ``-p image_transport:=compressed -p
rectify:=true ...``; :func:`node_settings` shows what goes where).
"""

from __future__ import annotations

from typing import Any

try:
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.substitutions import FindPackageShare

    from launch import LaunchDescription  # type: ignore[attr-defined,unused-ignore]
except ImportError as _exc:  # the file stays importable (packaging checks) where ROS 2 launch is absent
    _IMPORT_ERROR: ImportError | None = _exc
else:
    _IMPORT_ERROR = None

PACKAGE = "selfcontra_ros"
#: The robot-bag launch arguments: name -> (default, description); see the module docstring.
ROBOT_ARGUMENTS: dict[str, tuple[str, str]] = {
    "image_transport": ("", "labeler input images: raw (sensor_msgs/Image) or compressed (<topic>/compressed)"),
    "rectify": ("", "labeler: true rectifies left/right image_raw with their camera_info"),
    "sync": ("", "labeler image synchronisation: exact or approximate"),
    "slop": ("", "labeler: largest left/right stamp difference with sync approximate, seconds"),
    "remaps": ("", "comma-separated FROM:=TO rules, as selfcontra label --remap"),
    "pose_source": (
        "",
        "pose: the bag's pose topic; tf: poses from the bag's /tf and /tf_static; "
        "odometry: the labeler's own stereo odometry",
    ),
    "tf_in_labeler": ("false", "pose_source tf: the labeler reads TF with tf2_ros (else the player converts it)"),
    "world_frame": ("", "pose_source tf: the fixed frame, e.g. odom"),
    "camera_frame": ("", "pose_source tf: the left camera frame (empty: the left camera_info's frame id)"),
}
# Subscriptions the player waits for: the labeler's two images, two camera infos and its pose.
_LABELER_INPUTS = 5


def _boolean(name: str, text: str) -> bool:
    value = text.strip().lower()
    if value not in ("true", "false"):
        raise ValueError(f"launch argument {name}:={text!r} must be true or false")
    return value == "true"


def node_settings(
    values: dict[str, str], namespace: str
) -> tuple[dict[str, Any], dict[str, Any], list[tuple[str, str]]]:
    """The player's and the labeler's parameters and the labeler's remappings, from the launch arguments' text.

    A pure function (no ROS, no launch), so that what goes where can be checked without ROS 2 launch.

    Args:
        values: launch argument -> its text, for the names of :data:`ROBOT_ARGUMENTS` (missing: the default).
        namespace: the stereo namespace (``namespace`` argument).

    Returns:
        ``(player parameters, labeler parameters, labeler remappings)``; the labeler's parameters
        override the parameter file's only for arguments given.

    Raises:
        ValueError: an argument that is no boolean / number where one is expected, an unknown
            pose_source, or a malformed remap rule.
    """
    from selfcontra_ros.bags.stereo_input import parse_remaps

    v = {name: str(values.get(name, default)).strip() for name, (default, _) in ROBOT_ARGUMENTS.items()}
    rules = [rule.strip() for rule in v["remaps"].split(",") if rule.strip()]
    remappings = list(parse_remaps(rules).items())  # checked: names the package reads or writes
    labeler: dict[str, Any] = {}
    if v["image_transport"]:
        labeler["image_transport"] = v["image_transport"]
    if v["rectify"]:
        labeler["rectify"] = _boolean("rectify", v["rectify"])
    if v["sync"]:
        labeler["sync"] = v["sync"]
    if v["slop"]:
        labeler["slop"] = float(v["slop"])
    player: dict[str, Any] = {"wait_for_subscribers": _LABELER_INPUTS}
    source = v["pose_source"]
    if source not in ("", "pose", "tf", "odometry"):
        raise ValueError(f"launch argument pose_source:={source!r} must be pose, tf or odometry (or empty)")
    frames = {"world_frame": v["world_frame"], "camera_frame": v["camera_frame"]}
    if source == "pose":
        labeler["pose_source"] = "pose"
    elif source == "odometry":  # the labeler estimates the poses from the images: no pose subscription
        labeler["pose_source"] = "odometry"
        player["wait_for_subscribers"] = _LABELER_INPUTS - 1
    elif source == "tf" and _boolean("tf_in_labeler", v["tf_in_labeler"]):
        labeler.update(pose_source="tf", **frames)
        # No pose subscription, but the labeler's TF listener subscribes to /tf and /tf_static.
        player["wait_for_subscribers"] = _LABELER_INPUTS + 1
    elif source == "tf":
        labeler["pose_source"] = "pose"
        player.update(
            pose_source="tf",
            stereo_namespace=namespace,
            image_transport=labeler.get("image_transport", "raw"),
            rectify=labeler.get("rectify", False),
            **frames,
        )
        if rules:
            player["remaps"] = rules
    return player, labeler, remappings


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
    return LaunchDescription(
        [
            DeclareLaunchArgument("bag", description="bag folder or .mcap file to play"),
            DeclareLaunchArgument("rate", default_value="1.0", description="playback speed factor"),
            DeclareLaunchArgument("namespace", default_value="/stereo", description="namespace of the stereo topics"),
            DeclareLaunchArgument(
                "params_file", default_value=default_params, description="labeler parameter file (YAML)"
            ),
            *(
                DeclareLaunchArgument(name, default_value=default, description=description)
                for name, (default, description) in ROBOT_ARGUMENTS.items()
            ),
            OpaqueFunction(function=_nodes),
        ]
    )


def _nodes(context: Any) -> list[Any]:
    """The two nodes, once the launch arguments are known (remappings are a list of any length)."""
    text = {name: LaunchConfiguration(name).perform(context) for name in ROBOT_ARGUMENTS}
    namespace = LaunchConfiguration("namespace").perform(context)
    player, labeler, remappings = node_settings(text, namespace)
    bag = LaunchConfiguration("bag").perform(context)
    rate = float(LaunchConfiguration("rate").perform(context))
    return [
        Node(
            package=PACKAGE,
            executable="player",
            name="player",
            output="screen",
            parameters=[{"bag": bag, "rate": rate, **player}],
        ),
        Node(
            package=PACKAGE,
            executable="labeler",
            name="labeler",
            namespace=namespace,
            output="screen",
            parameters=[LaunchConfiguration("params_file").perform(context), labeler],
            remappings=remappings,
        ),
    ]
