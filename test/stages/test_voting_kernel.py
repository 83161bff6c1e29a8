"""Stage 2's compiled kernels (and the pre-tests they share with Stage 1) against slow Python references.

The scenes are small (64x48): a back wall and a box in front of it, rendered exactly from poses on an arc,
then spoiled on purpose (disparity noise, gross errors, unsupported pixels) so that every branch of the vote
happens: positives, occlusions, free-space violations, outlines that suppress them, the band between the two
tolerances, and less accurate references.

The slow reference decides with the package's own projection and tolerance functions, which the kernels share
(same arithmetic, same bits), except for the observation angle and the occlusion's range comparison, which it
computes with numpy (BLAS dot products, whose kernels differ per CPU). Those two decisions may go either way on
another machine when they lie within :data:`DOUBT` of their threshold; the comparison leaves such pixels out
(there are none in the scene: its margins are 3e-6 and more) and requires them to stay rare.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.projection import project_to_pixels, transform
from selfcontra_ros.stages import kernels
from selfcontra_ros.stages._common import tolerance_sq
from selfcontra_ros.stages.outliers import augmented_depth
from selfcontra_ros.stages.voting import consistency_voting, fattening_band
from selfcontra_ros.window import View, make_view, support_count

CAMERA = StereoCamera(fx=120.0, fy=120.0, cx=31.5, cy=23.5, baseline=1.0, width=64, height=48)
TARGET = np.array([0.0, 0.0, 8.0])
WALL_Z = 8.0
#: Box front face: z, x range, y range (world, metres).
BOX = (5.0, (-0.5, 0.2), (-0.3, 0.4))
#: Relative distance to a threshold within which the reference's numpy decisions count as ties (module docstring):
#: far above the 1e-15 by which numpy and the kernels round differently, far below the scene's margins.
DOUBT = 1e-9


def _pose(theta_deg: float, radius: float = 7.0) -> np.ndarray:
    """Camera on a horizontal arc around TARGET, looking at it."""
    t = np.radians(theta_deg)
    position = TARGET + radius * np.array([np.sin(t), 0.0, -np.cos(t)])
    z = (TARGET - position) / radius
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = position
    return pose


def _render_depth(pose: np.ndarray) -> np.ndarray:
    """Exact depth (HxW, metres) of the wall ``z = WALL_Z`` and the box's front face seen from ``pose``."""
    u, v = np.meshgrid(np.arange(CAMERA.width, dtype=float), np.arange(CAMERA.height, dtype=float))
    rays = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u)], axis=-1)
    world_dir = rays @ pose[:3, :3].T  # world direction per unit of camera depth
    depth = (WALL_Z - pose[2, 3]) / world_dir[..., 2]
    box_z, (x0, x1), (y0, y1) = BOX
    t = (box_z - pose[2, 3]) / world_dir[..., 2]
    hit = pose[:3, 3] + t[..., None] * world_dir
    on_box = (t > 0) & (hit[..., 0] >= x0) & (hit[..., 0] <= x1) & (hit[..., 1] >= y0) & (hit[..., 1] <= y1)
    return np.where(on_box & (t < depth), t, depth)


def _view(theta_deg: float, index: int, rng: np.random.Generator, *, radius: float = 7.0) -> View:
    """A view with noisy disparity, gross errors (pixels and patches), invalid pixels and random Stage-1 support."""
    pose = _pose(theta_deg, radius)
    disparity = CAMERA.depth_to_disparity(_render_depth(pose))
    disparity = disparity + rng.normal(0.0, 0.15, disparity.shape)
    gross = rng.random(disparity.shape) < 0.03
    disparity[gross] *= rng.uniform(0.6, 1.6, int(gross.sum()))
    for _ in range(8):  # patches of wrong depth, too wide for the outline test to excuse
        row, col = rng.integers(0, CAMERA.height - 6), rng.integers(0, CAMERA.width - 6)
        disparity[row : row + 7, col : col + 7] *= rng.choice([0.6, 0.75, 1.4])
    disparity[rng.random(disparity.shape) < 0.03] = np.nan
    view = make_view(CAMERA, disparity, pose, index=index, key=index, stamp=0.0, sigma_px=1.0)
    bits = rng.integers(0, 8, view.valid.size).astype(np.uint64)  # 0 (unsupported) for one pixel in eight
    view.support_bits[:] = bits
    return view


