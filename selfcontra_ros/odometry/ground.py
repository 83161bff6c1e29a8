"""The road under a driving camera: a second measure of each step's length, from near pixels.

A stereo odometry's scale comes from its features' disparities. On a
highway most corners are far (1-3 px of disparity), so a bias of a tenth of
a pixel moves a step by several percent, and the step lengths of whole runs
of frames come out short together (docs/visual_odometry.md). The
road in front of the car is the one surface that is always near: 6-25 m on
a KITTI-like rig, 15-65 px of disparity. It gives the step's length
independently of the features:

1. **The plane** (:func:`fit_ground`). Semi-global matching on the image's
   lower part at half resolution; among the planes below the camera
   (normal within ``max_tilt_deg`` of straight down, height within
   ``height_range_m``) the one with the most pixels within half a pixel of
   disparity, by RANSAC; then refined by aligning the right image to the
   left one through the plane's disparity ``d(u, v) = fx b (m . ray)``
   (Gauss-Newton on ``m``, Cauchy weights: thousands of pixels pin it to a
   few hundredths of a pixel). Vehicles and verges are not on it and leave
   the fit.
2. **The step** (:func:`road_step`). A point ``X`` of the plane in the
   earlier frame is ``R X + t`` in the later one, so the earlier image's road
   pixels, moved by the candidate motion, must look the same in the later
   image (direct photometric alignment, Cauchy loss). Started from the
   feature odometry's motion, the length is searched along its direction
   (``+-search_pct``), then the translation and the rotation are refined
   together (Gauss-Newton, Cauchy weights): a pitch error shifts the road's
   image the way a forward step does, but the same for every row, whereas
   the step's shift grows with nearness, and on a turning camera (the
   orbit) the odometry's rotation error biased the length by +0.3 % when
   only the pitch was refined.

What it cannot do: a road hidden by a truck, a surface that is not planar
or not the ground (a drone's view, a room), a road without texture. Each
is reported (``None``, too few pixels, too few pixels that agree) rather
than measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera

__all__ = ["GroundParams", "GroundPlane", "RoadStep", "fit_ground", "road_costs", "road_step"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GroundParams:
    """How the road is found and aligned (the defaults were set by looking at a few synthetic highway, orbit
    and street sequences and KITTI 06, not by a sweep: docs/visual_odometry.md, fourteenth round).

    Attributes:
        top_margin: the region searched starts this share of the image
            height below the principal point (the horizon of a level camera).
        max_tilt_deg: largest angle between the plane's normal and the
            camera's down axis.
        height_range_m: the camera's height above the plane, metres (min, max).
        min_pixels: fewest pixels (at half resolution, both directions) on the
            plane, and fewest of them aligned in a step, per million image pixels.
        cauchy_grey: scale of the Cauchy loss on grey-level differences.
        search_pct: the step length is searched within this percentage of the odometry's.
        min_agreement: share of the step's pixels whose difference stays within
            two ``cauchy_grey`` at the solution; fewer: the road moved unlike
            the plane (hidden, not the ground).
    """

    top_margin: float = 0.07
    max_tilt_deg: float = 20.0
    height_range_m: tuple[float, float] = (0.5, 4.0)
    min_pixels: int = 4000
    cauchy_grey: float = 4.0
    search_pct: float = 8.0
    min_agreement: float = 0.5


@dataclass(frozen=True)
class GroundPlane:
    """The road in one frame's left camera: points ``X`` on it satisfy ``m . X = 1``.

    Attributes:
        m: (3,) the plane's normal over its distance from the camera, 1/metres.
        uv: (N, 2) left-image pixels on the plane (every other row and column; int16, as the stereo cache
            keeps it: up to 40 kB at KITTI size).
    """

    m: F64
    uv: NDArray[np.int16]

    @property
    def height_m(self) -> float:
        """The camera's distance from the plane, metres."""
        return float(1.0 / np.linalg.norm(self.m))

    def shifted(self, offset_px: float, camera: StereoCamera) -> GroundPlane:
        """The plane with every disparity ``offset_px`` larger (a rig's disparity offset undone)."""
        return GroundPlane(self.m + np.array([0.0, 0.0, offset_px / camera.focal_baseline]), self.uv)

    @property
    def nbytes(self) -> int:
        return int(self.m.nbytes + self.uv.nbytes)


