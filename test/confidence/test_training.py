"""Training-sample helpers: the fattening band's unlabelled pixels as negatives (``band_negatives``), and their look."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfcontra_ros.cli import main
from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.commands import _label_source, iter_frames, train_command
from selfcontra_ros.confidence.constants import BAND_LOOK_MIN_COUNT, BAND_LOOK_SMOOTHING, TRAINING
from selfcontra_ros.confidence.features import FeatureContext
from selfcontra_ros.confidence.forest import load_model
from selfcontra_ros.confidence.inputs import query_feature_input
from selfcontra_ros.confidence.kernels import band_look
from selfcontra_ros.confidence.training import BandPrior, band_labeler, band_look_scores, band_negatives
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.matching.base import MatcherParams, make_matcher
from selfcontra_ros.stages.voting import fattening_band

SMALL_FOREST = {"n_estimators": 3, "max_depth": 8, "min_samples_leaf": 5}
MATCHER = MatcherParams(num_disparities=32)


def _step(width: int = 200, height: int = 40, edge: int = 80) -> np.ndarray:
    """Background at 10 px left of ``edge``, an object at 30 px right of it, an invalid strip at the far right."""
    d = np.full((height, width), 10.0, np.float32)
    d[:, edge:] = 30.0
    d[:, width - 10 :] = np.nan
    return d


def test_band_negatives_fill_only_the_unknown_pixels_of_the_labelers_band() -> None:
    d = _step()
    p = LabelerParams()
    band = fattening_band(
        d,
        jump_px=p.stage2_edge_jump_px,
        occluded_side_px=p.stage2_edge_occluded_side_px,
        other_px=p.stage2_edge_other_px,
    )
    # The band is the object's side of the edge, as far from it as the band's left reach.
    assert band[:, 80 : 80 + p.stage2_edge_occluded_side_px].all()
    assert not band[:, :80].any() and not band[:, 80 + p.stage2_edge_occluded_side_px + 1 :].any()
    labels = np.full(d.shape, UNKNOWN, np.uint8)
    labels[5, 85] = POSITIVE  # the labeler never does this in its band, but a label is never overwritten
    labels[6, 40] = NEGATIVE
    labels[7, 150] = POSITIVE
    out = band_negatives(labels, d, 1.0, np.random.default_rng(0))
    assert out.dtype == np.uint8 and out.shape == labels.shape
    assert out[5, 85] == POSITIVE and out[6, 40] == NEGATIVE and out[7, 150] == POSITIVE
    assert np.array_equal(out == NEGATIVE, band & (labels == UNKNOWN) | (labels == NEGATIVE))
    assert not (out[:, -10:] != UNKNOWN).any()  # invalid disparity is never drawn
    assert np.array_equal(band_negatives(labels, d, 0.0, np.random.default_rng(0)), labels)  # 0: the paper


def test_band_negatives_follow_the_band_of_the_labeler_that_made_the_labels() -> None:
    d = _step()
    labels = np.zeros(d.shape, np.uint8)
    wide = LabelerParams(stage2_edge_occluded_side_px=32, stage2_edge_other_px=2)
    out = band_negatives(labels, d, 1.0, np.random.default_rng(0), labeler=wide)
    # The object's side of the edge as far as the labeler's left reach, 32 columns instead of the default 20.
    assert (out[:, 80:112] == NEGATIVE).all() and not (out[:, 112:] == NEGATIVE).any()
    assert not (out[:, :80] == NEGATIVE).any()
    # A larger jump than the edge's 20 px draws nothing; a labeler without a band (the paper) draws the default's.
    assert not band_negatives(
        labels, d, 1.0, np.random.default_rng(0), labeler=LabelerParams(stage2_edge_jump_px=25)
    ).any()
    paper = LabelerParams(stage2_edge_jump_px=0.0, stage2_edge_occluded_side_px=32)
    assert np.array_equal(
        band_negatives(labels, d, 1.0, np.random.default_rng(0), labeler=paper),
        band_negatives(labels, d, 1.0, np.random.default_rng(0)),
    )


def test_band_look_compares_with_the_background_beyond_the_labelers_jump(
    fattened_edge: tuple[np.ndarray, np.ndarray],
) -> None:
    image, d = fattened_edge
    band = fattening_band(d, jump_px=4.0, occluded_side_px=20, other_px=4)
    rows, cols = np.nonzero(band)
    assert np.isfinite(band_look_scores(image, d, band, rows, cols)).all()  # the background is 20 px below
    # With a jump of 20 px or more no pixel is far enough below to be the background: no look anywhere.
    assert np.isnan(band_look_scores(image, d, band, rows, cols, jump_px=20.0)).all()
    labels = np.zeros(d.shape, np.uint8)

    def drawn(labeler: LabelerParams | None) -> np.ndarray:
        return band_negatives(labels, d, 1.0, np.random.default_rng(0), image=image, look=-1.0, labeler=labeler)

    # So a labeler with that jump has no band at this edge; one with a jump of 19 px has it, and the look.
    assert not drawn(LabelerParams(stage2_edge_jump_px=20.0)).any()
    assert np.array_equal(drawn(LabelerParams(stage2_edge_jump_px=19.0)), drawn(None))


def test_band_labeler_reads_only_the_recorded_band() -> None:
    assert band_labeler(None) is None and band_labeler("not a section") is None
    recorded = {"stage2_edge_occluded_side_px": 32, "window_size": 7, "a_key_of_another_version": 1}
    p = band_labeler(recorded)
    assert p is not None and p.stage2_edge_occluded_side_px == 32
    assert p.stage2_edge_jump_px == LabelerParams().stage2_edge_jump_px  # missing: the default
    assert p.window_size == LabelerParams().window_size  # not a band size: not read
    with pytest.raises(SelfContraError, match="recorded fattening band"):
        band_labeler({"stage2_edge_occluded_side_px": -3})


def test_band_negatives_share_draws_that_share() -> None:
    d = _step(width=400, height=200, edge=150)
    labels = np.zeros(d.shape, np.uint8)
    band_pixels = 200 * LabelerParams().stage2_edge_occluded_side_px
    drawn = [int((band_negatives(labels, d, 0.3, np.random.default_rng(seed)) == NEGATIVE).sum()) for seed in range(3)]
    # Binomial(4000, 0.3): mean 1200, std 29; 6 std either side.
    assert all(abs(n - 0.3 * band_pixels) < 6 * np.sqrt(band_pixels * 0.3 * 0.7) for n in drawn)
    with pytest.raises(SelfContraError, match="does not match"):
        band_negatives(labels[:, :-1], d, 1.0, np.random.default_rng(0))


def _look_reference(
    grey: np.ndarray, d: np.ndarray, band: np.ndarray, r: int, c: int, jump: float, window: tuple[int, int], least: int
) -> float:
    """The look of one pixel, written out (float64)."""
    hh, hw = window[0] // 2, window[1] // 2
    ys, xs = slice(max(r - hh, 0), r + hh + 1), slice(max(c - hw, 0), c + hw + 1)
    g, w, b = grey[ys, xs].astype(np.float64), d[ys, xs], band[ys, xs]
    valid = np.isfinite(w) & (w > 0)
    background = g[valid & (w < d[r, c] - jump)]
    interior = g[valid & (np.abs(w - d[r, c]) <= 1) & ~b & ~(w < d[r, c] - jump)]
    if background.size < least or interior.size < least:
        return float("nan")
    z = [abs(grey[r, c] - s.mean()) / np.sqrt(max(s.var(), 1.0)) for s in (background, interior)]
    return float(z[0] - z[1])


def test_band_look_matches_the_written_out_score() -> None:
    rng = np.random.default_rng(4)
    grey = rng.uniform(0, 255, (30, 70)).astype(np.float32)
    d = rng.choice(np.array([5.0, 9.0, 9.5, 10.0, 20.0, np.nan, np.inf], np.float32), size=grey.shape)
    band = rng.random(grey.shape) < 0.3
    rows, cols = np.nonzero(np.isfinite(d))
    got = band_look(grey, d, band, rows, cols, jump=4.0, window=(5, 11), min_count=5)
    want = np.array([_look_reference(grey, d, band, r, c, 4.0, (5, 11), 5) for r, c in zip(rows, cols, strict=True)])
    assert np.isnan(want).any() and np.isfinite(want).sum() > 100  # both cases occur
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    # float32 output of float64 sums: a few ulp of values up to about 10.
    np.testing.assert_allclose(got[ok], want[ok], rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match="differ"):
        band_look(grey[:, :-1], d, band, rows, cols, jump=4.0, window=(5, 11), min_count=5)
    with pytest.raises(ValueError, match="inside"):
        band_look(grey, d, band, rows + 30, cols, jump=4.0, window=(5, 11), min_count=5)


def test_band_look_scores_fall_back_to_the_wider_window_where_the_first_is_short(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    windows = ((9, 49), (17, 81))
    monkeypatch.setattr(constants, "BAND_LOOK_WINDOWS", windows)
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (60, 160)).astype(np.uint8)
    # Sparse background (disparity 5) among an object at 20: many 9x49 windows hold fewer than 5 of it.
    d = np.where(rng.random(image.shape) < 0.004, 5.0, 20.0).astype(np.float32)
    band = rng.random(image.shape) < 0.2
    rows, cols = np.nonzero(band)
    got = band_look_scores(image, d, band, rows, cols)
    grey = cv2.GaussianBlur(image.astype(np.float32), (BAND_LOOK_SMOOTHING, BAND_LOOK_SMOOTHING), 0)
    jump = LabelerParams().stage2_edge_jump_px
    want = np.full(rows.size, np.nan)
    for window in windows:
        for k in np.flatnonzero(np.isnan(want)):
            want[k] = _look_reference(grey, d, band, rows[k], cols[k], jump, window, BAND_LOOK_MIN_COUNT)
    first = [
        _look_reference(grey, d, band, r, c, jump, windows[0], BAND_LOOK_MIN_COUNT)
        for r, c in zip(rows, cols, strict=True)
    ]
    wider = np.isnan(first) & np.isfinite(want)
    assert wider.sum() > 50 and np.isnan(want).sum() > 10  # the fallback scores some, and some stay NaN
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], rtol=1e-5, atol=1e-4)


def test_band_negatives_look_leaves_the_objects_own_pixels_out_of_the_draw(
    fattened_edge: tuple[np.ndarray, np.ndarray],
) -> None:
    image, d = fattened_edge
    labels = np.zeros(d.shape, np.uint8)
    everything = band_negatives(labels, d, 1.0, np.random.default_rng(0))  # inf: every band pixel (stop 40 on)
    band = everything == NEGATIVE
    assert band[:, 74:94].all() and not band[:, :74].any() and not band[:, 95:].any()
    out = band_negatives(labels, d, 1.0, np.random.default_rng(0), image=image, look=-1.0)
    # The fattened pixels (background carrying the object's disparity) look like the background: drawn;
    # the object's own band pixels look like its interior: left unknown.
    assert (out[:, 74:80] == NEGATIVE).all()
    assert (out[:, 80:] == UNKNOWN).all()
    # An RGB image is read as its grey.
    rgb = np.repeat(image[:, :, None], 3, axis=2)
    assert np.array_equal(band_negatives(labels, d, 1.0, np.random.default_rng(0), image=rgb, look=-1.0), out)
    # Where a set is too small to compare with the pixel is drawn: a 2x2 hole (4 background pixels < 5).
    hole = np.full(d.shape, 30.0, np.float32)
    hole[20:22, 100:102] = 10.0
    drawn = band_negatives(labels, hole, 1.0, np.random.default_rng(0))
    assert (drawn == NEGATIVE).sum() > 0
    assert np.array_equal(band_negatives(labels, hole, 1.0, np.random.default_rng(0), image=image, look=-1.0), drawn)
    with pytest.raises(SelfContraError, match="needs the left image"):
        band_negatives(labels, d, 1.0, np.random.default_rng(0), look=-1.0)
    with pytest.raises(SelfContraError, match="does not match"):
        band_negatives(labels, d, 1.0, np.random.default_rng(0), image=image[:, :-1], look=-1.0)


@pytest.fixture(scope="module")
def labelled(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A small street sequence and a label folder holding only its ground truth's positives."""
    root = tmp_path_factory.mktemp("band")
    data = root / "seq"
    write_sequence(data, scene="street", frames=2, seed=3, width=240, height=96)
    out = root / "labels_run"
    (out / "labels").mkdir(parents=True)
    matcher = make_matcher(MATCHER)
    for frame in iter_frames(data):
        ctx = FeatureContext(query_feature_input(matcher, frame.left, frame.right))
        assert frame.gt_disparity is not None
        d = ctx.data.disparity
        good = np.isfinite(d) & (np.abs(d - frame.gt_disparity) < 1)
        cv2.imwrite(str(out / "labels" / f"{frame.index:06d}.png"), np.where(good, POSITIVE, UNKNOWN).astype(np.uint8))
    (out / "metrics.json").write_text(json.dumps({"params": {"matcher": asdict(MATCHER)}}))
    return data, out


