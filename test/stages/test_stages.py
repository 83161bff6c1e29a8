"""Stages 1-3 on a wall seen from poses on an arc, with exact rendered depth."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.stages._common import within_tolerance
from selfcontra_ros.stages.outliers import (
    augmented_depth,
    augmented_margin,
    candidate_tolerance,
    free_space_witnesses,
    outlier_negatives,
    trivial_outliers,
)
from selfcontra_ros.stages.support import support_bits, update_support
from selfcontra_ros.stages.voting import consistency_voting, contradicted_positives, fattening_band, hole_margin
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


def wall_disparity(pose: np.ndarray, wall_z: float = WALL_Z) -> np.ndarray:
    u, v = np.meshgrid(np.arange(CAMERA.width, dtype=float), np.arange(CAMERA.height, dtype=float))
    rays = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u)], axis=-1)
    depth = (wall_z - pose[2, 3]) / (rays @ pose[2, :3])
    return CAMERA.depth_to_disparity(depth)


def view_at(theta_deg: float, radius: float = 8.0, index: int = 0, scale: float = 1.0, wall_z: float = WALL_Z) -> View:
    pose = orbit_pose(theta_deg, radius)
    disparity = wall_disparity(pose, wall_z) * scale
    return make_view(CAMERA, disparity, pose, index=index, key=index, stamp=0.0, sigma_px=1.0)


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


def test_references_under_the_minimum_angle_cast_no_positive_vote() -> None:
    query = view_at(0.0, radius=9.0)
    narrow = _supported(view_at(6.0, radius=6.0))  # about 6 degrees away from the query at the wall
    wide = _supported(view_at(20.0, radius=6.0))
    for refs, expected in (([narrow], UNKNOWN), ([wide], POSITIVE), ([narrow, wide], POSITIVE)):
        result = consistency_voting(query, refs, CAMERA, tolerance="sum", min_angle_deg=10.0, **KW)
        labels = result.labels.reshape(CAMERA.height, CAMERA.width)
        assert np.all(labels[CENTRE] == expected)
    # The paper's rule (0): the narrow reference votes positive.
    result = consistency_voting(query, [narrow], CAMERA, tolerance="sum", **KW)
    assert np.all(result.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == POSITIVE)
    # Where the narrow view is under the minimum angle, the sum of both views is the wide view's vote alone.
    both = consistency_voting(query, [narrow, wide], CAMERA, tolerance="sum", min_angle_deg=10.0, **KW)
    alone = consistency_voting(query, [wide], CAMERA, tolerance="sum", **KW)
    shape = (CAMERA.height, CAMERA.width)
    np.testing.assert_allclose(both.vote_sum.reshape(shape)[CENTRE], alone.vote_sum.reshape(shape)[CENTRE])


def test_narrow_references_still_vote_negative() -> None:
    refs = [_supported(view_at(6.0, radius=5.0))]
    in_front = view_at(0.0, radius=9.0, scale=1.25)  # depth / 1.25: blocks the reference's view of the wall
    result = consistency_voting(in_front, refs, CAMERA, tolerance="sum", min_angle_deg=10.0, **KW)
    assert np.all(result.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == NEGATIVE)


def test_minimum_query_support_leaves_unsupported_positives_unknown() -> None:
    query = view_at(0.0, radius=9.0)
    refs = [_supported(view_at(20.0, radius=6.0))]
    result = consistency_voting(query, refs, CAMERA, tolerance="sum", min_query_support=1, **KW)
    assert not np.any(result.labels == POSITIVE)
    assert np.all(result.vote_sum.reshape(CAMERA.height, CAMERA.width)[CENTRE] > 0)
    query.support_bits[: query.valid.size // 2] = 1  # the upper half of the image supported
    result = consistency_voting(query, refs, CAMERA, tolerance="sum", min_query_support=1, **KW)
    labels = result.labels.reshape(CAMERA.height, CAMERA.width)
    half = CAMERA.height // 2
    assert np.all(labels[half - 10 : half, 70:90] == POSITIVE)
    assert np.all(labels[half : half + 10, 70:90] == UNKNOWN)


def test_positive_accuracy_ratio_lets_less_accurate_references_confirm() -> None:
    query = view_at(0.0, radius=9.0)
    far_ref = _supported(view_at(20.0, radius=14.0))  # farther from the wall: u_r 3-14 times u_q
    lowest = float(np.min(far_ref.u[far_ref.valid]) / np.max(query.u[query.valid]))
    highest = float(np.max(far_ref.u[far_ref.valid]) / np.min(query.u[query.valid]))
    assert lowest > 2.0
    shape = (CAMERA.height, CAMERA.width)
    # A ratio under every u_r / u_q: the paper's rule, no vote.
    short = consistency_voting(query, [far_ref], CAMERA, tolerance="sum", positive_accuracy_ratio=0.5 * lowest, **KW)
    assert not short.voted.any()
    # A ratio over every u_r / u_q: the correct wall is confirmed.
    wide = consistency_voting(query, [far_ref], CAMERA, tolerance="sum", positive_accuracy_ratio=2.0 * highest, **KW)
    assert np.all(wide.labels.reshape(shape)[CENTRE] == POSITIVE)
    # One vote each, of at most the reference's largest weight support / sqrt(u_r).
    weights = support_count(far_ref.support_bits)[far_ref.valid] / np.sqrt(far_ref.u[far_ref.valid])
    assert np.all(wide.vote_sum.reshape(shape)[CENTRE] <= weights.max() * (1 + 1e-9))
    # The relaxed confirmation does not relax contradiction: depth 1.5 times too near stays unvoted.
    in_front = view_at(0.0, radius=9.0, scale=1.5)
    near = consistency_voting(in_front, [far_ref], CAMERA, tolerance="sum", positive_accuracy_ratio=2.0 * highest, **KW)
    assert not np.any(near.labels == NEGATIVE)
    assert not np.any(near.labels.reshape(shape)[CENTRE] == POSITIVE)
    with pytest.raises(ValueError, match="positive_accuracy_ratio"):
        consistency_voting(query, [far_ref], CAMERA, tolerance="sum", positive_accuracy_ratio=0.9, **KW)


def test_fallback_confirms_only_pixels_no_reference_voted_on() -> None:
    query = view_at(0.0, radius=9.0)
    far_refs = [_supported(view_at(a, radius=14.0)) for a in (20.0, -20.0)]  # u_r 3-14 times u_q
    highest = float(max(np.max(r.u[r.valid]) for r in far_refs) / np.min(query.u[query.valid]))
    lowest = float(min(np.min(r.u[r.valid]) for r in far_refs) / np.max(query.u[query.valid]))
    assert lowest > 2.0
    shape = (CAMERA.height, CAMERA.width)
    kw: dict[str, Any] = dict(tolerance="sum", fallback_accuracy_ratio=2.0 * highest, **KW)
    # Two agreeing less accurate views: positive, yet no vote is cast.
    two = consistency_voting(query, far_refs, CAMERA, fallback_min_views=2, **kw)
    assert np.all(two.labels.reshape(shape)[CENTRE] == POSITIVE)
    assert not two.voted.any() and not two.vote_sum.any()
    # The query's own ambiguous matches (View.reliable false) get no fallback positive.
    left_half = np.zeros(shape, dtype=bool)
    left_half[:, : CAMERA.width // 2] = True
    ambiguous = dataclasses.replace(query, reliable=query.reliable & ~left_half.ravel())
    half = consistency_voting(ambiguous, far_refs, CAMERA, fallback_min_views=2, **kw).labels.reshape(shape)
    split = CAMERA.width // 2 - CENTRE[1].start  # CENTRE's first column right of the ambiguous half
    assert np.all(half[CENTRE][:, :split] == UNKNOWN) and np.all(half[CENTRE][:, split:] == POSITIVE)
    # One agreeing view is not enough when two are asked for; a ratio under every u_r / u_q is the paper.
    one = consistency_voting(query, far_refs[:1], CAMERA, fallback_min_views=2, **kw)
    assert not np.any(one.labels == POSITIVE)
    paper = consistency_voting(query, far_refs, CAMERA, **dict(kw, fallback_accuracy_ratio=0.5 * lowest))
    assert not np.any(paper.labels == POSITIVE)
    # Where a more accurate reference votes, the fallback never overrides it. The query sees a phantom wall 3 m
    # in front of the true one (its disparity 1.5 times too large); two less accurate views see the same phantom
    # and agree with it, one nearer view sees the true wall and votes the query's points occluding.
    in_front = view_at(0.0, radius=9.0, scale=1.5)
    liars = [_supported(view_at(a, radius=14.0, wall_z=WALL_Z - 3.0)) for a in (20.0, -20.0)]
    alone = consistency_voting(in_front, liars, CAMERA, fallback_min_views=2, **kw)
    assert np.all(alone.labels.reshape(shape)[CENTRE] == POSITIVE)  # the repeated error alone confirms itself
    near_ref = _supported(view_at(0.0, radius=5.0))  # 5 m from the true wall, the query 6 m from its phantom
    mixed = consistency_voting(in_front, [near_ref, *liars], CAMERA, fallback_min_views=2, **kw)
    assert np.all(mixed.labels.reshape(shape)[CENTRE] == NEGATIVE)
    with pytest.raises(ValueError, match="fallback_min_views"):
        consistency_voting(query, far_refs, CAMERA, fallback_min_views=0, **kw)


def test_less_accurate_references_vote_negative_only_when_allowed() -> None:
    far_ref = [_supported(view_at(25.0, radius=10.0))]  # farther from the wall than the query: u_r > u_q
    in_front = view_at(0.0, radius=9.0, scale=1.5)  # 3 m in front of the wall, beyond the reference's 2 sigma
    paper = consistency_voting(in_front, far_ref, CAMERA, tolerance="sum", **KW)
    assert not paper.voted.any()
    anyone = consistency_voting(in_front, far_ref, CAMERA, tolerance="sum", negative_voters="any", **KW)
    assert np.all(anyone.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == NEGATIVE)
    # Correct depth gets no negative vote, and positive votes still need a more accurate reference.
    correct = view_at(0.0, radius=9.0)
    result = consistency_voting(correct, far_ref, CAMERA, tolerance="sum", negative_voters="any", **KW)
    assert not np.any(result.labels == NEGATIVE)
    assert not np.any(result.voted.reshape(CAMERA.height, CAMERA.width)[CENTRE])


def _brute_covariance(points: np.ndarray, sigma_px: float) -> np.ndarray:
    """Covariances (n, 3, 3) from finite-difference Jacobians of the explicit stereo projection, numpy.linalg."""

    def observe(p: np.ndarray) -> np.ndarray:
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        u_l = CAMERA.fx * x / z + CAMERA.cx
        u_r = CAMERA.fx * (x - CAMERA.baseline) / z + CAMERA.cx
        v = CAMERA.fy * y / z + CAMERA.cy
        return np.stack([u_l, v, u_r, v], axis=-1)

    step = 1e-6
    jac = np.stack([(observe(points + step * e) - observe(points - step * e)) / (2 * step) for e in np.eye(3)], axis=-1)
    return np.linalg.inv(np.einsum("nki,nkj->nij", jac, jac) / sigma_px**2)


def test_sum_tolerance_matches_brute_force() -> None:
    rng = np.random.default_rng(5)
    query_pose, ref_pose = orbit_pose(0.0, 9.0), orbit_pose(23.0, 6.0)
    ref_from_query = np.linalg.inv(ref_pose) @ query_pose
    x_q = np.column_stack([rng.uniform(-2, 2, 500), rng.uniform(-1, 1, 500), rng.uniform(5, 12, 500)])
    x_r_in_q = x_q + rng.normal(scale=0.3, size=(500, 3))
    x_r = x_r_in_q @ ref_from_query[:3, :3].T + ref_from_query[:3, 3]
    rotation_qr = ref_from_query[:3, :3].T
    c_sum = _brute_covariance(x_q, 1.0) + rotation_qr @ _brute_covariance(x_r, 1.0) @ rotation_qr.T
    delta = x_r_in_q - x_q
    m2 = np.einsum("ni,nij,nj->n", delta, np.linalg.inv(c_sum), delta)
    u_q = np.linalg.eigvalsh(_brute_covariance(x_q, 1.0))[:, -1]
    u_r = np.linalg.eigvalsh(_brute_covariance(x_r, 1.0))[:, -1]
    got = within_tolerance("sum", x_q, x_r, x_r_in_q, ref_from_query, u_q, u_r, CAMERA, 1.0, 2.0)
    clear = np.abs(m2 - 4.0) > 1e-3 * 4.0  # leave out numerically borderline cases
    assert np.sum(got & clear) > 50 and np.sum(~got & clear) > 50
    np.testing.assert_array_equal(got[clear], m2[clear] <= 4.0)


def test_free_space_votes_can_be_switched_off() -> None:
    refs = [_supported(view_at(25.0, radius=5.0))]
    behind = view_at(0.0, radius=6.0, scale=0.6)  # only the splat sees the contradiction (see above)
    with_splat = consistency_voting(behind, refs, CAMERA, tolerance="sum", **KW)
    without = consistency_voting(behind, refs, CAMERA, tolerance="sum", free_space_votes=False, **KW)
    assert np.all(with_splat.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == NEGATIVE)
    assert not np.any(without.voted.reshape(CAMERA.height, CAMERA.width)[CENTRE])
    # The lookup's votes are unchanged: an occluding query is still negative.
    in_front = view_at(0.0, radius=9.0, scale=1.25)
    result = consistency_voting(in_front, refs, CAMERA, tolerance="sum", free_space_votes=False, **KW)
    assert np.all(result.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == NEGATIVE)


def _box_view(last_col: int) -> View:
    """The wall from straight on, with a box at half the wall's depth over rows 50-69, columns 70..last_col."""
    pose = orbit_pose(0.0)
    disparity = wall_disparity(pose)
    disparity[50:70, 70 : last_col + 1] *= 2.0
    return make_view(CAMERA, disparity, pose, index=0, key=0, stamp=0.0, sigma_px=1.0)


