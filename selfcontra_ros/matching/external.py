"""The "external" query algorithm: a disparity map computed elsewhere.

Any stereo algorithm running on the robot (a bag's ``disparity`` topic, a GPU
matcher, a learned network) can be labelled: the caller hands its disparity
to :meth:`ExternalMatcher.provide` and then calls :meth:`compute` with the
image pair it belongs to, like any other matcher. The labels are then *for
that algorithm* (DESIGN section 5).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.matching.base import DisparityPair, MatcherError, MatcherParams, validate_pair

__all__ = ["ExternalMatcher", "normalize_disparity"]


def normalize_disparity(disparity: ArrayLike, *, name: str = "disparity") -> NDArray[np.float32]:
    """Return an HxW float32 copy of ``disparity`` (pixels) with NaN where it has no finite depth.

    Non-finite and non-positive values become NaN (DESIGN section 2).

    Raises:
        MatcherError: if ``disparity`` is not a 2-D real array.
    """
    array = np.asarray(disparity)
    if array.ndim != 2 or not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise MatcherError(f"{name} must be a 2-D real array (HxW pixels), got {array.dtype} of shape {array.shape}")
    out = array.astype(np.float32, copy=True)
    with np.errstate(invalid="ignore"):
        out[~(np.isfinite(out) & (out > 0))] = np.nan
    return out


class ExternalMatcher:
    """Pass-through query algorithm for disparities computed outside the package.

    Each provided map is used for exactly one :meth:`compute` call, so a
    missing message can never silently re-label a stale map.
    """

    def __init__(self, params: MatcherParams | None = None) -> None:
        """Create the matcher (``params.algorithm`` should be ``"external"``; other fields are unused)."""
        self.params = params if params is not None else MatcherParams(algorithm="external")
        self._pending: DisparityPair | None = None

    def provide(self, left: ArrayLike, right: ArrayLike | None = None) -> None:
        """Hand in the disparity for the next :meth:`compute` call.

        Args:
            left: HxW left disparity, pixels (``u_right = u - d``).
            right: optional HxW right disparity, pixels (``u_left = u + d``).

        Raises:
            MatcherError: if a map is not 2-D or the two maps differ in shape.
        """
        pair = DisparityPair(left=normalize_disparity(left, name="external left disparity"))
        if right is not None:
            pair.right = normalize_disparity(right, name="external right disparity")
            if pair.right.shape != pair.left.shape:
                raise MatcherError(
                    f"external right disparity has shape {pair.right.shape}, the left one {pair.left.shape}"
                )
        self._pending = pair

    def compute(self, left: NDArray[np.uint8], right: NDArray[np.uint8], *, with_right: bool = True) -> DisparityPair:
        """Return the provided disparity after checking that it fits the image pair.

        ``right`` of the result is the provided right disparity, or ``None``
        when none was provided or ``with_right`` is false.

        Raises:
            MatcherError: if no disparity was provided since the last call, or
                its size differs from the images'.
        """
        validate_pair(left, right)
        if self._pending is None:
            raise MatcherError("external matcher: no disparity was provided for this image pair (call provide())")
        pair, self._pending = self._pending, None
        if pair.left.shape != np.shape(left)[:2]:
            raise MatcherError(
                f"external disparity has shape {pair.left.shape}, the images {np.shape(left)[:2]} (HxW expected equal)"
            )
        return DisparityPair(left=pair.left, right=pair.right if with_right else None)
