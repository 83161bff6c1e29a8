"""KITTI odometry metrics: relative pose errors over sub-sequences of fixed path lengths.

The KITTI devkit (``evaluate_odometry.cpp``) measures drift as follows: for
every first frame ``i`` (every ``step`` frames; the devkit uses 10) and every
length ``L``, the last frame ``j`` is the first one whose ground-truth path
length from ``i`` reaches ``L``. The error of the pair is the relative motion
of the estimate compared with that of the ground truth::

    E = (T_gt_i^-1 T_gt_j)^-1 (T_est_i^-1 T_est_j)

with translation error ``|t(E)| / L`` and rotation error ``angle(R(E)) / L``.
Averaged over all pairs, they are reported as a percentage (translation) and
degrees per metre (rotation). Pairs for which no frame reaches ``L`` are left
out.

KITTI's lengths are 100, 200, ..., 800 m, which short sequences (a 51-frame,
~60 m KITTI sample, 30-frame synthetic scenes) never reach. This module
defaults to :data:`SHORT_LENGTHS` (5, 10, 20, 30, 40, 50 m) and ``step = 1``
(every frame a start), which uses all the sub-sequences a short sequence
allows; pass ``lengths=KITTI_LENGTHS, step=10`` for the devkit's setting.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.geometry import invert_pose

__all__ = [
    "KITTI_LENGTHS",
    "SHORT_LENGTHS",
    "OdometryMetrics",
    "evaluate_odometry",
    "path_lengths",
]

#: The official KITTI sub-sequence lengths, metres.
KITTI_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
#: Lengths for short sequences, metres (this package's default).
SHORT_LENGTHS: tuple[float, ...] = (5.0, 10.0, 20.0, 30.0, 40.0, 50.0)


@dataclass(frozen=True)
class OdometryMetrics:
    """Relative pose errors of an estimated trajectory.

    Attributes:
        translation_error_pct: mean ``|t(E)| / L`` over all pairs, percent (NaN without pairs).
        rotation_error_deg_per_m: mean ``angle(R(E)) / L``, degrees per metre.
        pairs: number of (first frame, length) pairs evaluated.
        per_length: length (m) -> (translation %, rotation deg/m, pairs) for the lengths reached.
        lengths: the lengths asked for, metres.
        step: first frames used every ``step`` frames.
        path_length_m: ground-truth path length of the whole sequence, metres.
        end_translation_error_m: distance between the estimated and true last position (world frames aligned
            at frame 0), metres.
    """

    translation_error_pct: float
    rotation_error_deg_per_m: float
    pairs: int
    per_length: dict[float, tuple[float, float, int]] = field(default_factory=dict)
    lengths: tuple[float, ...] = SHORT_LENGTHS
    step: int = 1
    path_length_m: float = 0.0
    end_translation_error_m: float = float("nan")

    def summary(self) -> str:
        """One line: translation %, rotation deg/m, pairs and path length."""
        return (
            f"translation error {self.translation_error_pct:.2f} %, rotation error "
            f"{self.rotation_error_deg_per_m:.4f} deg/m over {self.pairs} sub-sequences "
            f"(lengths {', '.join(f'{v:g}' for v in self.per_length)} m, step {self.step}) "
            f"of a {self.path_length_m:.1f} m path; end-point error {self.end_translation_error_m:.3f} m"
        )


def _as_poses(poses: ArrayLike, what: str) -> NDArray[np.float64]:
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim == 3 and array.shape[1:] == (3, 4):
        full = np.tile(np.eye(4), (array.shape[0], 1, 1))
        full[:, :3] = array
        array = full
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise SelfContraError(f"{what} must have shape (N, 4, 4) or (N, 3, 4), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise SelfContraError(f"{what} holds non-finite values")
    return array


def path_lengths(poses: ArrayLike) -> NDArray[np.float64]:
    """Cumulative path length (metres) along the camera positions of (N, 4, 4) poses; starts at 0."""
    p = _as_poses(poses, "poses")
    steps = np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _rotation_angle(rotations: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angles (radians) of (M, 3, 3) rotation matrices."""
    cos = np.clip((np.trace(rotations, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(cos)


def evaluate_odometry(
    estimated: ArrayLike,
    ground_truth: ArrayLike,
    *,
    lengths: tuple[float, ...] = SHORT_LENGTHS,
    step: int = 1,
    mask: ArrayLike | None = None,
) -> OdometryMetrics:
    """KITTI relative translation and rotation errors of ``estimated`` against ``ground_truth``.

    Args:
        estimated: (N, 4, 4) or (N, 3, 4) poses ``T_world_left``, metres.
        ground_truth: the true poses of the same frames.
        lengths: sub-sequence lengths, metres.
        step: a first frame every ``step`` frames (KITTI devkit: 10).
        mask: optional (N,) booleans; pairs whose first or last frame is False
            (e.g. frames flagged unreliable) are left out.

    Raises:
        SelfContraError: poses of different counts or shapes, or a step < 1.
    """
    est = _as_poses(estimated, "estimated poses")
    gt = _as_poses(ground_truth, "ground-truth poses")
    if est.shape != gt.shape:
        raise SelfContraError(f"{est.shape[0]} estimated poses for {gt.shape[0]} ground-truth poses")
    if step < 1:
        raise SelfContraError(f"step must be >= 1, got {step}")
    n = est.shape[0]
    keep = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(n)
    dist = path_lengths(gt)
    firsts = np.arange(0, n, step)
    t_errors: list[NDArray[np.float64]] = []
    r_errors: list[NDArray[np.float64]] = []
    per_length: dict[float, tuple[float, float, int]] = {}
    for length in lengths:
        # First frame j with dist[j] >= dist[i] + L (as the devkit's lastFrameFromSegmentLength).
        last = np.searchsorted(dist, dist[firsts] + length, side="left")
        ok = last < n
        i, j = firsts[ok], last[ok]
        ok = keep[i] & keep[j]
        i, j = i[ok], j[ok]
        if i.size == 0:
            continue
        delta_gt = np.linalg.inv(gt[i]) @ gt[j]
        delta_est = np.linalg.inv(est[i]) @ est[j]
        error = np.linalg.inv(delta_gt) @ delta_est
        t_err = np.linalg.norm(error[:, :3, 3], axis=1) / length
        r_err = np.degrees(_rotation_angle(error[:, :3, :3])) / length
        t_errors.append(t_err)
        r_errors.append(r_err)
        per_length[float(length)] = (float(100.0 * t_err.mean()), float(r_err.mean()), int(i.size))
    all_t = np.concatenate(t_errors) if t_errors else np.zeros(0)
    all_r = np.concatenate(r_errors) if r_errors else np.zeros(0)
    end = invert_pose(gt[0]) @ gt[-1]
    end_est = invert_pose(est[0]) @ est[-1]
    return OdometryMetrics(
        translation_error_pct=float(100.0 * all_t.mean()) if all_t.size else float("nan"),
        rotation_error_deg_per_m=float(all_r.mean()) if all_r.size else float("nan"),
        pairs=int(all_t.size),
        per_length=per_length,
        lengths=tuple(float(v) for v in lengths),
        step=step,
        path_length_m=float(dist[-1]),
        end_translation_error_m=float(np.linalg.norm(end[:3, 3] - end_est[:3, 3])),
    )
