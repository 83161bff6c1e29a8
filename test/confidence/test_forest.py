"""The forest's model file: exact round trip, scikit-learn agreement, and no code execution on load."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
from sklearn.ensemble import RandomForestClassifier

from selfcontra_ros.confidence.forest import ModelError, fit_forest, load_model, save_model

SMALL = {"n_estimators": 4, "max_depth": 6, "min_samples_leaf": 5}


def data(n: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 5)).astype(np.float32)
    y = (x[:, 0] + 0.5 * x[:, 3] + 0.3 * rng.normal(size=n)) > 0
    return x, y


def test_predictor_matches_scikit_learn_and_survives_a_round_trip(tmp_path: Path) -> None:
    x, y = data()
    model = fit_forest(x, y, {"feature_set": "test"}, forest=SMALL)
    reference = RandomForestClassifier(criterion="entropy", random_state=0, **SMALL).fit(x, y.astype(np.int8))
    x_test, _ = data(300, seed=1)
    expected = reference.predict_proba(x_test)[:, 1]
    np.testing.assert_allclose(model.predict(x_test), expected, atol=1e-6)
    path = save_model(model, tmp_path / "model.npz")
    loaded = load_model(path)
    np.testing.assert_array_equal(loaded.predict(x_test), model.predict(x_test))
    assert loaded.metadata["feature_set"] == "test"
    assert loaded.n_trees == 4


class _Payload:
    """Unpickling this object opens (and so creates) a marker file: proof that code ran."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str, str]]:
        return (open, (str(self.marker), "w"))


def test_crafted_model_files_never_execute_code(tmp_path: Path) -> None:
    x, y = data()
    good = fit_forest(x, y, forest=SMALL)
    arrays = {
        name: getattr(good, name)
        for name in ("tree_offsets", "children_left", "children_right", "feature", "threshold", "positive")
    }
    marker = tmp_path / "code_ran"
    crafted = tmp_path / "crafted.npz"
    # A model whose metadata is a pickled object array.
    np.savez(crafted, metadata=np.array([_Payload(marker)], dtype=object), **arrays)
    # The payload works: loading it the unsafe way does run code.
    control = tmp_path / "control_ran"
    np.savez(tmp_path / "control.npz", payload=np.array([_Payload(control)], dtype=object))
    with np.load(tmp_path / "control.npz", allow_pickle=True) as unsafe:
        unsafe["payload"]
    assert control.exists()
    with pytest.raises(ModelError):
        load_model(crafted)
    # A bare pickle stream named like a model.
    raw = tmp_path / "raw.npz"
    raw.write_bytes(pickle.dumps(_Payload(marker)))
    with pytest.raises(ModelError):
        load_model(raw)
    # An object array among the node arrays.
    np.savez(
        tmp_path / "nodes.npz",
        metadata=np.frombuffer(b"{}", np.uint8),
        **{**arrays, "threshold": np.array([_Payload(marker)], dtype=object)},
    )
    with pytest.raises(ModelError):
        load_model(tmp_path / "nodes.npz")
    assert not marker.exists()


def test_inconsistent_trees_are_refused(tmp_path: Path) -> None:
    x, y = data()
    model = fit_forest(x, y, forest=SMALL)
    model.children_left[0] = 10**6  # a child outside the tree
    path = save_model(model, tmp_path / "bad.npz")
    with pytest.raises(ModelError, match="outside its tree"):
        load_model(path)
    with pytest.raises(ModelError, match="does not exist"):
        load_model(tmp_path / "missing.npz")


def test_the_model_file_is_the_path_given(tmp_path: Path) -> None:
    x, y = data()
    model = fit_forest(x, y, {"feature_set": "test"}, forest=SMALL)
    # A suffix of the user's own is kept (evaluate-confidence --model park.model must find it) ...
    assert save_model(model, tmp_path / "park.model") == tmp_path / "park.model"
    assert load_model(tmp_path / "park.model").n_trees == 4
    # ... and only a bare name gets .npz.
    assert save_model(model, tmp_path / "park") == tmp_path / "park.npz"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["park.model", "park.npz"]  # no temporary left behind
