"""Second process of the transport test: publishes deterministic rgb8 images.

Run as ``python test/ros/_image_publisher.py --topic T``. Frame ``k`` carries
``frame_id = "frame <k>"`` and the pixels of :func:`expected_frame` ``(k)``,
so the receiving process can check every byte. The process stops by itself
after ``--duration`` seconds, so it cannot outlive a crashed test for long.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from numpy.typing import NDArray

WIDTH = 1242  # KITTI colour image size
HEIGHT = 375


def expected_frame(index: int, width: int = WIDTH, height: int = HEIGHT) -> NDArray[np.uint8]:
    """Pixels of frame ``index``: a ramp over (row, column, channel) shifted by the frame index, mod 256."""
    v = np.arange(height, dtype=np.int64)[:, None, None]
    u = np.arange(width, dtype=np.int64)[None, :, None]
    c = np.arange(3, dtype=np.int64)[None, None, :]
    return ((7 * v + 3 * u + 101 * c + 13 * index) % 256).astype(np.uint8)


def frame_index(frame_id: str) -> int:
    """Inverse of the ``frame_id`` written by the publisher."""
    prefix = "frame "
    if not frame_id.startswith(prefix):
        raise ValueError(f"unexpected frame_id {frame_id!r}")
    return int(frame_id[len(prefix) :])


def main(argv: list[str] | None = None) -> int:
    """Publish frames at ``--rate`` Hz with sensor-data (best effort) QoS until ``--duration`` elapses."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--rate", type=float, default=10.0, help="frames per second")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds before the process exits on its own")
    args = parser.parse_args(argv)

    # Imported here so that the module's helpers are usable without ROS (the test imports them).
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from selfcontra_ros.ros.conversions import numpy_to_image, seconds_to_stamp
    from selfcontra_ros.ros.environment import prepare_ros_environment

    prepare_ros_environment()
    rclpy.init()
    node = rclpy.create_node("selfcontra_test_image_publisher")
    publisher = node.create_publisher(Image, args.topic, qos_profile_sensor_data)
    counter = 0

    def publish() -> None:
        nonlocal counter
        msg = numpy_to_image(
            expected_frame(counter), "rgb8", stamp=seconds_to_stamp(counter / args.rate), frame_id=f"frame {counter}"
        )
        publisher.publish(msg)
        counter += 1

    node.create_timer(1.0 / args.rate, publish)
    deadline = time.monotonic() + args.duration
    try:
        while rclpy.ok() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(f"published {counter} frames", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
