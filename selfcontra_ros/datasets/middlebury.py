"""Middlebury 2003 stereo pairs (Cones, Teddy): ``im2``/``im6`` left/right, ``disp2`` left ground truth.

Layout of one scene folder::

    SCENE/im2.png   left colour image (RGB after reading)
    SCENE/im6.png   right colour image
    SCENE/disp2.png left ground-truth disparity, uint8 = 4 x disparity (quarter-pixel), 0 = unknown

The 2003 ground truth is at the images' full resolution (450x375) with the
factor 4 of the quarter-size release.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.datasets.kitti import StereoFrame, read_image
from selfcontra_ros.errors import DatasetError

__all__ = ["DISPARITY_SCALE", "is_middlebury_scene", "middlebury_scenes", "read_middlebury"]

#: ``disp2.png`` stores ``DISPARITY_SCALE * disparity`` as uint8.
DISPARITY_SCALE = 4.0

_FILES = ("im2.png", "im6.png", "disp2.png")


def is_middlebury_scene(path: Path | str) -> bool:
    """Whether ``path`` is a folder holding ``im2.png``, ``im6.png`` and ``disp2.png``."""
    path = Path(path)
    return all((path / name).is_file() for name in _FILES)


def middlebury_scenes(path: Path | str) -> list[Path]:
    """Scene folders of ``path``: itself when it is a scene, else its sub-folders that are scenes (sorted)."""
    path = Path(path)
    if is_middlebury_scene(path):
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.is_dir() and is_middlebury_scene(p))


def read_middlebury(scene: Path | str, index: int = 0) -> StereoFrame:
    """Read one Middlebury 2003 scene as a :class:`StereoFrame` (RGB pair, ground truth in pixels, NaN = none).

    Raises:
        DatasetError: naming the file that is missing or malformed.
    """
    scene = Path(scene)
    left = read_image(scene / "im2.png", color=True)
    right = read_image(scene / "im6.png", color=True)
    if left.shape != right.shape:
        raise DatasetError(f"{scene}: im2.png {left.shape} and im6.png {right.shape} differ in size")
    raw = cv2.imread(str(scene / "disp2.png"), cv2.IMREAD_GRAYSCALE)
    if raw is None or raw.shape != left.shape[:2]:
        raise DatasetError(f"{scene / 'disp2.png'} is missing or not a {left.shape[1]}x{left.shape[0]} grey image")
    gt = raw.astype(np.float32) / np.float32(DISPARITY_SCALE)
    gt[raw == 0] = np.nan
    gt_disparity: NDArray[np.float32] = gt
    return StereoFrame(
        index=index, name=scene.name, stamp=0.0, left=left, right=right, pose=None, gt_disparity=gt_disparity
    )
