"""KITTI readers: odometry sequences, stereo 2012/2015 multiview scenes, and the KITTI file formats.

Two layouts are read, both yielding :class:`StereoFrame` objects with lazily
loaded images:

* **Odometry** (:func:`open_sequence`), real KITTI or the package's synthetic
  renderer::

      ROOT/sequences/XX/image_0|image_1/NNNNNN.png    grey left/right (cameras 0, 1)
      ROOT/sequences/XX/image_2|image_3/NNNNNN.png    colour left/right (cameras 2, 3)
      ROOT/sequences/XX/calib.txt                     "P0: 12 numbers" ... "P3: ..." (labels optional)
      ROOT/sequences/XX/times.txt                     optional, one stamp (s) per line; else 10 Hz
      ROOT/sequences/XX/disp_0|disp_2/NNNNNN.png      optional left ground-truth disparity (KITTI PNG)
      ROOT/poses/XX.txt                               optional, 12 numbers per line (3x4 T_world_cam0)

* **Stereo 2012 / 2015** (:func:`open_stereo_dataset`), the multiview
  benchmark layout: scenes ``NNNNNN`` with frames ``NNNNNN_MM`` (MM = 00..20,
  frame 10 is the reference frame that carries the ground truth)::

      SPLIT/image_2|image_3/NNNNNN_MM.png          2015 colour pair (P_rect_02/03 of calib_cam_to_cam/NNNNNN.txt)
      SPLIT/disp_noc_0|disp_occ_0/NNNNNN_10.png    2015 ground truth of frame 10, camera 2
      SPLIT/image_0|image_1/NNNNNN_MM.png          2012 grey pair (P0/P1 of calib/NNNNNN.txt)
      SPLIT/colored_0|colored_1/NNNNNN_MM.png      2012 colour pair (P2/P3 of calib/NNNNNN.txt)
      SPLIT/disp_noc|disp_occ/NNNNNN_10.png        2012 ground truth of frame 10, grey camera 0

Conventions:

* Colour images are returned RGB (OpenCV reads BGR; the readers convert).
* Ground-truth disparity is float32 pixels with NaN where there is none
  (KITTI stores ``uint16 = round(d * 256)``, 0 = no ground truth).
* KITTI's rectified projection matrices are ``P_i = K [I | t_i]`` in the
  rectified frame of camera 0. The colour cameras (2, 3) carry a few-millimetre
  vertical/forward offset besides the horizontal one; their images are row
  aligned, so the readers keep only the horizontal part of each offset
  (``t_x = (K^-1 P[:, 3])_x``) and reject pairs whose off-axis offsets differ by
  more than 2 % of the baseline. For matrices without such offsets the baseline
  is exactly ``(P_left[0, 3] - P_right[0, 3]) / fx``.
* Odometry poses are ``T_world_left`` 4x4 with world = camera 0 at frame 0 (the
  KITTI convention). For the colour pair the pose is that of camera 2:
  ``T_world_cam2 = T_world_cam0 @ [I | c_2]`` where ``c_2 = -K^-1 P2[:, 3]`` is
  camera 2's optical centre in camera 0's frame (rectified cameras share one
  orientation); the world frame stays camera 0 at frame 0.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.errors import CalibrationError, DatasetError
from selfcontra_ros.geometry import StereoCamera

__all__ = [
    "DISPARITY_SCALE",
    "FRAME_PERIOD",
    "OdometrySequence",
    "StereoDataset",
    "StereoFrame",
    "StereoScene",
    "camera_from_calib",
    "open_sequence",
    "open_stereo_dataset",
    "read_calib",
    "read_disparity_png",
    "read_image",
    "read_poses",
    "read_times",
    "write_calib",
    "write_disparity_png",
    "write_poses",
    "write_times",
]

#: KITTI disparity PNGs store ``round(disparity * DISPARITY_SCALE)`` as uint16.
DISPARITY_SCALE = 256.0
#: Seconds between frames when a sequence has no times.txt (KITTI records at about 10 Hz).
FRAME_PERIOD = 0.1
#: Frame number ``MM`` of the stereo benchmarks' reference frame, the one with ground truth.
REFERENCE_FRAME = 10

_IMAGE_SUFFIX = ".png"
_MAX_DISPARITY = 65535.0 / DISPARITY_SCALE
# A "rectified" pair may differ in its vertical/forward camera offsets by this
# share of the baseline (KITTI colour cameras: about 0.5 %); beyond it the rows
# no longer line up at close range and the pair is rejected.
_MAX_OFF_AXIS_RATIO = 0.02
_PROJECTION_KEY = re.compile(r"^(P\d|P_rect_\d\d)$")
_MULTIVIEW_NAME = re.compile(r"^(\d+)_(\d+)$")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass
class StereoFrame:
    """One rectified stereo pair of a sequence, with its pose and ground truth when known.

    Attributes:
        index: position in the sequence (0-based).
        name: file stem, e.g. ``"000012"`` or ``"000000_10"``.
        stamp: seconds (times.txt, else ``index * FRAME_PERIOD``; stereo scenes:
            ``MM * FRAME_PERIOD``).
        left: HxW grey or HxWx3 RGB uint8 image of the left camera.
        right: the right image, same shape as ``left``.
        pose: 4x4 ``T_world_left`` (metres), or None when the sequence has no poses.
        gt_disparity: HxW float32 left disparity in pixels, NaN where there is no
            ground truth; None when the frame has no ground-truth file.
    """

    index: int
    name: str
    stamp: float
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    pose: NDArray[np.float64] | None
    gt_disparity: NDArray[np.float32] | None


# --------------------------------------------------------------------------- images


def read_image(path: Path | str, *, color: bool | None = False) -> NDArray[np.uint8]:
    """Load an 8-bit image as HxW grey (``color=False``), HxWx3 RGB (``color=True``) or as stored (``None``).

    Raises:
        DatasetError: naming the path when the file is missing or unreadable,
            not 8-bit, or has the wrong number of channels.
    """
    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"cannot read image {path} (missing or not an image file)")
    if image.dtype != np.uint8:
        raise DatasetError(f"image {path} is {image.dtype}, expected 8-bit (uint8)")
    if color is None:
        color = image.ndim == 3
    if color:
        if image.ndim != 3 or image.shape[2] not in (3, 4):
            raise DatasetError(f"image {path} has shape {image.shape}, expected a colour image (HxWx3)")
        code = cv2.COLOR_BGR2RGB if image.shape[2] == 3 else cv2.COLOR_BGRA2RGB
        return np.asarray(cv2.cvtColor(image, code), dtype=np.uint8)
    if image.ndim != 2:
        raise DatasetError(f"image {path} has shape {image.shape}, expected a single-channel grey image (HxW)")
    return np.asarray(image, dtype=np.uint8)


def _image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image; read from the PNG header when possible (no decoding)."""
    try:
        with path.open("rb") as f:
            head = f.read(24)
    except OSError as exc:
        raise DatasetError(f"cannot read image {path}: {exc}") from exc
    if head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
        width, height = struct.unpack(">II", head[16:24])
        return int(width), int(height)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"cannot read image {path} (missing or not an image file)")
    return int(image.shape[1]), int(image.shape[0])


