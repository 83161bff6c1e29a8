"""Label codes and their colours, the one place that defines them.

``0`` unknown (ignored in training), ``1`` positive (consistent depth),
``2`` negative (contradicting depth). The colour view follows the paper's
figures: green positive, red negative, blue unknown.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["LABEL_COLORS", "NEGATIVE", "POSITIVE", "UNKNOWN", "colorize_labels"]

UNKNOWN = 0
POSITIVE = 1
NEGATIVE = 2

#: RGB colour per label code (index = code).
LABEL_COLORS: NDArray[np.uint8] = np.array(
    [
        [0, 0, 255],  # unknown: blue
        [0, 255, 0],  # positive: green
        [255, 0, 0],  # negative: red
    ],
    dtype=np.uint8,
)


def colorize_labels(labels: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Return the RGB colour image (HxWx3 uint8) of a label image (HxW uint8).

    Raises:
        ValueError: if the image holds a code other than 0, 1 or 2.
    """
    labels = np.asarray(labels)
    if labels.size and int(labels.max()) > NEGATIVE:
        raise ValueError(f"label image holds code {int(labels.max())}; expected 0, 1 or 2")
    return LABEL_COLORS[labels]
