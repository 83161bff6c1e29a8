"""Synthetic rectified stereo sequences with exact ground truth: the package's own test bed.

A scene is a list of analytic primitives (see :mod:`._raycast`) with solid
procedural textures (functions of the 3D point, so every view agrees) and a
camera trajectory. Rendering a frame ray-casts the left and the right camera
and returns grey images, the left depth and disparity and the pose.

Three scenes:

- ``street``: a car drives along a street (about 1 m per frame, 10 Hz) with a
  gentle S-bend part of the way; road with lane markings, raised sidewalks
  with kerbs, facades with repetitive windows and plain walls, parked cars
  (whose near sides come closer than 3 m, i.e. beyond 128 px of disparity),
  thin poles and a textureless sky.
- ``orbit``: a drone circles a few boxes, cylinders and a sphere on textured
  ground, a few degrees per frame, looking slightly down at them.
- ``room``: a MAV flies a loop inside a furnished room (the on-board use
  case): large near-textureless walls and ceiling, a window onto a bright,
  overexposed outside, a floor of repetitive tiles, a table and chairs on
  thin legs, shelves with clutter, and parts of the furniture nearer than the
  disparity range at times. The camera yaws, pitches and rolls as it flies
  (about 0.1 m per frame), and its baseline is a MAV's (0.12-0.2 m, drawn per
  seed), not KITTI's.
- ``highway``: a long straight motorway, three lanes each way, driven at
  25-35 m/s (2.5-3.5 m per frame at 10 Hz, speeding up); dashed lane lines,
  guard rails on posts beside the hard shoulder and in the median, sparse
  far structure (trees, wooded hills, a few distant buildings), and traffic:
  trucks being overtaken, cars overtaking, cars ahead at about the camera's
  own speed and oncoming cars. Vehicles are the only primitives that move
  (see :meth:`SyntheticScene.primitives_at`); both cameras of a frame see
  them at the same instant, and their texture moves with them.

World coordinates of the written poses are those of the left camera at frame
0 (KITTI odometry convention); inside a scene, primitives live in a scene
frame with y pointing down and the ground at ``y = ground``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.datasets import SCENES
from selfcontra_ros.datasets._raycast import (
    Box,
    Cylinder,
    GroundPlane,
    Primitive,
    Sphere,
    ValueNoise,
    cast,
    pulse,
    surface_normals,
)
from selfcontra_ros.errors import DatasetError
from selfcontra_ros.geometry import StereoCamera, invert_pose

__all__ = [
    "SCENES",
    "SyntheticFrame",
    "SyntheticScene",
    "kitti_like_camera",
    "make_scene",
    "render_frame",
    "write_sequence",
]

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

FRAME_RATE_HZ = 10.0

# KITTI odometry grey camera 0/1 of sequence 00 at 1226x370.
_KITTI_SIZE = (1226, 370)
_KITTI_FX = 707.0912
_KITTI_CX = 601.8873
_KITTI_CY = 183.1104
_KITTI_BASELINE = 0.5372

# Material codes: which texture function colours a primitive.
_ROAD, _PAVING, _FACADE, _CAR, _POLE, _OBJECT, _GRASS, _TILES, _PLASTER, _OUTSIDE, _WOOD = range(11)
_MOTORWAY, _RAIL, _FOLIAGE = range(11, 14)
_N_PARAMS = 8

# Direction towards the light (y down: from above, front left); Lambertian plus ambient.
_LIGHT = np.array([-0.45, -1.0, -0.35]) / np.linalg.norm([-0.45, -1.0, -0.35])
_AMBIENT = 0.5
# Grey levels: Gaussian sensor noise and the sky's brightness.
_NOISE_SIGMA = 1.5
_SKY = 0.80
# Brightness of the outside through the room's window relative to white (see SyntheticScene.render_view).
_OUTSIDE_GAIN = 1.25


def kitti_like_camera(
    width: int = _KITTI_SIZE[0], height: int = _KITTI_SIZE[1], *, baseline: float = _KITTI_BASELINE
) -> StereoCamera:
    """KITTI odometry camera 0/1 intrinsics scaled to ``width`` x ``height``.

    At 1226x370 this is KITTI's ``fx = fy = 707.0912``, ``(cx, cy) = (601.8873,
    183.1104)`` and baseline 0.5372 m. Other sizes scale the focal length and
    ``cx`` with the width (the horizontal field of view stays KITTI's) and
    ``cy`` with the height, so the horizon stays at the same relative row.
    ``baseline`` (metres) replaces KITTI's, e.g. for a MAV's camera.
    """
    if width < 16 or height < 16:
        raise DatasetError(f"synthetic image size must be at least 16x16, got {width}x{height}")
    sx = width / _KITTI_SIZE[0]
    sy = height / _KITTI_SIZE[1]
    return StereoCamera(
        fx=_KITTI_FX * sx,
        fy=_KITTI_FX * sx,
        cx=_KITTI_CX * sx,
        cy=_KITTI_CY * sy,
        baseline=float(baseline),
        width=int(width),
        height=int(height),
    )


@dataclass(frozen=True)
class SyntheticFrame:
    """One rendered stereo frame with its ground truth.

    Attributes:
        index: frame number (0-based).
        stamp: seconds, ``index / 10 Hz``.
        left: HxW uint8 grey left image.
        right: HxW uint8 grey right image.
        depth: HxW float64 left depth ``z`` in metres; inf where the ray sees sky.
        disparity: HxW float32 left disparity ``fx * b / z`` in pixels; NaN where no ground truth.
        pose: 4x4 float64 ``T_world_left``, world = left camera at frame 0.
        camera: the rectified stereo camera.
        moving: HxW bool, left pixels that see a moving primitive (a vehicle
            of the highway); None in scenes where nothing moves.
    """

    index: int
    stamp: float
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    depth: F64
    disparity: F32
    pose: F64
    camera: StereoCamera
    moving: NDArray[np.bool_] | None = None


def _rotation(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> F64:
    """Camera-to-scene rotation: yaw about y (down), then pitch about x, then roll about z (radians)."""
    cy_, sy_ = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    r_yaw = np.array([[cy_, 0.0, sy_], [0.0, 1.0, 0.0], [-sy_, 0.0, cy_]])
    r_pitch = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    r_roll = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return r_yaw @ r_pitch @ r_roll


def _pose(rotation: F64, position: F64) -> F64:
    """4x4 homogeneous transform from a rotation and a translation."""
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = position
    return t


# --------------------------------------------------------------------------- textures
# Each texture maps hit points p (3, N, scene frame, metres), unit normals
# n (3, N), pixel footprints fp (N, metres per pixel) and per-primitive
# parameters prm (_N_PARAMS, N) to an albedo in [0, 1]. Rows, not columns,
# hold the coordinates so numpy's loops run over long contiguous arrays.

_Texture = Callable[[F64, F64, F64, F64, ValueNoise], F64]


def _line(x: F64, centre: F64 | float, width: float, fp: F64) -> F64:
    """Box-filtered indicator of the band ``|x - centre| < width / 2`` (metres)."""
    return pulse(x - centre + 0.5 * width, 1e4, width * 1e-4, fp)


def _tex_road(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Asphalt with lane markings between the kerbs; a meadow beyond the sidewalks.

    params: ground y, centre-line x, right parking-line x, left parking-line x, outer x right, left.
    """
    x, z = p[0], p[2]
    albedo = 0.30 + 0.2 * noise.fbm(p, fp, 0.25, 8, gain=0.85)
    dash = _line(x, prm[1], 0.15, fp) * pulse(z, 9.0, 1.0 / 3.0, fp)
    marking = np.clip(dash + _line(x, prm[2], 0.12, fp) + _line(x, prm[3], 0.12, fp), 0.0, 1.0)
    albedo += marking * (0.78 - albedo)
    outside = (x > prm[4]) | (x < prm[5])
    if outside.any():
        albedo[outside] = _tex_grass(p[:, outside], n[:, outside], fp[outside], prm[:, outside], noise)
    return albedo.astype(np.float64)


def _tex_paving(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Paving slabs with darker joints on top; plain kerb stone on the sides."""
    albedo = 0.52 + 0.14 * noise.fbm(p, fp, 0.5, 6, gain=0.85)
    joints = np.clip(2.0 - pulse(p[0], 0.6, 0.93, fp) - pulse(p[2], 0.6, 0.93, fp), 0.0, 1.0)
    top = n[1] < -0.5
    return np.where(top, albedo * (1.0 - 0.35 * joints), 0.55 + 0.5 * (albedo - 0.52))


def _tex_facade(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """A facade: wall with a grid of windows above the ground floor, or a plain (textureless) wall.

    params: ground y, wall albedo, wall noise amplitude, window period horizontal, storey height,
    window duty horizontal, window duty vertical, window albedo (< 0: plain wall).
    """
    ground, wall, amp, period_u, storey, duty_u, duty_v, glass = prm
    # Horizontal coordinate along the face; the sign depends on the face, which only shifts the pattern.
    u = p[0] * -n[2] + p[2] * n[0]
    height = ground - p[1]
    albedo = wall * (1.0 + amp * noise.fbm(p, fp, 0.4, 6, gain=0.85))
    window = pulse(u, period_u, duty_u, fp) * pulse(height - 3.8, storey, duty_v, fp) * (height > 3.8) * (glass >= 0)
    glazed = window > 0
    if glazed.any():
        pane = glass[glazed] * (1.0 + 0.3 * noise.fbm(p[:, glazed] * 0.5, fp[glazed] * 0.5, 0.5, 3))
        albedo[glazed] += window[glazed] * (pane - albedo[glazed])
    # A plinth along the ground floor: a darker band.
    albedo -= (height < 0.8) * 0.25 * wall
    return np.clip(albedo, 0.0, 1.0)


def _tex_car(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Car body (near uniform paint) or cabin (dark glass with faint reflections). params: albedo, cabin flag."""
    glass = (prm[1] > 0) & (n[1] > -0.5)
    paint = prm[0] * (1.0 + 0.03 * noise.fbm(p, fp, 1.0, 4))
    return np.where(glass, 0.13 + 0.1 * (paint - prm[0]) / np.maximum(prm[0], 0.05), paint)


def _tex_pole(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Painted metal pole with a faint grain. params: albedo."""
    return prm[0] * (1.0 + 0.05 * noise.fbm(p, fp, 4.0, 3))


def _tex_object(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Orbit-scene objects: noise, horizontal stripes or a 3D checker.

    params: albedo, noise amplitude, noise frequency (1/m), pattern (0 noise, 1 stripes, 2 checker), period (m).
    """
    albedo, amp, freq, pattern, period = prm[:5]
    base = albedo * (1.0 + amp * noise.fbm(p * freq, fp * freq, 1.0, 5, gain=0.8))
    stripes = pulse(p[1], period, 0.5, fp)
    checker = 0.5 + 4.0 * np.prod(np.stack([pulse(p[k], period, 0.5, fp) - 0.5 for k in range(3)]), axis=0)
    mod = np.where(pattern == 1, stripes, np.where(pattern == 2, checker, 0.5))
    return np.clip(base * (0.6 + 0.8 * mod), 0.0, 1.0)


def _tex_grass(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Meadow: noise from large patches down to fine grain."""
    return (0.40 + 0.2 * noise.fbm(p, fp, 0.25, 9, gain=0.85)).astype(np.float64)


def _tex_tiles(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Square floor tiles, nearly alike (a repetitive pattern), with dark grout. params: tile size (m), albedo."""
    size, albedo = prm[0], prm[1]
    # One low-amplitude offset per tile: neighbours differ a little, so matching along a row stays ambiguous.
    cell = np.stack([np.floor(p[0] / size), np.zeros_like(p[0]), np.floor(p[2] / size)]) * 3.17
    per_tile = 0.04 * noise.fbm(cell, np.zeros_like(fp), 1.0, 1)
    grain = 0.03 * noise.fbm(p, fp, 6.0, 4, gain=0.7)
    grout = np.clip(2.0 - pulse(p[0], size, 0.96, fp) - pulse(p[2], size, 0.96, fp), 0.0, 1.0)
    return np.clip((albedo + per_tile + grain) * (1.0 - 0.55 * grout), 0.0, 1.0)


def _tex_plaster(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Painted plaster: an almost uniform albedo (walls, ceiling). params: albedo, noise amplitude."""
    return np.clip(prm[0] * (1.0 + prm[1] * noise.fbm(p, fp, 0.7, 5, gain=0.8)), 0.0, 1.0)


def _tex_outside(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """The view out of the window: bright, low in contrast, mostly clipped to white by the exposure. params: albedo."""
    return np.clip(prm[0] * (1.0 + 0.12 * noise.fbm(p, fp, 0.2, 5, gain=0.7)), 0.0, 1.0)


def _tex_wood(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Wood: grain stretched along one horizontal axis. params: albedo, grain amplitude, grain axis (0 = x, 1 = z)."""
    albedo, amp, axis = prm[0], prm[1], prm[2]
    along_x = axis < 0.5
    stretched = np.stack(
        [np.where(along_x, p[0] * 0.1, p[0] * 3.0), p[1] * 3.0, np.where(along_x, p[2] * 3.0, p[2] * 0.1)]
    )
    return np.clip(albedo * (1.0 + amp * noise.fbm(stretched, fp * 3.0, 2.0, 5, gain=0.75)), 0.0, 1.0)


# Motorway layout across the road (scene x, metres; the camera's lane is centred on x = 0, y down).
_MW_LANE = 3.75
_MW_EDGE_RIGHT = 1.5 * _MW_LANE  # solid line between the right lane and the hard shoulder
_MW_EDGE_LEFT = -1.5 * _MW_LANE  # solid line beside the median
_MW_SHOULDER = 3.0
_MW_MEDIAN = 3.0  # between the two carriageways' inner edge lines
_MW_ONCOMING = _MW_EDGE_LEFT - _MW_MEDIAN  # inner edge line of the oncoming carriageway
_MW_DASH = (18.0, 6.0 / 18.0)  # lane-line period (m) and duty: 6 m lines, 12 m gaps


def _tex_motorway(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Motorway ground: asphalt with dashed lane lines and solid edge lines, a grass median and verges.

    Worn asphalt and mown verges have little contrast (unlike the street's), so
    most of the texture a camera finds on a motorway is far away.
    """
    x, z = p[0], p[2]
    albedo = 0.3 + 0.1 * noise.fbm(p, fp, 1.0, 8, gain=0.75)
    dash = pulse(z, _MW_DASH[0], _MW_DASH[1], fp)
    lines = np.zeros_like(x)
    for centre in (-0.5 * _MW_LANE, 0.5 * _MW_LANE, _MW_ONCOMING - _MW_LANE, _MW_ONCOMING - 2 * _MW_LANE):
        lines += _line(x, centre, 0.15, fp) * dash
    for centre in (_MW_EDGE_RIGHT, _MW_EDGE_LEFT, _MW_ONCOMING, _MW_ONCOMING - 3 * _MW_LANE):
        lines += _line(x, centre, 0.25, fp)
    albedo += np.clip(lines, 0.0, 1.0) * (0.8 - albedo)
    far_right = _MW_EDGE_RIGHT + _MW_SHOULDER
    far_left = _MW_ONCOMING - 3 * _MW_LANE - _MW_SHOULDER
    grass = (x > far_right) | (x < far_left) | ((x < _MW_EDGE_LEFT - 0.6) & (x > _MW_ONCOMING + 0.6))
    if grass.any():
        albedo[grass] = 0.42 + 0.08 * noise.fbm(p[:, grass], fp[grass], 0.15, 8, gain=0.75)
    return albedo.astype(np.float64)


def _tex_rail(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Galvanised guard rail or post: light metal, two horizontal grooves, weathering. params: albedo."""
    base = prm[0] * (1.0 + 0.12 * noise.fbm(p, fp, 0.8, 6, gain=0.8))
    grooves = pulse(p[1], 0.1, 0.3, fp)
    return np.clip(base * (1.0 - 0.3 * grooves), 0.0, 1.0)


def _tex_foliage(p: F64, n: F64, fp: F64, prm: F64, noise: ValueNoise) -> F64:
    """Tree crowns and wooded hills: dark, strongly varying noise. params: albedo."""
    return np.clip(prm[0] * (1.0 + 0.5 * noise.fbm(p, fp, 0.6, 9, gain=0.85)), 0.0, 1.0)


_TEXTURES: dict[int, _Texture] = {
    _ROAD: _tex_road,
    _PAVING: _tex_paving,
    _FACADE: _tex_facade,
    _CAR: _tex_car,
    _POLE: _tex_pole,
    _OBJECT: _tex_object,
    _GRASS: _tex_grass,
    _TILES: _tex_tiles,
    _PLASTER: _tex_plaster,
    _OUTSIDE: _tex_outside,
    _WOOD: _tex_wood,
    _MOTORWAY: _tex_motorway,
    _RAIL: _tex_rail,
    _FOLIAGE: _tex_foliage,
}


# --------------------------------------------------------------------------- scenes


class SyntheticScene:
    """A scene of primitives and a camera trajectory; renders exact stereo ground truth.

    Args:
        name: scene name (one of :data:`SCENES`).
        seed: the seed it was built from (recorded; noise streams derive from it).
        camera: the rectified stereo camera.
        primitives: the scene's primitives, scene frame (y down), as at frame 0.
        trajectory: maps frame indices (K,) to K 4x4 ``T_scene_left`` poses.
        noise: solid noise of the textures.
        motion: for a scene with moving primitives (boxes only), maps a frame
            index to the (len(primitives), 3) translation of every primitive
            since frame 0, metres (zero rows for static ones); None: all static.
    """

    def __init__(
        self,
        name: str,
        seed: int,
        camera: StereoCamera,
        primitives: list[Primitive],
        trajectory: Callable[[NDArray[np.int64]], F64],
        noise: ValueNoise,
        motion: Callable[[int], F64] | None = None,
    ) -> None:
        self.name = name
        self.seed = seed
        self.camera = camera
        self.primitives = primitives
        self._trajectory = trajectory
        self._noise = noise
        self._materials = np.array([p.material for p in primitives], dtype=np.int32)
        params = np.zeros((len(primitives), _N_PARAMS))
        for i, prim in enumerate(primitives):
            params[i, : len(prim.params)] = prim.params
        self._params = params
        self._origin_inv = invert_pose(trajectory(np.zeros(1, dtype=np.int64))[0])
        self._motion = motion
        if motion is not None:
            moved = np.any(motion(0) != 0.0, axis=1) | np.any(motion(1) != 0.0, axis=1)
            self._movers = np.flatnonzero(moved)
            if not all(isinstance(primitives[i], Box) for i in self._movers):
                raise DatasetError(f"scene {name!r}: only boxes can move")

    def _offsets(self, index: int) -> F64 | None:
        """(len(primitives), 3) translations of the primitives at frame ``index``, or None when nothing moves."""
        if self._motion is None:
            return None
        offsets = np.asarray(self._motion(int(index)), dtype=np.float64)
        if offsets.shape != (len(self.primitives), 3):
            raise DatasetError(
                f"scene {self.name!r}: motion gives {offsets.shape}, expected ({len(self.primitives)}, 3)"
            )
        return offsets

    def primitives_at(self, index: int) -> list[Primitive]:
        """The primitives as they stand at frame ``index`` (the moving ones translated; the list itself if static)."""
        offsets = self._offsets(index)
        if offsets is None:
            return self.primitives
        prims = list(self.primitives)
        for i in self._movers:
            box = prims[i]
            assert isinstance(box, Box)
            x, y, z = (float(c) for c in np.asarray(box.center) + offsets[i])
            prims[i] = replace(box, center=(x, y, z))
        return prims

    @property
    def moving_primitives(self) -> NDArray[np.int64]:
        """Indices (into :attr:`primitives`) of the primitives that move; empty in a static scene."""
        return self._movers if self._motion is not None else np.zeros(0, dtype=np.int64)

    def scene_pose(self, index: int) -> F64:
        """4x4 ``T_scene_left`` of frame ``index`` (scene frame, y down)."""
        if index < 0:
            raise DatasetError(f"frame index must be >= 0, got {index}")
        return self._trajectory(np.array([index], dtype=np.int64))[0]

    def pose(self, index: int) -> F64:
        """4x4 ``T_world_left`` of frame ``index``, world = left camera at frame 0."""
        return self._origin_inv @ self.scene_pose(index)

    def poses(self, frames: int) -> F64:
        """(frames, 4, 4) ``T_world_left`` of frames ``0 .. frames-1``."""
        return self._origin_inv @ self._trajectory(np.arange(frames, dtype=np.int64))

    def render_view(
        self, pose: F64, rng: np.random.Generator | None, *, index: int = 0
    ) -> tuple[NDArray[np.uint8], F64]:
        """Grey image and depth (metres, inf for sky) of a camera at ``pose`` (4x4 ``T_scene_camera``).

        ``rng`` draws the Gaussian sensor noise; None renders noise-free.
        Moving primitives stand where they are at frame ``index``.
        """
        image, depth, _ = self._render_view(pose, rng, index)
        return image, depth

    def _render_view(
        self, pose: F64, rng: np.random.Generator | None, index: int
    ) -> tuple[NDArray[np.uint8], F64, NDArray[np.int32]]:
        """:meth:`render_view` plus the primitive index each pixel sees (-1: sky)."""
        cam = self.camera
        offsets = self._offsets(index)
        primitives = self.primitives_at(index)
        rays, hits = cast(primitives, cam, pose)
        prim = hits.prim.ravel()
        idx = np.flatnonzero(prim >= 0)
        prim = prim[idx]
        t = hits.t.ravel()[idx]
        d = rays.dirs.reshape(3, -1).take(idx, axis=1)
        p = rays.origin[:, None] + t * d
        n = surface_normals(primitives, p, prim, hits.face.ravel()[idx])
        if offsets is not None:
            # A moving primitive's texture moves with it: texture its points where they were at frame 0.
            p = p - offsets.T.take(prim, axis=1)
        d_norm = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        cos_inc = np.abs(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / d_norm
        # Metres per pixel on the surface: range / focal length, stretched at grazing angles. The stretch is
        # only along one direction; the square root is a compromise between blurring across it and aliasing.
        footprint = t * d_norm / cam.fx / np.sqrt(np.maximum(cos_inc, 0.05))
        # Texture the hits in order of footprint, so fine noise octaves run over prefixes (see ValueNoise.fbm).
        order = np.argsort(footprint)
        idx, prim, footprint = idx.take(order), prim.take(order), footprint.take(order)
        p, n = p.take(order, axis=1), n.take(order, axis=1)
        albedo = np.empty(len(idx))
        materials = self._materials[prim]
        params = self._params.T
        for material in np.unique(materials):
            sel = np.flatnonzero(materials == material)
            albedo[sel] = _TEXTURES[int(material)](
                p.take(sel, axis=1), n.take(sel, axis=1), footprint[sel], params.take(prim[sel], axis=1), self._noise
            )
        shade = _AMBIENT + (1.0 - _AMBIENT) * np.maximum(_LIGHT @ n, 0.0)
        # The outside seen through a window is lit by daylight, not by the room's light: unshaded, and brighter
        # than white, so the exposure clips it.
        shade[materials == _OUTSIDE] = _OUTSIDE_GAIN
        # The sky is textureless: a smooth brightening towards the zenith, a function of the ray direction only.
        up = -rays.dirs[1] / np.sqrt(rays.dirs[0] ** 2 + rays.dirs[1] ** 2 + rays.dirs[2] ** 2)
        grey = (255.0 * (_SKY + 0.08 * np.clip(up, 0.0, 1.0))).ravel()
        grey[idx] = 255.0 * np.clip(albedo, 0.0, 1.0) * shade  # the final clip below saturates the outside
        if rng is not None:
            grey = grey + rng.normal(0.0, _NOISE_SIGMA, grey.shape)
        image = np.clip(np.rint(grey), 0, 255).astype(np.uint8).reshape(cam.height, cam.width)
        return image, hits.t, hits.prim

    def render(self, index: int, *, noise: bool = True) -> SyntheticFrame:
        """Render frame ``index``: both images, left depth and disparity, pose.

        The sensor noise is deterministic per (scene seed, frame, camera).
        """
        cam = self.camera
        left_pose = self.scene_pose(index)
        right_pose = left_pose @ _pose(np.eye(3), np.array([cam.baseline, 0.0, 0.0]))
        rng_l = np.random.default_rng([self.seed, index, 0]) if noise else None
        rng_r = np.random.default_rng([self.seed, index, 1]) if noise else None
        left, depth, seen = self._render_view(left_pose, rng_l, index)
        right, _, _ = self._render_view(right_pose, rng_r, index)
        disparity = cam.depth_to_disparity(depth).astype(np.float32)
        moving = np.isin(seen, self._movers) if self._motion is not None else None
        return SyntheticFrame(
            index=index,
            stamp=index / FRAME_RATE_HZ,
            left=left,
            right=right,
            depth=depth,
            disparity=disparity,
            pose=self._origin_inv @ left_pose,
            camera=cam,
            moving=moving,
        )


def render_frame(scene: SyntheticScene, index: int) -> SyntheticFrame:
    """Render frame ``index`` of ``scene`` (see :meth:`SyntheticScene.render`)."""
    return scene.render(index)


def _street(rng: np.random.Generator, frames: int) -> tuple[list[Primitive], Callable[[NDArray[np.int64]], F64]]:
    """Primitives and trajectory of the street scene, long enough for ``frames`` frames at about 1 m each."""
    ground = 1.65  # camera height above the road, metres (KITTI)
    lane = 3.5
    centre_x = -lane / 2  # the car drives in the right lane centred on x = 0
    park_r, park_l = lane / 2, centre_x - lane
    park_w = 2.3
    kerb_r, kerb_l = park_r + park_w, park_l - park_w
    walk_w, kerb_h = 3.0, 0.15
    z_start, z_end = -40.0, 1.15 * frames + 160.0
    zc, zh = 0.5 * (z_start + z_end), 0.5 * (z_end - z_start)

    prims: list[Primitive] = [
        GroundPlane(ground, _ROAD, (ground, centre_x, park_r, park_l, kerb_r + walk_w, kerb_l - walk_w)),
        Box((kerb_r + walk_w / 2, ground - kerb_h / 2, zc), (walk_w / 2, kerb_h / 2, zh), _PAVING),
        Box((kerb_l - walk_w / 2, ground - kerb_h / 2, zc), (walk_w / 2, kerb_h / 2, zh), _PAVING),
    ]
    for side in (1.0, -1.0):
        face = kerb_r + walk_w if side > 0 else kerb_l - walk_w
        # Facades.
        z = z_start
        while z < z_end:
            if rng.random() < 0.15:
                z += rng.uniform(4.0, 12.0)  # a gap between buildings
            width = rng.uniform(8.0, 26.0)
            setback = rng.uniform(0.0, 2.5) if rng.random() < 0.6 else 0.0
            height = rng.uniform(7.0, 22.0)
            depth = 12.0
            x = face + side * (setback + depth / 2)
            plain = rng.random() < 0.3
            params = (
                ground,
                rng.uniform(0.45, 0.8),
                rng.uniform(0.005, 0.02) if plain else rng.uniform(0.15, 0.35),
                rng.uniform(1.6, 3.2),
                rng.uniform(2.8, 3.4),
                rng.uniform(0.35, 0.6),
                rng.uniform(0.4, 0.6),
                -1.0 if plain else rng.uniform(0.1, 0.3),
            )
            prims.append(
                Box((x, ground - height / 2, z + width / 2), (depth / 2, height / 2, width / 2), _FACADE, params)
            )
            z += width
        # Parked cars; the near side of the right row is 2 m from the camera path.
        z = z_start + rng.uniform(0.0, 5.0)
        while z < z_end:
            if rng.random() < 0.25:
                z += rng.uniform(6.0, 25.0)
                continue
            length = rng.uniform(3.8, 4.8)
            width = rng.uniform(1.7, 1.9)
            x = (park_r + 0.25 + width / 2) if side > 0 else (park_l - 0.25 - width / 2)
            paint = float(rng.choice([0.15, 0.3, 0.5, 0.7, 0.85]))
            prims.append(Box((x, ground - 0.6, z + length / 2), (width / 2, 0.4, length / 2), _CAR, (paint, 0.0)))
            cabin = rng.uniform(0.45, 0.6) * length
            prims.append(
                Box(
                    (x, ground - 1.22, z + length / 2 + rng.uniform(-0.2, 0.3)),
                    (width / 2 - 0.1, 0.22, cabin / 2),
                    _CAR,
                    (paint, 1.0),
                )
            )
            z += length + rng.uniform(0.8, 5.0)
        # Thin poles (street lamps, sign posts) on the sidewalk near the kerb.
        z = z_start + rng.uniform(0.0, 10.0)
        pole_x = kerb_r + 0.4 if side > 0 else kerb_l - 0.4
        while z < z_end:
            prims.append(
                Cylinder(
                    pole_x + side * rng.uniform(0.0, 0.5),
                    z,
                    rng.uniform(0.04, 0.12),
                    ground - rng.uniform(2.5, 7.0),
                    ground - kerb_h,
                    _POLE,
                    (rng.uniform(0.2, 0.75),),
                )
            )
            z += rng.uniform(8.0, 30.0)

    # A gentle S-bend (left then back) after a straight stretch, at about 1 m per frame.
    bend_start = rng.uniform(5.0, 12.0)
    bend_len = rng.uniform(15.0, 25.0)
    amp = np.deg2rad(rng.uniform(3.0, 6.0))
    phase = rng.uniform(0.0, 2 * np.pi, 3)

    def yaw_at(k: F64) -> F64:
        s = np.clip((k - bend_start) / bend_len, 0.0, 2.0)
        return -amp * np.sin(np.pi * s)

    def trajectory(indices: NDArray[np.int64]) -> F64:
        last = int(indices.max()) if len(indices) else 0
        k = np.arange(last + 1, dtype=np.float64)
        speed = 1.0 + 0.1 * np.sin(k / 7.0 + phase[0])
        heading = yaw_at(k + 0.5)
        steps = np.stack([speed * np.sin(heading), np.zeros_like(k), speed * np.cos(heading)], axis=1)
        pos = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)[:-1]])
        # Small pitch and roll from the suspension.
        pitch = np.deg2rad(0.3) * np.sin(k / 3.0 + phase[1])
        roll = np.deg2rad(0.2) * np.sin(k / 4.0 + phase[2])
        yaw = yaw_at(k)
        return np.stack([_pose(_rotation(yaw[i], pitch[i], roll[i]), pos[i]) for i in indices])

    return prims, trajectory


def _orbit(rng: np.random.Generator, frames: int) -> tuple[list[Primitive], Callable[[NDArray[np.int64]], F64]]:
    """Primitives and trajectory of the orbit scene: objects within 4 m of the origin on the ground ``y = 0``."""
    prims: list[Primitive] = [GroundPlane(0.0, _GRASS)]
    placed: list[tuple[float, float, float]] = []
    kinds = ["sphere", "box", "cylinder", *rng.choice(["box", "cylinder", "sphere"], size=rng.integers(3, 6))]
    for kind in kinds:
        size = rng.uniform(0.35, 1.0)
        for _ in range(100):
            x, z = rng.uniform(-4.0, 4.0, 2)
            if np.hypot(x, z) < 4.0 and all(np.hypot(x - a, z - b) > size + r + 0.3 for a, b, r in placed):
                break
        placed.append((x, z, size))
        params: tuple[float, ...] = (
            rng.uniform(0.3, 0.8),
            rng.uniform(0.1, 0.35),
            rng.uniform(1.0, 6.0),
            float(rng.integers(0, 3)),
            rng.uniform(0.15, 0.6),
        )
        if kind == "sphere":
            prims.append(Sphere((x, -size, z), size, _OBJECT, params))
        elif kind == "box":
            half = (size, rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.0))
            prims.append(Box((x, -half[1], z), half, _OBJECT, params, yaw=rng.uniform(0, np.pi)))
        else:
            height = rng.uniform(0.6, 2.8)
            prims.append(Cylinder(x, z, 0.6 * size, -height, 0.0, _OBJECT, params))
    # A ring of distant buildings, so the background is not all sky.
    for angle in np.linspace(0.0, 2 * np.pi, 12, endpoint=False) + rng.uniform(0, 0.5):
        dist = rng.uniform(30.0, 45.0)
        height = rng.uniform(5.0, 15.0)
        params = (0.0, rng.uniform(0.45, 0.8), 0.08, 2.2, 3.0, 0.5, 0.5, rng.uniform(0.1, 0.3))
        prims.append(
            Box(
                (dist * np.sin(angle), -height / 2, dist * np.cos(angle)),
                (6.0, height / 2, 4.0),
                _FACADE,
                params,
                yaw=float(angle) + np.pi / 2,
            )
        )

    radius = rng.uniform(8.5, 10.0)
    altitude = rng.uniform(2.5, 3.5)
    step = np.deg2rad(rng.uniform(3.5, 5.0)) * rng.choice([-1.0, 1.0])
    start = rng.uniform(0.0, 2 * np.pi)
    target = np.array([0.0, -0.8, 0.0])

    def trajectory(indices: NDArray[np.int64]) -> F64:
        out = []
        for k in indices.astype(np.float64):
            angle = start + step * k
            r = radius + 0.4 * np.sin(k / 9.0)
            centre = np.array([r * np.sin(angle), -altitude - 0.3 * np.sin(k / 6.0), r * np.cos(angle)])
            forward = target - centre
            forward /= np.linalg.norm(forward)
            right = np.cross([0.0, 1.0, 0.0], forward)
            right /= np.linalg.norm(right)
            down = np.cross(forward, right)
            out.append(_pose(np.stack([right, down, forward], axis=1), centre))
        return np.stack(out)

    return prims, trajectory


def _room(rng: np.random.Generator, frames: int) -> tuple[list[Primitive], Callable[[NDArray[np.int64]], F64]]:
    """Primitives and trajectory of the room scene: a furnished room, floor ``y = 0``, centred on the origin.

    The MAV loops around the table at 1.0-1.4 m above the floor, about 0.1 m
    per frame, looking ahead and inwards with the yaw swinging, pitched down
    and rolling a little. ``frames`` does not bound anything here (the loop repeats).
    """
    width, depth, height = rng.uniform(7.0, 9.0), rng.uniform(6.0, 8.0), rng.uniform(2.6, 3.2)
    wall = 0.05  # half thickness
    plaster = (rng.uniform(0.65, 0.85), rng.uniform(0.004, 0.02))
    prims: list[Primitive] = [GroundPlane(0.0, _TILES, (rng.uniform(0.3, 0.6), rng.uniform(0.45, 0.7)))]

    def slab(
        center: tuple[float, float, float], half: tuple[float, float, float], material: int, params: tuple[float, ...]
    ) -> None:
        prims.append(Box(center, half, material, params))

    # Ceiling, three plain walls, and the window wall (x = +width/2) built around its opening.
    slab((0.0, -height - wall, 0.0), (width / 2 + 2 * wall, wall, depth / 2 + 2 * wall), _PLASTER, plaster)
    for z in (-depth / 2 - wall, depth / 2 + wall):
        slab((0.0, -height / 2, z), (width / 2 + 2 * wall, height / 2, wall), _PLASTER, plaster)
    slab((-width / 2 - wall, -height / 2, 0.0), (wall, height / 2, depth / 2 + 2 * wall), _PLASTER, plaster)
    sill, win_h, win_w = rng.uniform(0.8, 1.0), rng.uniform(1.0, 1.5), rng.uniform(1.2, 2.4)
    win_z = rng.uniform(-depth / 2 + win_w / 2 + 0.5, depth / 2 - win_w / 2 - 0.5)
    x_wall, top = width / 2 + wall, sill + win_h
    slab((x_wall, -sill / 2, 0.0), (wall, sill / 2, depth / 2 + 2 * wall), _PLASTER, plaster)
    slab((x_wall, -(top + height) / 2, 0.0), (wall, (height - top) / 2, depth / 2 + 2 * wall), _PLASTER, plaster)
    for z0, z1 in ((-depth / 2 - 2 * wall, win_z - win_w / 2), (win_z + win_w / 2, depth / 2 + 2 * wall)):
        slab((x_wall, -(sill + top) / 2, (z0 + z1) / 2), (wall, win_h / 2, (z1 - z0) / 2), _PLASTER, plaster)
    slab((width / 2 + rng.uniform(3.0, 5.0), -4.0, win_z), (0.5, 6.0, 12.0), _OUTSIDE, (rng.uniform(0.85, 1.0),))
    # A framed poster on the wall opposite the window: the one textured patch of wall.
    slab(
        (-width / 2 + 0.01, -rng.uniform(1.3, 1.8), rng.uniform(-depth / 4, depth / 4)),
        (0.01, rng.uniform(0.3, 0.5), rng.uniform(0.4, 0.7)),
        _OBJECT,
        (rng.uniform(0.3, 0.7), 0.35, rng.uniform(2.0, 6.0), 0.0, 0.3),
    )

    def object_params() -> tuple[float, ...]:
        return (
            rng.uniform(0.2, 0.8),
            rng.uniform(0.05, 0.4),
            rng.uniform(2.0, 12.0),
            float(rng.integers(0, 3)),
            rng.uniform(0.03, 0.15),
        )

    # Shelves against the back wall, cluttered.
    shelf_w, shelf_d, shelf_h = rng.uniform(1.2, 2.2), 0.3, rng.uniform(1.6, 2.1)
    shelf_x = rng.uniform(-width / 2 + shelf_w / 2 + 0.2, width / 2 - shelf_w / 2 - 0.6)
    shelf_z = depth / 2 - shelf_d / 2
    wood = (rng.uniform(0.3, 0.6), rng.uniform(0.1, 0.3), 0.0)
    for dx in (-shelf_w / 2, shelf_w / 2):
        slab((shelf_x + dx, -shelf_h / 2, shelf_z), (0.015, shelf_h / 2, shelf_d / 2), _WOOD, wood)
    boards = int(rng.integers(3, 6))
    for level in np.linspace(0.05, shelf_h - 0.02, boards):
        slab((shelf_x, -float(level), shelf_z), (shelf_w / 2, 0.012, shelf_d / 2), _WOOD, wood)
        x = shelf_x - shelf_w / 2 + 0.05
        while level < shelf_h - 0.3 and x < shelf_x + shelf_w / 2 - 0.1:
            size = rng.uniform(0.04, 0.12)
            kind = rng.integers(0, 3)
            base = -float(level) - 0.012
            if kind == 0:
                prims.append(Box((x + size, base - size, shelf_z), (size, size, size * 0.8), _OBJECT, object_params()))
            elif kind == 1:
                prims.append(Cylinder(x + size, shelf_z, size * 0.6, base - 2.5 * size, base, _OBJECT, object_params()))
            else:
                prims.append(Sphere((x + size, base - size, shelf_z), size, _OBJECT, object_params()))
            x += 2 * size + rng.uniform(0.01, 0.12)

    # A table in the middle of the loop and chairs around it, all on thin legs.
    table_x, table_z = rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3)
    top_half = (rng.uniform(0.45, 0.7), 0.02, rng.uniform(0.35, 0.5))
    table_h = rng.uniform(0.72, 0.78)
    slab((table_x, -table_h, table_z), top_half, _WOOD, (rng.uniform(0.35, 0.7), rng.uniform(0.1, 0.3), 1.0))
    for sx in (-1.0, 1.0):
        for sz in (-1.0, 1.0):
            lx, lz = table_x + sx * (top_half[0] - 0.05), table_z + sz * (top_half[2] - 0.05)
            prims.append(Cylinder(lx, lz, 0.025, -table_h + 0.02, 0.0, _POLE, (rng.uniform(0.2, 0.6),)))
    for side in rng.permutation(4)[: int(rng.integers(2, 5))]:
        angle = side * np.pi / 2
        reach = (top_half[0] if side % 2 else top_half[2]) + rng.uniform(0.15, 0.35)
        cx, cz = table_x + reach * np.sin(angle), table_z + reach * np.cos(angle)
        seat_h, leg_r = rng.uniform(0.43, 0.48), rng.uniform(0.010, 0.018)
        paint = rng.uniform(0.15, 0.8)
        slab((cx, -seat_h, cz), (0.21, 0.02, 0.21), _OBJECT, (paint, 0.1, 4.0, 0.0, 0.2))
        back = (cx + 0.2 * np.sin(angle), -seat_h - 0.25, cz + 0.2 * np.cos(angle))
        half_back = (0.015, 0.22, 0.21) if side % 2 else (0.21, 0.22, 0.015)
        slab(back, half_back, _OBJECT, (paint, 0.1, 4.0, 1.0, 0.08))
        for sx in (-0.18, 0.18):
            for sz in (-0.18, 0.18):
                prims.append(Cylinder(cx + sx, cz + sz, leg_r, -seat_h + 0.02, 0.0, _POLE, (rng.uniform(0.1, 0.7),)))

    # The loop: an ellipse around the table, clear of the walls and shelves.
    radius_x = width / 2 - rng.uniform(1.4, 1.9)
    radius_z = depth / 2 - rng.uniform(1.5, 1.9)
    # A standing lamp close beside the path: a thin pole that comes nearer than the disparity range.
    lamp_angle = rng.uniform(0.0, 2 * np.pi)
    lamp_r = 1.0 + rng.uniform(0.12, 0.22) * rng.choice([-1.0, 1.0])
    lamp_x, lamp_z = lamp_r * radius_x * np.sin(lamp_angle), lamp_r * radius_z * np.cos(lamp_angle)
    prims.append(Cylinder(lamp_x, lamp_z, 0.02, -1.6, 0.0, _POLE, (rng.uniform(0.2, 0.6),)))
    prims.append(Sphere((lamp_x, -1.75, lamp_z), 0.17, _OBJECT, (0.9, 0.05, 2.0, 0.0, 0.2)))

    speed = rng.uniform(0.08, 0.12)  # metres per frame
    step = speed / (0.5 * (radius_x + radius_z)) * rng.choice([-1.0, 1.0])
    start = rng.uniform(0.0, 2 * np.pi)
    altitude = rng.uniform(1.0, 1.4)
    inward = np.deg2rad(rng.uniform(30.0, 50.0))
    swing, pitch0 = np.deg2rad(rng.uniform(8.0, 15.0)), np.deg2rad(rng.uniform(8.0, 14.0))
    phase = rng.uniform(0.0, 2 * np.pi, 4)

    def trajectory(indices: NDArray[np.int64]) -> F64:
        out = []
        for k in indices.astype(np.float64):
            theta = start + step * k
            position = np.array(
                [radius_x * np.sin(theta), -altitude - 0.15 * np.sin(k / 11.0 + phase[0]), radius_z * np.cos(theta)]
            )
            # Along the path (the direction of motion), turned inwards towards the table, swinging.
            tangent = np.sign(step) * np.array([radius_x * np.cos(theta), -radius_z * np.sin(theta)])
            heading = np.arctan2(tangent[0], tangent[1])
            turn = np.sign(step) * inward + swing * np.sin(k / 9.0 + phase[1])
            pitch = -pitch0 + np.deg2rad(3.0) * np.sin(k / 7.0 + phase[2])
            roll = np.deg2rad(3.0) * np.sin(k / 5.0 + phase[3])
            out.append(_pose(_rotation(heading + turn, pitch, roll), position))
        return np.stack(out)

    return prims, trajectory


def _vehicle(rng: np.random.Generator, x: float, z: float, ground: float, truck: bool) -> list[Primitive]:
    """Boxes of a car (body, cabin, dark underbody) or a truck (cab, printed trailer, underbody) centred at ``x, z``."""
    paint = float(rng.choice([0.12, 0.3, 0.5, 0.7, 0.88]))
    if truck:
        length, half_w = rng.uniform(13.0, 16.5), 1.25
        trailer_h = rng.uniform(1.5, 1.9)
        print_params = (rng.uniform(0.4, 0.8), rng.uniform(0.15, 0.35), rng.uniform(0.5, 2.0), 0.0, 1.0)
        return [
            Box((x, ground - 0.5, z), (half_w - 0.15, 0.35, length / 2 - 0.3), _CAR, (0.08, 0.0)),
            Box((x, ground - 0.85 - trailer_h, z - 1.3), (half_w, trailer_h, length / 2 - 1.3), _OBJECT, print_params),
            Box((x, ground - 2.2, z + length / 2 - 1.2), (half_w, 1.3, 1.2), _CAR, (paint, 0.0)),
        ]
    length, half_w = rng.uniform(4.2, 4.9), rng.uniform(0.88, 0.95)
    return [
        Box((x, ground - 0.3, z), (half_w - 0.1, 0.25, length / 2 - 0.4), _CAR, (0.06, 0.0)),
        Box((x, ground - 0.8, z), (half_w, 0.3, length / 2), _CAR, (paint, 0.0)),
        Box((x, ground - 1.3, z - 0.2), (half_w - 0.08, 0.22, 0.27 * length), _CAR, (paint, 1.0)),
    ]


def _highway(
    rng: np.random.Generator, frames: int
) -> tuple[list[Primitive], Callable[[NDArray[np.int64]], F64], Callable[[int], F64]]:
    """Primitives, trajectory and vehicle motion of the highway scene, for ``frames`` frames at 2.5-3.5 m each.

    The camera drives in the middle of three lanes (x = 0), straight along +z,
    speeding up from ``v0`` to ``v1`` m per frame with a slight weave and
    suspension pitch and roll. Vehicles move along z at constant speeds (metres
    per frame): trucks in the right lane slower than the camera, cars in the
    left lane faster, cars far ahead in the camera's lane at about its speed,
    oncoming cars on the other carriageway.
    """
    ground = 1.65
    v0 = rng.uniform(2.5, 2.9)
    v1 = rng.uniform(max(v0, 3.0), 3.5)
    phase = rng.uniform(0.0, 2 * np.pi, 4)
    length = 3.5 * frames
    z_start, z_end = -60.0, length + 260.0
    zc, zh = 0.5 * (z_start + z_end), 0.5 * (z_end - z_start)

    prims: list[Primitive] = [GroundPlane(ground, _MOTORWAY)]
    rail_x = (_MW_EDGE_RIGHT + _MW_SHOULDER + 0.3, _MW_EDGE_LEFT - 0.8, _MW_ONCOMING + 0.8)
    post_step = rng.uniform(3.0, 4.0)
    metal = rng.uniform(0.55, 0.75)
    for x in rail_x:
        prims.append(Box((x, ground - 0.6, zc), (0.03, 0.17, zh), _RAIL, (metal,)))
        for z in np.arange(z_start, z_end, post_step):
            prims.append(Box((x + 0.1 * np.sign(x), ground - 0.4, float(z)), (0.06, 0.4, 0.06), _RAIL, (0.7 * metal,)))
    # Sparse far structure: trees and bushes beside the road, wooded hills and a few buildings far off.
    z = z_start + rng.uniform(0.0, 10.0)
    while z < z_end:
        side = float(rng.choice([-1.0, 1.0]))
        lateral = rng.uniform(3.0, 12.0)
        x = (_MW_EDGE_RIGHT + _MW_SHOULDER + lateral) if side > 0 else (_MW_ONCOMING - 3 * _MW_LANE - lateral)
        size = rng.uniform(0.6, 1.5)
        prims.append(Sphere((x, ground - 0.6 * size, z), size, _FOLIAGE, (rng.uniform(0.25, 0.45),)))
        z += rng.uniform(4.0, 15.0)
    z = z_start + rng.uniform(0.0, 20.0)
    while z < z_end:
        side = float(rng.choice([-1.0, 1.0]))
        lateral = rng.uniform(10.0, 60.0)
        x = (_MW_EDGE_RIGHT + lateral) if side > 0 else (_MW_ONCOMING - 3 * _MW_LANE - lateral)
        crown = rng.uniform(2.0, 4.0)
        trunk_h = rng.uniform(2.0, 4.0)
        prims.append(Cylinder(x, z, rng.uniform(0.15, 0.3), ground - trunk_h, ground, _POLE, (rng.uniform(0.2, 0.4),)))
        prims.append(Sphere((x, ground - trunk_h - 0.8 * crown, z), crown, _FOLIAGE, (rng.uniform(0.2, 0.4),)))
        z += rng.uniform(6.0, 25.0)
    for side in (1.0, -1.0):
        z = z_start + rng.uniform(0.0, 60.0)
        while z < z_end + 200.0:
            width = rng.uniform(40.0, 120.0)
            dist = rng.uniform(90.0, 250.0)
            height = rng.uniform(8.0, 30.0)
            if rng.random() < 0.25:
                params: tuple[float, ...] = (
                    ground, rng.uniform(0.45, 0.8), rng.uniform(0.15, 0.35), rng.uniform(2.0, 3.5),
                    rng.uniform(2.8, 3.4), 0.5, 0.5, rng.uniform(0.1, 0.3),
                )  # fmt: skip
                material, height = _FACADE, rng.uniform(6.0, 20.0)
            else:
                params, material = (rng.uniform(0.2, 0.35),), _FOLIAGE
            prims.append(
                Box(
                    (side * dist, ground - height / 2, z + width / 2),
                    (width / 4, height / 2, width / 2),
                    material,
                    params,
                )
            )
            z += width + rng.uniform(20.0, 150.0)

    # Traffic: (lane x, start z relative to the camera, speed in m per frame, truck?).
    traffic: list[tuple[float, float, float, bool]] = []
    for _ in range(int(rng.integers(2, 4))):  # trucks ahead in the right lane, being overtaken
        traffic.append((_MW_LANE, rng.uniform(15.0, 90.0), rng.uniform(2.1, 2.4), True))
    for _ in range(int(rng.integers(2, 4))):  # cars overtaking in the left lane, from behind or beside
        traffic.append((-_MW_LANE, rng.uniform(-25.0, 30.0), rng.uniform(3.6, 4.5), False))
    for _ in range(int(rng.integers(1, 3))):  # cars ahead in the camera's lane, at about its speed
        traffic.append((0.0, rng.uniform(35.0, 80.0), 0.5 * (v0 + v1) + rng.uniform(-0.1, 0.1), False))
    for _ in range(int(rng.integers(2, 5))):  # oncoming traffic on the other carriageway
        lane = _MW_ONCOMING - _MW_LANE * (0.5 + float(rng.integers(0, 3)))
        traffic.append((lane, rng.uniform(60.0, 60.0 + 7.0 * frames), -rng.uniform(2.4, 3.2), bool(rng.random() < 0.3)))
    n_static = len(prims)
    speeds = np.zeros(n_static)
    for x, z0, speed, truck in traffic:
        boxes = _vehicle(rng, x + rng.uniform(-0.3, 0.3), z0, ground, truck)
        prims.extend(boxes)
        speeds = np.concatenate([speeds, np.full(len(boxes), speed)])

    def motion(index: int) -> F64:
        offsets = np.zeros((len(speeds), 3))
        offsets[:, 2] = speeds * index
        return offsets

    def trajectory(indices: NDArray[np.int64]) -> F64:
        last = int(indices.max()) if len(indices) else 0
        k = np.arange(last + 1, dtype=np.float64)
        speed = v0 + (v1 - v0) * np.clip(k / max(frames - 1, 1), 0.0, 1.0)
        z = np.concatenate([[0.0], np.cumsum(speed)[:-1]])
        x = 0.25 * np.sin(z / 60.0 + phase[0])
        yaw = np.arctan(0.25 / 60.0 * np.cos(z / 60.0 + phase[0]))
        pitch = np.deg2rad(0.25) * np.sin(k / 3.0 + phase[1])
        roll = np.deg2rad(0.15) * np.sin(k / 4.0 + phase[2])
        return np.stack([_pose(_rotation(yaw[i], pitch[i], roll[i]), np.array([x[i], 0.0, z[i]])) for i in indices])

    return prims, trajectory, motion


_BASELINES = {"room": (0.12, 0.2)}


def make_scene(
    name: str, seed: int = 1, width: int = _KITTI_SIZE[0], height: int = _KITTI_SIZE[1], *, frames: int = 300
) -> SyntheticScene:
    """Build scene ``name`` (one of :data:`SCENES`) at image size ``width`` x ``height``.

    Object placement, textures and the trajectory are drawn from
    ``numpy.random.default_rng(seed)``, so a seed always gives the same scene.
    ``frames`` bounds how far the street and the highway extend (frames past
    it still render, but the road ends) and sets the highway's speed-up.
    """
    builders = {"street": _street, "orbit": _orbit, "room": _room}
    if name not in builders and name != "highway":
        raise DatasetError(f"unknown synthetic scene {name!r}; expected one of {', '.join(SCENES)}")
    rng = np.random.default_rng(seed)
    # The room's camera is a MAV's, with a short baseline; drawn first so the rest of the stream is the scene's.
    baseline = rng.uniform(*_BASELINES[name]) if name in _BASELINES else _KITTI_BASELINE
    camera = kitti_like_camera(width, height, baseline=baseline)
    noise = ValueNoise(rng)
    if name == "highway":
        prims, trajectory, motion = _highway(rng, max(int(frames), 1))
        return SyntheticScene(name, seed, camera, prims, trajectory, noise, motion)
    prims, trajectory = builders[name](rng, max(int(frames), 1))
    return SyntheticScene(name, seed, camera, prims, trajectory, noise)


def _format_row(values: F64) -> str:
    return " ".join(f"{v:.12e}" for v in values)


def _write_index(seq: Path, poses_file: Path, poses: F64) -> None:
    """``times.txt`` (10 Hz) and the pose file of the first ``len(poses)`` frames."""
    (seq / "times.txt").write_text("".join(f"{k / FRAME_RATE_HZ:.6e}\n" for k in range(len(poses))))
    poses_file.write_text("".join(_format_row(p[:3].ravel()) + "\n" for p in poses))


def write_sequence(
    out: Path, *, scene: str, frames: int, seed: int, width: int = _KITTI_SIZE[0], height: int = _KITTI_SIZE[1]
) -> Path:
    """Render ``frames`` frames of ``scene`` and write them in the KITTI odometry layout under ``out``.

    Writes ``sequences/00/{image_0,image_1,disp_0}/NNNNNN.png``, ``calib.txt``
    (P0..P3), ``times.txt`` (10 Hz) and ``poses/00.txt`` (T_world_left, world =
    left camera at frame 0). ``disp_0`` holds the left ground-truth disparity
    as uint16 ``round(d * 256)``, 0 where there is none.

    Returns:
        The sequence folder ``out/sequences/00``.
    """
    if frames < 1:
        raise DatasetError(f"frames must be >= 1, got {frames}")
    synthetic = make_scene(scene, seed, width, height, frames=frames)
    cam = synthetic.camera
    seq = Path(out) / "sequences" / "00"
    for folder in ("image_0", "image_1", "disp_0"):
        (seq / folder).mkdir(parents=True, exist_ok=True)
    (Path(out) / "poses").mkdir(parents=True, exist_ok=True)
    p_left, p_right = cam.projection_matrices()
    calib = [f"P{i}: {_format_row(p.ravel())}" for i, p in enumerate((p_left, p_right, p_left, p_right))]
    (seq / "calib.txt").write_text("\n".join(calib) + "\n")
    poses = synthetic.poses(frames)
    _write_index(seq, Path(out) / "poses" / "00.txt", poses)
    for k in tqdm(range(frames), desc=f"synth {scene}", unit="frame"):
        try:
            interrupts.check()
        except interrupts.Interrupted as exc:
            _write_index(seq, Path(out) / "poses" / "00.txt", poses[:k])  # reads like a shorter sequence
            exc.done = f"rendered {k} of {frames} frames; wrote them to {seq} (times.txt and poses list those {k})"
            raise
        frame = synthetic.render(k)
        name = f"{k:06d}.png"
        disp = np.nan_to_num(frame.disparity, nan=0.0)
        disp16 = np.where(np.isfinite(frame.disparity), np.clip(np.rint(disp * 256.0), 1, 65535), 0).astype(np.uint16)
        for folder, image in (("image_0", frame.left), ("image_1", frame.right), ("disp_0", disp16)):
            if not cv2.imwrite(str(seq / folder / name), image):
                raise DatasetError(f"could not write {seq / folder / name}")
    return seq
