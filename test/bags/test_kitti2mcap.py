"""kitti2mcap: rotations, and KITTI/synthetic sequences round-tripped through MCAP bags (rosbags and mcap readers)."""

from __future__ import annotations

import math
import shutil
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from numpy.typing import NDArray

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import (
    DEFAULT_STAMP_OFFSET_NS,
    kitti_to_mcap,
    seconds_to_nanoseconds,
)
from selfcontra_ros.bags.reader import BagError, open_bag
from selfcontra_ros.datasets.kitti import read_poses, read_times
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.errors import DatasetError, PoseError
from selfcontra_ros.geometry import quaternion_from_rotation, rotation_from_quaternion
from selfcontra_ros.ros.conversions import (
    disparity_from_message,
    image_to_numpy,
    stamp_to_nanoseconds,
    stereo_camera_from_camera_infos,
)

W, H, FRAMES = 320, 96, 5
LEFT, RIGHT = topics.bag_topic(topics.LEFT_IMAGE), topics.bag_topic(topics.RIGHT_IMAGE)
LEFT_INFO, RIGHT_INFO = topics.bag_topic(topics.LEFT_INFO), topics.bag_topic(topics.RIGHT_INFO)
POSE, GT = topics.bag_topic(topics.POSE), topics.bag_topic(topics.GT_DISPARITY)


# --------------------------------------------------------------------------- rotations


def _rodrigues(axis: list[float], angle: float) -> NDArray[np.float64]:
    """Rotation matrix from OpenCV (an implementation independent of the package)."""
    vec = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis) * angle
    matrix, _ = cv2.Rodrigues(vec)
    return np.asarray(matrix, dtype=np.float64)


def _rotate(q: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """``q v q*`` with Hamilton products, quaternions as (x, y, z, w)."""

    def mul(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
        return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])

    conj = np.array([-q[0], -q[1], -q[2], q[3]])
    return mul(mul(q, np.concatenate([v, [0.0]])), conj)[:3]


@pytest.mark.parametrize(
    ("axis", "angle", "expected"),
    [
        ([1, 0, 0], 0.0, [0, 0, 0, 1]),
        ([1, 0, 0], math.pi, [1, 0, 0, 0]),
        ([0, 1, 0], math.pi, [0, 1, 0, 0]),
        ([0, 0, 1], math.pi / 2, [0, 0, math.sqrt(0.5), math.sqrt(0.5)]),
        ([0, 0, 1], -math.pi / 2, [0, 0, -math.sqrt(0.5), math.sqrt(0.5)]),
        ([1, 1, 0], math.pi, [math.sqrt(0.5), math.sqrt(0.5), 0, 0]),
        ([1, 1, 1], 2 * math.pi / 3, [0.5, 0.5, 0.5, 0.5]),
    ],
)
def test_quaternion_of_known_rotations(axis: list[float], angle: float, expected: list[float]) -> None:
    q = quaternion_from_rotation(_rodrigues(axis, angle))
    # q and -q are the same rotation; w >= 0 fixes the sign except at w == 0.
    sign = 1.0 if np.dot(q, expected) >= 0 else -1.0
    np.testing.assert_allclose(sign * q, expected, atol=1e-12)
    assert q[3] >= 0


def test_quaternion_round_trips_and_rotates_like_the_matrix() -> None:
    rng = np.random.default_rng(3)
    angles = np.concatenate([rng.uniform(0, math.pi, 40), [math.pi - 1e-9, math.pi, 1e-9]])
    for angle in angles:
        rotation = _rodrigues(list(rng.normal(size=3)), float(angle))
        q = quaternion_from_rotation(rotation)
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        np.testing.assert_allclose(rotation_from_quaternion(q), rotation, atol=1e-12)
        v = rng.normal(size=3)
        np.testing.assert_allclose(_rotate(q, v), rotation @ v, atol=1e-12)
    for _ in range(40):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        back = quaternion_from_rotation(rotation_from_quaternion(q))
        np.testing.assert_allclose(back, q if q[3] >= 0 else -q, atol=1e-12)


def test_quaternion_rejects_non_rotations() -> None:
    with pytest.raises(PoseError, match="determinant"):
        quaternion_from_rotation(np.diag([1.0, 1.0, -1.0]))  # a reflection
    with pytest.raises(PoseError, match="3x3"):
        quaternion_from_rotation(np.eye(4))
    with pytest.raises(PoseError, match="quaternion"):
        rotation_from_quaternion([0.0, 0.0, 0.0, 0.0])


