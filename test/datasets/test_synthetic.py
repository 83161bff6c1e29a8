"""Tests of the synthetic stereo scenes: exact geometry, photo-consistency, the KITTI layout, SGBM difficulty."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.datasets._raycast import Box, Cylinder, GroundPlane, Primitive, Sphere, cast
from selfcontra_ros.datasets.synthetic import (
    SCENES,
    SyntheticScene,
    kitti_like_camera,
    make_scene,
    render_frame,
    write_sequence,
)
from selfcontra_ros.errors import DatasetError
from selfcontra_ros.geometry import StereoCamera, invert_pose, transform_points

W, H = 320, 96


@pytest.fixture(scope="module", params=SCENES)
def small_scene(request: pytest.FixtureRequest) -> SyntheticScene:
    return make_scene(request.param, 7, W, H, frames=10)


def _sample(image: NDArray, u: NDArray, v: NDArray) -> NDArray[np.float64]:
    """Bilinear samples of ``image`` at float pixel coordinates (NaN outside)."""
    out = cv2.remap(
        image.astype(np.float32),
        u.astype(np.float32),
        v.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    return out.astype(np.float64)


def test_kitti_intrinsics_and_scaling() -> None:
    cam = kitti_like_camera()
    assert (cam.width, cam.height) == (1226, 370)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline) == (707.0912, 707.0912, 601.8873, 183.1104, 0.5372)
    small = kitti_like_camera(613, 185)
    # Half the size: half the focal length and principal point, the same baseline and field of view.
    assert small.fx == pytest.approx(cam.fx / 2) and small.cx == pytest.approx(cam.cx / 2)
    assert small.cy == pytest.approx(cam.cy / 2) and small.baseline == cam.baseline
    with pytest.raises(DatasetError, match="size"):
        kitti_like_camera(8, 8)


def test_unknown_scene_and_bad_frame_count(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="unknown synthetic scene 'forest'"):
        make_scene("forest", 1, W, H)
    with pytest.raises(DatasetError, match="frames"):
        write_sequence(tmp_path, scene="street", frames=0, seed=1, width=W, height=H)


@pytest.mark.parametrize("name", SCENES)
def test_deterministic_per_seed_and_different_between_seeds(name: str) -> None:
    a = make_scene(name, 3, W, H, frames=10).render(4)
    b = render_frame(make_scene(name, 3, W, H, frames=10), 4)
    c = make_scene(name, 4, W, H, frames=10).render(4)
    for field in ("left", "right", "depth", "disparity", "pose"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert np.mean(a.left != c.left) > 0.5
    assert not np.allclose(np.nan_to_num(a.depth, posinf=0), np.nan_to_num(c.depth, posinf=0))


def test_frame_contents(small_scene: SyntheticScene) -> None:
    f = small_scene.render(3)
    cam = small_scene.camera
    assert f.left.shape == f.right.shape == f.depth.shape == f.disparity.shape == (H, W)
    assert f.left.dtype == f.right.dtype == np.uint8
    assert f.disparity.dtype == np.float32 and f.pose.shape == (4, 4) and f.pose.dtype == np.float64
    assert f.stamp == pytest.approx(0.3) and f.camera == cam
    sky = ~np.isfinite(f.depth)
    np.testing.assert_array_equal(sky, np.isnan(f.disparity))
    np.testing.assert_allclose(f.disparity[~sky], cam.fx * cam.baseline / f.depth[~sky], rtol=1e-6)
    assert sky.mean() < 0.5
    if small_scene.name == "street":
        assert sky.any()  # straight down the street, the sky shows
    np.testing.assert_allclose(small_scene.render(0).pose, np.eye(4), atol=1e-12)


def _surface_distance(prim: Primitive, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed distance (metres) of points (N, 3) from the primitive's surface, written independently."""
    if isinstance(prim, GroundPlane):
        return p[:, 1] - prim.height
    if isinstance(prim, Box):
        c, s = np.cos(prim.yaw), np.sin(prim.yaw)
        rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        local = (p - np.asarray(prim.center)) @ rot
        return np.max(np.abs(local) - np.asarray(prim.half), axis=1)
    if isinstance(prim, Cylinder):
        radial = np.hypot(p[:, 0] - prim.x, p[:, 2] - prim.z) - prim.radius
        return np.maximum(radial, np.maximum(prim.y_top - p[:, 1], p[:, 1] - prim.y_bottom))
    assert isinstance(prim, Sphere)
    return np.linalg.norm(p - np.asarray(prim.center), axis=1) - prim.radius


