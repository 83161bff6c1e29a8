"""The band cue: which unlabelled pixels of the query's fattening band are likely right, for the band prior.

The band prior (:func:`~selfcontra_ros.confidence.training.band_negatives`) lends training the unlabelled
pixels of the query's fattening band as negatives. About a third to a half of them are right (the object's
own edge pixels), and a right pixel drawn as a negative teaches the forest to distrust exactly the edges it
should trust. The band cue is a small classifier, shipped with the package as a model file (a
:class:`~selfcontra_ros.confidence.forest.ForestModel`, plain arrays, never pickle), that gives each band pixel
a probability of being right from cues a square matching window cannot see:

==========================  ================================================================================
``look``                    the pixel's look (:func:`~selfcontra_ros.confidence.training.band_look_scores`):
                            like the object at its disparity (> 0) or the background beyond its drop (< 0);
                            0 where it cannot be computed
``look_missing``            1 where the look could not be computed, else 0
``strip_own_vs_background``  cost of the pixel's thin vertical strip (:func:`~selfcontra_ros.confidence.kernels.
                            strip_costs`, 1x9) at its own disparity minus at the background's
                            (:func:`~selfcontra_ros.stages.voting.band_background`)
``strip_own_vs_best``       the strip's cost at its own disparity minus its smallest over 0-127 px
``strip_contrast``          (own - background) / (own + background), 0 where both are 0
``drop``                    the pixel's disparity minus the background's, pixels
``strip_texture``           the strip's mean absolute deviation, grey levels
``edge_distance``           how near the disparity drop is (:func:`edge_distances`): the smallest reach k
                            (1 .. the band's 20 px to the left) of the band's window, shrunk to k px left
                            and min(k, 4) px right, up and down, that holds it; 21 where none does
``edge_distance_row``       the same with the window in the pixel's row, to its left only
``edge_distance_other``     the same with the window right, up and down only (k <= 4 px)
``own_left_vs_right``       at the pixel's own disparity, the cost of a 5x5 window that ends at the pixel (4 px
                            to its left, :func:`~selfcontra_ros.confidence.kernels.window_costs`) minus that of
                            one that starts there (4 px to its right)
``background_left_vs_right``  the same at the background's disparity
``<window>_own_vs_background``  for each of :data:`WINDOWS` (5x5 and 9x9 windows left and right of the pixel,
                            1x5, 1x17 and 1x33 strips): its cost at the pixel's own disparity minus at the
                            background's
``<window>_texture``        and its mean absolute deviation, grey levels
==========================  ================================================================================

A fattened pixel is background carrying the object's disparity: its strip matches better at the background's
disparity than at its own. The strip is one pixel wide, so it does not straddle the object's vertical
outline as the matcher's window does. Fattening is densest next to the drop, so the distances let the
forest weigh the strip's evidence by where in the band a pixel lies. The band starts at the disparity drop
and reaches right, across the object's left outline; left of that outline the background is hidden from the
right camera and the matcher fills it with the object. An object pixel's right-hand window lies on the object
and matches at the pixel's disparity; a fattened pixel's right-hand window straddles the outline and its
left-hand one lies on background. The one-sided windows (5x5, 9x9) read this where one column holds too
little texture, the shorter and taller strips (1x5, 1x17, 1x33) where the outline is not vertical over nine
rows. Together the windows cost about half the strip's 128-disparity scan (``docs/label_quality.md``).

The model is fitted by ``bench/fit_band_cue.py`` on the tuning seeds of the synthetic scenes (the band's pixels
of the default matcher, against the ground truth): a prior learned on synthetic ground truth, never on the
user's data; its metadata records how.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence import kernels
from selfcontra_ros.confidence.forest import ForestModel, load_model
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.matching.base import to_grey
from selfcontra_ros.stages.voting import band_background, band_backgrounds

__all__ = [
    "FEATURES",
    "MAX_DISPARITY",
    "MODEL_FILE",
    "STRIP_HALF_HEIGHT",
    "WINDOWS",
    "band_cue_features",
    "default_band_cue",
    "edge_distances",
    "strip_textures",
]

#: The windows matched at a pixel's own and its background's disparity besides the 1x9 strip
#: (:func:`~selfcontra_ros.confidence.kernels.window_costs`): name -> (rows above and below, columns left of the
#: pixel, columns right of it). Each gives the features ``<name>_own_vs_background`` and ``<name>_texture``.
WINDOWS = {
    "left": (2, 4, 0),
    "right": (2, 0, 4),
    "short": (2, 0, 0),
    "tall": (8, 0, 0),
    "wide_left": (4, 8, 0),
    "wide_right": (4, 0, 8),
    "taller": (16, 0, 0),
}

#: Feature columns of the band cue, in order (see the module docstring).
FEATURES = (
    "look",
    "look_missing",
    "strip_own_vs_background",
    "strip_own_vs_best",
    "strip_contrast",
    "drop",
    "strip_texture",
    "edge_distance",
    "edge_distance_row",
    "edge_distance_other",
    "own_left_vs_right",
    "background_left_vs_right",
    *(f"{name}_{part}" for name in WINDOWS for part in ("own_vs_background", "texture")),
)

#: Rows above and below a pixel in its strip (a 1x9 strip).
STRIP_HALF_HEIGHT = 4

#: The strip's smallest cost is searched over the whole-pixel disparities 0 .. this.
MAX_DISPARITY = 127

#: The band cue shipped with the package.
MODEL_FILE = Path(__file__).resolve().parent / "models" / "band_cue.npz"


def band_cue_features(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    disparity: NDArray[np.floating],
    rows: NDArray[np.integer],
    cols: NDArray[np.integer],
    look: NDArray[np.floating],
    labeler: LabelerParams,
) -> NDArray[np.float32]:
    """The band cue's :data:`FEATURES` of band pixels ``(rows, cols)`` (each with a valid disparity).

    Args:
        left, right: HxW grey or HxWx3 RGB rectified pair of ``disparity``.
        disparity: HxW left query disparity; non-finite or <= 0 is invalid.
        rows, cols: (N,) pixels of the fattening band.
        look: (N,) their look (NaN where it could not be computed).
        labeler: the labeler whose band sizes give each pixel's background level.

    Returns:
        (N, len(FEATURES)) float32.

    Raises:
        SelfContraError: images that do not match the disparity map, or a pixel without a valid disparity or
            without a smaller one in its band window.
    """
    d = np.asarray(disparity, dtype=np.float32)
    if np.shape(left)[:2] != d.shape or np.shape(right)[:2] != d.shape:
        raise SelfContraError(f"images {np.shape(left)} / {np.shape(right)} do not match the disparity {d.shape}")
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    own = d[rows, cols]
    background = band_background(
        d, occluded_side_px=labeler.stage2_edge_occluded_side_px, other_px=labeler.stage2_edge_other_px
    )[rows, cols]
    if not (np.isfinite(own).all() and (own > 0).all() and np.isfinite(background).all()):
        raise SelfContraError("band cue: every pixel needs a valid disparity and a background level (a band pixel)")
    grey_left = to_grey(np.asarray(left)).astype(np.float32)
    grey_right = to_grey(np.asarray(right)).astype(np.float32)
    costs = kernels.strip_costs(
        grey_left,
        grey_right,
        rows,
        cols,
        own,
        background,
        max_disparity=MAX_DISPARITY,
        half_height=STRIP_HALF_HEIGHT,
    )
    at_own, at_background, best, texture = costs.T
    look = np.asarray(look, dtype=np.float32)
    total = at_own + at_background
    contrast = np.divide(at_own - at_background, total, out=np.zeros_like(total), where=total > 0)
    pair = np.column_stack([own, background])
    windows = {
        name: kernels.window_costs(grey_left, grey_right, rows, cols, pair, half_height=h, before=b, after=a)
        for name, (h, b, a) in WINDOWS.items()
    }
    return np.column_stack(
        [
            np.nan_to_num(look, nan=0.0),
            np.isnan(look),
            at_own - at_background,
            at_own - best,
            contrast,
            own - background,
            texture,
            edge_distances(d, rows, cols, labeler),
            windows["left"][:, 0] - windows["right"][:, 0],
            windows["left"][:, 1] - windows["right"][:, 1],
            *(column for w in windows.values() for column in (w[:, 0] - w[:, 1], w[:, 2])),
        ]
    ).astype(np.float32)


def strip_textures(
    left: NDArray[np.uint8], right: NDArray[np.uint8], rows: NDArray[np.integer], cols: NDArray[np.integer]
) -> NDArray[np.float32]:
    """The band cue's ``strip_texture`` of pixels ``(rows, cols)`` alone, (N,): without the strip's disparity scan.

    The same kernel as :func:`band_cue_features`, so the values are the same to the bit; for the band prior's
    texture rule when the cue itself is off.
    """
    zero = np.zeros(np.shape(rows), np.float32)
    grey_left = to_grey(np.asarray(left)).astype(np.float32)
    grey_right = to_grey(np.asarray(right)).astype(np.float32)
    costs = kernels.strip_costs(
        grey_left, grey_right, rows, cols, zero, zero, max_disparity=0, half_height=STRIP_HALF_HEIGHT
    )
    return np.ascontiguousarray(costs[:, 3])


def edge_distances(
    disparity: NDArray[np.floating], rows: NDArray[np.integer], cols: NDArray[np.integer], labeler: LabelerParams
) -> NDArray[np.float32]:
    """``edge_distance``, ``edge_distance_row`` and ``edge_distance_other`` of pixels ``(rows, cols)``, (N, 3).

    Each is the smallest reach k, pixels, of a window in which the disparity drops by more than the labeler's
    ``stage2_edge_jump_px`` below the pixel's (:func:`~selfcontra_ros.stages.voting.band_background` of the
    window): the band's window shrunk to k px left and min(k, ``stage2_edge_other_px``) right, up and down;
    k px left in the pixel's row; k px right, up and down (k up to ``stage2_edge_other_px``). A pixel whose
    window holds no drop at the largest reach gets ``stage2_edge_occluded_side_px + 1``.
    """
    d = np.asarray(disparity, dtype=np.float32)
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    left_px, other_px = labeler.stage2_edge_occluded_side_px, labeler.stage2_edge_other_px
    own = d[rows, cols]
    out = np.full((rows.size, 3), np.float32(left_px + 1), dtype=np.float32)
    jobs = []  # (reach k, output column, window)
    for k in range(max(left_px, other_px), 0, -1):  # downwards: the smallest reach that holds a drop wins
        windows = [(min(k, left_px), min(k, other_px)), (min(k, left_px), 0)]
        if k <= other_px:
            windows.append((0, k))
        jobs += [(k, j, window) for j, window in enumerate(windows)]
    for (k, j, _), smallest in zip(jobs, band_backgrounds(d, [window for _, _, window in jobs]), strict=True):
        with np.errstate(invalid="ignore"):
            out[own - smallest[rows, cols] > labeler.stage2_edge_jump_px, j] = k
    return out


@cache
def _load(path: Path) -> ForestModel:
    model = load_model(path)
    if model.metadata.get("feature_names") != list(FEATURES):
        raise SelfContraError(f"{path} is not a band cue model (features {model.metadata.get('feature_names')})")
    return model


def default_band_cue() -> ForestModel:
    """The band cue shipped with the package (:data:`MODEL_FILE`), loaded once.

    Raises:
        SelfContraError: the file is missing or is not a band cue model.
    """
    return _load(MODEL_FILE)
