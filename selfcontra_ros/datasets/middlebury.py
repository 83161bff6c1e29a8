"""Middlebury stereo pairs: the 2003 scenes, and Middlebury 2014 (MiddEval3) / ETH3D two-view folders.

**Middlebury 2003** (Cones, Teddy), one scene folder::

    SCENE/im2.png   left colour image (RGB after reading)
    SCENE/im6.png   right colour image
    SCENE/disp2.png left ground-truth disparity, uint8 = 4 x disparity (quarter-pixel), 0 = unknown

The 2003 ground truth is at the images' full resolution (450x375) with the
factor 4 of the quarter-size release.

**Middlebury 2014 (MiddEval3) and ETH3D two-view**, one scene folder (the
two benchmarks share the layout; ETH3D's images are grey, Middlebury's colour)::

    SCENE/im0.png        left image
    SCENE/im1.png        right image
    SCENE/calib.txt      cam0=[f 0 cx0; 0 f cy; 0 0 1], cam1=[...], doffs, baseline (mm), width, height, ndisp, ...
    SCENE/disp0GT.pfm    left ground-truth disparity, float PFM, inf = unknown (absent in test splits)
    SCENE/mask0nocc.png  optional: 255 = visible in both views, 128 = occluded, 0 = no ground truth

Disparities are image disparities ``x_left - x_right`` in pixels, the same
convention as the query algorithms'; ``doffs = cx1 - cx0`` only matters for
depth (``Z = baseline * f / (d + doffs)``, :class:`MiddleburyCalibration`).
With ``ground_truth="noc"`` (the default, as for KITTI's ``disp_noc``) the
ground truth is kept only where ``mask0nocc.png`` says visible in both views;
a scene without the mask keeps all of it. Mind ``ndisp``: the query
algorithm's ``num_disparities`` must cover it (full-size MiddEval3 scenes
need several hundred pixels; the quarter-size ``Q`` release fits 128-256).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.datasets.kitti import StereoFrame, read_image
from selfcontra_ros.errors import DatasetError

__all__ = [
    "DISPARITY_SCALE",
    "GROUND_TRUTH_CHOICES",
    "MiddleburyCalibration",
    "is_middlebury_scene",
    "middlebury_scenes",
    "read_calibration",
    "read_middlebury",
    "read_pfm",
]

#: ``disp2.png`` stores ``DISPARITY_SCALE * disparity`` as uint8.
DISPARITY_SCALE = 4.0
#: ``ground_truth`` of :func:`read_middlebury`: non-occluded pixels only, or every pixel with ground truth.
GROUND_TRUTH_CHOICES = ("noc", "all")

_FILES = ("im2.png", "im6.png", "disp2.png")
_FILES_2014 = ("im0.png", "im1.png", "calib.txt")
#: ``mask0nocc.png`` value of pixels visible in both views.
_NONOCCLUDED = 255


@dataclass(frozen=True)
class MiddleburyCalibration:
    """The ``calib.txt`` of a Middlebury 2014 / ETH3D scene.

    Attributes:
        fx, fy: focal lengths of ``cam0``, pixels.
        cx0, cy: principal point of ``cam0`` (left), pixels.
        cx1: principal point column of ``cam1`` (right), pixels.
        doffs: ``cx1 - cx0`` as the file states it, pixels.
        baseline: metres (the file gives millimetres).
        width, height: image size, pixels (0 when the file does not say).
        ndisp: the benchmark's bound on the disparity range, pixels (0 when absent).
    """

    fx: float
    fy: float
    cx0: float
    cy: float
    cx1: float
    doffs: float
    baseline: float
    width: int
    height: int
    ndisp: int

    def depth(self, disparity: NDArray[np.float32]) -> NDArray[np.float32]:
        """Depth in metres of image disparities (pixels): ``baseline * fx / (d + doffs)``, NaN where not positive."""
        d = np.asarray(disparity, dtype=np.float64) + self.doffs
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(d > 0, self.baseline * self.fx / d, np.nan)
        return z.astype(np.float32)


def _is_2003_scene(path: Path) -> bool:
    return all((path / name).is_file() for name in _FILES)


def _is_2014_scene(path: Path) -> bool:
    return all((path / name).is_file() for name in _FILES_2014)


def is_middlebury_scene(path: Path | str) -> bool:
    """Whether ``path`` is a 2003 scene (``im2``, ``im6``, ``disp2``) or a 2014/ETH3D one (``im0``, ``im1``, calib)."""
    path = Path(path)
    return _is_2003_scene(path) or _is_2014_scene(path)


def middlebury_scenes(path: Path | str) -> list[Path]:
    """Scene folders of ``path``: itself when it is a scene, else its sub-folders that are scenes (sorted)."""
    path = Path(path)
    if is_middlebury_scene(path):
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.is_dir() and is_middlebury_scene(p))


def read_middlebury(scene: Path | str, index: int = 0, *, ground_truth: str = "noc") -> StereoFrame:
    """Read one Middlebury scene (2003, 2014 or ETH3D layout) as a :class:`StereoFrame`.

    The pair is RGB (grey for ETH3D), the ground truth in pixels with NaN
    where there is none; a 2014 / ETH3D scene without ``disp0GT.pfm`` (a test
    split) has ``gt_disparity`` None.

    Args:
        scene: the scene folder.
        index: the frame's ``index``.
        ground_truth: ``"noc"``: only pixels ``mask0nocc.png`` marks visible in
            both views (2014 / ETH3D with a mask); ``"all"``: every pixel with
            ground truth. The 2003 ground truth is used as it is.

    Raises:
        DatasetError: naming the file that is missing or malformed.
    """
    scene = Path(scene)
    if ground_truth not in GROUND_TRUTH_CHOICES:
        raise DatasetError(f"ground_truth is {ground_truth!r}; expected one of {', '.join(GROUND_TRUTH_CHOICES)}")
    if not _is_2003_scene(scene) and _is_2014_scene(scene):
        return _read_2014(scene, index, ground_truth)
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


def _read_2014(scene: Path, index: int, ground_truth: str) -> StereoFrame:
    left = read_image(scene / "im0.png", color=None)  # ETH3D grey, Middlebury colour
    right = read_image(scene / "im1.png", color=None)
    if left.shape != right.shape:
        raise DatasetError(f"{scene}: im0.png {left.shape} and im1.png {right.shape} differ in size")
    calib = read_calibration(scene / "calib.txt")
    height, width = left.shape[:2]
    if (calib.width and calib.width != width) or (calib.height and calib.height != height):
        raise DatasetError(f"{scene / 'calib.txt'} gives {calib.width}x{calib.height}, but im0.png is {width}x{height}")
    gt_disparity: NDArray[np.float32] | None = None
    gt_file = scene / "disp0GT.pfm"
    if gt_file.is_file():
        gt = read_pfm(gt_file)
        if gt.shape != (height, width):
            raise DatasetError(f"{gt_file} is {gt.shape[1]}x{gt.shape[0]}, but im0.png is {width}x{height}")
        gt[~np.isfinite(gt) | (gt <= 0)] = np.nan  # inf marks unknown; no disparity is <= 0 in these benchmarks
        mask_file = scene / "mask0nocc.png"
        if ground_truth == "noc" and mask_file.is_file():
            mask = read_image(mask_file, color=False)
            if mask.shape != (height, width):
                raise DatasetError(f"{mask_file} is {mask.shape[1]}x{mask.shape[0]}, but im0.png is {width}x{height}")
            gt[mask != _NONOCCLUDED] = np.nan
        gt_disparity = gt
    return StereoFrame(
        index=index, name=scene.name, stamp=0.0, left=left, right=right, pose=None, gt_disparity=gt_disparity
    )


def read_pfm(path: Path | str) -> NDArray[np.float32]:
    """Read a single-channel PFM image (``Pf``) as HxW float32, first row at the top.

    PFM stores rows bottom to top, in the byte order the scale's sign gives
    (negative = little endian). Non-finite values (Middlebury's ``inf`` for
    unknown) are returned as they are.

    Raises:
        DatasetError: the file is missing, not a grey PFM, or shorter than its header says.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc
    header = re.match(rb"(P[fF])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data)
    if header is None:
        raise DatasetError(f"{path} is not a PFM file (expected the header 'Pf WIDTH HEIGHT SCALE')")
    if header.group(1) != b"Pf":
        raise DatasetError(f"{path} is a colour PFM (PF); expected a single-channel disparity map (Pf)")
    width, height = int(header.group(2)), int(header.group(3))
    try:
        scale = float(header.group(4))
    except ValueError:
        raise DatasetError(f"{path}: PFM scale {header.group(4)!r} is not a number") from None
    if scale == 0 or width <= 0 or height <= 0:
        raise DatasetError(f"{path}: PFM header gives size {width}x{height} and scale {scale}")
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    start, count = header.end(), width * height
    if len(data) - start < count * 4:
        raise DatasetError(f"{path} holds {len(data) - start} bytes of pixels; its header needs {count * 4}")
    values = np.frombuffer(data, dtype=dtype, count=count, offset=start).reshape(height, width)
    return np.ascontiguousarray(values[::-1], dtype=np.float32)


def _matrix(text: str, key: str, path: Path) -> NDArray[np.float64]:
    try:
        rows = [[float(v) for v in row.split()] for row in text.strip().strip("[]").split(";")]
        matrix = np.array(rows, dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}: {key} is not a 3x3 matrix: {text!r}") from None
    if matrix.shape != (3, 3):
        raise DatasetError(f"{path}: {key} is not a 3x3 matrix: {text!r}")
    return matrix


def read_calibration(path: Path | str) -> MiddleburyCalibration:
    """Read a Middlebury 2014 / ETH3D ``calib.txt`` (``key=value`` lines; ``cam0``/``cam1`` as ``[a b c; ...]``).

    Raises:
        DatasetError: the file is missing, or lacks ``cam0``, ``cam1`` or ``baseline``, or a value is malformed.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc
    values = {}
    for line in lines:
        if "=" in line:
            key, value = line.split("=", 1)
            values[key.strip()] = value.strip()
    missing = [key for key in ("cam0", "cam1", "baseline") if key not in values]
    if missing:
        raise DatasetError(f"{path} lacks {', '.join(missing)} (expected Middlebury 2014 / ETH3D calib.txt)")
    cam0, cam1 = _matrix(values["cam0"], "cam0", path), _matrix(values["cam1"], "cam1", path)

    def number(key: str, default: float = 0.0) -> float:
        try:
            return float(values.get(key, default))
        except ValueError:
            raise DatasetError(f"{path}: {key}={values[key]!r} is not a number") from None

    baseline_mm = number("baseline")
    if not baseline_mm > 0 or not cam0[0, 0] > 0:
        raise DatasetError(f"{path}: baseline {baseline_mm} mm and focal length {cam0[0, 0]} px must be positive")
    return MiddleburyCalibration(
        fx=float(cam0[0, 0]),
        fy=float(cam0[1, 1]),
        cx0=float(cam0[0, 2]),
        cy=float(cam0[1, 2]),
        cx1=float(cam1[0, 2]),
        doffs=number("doffs", float(cam1[0, 2] - cam0[0, 2])),
        baseline=baseline_mm / 1000.0,
        width=int(number("width")),
        height=int(number("height")),
        ndisp=int(number("ndisp")),
    )
