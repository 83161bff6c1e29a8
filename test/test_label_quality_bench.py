"""bench/label_quality.py's forest summary: the self and ground-truth forests apart from the other models."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

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
