"""The labeler node under a few hundred malformed and out-of-order messages: it survives, counts, and still labels.

Every kind of bad input of the node's module docstring is sent in its own
phase; the phase waits until the node has taken in everything, so the drop
counters read from ``/labeler/stats`` must equal what was sent, reason by
reason. A valid sequence afterwards must still be labelled exactly as a fresh
:class:`LabelingSession` labels it.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.bags import topics

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("compiled_kernels")]

# Upper bound (s) of the waits for a node: a passing run never waits it out, but a loaded 2-core machine needs the
# slack (a node process takes seconds to import and to load its kernels from numba's cache, more when others run).
WAIT_S = 60.0

HERE = Path(__file__).resolve().parent


def _load_helpers() -> ModuleType:
    """The publisher/recorder helpers and fixtures of test_labeler_node.py (test modules are not importable)."""
    spec = importlib.util.spec_from_file_location("_selfcontra_labeler_node_tests", HERE / "test_labeler_node.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


helpers = _load_helpers()
frames = helpers.frames
params_file = helpers.params_file
labeler_node = helpers.labeler_node

MS = 1_000_000
POSE_MISSES = ("pose_none_yet", "pose_before_buffer", "pose_after_buffer", "pose_gap")


def test_fuzzed_inputs_are_counted_and_the_node_still_labels(
    frames: Any, params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    from selfcontra_ros.ros.conversions import nanoseconds_to_stamp, numpy_to_image

    # Deep subscription queues: the phases are sent in bursts (a live camera sends one frame at a time).
    node = labeler_node(label_queue_size=64, queue_size=200, max_pose_gap=0.5)
    feeder = helpers.Feeder(ros_node)
    recorder = helpers.Recorder(ros_node)

    def spin(predicate: Callable[[], bool], timeout: float = WAIT_S) -> bool:
        return bool(helpers.spin_nodes([node, ros_node], predicate, timeout))

    def settled(frames_matched: int) -> Callable[[], bool]:
        """Everything sent so far has been taken in: frames matched, nothing waiting for a pose or labeling."""

        def predicate() -> bool:
            s = node.stats()
            c = s["counts"]
            return (
                c["frames"] >= frames_matched
                and s["awaiting_pose"] == 0
                and s["label_queue"] == 0
                and c["views_labelled"] == c["views_queued"]
            )

        return predicate

    def drops_reach(expected: dict[str, int]) -> Callable[[], bool]:
        return lambda: all(node.stats()["drops"][k] >= v for k, v in expected.items())

    assert spin(lambda: feeder.matched() and recorder.matched())
    camera = frames.camera
    left0, right0 = frames.left[0], frames.right[0]
    stamp = helpers.STAMP0_NS
    slot = 0

    def next_stamp() -> int:
        nonlocal slot
        slot += 1
        return stamp + slot * 100 * MS

    matched = 0

    def valid_frame(k: int, *, cam: Any = camera, with_pose: bool = True) -> int:
        nonlocal matched
        t = next_stamp()
        if with_pose:
            feeder.send_pose(frames.poses[k], t)
        feeder.infos(cam, t)
        feeder.images(frames.left[k], frames.right[k], t)
        matched += 1
        return t

    expected = dict.fromkeys(node.stats()["drops"], 0)

    # Phase 0: two valid frames of camera A.
    for k in range(2):
        valid_frame(k)
    assert spin(settled(matched))

    # Phase 1: undecodable images: unsupported encodings and truncated data (40).
    for i in range(40):
        t = next_stamp()
        feeder.infos(camera, t)
        if i < 20:
            feeder.images(left0.astype(np.uint16), right0.astype(np.uint16), t, encoding="16UC1")
        elif i < 30:
            rgba = np.repeat(left0[:, :, None], 4, axis=2)
            feeder.images(rgba, rgba, t, encoding="rgba8")
        else:
            msg = numpy_to_image(left0, "mono8", stamp=nanoseconds_to_stamp(t), frame_id=helpers.FRAME_ID)
            msg.data = bytes(msg.data)[: len(msg.data) // 2]  # truncated: data shorter than height * step
            feeder.left.publish(msg)
            feeder.right.publish(numpy_to_image(right0, "mono8", stamp=nanoseconds_to_stamp(t)))
    expected["bad_image"] = 40

    # Phase 2: images of another size than the camera infos say (30).
    for _ in range(30):
        t = next_stamp()
        feeder.infos(camera, t)
        feeder.images(left0[::2, ::2].copy(), right0[::2, ::2].copy(), t)
    expected["size_mismatch"] = 30

    # Phase 3: camera infos of an uncalibrated left camera (P all zeros) (30).
    for _ in range(30):
        t = next_stamp()
        feeder.infos(camera, t, mangle=lambda info: setattr(info, "p", np.zeros(12)))
        feeder.images(left0, right0, t)
    expected["bad_camera_info"] = 30
    assert spin(drops_reach(expected)), node.stats()

    # Phase 4: images without camera infos (10 pairs) and left images without a right partner (20): 40 unsynced.
    for _ in range(10):
        feeder.images(left0, right0, next_stamp())
    for _ in range(20):
        feeder.left.publish(
            numpy_to_image(left0, "mono8", stamp=nanoseconds_to_stamp(next_stamp()), frame_id=helpers.FRAME_ID)
        )
    expected["unsynced"] = 40

    # Phase 5: a valid frame, then stamps going backwards on both images (40) and the pose (20), and bad poses (40).
    last = valid_frame(2)
    assert spin(settled(matched))
    for i in range(1, 21):
        back = nanoseconds_to_stamp(last - i * MS)
        feeder.left.publish(numpy_to_image(left0, "mono8", stamp=back, frame_id=helpers.FRAME_ID))
        feeder.right.publish(numpy_to_image(right0, "mono8", stamp=back, frame_id=helpers.FRAME_ID))
        feeder.send_pose(frames.poses[2], last - i * MS)
    expected["stamp_backwards"] = 40
    expected["pose_backwards"] = 20
    for i in range(40):
        pose = frames.poses[3].copy()
        if i < 20:
            pose[0, 3] = np.nan
            feeder.send_pose(pose, last + (i + 1) * MS)
        elif i < 30:
            feeder.send_pose(pose, last + (i + 1) * MS, quaternion=np.zeros(4))
        else:
            feeder.send_pose(pose, last + (i + 1) * MS, quaternion=np.array([0.0, 0.0, 0.0, 2.0]))
    expected["bad_pose"] = 40
    assert spin(drops_reach(expected)), node.stats()

    # Phase 6: the pose stream stops for 5 frames (0.6 s between the poses around them, max_pose_gap 0.5 s).
    for k in range(3, 8):
        valid_frame(k, with_pose=False)
    valid_frame(3)
    valid_frame(4)
    assert spin(settled(matched)), node.stats()
    pose_lost = 5

    # Phase 7: a camera change (another focal length): a new session.
    camera_b = dataclasses.replace(camera, fx=camera.fx * 1.1, fy=camera.fy * 1.1)
    for k in range(2):
        valid_frame(k, cam=camera_b)
    assert spin(settled(matched)), node.stats()

    # Phase 8: back to camera A (another new session): a valid sequence, labelled as a fresh session does.
    first_label = len(recorder.received[topics.LABELS])
    first_depth = len(recorder.received[topics.DEPTH])
    stamps = [valid_frame(k) for k in range(helpers.FRAMES)]
    done = spin(
        lambda: len(recorder.received[topics.LABELS_COLOR]) - first_label >= helpers.FRAMES - helpers.DELAY, 20.0
    )
    assert done, node.stats()
    assert spin(settled(matched)), node.stats()
    spin(lambda: recorder.stats is not None and recorder.stats["counts"]["frames"] == matched, WAIT_S)

    stats = recorder.stats  # read from the topic, as a monitoring tool would
    assert stats is not None and stats["counts"]["frames"] == matched
    drops = stats["drops"]
    assert sum(drops[r] for r in POSE_MISSES) == pose_lost, drops
    assert {k: v for k, v in drops.items() if k not in POSE_MISSES} == {
        k: v for k, v in expected.items() if k not in POSE_MISSES
    }
    assert stats["counts"]["camera_resets"] == 2
    assert stats["sync_backwards"] == {"left": 20, "right": 20, "left_info": 0, "right_info": 0}
    assert stats["sync_dropped"] == {"left": 30, "right": 10, "left_info": 0, "right_info": 0}

    # Still alive and still right: the last sequence's depth and labels are a fresh session's.
    sub = helpers.Recorder.__new__(helpers.Recorder)
    sub.received = {
        name: recorder.received[name][first_depth if name in (topics.DEPTH, topics.DISPARITY) else first_label :]
        for name in recorder.received
    }
    shifted = dataclasses.replace(frames)
    shifted.stamp_ns = lambda k: stamps[k]
    helpers.check_outputs(sub, shifted, params_file, flushed=False)


def test_time_jump_back_restarts_the_session(
    frames: Any, params_file: Path, ros_node: Any, labeler_node: Callable[..., Any]
) -> None:
    """A bag played twice (stamps jump back by 0.8 s > time_jump_reset): the second pass is labelled afresh."""
    node = labeler_node(time_jump_reset=0.5)
    feeder = helpers.Feeder(ros_node)
    recorder = helpers.Recorder(ros_node)
    assert helpers.spin_nodes([node, ros_node], lambda: feeder.matched() and recorder.matched(), WAIT_S)
    labelled = helpers.FRAMES - helpers.DELAY
    for k in range(helpers.FRAMES):
        feeder.frame(frames, k)
    assert helpers.spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= labelled, WAIT_S)
    for k in range(helpers.FRAMES):
        feeder.frame(frames, k)
    done = helpers.spin_nodes([node, ros_node], lambda: recorder.count(topics.LABELS_COLOR) >= 2 * labelled, WAIT_S)
    assert done, node.stats()
    stats = node.stats()
    assert stats["counts"]["time_jumps"] == 1
    # Every frame was matched and given to a session; the first pass's last label_delay views stay unlabelled
    # (their window went with the old session), which is no message drop.
    assert {k: v for k, v in stats["drops"].items() if v} == {}
    assert stats["counts"]["views_labelled"] == 2 * helpers.FRAMES
    first = recorder.received[topics.LABELS][:labelled]
    second = recorder.received[topics.LABELS][labelled:]
    assert [helpers.stamp_ns(m) for m in second] == [helpers.stamp_ns(m) for m in first]
    assert all(bytes(a.data) == bytes(b.data) for a, b in zip(first, second, strict=True))


def test_a_full_label_queue_skips_new_views_and_counts_them(
    frames: Any, params_file: Path, ros_node: Any, labeler_node: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Labeling falls behind (held on purpose): with a queue of 1, the views arriving meanwhile are skipped."""
    import threading

    from selfcontra_ros.session import LabelingSession

    release = threading.Event()
    original = LabelingSession.label

    def slow_label(self: Any, *args: Any, **kwargs: Any) -> Any:
        release.wait(timeout=2 * WAIT_S)  # longer than the waits below: held until released
        return original(self, *args, **kwargs)

    monkeypatch.setattr(LabelingSession, "label", slow_label)
    node = labeler_node(label_queue_size=1)
    feeder = helpers.Feeder(ros_node)
    recorder = helpers.Recorder(ros_node)
    assert helpers.spin_nodes([node, ros_node], lambda: feeder.matched() and recorder.matched(), WAIT_S)
    for k in range(helpers.FRAMES):
        feeder.frame(frames, k)
    # Depth keeps flowing while labeling is stuck: the callbacks never wait for the labeler.
    assert helpers.spin_nodes([node, ros_node], lambda: recorder.count(topics.DEPTH) >= helpers.FRAMES, WAIT_S)
    release.set()
    assert helpers.spin_nodes([node, ros_node], lambda: node.stats()["counts"]["views_labelled"] == 2, WAIT_S)
    stats = node.stats()
    # View 0 in the worker, view 1 in the queue, views 2..7 skipped.
    assert stats["drops"]["label_queue_full"] == helpers.FRAMES - 2
    assert stats["counts"]["views_queued"] == 2
    assert recorder.count(topics.LABELS) == 0  # two views are fewer than label_delay + 1
