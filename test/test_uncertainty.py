"""Uncertainty of triangulated points: analytic forms against numeric references."""

from __future__ import annotations

import numpy as np
import pytest

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.uncertainty import (
    covariance,
    information,
    largest_covariance_eigenvalue,
    mahalanobis_sq,
    mahalanobis_sq_sum,
    mean_camera_centre,
    rotate_sym,
    stereo_jacobian,
    stereo_observation,
    sym_eigvalsh,
    sym_from_matrix,
    sym_inverse,
    sym_quadratic_form,
    sym_to_matrix,
)

CAMERA = StereoCamera(fx=720.0, fy=710.0, cx=610.0, cy=180.0, baseline=0.54, width=1226, height=370)
SIGMA_PX = 0.7


def _random_points(rng: np.random.Generator, n: int) -> np.ndarray:
    z = rng.uniform(1.5, 60.0, n)
    x = rng.uniform(-0.8, 0.8, n) * z
    y = rng.uniform(-0.3, 0.3, n) * z
    return np.stack([x, y, z], axis=-1)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _numeric_jacobian(points: np.ndarray, step: float = 1e-6) -> np.ndarray:
    cols = []
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = step
        plus = stereo_observation(points + offset, CAMERA)
        minus = stereo_observation(points - offset, CAMERA)
        cols.append((plus - minus) / (2 * step))
    return np.stack(cols, axis=-1)


def test_observation_matches_camera_projection() -> None:
    points = _random_points(np.random.default_rng(0), 50)
    obs = stereo_observation(points, CAMERA)
    u, v, d = CAMERA.project(points)
    np.testing.assert_allclose(obs[:, 0], u)
    np.testing.assert_allclose(obs[:, 1], v)
    np.testing.assert_allclose(obs[:, 2], u - d)
    np.testing.assert_allclose(obs[:, 3], v)


def test_jacobian_matches_finite_differences() -> None:
    points = _random_points(np.random.default_rng(1), 200)
    numeric = _numeric_jacobian(points)
    np.testing.assert_allclose(stereo_jacobian(points, CAMERA), numeric, rtol=1e-5, atol=1e-6)


def test_information_and_covariance_match_finite_differences() -> None:
    points = _random_points(np.random.default_rng(2), 200)
    jac = _numeric_jacobian(points)
    fisher = np.einsum("nki,nkj->nij", jac, jac) / SIGMA_PX**2
    np.testing.assert_allclose(sym_to_matrix(information(points, CAMERA, SIGMA_PX)), fisher, rtol=1e-5)
    np.testing.assert_allclose(sym_to_matrix(covariance(points, CAMERA, SIGMA_PX)), np.linalg.inv(fisher), rtol=1e-4)


def test_largest_eigenvalue_matches_numpy_and_grows_with_depth() -> None:
    points = _random_points(np.random.default_rng(3), 300)
    cov = sym_to_matrix(covariance(points, CAMERA, SIGMA_PX))
    expected = np.linalg.eigvalsh(cov)[:, -1]
    np.testing.assert_allclose(largest_covariance_eigenvalue(points, CAMERA, SIGMA_PX), expected, rtol=1e-9)
    # Along the optical axis u scales with z^4 (depth std ~ z^2).
    axis = np.array([[0.27, 0.0, 5.0], [0.27, 0.0, 10.0]])
    u = largest_covariance_eigenvalue(axis, CAMERA, SIGMA_PX)
    assert u[1] / u[0] == pytest.approx(16.0, rel=0.02)


def test_largest_eigenvalue_is_nan_for_invalid_points() -> None:
    points = np.array([[0.0, 0.0, np.nan], [0.0, 0.0, -1.0], [0.0, 0.0, 4.0]])
    u = largest_covariance_eigenvalue(points, CAMERA, SIGMA_PX)
    assert np.isnan(u[0]) and np.isnan(u[1]) and u[2] > 0


