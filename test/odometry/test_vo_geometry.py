"""The odometry's geometry against numeric ground truth: refinement, its uncertainty, moving points, re-anchoring."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.datasets.synthetic import kitti_like_camera, write_sequence
from selfcontra_ros.geometry import StereoCamera, invert_pose
from selfcontra_ros.odometry.stereo_vo import (
    FrameQuality,
    IsolationGate,
    StereoOdometry,
    VOParams,
    _agreed_road_lengths,
    _Features,
    _hamming,
    _pose_from_vector,
    _rotation_deg,
    _row_candidates,
    _rts_constant_velocity,
    _vector_from_pose,
    _WindowProblem,
    mark_isolated,
    mark_uncertain,
    smooth_step_lengths,
    step_length_spread,
)

CAMERA = kitti_like_camera(640, 192)
CAMERA_FB_REFERENCE = VOParams().reference_focal_baseline


def _motion(forward: float = 1.5, yaw_deg: float = 0.5) -> NDArray[np.float64]:
    """T_ref_cur: the camera moves ``forward`` metres along z and turns ``yaw_deg`` about y."""
    return _pose_from_vector(np.array([0.0, np.deg2rad(yaw_deg), 0.0, 0.05, 0.0, forward]))


def _points(rng: np.random.Generator, n: int, near: float, far: float) -> NDArray[np.float64]:
    """Points (n, 3) in the reference camera that both cameras of both frames see."""
    z = rng.uniform(near, far, n)
    u = rng.uniform(60, CAMERA.width - 60, n)
    v = rng.uniform(30, CAMERA.height - 30, n)
    return np.column_stack([(u - CAMERA.cx) * z / CAMERA.fx, (v - CAMERA.cy) * z / CAMERA.fy, z])


def _features(points: NDArray[np.float64], rng: np.random.Generator, sigma: float) -> _Features:
    """Measured stereo features of points (N, 3) in a camera: left position and disparity with noise ``sigma`` px."""
    cam: StereoCamera = CAMERA
    uv = np.column_stack([cam.fx * points[:, 0] / points[:, 2] + cam.cx, cam.fy * points[:, 1] / points[:, 2] + cam.cy])
    disparity = cam.focal_baseline / points[:, 2]
    uv = uv + rng.normal(0.0, sigma, uv.shape)
    disparity = disparity + rng.normal(0.0, sigma, disparity.shape)
    z = cam.focal_baseline / disparity
    measured = np.column_stack([(uv[:, 0] - cam.cx) * z / cam.fx, (uv[:, 1] - cam.cy) * z / cam.fy, z])
    return _Features(uv, disparity, np.zeros((len(uv), 32), np.uint8), measured)


def _pair(
    rng: np.random.Generator, motion: NDArray[np.float64], sigma: float, n: int = 150, far: float = 60.0
) -> tuple[_Features, _Features]:
    ref_points = _points(rng, n, 4.0, far)
    cur_points = ref_points @ invert_pose(motion)[:3, :3].T + invert_pose(motion)[:3, 3]
    return _features(ref_points, rng, sigma), _features(cur_points, rng, sigma)


def test_refinement_recovers_the_motion_and_its_uncertainty_is_calibrated() -> None:
    """The step length's spread over noise draws matches the reported standard deviation (within a factor 1.6)."""
    vo = StereoOdometry(CAMERA)
    motion = _motion()
    rng = np.random.default_rng(3)
    lengths, stds = [], []
    for _ in range(25):
        ref, cur = _pair(rng, motion, sigma=0.2)
        index = np.arange(len(ref.uv))
        start = invert_pose(motion) @ _pose_from_vector(np.array([0.01, -0.01, 0.0, 0.05, -0.03, 0.1]))
        t_cur_ref, std_pct, bias_pct, _ = vo._refine_two_way(start, ref, cur, index, index, cur.uv)
        step = invert_pose(t_cur_ref)
        lengths.append(np.linalg.norm(step[:3, 3]))
        stds.append(std_pct)
        assert np.linalg.norm(step[:3, 3] - motion[:3, 3]) < 0.05
        assert bias_pct > 0
    spread_pct = 100.0 * np.std(lengths) / np.linalg.norm(motion[:3, 3])
    assert abs(np.mean(lengths) / np.linalg.norm(motion[:3, 3]) - 1.0) < 0.01
    assert np.median(stds) / 1.6 < spread_pct < 1.6 * np.median(stds)


@pytest.mark.parametrize("far", [20.0, 120.0])
def test_bias_sensitivity_predicts_the_effect_of_a_disparity_bias(far: float) -> None:
    """The reported change of the step for a disparity bias is what re-solving with biased disparities gives."""
    params = VOParams(disparity_bias_px=0.1)
    vo = StereoOdometry(CAMERA, params)
    motion = _motion(forward=2.5)
    rng = np.random.default_rng(4)
    ref, cur = _pair(rng, motion, sigma=0.0, far=far)
    index = np.arange(len(ref.uv))
    t_cur_ref, _, bias_pct, _ = vo._refine_two_way(invert_pose(motion), ref, cur, index, index, cur.uv)
    length = np.linalg.norm(invert_pose(t_cur_ref)[:3, 3])

    def biased(f: _Features) -> _Features:
        d = f.disparity - 0.1
        z = CAMERA.focal_baseline / d
        points = np.column_stack(
            [(f.uv[:, 0] - CAMERA.cx) * z / CAMERA.fx, (f.uv[:, 1] - CAMERA.cy) * z / CAMERA.fy, z]
        )
        return _Features(f.uv, d, f.descriptors, points)

    t_biased, _, _, _ = vo._refine_two_way(invert_pose(motion), biased(ref), biased(cur), index, index, cur.uv)
    actual_pct = 100.0 * abs(np.linalg.norm(invert_pose(t_biased)[:3, 3]) - length) / length
    assert bias_pct == pytest.approx(actual_pct, rel=0.25)
    # Points out to 120 m rest the scale on small disparities: a larger sensitivity than out to 20 m.
    if far > 100:
        near_ref, near_cur = _pair(np.random.default_rng(4), motion, sigma=0.0, far=20.0)
        _, _, near_bias, _ = vo._refine_two_way(invert_pose(motion), near_ref, near_cur, index, index, near_cur.uv)
        assert bias_pct > 1.5 * near_bias


