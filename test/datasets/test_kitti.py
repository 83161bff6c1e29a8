"""KITTI readers: real samples from the shared data folder and small synthetic folders built here."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.datasets.kitti import (
    DISPARITY_SCALE,
    camera_from_calib,
    open_sequence,
    open_stereo_dataset,
    read_calib,
    read_disparity_png,
    read_image,
    read_poses,
    write_calib,
    write_disparity_png,
    write_poses,
    write_times,
)
from selfcontra_ros.errors import CalibrationError, DatasetError
from selfcontra_ros.geometry import StereoCamera

# KITTI odometry sequence 06 calibration (from the dataset's calib.txt, also in the sample's SOURCE.md).
ODO_FX = 707.0912
ODO_CX = 601.8873
ODO_CY = 183.1104
ODO_TX_RIGHT = -379.8145

W, H = 40, 30


# --------------------------------------------------------------------------- helpers


def _p(fx: float, cx: float, cy: float, offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
    """``K [I | offset]`` (offset = translation t of the camera, metres)."""
    k = np.array([[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]])
    return np.hstack([k, k @ np.reshape(offset, (3, 1))])


def _calib_line(key: str | None, p: NDArray[np.float64]) -> str:
    numbers = " ".join(f"{v:.12e}" for v in p.reshape(-1))
    return numbers if key is None else f"{key}: {numbers}"


def _random_pose(rng: np.random.Generator) -> NDArray[np.float64]:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pose = np.eye(4)
    pose[:3, :3] = q * np.sign(np.linalg.det(q))
    pose[:3, 3] = rng.normal(scale=5.0, size=3)
    return pose


def _write_grey(path: Path, image: NDArray[np.uint8]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def _write_rgb(path: Path, rgb: NDArray[np.uint8]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))  # cv2 writes BGR


# Synthetic odometry layout: camera 2 sits 6 cm left of camera 0 (P2[0,3] = +fx * 0.06), as in KITTI.
FX, CX, CY, BASELINE, CAM2_X = 50.0, 19.5, 14.5, 0.5, -0.06


@dataclass
class OdometryTruth:
    """What :func:`make_odometry` wrote."""

    folder: Path
    grey: NDArray[np.uint8]  # (N, 2, H, W)
    rgb: NDArray[np.uint8]  # (N, 2, H, W, 3)
    gt: NDArray[np.float64]  # (N, H, W), NaN = none
    stamps: NDArray[np.float64]
    poses: NDArray[np.float64]  # (N, 4, 4) T_world_cam0


def make_odometry(
    tmp_path: Path, n: int = 4, *, seq: str = "00", seed: int = 0, times: bool = True, poses: bool = True
) -> OdometryTruth:
    """Write a tiny KITTI odometry root (grey + colour pairs, calib, times, poses, disp_0) and return its truth."""
    rng = np.random.default_rng(seed)
    folder = tmp_path / "sequences" / seq
    grey = rng.integers(0, 256, size=(n, 2, H, W), dtype=np.uint8)
    rgb = rng.integers(0, 256, size=(n, 2, H, W, 3), dtype=np.uint8)
    gt = rng.uniform(1.0, 60.0, size=(n, H, W))
    gt[:, :5, :] = np.nan
    for i in range(n):
        for cam in (0, 1):
            _write_grey(folder / f"image_{cam}" / f"{i:06d}.png", grey[i, cam])
            _write_rgb(folder / f"image_{cam + 2}" / f"{i:06d}.png", rgb[i, cam])
        write_disparity_png(folder / "disp_0" / f"{i:06d}.png", gt[i])
    # Colour cameras with KITTI-like small vertical/forward offsets (equal for both: rows still align).
    p2 = _p(FX, CX, CY, (-CAM2_X, 0.001, 0.003))
    p3 = _p(FX, CX, CY, (-CAM2_X - BASELINE, 0.001, 0.003))
    lines = [
        _calib_line("P0", _p(FX, CX, CY)),
        _calib_line("P1", _p(FX, CX, CY, (-BASELINE, 0.0, 0.0))),
        _calib_line("P2", p2),
        _calib_line("P3", p3),
        "Tr: 1 0 0 0 0 1 0 0 0 0 1 0",
    ]
    (folder / "calib.txt").write_text("\n".join(lines) + "\n")
    stamps = 100.0 + np.cumsum(rng.uniform(0.09, 0.11, size=n))
    if times:
        write_times(folder / "times.txt", stamps)
    pose_array = np.stack([_random_pose(rng) for _ in range(n)])
    if poses:
        write_poses(tmp_path / "poses" / f"{seq}.txt", pose_array)
    return OdometryTruth(folder, grey, rgb, gt, stamps, pose_array)


# --------------------------------------------------------------------------- real data


def test_real_odometry_sequence(shared_data: Path) -> None:
    root = shared_data / "kitti_odometry"
    seq = open_sequence(root)
    assert seq.sequence == "06"
    assert len(seq) == 51
    cam = seq.camera
    assert cam.fx == pytest.approx(ODO_FX) and cam.fy == pytest.approx(ODO_FX)
    assert cam.cx == pytest.approx(ODO_CX) and cam.cy == pytest.approx(ODO_CY)
    assert cam.baseline == pytest.approx(-ODO_TX_RIGHT / ODO_FX, rel=1e-9)
    assert (cam.width, cam.height) == (1226, 370)
    np.testing.assert_allclose(seq.stamps, np.arange(51) * 0.1, atol=1e-12)
    assert seq.stamps[-1] == pytest.approx(5.0)

    assert seq.poses is not None and seq.poses.shape == (51, 4, 4)
    np.testing.assert_allclose(seq.poses[0], np.eye(4), atol=1e-8)
    last_row = np.array((root / "poses" / "06.txt").read_text().split("\n")[50].split(), dtype=float)
    np.testing.assert_array_equal(seq.poses[50][:3].reshape(-1), last_row)
    # About 1.2 m forward per frame on this straight drive.
    assert 55.0 < seq.poses[50][2, 3] < 65.0

    frame = seq[50]
    assert frame.index == 50 and frame.name == "000050" and frame.stamp == pytest.approx(5.0)
    for image in (frame.left, frame.right):
        assert image.dtype == np.uint8 and image.shape == (370, 1226)
    assert frame.gt_disparity is None
    assert frame.pose is not None
    np.testing.assert_array_equal(frame.pose, seq.poses[50])
    np.testing.assert_array_equal(frame.left, cv2.imread(str(root / "sequences/06/image_0/000050.png"), 0))

    # The sequence folder itself opens the same sequence, poses found two levels up.
    same = open_sequence(root / "sequences" / "06")
    assert same.camera == cam and same.poses is not None
    np.testing.assert_array_equal(same.poses, seq.poses)


def test_real_stereo_2015(shared_data: Path) -> None:
    root = shared_data / "kitti_stereo_2015"
    data = open_stereo_dataset(root)
    assert data.benchmark == "2015" and data.color and data.scenes == ["000000"]
    scene = data.scene("000000")
    assert scene.names == ["000000_10"] and scene.reference_index == 0

    # Baseline from P_rect_02/03 despite P_rect_02's non-zero Tx: the naive reading of the file.
    entries = read_calib(root / "training" / "calib_cam_to_cam" / "000000.txt")
    p2, p3 = entries["P_rect_02"].reshape(3, 4), entries["P_rect_03"].reshape(3, 4)
    assert p2[0, 3] > 40.0
    naive = (p2[0, 3] - p3[0, 3]) / p2[0, 0]
    assert scene.camera.baseline == pytest.approx(naive, abs=1e-3)
    assert 0.52 < scene.camera.baseline < 0.55
    assert scene.camera.fx == pytest.approx(721.5377)
    assert (scene.camera.width, scene.camera.height) == (1242, 375)

    frame = scene[0]
    assert frame.pose is None and frame.stamp == pytest.approx(1.0)
    assert frame.left.shape == (375, 1242, 3) and frame.right.shape == (375, 1242, 3)
    bgr = cv2.imread(str(root / "training" / "image_2" / "000000_10.png"), cv2.IMREAD_COLOR)
    assert bgr is not None
    np.testing.assert_array_equal(frame.left, bgr[..., ::-1])

    noc = frame.gt_disparity
    assert noc is not None and noc.dtype == np.float32 and noc.shape == (375, 1242)
    valid_noc = np.isfinite(noc)
    assert 0.05 < valid_noc.mean() < 0.5
    assert np.all((noc[valid_noc] > 0) & (noc[valid_noc] < 256))

    occ = open_stereo_dataset(root / "training", ground_truth="occ").scene(0)[0].gt_disparity
    assert occ is not None
    valid_occ = np.isfinite(occ)
    assert np.all(valid_occ[valid_noc])
    assert valid_occ.sum() > valid_noc.sum()


def test_real_calib_agrees_with_rewritten_file(shared_data: Path, tmp_path: Path) -> None:
    calib = shared_data / "kitti_odometry" / "sequences" / "06" / "calib.txt"
    camera = camera_from_calib(calib, 1226, 370)
    written = tmp_path / "calib.txt"
    write_calib(written, camera)
    other = camera_from_calib(written, 1226, 370)
    for field in ("fx", "fy", "cx", "cy", "baseline"):
        assert getattr(other, field) == pytest.approx(getattr(camera, field), rel=1e-12)
    # The same two rows without labels (the form the sample was first published in).
    unlabelled = tmp_path / "unlabelled.txt"
    unlabelled.write_text("\n".join(line.split(":", 1)[1].strip() for line in calib.read_text().splitlines()))
    assert camera_from_calib(unlabelled, 1226, 370) == camera


# --------------------------------------------------------------------------- calibration


def test_write_calib_round_trip(tmp_path: Path) -> None:
    camera = StereoCamera(fx=612.25, fy=611.5, cx=320.125, cy=240.75, baseline=0.1234567, width=640, height=480)
    write_calib(tmp_path / "calib.txt", camera)
    entries = read_calib(tmp_path / "calib.txt")
    assert sorted(entries) == ["P0", "P1", "P2", "P3"]
    assert entries["P1"][3] == pytest.approx(-camera.fx * camera.baseline)
    for pair in (("P0", "P1"), ("P2", "P3")):
        other = camera_from_calib(tmp_path / "calib.txt", 640, 480, left=pair[0], right=pair[1])
        for field in ("fx", "fy", "cx", "cy", "baseline"):
            assert getattr(other, field) == pytest.approx(getattr(camera, field), rel=1e-12)


def test_colour_calib_with_left_tx(tmp_path: Path) -> None:
    p2 = _p(700.0, 600.0, 180.0, (0.06, 0.0, 0.0))
    p3 = _p(700.0, 600.0, 180.0, (0.06 - 0.54, 0.0, 0.0))
    path = tmp_path / "calib.txt"
    path.write_text("\n".join(_calib_line(k, p) for k, p in (("P2", p2), ("P3", p3))))
    camera = camera_from_calib(path, 1242, 375, left="P2", right="P3")
    assert p2[0, 3] != 0.0
    assert camera.baseline == pytest.approx((p2[0, 3] - p3[0, 3]) / p2[0, 0], rel=1e-12)
    assert camera.baseline == pytest.approx(0.54, rel=1e-12)


def test_calib_rejects_non_horizontal_pair(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    p0 = _p(700.0, 600.0, 180.0)
    p1 = _p(700.0, 600.0, 180.0, (-0.5, 0.05, 0.0))  # 5 cm vertical offset: rows do not line up
    path.write_text("\n".join(_calib_line(k, p) for k, p in (("P0", p0), ("P1", p1))))
    with pytest.raises(CalibrationError, match=r"calib\.txt"):
        camera_from_calib(path, 100, 100)


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("P0: " + " ".join(["1"] * 12) + "\nP1: " + " ".join(["1"] * 11), 2),
        ("P0: " + " ".join(["1"] * 12) + "\nP1: 1 2 x 4 5 6 7 8 9 10 11 12", 2),
        (" ".join(["1"] * 11), 1),
        ("P0: " + " ".join(["1"] * 12) + "\nP0: " + " ".join(["1"] * 12), 2),
    ],
)
def test_malformed_calib_line_names_file_and_line(tmp_path: Path, text: str, line: int) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=rf"calib\.txt:{line}"):
        read_calib(path)


# --------------------------------------------------------------------------- synthetic odometry


def test_synthetic_odometry_grey(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    seq = open_sequence(tmp_path)
    assert len(seq) == 4 and not seq.color
    assert (seq.camera.fx, seq.camera.cx, seq.camera.cy) == (FX, CX, CY)
    assert seq.camera.baseline == pytest.approx(BASELINE, rel=1e-12)
    assert (seq.camera.width, seq.camera.height) == (W, H)
    np.testing.assert_allclose(seq.stamps, truth.stamps, rtol=0, atol=1e-9)
    assert seq.poses is not None
    np.testing.assert_allclose(seq.poses, truth.poses, atol=1e-11)
    frames = list(seq)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [f.name for f in frames] == ["000000", "000001", "000002", "000003"]
    for i, frame in enumerate(frames):
        np.testing.assert_array_equal(frame.left, truth.grey[i, 0])
        np.testing.assert_array_equal(frame.right, truth.grey[i, 1])
        gt = truth.gt[i]
        assert frame.gt_disparity is not None
        np.testing.assert_array_equal(np.isnan(frame.gt_disparity), np.isnan(gt))
        np.testing.assert_allclose(frame.gt_disparity, gt, atol=0.5 / DISPARITY_SCALE + 1e-6)
    assert seq[-1].name == "000003"
    with pytest.raises(IndexError):
        seq[4]


def test_synthetic_odometry_colour_is_rgb_and_pose_is_camera_2(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    seq = open_sequence(tmp_path, color=True)
    assert seq.color
    # Off-axis offsets are equal for P2 and P3, so the baseline is the horizontal one.
    assert seq.camera.baseline == pytest.approx(BASELINE, rel=1e-9)
    frame = seq[2]
    np.testing.assert_array_equal(frame.left, truth.rgb[2, 0])
    np.testing.assert_array_equal(frame.right, truth.rgb[2, 1])
    assert frame.gt_disparity is None  # disp_0 belongs to the grey camera 0
    # Camera 2's optical centre is at (CAM2_X, -0.001, -0.003) in camera 0's frame.
    assert seq.poses is not None
    centre_cam0 = np.array([CAM2_X, -0.001, -0.003, 1.0])
    for pose0, pose2 in zip(truth.poses, seq.poses, strict=True):
        np.testing.assert_allclose(pose2[:, 3], pose0 @ centre_cam0, atol=1e-9)
        np.testing.assert_allclose(pose2[:3, :3], pose0[:3, :3], atol=1e-12)


def test_open_sequence_path_forms(tmp_path: Path) -> None:
    make_odometry(tmp_path / "a", seq="07", times=False)
    by_folder = open_sequence(tmp_path / "a" / "sequences" / "07")
    assert by_folder.poses is not None and by_folder.sequence == "07"
    np.testing.assert_allclose(by_folder.stamps, np.arange(4) * 0.1)
    assert open_sequence(tmp_path / "a", sequence="7").sequence == "07"

    make_odometry(tmp_path / "b", seq="00", poses=False)
    make_odometry(tmp_path / "b", seq="01", poses=False)
    with pytest.raises(DatasetError, match="sequence="):
        open_sequence(tmp_path / "b")
    seq = open_sequence(tmp_path / "b", sequence="01")
    assert seq.sequence == "01" and seq.poses is None and seq[0].pose is None
    with pytest.raises(DatasetError, match="'05'"):
        open_sequence(tmp_path / "b", sequence="05")
    with pytest.raises(DatasetError, match="neither"):
        open_sequence(tmp_path / "b" / "sequences")


def test_colour_only_sequence_is_taken(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    folder = truth.folder
    for cam in (0, 1):
        for f in (folder / f"image_{cam}").iterdir():
            f.unlink()
        (folder / f"image_{cam}").rmdir()
    seq = open_sequence(tmp_path)
    assert seq.color and seq[0].left.shape == (H, W, 3)


# --------------------------------------------------------------------------- malformed inputs


def test_missing_calib(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    calib = truth.folder / "calib.txt"
    calib.unlink()
    with pytest.raises(DatasetError, match=re.escape(str(calib))):
        open_sequence(tmp_path)


def test_calib_with_eleven_numbers(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    calib = truth.folder / "calib.txt"
    lines = calib.read_text().splitlines()
    lines[1] = lines[1].rsplit(" ", 1)[0]
    calib.write_text("\n".join(lines))
    with pytest.raises(DatasetError, match=re.escape(f"{calib}:2: projection matrix P1 has 11 numbers")):
        open_sequence(tmp_path)


def test_calib_missing_colour_matrices(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    calib = truth.folder / "calib.txt"
    calib.write_text("\n".join(calib.read_text().splitlines()[:2]))
    assert open_sequence(tmp_path).camera.baseline == pytest.approx(BASELINE)
    with pytest.raises(DatasetError, match=re.escape(f"{calib} has no P2")):
        open_sequence(tmp_path, color=True)


def test_three_poses_for_four_frames(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    poses_path = tmp_path / "poses" / "00.txt"
    write_poses(poses_path, truth.poses[:3])
    with pytest.raises(DatasetError, match=re.escape(f"{poses_path} holds 3 poses for 4 frames")):
        open_sequence(tmp_path)


def test_times_count_mismatch(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    write_times(truth.folder / "times.txt", [0.0, 0.1])
    with pytest.raises(DatasetError, match=r"times\.txt holds 2 stamps for 4 frames"):
        open_sequence(tmp_path)


def test_missing_right_image(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    right = truth.folder / "image_1" / "000002.png"
    right.unlink()
    with pytest.raises(DatasetError, match=r"image_0 holds 4 images but right folder .*image_1 holds 3"):
        open_sequence(tmp_path)
    # Same counts but different names: the missing file is named.
    _write_grey(right.parent / "000009.png", np.zeros((H, W), np.uint8))
    with pytest.raises(DatasetError, match=re.escape(str(right))):
        open_sequence(tmp_path)


def test_inconsistent_image_sizes(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    right = truth.folder / "image_1" / "000001.png"
    _write_grey(right, np.zeros((H, W + 2), np.uint8))
    seq = open_sequence(tmp_path)
    seq[0]
    with pytest.raises(DatasetError, match=re.escape(str(right))):
        seq[1]
    left = truth.folder / "image_0" / "000003.png"
    _write_grey(left, np.zeros((H + 1, W), np.uint8))
    _write_grey(left.parent.parent / "image_1" / "000003.png", np.zeros((H + 1, W), np.uint8))
    with pytest.raises(DatasetError, match=re.escape(f"{left} is {W}x{H + 1}, expected {W}x{H}")):
        seq[3]


def test_unreadable_image_names_path(tmp_path: Path) -> None:
    truth = make_odometry(tmp_path)
    left = truth.folder / "image_0" / "000001.png"
    left.write_bytes(b"not a png at all")
    seq = open_sequence(tmp_path)
    with pytest.raises(DatasetError, match=re.escape(f"cannot read image {left}")):
        seq[1]
    with pytest.raises(DatasetError, match="expected a colour image"):
        read_image(truth.folder / "image_0" / "000000.png", color=True)


# --------------------------------------------------------------------------- file formats


def test_disparity_png_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    disparity = rng.uniform(0.01, 255.9, size=(37, 53))
    invalid = rng.random(disparity.shape) < 0.3
    disparity[invalid] = np.nan
    disparity[0, :3] = [-1.0, 0.0, np.inf]  # all three mean "no disparity"
    invalid[0, :3] = True
    path = tmp_path / "sub" / "d.png"
    write_disparity_png(path, disparity)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16
    np.testing.assert_array_equal(raw == 0, invalid)
    back = read_disparity_png(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(back), invalid)
    assert np.max(np.abs(back[~invalid] - disparity[~invalid])) <= 0.5 / DISPARITY_SCALE + 1e-5
    # A tiny positive disparity stays valid rather than turning into "no value".
    write_disparity_png(path, np.full((2, 2), 1e-4))
    assert np.all(read_disparity_png(path) == np.float32(1.0 / DISPARITY_SCALE))


def test_disparity_png_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="holds at most"):
        write_disparity_png(tmp_path / "d.png", np.full((2, 2), 300.0))
    with pytest.raises(DatasetError, match=r"\.png"):
        write_disparity_png(tmp_path / "d.jpg", np.ones((2, 2)))
    grey8 = tmp_path / "grey8.png"
    _write_grey(grey8, np.ones((4, 4), np.uint8))
    with pytest.raises(DatasetError, match=re.escape(f"{grey8} is uint8")):
        read_disparity_png(grey8)
    with pytest.raises(DatasetError, match=r"missing\.png"):
        read_disparity_png(tmp_path / "missing.png")


def test_poses_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    poses = np.stack([_random_pose(rng) for _ in range(6)])
    write_poses(tmp_path / "p" / "00.txt", poses)
    lines = (tmp_path / "p" / "00.txt").read_text().splitlines()
    assert len(lines) == 6 and all(len(line.split()) == 12 for line in lines)
    np.testing.assert_allclose(read_poses(tmp_path / "p" / "00.txt"), poses, rtol=1e-11, atol=1e-11)
    write_poses(tmp_path / "p3x4.txt", poses[:, :3, :])
    np.testing.assert_allclose(read_poses(tmp_path / "p3x4.txt"), poses, rtol=1e-11, atol=1e-11)
    bad = poses.copy()
    bad[2, 3, 0] = 1.0
    with pytest.raises(DatasetError, match="last row"):
        write_poses(tmp_path / "bad.txt", bad)
    (tmp_path / "short.txt").write_text(" ".join(["0"] * 12) + "\n" + " ".join(["0"] * 13) + "\n")
    with pytest.raises(DatasetError, match=r"short\.txt:2: .*13 numbers"):
        read_poses(tmp_path / "short.txt")


# --------------------------------------------------------------------------- synthetic stereo 2012 / 2015


@dataclass
class StereoTruth:
    """What :func:`make_stereo_2015` wrote: images by ``<name>_<camera>`` and (noc, occ) ground truth by scene."""

    images: dict[str, NDArray[np.uint8]]
    gt: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]


def make_stereo_2015(split: Path, scenes: dict[str, list[int]], seed: int = 0) -> StereoTruth:
    """A KITTI 2015 multiview split: colour pairs, calib_cam_to_cam with P_rect_02/03, noc/occ ground truth."""
    rng = np.random.default_rng(seed)
    images: dict[str, NDArray[np.uint8]] = {}
    gts: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    for scene, numbers in scenes.items():
        for mm in numbers:
            name = f"{scene}_{mm:02d}"
            for cam in (2, 3):
                images[f"{name}_{cam}"] = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
                _write_rgb(split / f"image_{cam}" / f"{name}.png", images[f"{name}_{cam}"])
        occ = rng.uniform(1.0, 80.0, size=(H, W))
        occ[:4] = np.nan
        noc = occ.copy()
        noc[:, :6] = np.nan
        gts[scene] = (noc, occ)
        write_disparity_png(split / "disp_noc_0" / f"{scene}_10.png", noc)
        write_disparity_png(split / "disp_occ_0" / f"{scene}_10.png", occ)
        calib = [
            "calib_time: 09-Jan-2012 13:57:47",
            "S_rect_02: 4.000000e+01 3.000000e+01",
            _calib_line("P_rect_00", _p(FX, CX, CY)),
            _calib_line("P_rect_01", _p(FX, CX, CY, (-0.54, 0.0, 0.0))),
            _calib_line("P_rect_02", _p(FX, CX, CY, (0.06, 0.0003, 0.0027))),
            _calib_line("P_rect_03", _p(FX, CX, CY, (0.06 - 0.53, -0.0024, 0.0027))),
        ]
        (split / "calib_cam_to_cam").mkdir(parents=True, exist_ok=True)
        (split / "calib_cam_to_cam" / f"{scene}.txt").write_text("\n".join(calib) + "\n")
    return StereoTruth(images, gts)


def test_synthetic_stereo_2015_multiview(tmp_path: Path) -> None:
    truth = make_stereo_2015(tmp_path / "training", {"000001": [9, 10, 11, 0], "000000": [10, 11]})
    data = open_stereo_dataset(tmp_path)
    assert data.benchmark == "2015" and data.color
    assert data.scenes == ["000000", "000001"] and len(data) == 2
    scene = data["000001"]
    assert data[1].names == scene.names and data.scene(1).names == scene.names
    assert scene.names == ["000001_00", "000001_09", "000001_10", "000001_11"]
    np.testing.assert_allclose(scene.stamps, [0.0, 0.9, 1.0, 1.1])
    assert scene.reference_index == 2
    # Off-axis offsets differ by 2.7 mm: ignored; horizontal baseline 0.53 m.
    assert scene.camera.baseline == pytest.approx(0.53, rel=1e-9)
    frames = list(scene)
    noc, _ = truth.gt["000001"]
    for frame in frames:
        assert frame.pose is None
        np.testing.assert_array_equal(frame.left, truth.images[f"{frame.name}_2"])
        np.testing.assert_array_equal(frame.right, truth.images[f"{frame.name}_3"])
        if frame.name.endswith("_10"):
            assert frame.gt_disparity is not None
            np.testing.assert_array_equal(np.isnan(frame.gt_disparity), np.isnan(noc))
        else:
            assert frame.gt_disparity is None
    occ_frame = open_stereo_dataset(tmp_path / "training", ground_truth="occ")[1][2]
    assert occ_frame.gt_disparity is not None
    noc_frame = frames[2].gt_disparity
    assert noc_frame is not None
    assert np.isfinite(occ_frame.gt_disparity).sum() > np.isfinite(noc_frame).sum()
    assert [s.scene for s in data] == ["000000", "000001"]


def test_synthetic_stereo_2015_missing_right_image(tmp_path: Path) -> None:
    make_stereo_2015(tmp_path / "training", {"000000": [10, 11], "000001": [10, 11]})
    right = tmp_path / "training" / "image_3" / "000001_11.png"
    right.unlink()
    with pytest.raises(DatasetError, match=r"holds 4 images but right folder .*holds 3"):
        open_stereo_dataset(tmp_path)
    _write_rgb(right.parent / "000000_12.png", np.zeros((H, W, 3), np.uint8))
    with pytest.raises(DatasetError, match=re.escape(str(right))):
        open_stereo_dataset(tmp_path)
    # Removed after opening: the scene names it.
    _write_rgb(right, np.zeros((H, W, 3), np.uint8))
    _write_rgb(right.parent.parent / "image_2" / "000000_12.png", np.zeros((H, W, 3), np.uint8))
    data = open_stereo_dataset(tmp_path)
    right.unlink()
    with pytest.raises(DatasetError, match=re.escape(str(right))):
        data.scene("000001")
    (tmp_path / "training" / "calib_cam_to_cam" / "000000.txt").unlink()
    with pytest.raises(DatasetError, match=r"000000\.txt does not exist"):
        data.scene(0)


def test_synthetic_stereo_2012_grey_and_colour(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    split = tmp_path / "testing"
    grey = {mm: rng.integers(0, 256, size=(2, H, W), dtype=np.uint8) for mm in (10, 11)}
    for mm, pair in grey.items():
        for cam in (0, 1):
            _write_grey(split / f"image_{cam}" / f"000004_{mm}.png", pair[cam])
            _write_rgb(split / f"colored_{cam}" / f"000004_{mm}.png", np.dstack([pair[cam]] * 3))
    gt = rng.uniform(1.0, 50.0, size=(H, W))
    write_disparity_png(split / "disp_occ" / "000004_10.png", gt)
    lines = [
        _calib_line("P0", _p(FX, CX, CY)),
        _calib_line("P1", _p(FX, CX, CY, (-0.54, 0.0, 0.0))),
        _calib_line("P2", _p(FX, CX, CY, (0.06, 0.0, 0.0))),
        _calib_line("P3", _p(FX, CX, CY, (0.06 - 0.54, 0.0, 0.0))),
    ]
    (split / "calib").mkdir()
    (split / "calib" / "000004.txt").write_text("\n".join(lines))

    data = open_stereo_dataset(tmp_path, split="testing", ground_truth="occ")
    assert data.benchmark == "2012" and not data.color
    scene = data[0]
    assert scene.camera.baseline == pytest.approx(0.54, rel=1e-12)
    frames = list(scene)
    np.testing.assert_array_equal(frames[1].right, grey[11][1])
    assert frames[0].gt_disparity is not None and frames[1].gt_disparity is None
    np.testing.assert_allclose(frames[0].gt_disparity, gt, atol=0.5 / DISPARITY_SCALE + 1e-5)
    # No disp_noc folder: no ground truth with the default choice.
    assert open_stereo_dataset(tmp_path, split="testing")[0][0].gt_disparity is None

    colour = open_stereo_dataset(split, color=True, ground_truth="occ")[0]
    assert colour.camera.baseline == pytest.approx(0.54, rel=1e-12)
    frame = colour[0]
    assert frame.left.shape == (H, W, 3) and frame.gt_disparity is None  # 2012 ground truth is camera 0's
    np.testing.assert_array_equal(frame.left[..., 0], grey[10][0])

    with pytest.raises(DatasetError, match="'noc' or 'occ'"):
        open_stereo_dataset(tmp_path, ground_truth="all")
    with pytest.raises(DatasetError, match="not a KITTI stereo split"):
        open_stereo_dataset(tmp_path)
