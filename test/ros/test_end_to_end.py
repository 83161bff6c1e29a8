"""Acceptance: bag -> player process -> labeler process -> the test, equal to the offline bag labeler.

A synthetic street sequence (320x96, 10 frames) is written as a KITTI
sequence, converted to an MCAP bag, replayed by the player node in one process
and labelled by the labeler node (namespace ``/stereo``) in another; the test
records the outputs. Every depth image and every label image must equal the
ones :func:`selfcontra_ros.bags.label_bag.label_bag` writes for the same bag
and parameter file (same core, same result), and no frame may be lost.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.label_bag import label_bag
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.datasets.synthetic import write_sequence

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("compiled_kernels")]

# Upper bound (s) of the waits for a node: a passing run never waits it out, but a loaded 2-core machine needs the
# slack (a node process takes seconds to import and to load its kernels from numba's cache, more when others run).
WAIT_S = 60.0

FRAMES = 10
DELAY = 3
# "/**": the labeler runs in the namespace /stereo, where a "labeler:" key would not apply.
PARAMS_YAML = f"""\
/**:
  ros__parameters:
    matcher:
      num_disparities: 64
    labeler:
      window_size: 6
      label_delay: {DELAY}
      flush_incomplete: true  # flush_on_shutdown labels the last label_delay views too
"""
# The bag's pace (10 Hz): a labeling takes 0.05-0.1 s here, so the labeler keeps up; the label queue
# (16 views) absorbs any hiccup of a loaded CI machine. Nothing may be skipped (asserted below).
RATE = 1.0
LABEL_QUEUE = 16
INPUT_SUBSCRIPTIONS = 5  # left, right, two camera infos, pose


@pytest.fixture(scope="module")
def bag_and_offline(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, list[tuple[int, Any]]]]:
    """``(bag, params file, offline outputs)``: the offline outputs are ``topic -> [(stamp ns, message)]``."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    root = tmp_path_factory.mktemp("end_to_end")
    write_sequence(root / "data", scene="street", frames=FRAMES, seed=2, width=320, height=96)
    bag = kitti_to_mcap(root / "data", root / "bag", progress=False)
    params = root / "labeler.yaml"
    params.write_text(PARAMS_YAML)
    label_bag(bag, root / "offline", params_file=params, progress=False)
    offline: dict[str, list[tuple[int, Any]]] = {}
    wanted = {topics.bag_topic(name) for name in (topics.LABELS, topics.DEPTH)}
    with open_bag(root / "offline") as out:
        for raw in out.raw_messages():
            if raw.topic in wanted:
                offline.setdefault(raw.topic, []).append((raw.stamp_ns, deserialize_message(raw.data, Image)))
    return bag, params, offline


@pytest.fixture
def stereo_node(rclpy_context: Any) -> Iterator[Any]:
    """A test node in the namespace /stereo, so that relative names meet the labeler's outputs."""
    import rclpy

    node = rclpy.create_node("end_to_end_recorder", namespace=topics.STEREO_NAMESPACE, context=rclpy_context)
    try:
        yield node
    finally:
        node.destroy_node()


def test_player_and_labeler_processes_equal_the_offline_bag_labeler(
    bag_and_offline: tuple[Path, Path, dict[str, list[tuple[int, Any]]]],
    stereo_node: Any,
    ros_process: Callable[..., Any],
    spin_until: Callable[[Any, Callable[[], bool], float], bool],
) -> None:
    import json
    import signal

    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from selfcontra_ros.ros.conversions import image_to_numpy, stamp_to_nanoseconds

    bag, params, offline = bag_and_offline
    received: dict[str, list[Any]] = {topics.LABELS: [], topics.LABELS_COLOR: [], topics.DEPTH: []}
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    subscriptions = {
        name: stereo_node.create_subscription(Image, name, messages.append, qos) for name, messages in received.items()
    }
    stats: list[dict[str, Any]] = []
    stats_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    stereo_node.create_subscription(String, "labeler/stats", lambda m: stats.append(json.loads(m.data)), stats_qos)

    labeler = ros_process(
        [
            "-m",
            "selfcontra_ros.ros.labeler_node",
            "--ros-args",
            "--params-file",
            str(params),
            "-r",
            f"__ns:={topics.STEREO_NAMESPACE}",
            "-p",
            "input_qos:=reliable",  # the player publishes reliably: nothing may be lost
            "-p",
            "flush_on_shutdown:=true",  # as label_bag, which labels the last views at the end of the bag
            "-p",
            "stats_period:=0.2",
            "-p",
            f"label_queue_size:={LABEL_QUEUE}",
        ],
        name="labeler",
    )
    assert spin_until(stereo_node, lambda: all(s.get_publisher_count() for s in subscriptions.values()), WAIT_S), (
        labeler.stderr()
    )
    player = ros_process(
        [
            "-m",
            "selfcontra_ros.ros.player_node",
            "--ros-args",
            "-p",
            f"bag:={bag}",
            "-p",
            f"rate:={RATE}",
            "-p",
            f"wait_for_subscribers:={INPUT_SUBSCRIPTIONS}",
        ],
        name="player",
    )
    # While playing: depth for every frame, labels label_delay frames back.
    done = spin_until(
        stereo_node,
        lambda: len(received[topics.DEPTH]) >= FRAMES and len(received[topics.LABELS_COLOR]) >= FRAMES - DELAY,
        WAIT_S,
    )
    assert done, f"{ {k: len(v) for k, v in received.items()} }\n{player.stderr()}\n{labeler.stderr()}"
    assert player.popen.wait(timeout=WAIT_S) == 0, player.stderr()
    assert spin_until(stereo_node, lambda: bool(stats) and stats[-1]["counts"]["views_labelled"] == FRAMES, WAIT_S), (
        stats[-1:] or labeler.stderr()
    )
    # Stopping flushes the window: the last label_delay views get their labels too.
    labeler.popen.send_signal(signal.SIGINT)
    assert spin_until(stereo_node, lambda: len(received[topics.LABELS_COLOR]) >= FRAMES, WAIT_S), labeler.stderr()
    assert labeler.popen.wait(timeout=WAIT_S) == 0, labeler.stderr()

    final = stats[-1]
    assert sum(final["drops"].values()) == 0, final["drops"]  # nothing skipped, nothing lost
    assert final["counts"]["frames"] == FRAMES and final["counts"]["keyframe_skipped"] == 0

    for name in (topics.DEPTH, topics.LABELS):
        expected = offline[topics.bag_topic(name)]
        got = received[name]
        assert len(expected) == FRAMES, f"offline {name}: {len(expected)} messages"
        assert [stamp_to_nanoseconds(m.header.stamp) for m in got] == [stamp for stamp, _ in expected]
        for k, (msg, (_, ref)) in enumerate(zip(got, expected, strict=True)):
            assert msg.header.frame_id == ref.header.frame_id == topics.LEFT_FRAME
            assert msg.encoding == ref.encoding
            assert np.array_equal(image_to_numpy(msg), image_to_numpy(ref), equal_nan=name == topics.DEPTH), (
                f"{name} of frame {k}: the node and label_bag differ"
            )
    labels = np.stack([image_to_numpy(m) for m in received[topics.LABELS]])
    assert (labels == 1).any() and (labels == 2).any(), "expected both positive and negative labels"