def test_region_influence_is_the_step_change_without_that_region() -> None:
    """Leaving one image region out: the linearised change of the step matches a re-solve without it.

    A vehicle ahead that moves at 60 % of the camera's speed, all in one
    region of the influence grid, pulls the two-way refinement's step (it is
    not rejected here, as no RANSAC runs); its region's influence is large,
    and without it every region's is small.
    """
    params = VOParams(influence_grid=(3, 8))
    vo = StereoOdometry(CAMERA, params)
    motion = _motion(forward=2.5)
    rng = np.random.default_rng(7)
    ref, cur = _pair(rng, motion, sigma=0.05, n=200)
    # The vehicle: 25 points 8-10 m ahead, in one grid cell (u 280-320, v 70-110 px of 640x192).
    z = rng.uniform(8.0, 10.0, 25)
    u, v = rng.uniform(285, 315, 25), rng.uniform(72, 108, 25)
    vehicle = np.column_stack([(u - CAMERA.cx) * z / CAMERA.fx, (v - CAMERA.cy) * z / CAMERA.fy, z])
    own = motion.copy()
    own[:3, 3] *= 0.6  # the vehicle drove 60 % of the camera's step: seen from the camera it came only 40 % nearer
    relative = invert_pose(motion) @ own
    vehicle_cur = vehicle @ relative[:3, :3].T + relative[:3, 3]
    vr, vc = _features(vehicle, rng, 0.05), _features(vehicle_cur, rng, 0.05)

    def joined(a: _Features, b: _Features) -> _Features:
        return _Features(np.vstack([a.uv, b.uv]), np.concatenate([a.disparity, b.disparity]),
                         np.vstack([a.descriptors, b.descriptors]), np.vstack([a.points, b.points]))  # fmt: skip

    both_ref, both_cur = joined(ref, vr), joined(cur, vc)
    index = np.arange(len(both_ref.uv))
    fitted, _, _, influence = vo._refine_two_way(invert_pose(motion), both_ref, both_cur, index, index, both_cur.uv)
    static = np.arange(len(ref.uv))
    cell = (np.clip((both_cur.uv[:, 1] * 3 / CAMERA.height).astype(int), 0, 2) * 8
            + np.clip((both_cur.uv[:, 0] * 8 / CAMERA.width).astype(int), 0, 7))  # fmt: skip
    others = index[cell != cell[-1]]
    without, _, _, _ = vo._refine_two_way(fitted, both_ref, both_cur, others, others, both_cur.uv[others])
    length = np.linalg.norm(invert_pose(fitted)[:3, 3])
    resolved_pct = 100.0 * abs(np.linalg.norm(invert_pose(without)[:3, 3]) - length) / length
    assert resolved_pct > 1.0  # the vehicle's region did pull the step, against the Huber loss
    assert influence == pytest.approx(resolved_pct, rel=0.1)
    _, _, _, clean = vo._refine_two_way(invert_pose(motion), ref, cur, static, static, cur.uv)
    assert clean < 0.25 * influence
    off = StereoOdometry(CAMERA, VOParams(influence_grid=(1, 1)))
    assert off._refine_two_way(invert_pose(motion), ref, cur, static, static, cur.uv)[3] == 0.0


def test_depth_weights_follow_the_propagated_depth_noise() -> None:
    """On the optical axis, after a step t towards a point at z: left weights 1, right ``1 / sqrt(1 + (z/(z-t))^4)``."""
    vo = StereoOdometry(CAMERA)
    z = np.array([5.0, 20.0, 80.0])
    on_axis = np.column_stack([np.zeros(3), np.zeros(3), z])
    step = 3.0
    weights = vo._depth_weights(on_axis, invert_pose(_pose_from_vector(np.array([0, 0, 0, 0, 0, step]))))
    np.testing.assert_allclose(weights[:, :2], 1.0, atol=1e-6)
    np.testing.assert_allclose(weights[:, 2], 1.0 / np.sqrt(1.0 + (z / (z - step)) ** 4), rtol=1e-3)
    # Off the axis the left u weight falls with the step (the point's depth error moves its pixel).
    off_axis = np.array([[4.0, 0.5, 20.0]])
    small = vo._depth_weights(off_axis, invert_pose(_motion(forward=0.5)))
    large = vo._depth_weights(off_axis, invert_pose(_motion(forward=3.0)))
    assert 0 < large[0, 0] < small[0, 0] <= 1


def test_vehicle_points_are_kept_out_of_ransac_and_the_largest_implausible_group_is_skipped() -> None:
    """A truck beside the camera, moving almost with it, has more matches than the static scene."""
    vo = StereoOdometry(CAMERA)
    rng = np.random.default_rng(5)
    motion = _motion(forward=2.8, yaw_deg=0.0)
    static_ref, static_cur = _pair(rng, motion, sigma=0.1, n=40)
    truck_motion = _motion(forward=0.4, yaw_deg=0.0)  # the camera relative to the truck
    truck_points = np.column_stack([rng.uniform(2.5, 4.0, 70), rng.uniform(-1.5, 0.8, 70), rng.uniform(5.0, 12.0, 70)])
    truck_cur = truck_points @ invert_pose(truck_motion)[:3, :3].T + invert_pose(truck_motion)[:3, 3]
    truck_ref_f, truck_cur_f = _features(truck_points, rng, 0.1), _features(truck_cur, rng, 0.1)

    def cat(a: _Features, b: _Features) -> _Features:
        return _Features(
            np.vstack([a.uv, b.uv]), np.concatenate([a.disparity, b.disparity]),
            np.vstack([a.descriptors, b.descriptors]), np.vstack([a.points, b.points]),
        )  # fmt: skip

    ref, cur = cat(static_ref, truck_ref_f), cat(static_cur, truck_cur_f)
    index = np.arange(len(ref.uv))
    is_truck = index >= 40
    # The prediction (the camera's last step) tells them apart in 3D before any RANSAC.
    still = vo._static_under_prediction(ref, cur, index, index, motion)
    assert still[~is_truck].mean() > 0.95 and not still[is_truck].any()
    # Without it, RANSAC's largest group is the truck, which moves unlike the prediction allows.
    t_cur_ref, inliers = vo._pnp_ransac(ref.points, cur.uv, motion, True, index)
    assert is_truck[inliers].mean() > 0.9 and not vo._plausible(t_cur_ref, motion)
    t_cur_ref, inliers = vo._pnp_ransac(ref.points, cur.uv, motion, True, np.setdiff1d(index, inliers))
    assert not is_truck[inliers].any() and vo._plausible(t_cur_ref, motion)
    assert np.linalg.norm(invert_pose(t_cur_ref)[:3, 3] - motion[:3, 3]) < 0.1


