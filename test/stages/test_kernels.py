"""Compiled kernels against slow, obviously correct per-point references on tiny images.

Each reference below works point by point with full 3x3 matrices and
``numpy.linalg`` (Jacobian ``J``, ``F = J^T J / sigma^2``, ``C = F^-1``), as
DESIGN section 2 and 3 state the computations; the package's kernels must
agree with them on 8x12 images with invalid pixels, points behind the camera,
points outside the image, exact half-pixel projections and z-buffer ties.

Where a float threshold decides (rounding to a pixel, ``alpha_min`` and its
bins, ``sigma_max``, the Stage-3 vote), the kernels and these references
compute the deciding quantity by different formulas, and the references
partly with numpy's BLAS/LAPACK, whose kernels differ from CPU to CPU: the
two agree to about 1e-13 relative, not to the bit. A decision that close to
its threshold may go either way on another machine, so the comparisons skip
the few points whose quantity lies within :data:`DOUBT` of a threshold (none
in these scenes, whose decisions keep at least 1e-5 of margin) and require
them to stay rare; everywhere else the results must be equal.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.projection import lookup, project_to_pixels, splat_all, splat_nearest
from selfcontra_ros.stages._common import within_tolerance
from selfcontra_ros.stages.outliers import augmented_depth
from selfcontra_ros.stages.support import MAX_BINS, observation_angle_deg, support_bits, update_support
from selfcontra_ros.uncertainty import largest_covariance_eigenvalue
from selfcontra_ros.window import View, make_view

CAM = StereoCamera(fx=10.0, fy=10.0, cx=5.5, cy=3.5, baseline=0.5, width=12, height=8)
SIGMA_PX = 1.0
SIGMA_MAX = 2.0
#: Relative distance (absolute in pixels for the rounding) to a threshold within which a decision counts as a tie
#: (module docstring): far above the 1e-13 the formulas differ by, far below the 1e-5 margin of the scenes.
DOUBT = 1e-9


# ---------------------------------------------------------------------------------------------------------------------
# Slow references (one point at a time).


def _ref_pixel(point: np.ndarray) -> int:
    """Nearest pixel (flat) of a left-frame point, -1 behind the camera, outside the image or not finite."""
    x, y, z = (float(c) for c in point)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)) or z <= 0:
        return -1
    col = round(CAM.fx * x / z + CAM.cx)  # Python rounds half to even, like numpy.rint
    row = round(CAM.fy * y / z + CAM.cy)
    if 0 <= col <= CAM.width - 1 and 0 <= row <= CAM.height - 1:
        return row * CAM.width + col
    return -1


def _near(value: float, threshold: float) -> bool:
    """Whether ``value`` lies within :data:`DOUBT` of ``threshold`` (relative, absolute below 1)."""
    return abs(value - threshold) <= DOUBT * max(abs(threshold), 1.0)


def _half_tie(coordinate: float) -> bool:
    """Whether a pixel coordinate lies within DOUBT of a half pixel, but not on it.

    Exactly on it is no tie between implementations: such values come from exact arithmetic (the hand-made
    cases, a coordinate 0 that a rotation about the y axis keeps), which every implementation reproduces.
    """
    offset = coordinate - math.floor(coordinate)
    return offset != 0.5 and _near(offset, 0.5)


def _pixel_doubtful(point: np.ndarray) -> bool:
    """Whether the nearest pixel of a left-frame point is a rounding tie (:func:`_half_tie` of u or v)."""
    x, y, z = (float(c) for c in point)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)) or z <= 0:
        return False
    return _half_tie(CAM.fx * x / z + CAM.cx) or _half_tie(CAM.fy * y / z + CAM.cy)


def _tie_pixels(point: np.ndarray) -> list[int]:
    """The pixels (flat, inside the image) a point whose rounding is a tie may go to: both sides of each tie."""
    x, y, z = (float(c) for c in point)
    u, v = CAM.fx * x / z + CAM.cx, CAM.fy * y / z + CAM.cy
    cols = {math.floor(u), math.ceil(u)} if _half_tie(u) else {round(u)}
    rows = {math.floor(v), math.ceil(v)} if _half_tie(v) else {round(v)}
    return [r * CAM.width + c for r in rows for c in cols if 0 <= r < CAM.height and 0 <= c < CAM.width]


def _assert_equal_unless_doubtful(got: np.ndarray, want: np.ndarray, doubtful: np.ndarray) -> None:
    """``got == want`` wherever the reference's decisions were clear; the ties must stay rare."""
    assert doubtful.mean() < 0.01, f"{int(doubtful.sum())} of {doubtful.size} pixels decided at a tie"
    np.testing.assert_array_equal(got[~doubtful], want[~doubtful])


