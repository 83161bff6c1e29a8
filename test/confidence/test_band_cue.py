"""The band cue: the strip costs against a written-out reference, its features and the shipped model on an edge."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.confidence.band_cue import (
    FEATURES,
    MODEL_FILE,
    band_cue_features,
    default_band_cue,
    edge_distances,
    strip_textures,
)
from selfcontra_ros.confidence.constants import TRAINING
from selfcontra_ros.confidence.forest import ForestModel, fit_forest, load_model, save_model
from selfcontra_ros.confidence.kernels import strip_costs, window_costs
from selfcontra_ros.confidence.training import BandPrior, band_look_scores, band_negatives, prior_band
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE
from selfcontra_ros.stages.voting import band_background


def _strip_reference(left: np.ndarray, right: np.ndarray, r: int, c: int, d: float, half: int) -> float:
    """The zero-mean mean absolute difference of the 1 x (2 half + 1) strips, written out."""
    return _window_reference(left, right, r, c, d, half, 0, 0)[0]


def test_strip_costs_match_the_written_out_strips() -> None:
    rng = np.random.default_rng(0)
    left = rng.uniform(0, 255, (30, 50)).astype(np.float32)
    right = rng.uniform(0, 255, (30, 50)).astype(np.float32)
    # Pixels at the borders too: rows clipped, strips matched beyond the left border read its column.
    rows = np.array([0, 29, 15, 3, 10, 20])
    cols = np.array([0, 49, 25, 2, 40, 6])
    own = np.array([0.0, 12.5, 3.25, 7.0, 39.9, 6.0], np.float32)
    background = np.array([0.0, 2.0, 24.75, 0.5, 1.0, 0.0], np.float32)
    got = strip_costs(left, right, rows, cols, own, background, max_disparity=12, half_height=3)
    assert got.shape == (6, 4) and got.dtype == np.float32
    for k, (r, c) in enumerate(zip(rows, cols, strict=True)):
        strip = left[np.clip(np.arange(r - 3, r + 4), 0, 29), c]
        want = [
            _strip_reference(left, right, r, c, float(own[k]), 3),
            _strip_reference(left, right, r, c, float(background[k]), 3),
            min(_strip_reference(left, right, r, c, float(d), 3) for d in range(min(12, c) + 1)),
            float(np.mean(np.abs(strip - strip.mean()))),
        ]
        np.testing.assert_allclose(got[k], want, rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="inside"):
        strip_costs(left, right, np.array([30]), np.array([0]), own[:1], own[:1], max_disparity=4, half_height=3)
    with pytest.raises(ValueError, match="finite"):
        strip_costs(left, right, rows[:1], cols[:1], np.array([np.nan]), own[:1], max_disparity=4, half_height=3)


def _window_reference(
    left: np.ndarray, right: np.ndarray, r: int, c: int, d: float, half: int, before: int, after: int
) -> tuple[float, float]:
    """The window's zero-mean mean absolute difference and its texture, written out column by column."""
    height, width = left.shape
    ys = np.clip(np.arange(r - half, r + half + 1), 0, height - 1)
    a_cols, b_cols = [], []
    for u in np.clip(np.arange(c - before, c + after + 1), 0, width - 1):
        x = min(max(u - d, 0.0), width - 1.0)
        x0 = min(int(np.floor(x)), width - 2)
        t = x - x0
        a_cols.append(left[ys, u].astype(np.float64))
        b_cols.append((1 - t) * right[ys, x0].astype(np.float64) + t * right[ys, x0 + 1])
    a, b = np.concatenate(a_cols), np.concatenate(b_cols)
    return float(np.mean(np.abs((a - a.mean()) - (b - b.mean())))), float(np.mean(np.abs(a - a.mean())))