def test_sym_eigvalsh_matches_numpy() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(size=(500, 3, 3))
    sym = a @ np.swapaxes(a, 1, 2)
    np.testing.assert_allclose(sym_eigvalsh(sym_from_matrix(sym)), np.linalg.eigvalsh(sym), rtol=1e-7, atol=1e-9)
    diagonal = sym_from_matrix(np.diag([3.0, 1.0, 2.0])[None])
    np.testing.assert_allclose(sym_eigvalsh(diagonal)[0], [1.0, 2.0, 3.0])


def test_sym_inverse_and_quadratic_form() -> None:
    rng = np.random.default_rng(5)
    a = rng.normal(size=(100, 3, 3))
    sym = a @ np.swapaxes(a, 1, 2) + np.eye(3)
    np.testing.assert_allclose(sym_to_matrix(sym_inverse(sym_from_matrix(sym))), np.linalg.inv(sym), rtol=1e-8)
    d = rng.normal(size=(100, 3))
    np.testing.assert_allclose(sym_quadratic_form(sym_from_matrix(sym), d), np.einsum("ni,nij,nj->n", d, sym, d))


def test_mahalanobis_without_matrix_equals_quadratic_form() -> None:
    rng = np.random.default_rng(6)
    points = _random_points(rng, 100)
    delta = rng.normal(scale=0.1, size=(100, 3))
    expected = sym_quadratic_form(information(points, CAMERA, SIGMA_PX), delta)
    np.testing.assert_allclose(mahalanobis_sq(points, delta, CAMERA, SIGMA_PX), expected, rtol=1e-9)


def test_rotating_point_and_information_keeps_mahalanobis_distance() -> None:
    rng = np.random.default_rng(7)
    points = _random_points(rng, 100)
    other = points + rng.normal(scale=0.2, size=(100, 3))
    rotation = _random_rotation(rng)
    translation = rng.normal(size=3)
    fisher = information(points, CAMERA, SIGMA_PX)
    before = sym_quadratic_form(fisher, other - points)
    moved_points = points @ rotation.T + translation
    moved_other = other @ rotation.T + translation
    after = sym_quadratic_form(rotate_sym(fisher, rotation), moved_other - moved_points)
    np.testing.assert_allclose(after, before, rtol=1e-9)
    # And the rotated information is the inverse of the rotated covariance.
    rotated_cov = rotate_sym(covariance(points, CAMERA, SIGMA_PX), rotation)
    np.testing.assert_allclose(
        sym_to_matrix(sym_inverse(rotated_cov)), sym_to_matrix(rotate_sym(fisher, rotation)), rtol=1e-6, atol=1e-9
    )


def test_sum_of_covariances_matches_explicit_inverse() -> None:
    rng = np.random.default_rng(8)
    points_a = _random_points(rng, 100)
    points_b = _random_points(rng, 100)
    rotation_ab = _random_rotation(rng)
    delta = rng.normal(scale=0.3, size=(100, 3))
    c_a = sym_to_matrix(covariance(points_a, CAMERA, SIGMA_PX))
    c_b = rotation_ab @ sym_to_matrix(covariance(points_b, CAMERA, SIGMA_PX)) @ rotation_ab.T
    expected = np.einsum("ni,nij,nj->n", delta, np.linalg.inv(c_a + c_b), delta)
    got = mahalanobis_sq_sum(points_a, points_b, rotation_ab, delta, CAMERA, SIGMA_PX)
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    # The sum test is never stricter than either covariance alone.
    alone = sym_quadratic_form(information(points_a, CAMERA, SIGMA_PX), delta)
    assert np.all(got <= alone * (1 + 1e-9))


def test_mean_camera_centre_is_midpoint_of_left_and_right() -> None:
    rng = np.random.default_rng(9)
    pose = np.eye(4)
    pose[:3, :3] = _random_rotation(rng)
    pose[:3, 3] = rng.normal(size=3)
    left = pose[:3, 3]
    right = pose[:3, :3] @ np.array([CAMERA.baseline, 0.0, 0.0]) + pose[:3, 3]
    np.testing.assert_allclose(mean_camera_centre(pose, CAMERA), (left + right) / 2)