def _apply(pose: np.ndarray, point: np.ndarray) -> np.ndarray:
    return pose[:3, :3] @ np.asarray(point, dtype=np.float64) + pose[:3, 3]


def _ref_information(point: np.ndarray) -> np.ndarray:
    """``J^T J / sigma^2`` from the Jacobian of ``(u_l, v_l, u_r, v_r)`` written out row by row."""
    x, y, z = (float(c) for c in point)
    j = np.array(
        [
            [CAM.fx / z, 0.0, -CAM.fx * x / z**2],
            [0.0, CAM.fy / z, -CAM.fy * y / z**2],
            [CAM.fx / z, 0.0, -CAM.fx * (x - CAM.baseline) / z**2],
            [0.0, CAM.fy / z, -CAM.fy * y / z**2],
        ]
    )
    return j.T @ j / SIGMA_PX**2


def _ref_u(point: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(np.linalg.inv(_ref_information(point)))[-1])


def _ref_tolerance_sq(mode: str, x_q: np.ndarray, x_r: np.ndarray, ref_from_query: np.ndarray) -> float:
    r_rq = ref_from_query[:3, :3]
    delta_q = _apply(np.linalg.inv(ref_from_query), x_r) - x_q
    if mode == "query" or (mode == "smaller" and _ref_u(x_q) <= _ref_u(x_r)):
        return float(delta_q @ _ref_information(x_q) @ delta_q)
    if mode == "smaller":
        delta_r = r_rq @ delta_q
        return float(delta_r @ _ref_information(x_r) @ delta_r)
    c_sum = np.linalg.inv(_ref_information(x_q)) + r_rq.T @ np.linalg.inv(_ref_information(x_r)) @ r_rq
    return float(delta_q @ np.linalg.solve(c_sum, delta_q))


