"""Offline bag labeling: same labels as the sequence labeler, bit-exact copy, robustness (label_bag)."""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from selfcontra_ros.bags import label_bag as label_bag_module
from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.label_bag import label_bag, metrics_path, resolve_namespace
from selfcontra_ros.bags.reader import BagError, default_typestore, open_bag
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.config import load_params
from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.matching.base import make_matcher
from selfcontra_ros.pipeline import label_sequence
from selfcontra_ros.ros.conversions import (
    disparity_from_message,
    image_to_numpy,
    stamp_to_nanoseconds,
    stereo_camera_from_camera_infos,
)

FRAMES, WIDTH, HEIGHT = 8, 320, 96
NS = topics.STEREO_NAMESPACE
LEFT, RIGHT = topics.bag_topic(topics.LEFT_IMAGE), topics.bag_topic(topics.RIGHT_IMAGE)
POSE, LABELS = topics.bag_topic(topics.POSE), topics.bag_topic(topics.LABELS)
LABELS_COLOR, DEPTH = topics.bag_topic(topics.LABELS_COLOR), topics.bag_topic(topics.DEPTH)
DISPARITY = topics.bag_topic(topics.DISPARITY)
CONFIDENCE, DEPTH_FILTERED = topics.bag_topic(topics.CONFIDENCE), topics.bag_topic(topics.DEPTH_FILTERED)
OUTPUTS = {LABELS, LABELS_COLOR, DEPTH, DISPARITY, CONFIDENCE, DEPTH_FILTERED}

#: the package defaults, labelling the last views too (the test sequences are shorter than the window)
FLUSH = Path(__file__).parent / "flush_all.yaml"


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("street")
    write_sequence(root, scene="street", frames=FRAMES, seed=1, width=WIDTH, height=HEIGHT)
    return root