def test_seconds_to_nanoseconds_keeps_epoch_precision() -> None:
    assert seconds_to_nanoseconds(0.1) == 100_000_000
    assert seconds_to_nanoseconds(2.0) == 2_000_000_000
    for seconds in (1_316_995_200.123456789, 1_700_000_000.987654321, 12.000000001):
        # Exact rational value of the float: the nanoseconds the conversion must round to.
        assert seconds_to_nanoseconds(seconds) == round(Fraction(seconds) * 10**9)


# --------------------------------------------------------------------------- synthetic sequence -> bag


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 5-frame 320x96 synthetic street sequence and its zstd bag: ``(sequence folder, bag folder)``."""
    root = tmp_path_factory.mktemp("synthetic")
    seq = write_sequence(root / "data", scene="street", frames=FRAMES, seed=5, width=W, height=H)
    bag = kitti_to_mcap(root / "data", root / "bag", progress=False)
    return seq, bag


def _messages_by_topic(bag_path: Path) -> dict[str, list[tuple[int, Any]]]:
    out: dict[str, list[tuple[int, Any]]] = {}
    with open_bag(bag_path) as bag:
        for topic, stamp_ns, msg in bag.messages():
            out.setdefault(topic, []).append((stamp_ns, msg))
    return out


def test_synthetic_bag_reads_back_with_rosbags(synthetic: tuple[Path, Path]) -> None:
    seq_dir, bag_path = synthetic
    from selfcontra_ros.datasets.kitti import open_sequence

    seq = open_sequence(seq_dir)
    times = read_times(seq_dir / "times.txt")
    expected_stamps = [DEFAULT_STAMP_OFFSET_NS + round(t * 1e9) for t in times]
    poses = read_poses(seq_dir.parent.parent / "poses" / "00.txt")
    got = _messages_by_topic(bag_path)

    assert set(got) == {LEFT, RIGHT, LEFT_INFO, RIGHT_INFO, POSE, GT}
    for topic, messages in got.items():
        assert [stamp for stamp, _ in messages] == expected_stamps, topic
        assert [stamp_to_nanoseconds(m.header.stamp) for _, m in messages] == expected_stamps, topic

    for k in range(FRAMES):
        name = f"{k:06d}.png"
        for topic, folder, frame_id in ((LEFT, "image_0", topics.LEFT_FRAME), (RIGHT, "image_1", topics.RIGHT_FRAME)):
            msg = got[topic][k][1]
            assert msg.encoding == "mono8" and msg.header.frame_id == frame_id
            png = cv2.imread(str(seq_dir / folder / name), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(image_to_numpy(msg), png), f"{topic} frame {k} differs from {folder}/{name}"

        left_info, right_info = got[LEFT_INFO][k][1], got[RIGHT_INFO][k][1]
        assert (left_info.header.frame_id, right_info.header.frame_id) == (topics.LEFT_FRAME, topics.RIGHT_FRAME)
        camera = stereo_camera_from_camera_infos(left_info, right_info)
        for field in ("fx", "fy", "cx", "cy", "baseline", "width", "height"):
            assert getattr(camera, field) == pytest.approx(getattr(seq.camera, field), rel=1e-12), field
        assert right_info.p[3] == pytest.approx(-seq.camera.fx * seq.camera.baseline, rel=1e-12)

        pose_msg = got[POSE][k][1]
        assert pose_msg.header.frame_id == topics.WORLD_FRAME
        p, o = pose_msg.pose.position, pose_msg.pose.orientation
        np.testing.assert_array_equal([p.x, p.y, p.z], poses[k][:3, 3])
        np.testing.assert_allclose(rotation_from_quaternion([o.x, o.y, o.z, o.w]), poses[k][:3, :3], atol=1e-9)

        disparity, f, t = disparity_from_message(got[GT][k][1])
        truth = seq[k].gt_disparity
        assert truth is not None
        assert np.array_equal(np.isnan(disparity), np.isnan(truth)), f"frame {k}: NaN pattern differs"
        assert np.array_equal(disparity[~np.isnan(truth)], truth[~np.isnan(truth)])
        assert np.isnan(truth).any() and (~np.isnan(truth)).any()  # the check above covers both cases
        assert (f, t) == (pytest.approx(seq.camera.fx), pytest.approx(seq.camera.baseline))


def test_synthetic_bag_is_a_valid_mcap_for_foxglove_and_mcap_ros2(synthetic: tuple[Path, Path]) -> None:
    seq_dir, bag_path = synthetic
    mcap_path = bag_path / f"{bag_path.name}.mcap"
    with mcap_path.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    assert {s.name for s in summary.schemas.values()} == {
        topics.IMAGE_TYPE,
        topics.CAMERA_INFO_TYPE,
        topics.POSE_TYPE,
        topics.DISPARITY_TYPE,
    }
    assert all(s.encoding == "ros2msg" for s in summary.schemas.values())
    assert {c.topic for c in summary.channels.values()} == {LEFT, RIGHT, LEFT_INFO, RIGHT_INFO, POSE, GT}
    assert summary.chunk_indexes and all(c.compression == "zstd" for c in summary.chunk_indexes)
    assert summary.statistics.message_count == 6 * FRAMES

    with mcap_path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [
            (channel.topic, message.log_time, msg) for _, channel, message, msg in reader.iter_decoded_messages()
        ]
    assert len(decoded) == 6 * FRAMES
    stamps = [log_time for _, log_time, _ in decoded]
    assert stamps == sorted(stamps)
    lefts = [(log_time, msg) for topic, log_time, msg in decoded if topic == LEFT]
    for k, (log_time, msg) in enumerate(lefts):
        png = cv2.imread(str(seq_dir / "image_0" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(image_to_numpy(msg), png)
        assert stamp_to_nanoseconds(msg.header.stamp) == log_time == DEFAULT_STAMP_OFFSET_NS + k * 10**8
    truth = cv2.imread(str(seq_dir / "disp_0" / "000004.png"), cv2.IMREAD_UNCHANGED)
    disparity, _, _ = disparity_from_message(next(m for t, _, m in reversed(decoded) if t == GT))
    assert np.array_equal(np.isnan(disparity), truth == 0)
    assert np.array_equal(disparity[truth > 0], truth[truth > 0] / np.float32(256))


def test_metadata_yaml_is_what_ros2_bag_info_reads(synthetic: tuple[Path, Path]) -> None:
    _, bag_path = synthetic
    info = yaml.safe_load((bag_path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap"
    assert info["version"] >= 8
    assert info["message_count"] == 6 * FRAMES
    assert info["relative_file_paths"] == [f"{bag_path.name}.mcap"]
    assert (bag_path / info["relative_file_paths"][0]).is_file()
    assert info["starting_time"]["nanoseconds_since_epoch"] == DEFAULT_STAMP_OFFSET_NS
    assert info["duration"]["nanoseconds"] == (FRAMES - 1) * 10**8
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    assert counts == dict.fromkeys((LEFT, RIGHT, LEFT_INFO, RIGHT_INFO, POSE, GT), FRAMES)
    types = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"] for t in info["topics_with_message_count"]}
    assert types[GT] == topics.DISPARITY_TYPE and types[POSE] == topics.POSE_TYPE
    assert info["custom_data"]["selfcontra.stamp_offset_ns"] == str(DEFAULT_STAMP_OFFSET_NS)
    with open_bag(bag_path) as bag:
        assert bag.start_ns == DEFAULT_STAMP_OFFSET_NS and bag.duration_ns == (FRAMES - 1) * 10**8
        assert {name: t.message_count for name, t in bag.topics.items()} == counts


def test_frame_slice_stamp_offset_and_no_compression(synthetic: tuple[Path, Path], tmp_path: Path) -> None:
    seq_dir, _ = synthetic
    out = kitti_to_mcap(
        seq_dir, tmp_path / "part", frames=slice(1, 5, 2), compress="none", stamp_offset_ns=0, progress=False
    )
    got = _messages_by_topic(out)
    assert [s for s, _ in got[LEFT]] == [100_000_000, 300_000_000]
    png = cv2.imread(str(seq_dir / "image_0" / "000003.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(image_to_numpy(got[LEFT][1][1]), png)
    with (out / "part.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and all(c.compression == "" for c in summary.chunk_indexes)
    with pytest.raises(DatasetError, match="selects no frame"):
        kitti_to_mcap(seq_dir, tmp_path / "none", frames=slice(9, 20), progress=False)


def test_colour_pair_is_written_as_rgb8(synthetic: tuple[Path, Path], tmp_path: Path) -> None:
    seq_dir, _ = synthetic
    colour = tmp_path / "colour"
    shutil.copytree(seq_dir, colour, ignore=shutil.ignore_patterns("image_0", "image_1", "disp_0"))
    for src, dst in (("image_0", "image_2"), ("image_1", "image_3")):
        (colour / dst).mkdir()
        for png in sorted((seq_dir / src).glob("*.png")):
            grey = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
            bgr = np.dstack([grey, 255 - grey, grey // 2])  # three different channels
            cv2.imwrite(str(colour / dst / png.name), bgr)
    out = kitti_to_mcap(colour, tmp_path / "bag", color=True, progress=False)
    got = _messages_by_topic(out)
    assert GT not in got and POSE not in got  # no disp_2 and no poses/ beside this copy
    for k, (_, msg) in enumerate(got[RIGHT]):
        assert msg.encoding == "rgb8"
        bgr = cv2.imread(str(colour / "image_3" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(image_to_numpy(msg), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


# --------------------------------------------------------------------------- failures


def test_refuses_to_overwrite(synthetic: tuple[Path, Path], tmp_path: Path) -> None:
    seq_dir, _ = synthetic
    existing = tmp_path / "bag"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    with pytest.raises(BagError, match="exists already"):
        kitti_to_mcap(seq_dir, existing, progress=False)
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]
    with pytest.raises(BagError, match="compress"):
        kitti_to_mcap(seq_dir, tmp_path / "other", compress="lz5", progress=False)


def test_failure_part_way_leaves_no_bag(synthetic: tuple[Path, Path], tmp_path: Path) -> None:
    seq_dir, _ = synthetic
    broken = tmp_path / "broken"
    shutil.copytree(seq_dir, broken)
    (broken / "image_1" / "000003.png").write_bytes(b"not a png")  # frame 3 fails after frames 0-2 were written
    with pytest.raises(DatasetError, match=r"000003\.png"):
        kitti_to_mcap(broken, tmp_path / "out" / "bag", progress=False)
    assert list((tmp_path / "out").iterdir()) == []  # neither the bag nor its staging folder


# --------------------------------------------------------------------------- real KITTI


def test_real_kitti_odometry_frames(shared_data: Path, tmp_path: Path) -> None:
    from selfcontra_ros.datasets.kitti import camera_from_calib

    root = shared_data / "kitti_odometry"
    seq_dir = root / "sequences" / "06"
    out = kitti_to_mcap(root, tmp_path / "kitti06", frames=slice(0, 3), progress=False)
    got = _messages_by_topic(out)
    assert set(got) == {LEFT, RIGHT, LEFT_INFO, RIGHT_INFO, POSE}  # KITTI odometry has no ground-truth disparity
    poses = read_poses(root / "poses" / "06.txt")
    camera = camera_from_calib(seq_dir / "calib.txt", 1226, 370)  # independent of the reader's own calibration
    for k in range(3):
        stamp = DEFAULT_STAMP_OFFSET_NS + k * 100_000_000  # no times.txt: 10 Hz from 0
        for topic, folder in ((LEFT, "image_0"), (RIGHT, "image_1")):
            assert got[topic][k][0] == stamp
            png = cv2.imread(str(seq_dir / folder / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
            assert png.shape == (370, 1226)
            assert np.array_equal(image_to_numpy(got[topic][k][1]), png)
        o = got[POSE][k][1].pose.orientation
        p = got[POSE][k][1].pose.position
        np.testing.assert_array_equal([p.x, p.y, p.z], poses[k][:3, 3])
        # KITTI poses are rounded to 6 digits, so the matrix is orthonormal to about 1e-6 only.
        np.testing.assert_allclose(rotation_from_quaternion([o.x, o.y, o.z, o.w]), poses[k][:3, :3], atol=1e-5)
        stereo = stereo_camera_from_camera_infos(got[LEFT_INFO][k][1], got[RIGHT_INFO][k][1])
        for field in ("fx", "fy", "cx", "cy", "baseline", "width", "height"):
            assert getattr(stereo, field) == pytest.approx(getattr(camera, field), rel=1e-12), field
        assert stereo.fx == pytest.approx(707.0912) and stereo.baseline == pytest.approx(0.5372, rel=1e-3)  # calib.txt