def _scene(seed: int) -> tuple[View, list[View]]:
    rng = np.random.default_rng(seed)
    query = _view(0.0, 0, rng)
    refs = [
        _view(theta, k + 1, rng, radius=radius)
        for k, (theta, radius) in enumerate([(-14.0, 6.0), (9.0, 7.5), (23.0, 5.5), (-4.0, 9.0)])
    ]
    return query, refs


def _tol_sq(mode: str, query: View, ref: View, q: int, x_r: np.ndarray, u_r: float) -> float:
    """Squared tolerance distance of reference point ``x_r`` (reference frame) from query pixel ``q``'s point."""
    x_q = query.points[q].astype(np.float64)[None]
    in_q = transform(query.from_view(ref), x_r[None])
    return float(
        tolerance_sq(
            mode, x_q, x_r[None], in_q, ref.from_view(query), query.u[q : q + 1], np.array([u_r]), CAMERA, 1.0
        )[0]
    )


def _slow_splat(query: View, ref: View, left_out: np.ndarray | None = None) -> dict[int, int]:
    """Brute-force z-buffer: query pixel -> reference pixel of the nearest supported valid point (later wins ties).

    ``left_out`` (flat bool): reference pixels kept out of the z-buffer.
    """
    in_q = transform(query.from_view(ref), ref.points)
    pixel, ok = project_to_pixels(in_q, CAMERA)
    nearest: dict[int, int] = {}
    for s in range(ref.valid.size):
        if left_out is not None and left_out[s]:
            continue
        if ref.valid[s] and ref.support_bits[s] != 0 and ok[s]:
            p = int(pixel[s])
            if p not in nearest or in_q[s, 2] <= in_q[nearest[p], 2]:
                nearest[p] = s
    return nearest


