"""Fixtures shared by the confidence tests."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def fattened_edge() -> tuple[np.ndarray, np.ndarray]:
    """A 200x40 left image and its disparity: an object from column 80 on (bright, disparity 30) before a dark
    background (disparity 10), the object's disparity spread 6 px left as a window matcher fattens it."""
    rng = np.random.default_rng(1)
    image = np.where(np.arange(200) >= 80, 200.0, 50.0) + rng.normal(0, 5, (40, 200))
    d = np.full((40, 200), 10.0, np.float32)
    d[:, 74:] = 30.0
    return np.clip(image, 0, 255).astype(np.uint8), d