# --------------------------------------------------------------------------- disparity PNG


def read_disparity_png(path: Path | str) -> NDArray[np.float32]:
    """Read a KITTI disparity PNG: HxW float32 disparity in pixels, NaN where the file holds 0 (no value).

    Raises:
        DatasetError: naming the path when the file is unreadable or not a
            single-channel 16-bit PNG.
    """
    path = Path(path)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f"cannot read disparity PNG {path} (missing or not an image file)")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DatasetError(
            f"disparity PNG {path} is {raw.dtype} with shape {raw.shape}, expected single-channel uint16 "
            f"(KITTI: disparity * {DISPARITY_SCALE:g}, 0 = none)"
        )
    disparity = raw.astype(np.float32) / np.float32(DISPARITY_SCALE)
    disparity[raw == 0] = np.nan
    return disparity


def write_disparity_png(path: Path | str, disparity: ArrayLike) -> None:
    """Write an HxW disparity map (pixels) as a KITTI uint16 PNG: ``round(d * 256)``, 0 where invalid.

    Non-finite and non-positive disparities become 0 (no value); positive
    disparities below ``1/512`` px are stored as ``1/256`` so that they stay
    valid. Parent folders are created.

    Raises:
        DatasetError: when the path is not ``.png``, the array is not 2-D, a
            disparity exceeds ``65535/256`` px, or the file cannot be written.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise DatasetError(f"disparity file {path} must end in .png (KITTI 16-bit PNG format)")
    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2:
        raise DatasetError(f"disparity for {path} has shape {d.shape}, expected HxW")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    if np.any(d[valid] > _MAX_DISPARITY):
        raise DatasetError(
            f"disparity for {path} reaches {np.max(d[valid]):.3f} px; the KITTI PNG format holds at most "
            f"{_MAX_DISPARITY:.3f} px"
        )
    encoded = np.zeros(d.shape, dtype=np.uint16)
    encoded[valid] = np.clip(np.rint(d[valid] * DISPARITY_SCALE), 1, 65535).astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), encoded):
        raise DatasetError(f"cannot write disparity PNG {path}")


# --------------------------------------------------------------------------- text files


def _read_lines(path: Path, what: str) -> list[str]:
    try:
        return path.read_text().splitlines()
    except FileNotFoundError as exc:
        raise DatasetError(f"{what} {path} does not exist") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read {what} {path}: {exc}") from exc


def _parse_numbers(text: str) -> NDArray[np.float64] | None:
    """Whitespace-separated finite floats of ``text``, or None when any token is not a finite number."""
    try:
        values = np.array([float(token) for token in text.split()], dtype=np.float64)
    except ValueError:
        return None
    return values if np.all(np.isfinite(values)) else None


def read_poses(path: Path | str) -> NDArray[np.float64]:
    """Read a KITTI pose file: (N, 4, 4) float64 camera-to-world transforms (metres).

    Each non-empty line holds 12 numbers, the row-major 3x4 ``[R | t]``.

    Raises:
        DatasetError: naming the file and line when a line does not hold 12 finite numbers.
    """
    path = Path(path)
    rows: list[NDArray[np.float64]] = []
    for number, line in enumerate(_read_lines(path, "pose file"), start=1):
        if not line.strip():
            continue
        values = _parse_numbers(line)
        if values is None or values.size != 12:
            found = "non-numeric values" if values is None else f"{values.size} numbers"
            raise DatasetError(f"{path}:{number}: pose line has {found}, expected 12 (row-major 3x4 [R | t])")
        rows.append(values)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        poses[:, :3, :] = np.stack(rows).reshape(-1, 3, 4)
    return poses


def write_poses(path: Path | str, poses: ArrayLike) -> None:
    """Write (N, 4, 4) or (N, 3, 4) camera-to-world poses in KITTI format (12 numbers per line).

    Parent folders are created.

    Raises:
        DatasetError: when the array is not (N, 3|4, 4), not finite, or a 4x4
            pose's last row is not ``[0, 0, 0, 1]``.
    """
    path = Path(path)
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] not in ((4, 4), (3, 4)):
        raise DatasetError(f"poses for {path} have shape {p.shape}, expected (N, 4, 4) or (N, 3, 4)")
    if not np.all(np.isfinite(p)):
        raise DatasetError(f"poses for {path} hold non-finite values")
    if p.shape[1] == 4 and not np.allclose(p[:, 3, :], [0.0, 0.0, 0.0, 1.0]):
        raise DatasetError(f"poses for {path}: last row of each 4x4 pose must be [0, 0, 0, 1]")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, p[:, :3, :].reshape(-1, 12), fmt="%.12e")


def read_times(path: Path | str) -> NDArray[np.float64]:
    """Read a KITTI times.txt: one stamp (seconds) per non-empty line, as a float64 array.

    Raises:
        DatasetError: naming the file and line when a line is not one finite number.
    """
    path = Path(path)
    stamps: list[float] = []
    for number, line in enumerate(_read_lines(path, "times file"), start=1):
        if not line.strip():
            continue
        values = _parse_numbers(line)
        if values is None or values.size != 1:
            raise DatasetError(f"{path}:{number}: expected one stamp in seconds, got {line.strip()!r}")
        stamps.append(float(values[0]))
    return np.array(stamps, dtype=np.float64)


def write_times(path: Path | str, stamps: ArrayLike) -> None:
    """Write stamps (seconds) one per line, KITTI times.txt style, to the nanosecond. Parent folders are created."""
    path = Path(path)
    s = np.asarray(stamps, dtype=np.float64).reshape(-1)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Fixed-point keeps nanoseconds for epoch stamps too (an exponent format would not).
    np.savetxt(path, s, fmt="%.9f")


# --------------------------------------------------------------------------- calibration


def read_calib(path: Path | str) -> dict[str, NDArray[np.float64]]:
    """Numeric entries of a KITTI calibration file as flat float64 arrays keyed by label.

    Reads ``KEY: numbers`` lines (odometry/2012 ``P0``..``P3``, ``Tr``;
    2015 ``P_rect_02``, ``S_rect_02``, ...). Lines without a label must hold
    12 numbers and are named ``P0``, ``P1``, ... in order. Labelled lines
    whose values are not numbers (``calib_time``) are skipped unless they are
    projection matrices.

    Raises:
        DatasetError: naming the file and line when the file is missing, a
            projection matrix (``P<i>``, ``P_rect_<ij>`` or an unlabelled line)
            does not hold 12 finite numbers, or a label repeats.
    """
    path = Path(path)
    entries: dict[str, NDArray[np.float64]] = {}
    unlabelled = 0
    for number, line in enumerate(_read_lines(path, "calibration file"), start=1):
        text = line.strip()
        if not text:
            continue
        if ":" in text:
            key, _, rest = text.partition(":")
            key = key.strip()
        else:
            key, rest = f"P{unlabelled}", text
            unlabelled += 1
        values = _parse_numbers(rest)
        is_projection = _PROJECTION_KEY.match(key) is not None
        if is_projection and (values is None or values.size != 12):
            found = "non-numeric values" if values is None else f"{values.size} numbers"
            raise DatasetError(f"{path}:{number}: projection matrix {key} has {found}, expected 12 (row-major 3x4)")
        if values is None:
            continue
        if key in entries:
            raise DatasetError(f"{path}:{number}: {key} appears twice")
        entries[key] = values
    return entries


def _projection(entries: dict[str, NDArray[np.float64]], key: str, source: Path) -> NDArray[np.float64]:
    if key not in entries:
        raise DatasetError(f"calibration file {source} has no {key} (found: {', '.join(sorted(entries)) or 'none'})")
    return entries[key].reshape(3, 4)


def _stereo_pair(
    p_left: NDArray[np.float64],
    p_right: NDArray[np.float64],
    width: int,
    height: int,
    source: str,
) -> tuple[StereoCamera, NDArray[np.float64]]:
    """The camera of a rectified pair and the left optical centre in the reference camera's frame (metres).

    ``P = K [I | t]``: ``t = K^-1 P[:, 3]`` and the optical centre is ``-t``.
    Only the horizontal offsets enter the camera (see the module docstring).
    """
    offsets = []
    for name, p in (("left", p_left), ("right", p_right)):
        try:
            offsets.append(np.linalg.solve(p[:, :3], p[:, 3]))
        except np.linalg.LinAlgError as exc:
            raise CalibrationError(f"{source}: {name} projection matrix has a singular K; is it calibrated?") from exc
    t_left, t_right = offsets
    difference = t_left - t_right
    off_axis = np.abs(difference[1:])
    if np.any(off_axis > _MAX_OFF_AXIS_RATIO * abs(difference[0])):
        raise CalibrationError(
            f"{source}: left and right cameras differ by {difference[1]:.4f} m vertically and {difference[2]:.4f} m "
            f"forward against a baseline of {difference[0]:.4f} m; expected a rectified, horizontal pair"
        )
    ideal = []
    for p, t in ((p_left, t_left), (p_right, t_right)):
        q = p.copy()
        q[:, 3] = p[:, 0] * t[0]  # K @ (t_x, 0, 0)
        ideal.append(q)
    camera = StereoCamera.from_projections(ideal[0], ideal[1], width, height, source=source)
    return camera, np.asarray(-t_left, dtype=np.float64)


def camera_from_calib(
    path: Path | str,
    width: int,
    height: int,
    *,
    left: str = "P0",
    right: str = "P1",
) -> StereoCamera:
    """StereoCamera of a KITTI calibration file from the projection matrices named ``left`` and ``right``.

    Args:
        path: calib.txt (odometry, 2012) or calib_cam_to_cam file (2015).
        width: image width, pixels.
        height: image height, pixels.
        left: key of the left camera's 3x4 matrix (``P0``, ``P2``, ``P_rect_02``, ...).
        right: key of the right camera's matrix.

    Raises:
        DatasetError: file missing, key missing or malformed line.
        CalibrationError: the matrices do not describe a rectified horizontal pair.
    """
    path = Path(path)
    entries = read_calib(path)
    camera, _ = _stereo_pair(
        _projection(entries, left, path), _projection(entries, right, path), width, height, f"{path} ({left}, {right})"
    )
    return camera


def write_calib(path: Path | str, camera: StereoCamera) -> None:
    """Write a KITTI odometry calib.txt for ``camera``: ``P0``/``P1`` and identical ``P2``/``P3`` lines.

    The left matrix has ``P[0, 3] = 0``, the right ``P[0, 3] = -fx * baseline``.
    Parent folders are created.
    """
    path = Path(path)
    p_left, p_right = camera.projection_matrices()
    lines = [
        f"{key}: " + " ".join(f"{v:.12e}" for v in p.reshape(-1))
        for key, p in (("P0", p_left), ("P1", p_right), ("P2", p_left), ("P3", p_right))
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- folders


def _frame_key(stem: str) -> tuple[int, str]:
    # Numeric order when names are numbers of different widths, else lexicographic.
    return (int(stem), stem) if stem.isdigit() else (-1, stem)


def _image_stems(folder: Path) -> list[str]:
    return sorted((p.stem for p in folder.glob(f"*{_IMAGE_SUFFIX}") if p.is_file()), key=_frame_key)


def _check_pairs(left_dir: Path, right_dir: Path, left: Sequence[str], right: Sequence[str]) -> None:
    """Raise DatasetError unless both folders hold the same frames."""
    if len(left) != len(right):
        raise DatasetError(
            f"left folder {left_dir} holds {len(left)} images but right folder {right_dir} holds {len(right)}"
        )
    missing = sorted(set(left) - set(right), key=_frame_key)
    if missing:
        raise DatasetError(f"right image {right_dir / (missing[0] + _IMAGE_SUFFIX)} is missing")
    if not left:
        raise DatasetError(f"no {_IMAGE_SUFFIX} images in {left_dir}")


def _load_pair(
    left_path: Path, right_path: Path, camera: StereoCamera, color: bool
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    left = read_image(left_path, color=color)
    right = read_image(right_path, color=color)
    if left.shape != right.shape:
        raise DatasetError(f"left image {left_path} is {left.shape} but right image {right_path} is {right.shape}")
    if left.shape[:2] != (camera.height, camera.width):
        raise DatasetError(
            f"image {left_path} is {left.shape[1]}x{left.shape[0]}, expected {camera.width}x{camera.height} "
            "like the first image of its sequence"
        )
    return left, right


def _load_gt(path: Path | None, camera: StereoCamera) -> NDArray[np.float32] | None:
    if path is None or not path.is_file():
        return None
    gt = read_disparity_png(path)
    if gt.shape != (camera.height, camera.width):
        raise DatasetError(
            f"ground truth {path} is {gt.shape[1]}x{gt.shape[0]}, expected {camera.width}x{camera.height}"
        )
    return gt


def _normalise_index(i: int, n: int, what: str) -> int:
    if not -n <= i < n:
        raise IndexError(f"{what} has {n} frames, index {i} is out of range")
    return i % n


# --------------------------------------------------------------------------- odometry


class OdometrySequence:
    """A KITTI odometry sequence (real or synthetic); frames load lazily from disk.

    Attributes:
        root: dataset root (the folder holding ``sequences/``), or the sequence
            folder itself when it does not sit in a ``sequences/`` folder.
        sequence: sequence name, e.g. ``"06"``.
        folder: the sequence folder (holding ``image_*`` and ``calib.txt``).
        color: True for the colour pair (cameras 2, 3), False for grey (0, 1).
        left_dir, right_dir: image folders of the left and right camera.
        gt_dir: ``disp_0`` (grey) or ``disp_2`` (colour) when present, else None.
        names: frame file stems in order.
        camera: the rectified pair's StereoCamera.
        stamps: (N,) seconds.
        poses: (N, 4, 4) ``T_world_left`` or None (no ``poses/XX.txt``).
    """

    def __init__(self, folder: Path | str, *, color: bool = False, poses_path: Path | str | None = None) -> None:
        """Index the sequence in ``folder``; see :func:`open_sequence` for the usual entry point.

        Raises:
            DatasetError: missing folders or files, unequal left/right image
                sets, malformed calibration/times/poses, or counts of
                stamps/poses that differ from the number of frames.
            CalibrationError: the calibration is not a rectified horizontal pair.
        """
        self.folder = Path(folder)
        self.sequence = self.folder.name
        self.root = self.folder.parent.parent if self.folder.parent.name == "sequences" else self.folder
        self.color = color
        cams = (2, 3) if color else (0, 1)
        self.left_dir = self.folder / f"image_{cams[0]}"
        self.right_dir = self.folder / f"image_{cams[1]}"
        for d in (self.left_dir, self.right_dir):
            if not d.is_dir():
                raise DatasetError(f"image folder {d} does not exist")
        self.names = _image_stems(self.left_dir)
        _check_pairs(self.left_dir, self.right_dir, self.names, _image_stems(self.right_dir))
        n = len(self.names)

        calib_path = self.folder / "calib.txt"
        entries = read_calib(calib_path)
        width, height = _image_size(self._left_path(0))
        keys = (f"P{cams[0]}", f"P{cams[1]}")
        self.camera, left_centre = _stereo_pair(
            _projection(entries, keys[0], calib_path),
            _projection(entries, keys[1], calib_path),
            width,
            height,
            f"{calib_path} ({keys[0]}, {keys[1]})",
        )

        times_path = self.folder / "times.txt"
        if times_path.is_file():
            self.stamps = read_times(times_path)
            if self.stamps.size != n:
                raise DatasetError(f"times file {times_path} holds {self.stamps.size} stamps for {n} frames")
        else:
            self.stamps = np.arange(n, dtype=np.float64) * FRAME_PERIOD

        self.poses: NDArray[np.float64] | None = None
        if poses_path is not None:
            poses_path = Path(poses_path)
            poses = read_poses(poses_path)
            if len(poses) != n:
                raise DatasetError(f"pose file {poses_path} holds {len(poses)} poses for {n} frames in {self.left_dir}")
            # Poses are of camera 0; move them to the left camera of the chosen pair.
            shift = np.eye(4)
            shift[:3, 3] = left_centre
            self.poses = poses @ shift

        gt_dir = self.folder / f"disp_{cams[0]}"
        self.gt_dir = gt_dir if gt_dir.is_dir() else None

    def _left_path(self, i: int) -> Path:
        return self.left_dir / (self.names[i] + _IMAGE_SUFFIX)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> StereoFrame:
        """Load frame ``i`` (negative indices count from the end).

        Raises:
            IndexError: ``i`` out of range.
            DatasetError: unreadable images, left/right or ground-truth sizes that disagree.
        """
        i = _normalise_index(i, len(self), f"sequence {self.folder}")
        name = self.names[i]
        left, right = _load_pair(self._left_path(i), self.right_dir / (name + _IMAGE_SUFFIX), self.camera, self.color)
        gt_path = None if self.gt_dir is None else self.gt_dir / (name + _IMAGE_SUFFIX)
        return StereoFrame(
            index=i,
            name=name,
            stamp=float(self.stamps[i]),
            left=left,
            right=right,
            pose=None if self.poses is None else self.poses[i].copy(),
            gt_disparity=_load_gt(gt_path, self.camera),
        )

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        pair = "colour" if self.color else "grey"
        return f"OdometrySequence({str(self.folder)!r}, {len(self)} {pair} frames, poses={self.poses is not None})"


def open_sequence(path: Path | str, *, sequence: str | None = None, color: bool = False) -> OdometrySequence:
    """Open a KITTI odometry sequence.

    Args:
        path: a dataset root holding ``sequences/XX`` (and optionally
            ``poses/XX.txt``), or a ``sequences/XX`` folder itself.
        sequence: which sequence of a root holding several (``"06"``; ``"6"``
            is padded to two digits). Not needed when the root holds one.
        color: read the colour pair ``image_2``/``image_3`` (P2/P3) instead of
            the grey pair ``image_0``/``image_1`` (P0/P1). The colour pair is
            also taken when the grey one is absent.

    Raises:
        DatasetError: the path is not a KITTI odometry root or sequence, the
            sequence is ambiguous or missing, or its files are malformed.
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"dataset path {path} is not a folder")
    if (path / "sequences").is_dir():
        root = path
        available = sorted(p.name for p in (root / "sequences").iterdir() if p.is_dir())
        if sequence is None:
            if len(available) != 1:
                raise DatasetError(
                    f"{root / 'sequences'} holds sequences {available or 'none'}; pass sequence= to choose one"
                )
            sequence = available[0]
        elif sequence not in available and sequence.isdigit() and sequence.zfill(2) in available:
            sequence = sequence.zfill(2)
        if sequence not in available:
            raise DatasetError(f"sequence {sequence!r} is not in {root / 'sequences'} (found: {available or 'none'})")
        folder = root / "sequences" / sequence
    elif any((path / f"image_{c}").is_dir() for c in range(4)):
        folder = path
        if sequence is not None and sequence != path.name:
            raise DatasetError(f"{path} is sequence {path.name!r}, not the requested {sequence!r}")
        root = path.parent.parent if path.parent.name == "sequences" else path
    else:
        raise DatasetError(
            f"{path} is neither a KITTI odometry root (with sequences/XX) nor a sequence folder (with image_0/image_1)"
        )
    if not color and not (folder / "image_0").is_dir() and (folder / "image_2").is_dir():
        color = True
    poses_path = root / "poses" / f"{folder.name}.txt"
    return OdometrySequence(folder, color=color, poses_path=poses_path if poses_path.is_file() else None)


