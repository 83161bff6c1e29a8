"""Fixtures shared by the confidence tests."""

from __future__ import annotations

from typing import Any

import cv2
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


def _texture(rng: np.random.Generator, shape: tuple[int, int], mean: float) -> np.ndarray:
    noise = rng.normal(mean, 40.0, shape).astype(np.float32)
    return np.asarray(cv2.GaussianBlur(noise, (3, 3), 0), dtype=np.float32)


@pytest.fixture(scope="module")
def stereo_edge() -> dict[str, Any]:
    """A rectified pair of a textured object (disparity 30, from column ``edge`` on) before a textured background
    (disparity 10), its true disparity, and a query disparity that carries the object's ``fattened`` px too far
    left (background hidden from the right camera, as beside any object's left outline)."""
    edge, fattened = 100, 8
    rng = np.random.default_rng(4)
    height, width = 60, 260
    background, front = _texture(rng, (height, width + 40), 110.0), _texture(rng, (height, width + 40), 140.0)
    columns = np.arange(width)
    left = np.where(columns >= edge, front[:, columns], background[:, columns])
    # A right pixel x shows the object where x + 30 falls on it, else the background at x + 10.
    on_object = columns + 30 >= edge
    right = np.where(on_object, front[:, columns + 30], background[:, columns + 10])
    truth = np.where(columns >= edge, 30.0, 10.0) * np.ones((height, 1))
    query = truth.copy()
    query[:, edge - fattened : edge] = 30.0
    as_image = lambda a: np.clip(a, 0, 255).astype(np.uint8)  # noqa: E731
    return {
        "left": as_image(left),
        "right": as_image(right),
        "truth": truth.astype(np.float32),
        "query": query.astype(np.float32),
        "edge": edge,
        "fattened": fattened,
    }
