"""The query-algorithm interface: parameters, result type and the matcher factory.

A *query algorithm* is the stereo matcher whose depth maps get labelled
(DESIGN section 5). Every matcher takes a rectified pair and returns the left
disparity and, when asked, the right disparity (needed by left-right
features), both as float32 pixels with NaN where there is no usable
disparity. "Usable" follows DESIGN section 2: a disparity must be finite and
strictly positive to have a depth, so the matchers turn their own invalid
markers, negative and zero disparities into NaN at this one boundary.

Disparity conventions: a left pixel ``(u, v)`` with left disparity ``d``
matches the right pixel ``(u - d, v)``; a right pixel ``(u, v)`` with right
disparity ``d`` matches the left pixel ``(u + d, v)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.errors import SelfContraError

__all__ = [
    "ALGORITHMS",
    "MODES",
    "DisparityPair",
    "Matcher",
    "MatcherError",
    "MatcherParams",
    "make_matcher",
    "to_grey",
    "validate_pair",
]

#: Query algorithms known to :func:`make_matcher`.
ALGORITHMS = ("sgbm", "bm", "external", "census_sgm")

#: StereoSGBM modes: ``sgbm`` (5 directions), ``hh`` (full 8-direction
#: two-pass), ``sgbm_3way`` (3 directions, faster), ``hh4`` (4 directions).
MODES = ("sgbm", "hh", "sgbm_3way", "hh4")


class MatcherError(SelfContraError, ValueError):
    """Bad matcher parameters or bad input images / disparity maps.

    Also a ValueError, like the other parameter dataclasses' complaints, so
    callers may catch either.
    """


@dataclass(frozen=True)
class MatcherParams:
    """Parameters of the query algorithm; defaults are the package defaults.

    ``config/labeler.yaml`` (section ``matcher``) mirrors these defaults. The
    defaults give the matcher's *raw* output: no speckle filter, no uniqueness
    check and no left-right check, because the labels are meant to catch the
    algorithm's own errors, not the ones a post-filter already removed.

    Attributes:
        algorithm: ``"sgbm"`` (OpenCV StereoSGBM), ``"bm"`` (OpenCV StereoBM)
            or ``"external"`` (a disparity map handed in by the caller).
        num_disparities: size of the disparity search range, pixels; a
            positive multiple of 16. The search covers
            ``[min_disparity, min_disparity + num_disparities)``.
        block_size: matching block side, pixels; odd. SGBM accepts 1..255,
            BM 5..255.
        min_disparity: smallest disparity searched, pixels.
        p1: SGBM penalty for disparity changes of +-1 between neighbours;
            ``0`` means the usual ``8 * cn * block_size**2`` with ``cn`` the
            number of image channels (1 grey, 3 RGB).
        p2: SGBM penalty for larger disparity changes; ``0`` means
            ``32 * cn * block_size**2``. Must exceed ``p1``.
        mode: SGBM variant, one of :data:`MODES`. Default ``sgbm_3way``: on
            the package's synthetic street and orbit scenes and on the real
            KITTI 2015 sample it had the lowest raw bad-pixel rate (> 3 px)
            at the same speed (KITTI 2015 pair 000000: 8.8 % against 12.9 %
            for ``sgbm`` and ``hh``; synthetic orbit: 15 % against 27 %),
            and so gives fewer consistent-but-wrong regions to label.
        pre_filter_cap: clip value of the x-derivative / normalisation
            pre-filter (SGBM and BM), 1..63.
        uniqueness_ratio: percentage by which the best cost must beat the
            second best; ``0`` disables the check.
        speckle_window_size: largest connected region (pixels) of similar
            disparity that is removed as a speckle; ``0`` disables the filter.
        speckle_range: largest disparity difference (pixels) inside one
            speckle region; used only when ``speckle_window_size > 0``.
        disp12_max_diff: largest allowed left-right disparity difference,
            pixels, of OpenCV's internal check; ``-1`` disables it.
        texture_threshold: BM only; blocks whose summed x-derivative is below
            this are invalid. ``0`` keeps every block.
        pre_filter_size: BM only; odd window of the normalising pre-filter,
            5..255.
    """

    algorithm: str = "sgbm"
    num_disparities: int = 128
    block_size: int = 5
    min_disparity: int = 0
    p1: int = 0
    p2: int = 0
    mode: str = "sgbm_3way"
    pre_filter_cap: int = 63
    uniqueness_ratio: int = 0
    speckle_window_size: int = 0
    speckle_range: int = 0
    disp12_max_diff: int = -1
    texture_threshold: int = 0
    pre_filter_size: int = 9

    def __post_init__(self) -> None:
        """Check every field; raises MatcherError naming the field and the expected range."""
        if self.algorithm not in ALGORITHMS:
            raise MatcherError(f"MatcherParams.algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}")
        if self.mode not in MODES:
            raise MatcherError(f"MatcherParams.mode must be one of {MODES}, got {self.mode!r}")
        for name in (
            "num_disparities",
            "block_size",
            "min_disparity",
            "p1",
            "p2",
            "pre_filter_cap",
            "uniqueness_ratio",
            "speckle_window_size",
            "speckle_range",
            "disp12_max_diff",
            "texture_threshold",
            "pre_filter_size",
        ):
            value = getattr(self, name)
            # bool is an int subclass; a YAML "true" in an int field is a typo, not a 1.
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise MatcherError(f"MatcherParams.{name} must be an integer, got {value!r}")
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise MatcherError(
                f"MatcherParams.num_disparities must be a positive multiple of 16, got {self.num_disparities}"
            )
        min_block = 5 if self.algorithm == "bm" else 1
        if not (min_block <= self.block_size <= 255) or self.block_size % 2 == 0:
            raise MatcherError(
                f"MatcherParams.block_size must be odd and in [{min_block}, 255] for {self.algorithm!r}, "
                f"got {self.block_size}"
            )
        if self.p1 < 0 or self.p2 < 0:
            raise MatcherError(f"MatcherParams.p1 and p2 must be >= 0 (0 = automatic), got {self.p1}, {self.p2}")
        if self.p1 and self.p2 and self.p2 <= self.p1:
            raise MatcherError(f"MatcherParams.p2 must exceed p1, got p1={self.p1}, p2={self.p2}")
        if not 1 <= self.pre_filter_cap <= 63:
            raise MatcherError(f"MatcherParams.pre_filter_cap must be in [1, 63], got {self.pre_filter_cap}")
        if not 0 <= self.uniqueness_ratio <= 100:
            raise MatcherError(f"MatcherParams.uniqueness_ratio must be in [0, 100], got {self.uniqueness_ratio}")
        if self.speckle_window_size < 0 or self.speckle_range < 0:
            raise MatcherError(
                "MatcherParams.speckle_window_size and speckle_range must be >= 0, "
                f"got {self.speckle_window_size}, {self.speckle_range}"
            )
        if self.disp12_max_diff < -1:
            raise MatcherError(f"MatcherParams.disp12_max_diff must be >= -1 (-1 = off), got {self.disp12_max_diff}")
        if self.texture_threshold < 0:
            raise MatcherError(f"MatcherParams.texture_threshold must be >= 0, got {self.texture_threshold}")
        if not (5 <= self.pre_filter_size <= 255) or self.pre_filter_size % 2 == 0:
            raise MatcherError(f"MatcherParams.pre_filter_size must be odd and in [5, 255], got {self.pre_filter_size}")

    @property
    def max_disparity(self) -> float:
        """Largest disparity searched, pixels: ``min_disparity + num_disparities - 1``.

        The one value every ``stereo_msgs/DisparityImage`` of the package
        reports (node and offline labeler alike), as stereo_image_proc does.
        """
        return float(self.min_disparity + self.num_disparities - 1)

    def penalties(self, channels: int) -> tuple[int, int]:
        """Return the SGBM smoothness penalties ``(P1, P2)`` for images with ``channels`` channels.

        Zero fields take the usual defaults ``8 * cn * block_size**2`` and
        ``32 * cn * block_size**2``.
        """
        area = channels * self.block_size * self.block_size
        p1 = self.p1 or 8 * area
        p2 = self.p2 or 32 * area
        if p2 <= p1:
            raise MatcherError(f"SGBM penalty P2 ({p2}) must exceed P1 ({p1}); set MatcherParams.p1/p2 explicitly")
        return p1, p2


@dataclass
class DisparityPair:
    """The output of a query algorithm for one stereo pair.

    Attributes:
        left: HxW float32 left disparity, pixels; NaN where there is none.
        right: HxW float32 right disparity, pixels, NaN where there is none;
            ``None`` when it was not requested or the source cannot give it
            (an external map without its right twin).
    """

    left: NDArray[np.float32]
    right: NDArray[np.float32] | None = None


@runtime_checkable
class Matcher(Protocol):
    """A query algorithm: rectified stereo pair in, disparities out."""

    params: MatcherParams

    def compute(self, left: NDArray[np.uint8], right: NDArray[np.uint8], *, with_right: bool = True) -> DisparityPair:
        """Match a rectified pair.

        Args:
            left: HxW grey or HxWx3 RGB uint8 left image.
            right: right image of the same shape.
            with_right: also compute the right disparity (about doubles the
                cost of the OpenCV matchers).

        Returns:
            The left (and right) disparity, float32 pixels, NaN invalid.
        """
        ...


def validate_pair(left: NDArray[np.generic], right: NDArray[np.generic]) -> None:
    """Check that ``left`` and ``right`` form one grey or RGB uint8 image pair.

    Raises:
        MatcherError: naming the offending image and what was expected.
    """
    for name, image in (("left", left), ("right", right)):
        image = np.asarray(image)
        if image.dtype != np.uint8:
            raise MatcherError(f"{name} image must be uint8, got {image.dtype}")
        if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
            raise MatcherError(f"{name} image must be HxW grey or HxWx3 RGB, got shape {image.shape}")
    if np.shape(left) != np.shape(right):
        raise MatcherError(f"left and right images differ in shape: {np.shape(left)} vs {np.shape(right)}")


def to_grey(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Return an HxW grey version of an HxW grey or HxWx3 RGB uint8 image (ITU-R 601 luma)."""
    image = np.asarray(image)
    if image.ndim == 2:
        return image
    import cv2

    return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def make_matcher(params: MatcherParams | None = None) -> Matcher:
    """Return the query algorithm named by ``params.algorithm`` (default parameters when ``None``)."""
    params = params if params is not None else MatcherParams()
    if params.algorithm == "external":
        from selfcontra_ros.matching.external import ExternalMatcher

        return ExternalMatcher(params)
    if params.algorithm == "census_sgm":
        from selfcontra_ros.matching.census import CensusSGMMatcher

        return CensusSGMMatcher(params)
    from selfcontra_ros.matching.opencv import OpenCVMatcher

    return OpenCVMatcher(params)
