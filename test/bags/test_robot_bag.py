"""A robot's own recording (driver names, compressed distorted image_raw, TF poses) labelled offline like the
package's own bag of the same sequence (bags/robot_bag.py, stereo_input.py, inspect.py, the label CLI)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from selfcontra_ros import cli
from selfcontra_ros.bags import topics
from selfcontra_ros.bags.inspect import inspect_bag, suggest_command
from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.label_bag import label_bag, metrics_path
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.bags.robot_bag import RobotLayout, write_robot_bag
from selfcontra_ros.bags.stereo_input import StereoImages, StereoInput, TFPoses
from selfcontra_ros.bags.tf import TFBuffer
from selfcontra_ros.bags.writer import BagWriter
from selfcontra_ros.confidence.bag_frames import iter_bag_frames, read_bag_labels
from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.geometry import invert_pose
from selfcontra_ros.odometry.run import bag_reference_poses, odometry_command
from selfcontra_ros.ros.conversions import stamp_to_nanoseconds

FRAMES, WIDTH, HEIGHT = 8, 320, 96
FLUSH = Path(__file__).parent / "flush_all.yaml"
LAYOUT = RobotLayout()
ROBOT_INPUT = StereoInput(
    image_transport="compressed", rectify=True, remaps=tuple(LAYOUT.remaps()), pose_source="tf", world_frame="odom"
)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("street")
    write_sequence(root, scene="street", frames=FRAMES, seed=1, width=WIDTH, height=HEIGHT)
    return root


@pytest.fixture(scope="module")
def robot_bag(sequence: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_robot_bag(sequence, tmp_path_factory.mktemp("robot") / "robot")


@pytest.fixture(scope="module")
def package_labels(sequence: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """The same sequence in the package's own layout, labelled with the same (current) defaults."""
    folder = tmp_path_factory.mktemp("package")
    bag = kitti_to_mcap(sequence, folder / "street", progress=False)
    return folder / "labelled", label_bag(bag, folder / "labelled", params_file=FLUSH, progress=False)