def test_scale_check_flags_a_step_it_cannot_trust() -> None:
    params = VOParams(
        max_step_error_pct=2.0, scale_sigmas=3.0, bias_share=0.5, adjustment_share=0.5, influence_share=0.5
    )
    vo = StereoOdometry(kitti_like_camera(), params)  # KITTI's fx b: the limits as given
    good = FrameQuality(index=3, stamp=0.0, status="ok", reliable=True, features=500, stereo_matches=300,
                        scale_std_pct=0.3, scale_bias_pct=0.5, adjustment_change_pct=0.2,
                        scale_influence_pct=0.5)  # fmt: skip
    assert vo._check_scale(good) == good
    for field, value, words in (
        ("scale_std_pct", 0.7, "3-sigma"),
        ("scale_bias_pct", 1.2, "disparity bias"),
        ("adjustment_change_pct", 1.5, "window adjustment"),
        ("scale_influence_pct", 1.5, "one image region"),
    ):
        flagged = vo._check_scale(FrameQuality(**{**good.__dict__, field: value}))
        assert flagged.status == "weak_scale" and not flagged.reliable and words in flagged.message
    # A camera with half KITTI's fx b measures depth half as finely: twice the limits.
    coarse = StereoOdometry(kitti_like_camera(613, 185), params)
    assert coarse._check_scale(FrameQuality(**{**good.__dict__, "scale_std_pct": 1.2})).reliable
    assert not coarse._check_scale(FrameQuality(**{**good.__dict__, "scale_std_pct": 1.4})).reliable
    off = StereoOdometry(CAMERA, VOParams(check_scale=False))
    assert off._check_scale(FrameQuality(**{**good.__dict__, "scale_bias_pct": 9.0})).reliable


def test_reanchoring_after_two_failed_frames(tmp_path: Path) -> None:
    """Frames that jump ahead fail; the second becomes the reference, and the next step is measured from it."""
    write_sequence(tmp_path, scene="street", frames=10, seed=1, width=640, height=192)
    seq = open_sequence(tmp_path)
    truth = seq.poses
    assert truth is not None
    vo = StereoOdometry(seq.camera)
    order = [0, 1, 2, 7, 8, 9]
    for k in order:
        vo.add(seq[k].left, seq[k].right)
    statuses = [q.status for q in vo.qualities]
    assert statuses[:3] == ["first", "ok", "ok"]
    assert not vo.qualities[3].reliable and not vo.qualities[4].reliable
    assert vo.qualities[4].reference == 2
    assert vo.qualities[5].reliable and vo.qualities[5].reference == 4
    step = invert_pose(vo.poses[4]) @ vo.poses[5]
    true_step = invert_pose(truth[8]) @ truth[9]
    assert np.linalg.norm(step[:3, 3] - true_step[:3, 3]) < 0.03


@pytest.mark.parametrize("angle", [0.3, 1e-6, 0.0])
def test_window_jacobian_matches_a_numeric_derivative(angle: float) -> None:
    """The windowed adjustment's analytic Jacobian against central differences (rotations large and near zero)."""
    rng = np.random.default_rng(3)
    n_free, n_points = 3, 40
    fixed = _pose_from_vector(np.array([0.02, -0.01, 0.03, 0.1, -0.2, 0.3]))
    cams = np.column_stack([rng.normal(0.0, 1.0, (n_free, 3)), rng.normal(0.0, 0.5, (n_free, 3))])
    cams[:, :3] *= angle / np.maximum(np.linalg.norm(cams[:, :3], axis=1, keepdims=True), 1e-12)
    points = _points(rng, n_points, 4.0, 40.0)
    fi = np.repeat(np.arange(n_free + 1), n_points)
    pi = np.tile(np.arange(n_points), n_free + 1)
    keep = rng.random(fi.size) < 0.8  # not every point in every frame
    fi, pi = fi[keep], pi[keep]
    uv = rng.uniform(0, 600, (fi.size, 2))
    problem = _WindowProblem(CAMERA, fixed, n_free, n_points, fi, pi, uv, uv[:, 0] - 10.0)
    problem.weight = np.where(rng.random(fi.size) < 0.1, 0.0, 1.0)
    x = np.concatenate([cams.ravel(), points.ravel()])
    analytic = problem.jacobian(x).toarray()
    step = 1e-6 * np.maximum(1.0, np.abs(x))
    numeric = np.empty_like(analytic)
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = step[k]
        numeric[:, k] = (problem.residuals(x + dx) - problem.residuals(x - dx)) / (2.0 * step[k])
    scale = np.abs(numeric).max()
    assert np.abs(analytic - numeric).max() <= 1e-5 * scale
    # The structure holds only the frame's and the point's columns: nothing of the fixed frame.
    assert analytic.shape == (3 * fi.size, x.size)
    assert not analytic[3 * np.flatnonzero(fi == 0)][:, : 6 * n_free].any()


def test_row_candidates_and_hamming_agree_with_brute_force() -> None:
    """The row-bucketed candidate pairs are exactly the brute-force pairs within reach; Hamming counts bits."""
    rng = np.random.default_rng(5)
    query = np.round(rng.uniform(0, 50, 300), 1)
    train = np.round(rng.uniform(0, 50, 400), 1)  # rounded: many pairs exactly at the reach
    reach = rng.choice([0.0, 1.0, 2.4], 300)
    qi, ti = _row_candidates(query, train, reach)
    exact = np.abs(train[ti] - query[qi]) <= reach[qi]
    found = set(zip(qi[exact].tolist(), ti[exact].tolist(), strict=True))
    brute = np.argwhere(np.abs(query[:, None] - train[None, :]) <= reach[:, None])
    assert found == {(int(q), int(t)) for q, t in brute}
    assert np.all(np.diff(qi) >= 0)
    a = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    assert np.array_equal(_hamming(a, b), np.unpackbits(a ^ b, axis=1).sum(axis=1))


@pytest.mark.parametrize(
    ("speed_up", "status", "references"),
    [
        # Speeding up 0.1 m per frame: two weak frames between reliable ones, each measured from the one before.
        (0.1, ["first", "ok", "ok", "weak_scale", "weak_scale", "ok"], [-1, 0, 1, 2, 3, 4]),
        # At constant speed: a weak frame, then a frame without a pose, then one measured across it.
        (0.0, ["first", "ok", "ok", "weak_scale", "weak_scale", "implausible", "ok"], [-1, 0, 1, 2, 3, 4, 4]),
    ],
)
def test_unreliable_steps_take_the_velocity_of_the_reliable_ones_around_them(
    speed_up: float, status: list[str], references: list[int]
) -> None:
    """A weak frame takes the last reliable step's translation; a reliable frame then interpolates the run."""
    vo = StereoOdometry(CAMERA)
    rng = np.random.default_rng(2)
    truth = [np.eye(4)]
    for k in range(1, len(status)):
        step = _pose_from_vector(np.array([0.0, np.deg2rad(0.5), 0.0, 0.02, 0.0, 2.0 + speed_up * k]))
        truth.append(truth[-1] @ step)
    for k, (name, reference) in enumerate(zip(status, references, strict=True)):
        reliable = name in ("first", "ok")
        if k == 0:
            pose = np.eye(4)
        elif name == "implausible":
            pose = vo.poses[-1] @ _pose_from_vector(np.array([0.0, 0.0, 0.0, 0.3, 0.0, 1.0]))  # a poor guess
        else:
            step = invert_pose(truth[reference]) @ truth[k]
            if not reliable:
                step[:3, 3] *= 1.0 + rng.uniform(-0.15, 0.15)  # a weak step: its length up to 15 % off
                step[:3, 3] += rng.normal(0.0, 0.1, 3)
            pose = vo.poses[reference] @ step
        quality = FrameQuality(index=k, stamp=0.0, status=name, reliable=reliable, features=500,
                               stereo_matches=300, reference=reference)  # fmt: skip
        vo._record(pose, quality)
        if k and name != "implausible":
            vo._step_prior(k, reliable)
        if k == 3:  # the first weak frame: the last reliable step's translation
            weak = invert_pose(vo.poses[2]) @ vo.poses[3]
            assert np.allclose(weak[:3, 3], (invert_pose(truth[1]) @ truth[2])[:3, 3])
    for k in range(len(status)):
        assert np.allclose(vo.poses[k], truth[k], atol=1e-9), k


