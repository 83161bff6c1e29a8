"""Convert a KITTI odometry sequence (real or synthetic) into a rosbag2 bag with MCAP storage.

Topics (names in :mod:`selfcontra_ros.bags.topics`), one message each per frame:

==================================  ============================  ==============================================
topic                               type                          content
==================================  ============================  ==============================================
``/stereo/left/image_rect``         sensor_msgs/Image             ``mono8`` (grey pair) or ``rgb8`` (``color``)
``/stereo/right/image_rect``        sensor_msgs/Image             same encoding
``/stereo/left/camera_info``        sensor_msgs/CameraInfo        rectified ``P`` of the left camera
``/stereo/right/camera_info``       sensor_msgs/CameraInfo        ``P[0,3] = -fx * baseline``
``/stereo/pose``                    geometry_msgs/PoseStamped     ``T_world_left`` in frame ``world`` (if poses)
``/stereo/ground_truth/disparity``  stereo_msgs/DisparityImage    left disparity (if the sequence has ``disp_*``)
==================================  ============================  ==============================================

**Compressed images** (``compress_images="jpeg"`` or ``"png"``): the two
image topics become ``/stereo/left|right/image_rect/compressed``
(``sensor_msgs/CompressedImage``, ``mono8; jpeg compressed mono8`` or, for
colour, ``rgb8; jpeg compressed bgr8``, as image_transport writes them); the
bag records it in ``custom_data`` (``selfcontra.input``), so the offline
commands read it without ``--image-transport compressed``.

**Stamps.** Header stamps and bag log times are equal:
``stamp_offset_ns + round(t * 1e9)`` with ``t`` the sequence stamp in seconds
(``times.txt``, else 10 Hz from 0). The default offset,
:data:`DEFAULT_STAMP_OFFSET_NS`, is 2011-09-26T00:00:00Z, the first KITTI
recording day: frame 0 is then not ROS's "unset" time 0 (which ``/clock``
consumers and tf treat specially) and tools show a plausible date; the
offset is recorded in ``metadata.yaml`` (``custom_data``,
``selfcontra.stamp_offset_ns``). Pass ``stamp_offset_ns=0`` to keep the
sequence stamps as they are.

**Ground truth.** The disparity image follows stereo_image_proc: ``32FC1``
pixels, ``f = fx``, ``t = baseline``, ``min_disparity = 0``; pixels without
ground truth hold ``min_disparity - 1`` (-1), so
:func:`selfcontra_ros.ros.conversions.disparity_from_message` gives back NaN
there. ``delta_d`` is 1/256 px, the resolution of KITTI disparity PNGs.

**Failures.** The bag is written in a hidden staging folder beside ``out``
and moved to ``out`` only once it is complete (see
:class:`~selfcontra_ros.bags.writer.BagWriter`, atomic mode): an error or
Ctrl-C part way leaves no bag at ``out`` (the staging folder is deleted). An
existing ``out`` is never overwritten.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.bags import topics
from selfcontra_ros.bags.compressed import IMAGE_FORMATS
from selfcontra_ros.bags.messages import MessageBuilder
from selfcontra_ros.bags.reader import BagError
from selfcontra_ros.bags.stereo_input import CUSTOM_DATA_KEY, StereoInput
from selfcontra_ros.bags.writer import COMPRESSIONS, BagWriter
from selfcontra_ros.datasets.kitti import StereoFrame, open_sequence
from selfcontra_ros.errors import DatasetError
from selfcontra_ros.geometry import StereoCamera

__all__ = [
    "DEFAULT_STAMP_OFFSET_NS",
    "GT_DELTA_D",
    "kitti_to_mcap",
    "seconds_to_nanoseconds",
]

_NS_PER_S = 1_000_000_000
#: 2011-09-26T00:00:00Z in nanoseconds since the epoch: the default offset added to sequence stamps.
DEFAULT_STAMP_OFFSET_NS = 1_316_995_200 * _NS_PER_S
#: Disparity resolution of the ground truth, pixels (KITTI PNGs store d * 256).
GT_DELTA_D = 1.0 / 256.0


# --------------------------------------------------------------------------- messages (rosbags types)


def seconds_to_nanoseconds(seconds: float) -> int:
    """Integer nanoseconds of ``seconds``, rounding the fraction only (exact for epoch-sized stamps)."""
    whole = math.floor(seconds)
    return whole * _NS_PER_S + round((seconds - whole) * _NS_PER_S)


def _write_frame(
    bag: BagWriter,
    make: MessageBuilder,
    camera: StereoCamera,
    frame: StereoFrame,
    stamp_ns: int,
    compress_images: str | None = None,
) -> None:
    """Append one frame's messages, all stamped ``stamp_ns``, in the order of the module table."""
    encoding = "rgb8" if frame.left.ndim == 3 else "mono8"
    left, right = topics.LEFT_FRAME, topics.RIGHT_FRAME
    for name, pixels, fid in ((topics.LEFT_IMAGE, frame.left, left), (topics.RIGHT_IMAGE, frame.right, right)):
        if compress_images is None:
            bag.write(topics.bag_topic(name), stamp_ns, make.image(pixels, encoding, stamp_ns, fid))
        else:
            msg = make.compressed_image(pixels, encoding, stamp_ns, fid, image_format=compress_images)
            bag.write(topics.bag_topic(name) + topics.COMPRESSED_SUFFIX, stamp_ns, msg)
    bag.write(topics.bag_topic(topics.LEFT_INFO), stamp_ns, make.camera_info(camera, stamp_ns, left, right=False))
    bag.write(topics.bag_topic(topics.RIGHT_INFO), stamp_ns, make.camera_info(camera, stamp_ns, right, right=True))
    if frame.pose is not None:
        bag.write(topics.bag_topic(topics.POSE), stamp_ns, make.pose_stamped(frame.pose, stamp_ns))
    if frame.gt_disparity is not None:
        bag.write(
            topics.bag_topic(topics.GT_DISPARITY),
            stamp_ns,
            make.disparity(frame.gt_disparity, camera, stamp_ns, left, delta_d=GT_DELTA_D),
        )