def test_train_draws_band_negatives_from_self_labels_only(labelled: tuple[Path, Path], tmp_path: Path) -> None:
    data, labels = labelled
    # Positives only: without band negatives no image has both classes, so there is nothing to learn.
    with pytest.raises(SelfContraError):
        train_command([(data, labels)], "gcp", tmp_path / "paper.npz", forest=SMALL_FOREST, band=BandPrior(share=0.0))
    summary = train_command([(data, labels)], "gcp", tmp_path / "band.npz", forest=SMALL_FOREST)
    assert summary["samples"] > 0 and summary["positive_share"] == pytest.approx(0.5)
    # Ground truth is used as it is (sparse ground truth leaves valid pixels unknown; they must stay out).
    assert _label_source("gt", data).is_ground_truth and not _label_source(labels, data).is_ground_truth


def test_train_draws_from_the_band_of_the_labels_own_labeler(labelled: tuple[Path, Path], tmp_path: Path) -> None:
    data, labels = labelled
    assert _label_source(labels, data).labeler is None  # nothing recorded: the default band
    wide = {"stage2_edge_occluded_side_px": 40, "stage2_edge_other_px": 6}
    (labels / "metrics.json").write_text(json.dumps({"params": {"matcher": asdict(MATCHER), "labeler": wide}}))
    source = _label_source(labels, data)
    assert source.labeler is not None and source.labeler.stage2_edge_occluded_side_px == 40
    # Training reads it: the same positives with a wider band lend more negatives, so more balanced samples.
    narrow = {"stage2_edge_occluded_side_px": 2, "stage2_edge_other_px": 1}
    counts = {}
    for name, band in (("wide", wide), ("narrow", narrow)):
        (labels / "metrics.json").write_text(json.dumps({"params": {"matcher": asdict(MATCHER), "labeler": band}}))
        summary = train_command(
            [(data, labels)], "gcp", tmp_path / f"{name}.npz", forest=SMALL_FOREST, band=BandPrior(cue=float("inf"))
        )
        counts[name] = summary["samples"]
    assert counts["wide"] > counts["narrow"] > 0


