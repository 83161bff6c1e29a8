"""The labeler on analytic scenes: a wall and a floor seen from an arc of stereo poses.

Depth is rendered exactly by ray-plane intersection, so every expectation is
known: perfect depth is consistent, depth pushed in front of or behind the
surface contradicts the other views, a part of the wall seen from one
direction only cannot be labelled, and views closer than ``alpha_min`` give no
support.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from selfcontra_ros.geometry import StereoCamera, transform_points
from selfcontra_ros.labeler import Labeler, LabelerParams, LabelResult
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.stages.voting import contradicted_positives

CAMERA = StereoCamera(fx=200.0, fy=200.0, cx=79.5, cy=59.5, baseline=0.5, width=160, height=120)
WALL_Z = 10.0
FLOOR_Y = 1.5
TARGET = np.array([0.0, 0.3, WALL_Z])
# (normal, offset) of the planes n . X = c, world frame (y down, like the optical frames).
PLANES = ((np.array([0.0, 0.0, 1.0]), WALL_Z), (np.array([0.0, 1.0, 0.0]), FLOOR_Y))


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_world_left`` of a camera at ``position`` looking at ``target`` with image rows pointing down (+y)."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = position
    return pose


def orbit_pose(theta_deg: float, radius: float = 8.0) -> np.ndarray:
    """Pose on a horizontal arc around TARGET, ``theta_deg`` from straight on."""
    t = np.radians(theta_deg)
    return look_at(TARGET + radius * np.array([np.sin(t), 0.0, -np.cos(t)]), TARGET)


def render_depth(pose: np.ndarray, planes: tuple[tuple[np.ndarray, float], ...] = PLANES) -> np.ndarray:
    """Exact depth (HxW, metres) of the nearest plane along each left-camera ray."""
    u, v = np.meshgrid(np.arange(CAMERA.width, dtype=float), np.arange(CAMERA.height, dtype=float))
    rays = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u)], axis=-1)
    directions = rays @ pose[:3, :3].T
    depth = np.full(u.shape, np.inf)
    for normal, offset in planes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (offset - normal @ pose[:3, 3]) / (directions @ normal)
        depth = np.where((t > 0) & (t < depth), t, depth)
    return depth


def world_points(pose: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    return transform_points(pose, CAMERA.backproject(disparity))


def run(disparities: list[np.ndarray], poses: list[np.ndarray], params: LabelerParams) -> list[LabelResult]:
    labeler = Labeler(CAMERA, params)
    results: list[LabelResult] = []
    for i, (disp, pose) in enumerate(zip(disparities, poses, strict=True)):
        results += labeler.add_view(disp, pose, stamp=100.0 + i, key=i)
    results += labeler.flush()
    return results


ANGLES = (-36.0, -24.0, -12.0, 0.0, 12.0, 24.0, 36.0)
MIDDLE = 3
PARAMS = LabelerParams(window_size=7, label_delay=3)
#: Without the ambiguity cues (the paper's votes), for the tests of those cues.
PAPER = LabelerParams(
    window_size=7, label_delay=3, ambiguity_min_texture=0.0, ambiguity_edge_px=0.0, ambiguity_saturation=0.0
)


def _middle_result(disparities: list[np.ndarray], poses: list[np.ndarray], params: LabelerParams) -> LabelResult:
    results = {r.key: r for r in run(disparities, poses, params)}
    return results[MIDDLE]


@pytest.fixture(scope="module")
def arc() -> tuple[list[np.ndarray], list[np.ndarray]]:
    poses = [orbit_pose(a) for a in ANGLES]
    return [CAMERA.depth_to_disparity(render_depth(p)) for p in poses], poses


def _inside_right_image(disparity: np.ndarray) -> np.ndarray:
    """Pixels whose disparity keeps them inside the right image (no trivial outlier)."""
    return np.arange(CAMERA.width)[None, :] - disparity >= 0


def test_perfect_depth_gives_positives_and_no_negatives(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    result = _middle_result(disparities, poses, PARAMS)
    inside = _inside_right_image(disparities[MIDDLE])
    assert not np.any((result.labels == NEGATIVE) & inside)
    assert np.mean(result.labels[inside] == POSITIVE) > 0.6
    # The centre of the wall is seen from six directions in three bins.
    assert np.all(result.support[50:70, 70:90] == 3)


def test_patch_in_front_of_surface_is_negative(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    bad = [d.copy() for d in disparities]
    bad[MIDDLE][40:70, 60:100] *= WALL_Z / 6.5  # the wall at ~8 m moved to ~5 m: blocks the other views
    result = _middle_result(bad, poses, PARAMS)
    core = result.labels[45:65, 65:95]
    assert np.mean(core == NEGATIVE) > 0.95
    outside = np.ones(core.shape[:0] + result.labels.shape, dtype=bool)
    outside[35:75, 55:105] = False
    assert not np.any((result.labels == NEGATIVE) & outside & _inside_right_image(bad[MIDDLE]))


def test_stage3_depth_ratio_reaches_the_labeler(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    bad = [d.copy() for d in disparities]
    bad[MIDDLE][40:70, 60:100] *= WALL_Z / 6.5  # the wall lies 1.54 times farther than the patch
    core = (slice(45, 65), slice(65, 95))
    kept = _middle_result(bad, poses, dataclasses.replace(PARAMS, stage3_min_depth_ratio=1.3))
    assert np.mean(kept.labels[core] == NEGATIVE) > 0.95
    stage3 = (kept.labels[core] == NEGATIVE) & (kept.stage2_labels[core] != NEGATIVE)
    assert stage3.mean() > 0.2  # part of the patch is Stage 3's to call
    dropped = _middle_result(bad, poses, dataclasses.replace(PARAMS, stage3_min_depth_ratio=1.7))
    np.testing.assert_array_equal(dropped.labels[core] == NEGATIVE, dropped.stage2_labels[core] == NEGATIVE)
    np.testing.assert_array_equal(dropped.stage2_labels, kept.stage2_labels)


def test_patch_behind_surface_is_negative(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    bad = [d.copy() for d in disparities]
    bad[MIDDLE][40:70, 60:100] *= 0.6  # depth * 1.67: the other views' wall blocks the query's line of sight
    result = _middle_result(bad, poses, PARAMS)
    assert np.mean(result.labels[45:65, 65:95] == NEGATIVE) > 0.95
    assert np.mean(result.stage2_labels[45:65, 65:95] == NEGATIVE) > 0.95


def test_a_confirmed_island_in_a_contradicted_region_abstains(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    bad = [d.copy() for d in disparities]
    bad[MIDDLE][40:70, 60:100] *= WALL_Z / 6.5  # a wrong patch in front of the wall ...
    island = (slice(53, 57), slice(78, 82))
    bad[MIDDLE][island] = disparities[MIDDLE][island]  # ... with a few right pixels inside it
    paper = _middle_result(bad, poses, dataclasses.replace(PARAMS, contradicted_share=1.0))
    result = _middle_result(bad, poses, PARAMS)
    assert np.all(paper.labels[island] == POSITIVE)  # the views confirm the island ...
    assert np.all(result.labels[island] == UNKNOWN)  # ... but it sits in a region they contradict
    # The rule only withholds positives, those of contradicted_positives at fx tan(2.6 deg) = 9 px, where
    # the trivial outliers (matches outside the right image, the left strip here) count as unlabelled.
    assert round(CAMERA.fx * np.tan(np.radians(PARAMS.contradicted_radius_deg))) == 9
    changed = paper.labels != result.labels
    by_views = np.where(_inside_right_image(bad[MIDDLE]), paper.labels, UNKNOWN)
    assert np.any((paper.labels == NEGATIVE) & ~_inside_right_image(bad[MIDDLE]))
    np.testing.assert_array_equal(changed, contradicted_positives(by_views, 9, PARAMS.contradicted_share))
    assert np.all(result.labels[changed] == UNKNOWN)
    # Away from the patch the wall keeps its positives.
    assert np.all(result.labels[:, :40][paper.labels[:, :40] == POSITIVE] == POSITIVE)


def test_region_seen_from_one_direction_stays_unknown(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    region = (-1.0, 0.5, -1.0, 0.2)  # x0, x1, y0, y1 on the wall
    masked = []
    for i, (disp, pose) in enumerate(zip(disparities, poses, strict=True)):
        pts = world_points(pose, disp)
        inside = (pts[..., 0] > region[0]) & (pts[..., 0] < region[1]) & (pts[..., 1] > region[2])
        inside &= pts[..., 1] < region[3]
        masked.append(disp if i == MIDDLE else np.where(inside, np.nan, disp))
    result = _middle_result(masked, poses, PARAMS)
    pts = world_points(poses[MIDDLE], disparities[MIDDLE])
    margin = 0.15
    core = (pts[..., 0] > region[0] + margin) & (pts[..., 0] < region[1] - margin)
    core &= (pts[..., 1] > region[2] + margin) & (pts[..., 1] < region[3] - margin)
    assert core.sum() > 100
    assert np.all(result.labels[core] == UNKNOWN)
    assert np.all(result.support[core] == 0)
    assert np.mean(result.labels[~core & _inside_right_image(disparities[MIDDLE])] == POSITIVE) > 0.5


def test_views_closer_than_alpha_min_give_no_support() -> None:
    # The default alpha_min; the views at most 0.8 of it apart at the wall (the wall alone: a nearby floor
    # would see larger angles).
    params = LabelerParams(window_size=5, label_delay=2, flush_incomplete=True)
    step = 0.2 * params.alpha_min_deg
    poses = [orbit_pose(k * step) for k in (-2, -1, 0, 1, 2)]
    disparities = [CAMERA.depth_to_disparity(render_depth(p, PLANES[:1])) for p in poses]
    results = run(disparities, poses, params)
    assert len(results) == 5
    for result in results:
        assert np.all(result.support == 0)
        assert np.all(result.stage2_labels == UNKNOWN)
        assert np.all(result.vote_sum == 0)
        inside = _inside_right_image(disparities[int(result.key)])
        assert not np.any((result.labels == NEGATIVE) & inside)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("stage2_min_angle_deg", -1.0),
        ("stage2_min_angle_deg", 180.0),
        ("stage2_min_query_support", -1),
        ("stage2_min_query_support", 1.5),
        ("stage2_negative_voters", "all"),
        ("stage2_free_space_votes", "yes"),
        ("stage2_free_space_neighbourhood", -1),
        ("stage2_free_space_neighbourhood", 1.5),
        ("contradicted_share", -0.1),
        ("contradicted_share", 1.5),
        ("contradicted_radius_deg", 0.0),
        ("contradicted_radius_deg", "2"),
        ("range_abstain", 1),
        ("range_margin_px", -1.0),
    ],
)
def test_invalid_stage2_options_are_rejected_by_name(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        LabelerParams.from_dict({field: value})


def _textured_image(flat: tuple[slice, slice] | None = None, value: int = 128) -> np.ndarray:
    """A strongly textured grey image, never clipped (0-254), optionally with one flat rectangle of ``value``."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (CAMERA.height, CAMERA.width)).astype(np.uint8)
    if flat is not None:
        image[flat] = value
    return image