def test_splatted_outline_agreeing_with_a_neighbour_casts_no_free_space_vote() -> None:
    query = _box_view(89)
    # The reference, from the same pose, sees the box 5 px too wide (foreground fattening): its points at
    # columns 90-94 are splatted in front of the query's correct wall there.
    refs = [_supported(_box_view(94))]
    shape = (CAMERA.height, CAMERA.width)
    paper = consistency_voting(query, refs, CAMERA, tolerance="sum", **KW).labels.reshape(shape)
    assert np.all(paper[50:70, 90:95] == NEGATIVE)
    result = consistency_voting(query, refs, CAMERA, tolerance="sum", free_space_neighbourhood=1, **KW)
    labels = result.labels.reshape(shape)
    # Column 90: the splatted box point agrees with the query's box point at column 89, one pixel away.
    assert not np.any(result.voted.reshape(shape)[50:70, 90])
    # Columns 91-94: no query measurement within one pixel is on the box; the violation still counts.
    assert np.all(labels[50:70, 91:95] == NEGATIVE)
    # A larger neighbourhood accepts correspondingly more of the fattened outline.
    wide = consistency_voting(query, refs, CAMERA, tolerance="sum", free_space_neighbourhood=2, **KW)
    assert not np.any(wide.voted.reshape(shape)[50:70, 90:92])
    assert np.all(wide.labels.reshape(shape)[50:70, 92:95] == NEGATIVE)
    # Nowhere else does the option change a label.
    outside = np.ones(shape, dtype=bool)
    outside[50:70, 90:95] = False
    np.testing.assert_array_equal(labels[outside], paper[outside])