def _slow_votes(
    query: View,
    ref: View,
    *,
    tolerance: str,
    sigma_max: float = 2.0,
    positive_sigma: float,
    negative_sigma: float,
    min_angle_deg: float,
    negatives_from_any: bool | np.ndarray,
    free_space: bool,
    radius: int,
    band_px: float = 0.0,
    occlusion_votes: bool | np.ndarray = True,
) -> tuple[np.ndarray, np.ndarray]:
    """One reference's vote per query pixel, pixel by pixel, as DESIGN section 3 states the rules.

    ``negatives_from_any``: for every query pixel, or per query pixel (flat bool), whether any supported
    reference measurement may vote negative. ``occlusion_votes``: likewise, whether an occlusion found by the
    lookup votes (elsewhere it decides the reference's vote as no vote). ``band_px > 0``: the reference's
    fattening band with that jump (16 px to the left, 3 elsewhere) is kept out of the free-space z-buffer.
    Returns the votes and the pixels whose angle or range comparison was a tie (module docstring).
    """
    from_any = np.broadcast_to(np.asarray(negatives_from_any, dtype=bool), query.valid.shape)
    occluding = np.broadcast_to(np.asarray(occlusion_votes, dtype=bool), query.valid.shape)
    votes = np.zeros(query.valid.size)
    doubtful = np.zeros(query.valid.size, dtype=bool)
    ref_from_query = ref.from_view(query)
    support = support_count(ref.support_bits)
    band = None
    if band_px > 0:
        band = _band(ref, band_px)
    nearest = _slow_splat(query, ref, band) if free_space else {}
    centre_q = np.array([0.5 * CAMERA.baseline, 0.0, 0.0])
    centre_r = transform(query.pose_inv, ref.centre[None])[0]
    for q in np.flatnonzero(query.valid):
        x_q = query.points[q].astype(np.float64)
        u_q = float(query.u[q])
        vote: float | None = None  # None: the lookup did not decide this reference's vote
        x_in_r = transform(ref_from_query, x_q[None])
        pixel, ok = project_to_pixels(x_in_r, CAMERA)
        j = int(pixel[0])
        if ok[0] and ref.valid[j] and support[j] >= 1:
            u_r = float(ref.u[j])
            accurate = u_r < u_q
            if accurate or from_any[q]:
                x_r = ref.points[j].astype(np.float64)
                distance = math.sqrt(_tol_sq(tolerance, query, ref, q, x_r, u_r))
                weight = float(support[j]) / math.sqrt(u_r)
                range_q, range_r = np.linalg.norm(x_in_r[0]), np.linalg.norm(x_r)
                if distance <= positive_sigma and accurate:
                    a, b = centre_r - x_q, centre_q - x_q
                    angle = math.degrees(math.acos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1)))
                    doubtful[q] = min_angle_deg > 0 and abs(angle - min_angle_deg) <= DOUBT * min_angle_deg
                    vote = weight if min_angle_deg <= 0 or angle > min_angle_deg else 0.0
                elif distance > negative_sigma and range_q < range_r:
                    doubtful[q] = range_r - range_q <= DOUBT * range_r
                    vote = -weight if occluding[q] else 0.0  # occlusion: X_q blocks the reference's line of sight
                elif distance <= negative_sigma and accurate:
                    vote = 0.0  # agrees roughly: decided, no vote
                elif distance > negative_sigma:
                    doubtful[q] = range_q - range_r <= DOUBT * range_r  # just not an occlusion
        if vote is None and q in nearest:
            s = nearest[q]
            u_s = float(ref.u[s])
            x_s = ref.points[s].astype(np.float64)
            in_front = transform(query.from_view(ref), x_s[None])[0, 2] < x_q[2]
            # The free-space test and its outline check use sigma_max, not the hysteresis band.
            far = not math.sqrt(_tol_sq(tolerance, query, ref, q, x_s, u_s)) <= sigma_max
            if (u_s < u_q or from_any[q]) and in_front and far:
                row, col = divmod(int(q), CAMERA.width)
                outline = False
                for r in range(max(row - radius, 0), min(row + radius, CAMERA.height - 1) + 1):
                    for c in range(max(col - radius, 0), min(col + radius, CAMERA.width - 1) + 1):
                        k = r * CAMERA.width + c
                        if k != q and query.valid[k]:
                            outline |= math.sqrt(_tol_sq(tolerance, query, ref, k, x_s, u_s)) <= sigma_max
                if not outline:
                    vote = -float(support[s]) / math.sqrt(u_s)  # free-space violation
        votes[q] = 0.0 if vote is None else vote
    return votes, doubtful


def _band(view: View, jump_px: float) -> np.ndarray:
    """The view's fattening band (flat), as the labeler computes it (16 px to the left, 3 px elsewhere)."""
    shape = (CAMERA.height, CAMERA.width)
    return fattening_band(view.disparity.reshape(shape), jump_px=jump_px, occluded_side_px=16, other_px=3).ravel()


OPTIONS = [
    pytest.param({}, id="defaults"),
    pytest.param({"tolerance": "query"}, id="query-tolerance"),
    pytest.param({"tolerance": "smaller", "voters": "any"}, id="smaller-any"),
    pytest.param({"min_angle_deg": 12.0}, id="min-angle"),
    pytest.param({"free_space": False}, id="no-free-space"),
    pytest.param({"band_px": 4.0}, id="reference-band"),
    pytest.param({"band_px": 4.0, "voters": "band"}, id="band-voters"),
    pytest.param({"band_px": 4.0, "voters": "band", "min_views": 2}, id="free-space-min-views"),
    pytest.param({"min_views": 2}, id="free-space-min-views-no-band"),
    pytest.param({"band_px": 4.0, "voters": "any", "occlusion": "band"}, id="occlusion-votes-in-band"),
    pytest.param({"band_px": 4.0, "voters": "band", "band_views": 2}, id="band-min-negative-views"),
    pytest.param({"band_px": 4.0, "voters": "band", "min_views": 2, "band_views": 3}, id="band-views-and-min-views"),
    pytest.param({"radius": 0, "positive_sigma": 2.0, "negative_sigma": 2.0}, id="paper"),
]