# --------------------------------------------------------------------------- stereo 2012 / 2015


@dataclass(frozen=True)
class _StereoLayout:
    """Folder and calibration names of one image pair of a stereo benchmark."""

    left: str
    right: str
    calib_dir: str
    p_left: str
    p_right: str
    gt_noc: str | None
    gt_occ: str | None
    color: bool


# KITTI 2015 ships only the colour pair; a grey pair (cameras 0/1) has no
# ground truth of its own. KITTI 2012's ground truth is defined on the grey
# reference camera 0: the colour pair (camera 2, 6 cm away) gets none rather
# than a misaligned one.
_LAYOUTS: dict[tuple[str, bool], _StereoLayout] = {
    ("2015", False): _StereoLayout(
        "image_0", "image_1", "calib_cam_to_cam", "P_rect_00", "P_rect_01", None, None, False
    ),
    ("2015", True): _StereoLayout(
        "image_2", "image_3", "calib_cam_to_cam", "P_rect_02", "P_rect_03", "disp_noc_0", "disp_occ_0", True
    ),
    ("2012", False): _StereoLayout("image_0", "image_1", "calib", "P0", "P1", "disp_noc", "disp_occ", False),
    ("2012", True): _StereoLayout("colored_0", "colored_1", "calib", "P2", "P3", None, None, True),
}