@pytest.fixture(scope="module")
def robot_labels(robot_bag: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """The robot bag labelled through the command line, with the command ``selfcontra inspect`` suggests."""
    out = tmp_path_factory.mktemp("robot_out") / "labelled"
    command = suggest_command(inspect_bag(robot_bag), out=str(out))
    assert command is not None
    argv = [*command.split()[1:], "--params", str(FLUSH)]
    assert cli.main(argv) == 0
    return out, json.loads(metrics_path(out).read_text())


def _left_stamps(bag: Path, topic: str) -> list[int]:
    with open_bag(bag) as opened:
        return [stamp_to_nanoseconds(m.msg.header.stamp) for m in opened.messages([topic])]


def test_inspect_suggests_the_driver_layout(robot_bag: Path) -> None:
    report = inspect_bag(robot_bag)
    assert len(report.pairs) == 1 and report.pairs[0].raw and report.pairs[0].compressed
    assert ("base_link", LAYOUT.left_frame, True) in report.tf_links
    assert ("odom", "base_link", False) in report.tf_links
    rates = {row["topic"]: row["rate_hz"] for row in report.topics}
    assert rates[topics.TF] == pytest.approx(50.0) and rates[LAYOUT.topic("left", "camera_info")] == pytest.approx(10)
    remaps = " ".join(f"--remap {rule}" for rule in LAYOUT.remaps())
    assert suggest_command(report, "OUT") == (
        f"selfcontra label {robot_bag} --out OUT --namespace {LAYOUT.namespace} {remaps} --image-transport compressed "
        "--rectify --sync approximate --slop 0.005 --pose-source tf --world-frame odom"
    )


def test_tf_poses_are_the_rectified_left_views(sequence: Path, robot_bag: Path) -> None:
    """TF chain odom -> base_link -> raw optical frame, times the calibration's R_left^T, is the sequence's pose.

    Without the rectification rotation (0.6 degrees here) the orientation would be off by that much.
    """
    seq = open_sequence(sequence)
    assert seq.poses is not None
    tf = TFBuffer()
    images = StereoImages(ROBOT_INPUT)
    topic = ROBOT_INPUT.topics(LAYOUT.namespace)
    infos: dict[str, Any] = {}
    with open_bag(robot_bag) as bag:
        for message in bag.messages():
            if message.topic in (topics.TF, topics.TF_STATIC):
                assert tf.add_message(message.msg, static=message.topic == topics.TF_STATIC) == []
            elif message.topic in (topic[topics.LEFT_INFO], topic[topics.RIGHT_INFO]):
                infos.setdefault(message.topic, message.msg)
    camera = images.camera_from_infos(infos[topic[topics.LEFT_INFO]], infos[topic[topics.RIGHT_INFO]])
    assert camera == seq.camera
    poses = TFPoses(tf, "odom")
    poses.set_camera(LAYOUT.left_frame, images.raw_from_rectified)
    odom_world = np.asarray(LAYOUT.base_camera) @ invert_pose(seq.poses[0])
    for i, stamp in enumerate(_left_stamps(robot_bag, topic[topics.LEFT_RAW])):
        found = poses.pose_at(stamp)
        assert found.pose is not None, found.detail
        np.testing.assert_allclose(found.pose, odom_world @ seq.poses[i], atol=1e-6)
    reference = bag_reference_poses(
        robot_bag, _left_stamps(robot_bag, topic[topics.LEFT_RAW]), stereo_input=ROBOT_INPUT
    )
    assert reference is not None
    np.testing.assert_allclose(reference, odom_world @ seq.poses, atol=1e-6)


def test_robot_bag_labels_match_the_package_layout(
    package_labels: tuple[Path, dict[str, Any]], robot_labels: tuple[Path, dict[str, Any]]
) -> None:
    """Same frames labelled, label metrics and labels themselves within tolerance.

    The robot bag's images went through JPEG (quality 95: about one grey level) and two bilinear
    resamplings (distortion here, rectification in the labeler: about one more), so SGBM's disparities
    move by fractions of a pixel and some pixels cross a threshold of the matcher or the stages. On
    this sequence that changed accuracy by 0.1 points, coverage by 9 % of itself, and under 1 % of the pixels
    labelled in both; the tolerances (2 points, 25 %, 3 %) leave room for other CPUs and later defaults
    while a wrong pose, a missed rectification or swapped cameras fail them by far.
    """
    package_bag, package = package_labels
    robot_bag, robot = robot_labels
    assert robot["status"] == "complete" and robot["dropped"] == {} and robot["input"]["pose_source"] == "tf"
    assert [f["frame"] for f in robot["frames"]] == [f["frame"] for f in package["frames"]]
    assert abs(robot["mean"]["accuracy"] - package["mean"]["accuracy"]) < 0.02
    assert 0.75 < robot["mean"]["coverage"] / package["mean"]["coverage"] < 1.25
    ours, theirs = read_bag_labels(robot_bag), read_bag_labels(package_bag)
    assert sorted(ours.images) == sorted(theirs.images)  # labels carry the left image's stamp in both
    agree = total = 0
    for stamp in theirs.images:
        a, b = ours.at(stamp), theirs.at(stamp)
        assert a is not None and b is not None and a.shape == b.shape == (HEIGHT, WIDTH)
        both = (a > 0) & (b > 0)
        agree += int((a[both] == b[both]).sum())
        total += int(both.sum())
    assert total > 0.5 * sum(int((theirs.at(s) > 0).sum()) for s in theirs.images)  # type: ignore[operator]
    assert agree / total > 0.97


def test_the_labelled_robot_bag_trains_like_it_was_labelled(
    sequence: Path, robot_labels: tuple[Path, dict[str, Any]]
) -> None:
    """bag_frames reads the labelled robot bag with the input it was labelled with (recorded in the bag)."""
    robot_bag, _ = robot_labels
    frames = list(iter_bag_frames(robot_bag))
    labels = read_bag_labels(robot_bag)
    assert len(frames) == FRAMES and all(f.stamp_ns in labels for f in frames)
    seq = open_sequence(sequence)
    inner = np.s_[8:-8, 8:-8]
    for frame in frames:
        original = seq[frame.index].left
        assert frame.left.shape == original.shape  # rectified, grey
        assert np.abs(frame.left.astype(float) - original)[inner].mean() < 4.0


def _damaged_copy(robot_bag: Path, damaged: Path) -> Path:
    """The robot bag with its third left image a JPEG cut short."""
    left = LAYOUT.topic("left", "image_raw") + topics.COMPRESSED_SUFFIX
    with open_bag(robot_bag) as bag, BagWriter(damaged) as writer:
        for summary in bag.topics.values():
            writer.add_topic(summary.name, summary.msgtype)
        seen = 0
        for message in bag.messages():
            if message.topic == left:
                seen += 1
                if seen == 3:
                    message.msg.data = message.msg.data[:200]
            writer.write(message.topic, message.stamp_ns, message.msg)
    return damaged


def test_a_corrupt_compressed_image_is_dropped_and_counted(robot_bag: Path, tmp_path: Path) -> None:
    damaged = _damaged_copy(robot_bag, tmp_path / "damaged")
    metrics = label_bag(
        damaged,
        tmp_path / "out",
        params_file=FLUSH,
        progress=False,
        sync="approximate",
        slop=0.005,
        namespace=LAYOUT.namespace,
        stereo_input=ROBOT_INPUT,
    )
    assert metrics["dropped"] == {"bad_compressed_image": 1}
    assert metrics["dropped_frames"] == [{"frame": 2, "reason": "bad_compressed_image"}]
    assert len(metrics["frames"]) == FRAMES - 1


def test_without_tf_links_the_error_names_them(
    robot_bag: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A bag whose /tf_static is missing: every frame dropped, counted by the TF reason; the log names the link."""
    stripped = tmp_path / "no_static"
    with open_bag(robot_bag) as bag, BagWriter(stripped) as writer:
        kept = [summary for summary in bag.topics.values() if summary.name != topics.TF_STATIC]
        for summary in kept:
            writer.add_topic(summary.name, summary.msgtype)
        for message in bag.raw_messages([summary.name for summary in kept]):
            writer.write_raw(message.topic, message.stamp_ns, message.data)
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING, logger="selfcontra_ros.bags.label_bag"):
        metrics = label_bag(
            stripped, out, params_file=FLUSH, progress=False, sync="approximate", slop=0.005, stereo_input=ROBOT_INPUT
        )
    assert metrics["dropped"] == {"tf_unknown_frame": FRAMES}
    warnings = [r.getMessage() for r in caplog.records if "tf_unknown_frame" in r.getMessage()]
    assert len(warnings) == 1  # once per reason
    assert f"no transform has child '{LAYOUT.left_frame}'" in warnings[0]
    assert f"missing link: {LAYOUT.base_frame} -> {LAYOUT.left_frame}" in warnings[0]


def test_compressed_package_bags_label_like_raw_ones(
    sequence: Path, package_labels: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    """kitti2mcap --compress-images png: lossless, so the labels are the raw bag's, bit for bit."""
    bag = tmp_path / "png"
    assert cli.main(["kitti2mcap", str(sequence), "--out", str(bag), "--compress-images", "png"]) == 0
    with open_bag(bag) as opened:
        assert opened.topics["/stereo/left/image_rect/compressed"].msgtype == topics.COMPRESSED_IMAGE_TYPE
    metrics = label_bag(bag, tmp_path / "out", params_file=FLUSH, progress=False)  # the bag records its transport
    package_bag, package = package_labels
    assert metrics["mean"] == package["mean"]
    ours, theirs = read_bag_labels(tmp_path / "out"), read_bag_labels(package_bag)
    for stamp in theirs.images:
        np.testing.assert_array_equal(ours.at(stamp), theirs.at(stamp))


def _robot_options() -> list[str]:
    remaps = [arg for rule in LAYOUT.remaps() for arg in ("--remap", rule)]
    return ["--namespace", LAYOUT.namespace, *remaps, "--image-transport", "compressed", "--rectify"]


def test_train_and_evaluate_read_a_robot_bag_with_its_options(
    robot_bag: Path, robot_labels: tuple[Path, dict[str, Any]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """train / evaluate-confidence take the robot options: the raw robot bag reads as its labelled copy does.

    The labelled bag records how it was read (and its sync); the raw recording needs the options. Both
    give the same frames, so the LRD scores are equal, and training matches every label image.
    """
    labelled, _ = robot_labels
    options = [*_robot_options(), "--slop", "0.005"]
    raw_out, stored_out = tmp_path / "raw", tmp_path / "stored"
    argv = ["evaluate-confidence", "--model", "lrd", "--algorithm", "sgbm"]
    assert cli.main([*argv, "--data", str(robot_bag), "--out", str(raw_out), *options]) == 0
    assert cli.main([*argv, "--data", str(labelled), "--out", str(stored_out)]) == 0
    raw, stored = (json.loads((out / "metrics.json").read_text()) for out in (raw_out, stored_out))
    assert len(raw["frames"]) == FRAMES
    assert raw["frames"] == stored["frames"]
    capsys.readouterr()
    model = tmp_path / "robot.model"
    train = ["train", "--features", "gcp", "--data", str(robot_bag), "--labels", str(labelled), "--out", str(model)]
    assert cli.main([*train, *options]) == 0
    assert f"from {FRAMES} frames" in capsys.readouterr().out
    assert model.is_file()


def test_options_given_for_a_labelled_bag_replace_only_their_part_of_its_record(
    robot_labels: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    """--image-transport compressed on a labelled robot bag keeps its recorded remaps, rectify and TF poses."""
    labelled, _ = robot_labels
    args = cli.build_parser().parse_args(
        [
            "evaluate-confidence",
            "--model",
            "lrd",
            "--data",
            str(labelled),
            "--out",
            "x",
            "--image-transport",
            "compressed",
        ]
    )
    read_as = cli._stereo_input(args, labelled)
    assert read_as == ROBOT_INPUT
    args = cli.build_parser().parse_args(
        ["label", str(labelled), "--out", "x", "--no-rectify", "--pose-source", "pose"]
    )
    read_as = cli._stereo_input(args, labelled)
    assert read_as is not None and read_as.remaps == ROBOT_INPUT.remaps and not read_as.rectify
    assert read_as.pose_source == "pose" and read_as.world_frame is None
    out = tmp_path / "eval"
    options = ["--image-transport", "compressed", "--slop", "0.005"]
    assert (
        cli.main(["evaluate-confidence", "--model", "lrd", "--data", str(labelled), "--out", str(out), *options]) == 0
    )
    assert len(json.loads((out / "metrics.json").read_text())["frames"]) == FRAMES


def test_rectification_maps_are_built_once_and_the_first_calibration_is_kept(
    robot_bag: Path, robot_labels: tuple[Path, dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One map build per camera for the whole bag; a calibration changing part way is dropped, not used.

    From the 4th right camera_info on, its distortion differs: the labels stay those of the unchanged
    bag (the session, the maps and the TF correction keep the first calibration).
    """
    changed = tmp_path / "changed"
    right_info = LAYOUT.topic("right", "camera_info")
    with open_bag(robot_bag) as bag, BagWriter(changed) as writer:
        for summary in bag.topics.values():
            writer.add_topic(summary.name, summary.msgtype)
        seen = 0
        for message in bag.messages():
            if message.topic == right_info:
                seen += 1
                if seen >= 4:
                    message.msg.d = np.asarray(message.msg.d) * 1.5
            writer.write(message.topic, message.stamp_ns, message.msg)
    builds: list[int] = []
    build = cv2.initUndistortRectifyMap
    monkeypatch.setattr(cv2, "initUndistortRectifyMap", lambda *args: builds.append(1) or build(*args))
    metrics = label_bag(
        changed,
        tmp_path / "out",
        params_file=FLUSH,
        progress=False,
        sync="approximate",
        slop=0.005,
        namespace=LAYOUT.namespace,
        stereo_input=ROBOT_INPUT,
    )
    assert len(builds) == 2  # left and right, once
    assert set(metrics["dropped"]) == {"camera_info_changed"} and metrics["dropped"]["camera_info_changed"] >= 5
    _, robot = robot_labels
    assert metrics["frames"] and [f["frame"] for f in metrics["frames"]] == [f["frame"] for f in robot["frames"]]
    assert metrics["mean"] == robot["mean"]


def test_odometry_skips_a_pair_with_a_corrupt_image_and_reports_it(robot_bag: Path, tmp_path: Path) -> None:
    """One bad compressed image costs the odometry its pair, not the run; the report counts it by reason."""
    damaged = _damaged_copy(robot_bag, tmp_path / "damaged")
    lines: list[str] = []
    report = odometry_command(
        damaged,
        tmp_path / "poses.txt",
        namespace=LAYOUT.namespace,
        stereo_input=ROBOT_INPUT,
        slop=0.005,
        progress=False,
        echo=lines.append,
    )
    assert report["dropped"] == {"bad_compressed_image": 1}
    assert report["frames"] == FRAMES - 1
    assert "skipped stereo pairs: bad_compressed_image=1" in lines
    assert len((tmp_path / "poses.txt").read_text().splitlines()) == FRAMES - 1
