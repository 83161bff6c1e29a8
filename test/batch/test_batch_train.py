"""batch train on the session's Ray cluster gives the forest of selfcontra train (identical arrays)."""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from selfcontra_ros.batch.train import batch_train
from selfcontra_ros.cli import main
from selfcontra_ros.confidence.commands import collect_samples, train_command
from selfcontra_ros.confidence.forest import load_model
from selfcontra_ros.errors import BatchError

#: a small forest: the test compares models, it does not need a good one
FOREST = {"n_estimators": 4, "max_depth": 8, "min_samples_leaf": 5}
NAMES = ("seqroot_00", "street", "orbit")


@pytest.fixture(scope="module")
def labelled(
    batch_run: tuple[Path, dict[str, Any], Path, str], batch_inputs: dict[str, Path]
) -> tuple[Path, list[str]]:
    """The session's batch-labelled folder and the data to train on: a sequence, two bags and the corrupt bag."""
    return batch_run[0], [str(batch_inputs[name]) for name in (*NAMES, "corrupt")]


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def test_batch_train_gives_the_forest_of_train(labelled: tuple[Path, list[str]], tmp_path: Path) -> None:
    out, data = labelled
    notes: list[str] = []
    summary = batch_train("gcp", out, data, tmp_path / "batch.npz", forest=FOREST, progress=False, echo=notes.append)
    assert summary["inputs"] == list(NAMES) and summary["left_out"] == ["corrupt"]
    assert any("left out" in note and "corrupt" in note for note in notes)

    pairs = [(d, str(out / name)) for d, name in zip(data, NAMES, strict=False)]
    sequential = train_command(pairs, "gcp", tmp_path / "train.npz", forest=FOREST)
    assert summary["samples"] == sequential["samples"] > 100 and summary["frames"] == sequential["frames"]
    got, want = _arrays(tmp_path / "batch.npz"), _arrays(tmp_path / "train.npz")
    assert got.keys() == want.keys() and {"metadata"} < set(want)
    for name, array in want.items():
        assert got[name].dtype == array.dtype and np.array_equal(got[name], array), name


def test_each_input_draws_its_own_samples(labelled: tuple[Path, list[str]]) -> None:
    """The samples of one input do not depend on the inputs before it: what makes parallel sampling exact."""
    out, data = labelled
    pairs = [(d, str(out / name)) for d, name in zip(data, NAMES, strict=False)]
    both, _ = collect_samples(pairs[:2], ["gcp"])
    first, _ = collect_samples(pairs[:1], ["gcp"])
    n = first["gcp"].labels.size
    assert 0 < n < both["gcp"].labels.size
    np.testing.assert_array_equal(both["gcp"].features[:n], first["gcp"].features)
    capped, _ = collect_samples(pairs[:1], ["gcp"], max_per_input=40)
    assert capped["gcp"].labels.size == 40 and capped["gcp"].labels.sum() == 20  # balanced within the cap


def test_batch_train_without_ray_and_without_labels(
    labelled: tuple[Path, list[str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out, data = labelled
    monkeypatch.setitem(sys.modules, "ray", None)
    notes: list[str] = []
    summary = batch_train("gcp", out, data[:1], tmp_path / "m.npz", forest=FOREST, progress=False, echo=notes.append)
    assert summary["engine"].startswith("this process") and any("Ray is not installed" in n for n in notes)
    with pytest.raises(BatchError, match="none of the 1 inputs has a complete label result"):
        batch_train("gcp", tmp_path / "empty", data[:1], tmp_path / "n.npz", progress=False, echo=None)


def test_the_batch_train_command(
    labelled: tuple[Path, list[str]],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out, data = labelled
    monkeypatch.setitem(sys.modules, "ray", None)
    args = ["batch", "train", "--features", "gcp", "--labels-from", str(out), "--data", data[1], data[3]]
    assert main([*args, "--out", str(tmp_path / "cli.npz"), "--max-per-input", "60"]) == 0
    printed = capsys.readouterr().out
    assert "left out (no complete label result" in printed and "corrupt" in printed
    assert re.search(r"trained gcp forest on 60 samples from \d+ frames of 1 input\(s\)", printed)
    assert (tmp_path / "cli.npz").is_file()
    assert load_model(tmp_path / "cli.npz").metadata["forest"]["random_state"] == 0  # FOREST's
    assert main([*args, "--out", str(tmp_path / "seed.npz"), "--max-per-input", "60", "--forest-seed", "7"]) == 0
    assert load_model(tmp_path / "seed.npz").metadata["forest"]["random_state"] == 7