@pytest.mark.parametrize("options", OPTIONS)
def test_consistency_voting_matches_slow_reference(options: dict) -> None:
    query, refs = _scene(seed=3)
    o = {
        "tolerance": "sum",
        "positive_sigma": 1.5,
        "negative_sigma": 3.0,
        "min_angle_deg": 0.0,
        "voters": "more_accurate",
        "free_space": True,
        "radius": 2,
        "band_px": 0.0,
        "min_views": 1,
        "occlusion": "everywhere",
        "band_views": 1,
    } | options
    band_views = o.pop("band_views")
    voters = o.pop("voters")
    min_views = o.pop("min_views")
    occlusion = o.pop("occlusion")
    # Where any reference may vote negative: everywhere, nowhere, or in the query's own fattening band.
    from_any = {"any": True, "more_accurate": False}.get(voters, False)
    if voters == "band":
        from_any = _band(query, o["band_px"])
        assert from_any.sum() > 50  # the band must hold enough pixels for the test to mean something
    # Where a lookup's occlusion votes: everywhere, or in the query's own fattening band.
    occluding = _band(query, o["band_px"]) if occlusion == "band" else True
    silenced = 0  # occlusion votes the band leaves out
    expected_sum = np.zeros(query.valid.size)
    expected_voted = np.zeros(query.valid.size, dtype=bool)
    doubtful = np.zeros(query.valid.size, dtype=bool)
    free_space_sum = np.zeros(query.valid.size)
    free_space_views = np.zeros(query.valid.size, dtype=int)
    negative_views = np.zeros(query.valid.size, dtype=int)  # references voting negative, lookup or free space
    for ref in refs:  # in window order, as the votes are summed
        votes, ties = _slow_votes(query, ref, **o, negatives_from_any=from_any, occlusion_votes=occluding)
        # A pixel's free-space vote is what the splat adds where the lookup left it undecided.
        lookup_only = o | {"free_space": False}
        lookup, _ = _slow_votes(query, ref, **lookup_only, negatives_from_any=from_any, occlusion_votes=occluding)
        if occlusion == "band":
            silenced += int((_slow_votes(query, ref, **lookup_only, negatives_from_any=from_any)[0] != lookup).sum())
        free_space_sum += votes - lookup
        free_space_views += votes != lookup
        negative_views += votes < 0
        expected_sum += lookup
        expected_voted |= lookup != 0
        doubtful |= ties
    # Free-space votes count where enough views cast them, or anywhere in the query's own band.
    enough = free_space_views >= min_views
    if o["band_px"] > 0:
        enough |= _band(query, o["band_px"])
    expected_sum += np.where(enough, free_space_sum, 0.0)
    expected_voted |= enough & (free_space_views > 0)
    if min_views > 1:  # the case must drop some free-space votes and keep others
        assert ((free_space_views > 0) & ~enough).sum() > 5 and (enough & (free_space_views > 0)).sum() > 2
    result = consistency_voting(
        query,
        refs,
        CAMERA,
        sigma_max=2.0,
        sigma_px=1.0,
        tolerance=o["tolerance"],
        min_angle_deg=o["min_angle_deg"],
        negative_voters=voters,
        free_space_votes=o["free_space"],
        free_space_neighbourhood=o["radius"],
        positive_sigma=o["positive_sigma"],
        negative_sigma=o["negative_sigma"],
        edge_jump_px=o["band_px"],
        edge_occluded_side_px=16,
        edge_other_px=3,
        free_space_band=o["band_px"] > 0,
        free_space_min_views=min_views,
        occlusion_votes=occlusion,
        band_min_negative_views=band_views,
    )
    if occlusion == "band":  # the case must leave some occlusion votes out
        assert silenced > 5
    assert doubtful.mean() < 0.01, f"{int(doubtful.sum())} pixels decided at a tie"
    clear = ~doubtful
    np.testing.assert_array_equal(result.voted[clear], expected_voted[clear])
    np.testing.assert_allclose(result.vote_sum[clear], expected_sum[clear], rtol=1e-12, atol=0.0)
    expected_labels = np.where(expected_sum > 0, POSITIVE, np.where(expected_sum < 0, NEGATIVE, UNKNOWN))
    if o["band_px"] > 0:  # the query's own band is never positive (edge_jump_px)
        expected_labels[(expected_labels == POSITIVE) & _band(query, o["band_px"])] = UNKNOWN
    if band_views > 1:  # ... and negative in it only where enough references voted against it
        held_back = (expected_labels == NEGATIVE) & _band(query, o["band_px"]) & (negative_views < band_views)
        assert held_back.sum() > 5 and ((expected_labels == NEGATIVE) & ~held_back).sum() > 5
        expected_labels[held_back] = UNKNOWN
    np.testing.assert_array_equal(result.labels[clear], np.where(expected_voted, expected_labels, UNKNOWN)[clear])
    # The scene must exercise both signs, or the comparison proves little.
    assert (expected_sum > 0).sum() > 50 and (expected_sum < 0).sum() > 10