def _ref_angle(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ta, tb = a - point, b - point
    cos = np.dot(ta, tb) / (np.linalg.norm(ta) * np.linalg.norm(tb))
    return math.degrees(math.acos(min(max(cos, -1.0), 1.0)))


def _ref_support_bits(query: View, ref: View, mode: str, alpha_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Stage-1 bits of ``query`` from ``ref``, and the pixels decided at a tie (pixel, angle, bin or tolerance)."""
    bits = np.zeros(query.valid.size, dtype=np.uint64)
    doubtful = np.zeros(query.valid.size, dtype=bool)
    ref_from_query = np.linalg.inv(ref.pose) @ query.pose
    centre_q = np.array([0.5 * CAM.baseline, 0.0, 0.0])
    centre_r = _apply(np.linalg.inv(query.pose), ref.centre)
    for i in np.flatnonzero(query.valid):
        x_q = query.points[i].astype(np.float64)
        in_ref = _apply(ref_from_query, x_q)
        doubtful[i] = _pixel_doubtful(in_ref)
        j = _ref_pixel(in_ref)
        if j < 0 or not ref.valid[j]:
            continue
        alpha = _ref_angle(x_q, centre_r, centre_q)
        doubtful[i] |= _near(alpha / alpha_min, round(alpha / alpha_min))  # alpha_min itself or a bin edge
        if alpha <= alpha_min:
            continue
        x_r = ref.points[j].astype(np.float64)
        if mode == "smaller":  # which covariance the test uses
            doubtful[i] |= _near(_ref_u(x_q), _ref_u(x_r))
        m2 = _ref_tolerance_sq(mode, x_q, x_r, ref_from_query)
        doubtful[i] |= _near(m2, SIGMA_MAX**2)
        if m2 <= SIGMA_MAX**2:
            bits[i] |= np.uint64(1) << np.uint64(min(int(alpha // alpha_min), MAX_BINS - 1))
    return bits, doubtful


def _ref_augmented_depth(
    query: View, refs: list[View], pending: np.ndarray, min_votes: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per pending pixel: all splatted candidates nearest first; the first one the relaxed vote validates.

    Returns the augmented depth and the pixels decided at a tie (a candidate's pixel, a lookup's pixel or a vote).
    """
    candidates: dict[int, list[float]] = {}
    doubtful = np.zeros(query.valid.size, dtype=bool)
    for ref in refs:
        query_from_ref = np.linalg.inv(query.pose) @ ref.pose
        for s in np.flatnonzero(ref.valid):
            p = _apply(query_from_ref, ref.points[s])
            pixel = _ref_pixel(p)
            if _pixel_doubtful(p):  # the candidate may go to either pixel of the tie: doubt both
                doubtful[_tie_pixels(p)] = True
            if pixel >= 0 and pending[pixel]:
                candidates.setdefault(pixel, []).append(float(p[2]))
    z_aug = np.full(query.valid.size, np.nan)
    for pixel, depths in candidates.items():
        row, col = divmod(pixel, CAM.width)
        ray = np.array([(col - CAM.cx) / CAM.fx, (row - CAM.cy) / CAM.fy, 1.0])
        for depth in sorted(depths):
            point = depth * ray
            plus = total = 0
            for view in refs:
                in_ref = _apply(np.linalg.inv(view.pose) @ query.pose, point)
                doubtful[pixel] |= _pixel_doubtful(in_ref)
                j = _ref_pixel(in_ref)
                if j < 0 or not view.valid[j]:
                    continue
                range_c = np.linalg.norm(in_ref)
                range_r = np.linalg.norm(view.points[j].astype(np.float64))
                tol = (math.sqrt(_ref_u(point)) + math.sqrt(float(view.u[j]))) * SIGMA_MAX
                doubtful[pixel] |= _near(abs(range_c - range_r), tol) or _near(range_c, range_r)
                if abs(range_c - range_r) <= tol:
                    plus, total = plus + 1, total + 1
                elif range_c < range_r:
                    total -= 1
            if plus >= min_votes and total > 0:
                z_aug[pixel] = depth
                break
    return z_aug, doubtful


# ---------------------------------------------------------------------------------------------------------------------
# Tiny scenes.


def _pose(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    a = math.radians(yaw_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    pose[:3, 3] = t
    return pose


def _plane_disparity(pose: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """Disparity of the plane ``z = 4`` (world) seen from ``pose``, with noise and some invalid pixels."""
    u, v = np.meshgrid(np.arange(CAM.width, dtype=float), np.arange(CAM.height, dtype=float))
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u)], axis=-1)
    depth = (4.0 - pose[2, 3]) / (rays @ pose[2, :3])
    disparity = CAM.fx * CAM.baseline / depth + rng.normal(0.0, noise, depth.shape)
    disparity[rng.random(depth.shape) < 0.1] = np.nan
    disparity[rng.random(depth.shape) < 0.05] = 0.0
    disparity[rng.random(depth.shape) < 0.05] = -1.0
    return disparity


def _views(seed: int, noise: float = 0.3) -> list[View]:
    rng = np.random.default_rng(seed)
    poses = [_pose(0.0, (0.0, 0.0, 0.0)), _pose(-14.0, (0.9, 0.05, 0.2)), _pose(25.0, (-1.6, -0.1, 0.4))]
    poses.append(_pose(8.0, (-0.5, 0.0, -0.3)))
    return [
        make_view(CAM, _plane_disparity(p, rng, noise), p, index=k, key=k, stamp=float(k), sigma_px=SIGMA_PX)
        for k, p in enumerate(poses)
    ]


# ---------------------------------------------------------------------------------------------------------------------
# Projection: lookup, splats.


def _edge_points(rng: np.random.Generator) -> np.ndarray:
    """Random points in and around the view frustum plus the edge cases, in one left frame (metres)."""
    z = rng.uniform(0.5, 6.0, 200)
    points = np.stack([rng.uniform(-1.0, 1.0, 200) * z, rng.uniform(-0.6, 0.6, 200) * z, z], axis=-1)
    edge = [
        [0.0, 0.0, -2.0],  # behind the camera
        [0.0, 0.0, 0.0],  # on the camera plane
        [np.nan, 0.0, 2.0],  # not finite
        [5.0, 0.0, 1.0],  # far right of the image
        [0.0, -3.0, 1.0],  # above the image
        [0.05, 0.05, 1.0],  # u = 6.0, v = 4.0: exact pixel
        [0.0, 0.0, 1.0],  # u = 5.5, v = 3.5: exact half pixels, round half to even -> (6, 4)
        [-0.1, -0.1, 1.0],  # u = 4.5, v = 2.5 -> (4, 2)
        [-0.55, -0.35, 1.0],  # u = 0.0, v = 0.0: the first pixel
        [0.6, 0.4, 1.0],  # u = 11.5 -> 12 (even): just outside
    ]
    return np.vstack([points, np.asarray(edge)])


def test_project_to_pixels_matches_reference_with_edge_cases() -> None:
    points = _edge_points(np.random.default_rng(3))
    index, ok = project_to_pixels(points, CAM)
    expected = np.array([_ref_pixel(p) for p in points])
    np.testing.assert_array_equal(ok, expected >= 0)
    np.testing.assert_array_equal(index, np.maximum(expected, 0))
    # The hand-made cases: behind, on the plane, NaN, outside right/top, then the rounding cases.
    assert not ok[200:205].any()
    assert list(index[205:209]) == [4 * 12 + 6, 4 * 12 + 6, 2 * 12 + 4, 0]
    assert not ok[209]


def test_lookup_matches_reference() -> None:
    rng = np.random.default_rng(4)
    points = _edge_points(rng)
    pose = _pose(7.0, (0.3, -0.1, 0.2))
    ref_valid = rng.random(CAM.width * CAM.height) < 0.7
    found = lookup(points, pose, CAM, ref_valid)
    ties = 0
    for k, p in enumerate(points):
        moved = _apply(pose, p)
        if _pixel_doubtful(moved):  # a rounding tie: either neighbour may be found (module docstring)
            ties += 1
            continue
        pixel = _ref_pixel(moved)
        assert found.ok[k] == (pixel >= 0 and ref_valid[pixel])
        if found.ok[k]:
            assert found.ref_index[k] == pixel
        if np.all(np.isfinite(moved)):
            np.testing.assert_allclose(found.points_in_ref[k], moved, rtol=1e-12, atol=1e-12)
    assert 20 < found.ok.sum() < len(points) and ties <= 2


def test_splat_all_and_nearest_match_reference_with_ties() -> None:
    rng = np.random.default_rng(5)
    points = _edge_points(rng)
    pose = _pose(-5.0, (0.1, 0.0, -0.2))
    # Two coincident points nearer than any random one: a z-buffer tie (the later one is kept); a farther third.
    # The coincident pair is one transformed point twice: two rows of one BLAS product may differ in the last bit.
    tie_in_query = np.array([[0.03, 0.015, 0.3], [0.036, 0.018, 0.36]])
    tie = (np.linalg.inv(pose) @ np.c_[tie_in_query, np.ones(2)].T).T[[0, 0, 1], :3]
    points = np.vstack([points, tie])
    # The pixel and the depth order of each splat are the same on every CPU: no rounding tie, and no two distinct
    # points at one pixel within DOUBT of each other's depth (module docstring).
    moved = np.array([_apply(pose, p) for p in points])
    assert not any(_pixel_doubtful(m) for m in moved)
    pixel_of = np.array([_ref_pixel(m) for m in moved])
    for pixel in set(pixel_of[pixel_of >= 0].tolist()):
        depths = np.unique(moved[pixel_of == pixel, 2])  # coincident points count once
        assert depths.size < 2 or np.min(np.diff(depths) / depths[:-1]) > DOUBT
    source = np.arange(len(points), dtype=np.int64) * 3 + 1  # any labels, distinct from the row numbers
    splat = splat_all(points, source, pose, CAM)
    expected = [(_ref_pixel(_apply(pose, p)), _apply(pose, p)[2], s) for p, s in zip(points, source, strict=True)]
    expected = [e for e in expected if e[0] >= 0]
    np.testing.assert_array_equal(splat.query_index, [e[0] for e in expected])
    np.testing.assert_allclose(splat.depth, [e[1] for e in expected], rtol=1e-12)
    np.testing.assert_array_equal(splat.source, [e[2] for e in expected])

    nearest = splat_nearest(points, source, pose, CAM)
    best: dict[int, tuple[float, int]] = {}
    for pixel, depth, s in expected:
        if pixel not in best or depth <= best[pixel][0]:
            best[pixel] = (depth, s)
    want = np.full(CAM.width * CAM.height, -1)
    for pixel, (_, s) in best.items():
        want[pixel] = s
    np.testing.assert_array_equal(nearest, want)
    tie_pixel = _ref_pixel(_apply(pose, tie[0]))
    assert nearest[tie_pixel] == source[-2]  # the later of the two coincident points, not the farther third


# ---------------------------------------------------------------------------------------------------------------------
# Uncertainty and tolerance.


def test_u_matches_eigenvalues_of_inverted_information() -> None:
    rng = np.random.default_rng(6)
    points = _edge_points(rng)
    u = largest_covariance_eigenvalue(points, CAM, SIGMA_PX)
    for k, p in enumerate(points):
        if np.all(np.isfinite(p)) and p[2] > 0:
            assert u[k] == pytest.approx(_ref_u(p), rel=1e-7)
        else:
            assert np.isnan(u[k])
    # float32 points (as views store them) give the u of the float32 values.
    u32 = largest_covariance_eigenvalue(points[:50].astype(np.float32), CAM, SIGMA_PX)
    np.testing.assert_allclose(u32, [_ref_u(p) for p in points[:50].astype(np.float32)], rtol=1e-7)


@pytest.mark.parametrize("mode", ["query", "smaller", "sum"])
def test_within_tolerance_matches_full_matrix_reference(mode: str) -> None:
    rng = np.random.default_rng(7)
    ref_from_query = _pose(12.0, (0.6, 0.1, 0.3))
    x_q = np.stack([rng.uniform(-1, 1, 300), rng.uniform(-0.5, 0.5, 300), rng.uniform(1.0, 5.0, 300)], axis=-1)
    # Reference points near X_q: offsets of a few standard deviations, so both outcomes occur.
    scale = np.sqrt([_ref_u(p) for p in x_q])[:, None]
    x_r_in_q = x_q + rng.normal(0.0, 1.0, x_q.shape) * scale * rng.uniform(0.05, 1.5, (300, 1))
    x_r = (ref_from_query[:3, :3] @ x_r_in_q.T).T + ref_from_query[:3, 3]
    u_q = np.array([_ref_u(p) for p in x_q])
    u_r = np.array([_ref_u(p) for p in x_r])
    got = within_tolerance(mode, x_q, x_r, x_r_in_q, ref_from_query, u_q, u_r, CAM, SIGMA_PX, SIGMA_MAX)
    m2 = np.array([_ref_tolerance_sq(mode, q, r, ref_from_query) for q, r in zip(x_q, x_r, strict=True)])
    clear = np.abs(m2 - SIGMA_MAX**2) > 1e-6 * SIGMA_MAX**2
    np.testing.assert_array_equal(got[clear], (m2 <= SIGMA_MAX**2)[clear])
    assert 10 < got.sum() < 290


def test_observation_angle_matches_reference() -> None:
    rng = np.random.default_rng(8)
    points = rng.normal(0.0, 3.0, (100, 3))
    a, b = np.array([0.25, 0.0, 0.0]), np.array([1.5, -0.2, 0.4])
    got = observation_angle_deg(points, a, b)
    np.testing.assert_allclose(got, [_ref_angle(p, a, b) for p in points], rtol=1e-10, atol=1e-9)


# ---------------------------------------------------------------------------------------------------------------------
# Stage 1 and Stage 3 kernels.


@pytest.mark.parametrize("mode", ["smaller", "sum", "query"])
def test_support_bits_match_reference(mode: str) -> None:
    views = _views(seed=11)
    total_set = 0
    for query in views:
        for ref in views:
            if ref is query:
                continue
            got = support_bits(
                query, ref, CAM, alpha_min_deg=10.0, sigma_max=SIGMA_MAX, sigma_px=SIGMA_PX, tolerance=mode
            )
            _assert_equal_unless_doubtful(got, *_ref_support_bits(query, ref, mode, 10.0))
            total_set += int(np.count_nonzero(got))
    assert total_set > 20  # the scenes do produce support, so equality is not vacuous


def test_update_support_is_both_directions_of_support_bits() -> None:
    views = _views(seed=12)
    new, others = views[-1], views[:-1]
    expected_new = np.zeros_like(new.support_bits)
    doubtful_new = np.zeros(new.valid.size, dtype=bool)
    expected_others = [v.support_bits.copy() for v in others]
    doubtful_others = [np.zeros(v.valid.size, dtype=bool) for v in others]
    kw = {"alpha_min_deg": 10.0, "sigma_max": SIGMA_MAX, "sigma_px": SIGMA_PX, "tolerance": "smaller"}
    for k, other in enumerate(others):
        bits, doubtful = _ref_support_bits(new, other, "smaller", 10.0)
        expected_new |= bits
        doubtful_new |= doubtful
        bits, doubtful = _ref_support_bits(other, new, "smaller", 10.0)
        expected_others[k] |= bits
        doubtful_others[k] |= doubtful
    update_support(new, others, CAM, **kw)
    _assert_equal_unless_doubtful(new.support_bits, expected_new, doubtful_new)
    for other, expected, doubtful in zip(others, expected_others, doubtful_others, strict=True):
        _assert_equal_unless_doubtful(other.support_bits, expected, doubtful)


@pytest.mark.parametrize("min_votes", [1, 2])
def test_augmented_depth_matches_reference(min_votes: int) -> None:
    views = _views(seed=13, noise=0.6)
    query, refs = views[0], views[1:]
    rng = np.random.default_rng(14)
    pending = query.valid & (rng.random(query.valid.size) < 0.8)
    got = augmented_depth(
        query,
        refs,
        pending,
        CAM,
        sigma_max=SIGMA_MAX,
        sigma_px=SIGMA_PX,
        reading="std",
        min_positive_votes=min_votes,
    )
    want, doubtful = _ref_augmented_depth(query, refs, pending, min_votes)
    _assert_equal_unless_doubtful(np.isnan(got), np.isnan(want), doubtful)
    both = ~doubtful & ~np.isnan(want)
    np.testing.assert_allclose(got[both], want[both], rtol=1e-12)
    assert np.count_nonzero(~np.isnan(got)) > 10
    assert np.all(np.isnan(got[~pending]))


def test_augmented_depth_prefers_the_nearest_valid_candidate_over_a_nearer_invalid_one() -> None:
    """A lone near point splatted by one view is rejected by the others; the agreed surface behind it wins."""
    views = _views(seed=15, noise=0.0)
    query, refs = views[0], views[1:]
    # Put one reference measurement far in front of the plane: its splat is the nearest candidate somewhere.
    j = int(np.flatnonzero(refs[0].valid)[len(np.flatnonzero(refs[0].valid)) // 2])
    refs[0].points[j] *= np.float32(0.5)
    pending = query.valid.copy()
    got = augmented_depth(
        query, refs, pending, CAM, sigma_max=SIGMA_MAX, sigma_px=SIGMA_PX, reading="std", min_positive_votes=2
    )
    want, doubtful = _ref_augmented_depth(query, refs, pending, 2)
    _assert_equal_unless_doubtful(np.isnan(got), np.isnan(want), doubtful)
    both = ~doubtful & ~np.isnan(want)
    np.testing.assert_allclose(got[both], want[both], rtol=1e-12)
    hit = _ref_pixel(_apply(np.linalg.inv(query.pose) @ refs[0].pose, refs[0].points[j]))
    if hit >= 0 and pending[hit]:
        near = float(_apply(np.linalg.inv(query.pose) @ refs[0].pose, refs[0].points[j])[2])
        assert np.isnan(got[hit]) or got[hit] > near
