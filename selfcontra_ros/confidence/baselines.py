"""Confidence baselines taken from elsewhere: OpenCV's ``DisparityWLSFilter`` confidence map (``cv2.ximgproc``).

The confidence a robotics engineer would otherwise reach for is the one
OpenCV's WLS disparity filter computes before it smooths (``ximgproc``,
``createDisparityWLSFilter`` + ``getConfidenceMap``): a discontinuity-aware
left-right check times a local disparity variance term. The package does not
re-implement it; it hands OpenCV's own filter the very disparity maps it
evaluates (the query algorithm's left and right maps), so that the baseline
is scored on the same pixels as LRD and the forests.

What the filter is fed (OpenCV's conventions, which differ from the package's):

* **left disparity**: ``int16`` in 16ths of a pixel, ``round(16 d)``; pixels the
  package calls invalid (NaN or ``d <= 0``) get ``16 (min_disparity - 1)``,
  the value OpenCV's own matchers write there.
* **right disparity**: ``int16``, ``-round(16 d_R)``, *negative*: OpenCV's
  right matcher (``createRightMatcher``) searches ``[-(min + num) + 1, -min]``
  on the mirrored roles, so a right pixel ``x`` pairs with the left pixel
  ``x + |d_R|`` and the filter's left-right test reads
  ``|16 d(x) + right(x - d(x))| < LRC_thresh``. Invalid right pixels get
  ``-16 (min_disparity + num_disparities)``, what that right matcher writes
  there (its ``(minDisparity - 1) * 16``).
* **left view**: the grey left image (only the smoothing reads it; the
  confidence map does not depend on it).
* **filter**: ``createDisparityWLSFilterGeneric(True)`` with the region of
  interest the whole image (the package's own invalid pixels are not scored
  anyway, and a matcher-specific border would zero pixels the other measures
  keep), ``LRC_thresh`` 24 (1.5 px, OpenCV's default) and the depth
  discontinuity radius ``createDisparityWLSFilter(matcher)`` sets for the
  query algorithm: ``ceil(0.33 * block_size)`` for StereoBM,
  ``ceil(0.5 * block_size)`` for StereoSGBM and every other algorithm.

OpenCV's map, per pixel ``x`` with ``x' = x - floor(16 d(x) / 16)``:
``conf(x) = min(w_L(x), w_R(x'))`` when ``|16 d(x) + right(x')| < LRC_thresh``
and ``x'`` is inside the image, ``0`` when the check fails, ``w_L(x)`` when
``x'`` is outside; ``w = max(1 - 0.001 var, 0)`` with ``var`` the variance of
the 16x fixed-point disparities in the ``(2r + 1)^2`` box around the pixel
(invalid pixels included at their marker values). OpenCV scales it to
``[0, 255]``; the package divides by 255 (confidence in ``[0, 1]``).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence.features import FeatureContext
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.matching.base import MatcherParams

__all__ = [
    "WLS_LRC_THRESHOLD",
    "WLS_SCALE",
    "WLSUnavailableError",
    "left_fixed_point",
    "right_fixed_point",
    "wls_confidence",
    "wls_confidence_map",
    "wls_discontinuity_radius",
]

#: OpenCV's disparity fixed point: 16ths of a pixel.
WLS_SCALE = 16
#: Left-right check threshold of the filter, 16ths of a pixel (OpenCV's default: 1.5 px).
WLS_LRC_THRESHOLD = 24
#: Largest value of OpenCV's confidence map.
_MAP_MAX = 255.0


class WLSUnavailableError(SelfContraError):
    """The installed OpenCV lacks ``cv2.ximgproc`` (plain ``opencv-python-headless`` instead of the contrib build)."""


def wls_discontinuity_radius(params: MatcherParams) -> int:
    """The depth discontinuity radius ``createDisparityWLSFilter`` sets for the query algorithm, pixels."""
    factor = 0.33 if params.algorithm == "bm" else 0.5
    return max(1, math.ceil(factor * params.block_size))


def _valid(disparity: NDArray[np.floating]) -> NDArray[np.bool_]:
    with np.errstate(invalid="ignore"):
        return np.isfinite(disparity) & (disparity > 0)


def _to_int16(values: NDArray[np.float64]) -> NDArray[np.int16]:
    info = np.iinfo(np.int16)
    return np.clip(values, info.min, info.max).astype(np.int16)


def left_fixed_point(disparity: NDArray[np.floating], min_disparity: int) -> NDArray[np.int16]:
    """Left disparity (pixels, NaN invalid) in OpenCV's 16x ``int16``; invalid = ``16 (min_disparity - 1)``."""
    d = np.asarray(disparity, dtype=np.float64)
    fixed = np.where(_valid(d), np.rint(d * WLS_SCALE), WLS_SCALE * (min_disparity - 1))
    return _to_int16(fixed)