def test_scene_exercises_every_kind_of_vote() -> None:
    """Free-space votes and their outline suppression both occur in the test scene (not only lookup votes)."""
    query, refs = _scene(seed=3)
    base = {"tolerance": "sum", "positive_sigma": 1.5, "negative_sigma": 3.0, "min_angle_deg": 0.0}
    ref = refs[2]
    lookup_only, _ = _slow_votes(query, ref, **base, negatives_from_any=False, free_space=False, radius=0)
    with_splat, _ = _slow_votes(query, ref, **base, negatives_from_any=False, free_space=True, radius=0)
    with_outline, _ = _slow_votes(query, ref, **base, negatives_from_any=False, free_space=True, radius=2)
    free_space = (with_splat < 0) & (lookup_only == 0)
    assert free_space.sum() > 5
    assert ((with_outline == 0) & free_space).sum() > 0  # some suppressed as outlines
    assert ((with_outline < 0) & free_space).sum() > 0  # and some not
    # The reference's fattening band holds free-space voters, and keeping it out silences some of them.
    with_band, _ = _slow_votes(query, ref, **base, negatives_from_any=False, free_space=True, radius=2, band_px=4.0)
    assert _band(ref, 4.0).sum() > 0
    assert ((with_outline < 0) & (with_band == 0)).sum() > 0
    # Voters of any accuracy in the query's own band add negatives there, and nowhere else.
    query_band = _band(query, 4.0)
    band_any = dict(base, free_space=True, radius=2, band_px=4.0)
    accurate_only = sum(_slow_votes(query, r, **band_any, negatives_from_any=False)[0] for r in refs)
    in_band_any = sum(_slow_votes(query, r, **band_any, negatives_from_any=query_band)[0] for r in refs)
    assert ((in_band_any < 0) & (accurate_only >= 0)).sum() > 20
    np.testing.assert_array_equal(in_band_any[~query_band], accurate_only[~query_band])


@pytest.mark.parametrize("share_needed", [1.0, 0.3])
def test_splat_supported_kernel_matches_brute_force_zbuffer(share_needed: float) -> None:
    query, refs = _scene(seed=5)
    need = np.random.default_rng(1).random(query.valid.size) < share_needed
    for ref in refs:
        source = kernels.splat_supported_kernel(
            ref.points,
            ref.valid,
            ref.support_bits,
            query.from_view(ref),
            need,
            CAMERA.fx,
            CAMERA.fy,
            CAMERA.cx,
            CAMERA.cy,
            CAMERA.width,
            CAMERA.height,
        )
        expected = np.full(query.valid.size, -1)
        for pixel, s in _slow_splat(query, ref).items():
            if need[pixel]:
                expected[pixel] = s
        np.testing.assert_array_equal(source, expected)
        assert (source >= 0).sum() > 50


def test_support_count_scalar_counts_bits() -> None:
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2**63, 500, dtype=np.uint64) >> rng.integers(0, 64, 500).astype(np.uint64)
    bits[:3] = [0, 1, np.uint64(2**64 - 1)]
    counts = [kernels.support_count_scalar(b) for b in bits]
    assert counts[:3] == [0, 1, 64]
    np.testing.assert_array_equal(counts, support_count(bits))


# Stage 3 reuses per-thread work buffers between calls: results must not depend on what ran before.