def test_window_costs_match_the_written_out_windows_and_the_strip() -> None:
    rng = np.random.default_rng(3)
    left = rng.uniform(0, 255, (30, 50)).astype(np.float32)
    right = rng.uniform(0, 255, (30, 50)).astype(np.float32)
    rows = np.array([0, 29, 15, 3, 10, 20])
    cols = np.array([0, 49, 25, 2, 40, 6])
    pairs = np.array([[0.0, 0.0], [12.5, 2.0], [3.25, 24.75], [7.0, 0.5], [39.9, 1.0], [6.0, 0.0]], np.float32)
    for half, before, after in [(2, 4, 0), (2, 0, 4), (8, 0, 0), (1, 3, 2)]:
        got = window_costs(left, right, rows, cols, pairs, half_height=half, before=before, after=after)
        assert got.shape == (6, 3) and got.dtype == np.float32
        for k, (r, c) in enumerate(zip(rows, cols, strict=True)):
            (own, texture), (background, _) = (
                _window_reference(left, right, r, c, float(d), half, before, after) for d in pairs[k]
            )
            np.testing.assert_allclose(got[k], [own, background, texture], rtol=1e-4, atol=1e-3)
    # A window one column wide is the strip.
    strip = strip_costs(left, right, rows, cols, pairs[:, 0], pairs[:, 1], max_disparity=0, half_height=3)
    got = window_costs(left, right, rows, cols, pairs, half_height=3, before=0, after=0)
    np.testing.assert_allclose(got, strip[:, [0, 1, 3]], rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="inside"):
        window_costs(left, right, np.array([30]), np.array([0]), pairs[:1], half_height=1, before=0, after=0)
    with pytest.raises(ValueError, match="finite"):
        window_costs(left, right, rows[:1], cols[:1], np.array([[np.nan, 1.0]]), half_height=1, before=0, after=0)
    with pytest.raises(ValueError, match=">= 0"):
        window_costs(left, right, rows, cols, pairs, half_height=1, before=-1, after=0)
    with pytest.raises(ValueError, match="K >= 1"):
        window_costs(left, right, rows, cols, pairs[:, :0], half_height=1, before=0, after=0)


def test_band_background_is_the_smallest_disparity_of_the_band_window() -> None:
    rng = np.random.default_rng(1)
    d = rng.uniform(1, 60, (25, 40)).astype(np.float32)
    d[rng.random(d.shape) < 0.2] = np.nan
    got = band_background(d, occluded_side_px=6, other_px=2)
    filled = np.where(np.isfinite(d), d, np.inf)
    for r in range(25):
        for c in range(40):
            window = filled[max(r - 2, 0) : r + 3, max(c - 6, 0) : c + 3]
            assert got[r, c] == pytest.approx(window.min())


def test_band_cue_features_tell_fattened_pixels_from_the_objects_own(stereo_edge: dict[str, Any]) -> None:
    left, right, query = stereo_edge["left"], stereo_edge["right"], stereo_edge["query"]
    edge = stereo_edge["edge"]
    labeler = LabelerParams()
    band = prior_band(query, labeler)
    rows, cols = np.nonzero(band[5:-5])
    rows += 5  # away from the top and bottom rows, where the strips are clipped
    look = band_look_scores(left, query, band, rows, cols)
    x = band_cue_features(left, right, query, rows, cols, look, labeler)
    assert x.shape == (rows.size, len(FEATURES)) and x.dtype == np.float32
    column = dict(zip(FEATURES, x.T, strict=True))
    fattened, own = cols < edge, cols >= edge
    assert fattened.sum() > 100 and own.sum() > 100
    # The object's own band pixels match best at their own disparity, far better than at the background's; the
    # fattened ones (background hidden from the right camera, as beside any object's left outline) match
    # nowhere at the object's disparity they carry: some other disparity matches their strip better.
    assert np.median(column["strip_own_vs_background"][own]) < -5
    assert np.percentile(column["strip_own_vs_best"][own], 90) < 0.5
    assert np.median(column["strip_own_vs_best"][fattened]) > 5
    # The window right of an object pixel lies on the object: it matches at the pixel's disparity, not at the
    # background's; the fattened pixels' windows and strips match at neither (they are hidden from the right
    # camera). Next to the outline an object pixel's left window takes in that hidden background.
    assert np.percentile(column["right_own_vs_background"][own], 90) < -5
    for strip in ("short_own_vs_background", "tall_own_vs_background"):
        assert np.median(column[strip][own]) < -5 < np.median(column[strip][fattened])
    assert np.median(column["right_own_vs_background"][fattened]) > -5
    assert np.median(column["own_left_vs_right"][own & (cols < edge + 4)]) > 2
    # The look: like the object's interior on its own pixels, like the background on the fattened ones.
    assert np.median(column["look"][own]) > 0 > np.median(column["look"][fattened])
    np.testing.assert_allclose(column["drop"], 20.0)
    # The drop is the background column left of the fattened run: nearer to the fattened pixels.
    reach = cols - (edge - stereo_edge["fattened"] - 1)
    np.testing.assert_array_equal(column["edge_distance"], reach)
    np.testing.assert_array_equal(column["edge_distance_row"], reach)
    np.testing.assert_array_equal(column["edge_distance_other"], labeler.stage2_edge_occluded_side_px + 1)
    # The shipped cue ranks the object's own band pixels above the fattened ones.
    p_right = default_band_cue().predict(x)
    wins = (p_right[own][:, None] > p_right[fattened][None, :]).mean()
    assert wins > 0.9
    hole = query.copy()
    hole[0, 0] = np.nan
    with pytest.raises(SelfContraError, match="valid disparity"):
        band_cue_features(left, right, hole, np.array([0]), np.array([0]), np.array([np.nan]), labeler)


