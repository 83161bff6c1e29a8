"""Loading the labeler's parameters from a ROS 2 parameter YAML file.

The file has the form ROS 2's ``--params-file`` reads::

    labeler:                # the node name (``/**`` also accepted)
      ros__parameters:
        matcher: {algorithm: sgbm, num_disparities: 128, ...}   # MatcherParams
        labeler: {window_size: ..., alpha_min_deg: 7.0, ...}   # LabelerParams
        confidence: {feature_set: gcp, retrain_every: 10, ...}  # ConfidenceParams
        threads: 0          # node-level keys (NODE_PARAMETERS) sit beside the sections

The ROS node flattens the nested sections to dotted parameter names
(``matcher.block_size``); :func:`to_ros_parameters` and
:func:`from_ros_parameters` convert between those names and the dataclasses.
The dataclasses hold the defaults; the package's ``config/labeler.yaml``
mirrors them (a test keeps both equal). A file may set only some keys; the
others keep their dataclass defaults.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

from selfcontra_ros.confidence.online import ConfidenceParams
from selfcontra_ros.cross_check import check_supported
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.matching.base import MatcherParams
from selfcontra_ros.resources import config_file

__all__ = [
    "DEFAULT_FILE",
    "NODE_NAMES",
    "NODE_PARAMETERS",
    "SECTIONS",
    "confidence_from_ros_parameters",
    "from_ros_parameters",
    "load_confidence_params",
    "load_params",
    "params_to_dict",
    "read_node_parameters",
    "read_parameter_file",
    "to_ros_parameters",
]

#: Name of the package's default parameter file in ``config/``.
DEFAULT_FILE = "labeler.yaml"

#: Node keys accepted at the top of a parameter file, in order of preference.
NODE_NAMES = ("labeler", "/**/labeler", "/**")

#: Parameter sections and the dataclass each one fills.
SECTIONS: dict[str, type] = {"matcher": MatcherParams, "labeler": LabelerParams, "confidence": ConfidenceParams}

#: Node-level parameters a file may set beside the sections, with their defaults (the node declares these):
#: ``threads`` caps every thread pool (:func:`selfcontra_ros.threads.limit_threads`; 0 = all cores given).
NODE_PARAMETERS: dict[str, int] = {"threads": 0}


def _load_document(path: Path) -> dict[str, Any]:
    """The ``ros__parameters`` mapping of a parameter file (see the module docstring)."""
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise SelfContraError(f"cannot read parameter file {path}: {exc}") from exc
    except yaml.YAMLError as exc:
        raise SelfContraError(f"parameter file {path} is not valid YAML: {exc}") from exc
    if not isinstance(document, dict):
        raise SelfContraError(f"parameter file {path}: expected a mapping '<node>: ros__parameters: ...' at the top")
    node = next((name for name in NODE_NAMES if name in document), None)
    if node is None:
        raise SelfContraError(
            f"parameter file {path}: expected a top-level key {' or '.join(repr(n) for n in NODE_NAMES)}, "
            f"found {sorted(map(str, document))}"
        )
    body = document[node]
    if not isinstance(body, dict) or not isinstance(body.get("ros__parameters"), dict):
        raise SelfContraError(f"parameter file {path}: '{node}' must hold a 'ros__parameters' mapping")
    parameters: dict[str, Any] = body["ros__parameters"]
    return parameters


def read_parameter_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """Return the ``ros__parameters`` sections of a labeler parameter file.

    Args:
        path: YAML file of the form shown in the module docstring.

    Returns:
        Section name (``matcher``, ``labeler``) -> its key/value mapping;
        absent sections are empty.

    Raises:
        SelfContraError: if the file is missing, not YAML, lacks the
            ``<node>: ros__parameters:`` structure, or has an unknown section.
    """
    path = Path(path)
    parameters = _load_document(path)
    sections: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
    for name, values in parameters.items():
        if name in NODE_PARAMETERS:
            continue  # read by read_node_parameters
        if name not in SECTIONS:
            raise SelfContraError(
                f"parameter file {path}: unknown section {name!r} under ros__parameters; expected {sorted(SECTIONS)} "
                f"or a node-level key {sorted(NODE_PARAMETERS)}"
            )
        if values is None:
            continue
        if not isinstance(values, dict):
            raise SelfContraError(f"parameter file {path}: section {name!r} must be a mapping, got {values!r}")
        sections[name] = dict(values)
    return sections


def read_node_parameters(path: str | Path | None = None) -> dict[str, int]:
    """Return the node-level keys of a parameter file (:data:`NODE_PARAMETERS`), defaults for those it lacks.

    Args:
        path: the YAML file; ``None`` reads the package's ``config/labeler.yaml``.

    Returns:
        Name -> value, e.g. ``{"threads": 0}`` (threads per pool, 0 = all cores).

    Raises:
        SelfContraError: the file cannot be read or a value is not an integer >= 0.
    """
    resolved = Path(path) if path is not None else config_file(DEFAULT_FILE)
    parameters = _load_document(resolved)
    values = dict(NODE_PARAMETERS)
    for name in NODE_PARAMETERS:
        if name not in parameters:
            continue
        value = parameters[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise SelfContraError(f"parameter file {resolved}: {name!r} is {value!r}; expected an integer >= 0")
        values[name] = value
    return values


def _coerce(cls: type, values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """Check keys against ``cls``'s fields and widen YAML ints/lists to the default's float/tuple type."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise SelfContraError(
            f"{where}: unknown {cls.__name__} key(s) {', '.join(map(repr, unknown))}; known keys: {sorted(fields)}"
        )
    out: dict[str, Any] = {}
    for key, value in values.items():
        default = fields[key].default
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        out[key] = value
    return out


