"""StereoCamera: calibration parsing, depth/disparity, projection."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from selfcontra_ros.errors import CalibrationError
from selfcontra_ros.geometry import StereoCamera, invert_pose, transform_points

KITTI_ODOMETRY_P0 = [707.0912, 0, 601.8873, 0, 0, 707.0912, 183.1104, 0, 0, 0, 1, 0]
KITTI_ODOMETRY_P1 = [707.0912, 0, 601.8873, -379.8145, 0, 707.0912, 183.1104, 0, 0, 0, 1, 0]


def _camera() -> StereoCamera:
    return StereoCamera.from_projections(KITTI_ODOMETRY_P0, KITTI_ODOMETRY_P1, 1226, 370)


def test_baseline_from_right_projection() -> None:
    camera = _camera()
    assert camera.baseline == pytest.approx(379.8145 / 707.0912)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (707.0912, 707.0912, 601.8873, 183.1104)


def test_left_tx_only_difference_matters() -> None:
    shift = 0.06 * 707.0912  # a left camera 6 cm beside the reference, as KITTI's P2
    p_left = np.array(KITTI_ODOMETRY_P0, dtype=float)
    p_right = np.array(KITTI_ODOMETRY_P1, dtype=float)
    p_left[3] += shift
    p_right[3] += shift
    camera = StereoCamera.from_projections(p_left, p_right, 1226, 370)
    assert camera.baseline == pytest.approx(_camera().baseline)


def test_real_kitti_colour_calibration_from_file_and_camera_info_agree(shared_data: Path) -> None:
    pytest.importorskip("sensor_msgs.msg", reason="CameraInfo needs the [ros] extra")
    from sensor_msgs.msg import CameraInfo

    from selfcontra_ros.datasets.kitti import open_stereo_dataset, read_calib
    from selfcontra_ros.ros.conversions import stereo_camera_from_camera_infos

    root = shared_data / "kitti_stereo_2015"
    scene = open_stereo_dataset(root, color=True)[0]
    calib = read_calib(root / "training" / "calib_cam_to_cam" / "000000.txt")
    infos = []
    for key in ("P_rect_02", "P_rect_03"):
        info = CameraInfo()
        info.width, info.height = 1242, 375
        info.p = [float(x) for x in calib[key]]
        infos.append(info)
    from_info = stereo_camera_from_camera_infos(*infos)
    assert from_info.width == scene.camera.width and from_info.height == scene.camera.height
    for field in ("fx", "fy", "cx", "cy", "baseline"):
        assert getattr(from_info, field) == pytest.approx(getattr(scene.camera, field), rel=1e-9)
    assert from_info.baseline == pytest.approx(0.5327, abs=1e-3)


@pytest.mark.parametrize(
    ("index", "value", "field"),
    [(5, 700.0, "fy"), (2, 600.0, "cx"), (7, 50.0, "vertical"), (3, 379.8145, "baseline")],
)
def test_inconsistent_projections_name_the_field(index: int, value: float, field: str) -> None:
    p_right = list(KITTI_ODOMETRY_P1)
    p_right[index] = value
    with pytest.raises(CalibrationError, match=field):
        StereoCamera.from_projections(KITTI_ODOMETRY_P0, p_right, 1226, 370)


def test_uncalibrated_projection_is_rejected() -> None:
    with pytest.raises(CalibrationError, match="fx"):
        StereoCamera.from_projections([0.0] * 12, [0.0] * 12, 640, 480)


def test_backproject_then_project_returns_pixels_and_disparity() -> None:
    camera = _camera()
    rng = np.random.default_rng(0)
    disparity = rng.uniform(1.0, 120.0, size=(camera.height, camera.width))
    disparity[0, 0] = np.nan
    disparity[1, 1] = -3.0
    points = camera.backproject(disparity)
    assert np.isnan(points[0, 0]).all() and np.isnan(points[1, 1]).all()
    u, v, d = camera.project(points)
    valid = np.isfinite(disparity) & (disparity > 0)
    grid_v, grid_u = np.mgrid[0 : camera.height, 0 : camera.width]
    np.testing.assert_allclose(u[valid], grid_u[valid], atol=1e-8)
    np.testing.assert_allclose(v[valid], grid_v[valid], atol=1e-8)
    np.testing.assert_allclose(d[valid], disparity[valid], rtol=1e-10)
    np.testing.assert_allclose(camera.depth_to_disparity(camera.disparity_to_depth(disparity))[valid], disparity[valid])


def test_pose_inverse_and_transform() -> None:
    angle = 0.3
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    pose[:3, 3] = [1.0, -2.0, 3.0]
    np.testing.assert_allclose(invert_pose(pose) @ pose, np.eye(4), atol=1e-12)
    points = np.array([[0.0, 0.0, 1.0], [2.0, 1.0, 5.0]])
    # The round trip is exact only up to rounding (R^T R != I in floating point; BLAS kernels differ per CPU),
    # so the zeros come back as a few 1e-17: an absolute tolerance far below any real error, not rtol alone.
    np.testing.assert_allclose(
        transform_points(invert_pose(pose), transform_points(pose, points)), points, rtol=0, atol=1e-12
    )