def test_edge_distances_are_the_smallest_reach_that_holds_a_drop() -> None:
    rng = np.random.default_rng(2)
    d = rng.choice([5.0, 12.0, 30.0], size=(30, 70), p=[0.1, 0.2, 0.7]).astype(np.float32)
    d[rng.random(d.shape) < 0.05] = np.nan
    labeler = LabelerParams(stage2_edge_occluded_side_px=9, stage2_edge_other_px=3)
    rows, cols = np.nonzero(np.isfinite(d))
    got = edge_distances(d, rows, cols, labeler)
    jump = labeler.stage2_edge_jump_px
    filled = np.where(np.isfinite(d), d, np.inf)

    def reach(r: int, c: int, window: Any) -> float:
        """The smallest k whose window (rows up and down, columns left, columns right) holds a drop."""
        for k in range(1, 10):
            sizes = window(k)
            if sizes is None:
                break
            vertical, left, right = sizes
            box = filled[max(r - vertical, 0) : r + vertical + 1, max(c - left, 0) : c + right + 1]
            if d[r, c] - box.min() > jump:
                return float(k)
        return 10.0

    for n in rng.choice(rows.size, 300, replace=False):
        r, c = int(rows[n]), int(cols[n])
        want = [
            reach(r, c, lambda k: (min(k, 3), min(k, 9), min(k, 3))),
            reach(r, c, lambda k: (0, k, 0)),
            reach(r, c, lambda k: (k, 0, k) if k <= 3 else None),
        ]
        np.testing.assert_array_equal(got[n], want, err_msg=f"pixel ({r}, {c})")


def test_the_shipped_band_cue_is_a_plain_array_model_that_records_its_fit() -> None:
    model = default_band_cue()
    assert model is default_band_cue()  # loaded once
    assert model.metadata["feature_names"] == list(FEATURES) and model.n_features == len(FEATURES)
    assert set(model.metadata["fitted_on"]["scenes"]) == {"orbit", "street", "room"}
    with np.load(MODEL_FILE, allow_pickle=False) as archive:  # never pickle
        assert all(archive[name].dtype != object for name in archive.files)


