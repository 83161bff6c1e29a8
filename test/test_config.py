"""Parameter files: the package default equals the dataclass defaults, round trips, clear errors."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from selfcontra_ros.confidence.online import ConfidenceParams
from selfcontra_ros.config import (
    confidence_from_ros_parameters,
    from_ros_parameters,
    load_confidence_params,
    load_params,
    params_to_dict,
    read_parameter_file,
    to_ros_parameters,
)
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.resources import config_file


def _write(path: Path, parameters: object, node: str = "labeler") -> Path:
    path.write_text(yaml.safe_dump({node: {"ros__parameters": parameters}}))
    return path


def test_package_yaml_mirrors_dataclass_defaults() -> None:
    """One source of truth: every field is in the YAML with the dataclass default, of the same type (for ROS)."""
    sections = read_parameter_file(config_file("labeler.yaml"))
    for name, cls in (("matcher", MatcherParams), ("labeler", LabelerParams), ("confidence", ConfidenceParams)):
        defaults = dataclasses.asdict(cls())
        assert sections[name] == defaults, name
        for key, value in defaults.items():
            assert type(sections[name][key]) is type(value), f"{name}.{key}"
    assert load_params(None) == (MatcherParams(), LabelerParams())
    assert load_confidence_params(None) == ConfidenceParams()


def test_confidence_section_round_trips_and_is_checked(tmp_path: Path) -> None:
    confidence = ConfidenceParams(feature_set="ensemble", retrain_every=3, confidence_threshold=0.7, model_out="m.npz")
    path = _write(tmp_path / "p.yaml", params_to_dict(MatcherParams(), LabelerParams(), confidence))
    assert load_confidence_params(path) == confidence
    assert load_params(path) == (MatcherParams(), LabelerParams())
    flat = to_ros_parameters(MatcherParams(), LabelerParams(), confidence)
    assert flat["confidence.retrain_every"] == 3
    assert confidence_from_ros_parameters(flat) == confidence
    assert from_ros_parameters(flat) == (MatcherParams(), LabelerParams())
    _write(tmp_path / "bad.yaml", {"confidence": {"feature_set": "sift"}})
    with pytest.raises(SelfContraError, match="feature_set"):
        load_confidence_params(tmp_path / "bad.yaml")
    _write(tmp_path / "typo.yaml", {"confidence": {"retrain_evry": 3}})
    with pytest.raises(SelfContraError, match="retrain_evry"):
        load_confidence_params(tmp_path / "typo.yaml")


def test_round_trip_through_a_file(tmp_path: Path) -> None:
    matcher = MatcherParams(algorithm="bm", num_disparities=64, block_size=9, speckle_window_size=50, speckle_range=2)
    labeler = LabelerParams(window_size=20, label_delay=10, alpha_min_deg=7.5, stage1_tolerance="sum")
    path = _write(tmp_path / "p.yaml", params_to_dict(matcher, labeler))
    assert load_params(path) == (matcher, labeler)
    assert load_params(str(path)) == (matcher, labeler)


def test_round_trip_through_ros_parameter_names() -> None:
    matcher = MatcherParams(mode="hh", p1=100, p2=400)
    labeler = LabelerParams(sigma_max=3.0)
    flat = to_ros_parameters(matcher, labeler)
    assert flat["matcher.mode"] == "hh" and flat["labeler.sigma_max"] == 3.0
    assert from_ros_parameters(flat) == (matcher, labeler)
    with pytest.raises(SelfContraError, match="window"):
        from_ros_parameters({"window_size": 3})


def test_partial_file_keeps_defaults_and_widens_ints(tmp_path: Path) -> None:
    path = _write(tmp_path / "p.yaml", {"labeler": {"alpha_min_deg": 15}}, node="/**")
    matcher, labeler = load_params(path)
    assert matcher == MatcherParams()
    assert labeler == LabelerParams(alpha_min_deg=15.0)
    assert isinstance(labeler.alpha_min_deg, float)


def test_unknown_key_names_key_and_file(tmp_path: Path) -> None:
    path = _write(tmp_path / "typo.yaml", {"matcher": {"blocksize": 7}})
    with pytest.raises(SelfContraError, match=r"'blocksize'.*") as info:
        load_params(path)
    assert str(path) in str(info.value)
    path = _write(tmp_path / "typo2.yaml", {"labeler": {"window": 7}})
    with pytest.raises(SelfContraError, match="'window'") as info:
        load_params(path)
    assert str(path) in str(info.value)
    path = _write(tmp_path / "section.yaml", {"matchers": {}})
    with pytest.raises(SelfContraError, match="'matchers'"):
        load_params(path)


def test_invalid_values_and_malformed_files(tmp_path: Path) -> None:
    path = _write(tmp_path / "bad.yaml", {"matcher": {"num_disparities": 100}})
    with pytest.raises(SelfContraError, match="num_disparities") as info:
        load_params(path)
    assert str(path) in str(info.value)
    path = _write(tmp_path / "bad2.yaml", {"labeler": {"label_delay": 25}})
    with pytest.raises(SelfContraError, match="label_delay"):
        load_params(path)
    path = _write(tmp_path / "bad3.yaml", {"labeler": {"stage3_min_free_space_views": -1}})
    with pytest.raises(SelfContraError, match="stage3_min_free_space_views"):
        load_params(path)
    path = _write(tmp_path / "bad4.yaml", {"labeler": {"stage2_positive_accuracy_ratio": 0.5}})
    with pytest.raises(SelfContraError, match="stage2_positive_accuracy_ratio"):
        load_params(path)
    path = _write(tmp_path / "bad5.yaml", {"labeler": {"stage3_min_depth_ratio": 0.5}})
    with pytest.raises(SelfContraError, match="stage3_min_depth_ratio"):
        load_params(path)
    path = _write(tmp_path / "bad6.yaml", {"labeler": {"cross_check_matcher": "sgbm"}})
    with pytest.raises(SelfContraError, match="cross_check_matcher"):
        load_params(path)
    path = _write(tmp_path / "bad7.yaml", {"labeler": {"cross_check_min_difference_px": 0}})
    with pytest.raises(SelfContraError, match="cross_check_min_difference_px"):
        load_params(path)
    path = _write(
        tmp_path / "bad8.yaml", {"matcher": {"algorithm": "external"}, "labeler": {"cross_check_matcher": "census_sgm"}}
    )
    with pytest.raises(SelfContraError, match="stereo images"):
        load_params(path)
    with pytest.raises(SelfContraError, match="cannot read"):
        load_params(tmp_path / "missing.yaml")
    (tmp_path / "node.yaml").write_text("talker:\n  ros__parameters: {}\n")
    with pytest.raises(SelfContraError, match="top-level key"):
        load_params(tmp_path / "node.yaml")
    (tmp_path / "flat.yaml").write_text("labeler:\n  window_size: 3\n")
    with pytest.raises(SelfContraError, match="ros__parameters"):
        load_params(tmp_path / "flat.yaml")
    (tmp_path / "broken.yaml").write_text("labeler: [\n")
    with pytest.raises(SelfContraError, match="not valid YAML"):
        load_params(tmp_path / "broken.yaml")
