"""Views and the bounded sliding window that holds them (DESIGN section 4).

A :class:`View` caches, per pixel and flattened to ``H*W`` entries, what the
stages need again and again: validity, the 3D point in the view's own left
frame, the uncertainty ``u`` and the Stage-1 support bit mask. Points stay in
the view's own frame: relative poses are composed in float64 once per view
pair, and a covariance is rotated into another frame only where a test needs
it (``F' = R F R^T``, :func:`selfcontra_ros.uncertainty.rotate_sym`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera, invert_pose
from selfcontra_ros.uncertainty import largest_covariance_eigenvalue, mean_camera_centre

__all__ = ["View", "ViewWindow", "make_view", "support_count"]


@dataclass(eq=False)
class View:
    """One rectified stereo view with its cached per-pixel data (flat arrays of ``H*W`` entries).

    Attributes:
        index: running number of the view among the kept views (0, 1, ...).
        key: what the caller passed with the view (frame index, ROS header, ...).
        stamp: the view's stamp, seconds.
        pose: 4x4 ``T_world_left``.
        pose_inv: 4x4 ``T_left_world``.
        centre: mean camera centre of the pair (world, metres).
        disparity: the query algorithm's disparity, pixels (float32, as given).
        valid: disparity finite and > 0.
        points: 3D points in the view's left frame, metres (float32, NaN invalid).
        u: largest covariance eigenvalue per pixel, m^2 (float32, NaN invalid).
        support_bits: Stage-1 angular bins activated per pixel (bit ``k`` = bin ``k``).
        labelled: whether labels for this view have been produced.
    """

    index: int
    key: Hashable
    stamp: float
    pose: NDArray[np.float64]
    pose_inv: NDArray[np.float64]
    centre: NDArray[np.float64]
    disparity: NDArray[np.float32]
    valid: NDArray[np.bool_]
    points: NDArray[np.float32]
    u: NDArray[np.float32]
    support_bits: NDArray[np.uint64]
    labelled: bool = field(default=False)

    def from_view(self, other: View) -> NDArray[np.float64]:
        """4x4 transform taking points of ``other``'s left frame into this view's left frame."""
        return self.pose_inv @ other.pose


def make_view(
    camera: StereoCamera,
    disparity: NDArray[np.floating],
    pose: NDArray[np.float64],
    *,
    index: int,
    key: Hashable,
    stamp: float,
    sigma_px: float,
) -> View:
    """Build a :class:`View` from a disparity map (HxW, pixels) and its pose (4x4 ``T_world_left``)."""
    disp = np.asarray(disparity, dtype=np.float32)
    valid = (np.isfinite(disp) & (disp > 0)).ravel()
    points = camera.backproject(disp).reshape(-1, 3)
    u = largest_covariance_eigenvalue(points, camera, sigma_px)
    pose64 = np.asarray(pose, dtype=np.float64)
    return View(
        index=index,
        key=key,
        stamp=float(stamp),
        pose=pose64,
        pose_inv=invert_pose(pose64),
        centre=mean_camera_centre(pose64, camera),
        disparity=disp,
        valid=valid,
        points=points.astype(np.float32),
        u=u.astype(np.float32),
        support_bits=np.zeros(valid.size, dtype=np.uint64),
    )


def support_count(bits: NDArray[np.uint64]) -> NDArray[np.uint8]:
    """Number of distinct activated angular bins per pixel (the paper's ``support``)."""
    return np.bitwise_count(bits).astype(np.uint8)


class ViewWindow:
    """The last ``size`` kept views, oldest first, plus the keyframe rule.

    Memory is bounded by ``size`` views whatever the length of the sequence.
    """

    def __init__(self, size: int, min_translation: float, min_rotation_deg: float) -> None:
        """Create an empty window of at most ``size`` views; see :meth:`is_keyframe` for the two thresholds."""
        self.size = size
        self.min_translation = min_translation
        self.min_rotation_deg = min_rotation_deg
        self._views: deque[View] = deque()

    def __len__(self) -> int:
        return len(self._views)

    def __iter__(self) -> Iterator[View]:
        return iter(self._views)

    @property
    def newest(self) -> View | None:
        """The most recently added view, or None when empty."""
        return self._views[-1] if self._views else None

    def is_keyframe(self, pose: NDArray[np.float64]) -> bool:
        """Whether a view at ``pose`` moved enough from the newest kept view to be kept.

        A view is skipped only when it is both closer than ``min_translation``
        (metres, left camera centres) and rotated less than
        ``min_rotation_deg`` from the newest kept view: a robot standing still
        would otherwise fill the window with copies of one viewpoint, which
        give no support (angles under ``alpha_min``) and push useful views out.
        """
        last = self.newest
        if last is None:
            return True
        relative = last.pose_inv @ pose
        translation = float(np.linalg.norm(relative[:3, 3]))
        cos_angle = np.clip((np.trace(relative[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        rotation_deg = float(np.degrees(np.arccos(cos_angle)))
        return translation >= self.min_translation or rotation_deg >= self.min_rotation_deg

    def push(self, view: View) -> View | None:
        """Append a view; returns the evicted oldest view when the window was full."""
        evicted = self._views.popleft() if len(self._views) >= self.size else None
        self._views.append(view)
        return evicted

    def others(self, view: View) -> list[View]:
        """All views in the window except ``view``."""
        return [v for v in self._views if v is not view]

    def clear(self) -> None:
        """Drop every view."""
        self._views.clear()
