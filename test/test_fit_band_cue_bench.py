"""bench/fit_band_cue.py: a small fit end to end, and the rank AUC it reports."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from selfcontra_ros.confidence.band_cue import FEATURES
from selfcontra_ros.confidence.forest import load_model


@pytest.fixture(scope="module")
def bench(bench_script: Callable[[str], ModuleType]) -> ModuleType:
    return bench_script("fit_band_cue")


def test_rank_auc_counts_pairs(bench: ModuleType) -> None:
    wrong = np.array([True, True, False, False, False])
    assert bench.rank_auc(np.array([5.0, 4.0, 3.0, 2.0, 1.0]), wrong) == pytest.approx(1.0)
    assert bench.rank_auc(np.array([1.0, 2.0, 3.0, 4.0, 5.0]), wrong) == pytest.approx(0.0)
    # One of the six pairs reversed, one tied (half).
    assert bench.rank_auc(np.array([5.0, 2.5, 3.0, 2.5, 1.0]), wrong) == pytest.approx((4 + 0.5) / 6)
    assert np.isnan(bench.rank_auc(np.ones(3), np.zeros(3, bool)))


def test_a_small_fit_writes_a_band_cue_that_ranks_the_test_seed(bench: ModuleType, tmp_path: Path) -> None:
    """Orbit at 306x92, two sequences of 12 frames (about 20 s): fit on one, score the other."""
    out = tmp_path / "cue.npz"
    argv = ["--scenes", "orbit", "--seeds", "1", "--test-seeds", "2", "--size", "306x92", "--frames", "12"]
    argv += ["--frame-step", "4", "--trees", "4", "--min-leaf", "20", "--cache", str(tmp_path / "cache")]
    argv += ["--out", str(out)]
    run = subprocess.run(
        [sys.executable, str(Path(bench.__file__)), *argv], capture_output=True, text=True, timeout=600, check=False
    )
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(run.stdout.strip().splitlines()[-1])["test"]["orbit"]
    assert report["pixels"] > 500 and 0 < report["wrong_share"] < 1
    # Better than chance on an unseen sequence (0.8-0.9 at KITTI size; small images are harder).
    assert report["auc_cue"] > 0.6, report
    model = load_model(out)
    assert model.metadata["feature_names"] == list(FEATURES) and model.n_trees == 4
    assert model.metadata["fitted_on"]["seeds"] == [1] and model.metadata["test"] == {"seeds": [2], "orbit": report}
