"""What every offline run writes beside its output: ``metrics.json`` and the figures of each labelled view.

The sequence labeler (:func:`selfcontra_ros.pipeline.label_sequence`), the bag
labeler (:func:`selfcontra_ros.bags.label_bag.label_bag`), the odometry
command (:mod:`selfcontra_ros.odometry.run`) and the batch runner
(:mod:`selfcontra_ros.batch`) share these helpers. They live in a module of
their own, below all of them, so that none of those modules imports another
one back: :mod:`selfcontra_ros.pipeline` is the one that chooses the front end
of an input and imports the bag labeler, never the other way round.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.evaluation.metrics import label_metrics, label_shares
from selfcontra_ros.labeler import LabelResult

__all__ = [
    "LABELS_COLOR_DIR",
    "LABELS_DIR",
    "METRICS_FILE",
    "PendingView",
    "evaluate_view",
    "json_safe",
    "write_json",
]

#: Label images of a sequence run, ``OUT/labels/NNNNNN.png`` (mono8, codes 0/1/2).
LABELS_DIR = "labels"
#: Their colour view, ``OUT/labels_color/NNNNNN.png``.
LABELS_COLOR_DIR = "labels_color"
#: The report of a run: ``OUT/metrics.json`` (sequence) or ``OUT_BAG/metrics.json`` (bag).
METRICS_FILE = "metrics.json"


@dataclass
class PendingView:
    """What the evaluation of a view needs once the labeler releases it."""

    disparity: NDArray[np.float32]
    gt_disparity: NDArray[np.float32] | None


def evaluate_view(result: LabelResult, pending: PendingView) -> dict[str, float]:
    """Figures of one labelled view: label metrics with ground truth, else the label shares."""
    if pending.gt_disparity is None:
        return label_shares(result.labels, pending.disparity)
    return label_metrics(result.labels, pending.disparity, pending.gt_disparity, stage2_labels=result.stage2_labels)


def json_safe(value: Any) -> Any:
    """Return ``value`` with NaN/inf floats as ``None`` and numpy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: Path, report: dict[str, Any]) -> None:
    """Write a metrics/report dictionary as indented JSON (:func:`json_safe`: undefined figures as ``null``)."""
    path.write_text(json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n", encoding="utf-8")
