"""Views and the bounded sliding window that holds them (DESIGN section 4).

A :class:`View` caches, per pixel and flattened to ``H*W`` entries, what the
stages need again and again: validity, the 3D point in the view's own left
frame, the uncertainty ``u`` and the Stage-1 support bit mask. Points stay in
the view's own frame: relative poses are composed in float64 once per view
pair, and a covariance is rotated into another frame only where a test needs
it (``F' = R F R^T``, :func:`selfcontra_ros.uncertainty.rotate_sym`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Hashable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera, invert_pose
from selfcontra_ros.matching.base import to_grey
from selfcontra_ros.matching.census import popcount
from selfcontra_ros.uncertainty import largest_covariance_eigenvalue, mean_camera_centre

__all__ = ["View", "ViewWindow", "make_view", "saturated_pixels", "support_count"]


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
        reliable: pixels whose match is not ambiguous (see :func:`ambiguous_pixels`): only these vote
            as references in Stage 2 and may be labelled positive. All true when no cue is enabled.
        clipped: pixels whose left-image grey value is saturated (see :func:`saturated_pixels`): never
            labelled positive whatever the votes; None when the cue is off or the view came without image.
        labelled: whether labels for this view have been produced.
        max_disparity: the largest disparity the view's matcher searched, pixels (inf: unknown). A point
            whose disparity in this view would exceed it could not have been measured here: a surface that
            near comes out at some farther disparity, or not at all (``LabelerParams.range_abstain``).
        bands: the view's fattening bands (flat bool) by ``(jump_px, occluded_side_px, other_px, below_px)``,
            computed once by Stage 2 (:func:`selfcontra_ros.stages.voting.view_band`) for the view as query and
            as reference.
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
    reliable: NDArray[np.bool_]
    labelled: bool = field(default=False)
    clipped: NDArray[np.bool_] | None = field(default=None, repr=False)
    max_disparity: float = math.inf
    bands: dict[tuple[float, int, int, int], NDArray[np.bool_]] = field(default_factory=dict, repr=False)

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
    reliable: NDArray[np.bool_] | None = None,
    clipped: NDArray[np.bool_] | None = None,
    max_disparity: float = math.inf,
) -> View:
    """Build a :class:`View` from a disparity map (HxW, pixels) and its pose (4x4 ``T_world_left``).

    ``reliable`` (HxW) marks the pixels whose match is trusted; None trusts every valid pixel.
    ``clipped`` (HxW) marks the pixels that may never be labelled positive (saturated ones); None: none.
    ``max_disparity``: the largest disparity the matcher searched (pixels; inf: unknown).
    """
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
        reliable=valid.copy() if reliable is None else (np.asarray(reliable, dtype=bool).ravel() & valid),
        clipped=None if clipped is None else np.asarray(clipped, dtype=bool).ravel().copy(),
        max_disparity=float(max_disparity),
    )


#: Texture measures of :func:`ambiguous_pixels`.
TEXTURE_MEASURES = ("std", "gradient_x")


def ambiguous_pixels(
    disparity: NDArray[np.floating],
    image: NDArray[np.uint8] | None,
    *,
    min_texture: float,
    texture_window: int,
    edge_px: float,
    texture_measure: str = "std",
) -> NDArray[np.bool_]:
    """Pixels whose match the query algorithm may have got wrong from every viewpoint alike (HxW bool).

    Two cues, each off at 0:

    * *texture*: the grey-level standard deviation of ``image`` in a
      ``texture_window`` x ``texture_window`` window (``texture_measure``
      ``std``), or the RMS of its horizontal central difference there
      (``gradient_x``), is below ``min_texture`` (grey levels). A textureless patch matches equally well at many
      disparities; SGM then fills it from its surroundings, and nearby views
      make the same guess. Needs the left image (None: the cue is off).
    * *depth edge*: the disparity varies by more than ``edge_px`` pixels within
      the 3x3 neighbourhood. A lookup landing there takes the foreground or the
      background depending on a fraction of a pixel, so it neither confirms
      nor contradicts reliably.
    """
    d = np.asarray(disparity, dtype=np.float32)
    ambiguous = np.zeros(d.shape, dtype=bool)
    if image is not None and min_texture > 0:
        g = to_grey(image).astype(np.float64)  # float64: the variance is a small difference of large sums
        size = (int(texture_window), int(texture_window))
        if texture_measure == "gradient_x":
            gx = np.zeros_like(g)
            gx[:, 1:-1] = 0.5 * (g[:, 2:] - g[:, :-2])
            ambiguous |= np.sqrt(cv2.blur(gx * gx, size, borderType=cv2.BORDER_REFLECT)) < min_texture
        else:
            mean = cv2.blur(g, size, borderType=cv2.BORDER_REFLECT)
            mean_sq = cv2.blur(g * g, size, borderType=cv2.BORDER_REFLECT)
            ambiguous |= np.sqrt(np.maximum(mean_sq - mean * mean, 0.0)) < min_texture
    if edge_px > 0:
        valid = np.isfinite(d) & (d > 0)
        kernel = np.ones((3, 3), np.uint8)
        high = cv2.dilate(np.where(valid, d, -np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
        low = cv2.erode(np.where(valid, d, np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
        with np.errstate(invalid="ignore"):
            ambiguous |= valid & (high - low > edge_px)
    return ambiguous


def saturated_pixels(image: NDArray[np.uint8], level: float) -> NDArray[np.bool_]:
    """Pixels whose grey value (of ``image``, HxW grey or HxWx3 RGB, 8 bit) is at least ``level`` (HxW bool).

    A clipped pixel says only that the scene there is at least as bright as the
    sensor's full scale: its own value constrains no match, so the disparity it
    gets comes from the texture of its neighbours (the edge of a window onto a
    bright outside, matched at the wall's depth), and every view repeats it.
    """
    return to_grey(image) >= level


def support_count(bits: NDArray[np.uint64]) -> NDArray[np.uint8]:
    """Number of distinct activated angular bins per pixel (the paper's ``support``)."""
    return popcount(bits)


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