def _straight_run(lengths: NDArray[np.float64], yaw_deg: float = 0.3) -> NDArray[np.float64]:
    """Poses (N+1, 4, 4) of steps of the given lengths, each along a slightly turning direction."""
    poses = [np.eye(4)]
    for k, length in enumerate(lengths):
        direction = np.array([0.05 * np.sin(k), 0.01, 1.0])
        translation = length * direction / np.linalg.norm(direction)
        step = _pose_from_vector(np.concatenate([[0.0, np.deg2rad(yaw_deg), 0.0], translation]))
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _qualities(lengths: NDArray[np.float64], std_pct: float, reliable: NDArray[np.bool_]) -> list[FrameQuality]:
    first = FrameQuality(index=0, stamp=0.0, status="first", reliable=True, features=500, stereo_matches=300)
    common = {"stamp": 0.0, "features": 500, "stereo_matches": 300, "scale_std_pct": std_pct}
    steps = [
        FrameQuality(
            index=k + 1,
            status="ok" if ok else "weak_scale",
            reliable=bool(ok),
            reference=k,
            translation_m=float(length),
            **common,
        )
        for k, (length, ok) in enumerate(zip(lengths, reliable, strict=True))
    ]
    return [first, *steps]


def test_rts_smoother_keeps_a_ramp_and_predicts_the_gaps() -> None:
    ramp = 2.5 + 0.03 * np.arange(30)
    measured = np.ones(30, dtype=bool)
    measured[[0, 7, 8, 9, 29]] = False
    smoothed, _ = _rts_constant_velocity(ramp, measured, np.full(30, 0.01), 0.02)
    np.testing.assert_allclose(smoothed, ramp, rtol=1e-3)
    # Measurements within the gate are used as they are: the gated smoother is the plain one.
    gated, _ = _rts_constant_velocity(ramp, measured, np.full(30, 0.01), 0.02, gate=3.0)
    np.testing.assert_allclose(gated, smoothed, rtol=1e-12)
    # One measurement at a fifth of the truth: gated, it is left out; not subject to the gate, it pulls.
    outlier = ramp.copy()
    outlier[15] *= 0.2
    left_out, _ = _rts_constant_velocity(outlier, measured, np.full(30, 0.01), 0.02, gate=3.0)
    np.testing.assert_allclose(left_out, ramp, rtol=1e-3)
    exempt = np.zeros(30, dtype=bool)
    used, _ = _rts_constant_velocity(outlier, measured, np.full(30, 0.01), 0.02, gate=3.0, gated=exempt)
    assert used[15] < 0.8 * ramp[15]


def test_the_smoothers_spread_is_the_spread_of_its_errors() -> None:
    """The standard deviation the smoother reports is that of its error over 2000 drives drawn from its own
    model (the step length's change random-walking by 0.02 m per frame, each measurement with its stated
    noise, some missing, noisier ones in a stretch): within 8 % at every frame (measured: 3-4 %, three seeds)."""
    rng = np.random.default_rng(5)
    n, draws, acceleration = 30, 2000, 0.02
    noise = np.full(n, 0.03)
    noise[12:18] = 0.25
    measured = np.ones(n, dtype=bool)
    measured[[6, 7, 20]] = False
    errors = np.zeros((draws, n))
    for i in range(draws):
        w = rng.normal(0.0, acceleration, n)
        truth, v = np.zeros(n), 0.0
        truth[0] = 3.0
        for k in range(1, n):  # x' = x + v + w / 2, v' = v + w: the smoother's process model
            truth[k] = truth[k - 1] + v + 0.5 * w[k]
            v += w[k]
        value = truth + rng.normal(0.0, 1.0, n) * noise
        smoothed, std = _rts_constant_velocity(value, measured, noise, acceleration)
        errors[i] = smoothed - truth
    np.testing.assert_allclose(errors.std(axis=0), std, rtol=0.08)
    # Least sure where nothing was measured well near it, and at the ends (one side only).
    assert std[15] > 2.0 * std[4] and std[0] > 1.2 * std[4] and std[-1] > 1.2 * std[24]


def test_an_ok_step_the_sequence_pins_down_loosely_is_reported_uncertain() -> None:
    """Steps of 3 m measured to 0.3 %, frames 12-17 ``weak_scale`` (noise 8 times larger): the spread is
    smallest among well measured frames, larger at the ends and next to the weak stretch, largest inside it;
    ``mark_uncertain`` reports ``uncertain`` exactly the ``ok`` frames above the limit (0: off), the limit
    scaled by the camera's depth precision, frames measured across a gap left alone."""
    lengths = np.full(29, 3.0)
    reliable = np.ones(29, dtype=bool)
    reliable[11:17] = False  # frames 12-17
    qualities = _qualities(lengths, std_pct=0.3, reliable=reliable)
    spread = step_length_spread(qualities, VOParams())
    assert np.isnan(spread[0]) and np.all(np.isfinite(spread[1:]))
    middle = spread[5]
    assert spread[1] > middle and spread[29] > middle and spread[11] > middle and spread[14] > spread[11]
    limit = float(np.median(spread[1:]))
    marked = mark_uncertain(qualities, spread, VOParams(max_length_spread_pct=limit))
    expected = [q.status == "ok" and s > limit for q, s in zip(qualities, spread, strict=True)]
    assert [q.status == "uncertain" for q in marked] == expected and any(expected)
    assert all(not q.reliable for q in marked if q.status == "uncertain")
    assert [q.status for q in marked if q.status != "uncertain"] == [
        q.status for q, e in zip(qualities, expected, strict=True) if not e
    ]
    assert mark_uncertain(qualities, spread, VOParams(max_length_spread_pct=0)) == qualities
    assert np.all(np.isnan(step_length_spread(qualities, VOParams(smooth_lengths=False))))
    # A camera with half KITTI's fx * b measures depth twice as coarsely: the limit doubles, as the scale check's.
    coarse = mark_uncertain(qualities, spread, VOParams(max_length_spread_pct=limit / 2), CAMERA_FB_REFERENCE / 2)
    assert [q.status for q in coarse] == [q.status for q in marked]
    # A frame measured across a gap (its reference two frames back) has no step of its own to judge.
    across = replace(qualities[29], reference=27)
    assert mark_uncertain([*qualities[:29], across], spread, VOParams(max_length_spread_pct=limit))[29] == across


