"""``make demo``: the main job, end to end over ROS 2, on built-in synthetic data.

1. Render a synthetic street sequence (exact ground truth) and convert it to a
   rosbag2 MCAP bag.
2. Label the bag offline (``selfcontra label BAG``): the reference.
3. Replay the bag with the player node and label it with the labeler node, two
   separate processes talking ROS 2 over loopback; this process records the
   labeler's outputs into an MCAP bag and writes the colour label images.
4. Print label accuracy and coverage against the ground truth for both runs;
   they must be equal (same core, same result).

Network safety: the Makefile runs this with ``ROS_AUTOMATIC_DISCOVERY_RANGE=
LOCALHOST`` and a domain of its own; run directly, the demo sets both itself
unless they are set (LOCALHOST and the Makefile's domain, 73), so that its
nodes neither leave the machine nor meet a robot's nodes on the default domain.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from selfcontra_ros.datasets import SCENES

__all__ = ["main"]

# The labeler's queue holds every view, so replaying at the bag's own pace never
# skips one even when labeling is slower than the camera; the views are labelled
# as fast as the machine allows and the window is flushed at the end, as the
# offline labeler does at the end of the bag.
_LABEL_QUEUE = 256
_WAIT_S = 900.0
# The Makefile's domain: run directly, the demo keeps off the default domain 0 a robot's nodes use.
_DEFAULT_DOMAIN = "73"


def _format(mean: dict[str, Any]) -> str:
    return (
        f"accuracy {100 * mean['accuracy']:.2f} % at coverage {100 * mean['coverage']:.2f} % "
        f"(positive precision {100 * mean['positive_precision']:.2f} %, query bad-pixel rate "
        f"{100 * mean['query_bad_rate']:.2f} %)"
    )


def _run_ros(bag: Path, params: Path, labelled: int, out: Path) -> dict[int, dict[str, Any]]:
    """Replay ``bag`` through a labeler process; record its outputs. Returns ``stamp_ns -> messages``.

    ``labelled`` is the number of label images to wait for (frames with ``label_delay`` newer frames,
    or every frame when the parameters label incomplete views at the end).
    """
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from stereo_msgs.msg import DisparityImage

    from selfcontra_ros.bags import topics
    from selfcontra_ros.bags.writer import BagWriter
    from selfcontra_ros.ros.conversions import stamp_to_nanoseconds
    from selfcontra_ros.ros.environment import prepare_ros_environment, start_python, stop_process

    prepare_ros_environment()
    outputs = {
        topics.LABELS: (Image, topics.IMAGE_TYPE),
        topics.LABELS_COLOR: (Image, topics.IMAGE_TYPE),
        topics.DEPTH: (Image, topics.IMAGE_TYPE),
        topics.DISPARITY: (DisparityImage, topics.DISPARITY_TYPE),
    }
    recorded: dict[int, dict[str, Any]] = {}
    stats: list[dict[str, Any]] = []
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    rclpy.init()
    node = rclpy.create_node("selfcontra_demo_recorder", namespace=topics.STEREO_NAMESPACE)
    labeler = player = None
    writer = BagWriter(out / "ros_outputs")
    try:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        subscriptions = []
        for name, (msg_type, type_name) in outputs.items():
            topic = topics.bag_topic(name)
            writer.add_topic(topic, type_name)

            def record(data: bytes, name: str = name, topic: str = topic, msg_type: Any = msg_type) -> None:
                msg = deserialize_message(data, msg_type)
                stamp = stamp_to_nanoseconds(msg.header.stamp)
                writer.write_raw(topic, stamp, data)
                recorded.setdefault(stamp, {})[name] = msg

            subscriptions.append(node.create_subscription(msg_type, name, record, qos, raw=True))
        stats_qos = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )

        # A typed function, not a lambda: Jazzy's rclpy does not tie the callback's argument to the message type.
        def on_stats(msg: String) -> None:
            stats.append(json.loads(msg.data))

        node.create_subscription(String, "labeler/stats", on_stats, stats_qos)

        labeler = start_python(
            [
                "-m",
                "selfcontra_ros.ros.labeler_node",
                "--ros-args",
                "--params-file",
                str(params),
                "-r",
                f"__ns:={topics.STEREO_NAMESPACE}",
                "-p",
                "input_qos:=reliable",
                "-p",
                "flush_on_shutdown:=true",
                "-p",
                "stats_period:=0.5",
                "-p",
                f"label_queue_size:={_LABEL_QUEUE}",
            ],
            logs / "labeler.log",
        )

        def spin_until(done: Any, timeout: float, what: str) -> None:
            deadline = time.monotonic() + timeout
            while not done():
                if time.monotonic() > deadline:
                    raise RuntimeError(f"demo: timed out waiting for {what}; see {logs}")
                if labeler is not None and labeler.poll() is not None and not done():
                    raise RuntimeError(f"demo: the labeler exited early; see {logs / 'labeler.log'}")
                rclpy.spin_once(node, timeout_sec=0.1)

        spin_until(lambda: all(s.get_publisher_count() for s in subscriptions), 60.0, "the labeler's publishers")
        player = start_python(
            [
                "-m",
                "selfcontra_ros.ros.player_node",
                "--ros-args",
                "-p",
                f"bag:={bag}",
                "-p",
                "wait_for_subscribers:=5",
                # Keep-last 10 lets a reliable writer overwrite samples a reader has not acknowledged yet: on a
                # loaded machine the labeler missed frames 11 and 13 of 24 that way (no drop it could count).
                # The whole bag fits in the history.
                "-p",
                "qos_depth:=1000",
            ],
            logs / "player.log",
        )
        print(f"replaying {bag} through the labeler node (player and labeler are separate processes) ...")
        spin_until(lambda: player is not None and player.poll() is not None, _WAIT_S, "the player to finish")
        if player.returncode != 0:
            raise RuntimeError(f"demo: the player failed; see {logs / 'player.log'}")
        spin_until(
            lambda: bool(stats) and stats[-1]["counts"]["views_labelled"] >= labelled,
            _WAIT_S,
            "the labeler to catch up",
        )
        labeler.send_signal(signal.SIGINT)  # flush_on_shutdown: as label_bag at the end of the bag
        complete = (topics.LABELS, topics.LABELS_COLOR)
        spin_until(
            lambda: sum(all(k in m for k in complete) for m in recorded.values()) >= labelled,
            120.0,
            "the flushed labels",
        )
        labeler.wait(timeout=30.0)
        final = stats[-1]
        dropped = {k: v for k, v in final["drops"].items() if v}
        print(f"labeler node: {final['counts']['frames']} frames, drops {dropped or 'none'}")
    finally:
        writer.close()
        for process in (player, labeler):
            stop_process(process)
        node.destroy_node()
        rclpy.shutdown()
    return recorded


def _evaluate_ros(recorded: dict[int, dict[str, Any]], sequence_dir: Path, out: Path) -> dict[str, float]:
    """Label metrics of the node's outputs against the sequence's ground truth; writes colour PNGs."""
    from selfcontra_ros.bags import topics
    from selfcontra_ros.datasets.kitti import open_sequence
    from selfcontra_ros.evaluation.metrics import label_metrics, mean_metrics
    from selfcontra_ros.ros.conversions import disparity_from_message, image_to_numpy

    sequence = open_sequence(sequence_dir)
    colour_dir = out / "labels_color"
    colour_dir.mkdir(parents=True, exist_ok=True)
    figures = []
    for index, stamp in enumerate(sorted(recorded)):
        messages = recorded[stamp]
        if topics.LABELS not in messages:
            continue  # a last view without label_delay newer views (labeler.flush_incomplete: false)
        labels = image_to_numpy(messages[topics.LABELS])
        disparity = disparity_from_message(messages[topics.DISPARITY])[0]
        gt = sequence[index].gt_disparity
        assert gt is not None
        figures.append(label_metrics(labels, disparity, gt))
        colour = image_to_numpy(messages[topics.LABELS_COLOR])
        cv2.imwrite(str(colour_dir / f"{index:06d}.png"), np.ascontiguousarray(colour[:, :, ::-1]))
    return mean_metrics(figures)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demo; returns the process exit code."""
    parser = argparse.ArgumentParser(prog="selfcontra-demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo_out", help="output folder, replaced on every run (default demo_out)")
    parser.add_argument("--scene", choices=SCENES, default="street")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--size", default="620x188", help="image size WxH (default 620x188: a half-size KITTI)")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", _DEFAULT_DOMAIN)

    from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
    from selfcontra_ros.bags.label_bag import label_bag
    from selfcontra_ros.datasets.synthetic import write_sequence
    from selfcontra_ros.resources import config_file

    width, height = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    started = time.monotonic()

    sequence_dir = write_sequence(
        out / "sequence", scene=args.scene, frames=args.frames, seed=args.seed, width=width, height=height
    )
    bag = kitti_to_mcap(out / "sequence", out / "input_bag")
    print(f"1. rendered {args.frames} frames of the synthetic {args.scene!r} scene ({width}x{height}) into {bag}")

    # The package's default parameters, under "/**" so that they reach the labeler in any namespace.
    params = out / "labeler.yaml"
    document = yaml.safe_load(config_file("labeler.yaml").read_text())
    body = next(iter(document.values()))
    params.write_text(yaml.safe_dump({"/**": body}, sort_keys=False))

    offline = label_bag(bag, out / "offline_bag", params_file=params)
    labelled = len(offline["frames"])
    print(f"2. offline `selfcontra label BAG`, {labelled} labelled frames: {_format(offline['mean'])}")

    recorded = _run_ros(bag, params, labelled, out)
    ros_mean = _evaluate_ros(recorded, sequence_dir, out)
    print(f"3. over ROS 2 (player node -> labeler node -> recorder): {_format(ros_mean)}")
    print(f"   outputs: {out / 'ros_outputs'} (MCAP), colour labels in {out / 'labels_color'}")

    keys = ("accuracy", "coverage", "positive_precision")
    same = all(np.isclose(ros_mean[k], offline["mean"][k], rtol=0, atol=1e-12) for k in keys)
    print(f"4. node and offline command agree: {'yes' if same else 'NO'}; done in {time.monotonic() - started:.0f} s")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