def kitti_to_mcap(
    src: Path | str,
    out: Path | str,
    *,
    frames: slice | None = None,
    compress: str = "zstd",
    color: bool = False,
    sequence: str | None = None,
    stamp_offset_ns: int = DEFAULT_STAMP_OFFSET_NS,
    progress: bool = True,
    estimate_poses: bool = False,
    compress_images: str | None = None,
) -> Path:
    """Write a KITTI odometry sequence as a rosbag2 bag folder with MCAP storage (see the module docstring).

    Args:
        src: dataset root (``sequences/XX``) or sequence folder, as for
            :func:`selfcontra_ros.datasets.kitti.open_sequence`.
        out: bag folder to create (holds ``<name>.mcap`` and ``metadata.yaml``);
            missing parent folders are created.
        frames: which frames (a slice of frame indices, e.g. ``slice(0, 3)``); all when None.
        compress: ``"zstd"`` (compressed MCAP chunks) or ``"none"``.
        color: convert the colour pair (``image_2``/``image_3``, ``rgb8``)
            instead of the grey one (``mono8``).
        sequence: which sequence of a root holding several.
        stamp_offset_ns: nanoseconds added to every sequence stamp.
        progress: show a tqdm progress bar.
        estimate_poses: when the sequence has no poses, estimate them with the
            package's stereo visual odometry and write ``/stereo/pose`` for the
            frames whose pose is reliable (unreliable frames get no pose message,
            so the labelers interpolate or drop them).
        compress_images: ``"jpeg"`` or ``"png"``: images as ``sensor_msgs/CompressedImage``; None: raw.

    Returns:
        The bag folder ``out``.

    Raises:
        BagError: ``out`` exists already, or the bag cannot be written.
        DatasetError: the sequence cannot be read, or ``frames`` selects no frame.
        CalibrationError: the sequence's calibration is not a rectified pair.
    """
    out = Path(out)
    if compress_images is not None and compress_images not in IMAGE_FORMATS:
        raise BagError(f"compress_images is {compress_images!r}; expected one of {', '.join(IMAGE_FORMATS)} or None")
    if compress not in COMPRESSIONS:
        raise BagError(f"compress is {compress!r}; expected one of {', '.join(COMPRESSIONS)}")
    if out.exists() or out.is_symlink():
        raise BagError(f"output bag {out} exists already; remove it or choose another path (not overwriting)")
    seq = open_sequence(src, sequence=sequence, color=color)
    indices = range(len(seq))[frames if frames is not None else slice(None)]
    if len(indices) == 0:
        raise DatasetError(f"frames {frames} selects no frame of {seq} ({len(seq)} frames)")
    stamps_ns = [int(stamp_offset_ns) + seconds_to_nanoseconds(float(seq.stamps[i])) for i in indices]
    if any(b <= a for a, b in itertools.pairwise(stamps_ns)):
        raise DatasetError(f"stamps of {seq.folder} (times.txt) are not strictly increasing over the chosen frames")

    reliable = None
    if seq.poses is None and estimate_poses:
        from selfcontra_ros.odometry.run import poses_for_sequence

        seq.poses, reliable = poses_for_sequence(seq, progress=progress)

    out.parent.mkdir(parents=True, exist_ok=True)
    custom_data = {
        "selfcontra.source": str(seq.folder.resolve()),
        "selfcontra.sequence": seq.sequence,
        "selfcontra.frames": f"{indices[0]}:{indices[-1] + 1}:{indices.step}",
        "selfcontra.stamp_offset_ns": str(int(stamp_offset_ns)),
        "selfcontra.pose_source": "none" if seq.poses is None else "file" if reliable is None else "odometry",
    }
    if compress_images is not None:
        custom_data[CUSTOM_DATA_KEY] = StereoInput(image_transport="compressed").to_json()
    written = 0
    try:
        with BagWriter(out, compress=compress, atomic=True, custom_data=custom_data) as bag:
            make = MessageBuilder(bag.typestore)
            bar = tqdm(indices, desc=f"kitti2mcap {seq.sequence}", unit="frame", disable=not progress)
            for i, stamp_ns in zip(bar, stamps_ns, strict=True):
                interrupts.check()
                frame = seq[i]
                if reliable is not None and not reliable[i]:
                    frame.pose = None  # an unreliable odometry pose is left out rather than written
                _write_frame(bag, make, seq.camera, frame, stamp_ns, compress_images)
                written += 1
    except interrupts.Interrupted as exc:
        exc.done = f"converted {written} of {len(indices)} frames; no bag written (a conversion is complete or absent)"
        raise
    return out