class StereoScene:
    """One scene ``NNNNNN`` of KITTI stereo 2012/2015: its multiview frames in order, lazily loaded.

    Attributes:
        root: the split folder (``.../training`` or ``.../testing``).
        scene: scene number as in the file names, e.g. ``"000000"``.
        camera: the rectified pair's StereoCamera (from the scene's own calibration file).
        names: frame stems in order, e.g. ``["000000_00", ..., "000000_20"]``
            (only those present on disk).
        frame_numbers: ``MM`` of each frame.
        stamps: ``MM * FRAME_PERIOD`` seconds: the multiview frames were
            recorded at 10 Hz, and a partial scene (only ``_10``, ``_11``) keeps
            its true spacing. On a full scene this is ``index * FRAME_PERIOD``.
        left_dir, right_dir: image folders.
        gt_path: ground truth of the reference frame ``MM = 10`` (None when absent).
    """

    def __init__(self, root: Path, scene: str, names: list[str], layout: _StereoLayout, gt_dir: str | None) -> None:
        self.root = root
        self.scene = scene
        self.color = layout.color
        self.left_dir = root / layout.left
        self.right_dir = root / layout.right
        self.names = names
        missing = [n for n in names if not (self.right_dir / (n + _IMAGE_SUFFIX)).is_file()]
        if missing:
            raise DatasetError(f"right image {self.right_dir / (missing[0] + _IMAGE_SUFFIX)} is missing")
        self.frame_numbers = [int(n.rsplit("_", 1)[1]) for n in names]
        self.stamps = np.array(self.frame_numbers, dtype=np.float64) * FRAME_PERIOD
        calib_path = root / layout.calib_dir / f"{scene}.txt"
        entries = read_calib(calib_path)
        width, height = _image_size(self.left_dir / (names[0] + _IMAGE_SUFFIX))
        self.camera, _ = _stereo_pair(
            _projection(entries, layout.p_left, calib_path),
            _projection(entries, layout.p_right, calib_path),
            width,
            height,
            f"{calib_path} ({layout.p_left}, {layout.p_right})",
        )
        reference = f"{scene}_{REFERENCE_FRAME:02d}{_IMAGE_SUFFIX}"
        gt_path = None if gt_dir is None else root / gt_dir / reference
        self.gt_path = gt_path if gt_path is not None and gt_path.is_file() else None

    @property
    def reference_index(self) -> int | None:
        """Position of the reference frame ``MM = 10`` in :attr:`names`, or None when it is absent."""
        return self.frame_numbers.index(REFERENCE_FRAME) if REFERENCE_FRAME in self.frame_numbers else None

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> StereoFrame:
        """Load frame ``i`` of the scene; ``pose`` is None, ``gt_disparity`` set on frame ``MM = 10`` only.

        Raises:
            IndexError: ``i`` out of range.
            DatasetError: unreadable images, left/right or ground-truth sizes that disagree.
        """
        i = _normalise_index(i, len(self), f"scene {self.scene} of {self.root}")
        name = self.names[i]
        left, right = _load_pair(
            self.left_dir / (name + _IMAGE_SUFFIX), self.right_dir / (name + _IMAGE_SUFFIX), self.camera, self.color
        )
        gt = _load_gt(self.gt_path, self.camera) if self.frame_numbers[i] == REFERENCE_FRAME else None
        return StereoFrame(
            index=i, name=name, stamp=float(self.stamps[i]), left=left, right=right, pose=None, gt_disparity=gt
        )

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"StereoScene({str(self.root)!r}, scene={self.scene!r}, {len(self)} frames)"