def test_a_run_of_steps_measured_on_a_vehicle_does_not_pull_its_neighbours() -> None:
    """Five ``weak_scale`` steps measured on a truck moving with the camera (15 % of the true length; highway
    seed 78 had 13-68 %), inside a run of weak frames: without the gate they pull the smoothed steps around
    them 5 % short; with ``length_gate_sigmas`` 3 they are left out and every step, theirs included,
    stays within 1.5 % (measured: 0.8 %)."""
    rng = np.random.default_rng(78)
    true_lengths = 2.8 + 0.03 * np.arange(30)
    measured = true_lengths * (1.0 + rng.normal(0.0, 0.01, 30))
    measured[10:15] = 0.15 * true_lengths[10:15]
    reliable = np.ones(30, dtype=bool)
    reliable[10:26] = False
    poses = _straight_run(measured)
    qualities = _qualities(measured, std_pct=0.4, reliable=reliable)
    for k in range(11, 16):
        qualities[k] = replace(qualities[k], scale_std_pct=5.0)
    worst = {}
    for gate in (0.0, 3.0):
        smoothed = smooth_step_lengths(poses, qualities, VOParams(length_gate_sigmas=gate))
        lengths = np.linalg.norm((np.linalg.inv(smoothed[:-1]) @ smoothed[1:])[:, :3, 3], axis=1)
        error = np.abs(lengths / true_lengths - 1.0)
        worst[gate] = float(np.delete(error, range(10, 15)).max()) if gate == 0 else float(error.max())
    assert worst[0.0] > 0.04 and worst[3.0] < 0.015, worst


def test_road_lengths_pin_a_run_of_short_weak_steps_and_a_lone_wrong_one_is_left_out() -> None:
    """A highway's failure: sixteen ``weak_scale`` steps measured 4 % short together (far corners read
    too near), with the road's lengths within 0.3 %. Smoothed with the road, every step is within 1 % of
    the truth (measured: 0.3 %); without it (``road_steps`` off) they stay up to 3 % short. A road length
    12 % off with no neighbour agreeing is not used; two that agree with each other are."""
    rng = np.random.default_rng(3)
    true_lengths = 2.8 + 0.03 * np.arange(30)
    measured = true_lengths * (1.0 + rng.normal(0.0, 0.005, 30))
    measured[8:24] *= 0.96
    reliable = np.ones(30, dtype=bool)
    reliable[8:24] = False
    poses = _straight_run(measured)
    road = true_lengths * (1.0 + rng.normal(0.0, 0.003, 30))
    road[20] *= 0.88
    qualities = _qualities(measured, std_pct=0.4, reliable=reliable)
    qualities = [qualities[0]] + [replace(q, road_length_m=float(r)) for q, r in zip(qualities[1:], road, strict=True)]

    def errors(params: VOParams) -> NDArray[np.float64]:
        smoothed = smooth_step_lengths(poses, qualities, params)
        return np.linalg.norm((np.linalg.inv(smoothed[:-1]) @ smoothed[1:])[:, :3, 3], axis=1) / true_lengths - 1.0

    with_road, without = errors(VOParams()), errors(VOParams(road_steps=False))
    assert np.abs(with_road).max() < 0.01, np.abs(with_road).max()
    assert without.min() < -0.025
    # The agreement rule: the lone wrong length goes, its neighbours stay; road_steps off drops them all.
    agreed = _agreed_road_lengths(qualities[1:], VOParams())
    assert np.isnan(agreed[20]) and np.isfinite(agreed[[19, 21]]).all() and np.isfinite(agreed).sum() == 29
    assert np.isnan(_agreed_road_lengths(qualities[1:], VOParams(road_steps=False))).all()
    pair = [replace(q, road_length_m=q.road_length_m * (0.88 if k == 21 else 1.0)) for k, q in enumerate(qualities[1:])]
    assert np.isfinite(_agreed_road_lengths(pair, VOParams())[[20, 21]]).all()


def test_steps_the_road_measured_take_its_rotation_and_direction() -> None:
    """Where the road's length of a step is used, the smoothed step is the road's motion
    (``road_motion``): its rotation exactly, its direction exactly, its length smoothed, also for a frame
    whose features were measured across a gap (the road's step is always from the frame before). A road
    step no neighbour agrees with and a ``static`` frame keep their own; ``road_motion`` off keeps every
    step's rotation and direction."""
    rng = np.random.default_rng(5)
    true_lengths = 2.8 + 0.03 * np.arange(20)
    truth = _straight_run(true_lengths, yaw_deg=0.3)
    # The features' steps: each rotation 0.05 deg off about a random axis, each direction about 0.5 deg off
    # (a translation error across the step, which runs along z).
    measured = [np.eye(4)]
    for k in range(20):
        step = invert_pose(truth[k]) @ truth[k + 1]
        axis, across = rng.normal(size=3), np.cross(rng.normal(size=3), [0.0, 0.0, 1.0])
        turn = np.deg2rad(0.05) * axis / np.linalg.norm(axis)
        error = _pose_from_vector(np.concatenate([turn, 0.0087 * true_lengths[k] * across / np.linalg.norm(across)]))
        measured.append(measured[-1] @ step @ error)
    poses = np.stack(measured)
    qualities = _qualities(true_lengths, std_pct=0.4, reliable=np.ones(20, dtype=bool))
    road = [_vector_from_pose(invert_pose(truth[k]) @ truth[k + 1]) for k in range(20)]
    qualities = [qualities[0]] + [
        replace(q, road_length_m=float(np.linalg.norm(r[3:])), road_motion=tuple(float(x) for x in r))
        for q, r in zip(qualities[1:], road, strict=True)
    ]
    lone, still, gap = 15, 10, 5  # frame numbers
    qualities[lone - 1] = replace(qualities[lone - 1], road_length_m=float("nan"), road_motion=())
    qualities[lone + 1] = replace(qualities[lone + 1], road_length_m=float("nan"), road_motion=())
    qualities[still] = replace(qualities[still], status="static")
    qualities[gap] = replace(qualities[gap], reference=gap - 2)

    def step_errors(params: VOParams) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        smoothed = smooth_step_lengths(poses, qualities, params)
        rotation, direction = np.zeros(20), np.zeros(20)
        for k in range(20):
            est, true = invert_pose(smoothed[k]) @ smoothed[k + 1], invert_pose(truth[k]) @ truth[k + 1]
            rotation[k] = _rotation_deg(est[:3, :3] @ true[:3, :3].T)
            cos = est[:3, 3] @ true[:3, 3] / np.linalg.norm(est[:3, 3]) / np.linalg.norm(true[:3, 3])
            direction[k] = np.degrees(np.arccos(min(1.0, cos)))
        return rotation, direction

    rotation, direction = step_errors(VOParams())
    own = np.zeros(20, dtype=bool)
    own[[lone - 2, lone - 1, lone, still - 1]] = True  # step k - 1 is frame k's; lone's neighbours: no road
    assert rotation[~own].max() < 1e-6 and direction[~own].max() < 1e-5, (rotation, direction)
    moved = [lone - 2, lone - 1, lone]
    assert rotation[own].min() > 0.04 and direction[moved].min() > 0.3, (rotation, direction)
    rotation_off, direction_off = step_errors(VOParams(road_motion=False))
    assert rotation_off.min() > 0.04 and direction_off.min() > 0.3, (rotation_off, direction_off)