def test_free_space_neighbourhood_keeps_genuine_violations() -> None:
    refs = [_supported(view_at(25.0, radius=5.0))]
    behind = view_at(0.0, radius=6.0, scale=0.6)  # a whole surface behind the wall: no neighbour agrees
    for radius in (1, 2):
        result = consistency_voting(behind, refs, CAMERA, tolerance="sum", free_space_neighbourhood=radius, **KW)
        assert np.all(result.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == NEGATIVE)


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


def _query_points_in(ref: View, query: View, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Query points of ``pixels`` in ``ref``'s frame, whether each lands in its image, and that pixel (0 if not)."""
    t = ref.from_view(query)
    moved = query.points[pixels].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
    col = np.rint(CAMERA.fx * moved[:, 0] / moved[:, 2] + CAMERA.cx)
    row = np.rint(CAMERA.fy * moved[:, 1] / moved[:, 2] + CAMERA.cy)
    inside = (moved[:, 2] > 0) & (col >= 0) & (col <= CAMERA.width - 1) & (row >= 0) & (row <= CAMERA.height - 1)
    return moved, inside, np.where(inside, row * CAMERA.width + col, 0).astype(int)


def _witnesses_by_numpy(query: View, refs: list[View], pixels: np.ndarray, margin: float | None = None) -> np.ndarray:
    """free_space_witnesses written out per reference with numpy (same projection, same tolerance, same range)."""
    count = np.zeros(pixels.size, dtype=int)
    for ref in refs:
        moved, inside, j = _query_points_in(ref, query, pixels)
        seen = inside & ref.valid[j]
        if margin is not None:
            seen &= CAMERA.fx * CAMERA.baseline <= (ref.max_disparity - margin) * moved[:, 2]
        behind = np.linalg.norm(ref.points[j].astype(np.float64), axis=1) - np.linalg.norm(moved, axis=1)
        tolerance = candidate_tolerance(query.u[pixels], ref.u[j], 2.0, "std")
        count += seen & (behind > tolerance)
    return count


def test_free_space_witnesses_count_the_references_seeing_through_the_query_point() -> None:
    refs = [view_at(a, index=i) for i, a in enumerate((-24.0, -12.0, 12.0, 24.0))]
    pixels = np.flatnonzero(view_at(0.0).valid)
    on_wall = free_space_witnesses(view_at(0.0), refs, pixels, CAMERA, sigma_max=2.0, reading="std")
    assert not on_wall.any()  # a point on the wall blocks nobody's view
    near = view_at(0.0, scale=1.6)
    counts = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std")
    np.testing.assert_array_equal(counts, _witnesses_by_numpy(near, refs, pixels))
    assert np.all(counts.reshape(CAMERA.height, CAMERA.width)[CENTRE] == len(refs))


def test_a_reference_is_no_witness_for_a_point_beyond_its_disparity_range() -> None:
    refs = [view_at(a, index=i) for i, a in enumerate((-24.0, -12.0, 12.0, 24.0))]
    near = view_at(0.0, scale=1.6)
    pixels = np.flatnonzero(near.valid)
    # The near points' disparities in each reference, and a range that cuts through them.
    in_refs = [CAMERA.fx * CAMERA.baseline / _query_points_in(ref, near, pixels)[0][:, 2] for ref in refs]
    for ref, disparity in zip(refs, in_refs, strict=True):
        ref.max_disparity = float(np.median(disparity)) + 2.0
    counts = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std", range_margin_px=2.0)
    np.testing.assert_array_equal(counts, _witnesses_by_numpy(near, refs, pixels, margin=2.0))
    full = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std")
    assert np.all(counts <= full) and counts.sum() < 0.8 * full.sum() and counts.sum() > 0.2 * full.sum()
    # The range known but wide: every witness counts again.
    for ref in refs:
        ref.max_disparity = 1000.0
    wide = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std", range_margin_px=2.0)
    np.testing.assert_array_equal(wide, full)


def test_only_reliable_reference_measurements_witness_when_asked() -> None:
    refs = [view_at(a, index=i) for i, a in enumerate((-24.0, -12.0, 12.0, 24.0))]
    near = view_at(0.0, scale=1.6)
    pixels = np.flatnonzero(near.valid)
    full = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std")
    # The left half of every reference's image ambiguous (View.reliable false): those measurements witness no more.
    for ref in refs:
        ref.reliable.reshape(CAMERA.height, CAMERA.width)[:, : CAMERA.width // 2] = False
    same = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std")
    np.testing.assert_array_equal(same, full)  # the paper: any valid measurement witnesses
    reliable = free_space_witnesses(near, refs, pixels, CAMERA, sigma_max=2.0, reading="std", reliable_only=True)
    expected = np.zeros_like(full)
    for ref in refs:
        kept = dataclasses.replace(ref, valid=ref.reliable)
        expected += free_space_witnesses(near, [kept], pixels, CAMERA, sigma_max=2.0, reading="std")
    np.testing.assert_array_equal(reliable, expected)
    assert 0.2 * full.sum() < reliable.sum() < 0.8 * full.sum()


def test_references_cast_no_stage2_vote_beyond_their_disparity_range() -> None:
    refs = [_supported(view_at(25.0, radius=5.0))]
    in_front = view_at(0.0, radius=9.0, scale=1.25)  # an occlusion for the reference (see the test above)
    paper = consistency_voting(in_front, refs, CAMERA, tolerance="sum", **KW)
    assert np.all(paper.labels.reshape(CAMERA.height, CAMERA.width)[CENTRE] == NEGATIVE)
    pixels = np.flatnonzero(in_front.valid)
    moved, inside, _ = _query_points_in(refs[0], in_front, pixels)
    disparity = CAMERA.fx * CAMERA.baseline / moved[:, 2]
    refs[0].max_disparity = float(np.median(disparity[inside])) + 1.0
    cut = consistency_voting(in_front, refs, CAMERA, tolerance="sum", range_margin_px=1.0, **KW)
    beyond = np.zeros(in_front.valid.size, dtype=bool)
    beyond[pixels] = inside & (CAMERA.fx * CAMERA.baseline > (refs[0].max_disparity - 1.0) * moved[:, 2])
    assert 0.2 < beyond[pixels][inside].mean() < 0.8
    assert paper.voted[beyond].mean() > 0.9
    assert not cut.voted[beyond].any()  # no vote at all there, neither the lookup's nor the splat's
    np.testing.assert_array_equal(cut.vote_sum[~beyond], paper.vote_sum[~beyond])
    # Without a margin (None, the paper) the range is not looked at.
    same = consistency_voting(in_front, refs, CAMERA, tolerance="sum", **KW)
    np.testing.assert_array_equal(same.vote_sum, paper.vote_sum)


def test_stage3_negative_needs_a_view_that_sees_through_the_query_point() -> None:
    refs = [view_at(a, index=i) for i, a in enumerate((-24.0, -12.0, 12.0, 24.0))]
    query = view_at(0.0, scale=1.6)  # every centre pixel in front of the wall the references agree on
    centre = np.zeros((CAMERA.height, CAMERA.width), dtype=bool)
    centre[CENTRE] = True
    sel = centre.ravel()
    for ref in refs:
        # Blind each reference where the centre's query points fall: it can no longer see through them,
        # while the wall behind them (the augmented depth) lies elsewhere in its image and stays measured.
        _, inside, j = _query_points_in(ref, query, np.flatnonzero(sel))
        ref.valid[j[inside]] = False
    pending = query.valid.copy()
    z_aug = augmented_depth(query, refs, pending, CAMERA, reading="std", min_positive_votes=3, **KW)
    assert np.isfinite(z_aug[sel]).all()
    paper = outlier_negatives(query, z_aug, pending, CAMERA, reading="std", **KW)
    assert paper[sel].all()
    witnessed = outlier_negatives(query, z_aug, pending, CAMERA, reading="std", refs=refs, min_free_space_views=1, **KW)
    assert not witnessed[sel].any()
    # Elsewhere the references still see through the near points: those stay negative.
    assert witnessed[paper & ~sel].sum() > 0.5 * paper[~sel].sum()


def test_stage3_depth_ratio_keeps_only_points_far_enough_in_front() -> None:
    refs = [view_at(a, index=i) for i, a in enumerate((-24.0, -12.0, 12.0, 24.0))]
    pose = orbit_pose(0.0)
    # The query's left half 1.3 times the wall's disparity, its right half 1.6 times: the wall lies that
    # many times farther than the query point.
    scale = np.where(np.arange(CAMERA.width)[None, :] < CAMERA.width // 2, 1.3, 1.6)
    query = make_view(CAMERA, wall_disparity(pose) * scale, pose, index=9, key=9, stamp=0.0, sigma_px=1.0)
    pending = query.valid.copy()
    z_aug = augmented_depth(query, refs, pending, CAMERA, reading="std", min_positive_votes=3, **KW)
    centre = np.zeros((CAMERA.height, CAMERA.width), dtype=bool)
    centre[CENTRE] = True
    near = (centre & (scale == 1.6)).ravel()
    less = (centre & (scale == 1.3)).ravel()
    assert near.any() and less.any()
    np.testing.assert_allclose(z_aug[near] / query.points[near, 2], 1.6, rtol=0.02)
    np.testing.assert_allclose(z_aug[less] / query.points[less, 2], 1.3, rtol=0.02)
    paper = outlier_negatives(query, z_aug, pending, CAMERA, reading="std", **KW)
    assert paper[near].all() and paper[less].all()
    same = outlier_negatives(query, z_aug, pending, CAMERA, reading="std", min_depth_ratio=1.0, **KW)
    np.testing.assert_array_equal(same, paper)
    split = outlier_negatives(query, z_aug, pending, CAMERA, reading="std", min_depth_ratio=1.45, **KW)
    assert split[near].all() and not split[less].any()
    assert not (split & ~paper).any()  # the ratio only takes negatives away
    assert not outlier_negatives(query, z_aug, pending, CAMERA, reading="std", min_depth_ratio=1.7, **KW)[near].any()


def test_stage3_tolerance_readings() -> None:
    u_a, u_b = np.array([0.04]), np.array([0.09])
    np.testing.assert_allclose(candidate_tolerance(u_a, u_b, 2.0, "std"), [2.0 * (0.2 + 0.3)])
    np.testing.assert_allclose(candidate_tolerance(u_a, u_b, 2.0, "paper"), [2.0 * (5.0 + 1.0 / 0.3)])
    np.testing.assert_allclose(augmented_margin(u_a, 2.0, "std"), [0.4])
    np.testing.assert_allclose(augmented_margin(u_a, 2.0, "paper"), [10.0])


# Stage 2: the fattening band


def _band_by_loops(disp: np.ndarray, jump: float, left: int, other: int, below: int | None = None) -> np.ndarray:
    """Obviously correct reference: look at every neighbour of every pixel."""
    h, w = disp.shape
    below = other if below is None else below
    valid = np.isfinite(disp) & (disp > 0)
    band = np.zeros((h, w), dtype=bool)
    for r in range(h):
        for c in range(w):
            if not valid[r, c]:
                continue
            window = [
                (rr, cc)
                for rr in range(max(r - other, 0), min(r + other, h - 1) + 1)
                for cc in range(max(c - left, 0), min(c + other, w - 1) + 1)
            ]
            window += [
                (rr, cc)
                for rr in range(r, min(r + below, h - 1) + 1)
                for cc in range(max(c - other, 0), min(c + other, w - 1) + 1)
            ]
            if any(valid[rr, cc] and disp[r, c] - disp[rr, cc] > jump for rr, cc in window):
                band[r, c] = True
    return band


def test_fattening_band_matches_brute_force() -> None:
    rng = np.random.default_rng(3)
    disp = np.full((30, 40), 10.0)
    disp[8:20, 15:30] = 30.0  # an object in front
    disp += rng.normal(0.0, 0.5, disp.shape)
    disp[rng.random(disp.shape) < 0.1] = np.nan  # holes are neither band nor neighbours
    disp[0, :5] = 0.0
    for jump, left, other in ((4.0, 6, 2), (4.0, 0, 0), (1.0, 3, 3), (4.0, 16, 3)):
        got = fattening_band(disp, jump_px=jump, occluded_side_px=left, other_px=other)
        np.testing.assert_array_equal(got, _band_by_loops(disp, jump, left, other))
    for jump, left, other, below in ((4.0, 6, 2, 9), (4.0, 0, 0, 5), (1.0, 3, 3, 0), (4.0, 20, 4, 24)):
        got = fattening_band(disp, jump_px=jump, occluded_side_px=left, other_px=other, below_px=below)
        np.testing.assert_array_equal(got, _band_by_loops(disp, jump, left, other, below))


def test_fattening_band_reaches_further_down_only_with_below_px() -> None:
    disp = np.full((60, 40), 10.0)
    disp[10:30, 10:30] = 30.0  # an object in front; its lower edge at row 29
    column = fattening_band(disp, jump_px=4.0, occluded_side_px=0, other_px=2, below_px=12)[:, 20]
    # Rows within 12 of the background below (from 18) and within 2 of the background above (10, 11).
    np.testing.assert_array_equal(np.flatnonzero(column), [10, 11, *range(18, 30)])
    # The strip below is other_px wide either side: an object whose left half reaches lower (an L) puts the
    # background 5 rows under a pixel 2 columns right of the step, and none under one 5 columns left of it.
    disp[30:50, 10:20] = 30.0
    strip = fattening_band(disp, jump_px=4.0, occluded_side_px=2, other_px=4, below_px=12)
    assert strip[25, 22] and strip[25, 16] and not strip[25, 15] and not strip[25, 14]
    assert not fattening_band(disp, jump_px=4.0, occluded_side_px=2, other_px=4)[25, 22]
    symmetric = fattening_band(disp, jump_px=4.0, occluded_side_px=0, other_px=2)[:, 20]
    np.testing.assert_array_equal(np.flatnonzero(symmetric), [10, 11, 28, 29])


def test_fattening_band_reaches_further_left() -> None:
    disp = np.full((40, 60), 10.0)
    disp[10:30, 20:40] = 30.0
    band = fattening_band(disp, jump_px=4.0, occluded_side_px=8, other_px=2)
    rows = band[20]  # a row through the middle of the object
    assert not rows[:20].any() and not rows[40:].any()  # the background is never in the band
    np.testing.assert_array_equal(np.flatnonzero(rows), [*range(20, 28), 38, 39])
    assert band[10:12, 30].all() and not band[12:28, 30].any() and band[28:30, 30].all()


def test_no_positive_label_in_the_fattening_band() -> None:
    query = view_at(0.0, radius=9.0)
    refs = [_supported(view_at(20.0, radius=6.0)), _supported(view_at(-20.0, radius=6.0))]
    disp = query.disparity.reshape(CAMERA.height, CAMERA.width).copy()
    step = np.zeros_like(disp, dtype=bool)
    step[:, :80] = True  # pretend everything left of column 80 lies well behind: an object's left edge
    query.disparity[step] -= 5.0  # only the band sees the edited disparity; the 3D points stay on the wall
    off = consistency_voting(query, refs, CAMERA, tolerance="sum", **KW).labels.reshape(disp.shape)
    on = consistency_voting(query, refs, CAMERA, tolerance="sum", edge_jump_px=4.0, **KW).labels.reshape(disp.shape)
    band = fattening_band(query.disparity.reshape(disp.shape), jump_px=4.0, occluded_side_px=16, other_px=3)
    assert band[:, 80:96].all() and not band[:, :80].any() and not band[:, 96:].any()
    assert np.all(off[40:80, 80:96] == POSITIVE)  # the references confirm these points ...
    assert np.all(on[band] == UNKNOWN)  # ... but a pixel in the band is never positive
    np.testing.assert_array_equal(on[~band], off[~band])


def test_band_reaching_down_takes_positives_only() -> None:
    query = view_at(0.0, radius=9.0)
    refs = [_supported(view_at(20.0, radius=6.0)), _supported(view_at(-20.0, radius=6.0))]
    disp = query.disparity.reshape(CAMERA.height, CAMERA.width).copy()
    query.disparity.reshape(disp.shape)[70:, :] -= 5.0  # pretend rows from 70 down lie behind: an object's lower edge
    kw = {"tolerance": "sum", "edge_jump_px": 4.0, "edge_occluded_side_px": 16, "edge_other_px": 3, **KW}
    near = consistency_voting(query, refs, CAMERA, **kw).labels.reshape(disp.shape)
    far = consistency_voting(query, refs, CAMERA, edge_below_px=12, **kw).labels.reshape(disp.shape)
    assert np.all(near[62:67, 40:120] == POSITIVE)  # the symmetric band reaches rows 67-69 only ...
    assert np.all(far[58:70, 40:120] == UNKNOWN)  # ... the one reaching down 12 rows from 58
    np.testing.assert_array_equal(far[:58], near[:58])
    np.testing.assert_array_equal(far[70:], near[70:])
    # A band reaching down as far as the rest gives the very same labels.
    same = consistency_voting(query, refs, CAMERA, edge_below_px=3, **kw).labels
    np.testing.assert_array_equal(same, near.ravel())


def test_hole_margin_matches_brute_force_and_skips_each_rows_leading_strip() -> None:
    rng = np.random.default_rng(5)
    disp = 10.0 + rng.normal(0.0, 0.5, (30, 50))
    disp[:, :7] = np.nan  # the matcher's unmatched left strip: not a hole
    disp[4, :20] = 0.0  # a longer leading run in one row: not a hole either
    disp[12:15, 25:28] = np.nan  # a hole
    disp[25, 40] = 0.0  # a one-pixel hole
    disp[20, 3] = np.nan  # inside the strip
    valid = np.isfinite(disp) & (disp > 0)
    holes = [(12 + i, 25 + j) for i in range(3) for j in range(3)] + [(25, 40)]
    rows, cols = np.mgrid[:30, :50]
    nearest = np.min([np.hypot(rows - r, cols - c) for r, c in holes], axis=0)
    for margin in (1.0, 2.5, 6.0):
        np.testing.assert_array_equal(hole_margin(disp, margin), valid & (nearest <= margin))
    assert not hole_margin(disp, 0.0).any()
    strip_only = np.full((30, 50), 10.0)
    strip_only[:, :7] = np.nan
    strip_only[4, :20] = np.nan
    assert not hole_margin(strip_only, 6.0).any()


def test_contradicted_positives_match_brute_force() -> None:
    rng = np.random.default_rng(11)
    labels = rng.choice(np.array([UNKNOWN, POSITIVE, NEGATIVE], dtype=np.uint8), size=(23, 37), p=[0.3, 0.5, 0.2])
    labels[5:12, 20:30] = NEGATIVE  # a contradicted region with positives beside it
    # Shares that no window's negatives / labelled count can equal (denominators up to 81), so no tie decides.
    for radius, share in ((1, 0.1037), (3, 0.2513), (4, 0.6011)):
        out = contradicted_positives(labels, radius, share)
        expected = np.zeros(labels.shape, dtype=bool)
        for r in range(labels.shape[0]):
            for c in range(labels.shape[1]):
                win = labels[max(r - radius, 0) : r + radius + 1, max(c - radius, 0) : c + radius + 1]
                labelled = np.count_nonzero(win != UNKNOWN)
                expected[r, c] = labels[r, c] == POSITIVE and np.count_nonzero(win == NEGATIVE) > share * labelled
        np.testing.assert_array_equal(out, expected)
        assert out.any() and not out.all()
    assert not contradicted_positives(labels, 3, 1.0).any()  # share 1: the paper, nothing dropped
    assert not contradicted_positives(labels, 0, 0.0).any()  # radius 0: a positive's only pixel is itself
    with pytest.raises(ValueError, match="radius_px"):
        contradicted_positives(labels, -1, 0.5)


def test_no_positive_label_near_a_hole() -> None:
    query = view_at(0.0, radius=9.0)
    refs = [_supported(view_at(20.0, radius=6.0)), _supported(view_at(-20.0, radius=6.0))]
    shape = (CAMERA.height, CAMERA.width)
    off = consistency_voting(query, refs, CAMERA, tolerance="sum", **KW).labels.reshape(shape)
    query.disparity.reshape(shape)[60, 100] = np.nan  # only the hole test sees it: the points stay
    on = consistency_voting(query, refs, CAMERA, tolerance="sum", hole_margin_px=5.0, **KW).labels.reshape(shape)
    near = hole_margin(query.disparity.reshape(shape), 5.0)
    assert near.sum() == 80  # the pixels of a radius-5 disc but the hole itself
    assert np.all(off[near] == POSITIVE)  # the references confirm these points ...
    assert np.all(on[near] == UNKNOWN)  # ... but near the hole they abstain
    np.testing.assert_array_equal(on[~near], off[~near])


def test_occlusion_votes_outside_the_band_are_left_out_when_asked() -> None:
    """A nearer reference that measured the wall too far says the correct query point floats in front of it.

    The paper counts that occlusion against the query; ``occlusion_votes="band"`` counts it only in the query's
    own fattening band, and the wall has none (that the band's occlusions still vote is checked against the
    slow reference in ``test_voting_kernel``).
    """
    query = view_at(0.0)
    wrong_ref = _supported(view_at(20.0, radius=4.0, scale=0.7))  # 43 % too far, still more accurate than the query
    assert np.all(wrong_ref.u[wrong_ref.valid].max() < query.u[query.valid].min())
    shape = (CAMERA.height, CAMERA.width)
    band = {"edge_jump_px": 4.0, "edge_occluded_side_px": 16, "edge_other_px": 3}
    paper = consistency_voting(query, [wrong_ref], CAMERA, tolerance="sum", **band, **KW)
    assert np.all(paper.labels.reshape(shape)[CENTRE] == NEGATIVE)
    in_band = consistency_voting(query, [wrong_ref], CAMERA, tolerance="sum", occlusion_votes="band", **band, **KW)
    assert not np.any(in_band.labels == NEGATIVE)
    with pytest.raises(ValueError, match="occlusion_votes"):
        consistency_voting(query, [wrong_ref], CAMERA, tolerance="sum", occlusion_votes="nowhere", **KW)