@contextmanager
def _named_errors(where: str) -> Iterator[None]:
    """Re-raise validation errors as SelfContraError naming ``where`` (the file or the ROS parameters)."""
    try:
        yield
    except SelfContraError as exc:
        if where in str(exc):
            raise
        raise SelfContraError(f"{where}: {exc}") from exc
    except (TypeError, ValueError) as exc:
        raise SelfContraError(f"{where}: {exc}") from exc


def _build(sections: Mapping[str, Mapping[str, Any]], where: str) -> tuple[MatcherParams, LabelerParams]:
    with _named_errors(where):
        matcher = MatcherParams(**_coerce(MatcherParams, sections.get("matcher", {}), f"{where}, section 'matcher'"))
        labeler = LabelerParams.from_dict(
            _coerce(LabelerParams, sections.get("labeler", {}), f"{where}, section 'labeler'")
        )
        check_supported(matcher, labeler)
    return matcher, labeler


def load_params(path: str | Path | None = None) -> tuple[MatcherParams, LabelerParams]:
    """Load matcher and labeler parameters from a parameter file.

    Args:
        path: the YAML file; ``None`` loads the package's ``config/labeler.yaml``.

    Returns:
        ``(MatcherParams, LabelerParams)``; keys the file does not set keep
        their dataclass defaults.

    Raises:
        SelfContraError: if the file cannot be read, has an unknown key
            (named together with the file) or a value fails validation.
    """
    resolved = Path(path) if path is not None else config_file(DEFAULT_FILE)
    return _build(read_parameter_file(resolved), f"parameter file {resolved}")


def _build_confidence(sections: Mapping[str, Mapping[str, Any]], where: str) -> ConfidenceParams:
    with _named_errors(where):
        values = _coerce(ConfidenceParams, sections.get("confidence", {}), f"{where}, section 'confidence'")
        return ConfidenceParams(**values)


def load_confidence_params(path: str | Path | None = None) -> ConfidenceParams:
    """Load the ``confidence`` section of a parameter file (defaults for keys it does not set).

    Args:
        path: the YAML file; ``None`` loads the package's ``config/labeler.yaml``.

    Raises:
        SelfContraError: as :func:`load_params`.
    """
    resolved = Path(path) if path is not None else config_file(DEFAULT_FILE)
    return _build_confidence(read_parameter_file(resolved), f"parameter file {resolved}")


def params_to_dict(
    matcher: MatcherParams, labeler: LabelerParams, confidence: ConfidenceParams | None = None
) -> dict[str, dict[str, Any]]:
    """Return ``{"matcher": {...}, "labeler": {...}}`` (and ``"confidence"`` when given), the YAML's nested form."""

    def plain(params: Any) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(params).items()}

    nested = {"matcher": plain(matcher), "labeler": plain(labeler)}
    if confidence is not None:
        nested["confidence"] = plain(confidence)
    return nested


def to_ros_parameters(
    matcher: MatcherParams, labeler: LabelerParams, confidence: ConfidenceParams | None = None
) -> dict[str, Any]:
    """Return the ROS 2 parameter names (``section.key``) and values of the dataclasses."""
    nested = params_to_dict(matcher, labeler, confidence)
    return {f"{section}.{key}": value for section, values in nested.items() for key, value in values.items()}


def confidence_from_ros_parameters(values: Mapping[str, Any]) -> ConfidenceParams:
    """Build :class:`ConfidenceParams` from the ``confidence.<key>`` names among ``values`` (others ignored).

    Raises:
        SelfContraError: on an unknown ``confidence.`` key or a value failing validation.
    """
    section = {
        name.partition(".")[2]: value for name, value in values.items() if name.partition(".")[0] == "confidence"
    }
    return _build_confidence({"confidence": section}, "ROS parameters")


def from_ros_parameters(values: Mapping[str, Any]) -> tuple[MatcherParams, LabelerParams]:
    """Build the dataclasses from dotted ROS 2 parameter names (``matcher.block_size``, ...).

    Names outside the sections are rejected, so a typo in a launch file
    does not silently fall back to a default; ``confidence.*`` names are
    accepted and left to :func:`confidence_from_ros_parameters`.

    Raises:
        SelfContraError: on an unknown name or a value failing validation.
    """
    sections: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
    for name, value in values.items():
        section, _, key = name.partition(".")
        if section not in SECTIONS or not key:
            raise SelfContraError(
                f"ROS parameter {name!r}: expected 'matcher.<key>', 'labeler.<key>' or 'confidence.<key>'"
            )
        sections[section][key] = value
    return _build(sections, "ROS parameters")