def _constant_cue(tmp_path: Path, right_share: float) -> ForestModel:
    """A band cue model that gives every pixel the probability ``right_share`` of being right."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, len(FEATURES))).astype(np.float32)
    y = np.zeros(200, bool)
    y[: round(200 * right_share)] = True
    model = fit_forest(
        x,
        y,
        {"feature_names": list(FEATURES)},
        forest={"n_estimators": 1, "max_depth": 1, "min_samples_leaf": 200, "bootstrap": False},
    )
    return load_model(save_model(model, tmp_path / f"cue_{right_share}.npz"))


def test_band_negatives_leave_out_what_the_cue_calls_right(stereo_edge: dict[str, Any], tmp_path: Path) -> None:
    left, right, query = stereo_edge["left"], stereo_edge["right"], stereo_edge["query"]
    edge, fattened = stereo_edge["edge"], stereo_edge["fattened"]
    labels = np.zeros(query.shape, np.uint8)
    rng = np.random.default_rng(0)
    everything = band_negatives(labels, query, 1.0, rng)
    assert (everything == NEGATIVE).sum() > 0
    # A cue that calls every pixel right with 0.8 leaves out everything at 0.7 and nothing at 0.9.
    sure = _constant_cue(tmp_path, 0.8)
    kwargs = {"image": left, "right": right, "cue_model": sure}
    assert not band_negatives(labels, query, 1.0, rng, cue=0.7, **kwargs).any()
    assert np.array_equal(band_negatives(labels, query, 1.0, rng, cue=0.9, **kwargs), everything)
    # The shipped cue at its default threshold draws the fattened pixels and leaves most of the object's own out.
    drawn = band_negatives(labels, query, 1.0, rng, image=left, right=right, cue=0.5) == NEGATIVE
    inner = slice(5, -5)
    assert drawn[inner, edge - fattened : edge].mean() > 0.8
    assert drawn[inner, edge : edge + 12].mean() < 0.2
    # The prior as one object: the same draw, and what a model records of it.
    prior = BandPrior(share=1.0, look=float("inf"), cue=0.5, texture=0.0)
    same = prior.apply(labels, query, rng, left=left, right=right) == NEGATIVE
    assert np.array_equal(same, drawn)
    assert prior.metadata() == {"band_negatives": 1.0, "band_look": None, "band_cue": 0.5, "band_texture": 0.0}
    assert BandPrior().metadata()["band_texture"] == TRAINING["band_texture"]
    with pytest.raises(SelfContraError, match="both images"):
        band_negatives(labels, query, 1.0, rng, image=left, cue=0.7)
    with pytest.raises(SelfContraError, match="both images"):
        band_negatives(labels, query, 1.0, rng, image=left, texture=2.0)
    bad_priors = ({"share": 1.5}, {"look": float("nan")}, {"cue": 1.2}, {"cue": float("nan")}, {"texture": -1.0})
    for bad in (*bad_priors, {"texture": float("inf")}):
        with pytest.raises(SelfContraError, match="band prior"):
            BandPrior(**bad)  # type: ignore[arg-type]


def test_band_negatives_leave_out_band_pixels_whose_strip_has_no_texture(stereo_edge: dict[str, Any]) -> None:
    """texture: the band pixels whose 1x9 strip varies by less than that many grey levels are not drawn, exactly
    those (the cue's strip_texture), whatever the cue; 0 leaves the draw as it was."""
    left, right, query = stereo_edge["left"].copy(), stereo_edge["right"].copy(), stereo_edge["query"]
    left[20:41], right[20:41] = 120, 120  # a flat stripe across the edge, in both images
    labels = np.zeros(query.shape, np.uint8)
    rng = np.random.default_rng(0)
    kwargs: dict[str, Any] = {"image": left, "right": right}
    everything = band_negatives(labels, query, 1.0, rng) == NEGATIVE
    assert np.array_equal(band_negatives(labels, query, 1.0, rng, texture=0.0, **kwargs) == NEGATIVE, everything)
    drawn = band_negatives(labels, query, 1.0, rng, texture=2.0, **kwargs) == NEGATIVE
    rows, cols = np.nonzero(everything)
    look = np.full(rows.size, np.nan, np.float32)
    texture = band_cue_features(left, right, query, rows, cols, look, LabelerParams())[
        :, FEATURES.index("strip_texture")
    ]
    assert np.array_equal(drawn[rows, cols], texture >= 2.0)
    np.testing.assert_array_equal(strip_textures(left, right, rows, cols), texture)  # the cue-less path's values
    assert not drawn[24:37].any()  # every strip inside the stripe is flat
    assert np.array_equal(drawn[:12], everything[:12]) and np.array_equal(drawn[49:], everything[49:])
    # With the cue as well, a pixel leaves the draw if either rule says so.
    both = band_negatives(labels, query, 1.0, rng, cue=0.5, texture=2.0, **kwargs) == NEGATIVE
    cue_only = band_negatives(labels, query, 1.0, rng, cue=0.5, **kwargs) == NEGATIVE
    assert np.array_equal(both, cue_only & drawn)
    prior = BandPrior(share=1.0, look=float("inf"), cue=float("inf"), texture=2.0)
    assert np.array_equal(prior.apply(labels, query, rng, left=left, right=right) == NEGATIVE, drawn)
    assert prior.metadata()["band_texture"] == 2.0
