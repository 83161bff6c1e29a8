"""bench/label_quality.py: its forest summary (the self and ground-truth forests apart from the other models), and a
small run end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest


@pytest.fixture(scope="module")
def bench(bench_script: Callable[[str], ModuleType]) -> ModuleType:
    return bench_script("label_quality")


def test_oracles_named_gt_something_are_reported_apart_from_the_ground_truth_forest(bench: ModuleType) -> None:
    # Every oracle's name starts with "gt_" or "no_": a prefix test took the former for ground-truth forests.
    oracles = {name: 5.0 + i for i, name in enumerate(bench.ORACLES)}
    assert any(name.startswith("gt_") for name in oracles)
    scores = {"self": 4.0, "gt": 2.0, "self_f1": 3.0, "gt_f1": 3.0, "lrd": 9.0, **oracles}
    out = bench.forest_figures(scores, forest_seeds=2)
    assert out["ausc_ratio_self"] == pytest.approx(3.5)
    assert out["ausc_ratio_gt"] == pytest.approx(2.5)
    assert out["self_over_gt_by_forest_seed"] == pytest.approx([2.0, 1.0])
    assert out["self_over_gt"] == pytest.approx(1.5)
    assert out["ausc_ratio_lrd"] == pytest.approx(9.0)
    for name, value in oracles.items():
        assert out[f"ausc_ratio_{name}"] == pytest.approx(value)
    # The per-seed forests are summarised, not listed as models of their own.
    assert not {"ausc_ratio_self_f1", "ausc_ratio_gt_f1"} & out.keys()


def test_one_forest_seed_reads_the_package_forests_only(bench: ModuleType) -> None:
    out = bench.forest_figures({"self": 3.0, "gt": 2.0, "self_f1": 9.0, "lrd": 7.0}, forest_seeds=1)
    assert out["ausc_ratio_self"] == pytest.approx(3.0) and out["self_over_gt"] == pytest.approx(1.5)
    assert out["ausc_ratio_self_f1"] == pytest.approx(9.0)  # not a forest seed of this run


def test_forest_seeds_from_another_first_seed_read_their_own_forests(bench: ModuleType) -> None:
    scores = {"self": 3.0, "gt": 2.0, "self_f1": 4.0, "gt_f1": 2.0, "self_f2": 6.0, "gt_f2": 4.0, "lrd": 7.0}
    out = bench.forest_figures(scores, forest_seeds=2, first_forest_seed=1)
    assert out["self_over_gt_by_forest_seed"] == pytest.approx([2.0, 1.5])
    # Seed 0's forests ("self", "gt") are not this run's: the means are seeds 1 and 2's.
    assert out["ausc_ratio_self"] == pytest.approx(5.0) and out["ausc_ratio_gt"] == pytest.approx(3.0)
    assert out["ausc_ratio_lrd"] == pytest.approx(7.0)
    with pytest.raises(SystemExit):
        bench.main(["--confidence", "--first-forest-seed", "-1"])
    with pytest.raises(SystemExit):  # the second seed would be 2**32
        bench.main(["--confidence", "--first-forest-seed", str(2**32 - 1), "--forest-seeds", "2"])


def test_oracles_are_named_from_the_list(bench: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--oracles", "gt_in_band,gt_everywhere"])
    assert "--oracles takes names of gt_at_labels," in capsys.readouterr().err


def test_a_small_run_labels_trains_every_forest_and_mends_the_oracles_labels(bench: ModuleType, tmp_path: Path) -> None:
    """End to end at 306x92 (about 10 s): render, label, train the self, ground-truth and oracle forests, plot.

    Run as a command, as users run it (its thread cap is the process's own).
    """
    out, plot = tmp_path / "out", tmp_path / "lq.png"
    argv = ["--scenes", "orbit", "--seeds", "1-2", "--size", "306x92", "--frames", "14", "--oracles"]
    argv += ["--cache", str(tmp_path / "cache"), "--out", str(out), "--plot", str(plot)]
    run = subprocess.run(
        [sys.executable, str(Path(bench.__file__)), *argv], capture_output=True, text=True, timeout=600, check=False
    )
    assert run.returncode == 0, run.stderr[-3000:]
    summary = json.loads(run.stdout.strip().splitlines()[-1])
    rows = summary["sequences"]
    assert [r["seed"] for r in rows] == [1, 2] and all(r["frames"] > 0 for r in rows)
    # Orbit's labels at this size: 99 % accurate at 70-74 % coverage when written; the bounds leave room.
    for r in rows:
        assert r["accuracy"] >= 0.95 and r["positive_precision"] >= 0.97 and r["coverage"] >= 0.3, r
    scene = summary["scenes"]["orbit"]
    for key, _, larger_is_better in bench.FIGURES:
        # A sequence without a label of a class has no precision for it (NaN); the summary skips it, as here.
        values = [r[key] for r in rows if np.isfinite(r[key])]
        assert values or np.isnan(scene[key]["mean"]), key
        if values:
            assert scene[key]["mean"] == pytest.approx(np.mean(values), rel=1e-12)
            assert scene[key]["worst"] == (min(values) if larger_is_better else max(values))
    forests = scene["confidence"]
    assert forests["train_seeds"] == [1] and forests["test_seeds"] == [2]
    ratios = {k: v for k, v in forests.items() if k.startswith("ausc_ratio_")}
    assert {f"ausc_ratio_{name}" for name in ["self", "gt", "lrd", *bench.ORACLES]} <= ratios.keys()
    assert all(np.isfinite(v) and v >= 1.0 - 1e-9 for v in ratios.values()), ratios  # optimal is a lower bound
    assert forests["self_over_gt"] == pytest.approx(forests["ausc_ratio_self"] / forests["ausc_ratio_gt"])
    # Both forests rank far better than the left-right difference alone (78x optimal against 4-6x when written).
    assert max(forests["ausc_ratio_self"], forests["ausc_ratio_gt"]) < 0.5 * forests["ausc_ratio_lrd"]
    # The oracles' labels: ground truth on every pixel the labeler labelled, the unlabelled ones left alone.
    from selfcontra_ros.confidence.commands import iter_frames, training_matcher
    from selfcontra_ros.confidence.training import prior_band
    from selfcontra_ros.evaluation.metrics import ground_truth_labels
    from selfcontra_ros.labels import UNKNOWN
    from selfcontra_ros.matching.base import make_matcher

    own_root = out / "labels" / "orbit_s1"
    data = bench._sequence(tmp_path / "cache", "orbit", 1, 14, (306, 92))  # the rendered one, kept in the cache
    matcher = make_matcher(training_matcher([(data, own_root)]))
    checked = 0
    for frame in iter_frames(data):
        name = f"{frame.index:06d}.png"
        if not (own_root / "labels" / name).is_file():
            continue
        own = cv2.imread(str(own_root / "labels" / name), cv2.IMREAD_UNCHANGED)
        mended = cv2.imread(str(out / "oracles" / "gt_at_labels" / "orbit_s1" / "labels" / name), cv2.IMREAD_UNCHANGED)
        disparity = matcher.compute(frame.left, frame.right, with_right=False).left
        gt = ground_truth_labels(disparity, frame.gt_disparity)
        labelled = own != UNKNOWN
        assert labelled.any() and np.array_equal(mended[labelled], gt[labelled]), name
        assert (mended[~labelled] == UNKNOWN).all(), name
        # The unlabelled pixels with their true labels: in the band prior's band only, or all of them.
        in_band = cv2.imread(str(out / "oracles" / "gt_in_band" / "orbit_s1" / "labels" / name), cv2.IMREAD_UNCHANGED)
        unknown = cv2.imread(str(out / "oracles" / "gt_at_unknown" / "orbit_s1" / "labels" / name), -1)
        band = prior_band(disparity) & ~labelled
        assert band.any() and np.array_equal(in_band[band], gt[band]), name
        assert np.array_equal(in_band[~band], own[~band]), name
        assert np.array_equal(unknown[labelled], own[labelled]) and np.array_equal(unknown[~labelled], gt[~labelled])
        whole = cv2.imread(str(out / "oracles" / "gt_labelled_frames" / "orbit_s1" / "labels" / name), -1)
        assert np.array_equal(whole, gt), name
        checked += 1
    assert checked == rows[0]["frames"]
    # ... and only on the labelled frames: the last label_delay frames have no label, so none of their truth.
    labelled_frames = sorted(p.name for p in (own_root / "labels").glob("*.png"))
    whole_root = out / "oracles" / "gt_labelled_frames" / "orbit_s1" / "labels"
    whole_frames = sorted(p.name for p in whole_root.glob("*.png"))
    assert whole_frames == labelled_frames and 0 < len(labelled_frames) < 14
    image = cv2.imread(str(plot))
    assert image is not None and image.shape[0] > 100 and image.shape[1] > 100