@dataclass(frozen=True)
class RoadStep:
    """One step measured on the road.

    Attributes:
        t_cur_ref: (4, 4) the motion from the earlier to the later camera frame.
        length_m: its translation's length, metres.
        pixels: road pixels compared.
        agreement: share of them within two ``cauchy_grey`` at the solution.
    """

    t_cur_ref: F64
    length_m: float
    pixels: int
    agreement: float


def _rays(camera: StereoCamera, uv: NDArray[Any]) -> F64:
    return np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))])


def _sample(image: NDArray[Any], u: F64, v: F64) -> F64:
    """Bilinear samples of ``image`` at (u, v) (cv2.remap in rows of 1024: its maps are limited to 32767 rows)."""
    n = len(u)
    pad = (-n) % 1024
    mu = np.concatenate([u, np.zeros(pad)]).astype(np.float32).reshape(-1, 1024)
    mv = np.concatenate([v, np.zeros(pad)]).astype(np.float32).reshape(-1, 1024)
    return cv2.remap(image, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()[:n].astype(np.float64)


def _cauchy_step(jac: F64, residual: F64, scale: float) -> F64 | None:
    """One Gauss-Newton step of the Cauchy-weighted least squares (weights ``1 / (1 + (r / scale)^2)``,
    iteratively reweighted); None where the normal equations are not finite or nearly singular."""
    weight = 1.0 / (1.0 + (residual / scale) ** 2)
    normal = (jac * weight[:, None]).T @ jac
    if not np.isfinite(normal).all() or np.linalg.cond(normal) > 1e12:
        return None
    step: F64 = -np.linalg.solve(normal, (jac * weight[:, None]).T @ residual)
    return step


def _cauchy_cost(residual: F64, scale: float) -> float:
    """The mean Cauchy loss ``log(1 + (r / scale)^2)`` of the residuals: what the searches compare."""
    return float(np.mean(np.log1p((residual / scale) ** 2)))


def _min_pixels(params: GroundParams, camera: StereoCamera) -> int:
    return max(200, int(params.min_pixels * camera.width * camera.height / 1e6))


def fit_ground(
    left: NDArray[np.uint8], right: NDArray[np.uint8], camera: StereoCamera, params: GroundParams | None = None,
    seed: int = 0,
) -> GroundPlane | None:  # fmt: skip
    """The road plane of a rectified grey pair, or None where no plane below the camera holds enough pixels."""
    p = params or GroundParams()
    h, w = left.shape
    w -= w % 2  # whole pixel pairs: half-resolution pixel c covers full-resolution columns 2c and 2c + 1
    top = math.ceil(camera.cy + p.top_margin * h)
    top += (h - top) % 2
    if h - top < 16:
        return None
    # Semi-global matching at half resolution: a dense disparity for the plane's search, cheaply.
    small_l = cv2.resize(left[top:, :w], (w // 2, (h - top) // 2), interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(right[top:, :w], (w // 2, (h - top) // 2), interpolation=cv2.INTER_AREA)
    # The nearest road point in view (the bottom row) at the lowest height allowed, in half-resolution pixels.
    nearest = camera.focal_baseline * (h - camera.cy) / (camera.fy * p.height_range_m[0]) / 2.0
    reach = 16 * max(1, math.ceil(nearest / 16))
    reach = min(reach, 16 * max(1, (small_l.shape[1] // 3) // 16))
    sgbm = cv2.StereoSGBM.create(0, reach, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10,
                                 mode=cv2.StereoSGBM_MODE_SGBM_3WAY)  # fmt: skip
    d_small = sgbm.compute(small_l, small_r).astype(np.float64) / 16.0
    rows, cols = np.nonzero(d_small > 0.5)
    if rows.size < _min_pixels(p, camera):
        return None
    uv = np.column_stack([2.0 * cols + 0.5, top + 2.0 * rows + 0.5])
    d = 2.0 * d_small[rows, cols]
    a = _rays(camera, uv) * camera.focal_baseline  # d = a @ m
    m = _ransac_plane(a, d, p, np.random.default_rng(seed))
    if m is None:
        return None
    on = np.abs(a @ m - d) < 1.0
    if on.sum() < _min_pixels(p, camera):
        return None
    # Full-resolution pixels of the plane (every other row and column), refined by left-right alignment,
    # then chosen again within half a pixel of the refined plane (curbs, verges and wheels leave).
    uv_full = np.column_stack([2.0 * cols, top + 2.0 * rows])
    plane: F64 = np.linalg.lstsq(a[on], d[on], rcond=None)[0].astype(np.float64)
    for tolerance, blurs in ((1.0, (1.5, 0.0)), (0.5, (0.0,))):
        on = np.abs(a @ plane - d) < tolerance
        if on.sum() < _min_pixels(p, camera):
            return None
        start = np.linalg.lstsq(a[on], d[on], rcond=None)[0].astype(np.float64) if tolerance == 1.0 else plane
        refined = _align_left_right(left, right, camera, uv_full[on], start, p, blurs)
        if refined is None or not _plausible(refined, p):
            return None
        plane = refined
    chosen = np.abs(a @ plane - d) < 0.5
    if chosen.sum() < _min_pixels(p, camera):
        return None
    return GroundPlane(plane, uv_full[chosen].astype(np.int16))


def _plausible(m: F64, p: GroundParams) -> bool:
    height = 1.0 / float(np.linalg.norm(m))
    down = m[1] * height  # cosine between the normal and the camera's y (down) axis
    return bool(p.height_range_m[0] <= height <= p.height_range_m[1] and down >= math.cos(math.radians(p.max_tilt_deg)))


def _ransac_plane(a: F64, d: F64, p: GroundParams, rng: np.random.Generator, tries: int = 200) -> F64 | None:
    """The plausible plane (``d = a @ m``) with the most pixels within half a pixel; None when none is."""
    n = len(d)
    triples = rng.integers(0, n, size=(tries, 3))
    systems = a[triples]
    ok = np.abs(np.linalg.det(systems)) > 1e-12
    m = np.zeros((tries, 3))
    m[ok] = np.linalg.solve(systems[ok], d[triples[ok]][..., None])[..., 0]
    norm = np.maximum(np.linalg.norm(m, axis=1), 1e-12)
    height = 1.0 / norm
    ok &= (height >= p.height_range_m[0]) & (height <= p.height_range_m[1])
    ok &= m[:, 1] / norm >= math.cos(math.radians(p.max_tilt_deg))
    if not ok.any():
        return None
    sub = rng.choice(n, size=min(n, 2000), replace=False)
    support = (np.abs(a[sub] @ m[ok].T - d[sub, None]) < 0.5).sum(axis=0)
    return m[ok][int(np.argmax(support))]


def _align_left_right(
    left: NDArray[np.uint8], right: NDArray[np.uint8], camera: StereoCamera, uv: F64, m: F64, p: GroundParams,
    blurs: tuple[float, ...] = (1.5, 0.0), iterations: int = 10,
) -> F64 | None:  # fmt: skip
    """``m`` refined so that the right image, moved by the plane's disparity, matches the left one at ``uv``:
    on the images blurred by each of ``blurs`` in turn (Gaussian sigma, pixels; 0: as they are), a coarse
    one first, since it reaches further."""
    a = _rays(camera, uv) * camera.focal_baseline
    top = max(0, int(uv[:, 1].min()) - 8)  # only the rows the plane's pixels need
    local = uv - np.array([0.0, top])
    for blur in blurs:
        grey_l: NDArray[Any] = left[top:].astype(np.float32)
        grey_r: NDArray[Any] = right[top:].astype(np.float32)
        if blur > 0:
            grey_l = cv2.GaussianBlur(grey_l, (0, 0), blur)
            grey_r = cv2.GaussianBlur(grey_r, (0, 0), blur)
        m_new = _align_pass(grey_l, grey_r, local, a, m, p, iterations)
        if m_new is None:
            return None
        m = m_new
    return m


def _align_pass(
    grey_l: NDArray[Any], grey_r: NDArray[Any], uv: F64, a: F64, m: F64, p: GroundParams,
    iterations: int,
) -> F64 | None:  # fmt: skip
    grad_r = cv2.Sobel(grey_r, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    target = _sample(grey_l, uv[:, 0], uv[:, 1])
    for _ in range(iterations):
        u_right = uv[:, 0] - a @ m
        residual = _sample(grey_r, u_right, uv[:, 1]) - target
        jac = -_sample(grad_r, u_right, uv[:, 1])[:, None] * a
        step = _cauchy_step(jac, residual, p.cauchy_grey)
        if step is None:
            return None
        m = m + step
        if np.abs(a @ step).max() < 0.002:  # pixels of disparity
            break
    return m if np.all(np.isfinite(m)) else None


def _road_images(
    plane: GroundPlane, earlier: NDArray[np.uint8], later: NDArray[np.uint8], camera: StereoCamera
) -> tuple[int, NDArray[Any], F64, F64]:
    """What a step's alignment reads: the first image row read (the road's highest pixel less a tenth of
    the image, for the motion), the later image from there blurred, the road pixels' points on the plane
    (earlier frame) and the earlier image's blurred grey levels at them."""
    uv = plane.uv.astype(np.float64)
    top = max(0, int(uv[:, 1].min() - 0.1 * camera.height))
    smooth_e = cv2.GaussianBlur(earlier[top:].astype(np.float32), (5, 5), 0.7)
    smooth_l = cv2.GaussianBlur(later[top:].astype(np.float32), (5, 5), 0.7)
    rays = _rays(camera, uv)
    points = rays / (rays @ plane.m)[:, None]
    return top, smooth_l, points, _sample(smooth_e, uv[:, 0], uv[:, 1] - top)


def _project(camera: StereoCamera, top: int, y: F64) -> tuple[F64, F64, F64]:
    """Pixels (u, v - top) of the points ``y`` (later frame), and ``y``."""
    return camera.fx * y[:, 0] / y[:, 2] + camera.cx, camera.fy * y[:, 1] / y[:, 2] + camera.cy - top, y


def _in_view(camera: StereoCamera, top: int, u: F64, v: F64, y: F64) -> NDArray[np.bool_]:
    return (y[:, 2] > 0.5) & (u >= 1) & (u <= camera.width - 2) & (v >= 1) & (v <= camera.height - top - 2)


def road_costs(
    plane: GroundPlane,
    earlier: NDArray[np.uint8],
    later: NDArray[np.uint8],
    camera: StereoCamera,
    motions: list[F64],
    params: GroundParams | None = None,
) -> F64:
    """How well each motion (``T_cur_ref``, 4x4) aligns ``earlier``'s road with ``later``: the mean Cauchy
    loss over the road pixels every one of them keeps in view, so that the costs compare (inf for all
    where fewer than ``min_pixels`` stay)."""
    p = params or GroundParams()
    top, smooth_l, points, target = _road_images(plane, earlier, later, camera)
    projected = [_project(camera, top, points @ m[:3, :3].T + m[:3, 3]) for m in motions]
    keep = np.ones(len(points), dtype=bool)
    for u, v, y in projected:
        keep &= _in_view(camera, top, u, v, y)
    if keep.sum() < _min_pixels(p, camera):
        return np.full(len(motions), np.inf)
    return np.array([_cauchy_cost(_sample(smooth_l, u[keep], v[keep]) - target[keep], p.cauchy_grey)
                     for u, v, _ in projected])  # fmt: skip


def road_step(
    plane: GroundPlane,
    earlier: NDArray[np.uint8],
    later: NDArray[np.uint8],
    camera: StereoCamera,
    t_cur_ref: F64,
    params: GroundParams | None = None,
    iterations: int = 10,
    other_starts: tuple[F64 | float, ...] = (),
) -> RoadStep | None:
    """The motion from ``earlier`` (whose road is ``plane``) to ``later``, started at ``t_cur_ref``; None
    where the road does not give it (too few pixels stay in view or agree, a start without translation).

    ``other_starts`` are further starts for the translation: a vector (3,)
    (a velocity prediction) or a length along ``t_cur_ref``'s direction (the
    last step the road measured), metres. The length is searched around
    each along its own direction, and the best search decides.
    """
    p = params or GroundParams()
    start = float(np.linalg.norm(t_cur_ref[:3, 3]))
    if not start > 1e-6:
        return None
    starts = [t_cur_ref[:3, 3].copy()]
    for other in other_starts:
        vector = np.asarray(other, dtype=np.float64)
        vector = vector * t_cur_ref[:3, 3] / start if vector.ndim == 0 else vector.reshape(3)
        if (
            np.all(np.isfinite(vector))
            and np.linalg.norm(vector) > 1e-6
            and all(np.linalg.norm(vector - s) > p.search_pct / 200.0 * np.linalg.norm(s) for s in starts)
        ):
            starts.append(vector)
    if len(plane.uv) < _min_pixels(p, camera):
        return None
    top, smooth_l, points, target = _road_images(plane, earlier, later, camera)
    grad_u = cv2.Sobel(smooth_l, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    grad_v = cv2.Sobel(smooth_l, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    rotation = t_cur_ref[:3, :3]

    def project(rotated: F64, t: F64) -> tuple[F64, F64, F64]:
        return _project(camera, top, rotated + t)

    rotated_all = points @ rotation.T

    def cost(t: F64, rot: F64, target: F64) -> float:
        u, v, _ = project(rot, t)
        return _cauchy_cost(_sample(smooth_l, u, v) - target, p.cauchy_grey)

    # Pixels that stay in view (and in front) over every search: the same set for every candidate, so that
    # their costs compare.
    keep = np.ones(len(points), dtype=bool)
    for begin in starts:
        for factor in (1.0 - p.search_pct / 100.0, 1.0 + p.search_pct / 100.0):
            keep &= _in_view(camera, top, *project(rotated_all, factor * begin))
    if keep.sum() < _min_pixels(p, camera):
        return None
    rotated, target = rotated_all[keep], target[keep]
    found: tuple[float, F64] | None = None  # cost, translation
    factors = 1.0 + np.linspace(-p.search_pct, p.search_pct, 17) / 100.0
    for begin in starts:
        costs = np.array([cost(f * begin, rotated, target) for f in factors])
        best = int(np.argmin(costs))
        if best in (0, len(factors) - 1):
            continue  # the minimum is not inside this search
        if found is None or costs[best] < found[0]:
            found = (float(costs[best]), factors[best] * begin)
    if found is None:
        return None  # the road does not say
    t = found[1]
    length0 = float(np.linalg.norm(t))
    turn = np.eye(3)  # correction of the start's rotation
    for _ in range(iterations):
        base = rotated @ turn.T
        u, v, y = project(base, t)
        r = _sample(smooth_l, u, v) - target
        gu, gv = _sample(grad_u, u, v), _sample(grad_v, u, v)
        inv_z = 1.0 / y[:, 2]
        # d(u, v)/dY, then the residual's derivative along Y: image gradient times projection Jacobian.
        dy = np.column_stack([gu * camera.fx * inv_z, gv * camera.fy * inv_z,
                              -(gu * camera.fx * y[:, 0] + gv * camera.fy * y[:, 1]) * inv_z**2])  # fmt: skip
        # Y = (I + [w]x) turn R X + t: a small rotation w moves Y by w x (turn R X).
        d_rot = np.cross(base, dy)
        step = _cauchy_step(np.column_stack([d_rot, dy]), r, p.cauchy_grey)
        if step is None:
            return None
        w = step[:3]
        turn = cv2.Rodrigues(w)[0] @ turn
        t = t + step[-3:]
        if np.abs(w).max() < 1e-7 and np.abs(step[-3:]).max() < 1e-5 * length0:
            break
    u, v, _ = project(rotated @ turn.T, t)
    r = _sample(smooth_l, u, v) - target
    agreement = float(np.mean(np.abs(r) < 2.0 * p.cauchy_grey))
    length = float(np.linalg.norm(t))
    if not (np.isfinite(length) and abs(length / length0 - 1.0) <= 1.5 * p.search_pct / 100.0):
        return None
    if agreement < p.min_agreement:
        return None
    motion = np.eye(4)
    motion[:3, :3] = turn @ rotation
    motion[:3, 3] = t
    return RoadStep(motion, length, int(keep.sum()), agreement)
