"""Offline labeling: the ``selfcontra label`` command, for a sequence folder or a bag.

:func:`label_input` is the one place that decides which front end an input
needs (:func:`input_kind`): a rosbag2 bag goes to
:func:`selfcontra_ros.bags.label_bag.label_bag` (a new MCAP bag, see there),
anything else to :func:`label_sequence` here. The command line and the batch
runner (:mod:`selfcontra_ros.batch`) both call it, so a batch gives what
``selfcontra label`` gives on each input. The dependencies run one way: this
module imports the bag labeler and the odometry (for ``estimate_poses``);
they import neither this module nor each other, only the shared report
helpers of :mod:`selfcontra_ros.reports`.

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

The functions are pure in the sense of DESIGN section 9: they read only their
arguments' files, write only below ``out_dir`` (or the output bag) and keep no
global state, so a cluster engine can run them on many inputs at once.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.config import load_params, params_to_dict
from selfcontra_ros.datasets.kitti import OdometrySequence, StereoFrame, open_sequence
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.evaluation.metrics import mean_metrics
from selfcontra_ros.labeler import LabelResult
from selfcontra_ros.labels import colorize_labels
from selfcontra_ros.reports import (
    LABELS_COLOR_DIR,
    LABELS_DIR,
    METRICS_FILE,
    PendingView,
    evaluate_view,
    write_json,
)
from selfcontra_ros.session import LabelingSession

if TYPE_CHECKING:
    from selfcontra_ros.bags.stereo_input import StereoInput

__all__ = ["BAG", "SEQUENCE", "input_kind", "label_input", "label_sequence"]

#: The two front ends of :func:`label_input`: a rosbag2 bag, or a KITTI-layout sequence folder.
BAG, SEQUENCE = "bag", "sequence"


def _frame_indices(sequence: OdometrySequence, frames: slice | None) -> list[int]:
    indices = range(len(sequence))
    return list(indices[frames] if frames is not None else indices)


def _write_png(path: Path, image: NDArray[np.uint8]) -> None:
    if not cv2.imwrite(str(path), image):
        raise SelfContraError(f"cannot write image {path}")


def _write_labels(out_dir: Path, index: int, labels: NDArray[np.uint8]) -> None:
    name = f"{index:06d}.png"
    _write_png(out_dir / LABELS_DIR / name, np.ascontiguousarray(labels, dtype=np.uint8))
    # colorize_labels gives RGB; OpenCV writes BGR.
    _write_png(out_dir / LABELS_COLOR_DIR / name, np.ascontiguousarray(colorize_labels(labels)[:, :, ::-1]))


def _run(
    sequence: OdometrySequence, indices: list[int], session: LabelingSession, out_dir: Path, progress: bool
) -> Iterator[tuple[int, float, dict[str, float]]]:
    """Match and label the frames; yield ``(index, stamp, figures)`` per labelled frame, in labelling order."""
    pending: dict[int, PendingView] = {}
    stamps: dict[int, float] = {}

    def release(results: list[LabelResult]) -> Iterator[tuple[int, float, dict[str, float]]]:
        for result in results:
            index = cast(int, result.key)  # _run passes the frame index as the key
            _write_labels(out_dir, index, result.labels)
            yield index, stamps.pop(index), evaluate_view(result, pending.pop(index))

    for index in tqdm(indices, desc="label", unit="frame", disable=not progress):
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
    progress: bool = True,
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
        progress: show progress bars (frames; odometry with ``estimate_poses``).

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

        sequence.poses, reliable = poses_for_sequence(sequence, progress=progress)
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
        per_frame.extend(_run(sequence, indices, session, out_dir, progress))
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


def input_kind(source: Path | str) -> str:
    """The front end ``source`` needs: :data:`BAG` (a rosbag2 folder or ``.mcap`` file) or :data:`SEQUENCE`."""
    from selfcontra_ros.bags.reader import is_bag

    return BAG if is_bag(Path(source)) else SEQUENCE


def label_input(
    source: Path | str,
    out: Path | str,
    *,
    params_file: str | Path | None = None,
    progress: bool = True,
    frames: slice | None = None,
    estimate_poses: bool = False,
    sync: str = "exact",
    slop: float = 0.0,
    namespace: str | None = None,
    pose_topic: str | None = None,
    disparity_topic: str | None = None,
    model_out: str | Path | None = None,
    stereo_input: StereoInput | None = None,
) -> dict[str, Any]:
    """Label one input with the front end it needs (:func:`input_kind`): what ``selfcontra label`` does.

    Args:
        source: a KITTI-layout sequence (dataset root with one sequence, or ``sequences/XX``) or a bag.
        out: output folder (sequence) or output bag folder (bag; must not exist).
        params_file: parameter YAML; ``None`` uses the package's ``config/labeler.yaml``.
        progress: show progress bars.
        frames: frame range of a sequence (a bag is labelled whole).
        estimate_poses: a sequence without poses gets them from the stereo visual odometry.
        sync, slop, namespace, pose_topic, disparity_topic, model_out, stereo_input: bag input only,
            see :func:`~selfcontra_ros.bags.label_bag.label_bag`.

    Returns:
        The content of the run's ``metrics.json``.

    Raises:
        SelfContraError: an option of the other front end given (``frames`` for a bag;
            ``model_out`` or ``stereo_input`` for a sequence), and whatever the front end raises.
    """
    source, out = Path(source), Path(out)
    if input_kind(source) == BAG:
        from selfcontra_ros.bags.label_bag import label_bag

        if frames is not None:
            raise SelfContraError("--frames applies to sequence folders; a bag is labelled whole")
        return label_bag(
            source,
            out,
            params_file=params_file,
            sync=sync,
            slop=slop,
            progress=progress,
            namespace=namespace,
            pose_topic=pose_topic,
            disparity_topic=disparity_topic,
            model_out=model_out,
            stereo_input=stereo_input,
        )
    if model_out is not None:
        raise SelfContraError("--model-out applies to bag input (online confidence runs in the bag labeler)")
    if stereo_input is not None:
        raise SelfContraError(f"a stereo input (remaps, image transport, rectify) applies to bags, not to {source}")
    return label_sequence(
        source, out, params_file=params_file, frames=frames, estimate_poses=estimate_poses, progress=progress
    )
