"""Stages 1-3 on a wall seen from poses on an arc, with exact rendered depth."""

from __future__ import annotations

import numpy as np

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.stages.outliers import (
    augmented_depth,
    augmented_margin,
    candidate_tolerance,
    outlier_negatives,
    trivial_outliers,
)
from selfcontra_ros.stages.support import support_bits, update_support
from selfcontra_ros.stages.voting import consistency_voting
from selfcontra_ros.window import View, make_view, support_count

CAMERA = StereoCamera(fx=200.0, fy=200.0, cx=79.5, cy=59.5, baseline=0.5, width=160, height=120)
WALL_Z = 10.0
TARGET = np.array([0.0, 0.0, WALL_Z])
CENTRE = (slice(50, 70), slice(70, 90))
KW = {"sigma_max": 2.0, "sigma_px": 1.0}


def orbit_pose(theta_deg: float, radius: float = 8.0) -> np.ndarray:
    """Camera on a horizontal arc around TARGET on the wall ``z = WALL_Z``, looking at it."""
    t = np.radians(theta_deg)
    position = TARGET + radius * np.array([np.sin(t), 0.0, -np.cos(t)])
    z = (TARGET - position) / radius
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = position
    return pose


def wall_disparity(pose: np.ndarray) -> np.ndarray:
    u, v = np.meshgrid(np.arange(CAMERA.width, dtype=float), np.arange(CAMERA.height, dtype=float))
    rays = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u)], axis=-1)
    depth = (WALL_Z - pose[2, 3]) / (rays @ pose[2, :3])
    return CAMERA.depth_to_disparity(depth)


def view_at(theta_deg: float, radius: float = 8.0, index: int = 0, scale: float = 1.0) -> View:
    pose = orbit_pose(theta_deg, radius)
    return make_view(CAMERA, wall_disparity(pose) * scale, pose, index=index, key=index, stamp=0.0, sigma_px=1.0)


def _support(query: View, refs: list[View]) -> np.ndarray:
    bits = np.zeros_like(query.support_bits)
    for ref in refs:
        bits |= support_bits(query, ref, CAMERA, alpha_min_deg=10.0, tolerance="smaller", **KW)
    return support_count(bits).reshape(CAMERA.height, CAMERA.width)


def _supported(view: View) -> View:
    """Give every valid pixel of ``view`` one bin of support."""
    view.support_bits[view.valid] = 1
    return view


# Stage 1


def test_two_views_in_one_bin_give_support_one() -> None:
    query = view_at(0.0)
    support = _support(query, [view_at(13.0), view_at(-17.0)])
    assert np.all(support[CENTRE] == 1)


def test_two_views_in_different_bins_give_support_two() -> None:
    query = view_at(0.0)
    support = _support(query, [view_at(13.0), view_at(-25.0)])
    assert np.all(support[CENTRE] == 2)


def test_views_under_alpha_min_give_no_support() -> None:
    query = view_at(0.0)
    assert not _support(query, [view_at(6.0), view_at(-8.0)]).any()


def test_wrong_reference_depth_gives_no_support() -> None:
    query = view_at(0.0)
    assert not _support(query, [view_at(15.0, scale=1.5)])[CENTRE].any()


def test_update_support_works_both_ways() -> None:
    older = view_at(-15.0, index=0)
    new = view_at(15.0, index=1)
    update_support(new, [older], CAMERA, alpha_min_deg=10.0, tolerance="smaller", **KW)
    for view in (older, new):
        counts = support_count(view.support_bits).reshape(CAMERA.height, CAMERA.width)
        assert np.all(counts[CENTRE] == 1)


# Stage 2


def test_accurate_supported_reference_votes_positive() -> None:
    query = view_at(0.0, radius=9.0)
    refs = [_supported(view_at(20.0, radius=6.0)), _supported(view_at(-20.0, radius=6.0))]
    result = consistency_voting(query, refs, CAMERA, tolerance="sum", **KW)
    labels = result.labels.reshape(CAMERA.height, CAMERA.width)
    assert np.all(labels[CENTRE] == POSITIVE)
    assert not np.any(result.labels == NEGATIVE)
    # Two views, one vote each of weight support / sqrt(u_r): at most two of the largest weights.
    max_weight = 1.0 / np.sqrt(np.nanmin(refs[0].u))
    assert np.all(result.vote_sum <= 2 * max_weight + 1e-9)


