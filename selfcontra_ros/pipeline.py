"""Offline labeling of a stereo sequence: the ``selfcontra label`` command.

:func:`label_sequence` runs the query algorithm and the self-contradiction
labeler over a KITTI-layout sequence (real or synthetic) and writes, per
labelled frame ``N`` (zero-padded to six digits, the frame's index in the
sequence):

- ``OUT/labels/NNNNNN.png``: mono8 label image, codes 0 unknown / 1 positive / 2 negative;
- ``OUT/labels_color/NNNNNN.png``: the colour view (green / red / blue);

and ``OUT/metrics.json``::

    {
      "sequence": "<input path>",
      "status": "complete",                    # or "interrupted" (Ctrl-C, SIGTERM) / "failed": frames so far
      "frames": [{"frame": 12, "stamp": 1.2, "accuracy": ..., "coverage": ..., ...}, ...],
      "mean": {"accuracy": ..., ...},          # mean over frames of the per-frame values, NaN skipped
      "params": {"matcher": {...}, "labeler": {...}},
      "skipped_frames": [...],                 # views the labeler's keyframe rule rejected
      "has_ground_truth": true,
      "runtime_s": ...
    }

The per-frame figures are those of :mod:`selfcontra_ros.evaluation.metrics`:
with ground-truth disparity all of :func:`~selfcontra_ros.evaluation.metrics.label_metrics`
(accuracy, coverage, precisions, ``stage2_*``, ...); without it (real KITTI
odometry) only the ones needing none, :func:`~selfcontra_ros.evaluation.metrics.label_shares`
(``query_valid_share``, ``label_positive_share``, ``label_negative_share``,
``label_unknown_share``). Undefined figures (NaN) are written as ``null``.

The function is pure in the sense of DESIGN section 9: it reads only its
arguments' files, writes only below ``out_dir`` and keeps no global state, so
a cluster engine can run it on many sequences at once.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.config import load_params, params_to_dict
from selfcontra_ros.datasets.kitti import OdometrySequence, StereoFrame, open_sequence
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.evaluation.metrics import label_metrics, label_shares, mean_metrics
from selfcontra_ros.labeler import LabelResult
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.session import LabelingSession

__all__ = [
    "LABELS_COLOR_DIR",
    "LABELS_DIR",
    "METRICS_FILE",
    "PendingView",
    "evaluate_view",
    "json_safe",
    "label_sequence",
    "write_json",
]

LABELS_DIR = "labels"
LABELS_COLOR_DIR = "labels_color"
METRICS_FILE = "metrics.json"


@dataclass
class PendingView:
    """What the evaluation of a view needs once the labeler releases it."""

    disparity: NDArray[np.float32]
    gt_disparity: NDArray[np.float32] | None


def _frame_indices(sequence: OdometrySequence, frames: slice | None) -> list[int]:
    indices = range(len(sequence))
    return list(indices[frames] if frames is not None else indices)


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


def _write_png(path: Path, image: NDArray[np.uint8]) -> None:
    if not cv2.imwrite(str(path), image):
        raise SelfContraError(f"cannot write image {path}")


def _write_labels(out_dir: Path, index: int, labels: NDArray[np.uint8]) -> None:
    name = f"{index:06d}.png"
    _write_png(out_dir / LABELS_DIR / name, np.ascontiguousarray(labels, dtype=np.uint8))
    # colorize_labels gives RGB; OpenCV writes BGR.
    _write_png(out_dir / LABELS_COLOR_DIR / name, np.ascontiguousarray(colorize_labels(labels)[:, :, ::-1]))


def evaluate_view(result: LabelResult, pending: PendingView) -> dict[str, float]:
    """Figures of one labelled view: label metrics with ground truth, else the label shares."""
    if pending.gt_disparity is None:
        return label_shares(result.labels, pending.disparity)
    return label_metrics(result.labels, pending.disparity, pending.gt_disparity, stage2_labels=result.stage2_labels)


def _run(
    sequence: OdometrySequence, indices: list[int], session: LabelingSession, out_dir: Path
) -> Iterator[tuple[int, float, dict[str, float]]]:
    """Match and label the frames; yield ``(index, stamp, figures)`` per labelled frame, in labelling order."""
    pending: dict[int, PendingView] = {}
    stamps: dict[int, float] = {}

    def release(results: list[LabelResult]) -> Iterator[tuple[int, float, dict[str, float]]]:
        for result in results:
            index = cast(int, result.key)  # _run passes the frame index as the key
            _write_labels(out_dir, index, result.labels)
            yield index, stamps.pop(index), evaluate_view(result, pending.pop(index))

    for index in tqdm(indices, desc="label", unit="frame"):
        interrupts.check()  # between frames: every label PNG written so far is whole
        frame: StereoFrame = sequence[index]
        if frame.pose is None:
            raise SelfContraError(f"frame {index} of {sequence.root} has no pose")
        output = session.process(frame.left, frame.right, frame.pose, stamp=frame.stamp, key=index)
        if not output.skipped:  # a view the keyframe rule dropped is never labelled
            pending[index] = PendingView(disparity=output.disparity, gt_disparity=frame.gt_disparity)
            stamps[index] = frame.stamp
        yield from release(output.labelled)
    yield from release(session.flush())


def label_sequence(
    seq_dir: Path,
    out_dir: Path,
    *,
    params_file: str | Path | None = None,
    frames: slice | None = None,
    estimate_poses: bool = False,
) -> dict[str, Any]:
    """Label a KITTI-layout stereo sequence and evaluate the labels.

    Args:
        seq_dir: dataset root holding ``sequences/XX`` (one sequence) or a
            ``sequences/XX`` folder; needs poses (``poses/XX.txt``).
        out_dir: output folder; created if needed (see the module docstring).
        params_file: parameter YAML; ``None`` uses the package's ``config/labeler.yaml``.
        frames: the frame indices to run (a Python slice); ``None`` runs all.
        estimate_poses: when the sequence has no poses, estimate them with the
            package's stereo visual odometry; frames whose pose is unreliable
            are not labelled (listed as ``unreliable_pose_frames``).

    Returns:
        The content of ``metrics.json`` (with NaN, not ``null``, for undefined figures).

    Raises:
        SelfContraError: if the sequence cannot be read, has no poses, the
            parameters are invalid, or the matcher is ``external`` (a
            sequence folder holds no external disparity).
        Interrupted: SIGINT or SIGTERM (:mod:`selfcontra_ros.interrupts`), after
            ``metrics.json`` of the frames labelled so far is written.
    """
    started = time.perf_counter()
    seq_dir, out_dir = Path(seq_dir), Path(out_dir)
    matcher_params, labeler_params = load_params(params_file)
    if matcher_params.algorithm == "external":
        raise SelfContraError(
            "matcher.algorithm 'external' needs disparity maps from the caller; a sequence folder has none. "
            "Use 'sgbm' or 'bm' for offline labeling."
        )
    sequence = open_sequence(seq_dir)
    reliable: NDArray[np.bool_] | None = None
    if sequence.poses is None:
        if not estimate_poses:
            raise SelfContraError(
                f"sequence {seq_dir} has no poses (expected poses/<sequence>.txt beside sequences/); "
                "the labeler needs the camera pose of every frame: pass --estimate-poses to estimate them "
                "with stereo visual odometry"
            )
        from selfcontra_ros.odometry.run import poses_for_sequence

        sequence.poses, reliable = poses_for_sequence(sequence, progress=True)
    indices = _frame_indices(sequence, frames)
    unreliable = [] if reliable is None else [i for i in indices if not reliable[i]]
    indices = [i for i in indices if i not in set(unreliable)]  # an unreliable pose would make false labels
    if len(indices) == 0:
        raise SelfContraError(f"frame range {frames} selects no frame of the {len(sequence)} in {seq_dir}")
    for sub in (LABELS_DIR, LABELS_COLOR_DIR):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)

    session = LabelingSession(sequence.camera, matcher_params, labeler_params)
    params = params_to_dict(matcher_params, labeler_params)
    per_frame: list[tuple[int, float, dict[str, float]]] = []
    status = "failed"
    try:
        per_frame.extend(_run(sequence, indices, session, out_dir))
        status = "complete"
    except KeyboardInterrupt as exc:
        status = "interrupted"
        if isinstance(exc, interrupts.Interrupted):
            exc.done = (
                f"labelled {len(per_frame)} of {len(indices)} frames; wrote their labels to {out_dir} "
                f"and {out_dir / METRICS_FILE} (status interrupted)"
            )
        raise
    finally:
        report = _write_report(out_dir, seq_dir, per_frame, indices, status, reliable, unreliable, params, started)
    return report


def _write_report(
    out_dir: Path,
    seq_dir: Path,
    per_frame: list[tuple[int, float, dict[str, float]]],
    indices: list[int],
    status: str,
    reliable: NDArray[np.bool_] | None,
    unreliable: list[int],
    params: dict[str, Any],
    started: float,
) -> dict[str, Any]:
    """Write ``metrics.json`` for the frames labelled so far (all, or those before an interrupt); return it."""
    per_frame.sort(key=lambda item: item[0])
    labelled = {index for index, _, _ in per_frame}
    has_gt = any("accuracy" in figures for _, _, figures in per_frame)

    report: dict[str, Any] = {
        "sequence": str(seq_dir),
        "status": status,
        "frames": [{"frame": index, "stamp": stamp, **figures} for index, stamp, figures in per_frame],
        "mean": mean_metrics(figures for _, _, figures in per_frame),
        "params": params,
        "skipped_frames": [index for index in indices if index not in labelled],
        "pose_source": "ground truth file" if reliable is None else "stereo visual odometry",
        "unreliable_pose_frames": unreliable,
        "has_ground_truth": has_gt,
        "runtime_s": time.perf_counter() - started,
    }
    write_json(out_dir / METRICS_FILE, report)
    return report
