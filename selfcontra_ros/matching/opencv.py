"""OpenCV query algorithms: StereoSGBM (the package default) and StereoBM.

Both return OpenCV's *raw* disparity by default (see :class:`MatcherParams`):
its 16-bit fixed-point output divided by 16, with OpenCV's invalid marker and
non-positive disparities as NaN. The right disparity comes from the usual flip
trick: mirroring both images turns the right image into a "left" image whose
matches lie to its right, so matching ``flip(right)`` against ``flip(left)``
and mirroring the result back gives the right disparity with the same matcher
and the same parameters.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.matching.base import DisparityPair, MatcherError, MatcherParams, to_grey, validate_pair

__all__ = ["OpenCVMatcher", "fixed_point_to_disparity"]

_SGBM_MODES = {
    "sgbm": cv2.StereoSGBM_MODE_SGBM,
    "hh": cv2.StereoSGBM_MODE_HH,
    "sgbm_3way": cv2.StereoSGBM_MODE_SGBM_3WAY,
    "hh4": cv2.StereoSGBM_MODE_HH4,
}


def fixed_point_to_disparity(raw: NDArray[np.int16], min_disparity: int) -> NDArray[np.float32]:
    """Convert OpenCV's 16-bit fixed-point disparity (4 fractional bits) to float32 pixels.

    OpenCV marks pixels without a match with ``(min_disparity - 1) * 16``;
    those, and disparities ``<= 0`` (no finite depth), become NaN.

    Args:
        raw: HxW int16 output of ``StereoMatcher.compute``.
        min_disparity: the matcher's smallest searched disparity, pixels.

    Returns:
        HxW float32 disparity, pixels.
    """
    raw = np.asarray(raw)
    disparity = raw.astype(np.float32) / np.float32(cv2.StereoMatcher_DISP_SCALE)
    invalid = (raw < min_disparity * cv2.StereoMatcher_DISP_SCALE) | (disparity <= 0)
    disparity[invalid] = np.nan
    return disparity


class OpenCVMatcher:
    """StereoSGBM or StereoBM, chosen by ``params.algorithm`` (``"sgbm"`` or ``"bm"``).

    SGBM matches grey or RGB images directly (the default penalties scale with
    the channel count); BM needs grey, so RGB input is converted first.
    """

    def __init__(self, params: MatcherParams | None = None) -> None:
        """Create the OpenCV matcher objects for ``params`` (default parameters when ``None``).

        Raises:
            MatcherError: if ``params.algorithm`` is not an OpenCV algorithm.
        """
        self.params = params if params is not None else MatcherParams()
        if self.params.algorithm not in ("sgbm", "bm"):
            raise MatcherError(f"OpenCVMatcher runs 'sgbm' or 'bm', got algorithm={self.params.algorithm!r}")
        # One OpenCV object per channel count: P1/P2 depend on it, and creating them per frame is wasted work.
        self._engines: dict[int, Any] = {}

    def _engine(self, channels: int) -> Any:
        engine = self._engines.get(channels)
        if engine is not None:
            return engine
        p = self.params
        if p.algorithm == "sgbm":
            p1, p2 = p.penalties(channels)
            engine = cv2.StereoSGBM.create(
                minDisparity=p.min_disparity,
                numDisparities=p.num_disparities,
                blockSize=p.block_size,
                P1=p1,
                P2=p2,
                disp12MaxDiff=p.disp12_max_diff,
                preFilterCap=p.pre_filter_cap,
                uniquenessRatio=p.uniqueness_ratio,
                speckleWindowSize=p.speckle_window_size,
                speckleRange=p.speckle_range,
                mode=_SGBM_MODES[p.mode],
            )
        else:
            engine = cv2.StereoBM.create(numDisparities=p.num_disparities, blockSize=p.block_size)
            engine.setMinDisparity(p.min_disparity)
            engine.setPreFilterCap(p.pre_filter_cap)
            engine.setPreFilterSize(p.pre_filter_size)
            engine.setTextureThreshold(p.texture_threshold)
            engine.setUniquenessRatio(p.uniqueness_ratio)
            engine.setSpeckleWindowSize(p.speckle_window_size)
            engine.setSpeckleRange(p.speckle_range)
            engine.setDisp12MaxDiff(p.disp12_max_diff)
        self._engines[channels] = engine
        return engine

    def compute(self, left: NDArray[np.uint8], right: NDArray[np.uint8], *, with_right: bool = True) -> DisparityPair:
        """Match a rectified pair; see :meth:`selfcontra_ros.matching.base.Matcher.compute`.

        Raises:
            MatcherError: if the images are not a uint8 grey or RGB pair of one shape.
        """
        validate_pair(left, right)
        if self.params.algorithm == "bm":
            left, right = to_grey(left), to_grey(right)
        left = np.ascontiguousarray(left)
        right = np.ascontiguousarray(right)
        channels = 1 if left.ndim == 2 else left.shape[2]
        engine = self._engine(channels)
        disparity_left = fixed_point_to_disparity(engine.compute(left, right), self.params.min_disparity)
        if not with_right:
            return DisparityPair(left=disparity_left)
        flipped = engine.compute(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))
        disparity_right = fixed_point_to_disparity(np.ascontiguousarray(flipped[:, ::-1]), self.params.min_disparity)
        return DisparityPair(left=disparity_left, right=disparity_right)