class StereoDataset:
    """A split of KITTI stereo 2012 or 2015 (multiview layout): an ordered collection of scenes.

    Attributes:
        root: the split folder.
        benchmark: ``"2012"`` or ``"2015"`` (detected from ``calib/`` or ``calib_cam_to_cam/``).
        color: whether the colour pair is read.
        ground_truth: ``"noc"`` (non-occluded pixels) or ``"occ"`` (all pixels).
        scenes: scene numbers in order.
    """

    def __init__(self, root: Path, benchmark: str, layout: _StereoLayout, ground_truth: str) -> None:
        self.root = root
        self.benchmark = benchmark
        self.color = layout.color
        self.ground_truth = ground_truth
        self._layout = layout
        left_dir, right_dir = root / layout.left, root / layout.right
        for d in (left_dir, right_dir):
            if not d.is_dir():
                raise DatasetError(f"image folder {d} does not exist")
        left = _image_stems(left_dir)
        _check_pairs(left_dir, right_dir, left, _image_stems(right_dir))
        self._frames: dict[str, list[str]] = {}
        for stem in left:
            match = _MULTIVIEW_NAME.match(stem)
            if match is None:
                raise DatasetError(f"image {left_dir / (stem + _IMAGE_SUFFIX)} is not named NNNNNN_MM{_IMAGE_SUFFIX}")
            self._frames.setdefault(match.group(1), []).append(stem)
        for names in self._frames.values():
            names.sort(key=lambda n: int(n.rsplit("_", 1)[1]))
        self.scenes = sorted(self._frames, key=_frame_key)
        self._gt_dir = layout.gt_noc if ground_truth == "noc" else layout.gt_occ

    def scene(self, name: str | int) -> StereoScene:
        """Open scene ``name`` (``"000000"`` or ``0``).

        Raises:
            DatasetError: unknown scene, missing right image or malformed calibration.
        """
        key = f"{name:06d}" if isinstance(name, int) else name
        if key not in self._frames:
            raise DatasetError(f"scene {key!r} is not in {self.root / self._layout.left}")
        return StereoScene(self.root, key, self._frames[key], self._layout, self._gt_dir)

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, key: int | str) -> StereoScene:
        """The ``key``-th scene in order, or the scene named ``key`` (a string such as ``"000000"``)."""
        if isinstance(key, str):
            return self.scene(key)
        return self.scene(self.scenes[_normalise_index(key, len(self), f"dataset {self.root}")])

    def __iter__(self) -> Iterator[StereoScene]:
        for name in self.scenes:
            yield self.scene(name)

    def __repr__(self) -> str:
        pair = "colour" if self.color else "grey"
        return f"StereoDataset({str(self.root)!r}, KITTI {self.benchmark}, {pair}, {len(self)} scenes)"


