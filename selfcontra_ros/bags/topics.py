"""Topic names, message types and frame ids: the one place that names them.

Names follow image_pipeline / stereo_image_proc (DESIGN.md section 6). The
*relative* names below are what nodes use: a node resolves them in its own
namespace, so ``--ros-args -r __ns:=/stereo`` (or a remap rule) places them.
Bags written by the package store the same names under :data:`STEREO_NAMESPACE`,
e.g. ``/stereo/left/image_rect``; :func:`bag_topic` builds those.

Frames (REP 103 optical frames: z forward, x right, y down):

* :data:`LEFT_FRAME` / :data:`RIGHT_FRAME`: the rectified left / right camera;
  images, camera infos and disparity images carry these in their headers.
* :data:`WORLD_FRAME`: the fixed frame of the poses. For KITTI odometry it is
  the left camera at frame 0. ``/stereo/pose`` is ``T_world_left``: the pose
  of :data:`LEFT_FRAME` in :data:`WORLD_FRAME`, header frame id :data:`WORLD_FRAME`.
"""

from __future__ import annotations

__all__ = [
    "CAMERA_INFO_TYPE",
    "CLOCK",
    "CLOCK_TYPE",
    "COMPRESSED_IMAGE_TYPE",
    "COMPRESSED_SUFFIX",
    "CONFIDENCE",
    "DEPTH",
    "DEPTH_FILTERED",
    "DISPARITY",
    "DISPARITY_TYPE",
    "GT_DISPARITY",
    "IMAGE_ENCODINGS",
    "IMAGE_TYPE",
    "INPUT_TOPICS",
    "LABELS",
    "LABELS_COLOR",
    "LEFT_FRAME",
    "LEFT_IMAGE",
    "LEFT_INFO",
    "LEFT_RAW",
    "ODOMETRY_TYPE",
    "OUTPUT_TOPICS",
    "POSE",
    "POSE_TYPE",
    "POSE_TYPES",
    "RIGHT_FRAME",
    "RIGHT_IMAGE",
    "RIGHT_INFO",
    "RIGHT_RAW",
    "STEREO_NAMESPACE",
    "TF",
    "TF_STATIC",
    "TF_TYPE",
    "WORLD_FRAME",
    "bag_topic",
]

# --------------------------------------------------------------------------- message types (rosbag2 spelling)

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
DISPARITY_TYPE = "stereo_msgs/msg/DisparityImage"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
TF_TYPE = "tf2_msgs/msg/TFMessage"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
#: Message types read as the left camera's pose.
POSE_TYPES = (POSE_TYPE, ODOMETRY_TYPE)
#: ``sensor_msgs/Image`` encodings of the stereo images read and compressed (``bgr8`` is reordered to RGB).
IMAGE_ENCODINGS = ("mono8", "rgb8", "bgr8")

# --------------------------------------------------------------------------- inputs of the labeler (relative names)

#: Namespace of the stereo topics in bags written by the package.
STEREO_NAMESPACE = "/stereo"

LEFT_IMAGE = "left/image_rect"
RIGHT_IMAGE = "right/image_rect"
LEFT_INFO = "left/camera_info"
RIGHT_INFO = "right/camera_info"
#: Unrectified images (with a distorted camera_info), read instead of ``image_rect`` when the package rectifies.
LEFT_RAW = "left/image_raw"
RIGHT_RAW = "right/image_raw"
#: What image_transport appends to an image topic for its ``compressed`` transport (sensor_msgs/CompressedImage).
COMPRESSED_SUFFIX = "/compressed"
#: The TF topics (absolute, as tf2 names them; tf2_msgs/TFMessage).
TF = "/tf"
TF_STATIC = "/tf_static"
#: geometry_msgs/PoseStamped, ``T_world_left`` in :data:`WORLD_FRAME`.
POSE = "pose"
#: stereo_msgs/DisparityImage of the left camera from ground truth (datasets that have it).
GT_DISPARITY = "ground_truth/disparity"

#: Relative input name -> message type.
INPUT_TOPICS: dict[str, str] = {
    LEFT_IMAGE: IMAGE_TYPE,
    RIGHT_IMAGE: IMAGE_TYPE,
    LEFT_INFO: CAMERA_INFO_TYPE,
    RIGHT_INFO: CAMERA_INFO_TYPE,
    POSE: POSE_TYPE,
    GT_DISPARITY: DISPARITY_TYPE,
}

# --------------------------------------------------------------------------- outputs of the labeler (relative names)

LABELS = "labels"  # mono8, 0 unknown / 1 positive / 2 negative (selfcontra_ros.labels)
LABELS_COLOR = "labels/color"  # rgb8
CONFIDENCE = "confidence"  # 32FC1 in [0, 1]
DEPTH = "depth"  # 32FC1 metres (REP 118)
DEPTH_FILTERED = "depth/filtered"  # 32FC1, NaN where confidence < threshold
DISPARITY = "disparity"  # stereo_msgs/DisparityImage of the query algorithm

#: The labeler's outputs (relative names), as it publishes them and as labelled bags store them.
OUTPUT_TOPICS = (LABELS, LABELS_COLOR, DEPTH, DISPARITY, CONFIDENCE, DEPTH_FILTERED)

#: Simulated time (absolute: ROS nodes with ``use_sim_time`` listen on exactly this name).
CLOCK = "/clock"

# --------------------------------------------------------------------------- frames

LEFT_FRAME = "stereo_left_optical"
RIGHT_FRAME = "stereo_right_optical"
WORLD_FRAME = "world"


def bag_topic(name: str, namespace: str = STEREO_NAMESPACE) -> str:
    """Absolute topic name of a relative ``name`` under ``namespace`` (absolute names are returned unchanged).

    ``bag_topic(LEFT_IMAGE)`` is ``/stereo/left/image_rect``.
    """
    if name.startswith("/"):
        return name
    return f"{namespace.rstrip('/')}/{name}"