def test_a_reliable_step_far_from_the_roads_length_is_left_out() -> None:
    """A step measured on a vehicle that passed every check (reliable, 80 % short) among steps the road
    measured: with the road its length is gated out and every smoothed step stays within 1 % of the truth
    (measured: 0.3 %); without the road it pulls its neighbours."""
    rng = np.random.default_rng(6)
    true_lengths = 2.8 + 0.03 * np.arange(30)
    measured = true_lengths * (1.0 + rng.normal(0.0, 0.005, 30))
    measured[20] *= 0.2
    poses = _straight_run(measured)
    qualities = _qualities(measured, std_pct=0.4, reliable=np.ones(30, dtype=bool))
    road = true_lengths * (1.0 + rng.normal(0.0, 0.003, 30))
    qualities = [qualities[0]] + [replace(q, road_length_m=float(r)) for q, r in zip(qualities[1:], road, strict=True)]

    def errors(params: VOParams) -> NDArray[np.float64]:
        smoothed = smooth_step_lengths(poses, qualities, params)
        return np.linalg.norm((np.linalg.inv(smoothed[:-1]) @ smoothed[1:])[:, :3, 3], axis=1) / true_lengths - 1.0

    assert np.abs(errors(VOParams())).max() < 0.01
    assert np.abs(errors(VOParams(road_steps=False))).max() > 0.1


def test_two_measurements_of_a_step_weigh_as_their_noises_say() -> None:
    """The smoother given two measurements of each step (columns) is the smoother given their
    inverse-variance mean, and a column left unmeasured is as if absent."""
    rng = np.random.default_rng(4)
    truth = 3.0 + 0.02 * np.arange(20)
    a = truth + rng.normal(0.0, 0.02, 20)
    b = truth + rng.normal(0.0, 0.05, 20)
    both, _ = _rts_constant_velocity(np.column_stack([a, b]), np.ones((20, 2), bool),
                                     np.column_stack([np.full(20, 0.02), np.full(20, 0.05)]), 0.02)  # fmt: skip
    w_a, w_b = 1 / 0.02**2, 1 / 0.05**2
    mean = (w_a * a + w_b * b) / (w_a + w_b)
    merged, _ = _rts_constant_velocity(mean, np.ones(20, bool), np.full(20, (w_a + w_b) ** -0.5), 0.02)
    np.testing.assert_allclose(both, merged, rtol=1e-9)
    first_only = np.column_stack([np.ones(20, bool), np.zeros(20, bool)])
    only_a, _ = _rts_constant_velocity(np.column_stack([a, b]), first_only,
                                       np.column_stack([np.full(20, 0.02), np.full(20, 0.05)]), 0.02)  # fmt: skip
    plain, _ = _rts_constant_velocity(a, np.ones(20, bool), np.full(20, 0.02), 0.02)
    np.testing.assert_allclose(only_a, plain, rtol=1e-12)


def test_smoothed_step_lengths_are_nearer_the_truth_and_keep_directions() -> None:
    """Steps of a speeding-up drive measured with 2 % noise: the smoothed lengths are a third nearer the truth."""
    rng = np.random.default_rng(11)
    true_lengths = 2.5 + 0.03 * np.arange(40)
    measured = true_lengths * (1.0 + rng.normal(0.0, 0.02, 40))
    reliable = rng.random(40) > 0.3
    poses = _straight_run(measured)
    # The normal equations' std is a third of the real noise, as on the synthetic highway.
    qualities = _qualities(measured, std_pct=2.0 / 3.0, reliable=reliable)
    smoothed = smooth_step_lengths(poses, qualities, VOParams())
    steps_before = np.linalg.inv(poses[:-1]) @ poses[1:]
    steps_after = np.linalg.inv(smoothed[:-1]) @ smoothed[1:]
    after = np.linalg.norm(steps_after[:, :3, 3], axis=1)
    before_rms = np.sqrt(np.mean((measured / true_lengths - 1.0) ** 2))
    after_rms = np.sqrt(np.mean((after / true_lengths - 1.0) ** 2))
    assert after_rms < 0.75 * before_rms
    np.testing.assert_allclose(steps_after[:, :3, :3], steps_before[:, :3, :3], atol=1e-12)
    unit = steps_before[:, :3, 3] / np.linalg.norm(steps_before[:, :3, 3], axis=1)[:, None]
    np.testing.assert_allclose(steps_after[:, :3, 3] / after[:, None], unit, atol=1e-9)
    np.testing.assert_allclose(smoothed[0], poses[0])
    # Off: the poses as given.
    np.testing.assert_array_equal(smooth_step_lengths(poses, qualities, VOParams(smooth_lengths=False)), poses)


def test_static_frames_stay_still_when_smoothed() -> None:
    lengths = np.array([1.0, 1.0, 0.0, 0.0, 1.0, 1.0])
    poses = _straight_run(lengths, yaw_deg=0.0)
    qualities = _qualities(lengths, std_pct=0.3, reliable=np.ones(6, dtype=bool))
    for k in (3, 4):
        qualities[k] = FrameQuality(**{**qualities[k].__dict__, "status": "static", "translation_m": 0.0})
    smoothed = smooth_step_lengths(poses, qualities, VOParams())
    steps = np.linalg.inv(smoothed[:-1]) @ smoothed[1:]
    np.testing.assert_allclose(steps[2:4, :3, 3], 0.0, atol=1e-12)
    assert np.all(np.linalg.norm(steps[[0, 1, 4, 5], :3, 3], axis=1) > 0.5)