def open_stereo_dataset(
    path: Path | str, *, split: str = "training", color: bool = False, ground_truth: str = "noc"
) -> StereoDataset:
    """Open a KITTI stereo 2012 or 2015 split (multiview layout).

    Args:
        path: the dataset root holding ``training/``/``testing/``, or a split folder itself.
        split: ``"training"`` or ``"testing"``; ignored when ``path`` is a split folder.
        color: read the colour pair (2015 ``image_2/3``, 2012 ``colored_0/1``)
            instead of the grey pair (``image_0/1``); the colour pair is also
            taken when the grey one is absent (KITTI 2015 ships colour only).
        ground_truth: ``"noc"`` (non-occluded pixels, ``disp_noc*``) or
            ``"occ"`` (all pixels, ``disp_occ*``).

    Raises:
        DatasetError: unknown ``ground_truth``, a path that is not a KITTI
            stereo split, or unequal left/right folders.
    """
    path = Path(path)
    if ground_truth not in ("noc", "occ"):
        raise DatasetError(f"ground_truth must be 'noc' or 'occ', got {ground_truth!r}")
    if not path.is_dir():
        raise DatasetError(f"dataset path {path} is not a folder")
    root = path / split if (path / split).is_dir() else path
    if (root / "calib_cam_to_cam").is_dir():
        benchmark = "2015"
    elif (root / "calib").is_dir():
        benchmark = "2012"
    else:
        raise DatasetError(
            f"{root} is not a KITTI stereo split: expected calib_cam_to_cam/ (2015) or calib/ (2012) in it"
            + ("" if root != path else f", or a split folder {path / split}")
        )
    if not color and not (root / _LAYOUTS[benchmark, False].left).is_dir():
        color = True
    return StereoDataset(root, benchmark, _LAYOUTS[benchmark, color], ground_truth)