@pytest.fixture(scope="module")
def in_bag(sequence: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return kitti_to_mcap(sequence, tmp_path_factory.mktemp("in") / "street", progress=False)


@pytest.fixture(scope="module")
def reference(sequence: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """The sequence labeler's output on the same frames and parameters."""
    out = tmp_path_factory.mktemp("reference")
    return out, label_sequence(sequence, out, params_file=FLUSH)


@pytest.fixture(scope="module")
def labelled(in_bag: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("out") / "labelled"
    return out, label_bag(in_bag, out, params_file=FLUSH, progress=False)


def _left_stamps(bag_path: Path) -> list[int]:
    with open_bag(bag_path) as bag:
        return [stamp_to_nanoseconds(m.msg.header.stamp) for m in bag.messages([LEFT])]


def _reference_labels(reference: Path, index: int) -> np.ndarray:
    image = cv2.imread(str(reference / "labels" / f"{index:06d}.png"), cv2.IMREAD_UNCHANGED)
    assert image is not None, f"no reference label image for frame {index}"
    return image


def _figures(entry: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in entry.items() if k != "stamp"}


def _rewrite(src: Path, dst: Path, edit: Callable[[int, str, int, Any], list[tuple[str, int, Any]]]) -> Path:
    """Copy a bag message by message through ``edit(frame, topic, log_ns, msg) -> [(topic, log_ns, msg)]``."""
    first = open_bag(src).start_ns
    with open_bag(src) as bag, BagWriter(dst, compress="none") as out:
        for topic, log_ns, msg in bag.messages():
            frame = round((log_ns - first) / 1e8)  # the synthetic sequence runs at 10 Hz
            for new_topic, new_log, new_msg in edit(frame, topic, log_ns, msg):
                out.write(new_topic, new_log, new_msg)
    return dst


# --------------------------------------------------------------------------- same core, same result


def test_output_bag_holds_every_input_message_bit_exact(in_bag: Path, labelled: tuple[Path, dict[str, Any]]) -> None:
    out, _ = labelled
    with open_bag(in_bag) as src, open_bag(out) as dst:
        assert set(dst.topics) == set(src.topics) | OUTPUTS
        for name, summary in src.topics.items():
            assert dst.topics[name].msgtype == summary.msgtype
            copied = [(m.stamp_ns, m.data) for m in dst.raw_messages([name])]
            assert copied == [(m.stamp_ns, m.data) for m in src.raw_messages([name])], name
        assert dst.custom_data["selfcontra.namespace"] == NS


def test_labels_equal_the_sequence_labeler(
    in_bag: Path, labelled: tuple[Path, dict[str, Any]], reference: tuple[Path, dict[str, Any]]
) -> None:
    out, report = labelled
    ref_dir, ref_report = reference
    stamps = _left_stamps(in_bag)
    expected = [entry["frame"] for entry in ref_report["frames"]]
    assert expected, "the reference labelled no frame"
    with open_bag(out) as bag:
        labels = list(bag.messages([LABELS]))
        colours = list(bag.messages([LABELS_COLOR]))
        left_frame_id = next(bag.messages([LEFT])).msg.header.frame_id
    assert len(labels) == len(colours) == len(expected)
    seen = []
    for message, colour in zip(labels, colours, strict=True):
        header_ns = stamp_to_nanoseconds(message.msg.header.stamp)
        index = stamps.index(header_ns)  # stamped with a labelled view's own stamp ...
        seen.append(index)
        assert message.stamp_ns == header_ns  # ... logged at that stamp ...
        assert message.msg.header.frame_id == left_frame_id  # ... in the left image's frame
        assert message.msg.encoding == "mono8" and colour.msg.encoding == "rgb8"
        image = image_to_numpy(message.msg)
        np.testing.assert_array_equal(image, _reference_labels(ref_dir, index))
        np.testing.assert_array_equal(image_to_numpy(colour.msg), colorize_labels(image))
        assert stamp_to_nanoseconds(colour.msg.header.stamp) == header_ns
    assert sorted(seen) == expected
    assert report["skipped_frames"] == ref_report["skipped_frames"]


def test_metrics_equal_the_sequence_labeler(
    labelled: tuple[Path, dict[str, Any]], reference: tuple[Path, dict[str, Any]]
) -> None:
    out, report = labelled
    _, ref = reference
    assert report["status"] == "complete" and report["has_ground_truth"] is True
    assert report["dropped"] == {} and report["frames_synchronised"] == FRAMES
    assert [_figures(e) for e in report["frames"]] == [_figures(e) for e in ref["frames"]]
    for key, value in ref["mean"].items():
        assert (math.isnan(value) and math.isnan(report["mean"][key])) or report["mean"][key] == value, key
    assert report["params"] == ref["params"]
    on_disk = json.loads(metrics_path(out).read_text())
    assert on_disk["frames"][0]["frame"] == report["frames"][0]["frame"]
    assert on_disk["mean"]["accuracy"] == pytest.approx(report["mean"]["accuracy"])


def test_depth_and_disparity_are_the_query_algorithms(in_bag: Path, labelled: tuple[Path, dict[str, Any]]) -> None:
    out, _ = labelled
    matcher = make_matcher(load_params(FLUSH)[0])
    with open_bag(out) as bag:
        infos = [next(bag.messages([topics.bag_topic(n)])).msg for n in (topics.LEFT_INFO, topics.RIGHT_INFO)]
        camera = stereo_camera_from_camera_infos(*infos)
        lefts = [image_to_numpy(m.msg) for m in bag.messages([LEFT])]
        rights = [image_to_numpy(m.msg) for m in bag.messages([RIGHT])]
        depths = list(bag.messages([DEPTH]))
        disparities = list(bag.messages([DISPARITY]))
    stamps = _left_stamps(in_bag)
    assert [m.stamp_ns for m in depths] == [m.stamp_ns for m in disparities] == stamps
    for k in (0, FRAMES - 1):
        disparity, f, t = disparity_from_message(disparities[k].msg)
        expected = matcher.compute(lefts[k], rights[k], with_right=False).left
        np.testing.assert_array_equal(np.isnan(disparity), np.isnan(expected))
        np.testing.assert_array_equal(disparity[~np.isnan(disparity)], expected[~np.isnan(expected)])
        assert (f, t) == (pytest.approx(camera.fx, rel=1e-7), pytest.approx(camera.baseline, rel=1e-7))  # float32
        msg = disparities[k].msg
        assert (msg.min_disparity, msg.max_disparity, msg.delta_d) == (0.0, 127.0, 1.0 / 16.0)  # SGBM's range
        depth = image_to_numpy(depths[k].msg)
        assert depths[k].msg.encoding == "32FC1"
        np.testing.assert_allclose(depth, camera.fx * camera.baseline / disparity, rtol=1e-6)  # NaN where invalid


def test_confidence_switches_from_lrd_to_the_trained_forest(in_bag: Path, tmp_path: Path) -> None:
    """Every frame gets confidence and depth/filtered, as a session with an online confidence gives them."""
    from selfcontra_ros.confidence.online import ConfidenceParams, OnlineConfidence
    from selfcontra_ros.config import load_confidence_params
    from selfcontra_ros.session import LabelingSession

    params = tmp_path / "params.yaml"
    params.write_text(
        "labeler:\n  ros__parameters:\n    labeler: {window_size: 6, label_delay: 3, stage3_min_free_space_views: 0}\n"
        "    confidence: {retrain_every: 2, samples_per_view: 500, n_estimators: 3, max_depth: 8}\n"
    )
    model = tmp_path / "model.npz"
    out = tmp_path / "labelled"
    report = label_bag(in_bag, out, params_file=params, progress=False, model_out=model)
    assert report["confidence"]["source"] == "gcp" and report["confidence"]["models_trained"] >= 2
    assert model.is_file()
    matcher, labeler = load_params(params)
    confidence_params = load_confidence_params(params)
    with open_bag(out) as bag:
        infos = [next(bag.messages([topics.bag_topic(n)])).msg for n in (topics.LEFT_INFO, topics.RIGHT_INFO)]
        camera = stereo_camera_from_camera_infos(*infos)
        lefts = [image_to_numpy(m.msg) for m in bag.messages([LEFT])]
        rights = [image_to_numpy(m.msg) for m in bag.messages([RIGHT])]
        poses = [m.msg for m in bag.messages([POSE])]
        confidences = [image_to_numpy(m.msg) for m in bag.messages([CONFIDENCE])]
        filtered = [image_to_numpy(m.msg) for m in bag.messages([DEPTH_FILTERED])]
        depths = [image_to_numpy(m.msg) for m in bag.messages([DEPTH])]
    assert len(confidences) == len(filtered) == FRAMES
    # Reference: the same session and online confidence, driven directly (reproducible: one thread, seeded).
    from selfcontra_ros.bags.sync import PoseBuffer

    buffer = PoseBuffer()
    for msg in poses:
        buffer.add_message(msg)
    online = OnlineConfidence(confidence_params, background=False, log=lambda m: None)
    session = LabelingSession(camera, matcher, labeler, online)
    stamps = _left_stamps(in_bag)
    sources = []
    for k in range(FRAMES):
        pose = buffer.lookup(stamps[k], max_gap_s=0.5, max_extrapolation_s=0.05).pose
        assert pose is not None
        expected = session.process(lefts[k], rights[k], pose, stamp=stamps[k] / 1e9, key=k)
        assert expected.confidence is not None
        np.testing.assert_allclose(confidences[k], expected.confidence, atol=1e-6, err_msg=f"frame {k}")
        keep = confidences[k] >= confidence_params.confidence_threshold
        np.testing.assert_array_equal(filtered[k][keep], depths[k][keep])
        assert np.all(np.isnan(filtered[k][~keep]))
        sources.append(expected.confidence_source)
        lrd = online.lrd(session.match_frame(lefts[k], rights[k]).frame)
        if expected.confidence_source == "lrd":
            np.testing.assert_allclose(confidences[k], lrd, atol=1e-6)
        else:
            assert np.abs(confidences[k] - lrd).max() > 0.1, f"frame {k}: the forest equals LRD"
    assert sources[0] == "lrd" and sources[-1] == "gcp", sources
    session.flush()
    # model_out holds the last model (trained at the flush): the same forest as the reference's.
    saved = OnlineConfidence(ConfidenceParams(model_in=str(model)), background=False, log=lambda m: None)
    frame = session.match_frame(lefts[0], rights[0]).frame
    np.testing.assert_allclose(saved.confidence(frame), online.confidence(frame), atol=1e-6)


# --------------------------------------------------------------------------- robustness


def test_interruption_leaves_a_readable_bag(in_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    original = label_bag_module.LabelingSession.process
    calls = []

    def interrupted(self: Any, *args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(label_bag_module.LabelingSession, "process", interrupted)
    out = tmp_path / "partial"
    with pytest.raises(KeyboardInterrupt):
        label_bag(in_bag, out, params_file=FLUSH, progress=False)
    stamps = _left_stamps(in_bag)
    with open_bag(out) as bag:
        assert bag.topics[DEPTH].message_count == 4
        assert [m.stamp_ns for m in bag.raw_messages([DEPTH])] == stamps[:4]
        assert bag.topics[LEFT].message_count >= 5  # the input copy ran ahead of the labelling
        assert len(list(bag.raw_messages())) == bag.message_count
    report = json.loads(metrics_path(out).read_text())
    assert report["status"] == "interrupted"


def test_unreadable_or_corrupt_input_raises_bag_error(in_bag: Path, tmp_path: Path) -> None:
    """Nothing readable before the cut, or a damaged chunk: refused or stopped (test_truncated.py: cuts it survives)."""
    truncated = tmp_path / "truncated"
    shutil.copytree(in_bag, truncated)
    mcap = next(truncated.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match=r"truncated|corrupt"):
        label_bag(truncated, tmp_path / "out1", params_file=FLUSH, progress=False)
    mcap.write_bytes(data[:64] + bytes(len(data) - 64))
    with pytest.raises(BagError, match=r"truncated|corrupt"):
        label_bag(truncated, tmp_path / "out2", params_file=FLUSH, progress=False)
    assert not (tmp_path / "out1").exists() and not (tmp_path / "out2").exists()  # refused before writing
    with pytest.raises(BagError, match="does not exist"):
        label_bag(tmp_path / "missing", tmp_path / "out3", params_file=FLUSH, progress=False)
    # Damage inside a chunk, index and footer intact: found while reading, the partial output stays readable.
    damaged = bytearray(data)
    damaged[len(data) // 2 : len(data) // 2 + 2000] = bytes(2000)
    mcap.write_bytes(bytes(damaged))
    with pytest.raises(BagError, match=r"is corrupt: a chunk with .* messages from"):
        label_bag(truncated, tmp_path / "out4", params_file=FLUSH, progress=False)
    with open_bag(tmp_path / "out4") as bag:
        assert len(list(bag.raw_messages())) == bag.message_count
    assert json.loads(metrics_path(tmp_path / "out4").read_text())["status"] == "failed"


def test_an_existing_output_is_never_overwritten(in_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(BagError, match="exists already"):
        label_bag(in_bag, out, params_file=FLUSH, progress=False)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_bad_arguments_raise_package_errors(in_bag: Path, tmp_path: Path) -> None:
    with pytest.raises(SelfContraError, match="exact"):
        label_bag(in_bag, tmp_path / "o1", sync="exact", slop=0.01, params_file=FLUSH, progress=False)
    with pytest.raises(SelfContraError, match="max_pose_gap"):
        label_bag(in_bag, tmp_path / "o2", max_pose_gap=-1.0, params_file=FLUSH, progress=False)
    with pytest.raises(SelfContraError, match="external"):
        label_bag(in_bag, tmp_path / "o3", disparity_topic="/stereo/disparity", params_file=FLUSH, progress=False)
    assert not any(tmp_path.iterdir())


def test_missing_pose_topic_and_labelled_input_are_refused(
    in_bag: Path, labelled: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    no_pose = _rewrite(in_bag, tmp_path / "no_pose", lambda _f, t, s, m: [] if t == POSE else [(t, s, m)])
    with pytest.raises(BagError, match="pose"):
        label_bag(no_pose, tmp_path / "out1", params_file=FLUSH, progress=False)
    with pytest.raises(BagError, match="output topic"):
        label_bag(labelled[0], tmp_path / "out2", params_file=FLUSH, progress=False)


def test_bad_messages_are_counted_and_skipped(in_bag: Path, tmp_path: Path) -> None:
    def damage(frame: int, topic: str, log_ns: int, msg: Any) -> list[tuple[str, int, Any]]:
        if frame == 2 and topic == LEFT:
            msg.encoding = "bayer_rggb8"  # same bytes, an encoding the labeler does not match
        if frame == 4 and topic == RIGHT:  # a right image cropped to 300 columns, header kept
            pixels = image_to_numpy(msg)[:, :300]
            msg.width, msg.step, msg.data = 300, 300, np.ascontiguousarray(pixels).reshape(-1)
        if frame == 5 and topic == POSE:
            msg.pose.position.x = math.nan
        return [(topic, log_ns, msg)]

    bad = _rewrite(in_bag, tmp_path / "bad", damage)
    # Poses are 0.1 s apart: with a 0.15 s gap limit frame 5 cannot bridge its lost pose.
    report = label_bag(bad, tmp_path / "out", params_file=FLUSH, progress=False, max_pose_gap=0.15)
    assert report["status"] == "complete"
    assert report["dropped"] == {"bad_encoding": 1, "bad_pose": 1, "image_mismatch": 1, "pose_gap": 1}
    assert report["dropped_frames"] == [
        {"frame": 2, "reason": "bad_encoding"},
        {"frame": 4, "reason": "image_mismatch"},
        {"frame": 5, "reason": "pose_gap"},
    ]
    labelled_frames = {entry["frame"] for entry in report["frames"]}
    assert labelled_frames | set(report["skipped_frames"]) == {0, 1, 3, 6, 7}
    with open_bag(tmp_path / "out") as bag:
        assert bag.topics[DEPTH].message_count == 5
        assert bag.topics[LABELS].message_count == len(labelled_frames)
    # With the default gap limit (0.5 s) frame 5 takes the pose interpolated from frames 4 and 6.
    report = label_bag(bad, tmp_path / "out_default", params_file=FLUSH, progress=False)
    assert report["dropped"] == {"bad_encoding": 1, "bad_pose": 1, "image_mismatch": 1}


def test_approximate_sync_and_odometry_poses(
    in_bag: Path, tmp_path: Path, reference: tuple[Path, dict[str, Any]]
) -> None:
    """Right images 2 ms late and poses as nav_msgs/Odometry: exact sync pairs nothing, approximate all."""
    types = default_typestore().types
    vector = types["geometry_msgs/msg/Vector3"]

    def shift(frame: int, topic: str, log_ns: int, msg: Any) -> list[tuple[str, int, Any]]:
        if topic == RIGHT:
            stamp = stamp_to_nanoseconds(msg.header.stamp) + 2_000_000
            msg.header.stamp = types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
            return [(topic, log_ns + 2_000_000, msg)]
        if topic == POSE:
            odom = types["nav_msgs/msg/Odometry"](
                header=msg.header,
                child_frame_id=topics.LEFT_FRAME,
                pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=msg.pose, covariance=np.zeros(36)),
                twist=types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=types["geometry_msgs/msg/Twist"](
                        linear=vector(x=0.0, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.0)
                    ),
                    covariance=np.zeros(36),
                ),
            )
            return [("/odom", log_ns, odom)]
        return [(topic, log_ns, msg)]

    shifted = _rewrite(in_bag, tmp_path / "shifted", shift)
    exact = label_bag(shifted, tmp_path / "exact", params_file=FLUSH, progress=False, pose_topic="/odom")
    assert exact["frames"] == [] and exact["frames_synchronised"] == 0
    assert exact["dropped"]["unsynchronised_left"] == FRAMES
    approximate = label_bag(
        shifted,
        tmp_path / "approximate",
        sync="approximate",
        slop=0.005,
        params_file=FLUSH,
        progress=False,
        pose_topic="/odom",
    )
    ref_dir, ref = reference
    assert approximate["dropped"] == {}
    assert [_figures(e) for e in approximate["frames"]] == [_figures(e) for e in ref["frames"]]
    with open_bag(tmp_path / "approximate") as bag:
        for message in bag.messages([LABELS]):
            index = _left_stamps(shifted).index(message.stamp_ns)
            np.testing.assert_array_equal(image_to_numpy(message.msg), _reference_labels(ref_dir, index))


def test_external_disparity_topic(in_bag: Path, tmp_path: Path) -> None:
    """matcher.algorithm external: the disparity comes from a topic (here the ground truth, copied)."""
    gt_topic = topics.bag_topic(topics.GT_DISPARITY)
    with_external = _rewrite(
        in_bag,
        tmp_path / "external_in",
        lambda _f, t, s, m: [(t, s, m), ("/ext/disparity", s, m)] if t == gt_topic else [(t, s, m)],
    )
    params = tmp_path / "external.yaml"
    params.write_text(
        "labeler:\n  ros__parameters:\n    matcher: {algorithm: external}\n    labeler: {flush_incomplete: true}\n"
    )
    out = tmp_path / "external_out"
    report = label_bag(with_external, out, params_file=params, disparity_topic="/ext/disparity", progress=False)
    assert report["dropped"] == {} and report["frames"]
    # Labelling the ground truth itself: every evaluable pixel is correct, so no labelled pixel is a wrong positive.
    assert all(
        entry["positive_precision"] in (1.0, None) or math.isnan(entry["positive_precision"])
        for entry in report["frames"]
    )
    with open_bag(out) as bag:
        gts = [disparity_from_message(m.msg)[0] for m in bag.messages([gt_topic])]
        disparities = [disparity_from_message(m.msg)[0] for m in bag.messages([DISPARITY])]
    assert len(disparities) == FRAMES
    for gt, disparity in zip(gts, disparities, strict=True):
        np.testing.assert_array_equal(disparity, gt)


def test_namespace_resolution() -> None:
    assert resolve_namespace({"/stereo/left/image_rect", "/cam/left/image_rect"}) == "/stereo"
    assert resolve_namespace({"/cam/left/image_rect", "/cam/right/image_rect"}) == "/cam"
    assert resolve_namespace({"/left/image_rect"}) == ""
    assert resolve_namespace({"/a/left/image_rect"}, "b/") == "/b"
    with pytest.raises(BagError, match="several"):
        resolve_namespace({"/a/left/image_rect", "/b/left/image_rect"})
    with pytest.raises(BagError, match="no <namespace>"):
        resolve_namespace({"/a/image"})


def test_sequence_frames_are_bag_frames(sequence: Path, in_bag: Path) -> None:
    """Frame N of the bag is frame N of the sequence (the key of the metrics)."""
    seq = open_sequence(sequence)
    with open_bag(in_bag) as bag:
        lefts = [image_to_numpy(m.msg) for m in bag.messages([LEFT])]
    for k in (0, FRAMES - 1):
        np.testing.assert_array_equal(lefts[k], seq[k].left)