def _augmented(query: View, refs: list[View]) -> np.ndarray:
    return augmented_depth(
        query, refs, query.valid.copy(), CAMERA, sigma_max=2.0, sigma_px=1.0, reading="std", min_positive_votes=2
    )


def _augmented_in_fresh_thread(query: View, refs: list[View]) -> np.ndarray:
    """The result computed by a new thread, whose buffers start empty."""
    out: list[np.ndarray] = []
    thread = threading.Thread(target=lambda: out.append(_augmented(query, refs)))
    thread.start()
    thread.join()
    return out[0]


def test_augmented_depth_does_not_depend_on_earlier_calls() -> None:
    query, refs = _scene(seed=7)
    other_query, other_refs = _scene(seed=8)
    # Buffers sized by another scene first, then sliced for fewer views, then grown again.
    _augmented(other_query, other_refs)
    few = _augmented(query, refs[:2])
    every = _augmented(query, refs)
    again = _augmented(query, refs[:2])
    np.testing.assert_array_equal(few, again)
    np.testing.assert_array_equal(few, _augmented_in_fresh_thread(query, refs[:2]))
    np.testing.assert_array_equal(every, _augmented_in_fresh_thread(query, refs))
    assert np.isfinite(every).sum() > 100  # the comparison covers validated candidates
    assert not np.array_equal(few, every, equal_nan=True)  # and the two windows differ


@pytest.mark.parametrize("mode", [kernels.MODE_QUERY, kernels.MODE_SMALLER, kernels.MODE_SUM])
def test_capped_tolerance_rejects_only_what_the_exact_test_rejects(mode: int) -> None:
    """The cheap bound of the capped test never hides a distance within the cap; below it the value is exact."""
    query, refs = _scene(seed=11)
    ref = refs[0]
    ref_from_query, query_from_ref = ref.from_view(query), query.from_view(ref)
    rng = np.random.default_rng(2)
    q_index = rng.choice(np.flatnonzero(query.valid), 1500)
    r_index = rng.choice(np.flatnonzero(ref.valid), 1500)
    rejected = 0
    for cap in (2.25, 4.0, 9.0):
        for q, r in zip(q_index, r_index, strict=True):
            x_q = query.points[q].astype(np.float64)
            x_r = ref.points[r].astype(np.float64)
            if q % 2:  # about half the pairs: a point close to X_q instead of a random reference point
                x_r = transform(ref_from_query, (x_q + rng.normal(0.0, 0.3, 3))[None])[0]
            x_rq = transform(query_from_ref, x_r[None])[0]
            args = (mode, *x_q, *x_r, *x_rq, ref_from_query, float(query.u[q]), float(ref.u[r]))
            camera = (CAMERA.fx, CAMERA.fy, CAMERA.baseline, 1.0)
            exact = kernels.tolerance_sq_scalar(*args, *camera)
            capped = kernels.tolerance_sq_capped_scalar(*args, *camera, cap)
            if np.isinf(capped):
                rejected += 1
                assert exact > cap
            else:
                assert capped == exact
    assert 100 < rejected < 3 * 1500 - 100  # both branches taken


@pytest.mark.parametrize("alpha_min_deg", [10.0, 45.0, 120.0])
def test_angle_surely_above_accepts_only_angles_above_alpha_min(alpha_min_deg: float) -> None:
    """Stage 1 defers the exact angle where the cheap test is sure; it must never be wrong, and often be sure."""
    rng = np.random.default_rng(4)
    cos_accept = math.cos(math.radians(alpha_min_deg)) - 1e-9
    sure = 0
    for _ in range(4000):
        point, centre_a, centre_b = rng.normal(0.0, 3.0, 3), rng.normal(0.0, 3.0, 3), rng.normal(0.0, 3.0, 3)
        a, b = centre_a - point, centre_b - point
        angle = math.degrees(math.acos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0)))
        if kernels._angle_surely_above(*point, centre_a, centre_b, cos_accept):
            sure += 1
            assert angle > alpha_min_deg
        elif abs(angle - alpha_min_deg) > 1e-6:
            assert angle < alpha_min_deg  # not sure only near or below the threshold
    assert sure > 200