def _offset_window(
    rng: np.random.Generator, near: float, far: float, step_m: float, offset_px: float, sigma_px: float
) -> tuple[_WindowProblem, NDArray[np.float64]]:
    """A window of four frames (the oldest fixed) moving ``step_m`` forward per frame, 120 points seen in all,
    every disparity ``offset_px`` too small, noise ``sigma_px`` on each of u, v and u_right; the true state."""
    n_free, n_points = 3, 120
    points = _points(rng, n_points, near, far)
    motion = _pose_from_vector(np.array([0.0, np.deg2rad(0.3), 0.0, step_m / 6.0, 0.0, step_m]))
    cam_world = [np.eye(4)]
    for _ in range(n_free):
        cam_world.append(invert_pose(invert_pose(cam_world[-1]) @ motion))
    fi = np.repeat(np.arange(n_free + 1), n_points)
    pi = np.tile(np.arange(n_points), n_free + 1)
    xc = np.stack([points @ t[:3, :3].T + t[:3, 3] for t in cam_world])[fi, pi]
    u = CAMERA.fx * xc[:, 0] / xc[:, 2] + CAMERA.cx
    v = CAMERA.fy * xc[:, 1] / xc[:, 2] + CAMERA.cy
    noise = rng.normal(0.0, sigma_px, (fi.size, 3))
    uv = np.column_stack([u, v]) + noise[:, :2]
    u_right = u - CAMERA.focal_baseline / xc[:, 2] + offset_px + noise[:, 2]
    problem = _WindowProblem(CAMERA, cam_world[0], n_free, n_points, fi, pi, uv, u_right)
    x0 = np.concatenate([np.concatenate([_vector_from_pose(t) for t in cam_world[1:]]), points.ravel()])
    return problem, x0