def _run_with_images(
    disparities: list[np.ndarray], poses: list[np.ndarray], images: list[np.ndarray], params: LabelerParams
) -> LabelResult:
    labeler = Labeler(CAMERA, params)
    results: list[LabelResult] = []
    for i, (disp, pose, image) in enumerate(zip(disparities, poses, images, strict=True)):
        results += labeler.add_view(disp, pose, stamp=100.0 + i, key=i, image=image)
    results += labeler.flush()
    return {r.key: r for r in results}[MIDDLE]


def test_ambiguous_query_pixels_abstain_from_positives(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    flat = (slice(40, 80), slice(50, 110))
    images = [_textured_image(flat if i == MIDDLE else None) for i in range(len(poses))]
    params = LabelerParams(window_size=7, label_delay=3, ambiguity_abstain=True)
    result = _run_with_images(disparities, poses, images, params)
    plain = _middle_result(disparities, poses, PAPER)
    # The flat rectangle (shrunk by the texture window's half width) is never positive, though correct and supported.
    core = (slice(44, 76), slice(54, 106))
    assert np.mean(plain.labels[core] == POSITIVE) > 0.9
    assert not np.any(result.labels[core] == POSITIVE)
    # Elsewhere the labels are the paper's: every view is textured there and votes as before.
    outside = np.ones(result.labels.shape, dtype=bool)
    outside[36:84, 46:114] = False
    assert np.array_equal(result.labels[outside], plain.labels[outside])


def test_saturated_query_pixels_are_never_positive(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    # A clipped (255) rectangle in the middle view, its depth right and confirmed by every textured reference: the
    # texture cue alone lets it be positive (ambiguous pixels only stop voting by default); the saturation cue not.
    disparities, poses = arc
    white = (slice(40, 80), slice(50, 110))
    images = [_textured_image(white if i == MIDDLE else None, value=255) for i in range(len(poses))]
    result = _run_with_images(disparities, poses, images, PARAMS)
    plain = _run_with_images(disparities, poses, images, dataclasses.replace(PARAMS, ambiguity_saturation=0.0))
    assert PARAMS.ambiguity_saturation == 255.0
    assert np.mean(plain.labels[white] == POSITIVE) > 0.9
    assert not np.any(result.labels[white] == POSITIVE)
    assert not np.any(result.stage2_labels[white] == POSITIVE)
    assert not np.any(result.labels[white] == NEGATIVE)  # right depth: abstains, not contradicted
    # Elsewhere nothing changes: the references are never clipped, so they vote as before.
    outside = np.ones(result.labels.shape, dtype=bool)
    outside[white] = False
    assert np.array_equal(result.labels[outside], plain.labels[outside])
    # One view of 254 (not clipped at the default level) changes nothing; a level of 254 clips it.
    images254 = [_textured_image(white if i == MIDDLE else None, value=254) for i in range(len(poses))]
    assert np.array_equal(_run_with_images(disparities, poses, images254, PARAMS).labels, plain.labels)
    at254 = dataclasses.replace(PARAMS, ambiguity_saturation=254.0)
    assert not np.any(_run_with_images(disparities, poses, images254, at254).labels[white] == POSITIVE)


def test_saturated_references_cast_no_vote(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    # Only the saturation cue on: references clipped everywhere cast no vote; at level 0 (off) they do.
    disparities, poses = arc
    clipped = np.full((CAMERA.height, CAMERA.width), 255, np.uint8)
    images = [_textured_image() if i == MIDDLE else clipped for i in range(len(poses))]
    result = _run_with_images(disparities, poses, images, dataclasses.replace(PAPER, ambiguity_saturation=255.0))
    assert not np.any(result.vote_sum != 0)
    assert not np.any(result.stage2_labels != UNKNOWN)
    off = _run_with_images(disparities, poses, images, PAPER)
    assert np.mean(off.stage2_labels == POSITIVE) > 0.5


def test_ambiguous_references_cast_no_vote(arc: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    disparities, poses = arc
    bad = [d.copy() for d in disparities]
    bad[MIDDLE][40:70, 60:100] *= WALL_Z / 6.5  # as in the patch-in-front test: negative by every reference
    flat = _textured_image((slice(0, CAMERA.height), slice(0, CAMERA.width)))
    images = [_textured_image() if i == MIDDLE else flat for i in range(len(poses))]
    params = LabelerParams(window_size=7, label_delay=3, ambiguity_edge_px=0.0)
    result = _run_with_images(bad, poses, images, params)
    # Every reference is textureless: no Stage-2 vote at all, so no Stage-2 label either way.
    assert not np.any(result.vote_sum != 0)
    assert not np.any(result.stage2_labels != UNKNOWN)
    # Without the cue the references vote: the wall around the patch is confirmed by them.
    plain = _run_with_images(bad, poses, images, PAPER)
    assert np.mean(plain.stage2_labels[plain.vote_sum > 0] == POSITIVE) > 0.99
    assert np.mean(plain.vote_sum != 0) > 0.3


def _run_with_range(
    disparities: list[np.ndarray], poses: list[np.ndarray], params: LabelerParams, max_disparity: float | None
) -> LabelResult:
    labeler = Labeler(CAMERA, params)
    results: list[LabelResult] = []
    for i, (disp, pose) in enumerate(zip(disparities, poses, strict=True)):
        results += labeler.add_view(disp, pose, stamp=100.0 + i, key=i, max_disparity=max_disparity)
    results += labeler.flush()
    return {r.key: r for r in results}[MIDDLE]


def test_references_abstain_on_points_beyond_their_disparity_range() -> None:
    # The middle view stands back (10 m from the target) and measures a patch 4 m in front of the wall at
    # 16.7 px; the other views (8 m) would see it at 22.7-25.2 px but report the wall behind it, as a matcher
    # does whose search range ends short of the patch. They agree on the wall, so the paper calls the
    # middle view's patch negative; whether it is depends on whether they could have measured the patch.
    z_patch, half = 6.0, 0.6
    patch_plane = ((np.array([0.0, 0.0, 1.0]), z_patch),)
    poses = [orbit_pose(a, radius=10.0 if i == MIDDLE else 8.0) for i, a in enumerate(ANGLES)]
    disparities = []
    for i, pose in enumerate(poses):
        wall = CAMERA.depth_to_disparity(render_depth(pose, PLANES[:1]))
        patch_disparity = CAMERA.depth_to_disparity(render_depth(pose, patch_plane))
        on_plane = world_points(pose, patch_disparity)  # NaN where the ray misses the plane
        hit = np.isfinite(patch_disparity)
        hit[hit] = (np.abs(on_plane[hit] - TARGET)[:, :2] < half).all(axis=1)  # the square about TARGET
        if i == MIDDLE:
            disparities.append(np.where(hit, patch_disparity, wall))
            np.testing.assert_allclose(patch_disparity[hit], CAMERA.fx * CAMERA.baseline / z_patch, rtol=1e-9)
            patch = hit
        else:
            disparities.append(wall)
            if hit.any():  # inside a range of 30 px, beyond one of 22 px
                assert patch_disparity[hit].min() > 22.0 and patch_disparity[hit].max() < 26.0
    on = dataclasses.replace(PARAMS, range_abstain=True, range_margin_px=2.0)
    paper = _run_with_range(disparities, poses, dataclasses.replace(PARAMS, range_abstain=False), 22.0)
    assert np.mean(paper.labels[patch] == NEGATIVE) > 0.95
    # A range of 22 px less the 2 px margin: the references could not have seen the patch and abstain on it.
    short = _run_with_range(disparities, poses, on, 22.0)
    assert not np.any(short.labels[patch] == NEGATIVE)
    assert not np.any(short.labels[patch] == POSITIVE)  # nobody confirms it either
    assert not np.any(short.stage2_labels[patch] != UNKNOWN)
    # A range of 30 px: they could have, so the patch is a phantom they contradict, exactly as in the paper.
    wide = _run_with_range(disparities, poses, on, 30.0)
    np.testing.assert_array_equal(wide.labels, paper.labels)
    # An unknown range (no max_disparity) is the paper too.
    np.testing.assert_array_equal(_run_with_range(disparities, poses, on, None).labels, paper.labels)