@pytest.mark.parametrize("name", SCENES)
def test_depth_lies_on_the_hit_surfaces(name: str) -> None:
    """Back-projecting the ground-truth depth lands every pixel on the surface of the primitive it saw."""
    scene = make_scene(name, 5, W, H, frames=10)
    frame = scene.render(2)
    pose = scene.scene_pose(2)
    primitives = scene.primitives_at(2)
    _, hits = cast(primitives, scene.camera, pose)
    np.testing.assert_array_equal(hits.t, frame.depth)
    points = transform_points(pose, scene.camera.backproject(frame.disparity)).reshape(-1, 3)
    prim = hits.prim.ravel()
    seen = set(np.unique(prim[prim >= 0]).tolist())
    assert len(seen) >= 4
    for i in seen:
        sel = prim == i
        dist = _surface_distance(primitives[i], points[sel])
        assert np.max(np.abs(dist)) < 1e-6 * max(1.0, float(np.max(frame.depth.ravel()[sel]))), type(primitives[i])


def _photometric_error(
    image_a: NDArray[np.uint8],
    depth_a: NDArray[np.float64],
    image_b: NDArray[np.uint8],
    depth_b: NDArray[np.float64],
    cam: StereoCamera,
    t_b_a: NDArray[np.float64],
    mask: NDArray[np.bool_] | None = None,
) -> tuple[float, NDArray[np.bool_]]:
    """Median |I_a - I_b(warp)| over the pixels of A seen unoccluded in B, and those pixels.

    ``t_b_a`` maps points from camera A to camera B; a pixel is unoccluded when
    its warped depth agrees with B's own depth within 1 %. ``mask`` replaces
    that test (to compare a wrong pose on the same pixels).
    """
    disparity = cam.depth_to_disparity(depth_a)
    points_b = transform_points(t_b_a, cam.backproject(disparity))
    u, v, _ = cam.project(points_b)
    sampled = _sample(image_b, u, v)
    if mask is None:
        depth_seen = _sample(np.nan_to_num(depth_b, posinf=1e9), u, v)
        z = points_b[..., 2]
        mask = np.isfinite(sampled) & np.isfinite(z) & (np.abs(depth_seen - z) < 0.01 * z)
    err = np.abs(sampled - image_a)[mask & np.isfinite(sampled)]
    return float(np.median(err)), mask