@pytest.mark.parametrize(("near", "far", "step_m", "observable"), [(2.0, 4.0, 0.6, True), (6.0, 12.0, 0.2, False)])
def test_a_windows_offset_estimate_knows_its_own_spread(
    near: float, far: float, step_m: float, observable: bool
) -> None:
    """A window's offset estimate (the parabola through its cost at three disparity shifts) over 30 noise draws:
    it finds the simulated 0.3 px, and the standard deviation it states for itself is the spread the draws
    show. Strong parallax pins the offset to a few hundredths of a pixel; a short step over a narrow depth
    range leaves it loose, and such a window is not counted (``offset_window_std_px``, 0.1 px)."""
    vo = StereoOdometry(CAMERA, VOParams())
    steps, stds = [], []
    for seed in range(30):
        problem, x0 = _offset_window(np.random.default_rng(seed), near, far, step_m, 0.3, 0.2)
        step, std = vo._window_offset(problem, np.ones(problem.fi.size), x0)
        steps.append(step)
        stds.append(std)
    spread = float(np.std(steps, ddof=1))
    stated = float(np.mean(stds))
    # Measured: 0.290 (spread 0.023, stated 0.026) and 0.246 (0.142, 0.176).
    assert abs(np.mean(steps) - 0.3) < 3.0 * spread / np.sqrt(len(steps)) + 0.02
    assert 0.7 < stated / spread < 1.6, (stated, spread)
    assert (stated < 0.05) if observable else (stated > 0.1), stated
    # The estimate counts only when the window pins it down; with the test off (0) every window counts.
    for limit, counted in ((0.1, observable), (0.0, True)):
        gated = StereoOdometry(CAMERA, replace(VOParams(), offset_window_std_px=limit))
        gated._estimate_offset(problem, np.zeros(3 * problem.fi.size), x0, np.zeros(problem.fi.size, bool))
        assert len(gated._offset_windows) == int(counted)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_reduced_system_solver_reaches_the_least_squares_minimum(seed: int) -> None:
    """:meth:`_WindowProblem.solve` (Levenberg-Marquardt with the points eliminated) from a disturbed start
    reaches the minimum scipy's least_squares finds with tight tolerances: the same cost, a gradient near 0,
    the same poses; points whose every observation weighs 0 stay where they started."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(seed)
    problem, truth = _offset_window(rng, 3.0, 30.0, 0.8, 0.2, 0.3)
    weight = np.ones(problem.fi.size)
    weight[np.isin(problem.pi, [5, 17])] = 0.0  # two tracks left out entirely
    weight[rng.random(weight.size) < 0.05] = 0.0  # and some single observations
    problem = problem.with_right(problem.u_right, weight)
    x0 = truth.copy()
    x0[: 6 * problem.n_free] += rng.normal(0.0, 0.01, 6 * problem.n_free)  # 0.6 degrees, 1 cm
    x0[6 * problem.n_free :] *= 1.0 + rng.normal(0.0, 0.03, x0.size - 6 * problem.n_free)
    x, res = problem.solve(x0)
    np.testing.assert_allclose(res, problem.residuals(x), rtol=0, atol=1e-12)
    reference = least_squares(
        problem.residuals, x0, jac=problem.jacobian, method="trf", x_scale="jac", ftol=1e-14, xtol=1e-14,
        gtol=1e-14, max_nfev=500, tr_solver="lsmr",
    )  # fmt: skip
    cost, reference_cost = float(res @ res), float(reference.fun @ reference.fun)
    assert cost <= reference_cost * (1.0 + 1e-6), (cost, reference_cost)
    gradient = problem.jacobian(x).T @ res
    assert np.abs(gradient).max() <= 1e-4 * np.abs(problem.jacobian(x0).T @ problem.residuals(x0)).max()
    n_cam = 6 * problem.n_free
    np.testing.assert_allclose(x[:n_cam], reference.x[:n_cam], rtol=0, atol=1e-5)  # radians, metres: 10 um
    for track in (5, 17):
        np.testing.assert_array_equal(
            x[n_cam + 3 * track : n_cam + 3 * track + 3], x0[n_cam + 3 * track : n_cam + 3 * track + 3]
        )


def test_the_offset_estimate_follows_the_latest_windows() -> None:
    """A rig whose offset changes (0.3 px for 10 windows, then 0): with ``offset_max_windows`` 5 the applied
    offset returns to the configured 0 once the old windows have left, and no more than 5 are kept; with 0
    (every window since the start) the old ones hold it near the mean of all, 0.15 px."""
    for max_windows in (5, 0):
        vo = StereoOdometry(CAMERA, replace(VOParams(), offset_max_windows=max_windows))
        rng = np.random.default_rng(0)
        for value in 0.3 + 0.02 * rng.standard_normal(10):
            vo._add_offset_window(float(value))
        assert abs(vo.disparity_offset - 0.3) < 0.03, vo.disparity_offset
        for value in 0.02 * rng.standard_normal(10):
            vo._add_offset_window(float(value))
        mean, _, n = vo.offset_estimate()
        if max_windows:
            assert n == 5
            assert abs(mean) < 0.05, mean
            assert abs(vo.disparity_offset) < 1e-9, vo.disparity_offset
        else:
            assert n == 20
            assert abs(vo.disparity_offset - 0.15) < 0.03, vo.disparity_offset


def test_a_reliable_frame_among_unreliable_ones_is_marked_isolated() -> None:
    """A reliable frame with no other reliable frame within ``isolated_frames`` (2) on either side is
    reported unreliable, pose untouched; the first frame counts as a neighbour and is never marked."""
    pattern = "R..R..R.R...RR"  # R reliable, . weak_scale; frame 0 is the first
    qualities = [
        FrameQuality(index=k, stamp=float(k), status=("first" if k == 0 else "ok" if c == "R" else "weak_scale"),
                     reliable=c == "R", features=500, stereo_matches=300, translation_m=1.0 + k)
        for k, c in enumerate(pattern)
    ]  # fmt: skip
    marked = mark_isolated(qualities, VOParams())
    flags = "".join("R" if q.reliable else "i" if q.status == "isolated" else "." for q in marked)
    # Frame 3 is 3 from frame 0 and 3 from frame 6: alone. 6 and 8 are 2 apart, 12 and 13 neighbours.
    assert flags == "R..i..R.R...RR"
    assert marked[3].translation_m == qualities[3].translation_m and "within 2 frames" in marked[3].message
    # Frame 0 alone is still reliable; a reach of 3 keeps frame 3 (frame 0 and frame 6 are within it).
    assert mark_isolated(qualities[:1], VOParams())[0].reliable
    assert [q.reliable for q in mark_isolated(qualities, VOParams(isolated_frames=3))] == [c == "R" for c in pattern]
    assert mark_isolated(qualities, VOParams(isolated_frames=0)) == qualities


def _flagged(flags: NDArray[np.bool_], first: int) -> list[FrameQuality]:
    """Frame qualities with the given reliability; frame ``first`` is the first frame (before it: no features)."""
    out = []
    for k, ok in enumerate(flags):
        status = "first" if k == first else ("ok" if ok else "weak_scale") if k > first else "few_features"
        out.append(FrameQuality(index=k, stamp=0.1 * k, status=status, reliable=k == first or (bool(ok) and k > first),
                                features=500, stereo_matches=300))  # fmt: skip
    return out


def _isolated_by_counting(flags: NDArray[np.bool_], first: int, reach: int) -> list[bool]:
    """The rule counted over the whole sequence at once (the reference): a reliable frame other than the
    first with no other reliable frame within ``reach`` frames on either side is isolated."""
    total = np.concatenate([[0], np.cumsum(flags)])
    index = np.arange(flags.size)
    counts = total[np.minimum(index + reach + 1, flags.size)] - total[np.maximum(index - reach, 0)] - flags
    return [bool(ok and counts[k] == 0 and k != first and reach > 0) for k, ok in enumerate(flags)]


@pytest.mark.parametrize("reach", [0, 1, 2, 3])
def test_the_isolation_gate_decides_as_frames_arrive_what_counting_over_the_sequence_decides(reach: int) -> None:
    """IsolationGate (mark_isolated's mechanism, the node's too): on random reliability patterns, the frames
    a count over the whole sequence isolates, in frame order, each decided at most ``reach`` frames after
    it arrived."""
    rng = np.random.default_rng(reach)
    params = VOParams(isolated_frames=reach)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        first = int(rng.integers(0, 3))
        qualities = _flagged(rng.random(n) < rng.uniform(0.1, 0.9), first=first)
        reliable = np.array([q.reliable for q in qualities])
        gate = IsolationGate(params)
        decided: list[FrameQuality] = []
        for k, quality in enumerate(qualities):
            decided += gate.add(quality)
            assert len(decided) >= k + 1 - reach, "no frame waits longer than reach frames"
            assert gate.undecided() == list(range(len(decided), k + 1))
        decided += gate.finish()
        assert gate.undecided() == []
        assert [q.index for q in decided] == list(range(n))
        expected = _isolated_by_counting(reliable, first, reach)
        assert [q.status == "isolated" for q in decided] == expected
        for q, before, isolated in zip(decided, qualities, expected, strict=True):
            assert q is before or isolated  # the others untouched
            assert q.reliable == (before.reliable and not isolated)
        assert decided == mark_isolated(qualities, params)


def test_the_isolation_gate_holds_only_frames_after_an_unreliable_run() -> None:
    """A run of reliable frames goes through at once; a reliable frame after two unreliable ones waits for the
    next two frames, and the frames behind it wait with it."""
    gate = IsolationGate(VOParams())
    q = _flagged(np.array([1, 1, 1, 0, 0, 1, 0, 0, 1, 1], bool), first=0)
    assert [len(gate.add(q[k])) for k in range(5)] == [1, 1, 1, 1, 1]
    assert gate.add(q[5]) == [] and gate.undecided() == [5]
    assert gate.add(q[6]) == [] and gate.undecided() == [5, 6]
    out = gate.add(q[7])  # no reliable frame within 2 after frame 5 either: isolated
    assert [(o.index, o.status) for o in out] == [(5, "isolated"), (6, "weak_scale"), (7, "weak_scale")]
    assert gate.add(q[8]) == [] and gate.undecided() == [8]
    out = gate.add(q[9])  # frame 9 is frame 8's reliable neighbour, and has frame 8 before it
    assert [(o.index, o.status) for o in out] == [(8, "ok"), (9, "ok")]


@pytest.mark.parametrize("gap", [1, 2])
def test_a_weak_step_takes_the_last_reliable_translation_whatever_its_reference(gap: int) -> None:
    """A ``weak_scale`` frame keeps its measured rotation (per frame) and takes the last reliable step's
    translation from the frame before, also when it was measured across a failed frame (``gap`` 2): a truck
    moving with the camera measured 0.3 m over two frames, which kept as it was put the frame behind the
    constant-velocity guess before it (highway seed 120's last frame: 192 % off)."""
    vo = StereoOdometry(CAMERA, VOParams())
    forward = _pose_from_vector(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 3.0]))
    vo.poses = [np.eye(4), forward, forward @ forward]  # frame 2: reliable, or a constant-velocity guess
    yaw = np.deg2rad(0.4)
    measured = _pose_from_vector(np.array([0.0, yaw, 0.0, 0.0, 0.0, 0.3]))  # from frame 3 - gap to frame 3
    vo.poses.append(vo.poses[3 - gap] @ measured)
    statuses = ["first", "ok", "ok" if gap == 1 else "implausible", "weak_scale"]
    vo.qualities = [
        FrameQuality(index=k, stamp=float(k), status=s, reliable=s in ("first", "ok"), features=500,
                     stereo_matches=300, reference=(-1 if k == 0 else 3 - gap if k == 3 else k - 1))
        for k, s in enumerate(statuses)
    ]  # fmt: skip
    vo._reliable_step = np.array([0.0, 0.0, 3.0])
    vo._step_prior(3, reliable=False)
    step = invert_pose(vo.poses[2]) @ vo.poses[3]
    np.testing.assert_allclose(step[:3, 3], [0.0, 0.0, 3.0], atol=1e-12)
    angle = np.arccos(np.clip((np.trace(step[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    np.testing.assert_allclose(angle, yaw / gap, atol=1e-9)