def right_fixed_point(
    disparity_right: NDArray[np.floating], min_disparity: int, num_disparities: int
) -> NDArray[np.int16]:
    """Right disparity (pixels, positive, NaN invalid) as OpenCV's right matcher writes it: ``-round(16 d_R)``.

    Invalid pixels get ``-16 (min_disparity + num_disparities)``, the right
    matcher's own marker.
    """
    d = np.asarray(disparity_right, dtype=np.float64)
    fixed = np.where(_valid(d), -np.rint(d * WLS_SCALE), -WLS_SCALE * (min_disparity + num_disparities))
    return _to_int16(fixed)


def _ximgproc() -> Any:
    module = getattr(cv2, "ximgproc", None)
    if module is None:
        raise WLSUnavailableError(
            f"the WLS confidence needs OpenCV's contrib module ximgproc, absent from this cv2 ({cv2.__version__}): "
            "install opencv-contrib-python-headless in place of opencv-python-headless (`make venv` does; "
            "both together break cv2), or python3-opencv from Debian/Ubuntu"
        )
    return module


def wls_confidence_map(
    left: NDArray[np.uint8],
    disparity: NDArray[np.floating],
    disparity_right: NDArray[np.floating],
    *,
    min_disparity: int = 0,
    num_disparities: int = 128,
    radius: int = 3,
    lrc_threshold: int = WLS_LRC_THRESHOLD,
) -> NDArray[np.float32]:
    """OpenCV's WLS confidence map of a left/right disparity pair, HxW float32 in ``[0, 1]`` (1 = confident).

    Args:
        left: HxW grey or HxWx3 uint8 left image (the filter's guide).
        disparity: HxW left disparity, pixels, NaN (or ``<= 0``) invalid.
        disparity_right: HxW right disparity, pixels, positive (``x_left = x_right + d_R``), NaN invalid.
        min_disparity: the query algorithm's smallest searched disparity, pixels.
        num_disparities: its search range, pixels (sets the right invalid marker).
        radius: depth discontinuity radius of the variance box, pixels.
        lrc_threshold: left-right check threshold, 16ths of a pixel.

    Raises:
        WLSUnavailableError: OpenCV without ``ximgproc``.
        SelfContraError: shapes that differ, or a left image that is not 8-bit.
    """
    ximgproc = _ximgproc()
    disparity = np.asarray(disparity)
    disparity_right = np.asarray(disparity_right)
    guide = np.asarray(left)
    if disparity.ndim != 2 or disparity_right.shape != disparity.shape or guide.shape[:2] != disparity.shape:
        raise SelfContraError(
            f"WLS confidence: left image {guide.shape}, left disparity {disparity.shape} and right disparity "
            f"{disparity_right.shape} must share one HxW size"
        )
    if guide.dtype != np.uint8:
        raise SelfContraError(f"WLS confidence: the left image must be uint8, got {guide.dtype}")
    wls = ximgproc.createDisparityWLSFilterGeneric(True)
    wls.setLRCthresh(int(lrc_threshold))
    wls.setDepthDiscontinuityRadius(int(radius))
    height, width = disparity.shape
    wls.filter(
        left_fixed_point(disparity, min_disparity),
        np.ascontiguousarray(guide),
        disparity_map_right=right_fixed_point(disparity_right, min_disparity, num_disparities),
        ROI=(0, 0, width, height),
    )
    confidence = np.asarray(wls.getConfidenceMap(), dtype=np.float32)
    return np.clip(confidence / np.float32(_MAP_MAX), 0.0, 1.0).astype(np.float32)


def wls_confidence(ctx: FeatureContext, params: MatcherParams) -> NDArray[np.float32]:
    """WLS confidence at the valid pixels of ``ctx`` (its row-major order), from its left and right disparities.

    Args:
        ctx: feature context of the query algorithm's disparity pair.
        params: that query algorithm's parameters (disparity range, block size, BM or not).

    Raises:
        SelfContraError: the context has no right disparity (the filter needs both).
        WLSUnavailableError: OpenCV without ``ximgproc``.
    """
    right = ctx.data.disparity_right
    if right is None:
        raise SelfContraError(
            "the WLS confidence needs the right disparity map; this query algorithm gave only the left one"
        )
    guide = np.asarray(ctx.data.left)
    if guide.dtype != np.uint8:
        guide = np.clip(np.rint(guide), 0, 255).astype(np.uint8)
    confidence = wls_confidence_map(
        guide,
        ctx.data.disparity,
        right,
        min_disparity=params.min_disparity,
        num_disparities=params.num_disparities,
        radius=wls_discontinuity_radius(params),
    )
    return confidence[ctx.rows, ctx.cols]