def _textured(image: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """Pixels of a noise-free image with a grey-level gradient: where a wrong warp shows (the room is mostly plain)."""
    grey = image.astype(np.float32)
    gradient = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    return gradient > 8.0


def _yawed(pose: NDArray[np.float64], degrees: float) -> NDArray[np.float64]:
    """``pose`` with its rotation turned by ``degrees`` about the camera's y axis."""
    c, s = np.cos(np.deg2rad(degrees)), np.sin(np.deg2rad(degrees))
    out = pose.copy()
    out[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ pose[:3, :3]
    return out


def test_temporal_reprojection_reproduces_next_frame(small_scene: SyntheticScene) -> None:
    """Frame k's depth and the ground-truth poses warp frame k+1 onto frame k; a wrong pose does not."""
    cam = small_scene.camera
    a, b = small_scene.render(4), small_scene.render(5)
    t_b_a = invert_pose(b.pose) @ a.pose
    noisy, visible = _photometric_error(a.left, a.depth, b.left, b.depth, cam, t_b_a)
    if a.moving is not None:
        # Vehicles move: the camera's motion alone does not carry their pixels over (see test_vehicles_move).
        visible &= ~a.moving
    # The highway's sky is wide and its near road leaves the view within a frame (3 m).
    assert visible.mean() > (0.4 if small_scene.name != "highway" else 0.15)
    assert noisy < 3.0  # the noise of two images (sigma 1.5 each) plus interpolation
    # Without sensor noise only interpolation is left, and pose errors stand out.
    a, b = small_scene.render(4, noise=False), small_scene.render(5, noise=False)
    good, _ = _photometric_error(a.left, a.depth, b.left, b.depth, cam, t_b_a, visible)
    # 3 m per frame on the highway changes the near road's scale, and with it its band-limited texture.
    assert good < (0.6 if small_scene.name != "highway" else 1.5)
    visible &= _textured(a.left)
    assert visible.mean() > 0.02
    good, _ = _photometric_error(a.left, a.depth, b.left, b.depth, cam, t_b_a, visible)
    shifted = t_b_a.copy()
    # 30 cm sideways at about 1 m per frame; the highway's 3 m steps see mostly far surfaces: 1 m.
    shifted[:3, 3] += [0.3 * max(1.0, float(np.linalg.norm(t_b_a[:3, 3]))), 0.0, 0.0]
    # and its smooth, far textures (at this small size) need 2 degrees of yaw to stand out as clearly as 1 elsewhere.
    for wrong in (shifted, _yawed(t_b_a, 1.0 if small_scene.name != "highway" else 2.0)):
        bad, _ = _photometric_error(a.left, a.depth, b.left, b.depth, cam, wrong, visible)
        assert bad > 3.0 * good


def test_stereo_warp_reproduces_left_image(small_scene: SyntheticScene) -> None:
    """The right image warped with the ground-truth depth and baseline reproduces the left; a wrong baseline not."""
    cam = small_scene.camera
    right_pose = small_scene.scene_pose(6).copy()
    right_pose[:3, 3] += right_pose[:3, 0] * cam.baseline
    _, right_depth = small_scene.render_view(right_pose, None, index=6)
    t_right_left = np.eye(4)
    t_right_left[0, 3] = -cam.baseline
    f = small_scene.render(6)
    noisy, visible = _photometric_error(f.left, f.depth, f.right, right_depth, cam, t_right_left)
    assert visible.mean() > (0.7 if small_scene.name != "highway" else 0.45)  # the highway's sky is wide
    assert noisy < 3.0
    f = small_scene.render(6, noise=False)
    good, _ = _photometric_error(f.left, f.depth, f.right, right_depth, cam, t_right_left, visible)
    assert good < 0.6
    visible &= _textured(f.left)
    assert visible.mean() > 0.02
    good, _ = _photometric_error(f.left, f.depth, f.right, right_depth, cam, t_right_left, visible)
    wrong = t_right_left.copy()
    wrong[0, 3] *= 1.3
    bad, _ = _photometric_error(f.left, f.depth, f.right, right_depth, cam, wrong, visible)
    assert bad > 3.0 * good


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_highway_speed_and_traffic(seed: int) -> None:
    """2.5-3.5 m per frame, straight ahead, speeding up; vehicles move and some pass the camera."""
    scene = make_scene("highway", seed, W, H, frames=30)
    poses = np.stack([scene.scene_pose(k) for k in range(30)])
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert np.all((steps >= 2.5) & (steps <= 3.5)) and steps[-1] > steps[0]
    assert np.all(np.abs(poses[:, 0, 3]) < 0.6) and np.all(np.abs(poses[:, 1, 3]) < 1e-9)
    assert len(scene.moving_primitives) >= 3 * 7
    static = np.setdiff1d(np.arange(len(scene.primitives)), scene.moving_primitives)
    for a, b in zip(scene.primitives_at(0), scene.primitives_at(7), strict=True):
        if a is not b:
            assert isinstance(a, Box) and isinstance(b, Box) and a.center[:2] == b.center[:2]
    assert all(scene.primitives_at(7)[i] is scene.primitives[i] for i in static)
    moving = [scene.render(k, noise=False).moving for k in (0, 10, 20)]
    assert all(m is not None and m.any() for m in moving)


def test_highway_vehicles_move_with_their_texture() -> None:
    """A vehicle's pixels warp from frame k to k+1 by the camera motion and the vehicle's own translation."""
    scene = make_scene("highway", 2, 640, 192, frames=30)
    cam = scene.camera
    for k in range(0, 30, 3):
        a, b = scene.render(k, noise=False), scene.render(k + 1, noise=False)
        assert a.moving is not None
        seen = scene._render_view(scene.scene_pose(k), None, k)[2]
        counts = np.bincount(seen[a.moving], minlength=len(scene.primitives))
        if counts.max() > 400:
            break
    else:
        pytest.fail("no vehicle large enough in view")
    vehicle = int(np.argmax(counts))
    shift = scene._offsets(k + 1)[vehicle] - scene._offsets(k)[vehicle]
    assert np.linalg.norm(shift) > 1.0
    # Where the vehicle will be, seen from frame k: move the camera of frame k+1 back by the vehicle's shift.
    scene_a, scene_b = scene.scene_pose(k), scene.scene_pose(k + 1)
    moved_b = scene_b.copy()
    moved_b[:3, 3] -= shift
    t_b_a = invert_pose(moved_b) @ scene_a
    _, unoccluded = _photometric_error(a.left, a.depth, b.left, b.depth, cam, t_b_a)
    mask = unoccluded & (seen == vehicle)
    assert mask.sum() > 200
    good, _ = _photometric_error(a.left, a.depth, b.left, b.depth, cam, t_b_a, mask)
    static_only = invert_pose(scene_b) @ scene_a
    bad, _ = _photometric_error(a.left, a.depth, b.left, b.depth, cam, static_only, mask)
    assert good < 1.0 and bad > 5.0


def _read(path: Path) -> NDArray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image


def test_write_sequence_layout(tmp_path: Path) -> None:
    frames = 3
    seq = write_sequence(tmp_path, scene="street", frames=frames, seed=2, width=W, height=H)
    assert seq == tmp_path / "sequences" / "00"
    names = [f"{k:06d}.png" for k in range(frames)]
    for folder in ("image_0", "image_1", "disp_0"):
        assert sorted(p.name for p in (seq / folder).iterdir()) == names
    assert sorted(p.name for p in seq.iterdir()) == ["calib.txt", "disp_0", "image_0", "image_1", "times.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses", "sequences"]

    scene = make_scene("street", 2, W, H, frames=frames)
    rows = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, values = line.split(":")
        rows[key] = np.array(values.split(), dtype=np.float64).reshape(3, 4)
    assert sorted(rows) == ["P0", "P1", "P2", "P3"]
    camera = StereoCamera.from_projections(rows["P0"], rows["P1"], W, H)
    for attr in ("fx", "fy", "cx", "cy", "baseline", "width", "height"):
        assert getattr(camera, attr) == pytest.approx(getattr(scene.camera, attr), rel=1e-10), attr
    np.testing.assert_array_equal(rows["P2"], rows["P0"])
    np.testing.assert_array_equal(rows["P3"], rows["P1"])

    times = np.loadtxt(seq / "times.txt")
    np.testing.assert_allclose(times, np.arange(frames) / 10.0)
    poses = np.loadtxt(tmp_path / "poses" / "00.txt").reshape(frames, 3, 4)

    for k in range(frames):
        frame = scene.render(k)
        np.testing.assert_allclose(poses[k], frame.pose[:3], atol=1e-10)
        left, right = _read(seq / "image_0" / names[k]), _read(seq / "image_1" / names[k])
        assert left.dtype == np.uint8 and left.shape == (H, W)
        np.testing.assert_array_equal(left, frame.left)
        np.testing.assert_array_equal(right, frame.right)
        disp16 = _read(seq / "disp_0" / names[k])
        assert disp16.dtype == np.uint16 and disp16.shape == (H, W)
        has = disp16 > 0
        np.testing.assert_array_equal(has, np.isfinite(frame.depth))
        d = disp16[has] / 256.0
        assert np.max(np.abs(d - frame.disparity[has])) <= 0.5 / 256 + 1e-6
        # Depth from the stored disparity matches the rendered depth within the quantisation of 1/256 px.
        z_png = scene.camera.disparity_to_depth(d)
        z = frame.depth[has]
        tolerance = z * z / scene.camera.focal_baseline * (0.5 / 256) * 1.01 + 1e-9
        assert np.all(np.abs(z_png - z) <= tolerance)


@pytest.mark.skipif(
    importlib.util.find_spec("selfcontra_ros.datasets.kitti") is None, reason="selfcontra_ros.datasets.kitti absent"
)
def test_kitti_reader_reads_back_what_was_written(tmp_path: Path) -> None:
    from selfcontra_ros.datasets.kitti import open_sequence

    frames = 2
    write_sequence(tmp_path, scene="orbit", frames=frames, seed=3, width=W, height=H)
    scene = make_scene("orbit", 3, W, H, frames=frames)
    seq = open_sequence(tmp_path)
    assert len(seq) == frames
    for attr in ("fx", "fy", "cx", "cy", "baseline", "width", "height"):
        assert getattr(seq.camera, attr) == pytest.approx(getattr(scene.camera, attr), rel=1e-10), attr
    np.testing.assert_allclose(seq.stamps, np.arange(frames) / 10.0)
    for k, read in enumerate(seq):
        frame = scene.render(k)
        assert read.index == k
        np.testing.assert_array_equal(read.left, frame.left)
        np.testing.assert_array_equal(read.right, frame.right)
        assert read.pose is not None and read.gt_disparity is not None
        np.testing.assert_allclose(read.pose, frame.pose, atol=1e-10)
        np.testing.assert_array_equal(np.isnan(read.gt_disparity), np.isnan(frame.disparity))
        has = np.isfinite(frame.disparity)
        np.testing.assert_allclose(read.gt_disparity[has], frame.disparity[has], atol=0.5 / 256 + 1e-6)


def test_street_is_as_hard_for_sgbm_as_kitti() -> None:
    """Raw SGBM (128 disparities, 5x5) is > 3 px wrong on 5-15 % of the ground-truth pixels, as on KITTI."""
    scene = make_scene("street", 1, frames=30)
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=128,
        blockSize=5,
        P1=8 * 5 * 5,
        P2=32 * 5 * 5,
        disp12MaxDiff=-1,
        uniquenessRatio=0,
        speckleWindowSize=0,
    )
    bad = has_gt = 0
    beyond_range = False
    for k in (0, 12, 24):
        f = scene.render(k)
        d = sgbm.compute(f.left, f.right).astype(np.float32) / 16.0
        has = np.isfinite(f.disparity)
        bad += int(np.sum(has & (d >= 0) & (np.abs(d - f.disparity) > 3.0)))
        has_gt += int(has.sum())
        beyond_range |= bool(np.nanmax(f.disparity) > 128)
    assert 0.05 <= bad / has_gt <= 0.15
    assert beyond_range  # some near objects lie beyond SGBM's disparity range