def test_train_command_line_takes_the_share(labelled: tuple[Path, Path], tmp_path: Path) -> None:
    data, labels = labelled
    base = ["train", "--features", "gcp", "--data", str(data), "--labels", str(labels)]
    assert main([*base, "--out", str(tmp_path / "paper.npz"), "--band-negatives", "0"]) == 2  # one class only
    assert main([*base, "--out", str(tmp_path / "band.npz")]) == 0
    metadata = load_model(tmp_path / "band.npz").metadata
    assert metadata["feature_set"] == "gcp"
    defaults = {"band_negatives": 1.0, "band_look": None, "band_cue": 0.5, "band_texture": TRAINING["band_texture"]}
    assert metadata["sampling"] == defaults
    options = ["--band-look", "-1", "--band-cue", "inf", "--band-texture", "3"]
    assert main([*base, "--out", str(tmp_path / "look.npz"), *options]) == 0
    recorded = load_model(tmp_path / "look.npz").metadata["sampling"]
    assert recorded == {"band_negatives": 1.0, "band_look": -1.0, "band_cue": None, "band_texture": 3.0}
    assert main([*base, "--out", str(tmp_path / "bad.npz"), "--band-cue", "2"]) == 2  # not a probability
    assert main([*base, "--out", str(tmp_path / "bad.npz"), "--band-texture", "-1"]) == 2
    summary = train_command([(data, "gt")], "gcp", tmp_path / "gt.npz", forest=SMALL_FOREST, matcher=MATCHER)
    assert "sampling" not in load_model(summary["model"]).metadata  # ground truth is taken as it is


def test_train_command_line_takes_the_forest_seed(
    labelled: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data, labels = labelled
    base = ["train", "--features", "gcp", "--data", str(data), "--labels", str(labels), "--band-look", "inf"]
    for name, seed in (("a", "3"), ("b", "3"), ("c", "4")):
        assert main([*base, "--out", str(tmp_path / f"{name}.npz"), "--forest-seed", seed]) == 0
    a, b, c = (load_model(tmp_path / f"{name}.npz") for name in "abc")
    assert a.metadata["forest"]["random_state"] == 3 and c.metadata["forest"]["random_state"] == 4
    # The same samples: one seed gives the same trees, another seed other bootstrap draws (with this few
    # samples each tree is one leaf, whose positive share is its draw's).
    for name in ("tree_offsets", "feature", "threshold", "positive"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.positive.shape != c.positive.shape or not np.array_equal(a.positive, c.positive)
    with pytest.raises(SystemExit):
        main([*base, "--out", str(tmp_path / "bad.npz"), "--forest-seed", "-1"])
    assert "a forest seed is in 0 .. 4294967295 (2**32 - 1), not -1" in capsys.readouterr().err