def test_unsupported_or_less_accurate_references_do_not_vote() -> None:
    query = view_at(0.0, radius=9.0)
    unsupported = view_at(20.0, radius=6.0)
    less_accurate = _supported(view_at(20.0, radius=14.0))
    for ref in (unsupported, less_accurate):
        result = consistency_voting(query, [ref], CAMERA, tolerance="sum", **KW)
        assert not result.voted.any() and np.all(result.labels == UNKNOWN)


def test_query_in_front_is_an_occlusion_and_behind_a_free_space_violation() -> None:
    refs = [_supported(view_at(25.0, radius=5.0))]
    in_front = view_at(0.0, radius=9.0, scale=1.25)  # depth / 1.25: blocks the reference's view of the wall
    # Depth / 0.6 (6.7 px of disparity error, 2.8 sigma of the query): the reference's wall blocks the query.
    behind = view_at(0.0, radius=6.0, scale=0.6)
    for query in (in_front, behind):
        result = consistency_voting(query, refs, CAMERA, tolerance="sum", **KW)
        labels = result.labels.reshape(CAMERA.height, CAMERA.width)
        assert np.all(labels[CENTRE] == NEGATIVE)


def test_sum_tolerance_accepts_more_than_query_tolerance() -> None:
    query = view_at(0.0, radius=9.0)
    refs = [_supported(view_at(30.0, radius=6.0, scale=1.01))]  # a small error along the reference rays
    positives = {}
    for mode in ("sum", "query"):
        result = consistency_voting(query, refs, CAMERA, tolerance=mode, **KW)
        positives[mode] = int(np.sum(result.labels == POSITIVE))
    assert positives["sum"] > positives["query"]
    assert positives["sum"] > 0.5 * query.valid.sum()


# Stage 3


def test_trivial_outliers_are_pixels_leaving_the_right_image() -> None:
    view = view_at(0.0)
    outliers = trivial_outliers(view, CAMERA).reshape(CAMERA.height, CAMERA.width)
    columns = np.arange(CAMERA.width)[None, :]
    np.testing.assert_array_equal(outliers, columns < wall_disparity(orbit_pose(0.0)))
    view.valid[:] = False
    assert not trivial_outliers(view, CAMERA).any()


def test_augmented_depth_recovers_the_wall_and_flags_near_query_depth() -> None:
    refs = [view_at(a, index=i) for i, a in enumerate((-24.0, -12.0, 12.0, 24.0))]
    truth = view_at(0.0)
    near = view_at(0.0, scale=1.6)
    pending = truth.valid & ~trivial_outliers(truth, CAMERA)
    for query in (truth, near):
        z_aug = augmented_depth(query, refs, pending, CAMERA, reading="std", min_positive_votes=3, **KW)
        true_depth = truth.points[:, 2]
        centre = np.zeros((CAMERA.height, CAMERA.width), dtype=bool)
        centre[CENTRE] = True
        sel = centre.ravel()
        np.testing.assert_allclose(z_aug[sel], true_depth[sel], rtol=0.05)
        negatives = outlier_negatives(query, z_aug, pending, CAMERA, reading="std", **KW)
        assert np.all(negatives[sel]) if query is near else not negatives.any()


def test_candidates_need_enough_positive_votes() -> None:
    refs = [view_at(-12.0), view_at(12.0)]  # at most two +1 votes
    query = view_at(0.0, scale=1.6)
    pending = query.valid.copy()
    z_aug = augmented_depth(query, refs, pending, CAMERA, reading="std", min_positive_votes=3, **KW)
    assert np.all(np.isnan(z_aug))
    z_aug = augmented_depth(query, refs, pending, CAMERA, reading="std", min_positive_votes=2, **KW)
    assert np.isfinite(z_aug.reshape(CAMERA.height, CAMERA.width)[CENTRE]).all()


def test_stage3_tolerance_readings() -> None:
    u_a, u_b = np.array([0.04]), np.array([0.09])
    np.testing.assert_allclose(candidate_tolerance(u_a, u_b, 2.0, "std"), [2.0 * (0.2 + 0.3)])
    np.testing.assert_allclose(candidate_tolerance(u_a, u_b, 2.0, "paper"), [2.0 * (5.0 + 1.0 / 0.3)])
    np.testing.assert_allclose(augmented_margin(u_a, 2.0, "std"), [0.4])
    np.testing.assert_allclose(augmented_margin(u_a, 2.0, "paper"), [10.0])
