"""The sliding window, the keyframe rule, label timing and the parameters."""

from __future__ import annotations

import numpy as np
import pytest

from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import Labeler, LabelerParams
from selfcontra_ros.window import ViewWindow, make_view, support_count

CAMERA = StereoCamera(fx=40.0, fy=40.0, cx=15.5, cy=11.5, baseline=0.3, width=32, height=24)


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    t = np.radians(yaw_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(t), 0.0, np.sin(t)], [0.0, 1.0, 0.0], [-np.sin(t), 0.0, np.cos(t)]]
    pose[0, 3] = x
    return pose


def _wall_disparity(distance: float = 6.0) -> np.ndarray:
    return np.full((CAMERA.height, CAMERA.width), CAMERA.focal_baseline / distance)


def test_make_view_caches_points_and_uncertainty() -> None:
    disparity = _wall_disparity()
    disparity[0, :5] = np.nan
    disparity[1, :5] = -1.0
    view = make_view(CAMERA, disparity, _pose(1.0), index=0, key="k", stamp=3.5, sigma_px=1.0)
    assert view.valid.sum() == disparity.size - 10
    np.testing.assert_allclose(view.points.reshape(CAMERA.height, CAMERA.width, 3), CAMERA.backproject(disparity))
    assert np.all(np.isnan(view.u[~view.valid])) and np.all(view.u[view.valid] > 0)
    np.testing.assert_allclose(view.centre, [1.0 + CAMERA.baseline / 2, 0.0, 0.0])
    assert not support_count(view.support_bits).any()


def test_support_count_counts_bits() -> None:
    bits = np.array([0, 1, 0b1010, 2**63 + 1], dtype=np.uint64)
    np.testing.assert_array_equal(support_count(bits), [0, 1, 2, 2])


def test_keyframe_rule_skips_small_motion_only() -> None:
    window = ViewWindow(3, min_translation=0.1, min_rotation_deg=2.0)
    assert window.is_keyframe(_pose(0.0))
    window.push(make_view(CAMERA, _wall_disparity(), _pose(0.0), index=0, key=0, stamp=0.0, sigma_px=1.0))
    assert not window.is_keyframe(_pose(0.05, yaw_deg=1.0))
    assert window.is_keyframe(_pose(0.15))
    assert window.is_keyframe(_pose(0.0, yaw_deg=3.0))


def test_window_memory_stays_bounded_and_labels_come_late() -> None:
    params = LabelerParams(
        window_size=4,
        label_delay=2,
        keyframe_min_translation=0.0,
        keyframe_min_rotation_deg=0.0,
        flush_incomplete=True,
    )
    labeler = Labeler(CAMERA, params)
    seen = []
    for i in range(30):
        results = labeler.add_view(_wall_disparity(), _pose(0.5 * i), stamp=10.0 + 0.1 * i, key=f"frame{i}")
        assert len(labeler.window) <= params.window_size
        expected = [] if i < params.label_delay else [f"frame{i - params.label_delay}"]
        assert [r.key for r in results] == expected
        for r in results:
            j = int(str(r.key)[5:])
            assert r.stamp == pytest.approx(10.0 + 0.1 * j)
            assert r.labels.shape == (CAMERA.height, CAMERA.width) and r.labels.dtype == np.uint8
        seen += [r.key for r in results]
    rest = labeler.flush()
    assert [r.key for r in rest] == [f"frame{i}" for i in range(30 - params.label_delay, 30)]
    assert seen + [r.key for r in rest] == [f"frame{i}" for i in range(30)]
    assert len(labeler.window) == 0
    assert labeler.skipped_views == 0


def test_skipped_views_are_counted_and_not_labelled() -> None:
    params = LabelerParams(window_size=3, label_delay=1, keyframe_min_translation=0.2, flush_incomplete=True)
    labeler = Labeler(CAMERA, params)
    keys = []
    for i, x in enumerate([0.0, 0.05, 0.5, 0.52, 1.0]):
        keys += [r.key for r in labeler.add_view(_wall_disparity(), _pose(x), stamp=float(i))]
    keys += [r.key for r in labeler.flush()]
    assert labeler.skipped_views == 2
    assert keys == [0, 2, 4]  # default keys: the running number of add_view calls


def test_flush_drops_incomplete_views_by_default() -> None:
    params = LabelerParams(window_size=5, label_delay=3, keyframe_min_translation=0.0, keyframe_min_rotation_deg=0.0)
    labeler = Labeler(CAMERA, params)
    keys = []
    for i in range(7):
        keys += [r.key for r in labeler.add_view(_wall_disparity(), _pose(0.5 * i), stamp=float(i), key=i)]
    assert keys == [0, 1, 2, 3]  # each with label_delay newer views
    assert labeler.flush() == []
    assert labeler.dropped_views == 3 and len(labeler.window) == 0
    # The next sequence starts afresh: nothing of the dropped views is labelled later.
    keys = [r.key for i in range(4) for r in labeler.add_view(_wall_disparity(), _pose(0.5 * i), stamp=i, key=10 + i)]
    assert keys == [10]


