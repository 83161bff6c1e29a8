"""Rectified stereo camera model: disparity, depth and 3D points.

Conventions (REP 103/105 optical frames): the left camera looks along +z, x
points right and y down, in metres. A pixel ``(u, v)`` with disparity ``d``
(pixels, ``u_right = u - d``) has depth ``z = fx * b / d``. Poses are 4x4
homogeneous matrices ``T_world_left`` that map points from the left camera
frame into the world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.errors import CalibrationError, PoseError

__all__ = [
    "StereoCamera",
    "invert_pose",
    "quaternion_from_rotation",
    "rotation_from_quaternion",
    "transform_points",
]

FloatArray = NDArray[np.floating]

# Relative tolerance when checking that two projection matrices share their
# intrinsics (a rectified pair).
_RECTIFIED_RTOL = 1e-6
# Largest vertical or forward offset between the two optical centres accepted
# as rectification residue, as a share of the baseline (KITTI colour: < 1 %).
_MAX_OFF_AXIS_RATIO = 0.02


@dataclass(frozen=True)
class StereoCamera:
    """A rectified stereo pair seen from its left camera.

    Attributes:
        fx: focal length along x, pixels.
        fy: focal length along y, pixels.
        cx: principal point x, pixels.
        cy: principal point y, pixels.
        baseline: distance between the optical centres, metres (> 0); the
            right camera sits at ``(+baseline, 0, 0)`` in the left frame.
        width: image width, pixels.
        height: image height, pixels.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "baseline"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise CalibrationError(f"StereoCamera.{name} must be finite and > 0, got {value!r}")
        for name in ("cx", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise CalibrationError(f"StereoCamera.{name} must be finite, got {getattr(self, name)!r}")
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"StereoCamera size must be positive, got {self.width}x{self.height}")

    @classmethod
    def from_projections(
        cls,
        p_left: ArrayLike,
        p_right: ArrayLike,
        width: int,
        height: int,
        *,
        source: str = "projection matrices",
    ) -> StereoCamera:
        """Build the camera from the rectified 3x4 projection matrices.

        ``P = K [I | t]`` for both cameras of a rectified pair; the baseline
        is ``t_left,x - t_right,x`` with ``t = K^-1 P[:, 3]``, which is
        ``(P_left[0, 3] - P_right[0, 3]) / fx`` when the cameras have no
        forward offset. The left matrix may carry a non-zero ``t_x`` (KITTI
        colour cameras 2 and 3 are offset from the reference camera 0); only
        the difference matters. Vertical or forward offsets up to 2 % of the
        baseline (rectification residue, a few millimetres on KITTI) are
        ignored.

        Raises:
            CalibrationError: naming the offending entry when the matrices
                are not 3x4, not finite, describe different intrinsics (not
                rectified), a vertical or forward offset, or a baseline <= 0.
        """
        pl = np.asarray(p_left, dtype=np.float64)
        pr = np.asarray(p_right, dtype=np.float64)
        for name, p in (("left P", pl), ("right P", pr)):
            if p.size != 12:
                raise CalibrationError(f"{source}: {name} must have 12 entries (3x4), got {p.size}")
            if not np.all(np.isfinite(p)):
                raise CalibrationError(f"{source}: {name} holds non-finite values")
        pl = pl.reshape(3, 4)
        pr = pr.reshape(3, 4)
        fx = pl[0, 0]
        if fx <= 0:
            raise CalibrationError(f"{source}: left P[0,0] (fx) must be > 0, got {fx}; is the camera calibrated?")
        scale = max(abs(fx), 1.0)
        for (r, c), label in {
            (0, 0): "fx",
            (1, 1): "fy",
            (0, 2): "cx",
            (1, 2): "cy",
            (0, 1): "skew",
        }.items():
            if abs(pl[r, c] - pr[r, c]) > _RECTIFIED_RTOL * scale:
                raise CalibrationError(
                    f"{source}: {label} differs between left P[{r},{c}]={pl[r, c]} and right "
                    f"P[{r},{c}]={pr[r, c]}; the pair is not rectified"
                )
        if abs(pl[0, 1]) > _RECTIFIED_RTOL * scale:
            raise CalibrationError(f"{source}: P[0,1] (skew) = {pl[0, 1]}, expected 0 for a rectified camera")
        if not np.allclose(pl[2, :3], [0.0, 0.0, 1.0]) or not np.allclose(pr[2, :3], [0.0, 0.0, 1.0]):
            raise CalibrationError(f"{source}: third row of P must be [0, 0, 1, *] for a rectified camera")
        # P = K [I | t]: the camera offsets t = K^-1 P[:, 3], metres. Real rectified
        # pairs (KITTI colour cameras 2/3) keep millimetre vertical/forward offsets
        # after rectification; their rows stay aligned, so small ones are ignored.
        k_inv = np.linalg.inv(pl[:, :3])
        difference = k_inv @ pl[:, 3] - k_inv @ pr[:, 3]
        baseline = float(difference[0])
        if baseline <= 0:
            raise CalibrationError(
                f"{source}: baseline from P[0,3] is {baseline} m; expected > 0 "
                "(right P[0,3] = -fx * baseline relative to the left camera)"
            )
        for axis, label in ((1, "vertical (P[1,3])"), (2, "forward (P[2,3])")):
            if abs(difference[axis]) > _MAX_OFF_AXIS_RATIO * baseline:
                raise CalibrationError(
                    f"{source}: {label} offset between left and right is {difference[axis]:.4f} m against a "
                    f"baseline of {baseline:.4f} m; only a horizontal baseline is supported"
                )
        return cls(
            fx=float(fx),
            fy=float(pl[1, 1]),
            cx=float(pl[0, 2]),
            cy=float(pl[1, 2]),
            baseline=float(baseline),
            width=int(width),
            height=int(height),
        )

    @property
    def K(self) -> NDArray[np.float64]:  # noqa: N802 - the usual name of the intrinsic matrix
        """3x3 intrinsic matrix of the left camera."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def focal_baseline(self) -> float:
        """``fx * baseline`` in pixel-metres: ``z = focal_baseline / d``."""
        return self.fx * self.baseline

    def projection_matrices(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Rectified 3x4 projection matrices ``(P_left, P_right)`` with ``P_left[0, 3] = 0``."""
        p_left = np.zeros((3, 4))
        p_left[:, :3] = self.K
        p_right = p_left.copy()
        p_right[0, 3] = -self.fx * self.baseline
        return p_left, p_right

    def disparity_to_depth(self, disparity: ArrayLike) -> FloatArray:
        """Depth ``z`` (metres) per pixel; NaN where the disparity is invalid (<= 0 or not finite)."""
        d = np.asarray(disparity, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.focal_baseline / d
        return np.where(np.isfinite(d) & (d > 0), z, np.nan)

    def depth_to_disparity(self, depth: ArrayLike) -> FloatArray:
        """Disparity (pixels) per pixel; NaN where the depth is invalid (<= 0 or not finite)."""
        z = np.asarray(depth, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = self.focal_baseline / z
        return np.where(np.isfinite(z) & (z > 0), d, np.nan)

    def backproject(self, disparity: ArrayLike) -> FloatArray:
        """3D points (HxWx3, left camera frame, metres) of a disparity map; NaN where invalid."""
        d = np.asarray(disparity, dtype=np.float64)
        if d.shape != (self.height, self.width):
            raise ValueError(f"disparity shape {d.shape} does not match the camera {self.height}x{self.width}")
        z = self.disparity_to_depth(d)
        u = np.arange(self.width, dtype=np.float64)[None, :]
        v = np.arange(self.height, dtype=np.float64)[:, None]
        x = (u - self.cx) * z / self.fx
        y = (v - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=-1)

    def project(self, points: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Project left-frame points (...x3, metres) to ``(u, v, d)`` in pixels.

        Points at ``z <= 0`` give NaN coordinates.
        """
        p = np.asarray(points, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = np.where(z > 0, 1.0 / z, np.nan)
        u = self.fx * p[..., 0] * inv_z + self.cx
        v = self.fy * p[..., 1] * inv_z + self.cy
        d = self.focal_baseline * inv_z
        return u, v, d


def invert_pose(pose: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid 4x4 transform, using ``R^T`` rather than a general inverse."""
    t = np.asarray(pose, dtype=np.float64)
    inv = np.eye(4)
    inv[:3, :3] = t[:3, :3].T
    inv[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return inv


def transform_points(pose: ArrayLike, points: ArrayLike) -> FloatArray:
    """Apply a 4x4 rigid transform to points of shape (..., 3)."""
    t = np.asarray(pose, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    return p @ t[:3, :3].T + t[:3, 3]


def quaternion_from_rotation(rotation: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion ``(x, y, z, w)`` of a 3x3 rotation matrix, with ``w >= 0``.

    Shepperd's method: the quaternion component of largest magnitude is
    computed from the diagonal (so its square root is never of a small,
    cancellation-prone number) and the other three from off-diagonal sums and
    differences divided by it. The result is normalised, so a matrix that is
    slightly off orthonormal (text poses with 6-9 digits) gives the nearest
    unit quaternion.

    Raises:
        PoseError: the input is not a finite 3x3 matrix with determinant near +1.
    """
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise PoseError(f"rotation must be a finite 3x3 matrix, got shape {r.shape}")
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > 1e-3:
        raise PoseError(f"rotation matrix has determinant {det:.6f}; expected +1 (a proper rotation)")
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    # 4 q_i^2 - 1 for i = w, x, y, z; the largest gives the best-conditioned square root.
    candidates = (trace, r[0, 0] - r[1, 1] - r[2, 2], r[1, 1] - r[0, 0] - r[2, 2], r[2, 2] - r[0, 0] - r[1, 1])
    largest = int(np.argmax(candidates))
    s = 2.0 * math.sqrt(max(1.0 + candidates[largest], 0.0))  # 4 * |q_largest|
    if largest == 0:
        q = (r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], s * s / 4.0)
    elif largest == 1:
        q = (s * s / 4.0, r[0, 1] + r[1, 0], r[0, 2] + r[2, 0], r[2, 1] - r[1, 2])
    elif largest == 2:
        q = (r[0, 1] + r[1, 0], s * s / 4.0, r[1, 2] + r[2, 1], r[0, 2] - r[2, 0])
    else:
        q = (r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], s * s / 4.0, r[1, 0] - r[0, 1])
    quat = np.asarray(q, dtype=np.float64) / s
    quat /= np.linalg.norm(quat)
    return -quat if quat[3] < 0 else quat


def rotation_from_quaternion(quaternion: ArrayLike) -> NDArray[np.float64]:
    """3x3 rotation matrix of a quaternion ``(x, y, z, w)`` (normalised first).

    Raises:
        PoseError: the input is not 4 finite numbers of non-zero norm.
    """
    q = np.asarray(quaternion, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(q)) if q.size == 4 else 0.0
    if q.size != 4 or not np.all(np.isfinite(q)) or norm < 1e-12:
        raise PoseError(f"quaternion must be 4 finite numbers (x, y, z, w) of non-zero norm, got {q!r}")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