def test_label_delay_zero_labels_the_arriving_view() -> None:
    labeler = Labeler(CAMERA, LabelerParams(window_size=2, label_delay=0))
    assert [r.key for r in labeler.add_view(_wall_disparity(), _pose(0.0), stamp=0.0, key="a")] == ["a"]
    assert labeler.flush() == []


def test_bad_inputs_are_named() -> None:
    labeler = Labeler(CAMERA)
    with pytest.raises(SelfContraError, match="disparity has shape"):
        labeler.add_view(np.zeros((5, 5)), np.eye(4), stamp=0.0)
    with pytest.raises(SelfContraError, match="pose has shape"):
        labeler.add_view(_wall_disparity(), np.eye(3), stamp=0.0)
    skewed = np.eye(4)
    skewed[0, 1] = 0.5
    with pytest.raises(SelfContraError, match="rotation"):
        labeler.add_view(_wall_disparity(), skewed, stamp=0.0)
    for bad in (0.0, -16.0, float("nan"), float("inf")):
        with pytest.raises(SelfContraError, match="max_disparity"):
            labeler.add_view(_wall_disparity(), _pose(0.0), stamp=0.0, max_disparity=bad)
    assert labeler.skipped_views == 0 and len(labeler.window) == 0  # nothing half-added


def test_views_keep_their_matchers_disparity_range() -> None:
    labeler = Labeler(CAMERA, LabelerParams(window_size=3, label_delay=2))
    labeler.add_view(_wall_disparity(), _pose(0.0), stamp=0.0, max_disparity=63.0)
    labeler.add_view(_wall_disparity(), _pose(0.5), stamp=1.0)
    assert [view.max_disparity for view in labeler.window] == [63.0, float("inf")]


def test_params_validation_and_from_dict() -> None:
    params = LabelerParams.from_dict({"window_size": 20, "label_delay": 10, "stage2_tolerance": "query"})
    assert (params.window_size, params.label_delay, params.stage2_tolerance) == (20, 10, "query")
    assert params.alpha_min_deg == LabelerParams().alpha_min_deg
    with pytest.raises(ValueError, match=r"unknown labeler parameter.*'windw_size'"):
        LabelerParams.from_dict({"windw_size": 3})
    for bad in (
        {"label_delay": 20},  # = the default window_size: out of range
        {"window_size": 1},
        {"alpha_min_deg": 0.5},
        {"sigma_max": 0.0},
        {"stage1_tolerance": "largest"},
        {"stage3_tolerance": "x"},
        {"window_size": 4.5},
        {"keyframe_min_translation": -1.0},
        {"ambiguity_saturation": 256.0},
        {"ambiguity_saturation": -1.0},
    ):
        with pytest.raises(ValueError, match="LabelerParams"):
            LabelerParams.from_dict(bad)


def test_ambiguous_pixels_match_a_brute_force_reference() -> None:
    from selfcontra_ros.window import ambiguous_pixels

    rng = np.random.default_rng(3)
    image = rng.integers(100, 110, (24, 32)).astype(np.uint8)  # std about 2.9
    image[:, 16:] = 120 + (image[:, 16:] - 100) // 4  # std about 0.7: ambiguous
    disparity = np.full((24, 32), 10.0, np.float32)
    disparity[12:, 8:20] = 16.0  # a 6 px jump
    disparity[0, 0] = np.nan
    got = ambiguous_pixels(disparity, image, min_texture=1.5, texture_window=5, edge_px=4.0)
    padded = np.pad(image.astype(np.float64), 2, mode="symmetric")  # OpenCV's BORDER_REFLECT repeats the edge
    expected = np.zeros((24, 32), bool)
    for r in range(24):
        for c in range(32):
            texture = padded[r : r + 5, c : c + 5].std() < 1.5
            d = disparity[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2]
            d = d[np.isfinite(d)]
            edge = np.isfinite(disparity[r, c]) and d.max() - d.min() > 4.0
            expected[r, c] = texture or edge
    assert np.array_equal(got, expected)
    # Each cue is off at 0, and the texture cue without an image.
    assert not ambiguous_pixels(disparity, image, min_texture=0.0, texture_window=5, edge_px=0.0).any()
    assert np.array_equal(
        ambiguous_pixels(disparity, None, min_texture=1.5, texture_window=5, edge_px=4.0),
        ambiguous_pixels(disparity, image, min_texture=0.0, texture_window=5, edge_px=4.0),
    )


def test_saturated_pixels_are_those_at_or_above_the_level() -> None:
    from selfcontra_ros.window import saturated_pixels

    grey = np.array([[0, 250, 254], [255, 255, 128]], np.uint8)
    assert np.array_equal(saturated_pixels(grey, 255), grey == 255)
    assert np.array_equal(saturated_pixels(grey, 250), grey >= 250)
    # RGB: the grey value decides (a pure red 255 is grey 76, not clipped; white is).
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)
    rgb[1, 2] = (255, 255, 255)
    expected = np.zeros((2, 3), bool)
    expected[1, 2] = True
    assert np.array_equal(saturated_pixels(rgb, 255), expected)
