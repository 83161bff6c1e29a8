"""A small vectorised numpy ray caster for the synthetic scenes.

Rays are cast through every pixel of a pinhole camera; a ray's direction is
scaled so that its component along the camera's optical axis is 1, so the ray
parameter ``t`` of a hit *is* the hit's depth ``z`` in that camera (metres).
Primitives (horizontal plane, boxes turning about the vertical axis, vertical
cylinders, spheres) are intersected only over the image rectangle their
bounding box projects to, and the nearest hit is kept in a :class:`HitBuffer`.

World frames here follow the camera convention of the package: y points down,
so "vertical" means along y and the ground is a plane ``y = const``.

Also here: band-limited solid value noise and box-filtered pulse trains, the
building blocks of the procedural textures (functions of the 3D point only, so
every view sees the same surface).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera

__all__ = [
    "Box",
    "Cylinder",
    "GroundPlane",
    "HitBuffer",
    "Primitive",
    "Sphere",
    "ValueNoise",
    "cast",
    "pulse",
    "surface_normals",
]

F64 = NDArray[np.float64]

# Hits closer than this along the ray (metres of depth) are ignored, so a ray
# never hits the surface it starts on.
_T_EPS = 1e-6
# Near clipping depth (metres) when projecting bounding boxes to the image.
_NEAR = 0.02
# The 12 edges of a box given by its 8 corners indexed by 3 bits (x, y, z).
_BOX_EDGES = np.array(
    [(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit],
    dtype=np.intp,
)
_UNIT_CORNERS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64) * 2 - 1


def _rot_y(yaw: float) -> F64:
    """Rotation by ``yaw`` radians about the y (down) axis: maps +z towards +x."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass
class Rays:
    """The rays of one view.

    Attributes:
        origin: (3,) optical centre in the world, metres.
        dirs: (3, H, W) world directions, scaled to unit depth along the optical axis.
        inv: (3, H, W) reciprocals of ``dirs`` (exact zeros replaced by a tiny value), for slab tests.
    """

    origin: F64
    dirs: F64
    inv: F64

    @classmethod
    def for_camera(cls, camera: StereoCamera, pose: F64) -> Rays:
        """Rays through the pixel centres of ``camera`` placed at ``pose`` (4x4 T_world_camera)."""
        u = (np.arange(camera.width, dtype=np.float64) - camera.cx) / camera.fx
        v = (np.arange(camera.height, dtype=np.float64) - camera.cy) / camera.fy
        r = np.asarray(pose[:3, :3], dtype=np.float64)
        dirs = r[:, 0, None, None] * u[None, None, :] + r[:, 1, None, None] * v[None, :, None] + r[:, 2, None, None]
        return cls(origin=np.asarray(pose[:3, 3], dtype=np.float64).copy(), dirs=dirs, inv=_reciprocal(dirs))


def _reciprocal(d: F64) -> F64:
    """``1 / d`` with exact zeros nudged to 1e-12, so slab tests see a huge but finite, signed value."""
    return 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)


@dataclass
class HitBuffer:
    """Nearest hit per pixel: depth ``t`` (inf where nothing was hit), primitive index (-1) and face code."""

    t: F64
    prim: NDArray[np.int32]
    face: NDArray[np.int8]

    @classmethod
    def empty(cls, height: int, width: int) -> HitBuffer:
        """A buffer of ``height`` x ``width`` pixels with no hits."""
        return cls(
            t=np.full((height, width), np.inf),
            prim=np.full((height, width), -1, dtype=np.int32),
            face=np.zeros((height, width), dtype=np.int8),
        )


class Primitive:
    """Base of the analytic primitives; ``material`` and ``params`` feed the texture functions."""

    material: int
    params: tuple[float, ...]

    def corners(self) -> F64 | None:
        """(8, 3) corners of a box bounding the primitive (index bits = x, y, z), or None if unbounded."""
        raise NotImplementedError

    def intersect(self, origin: F64, dirs: F64, inv: F64) -> tuple[F64, NDArray[np.int8]]:
        """Depth ``t`` of the first hit per ray (inf on a miss) and a face code, for rays (3, h, w)."""
        raise NotImplementedError

    def normals(self, points: F64, face: NDArray[np.int8]) -> F64:
        """Outward unit normals (3, N) at hit points (3, N) with their face codes."""
        raise NotImplementedError


@dataclass
class GroundPlane(Primitive):
    """The horizontal plane ``y = height`` seen from above (y points down), up to ``max_range`` metres."""

    height: float
    material: int
    params: tuple[float, ...] = ()
    max_range: float = 500.0

    def corners(self) -> F64 | None:
        """Unbounded: always the whole image."""
        return None

    def intersect(self, origin: F64, dirs: F64, inv: F64) -> tuple[F64, NDArray[np.int8]]:
        """Hit where the ray goes down to the plane; beyond ``max_range`` (horizontal metres) counts as a miss."""
        t = (self.height - origin[1]) * inv[1]
        reach = t * np.hypot(dirs[0], dirs[2])
        t = np.where((dirs[1] > 0) & (t > _T_EPS) & (reach < self.max_range), t, np.inf)
        return t, np.zeros(t.shape, dtype=np.int8)

    def normals(self, points: F64, face: NDArray[np.int8]) -> F64:
        """Straight up: -y."""
        n = np.zeros(points.shape)
        n[1] = -1.0
        return n


@dataclass
class Box(Primitive):
    """A box with centre ``center``, half extents ``half`` (x, y, z, metres), turned by ``yaw`` about y.

    Face codes: ``2 * axis + (1 if the face is on the + side)``, axes of the box frame.
    """

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    material: int
    params: tuple[float, ...] = ()
    yaw: float = 0.0
    _rot: F64 = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._rot = _rot_y(self.yaw)

    def corners(self) -> F64 | None:
        """The 8 box corners in the world."""
        local = _UNIT_CORNERS * np.asarray(self.half)
        return local @ self._rot.T + np.asarray(self.center)

    def intersect(self, origin: F64, dirs: F64, inv: F64) -> tuple[F64, NDArray[np.int8]]:
        """Slab test in the box frame: the entry depth is the largest of the three near-slab depths."""
        o = self._rot.T @ (origin - np.asarray(self.center))
        if self.yaw != 0.0:
            dirs = np.tensordot(self._rot.T, dirs, axes=1)
            inv = _reciprocal(dirs)
        t_in = np.full(dirs.shape[1:], -np.inf)
        t_out = np.full(dirs.shape[1:], np.inf)
        face = np.zeros(dirs.shape[1:], dtype=np.int8)
        for axis in range(3):
            h = self.half[axis]
            t_lo = (-h - o[axis]) * inv[axis]
            t_hi = (h - o[axis]) * inv[axis]
            near = np.minimum(t_lo, t_hi)
            entering = near > t_in
            t_in = np.where(entering, near, t_in)
            # A ray entering through the + face travels in the - direction along the axis.
            face = np.where(entering, np.int8(2 * axis) + (dirs[axis] < 0), face).astype(np.int8)
            np.minimum(t_out, np.maximum(t_lo, t_hi), out=t_out)
        t = np.where((t_out >= t_in) & (t_in > _T_EPS), t_in, np.inf)
        return t, face

    def normals(self, points: F64, face: NDArray[np.int8]) -> F64:
        """The face's axis of the box frame, signed, turned into the world."""
        axis = face // 2
        sign = np.where(face % 2 == 1, 1.0, -1.0)
        return self._rot[:, axis] * sign


@dataclass
class Cylinder(Primitive):
    """A vertical cylinder with axis through ``(x, z)``, ``radius`` and y extent ``y_top`` < ``y_bottom``.

    The top cap is closed (face code 1); the wall has face code 0; the bottom
    is left open (it stands on the ground).
    """

    x: float
    z: float
    radius: float
    y_top: float
    y_bottom: float
    material: int
    params: tuple[float, ...] = ()

    def corners(self) -> F64 | None:
        """Corners of the axis-aligned bounding box."""
        c = np.array([self.x, 0.5 * (self.y_top + self.y_bottom), self.z])
        h = np.array([self.radius, 0.5 * (self.y_bottom - self.y_top), self.radius])
        return _UNIT_CORNERS * h + c

    def intersect(self, origin: F64, dirs: F64, inv: F64) -> tuple[F64, NDArray[np.int8]]:
        """Wall (outer root of the quadratic in x, z) and top cap; the nearer of the two."""
        ox, oz = origin[0] - self.x, origin[2] - self.z
        dx, dy, dz = dirs
        a = dx * dx + dz * dz
        b = 2.0 * (ox * dx + oz * dz)
        c = ox * ox + oz * oz - self.radius**2
        disc = b * b - 4.0 * a * c
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        y_side = origin[1] + t_side * dy
        side = (disc > 0) & (t_side > _T_EPS) & (y_side >= self.y_top) & (y_side <= self.y_bottom)
        t_side = np.where(side, t_side, np.inf)
        t_cap = (self.y_top - origin[1]) * inv[1]
        cap_x = ox + t_cap * dx
        cap_z = oz + t_cap * dz
        cap = (dy > 0) & (t_cap > _T_EPS) & (cap_x * cap_x + cap_z * cap_z <= self.radius**2)
        t_cap = np.where(cap, t_cap, np.inf)
        return np.minimum(t_side, t_cap), (t_cap < t_side).astype(np.int8)

    def normals(self, points: F64, face: NDArray[np.int8]) -> F64:
        """Radial on the wall, up on the cap."""
        wall = face == 0
        n = np.zeros(points.shape)
        n[0] = np.where(wall, (points[0] - self.x) / self.radius, 0.0)
        n[1] = np.where(wall, 0.0, -1.0)
        n[2] = np.where(wall, (points[2] - self.z) / self.radius, 0.0)
        return n


@dataclass
class Sphere(Primitive):
    """A sphere with ``center`` and ``radius`` (metres)."""

    center: tuple[float, float, float]
    radius: float
    material: int
    params: tuple[float, ...] = ()

    def corners(self) -> F64 | None:
        """Corners of the axis-aligned bounding box."""
        return _UNIT_CORNERS * self.radius + np.asarray(self.center)

    def intersect(self, origin: F64, dirs: F64, inv: F64) -> tuple[F64, NDArray[np.int8]]:
        """Outer root of the quadratic."""
        oc = origin - np.asarray(self.center)
        a = dirs[0] ** 2 + dirs[1] ** 2 + dirs[2] ** 2
        b = 2.0 * (oc[0] * dirs[0] + oc[1] * dirs[1] + oc[2] * dirs[2])
        c = float(oc @ oc) - self.radius**2
        disc = b * b - 4.0 * a * c
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        t = np.where((disc > 0) & (t > _T_EPS), t, np.inf)
        return t, np.zeros(t.shape, dtype=np.int8)

    def normals(self, points: F64, face: NDArray[np.int8]) -> F64:
        """Radial."""
        n: F64 = (points - np.asarray(self.center)[:, None]) / self.radius
        return n


def _screen_rect(corners: F64, camera: StereoCamera, pose: F64) -> tuple[int, int, int, int] | None:
    """Pixel rectangle ``(v0, v1, u0, u1)`` (half-open) covering a bounding box, or None if it is not visible.

    The box is clipped at the near plane first: the clipped solid's vertices are
    the corners in front plus the crossings of the 12 edges with the plane.
    """
    r = pose[:3, :3]
    pc = (corners - pose[:3, 3]) @ r
    z = pc[:, 2]
    front = z >= _NEAR
    if not front.any():
        return None
    pts = [pc[front]]
    a, b = _BOX_EDGES[:, 0], _BOX_EDGES[:, 1]
    crossing = front[a] != front[b]
    if crossing.any():
        pa, pb = pc[a[crossing]], pc[b[crossing]]
        s = (_NEAR - pa[:, 2]) / (pb[:, 2] - pa[:, 2])
        pts.append(pa + s[:, None] * (pb - pa))
    p = np.concatenate(pts)
    u = camera.fx * p[:, 0] / p[:, 2] + camera.cx
    v = camera.fy * p[:, 1] / p[:, 2] + camera.cy
    u0 = max(int(np.floor(u.min())) - 1, 0)
    u1 = min(int(np.ceil(u.max())) + 2, camera.width)
    v0 = max(int(np.floor(v.min())) - 1, 0)
    v1 = min(int(np.ceil(v.max())) + 2, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def cast(primitives: list[Primitive], camera: StereoCamera, pose: F64) -> tuple[Rays, HitBuffer]:
    """Cast the rays of ``camera`` at ``pose`` (4x4 T_world_camera) against all primitives; keep the nearest hit.

    Each primitive is tested only over the image rectangle its bounding box
    projects to, which keeps distant and off-screen objects nearly free.

    Returns:
        The rays and the hit buffer; ``hits.t`` is the depth along the camera's
        optical axis (metres), ``hits.prim`` indexes ``primitives``.
    """
    rays = Rays.for_camera(camera, pose)
    hits = HitBuffer.empty(camera.height, camera.width)
    for index, prim in enumerate(primitives):
        corners = prim.corners()
        if corners is None:
            rect: tuple[int, int, int, int] | None = (0, camera.height, 0, camera.width)
        else:
            rect = _screen_rect(corners, camera, pose)
        if rect is None:
            continue
        v0, v1, u0, u1 = rect
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t, face = prim.intersect(rays.origin, rays.dirs[:, v0:v1, u0:u1], rays.inv[:, v0:v1, u0:u1])
        best = hits.t[v0:v1, u0:u1]
        closer = t < best
        if not closer.any():
            continue
        best[closer] = t[closer]
        hits.prim[v0:v1, u0:u1][closer] = index
        hits.face[v0:v1, u0:u1][closer] = face[closer]
    return rays, hits


def surface_normals(primitives: list[Primitive], points: F64, prim: NDArray[np.int32], face: NDArray[np.int8]) -> F64:
    """Unit normals (3, N) at hit points (3, N) of primitives ``prim`` (N,) with face codes (N,).

    Flat faces (boxes, the ground, cylinder caps) take their normal from a
    (primitive, face) table; only hits on curved surfaces are grouped by
    primitive and asked for their normals.
    """
    table = np.zeros((len(primitives), 6, 3))
    curved = np.zeros(len(primitives), dtype=bool)
    for i, primitive in enumerate(primitives):
        if isinstance(primitive, (Cylinder, Sphere)):
            curved[i] = True
        else:
            faces = np.arange(6, dtype=np.int8)
            table[i] = primitive.normals(np.zeros((3, 6)), faces).T
    flat_index = prim.astype(np.int64) * 6 + face
    normals = np.stack([table[:, :, k].ravel().take(flat_index) for k in range(3)])
    on_curve = np.flatnonzero(curved[prim])
    if len(on_curve):
        order = on_curve[np.argsort(prim[on_curve], kind="stable")]
        ids, starts = np.unique(prim[order], return_index=True)
        stops = [*starts[1:], len(order)]
        for i, start, stop in zip(ids, starts, stops, strict=True):
            sel = order[start:stop]
            normals[:, sel] = primitives[int(i)].normals(points.take(sel, axis=1), face[sel])
    return normals


class ValueNoise:
    """Solid (3D) value noise from a random lattice, summed over octaves and band-limited per pixel.

    Points are passed as (3, N) arrays (one contiguous row per coordinate, which
    keeps numpy's inner loops long).

    Args:
        rng: source of the lattice values and per-octave offsets.
        size: lattice period (cells, a power of two) before the pattern
            repeats; offsets per octave hide the repetition.
    """

    def __init__(self, rng: np.random.Generator, size: int = 64) -> None:
        if size & (size - 1):
            raise ValueError(f"lattice size must be a power of two, got {size}")
        self._size = size
        cube = rng.random((size, size, size), dtype=np.float32) * 2.0 - 1.0
        self._values = cube.reshape(-1)
        # The +z neighbour of every lattice value, so both come from the same flat index.
        self._values_z = np.roll(cube, -1, axis=2).reshape(-1)
        self._offsets = rng.random((16, 3)) * size

    def _octave(self, p: F64, index: int) -> NDArray[np.float32]:
        """One octave in [-1, 1] at unit lattice spacing (smoothstep-interpolated lattice values), p (3, N)."""
        q = p + self._offsets[index % len(self._offsets)][:, None]
        cell = np.floor(q)
        f = (q - cell).astype(np.float32)
        w = f * f * (3.0 - 2.0 * f)
        n = self._size
        i = cell.astype(np.int32) & (n - 1)
        j = (i + 1) & (n - 1)
        wx, wy, wz = w[0], w[1], w[2]
        acc = np.zeros(q.shape[1], dtype=np.float32)
        for xx, ax in ((i[0] * (n * n), 1.0 - wx), (j[0] * (n * n), wx)):
            for yy, ay in ((i[1] * n, 1.0 - wy), (j[1] * n, wy)):
                k = xx + yy + i[2]
                a = self._values.take(k)
                b = self._values_z.take(k)
                acc += (ax * ay) * (a + wz * (b - a))
        return acc

    def fbm(self, p: F64, footprint: F64, freq: float, octaves: int, gain: float = 0.5) -> NDArray[np.float32]:
        """Fractal sum of ``octaves`` octaves from ``freq`` cycles per metre at points p (3, N); about [-1, 1].

        Octaves finer than the pixel footprint (metres per pixel at the point)
        fade out, so distant surfaces do not alias: the texture stays a
        function of the 3D point and of the scale it is seen at only.
        """
        total = np.zeros(p.shape[1], dtype=np.float32)
        # With footprints in ascending order (the renderer sorts its hits so), the points that still see an
        # octave form a prefix: slices instead of boolean gathers.
        ascending = bool(np.all(footprint[:-1] <= footprint[1:]))
        amp = 1.0
        norm = 0.0
        f = freq
        for k in range(octaves):
            if ascending:
                m = int(np.searchsorted(footprint, 0.5 / f, side="left"))
                if m:
                    weight = np.clip((0.5 - f * footprint[:m]) / 0.25, 0.0, 1.0).astype(np.float32)
                    total[:m] += (amp * weight) * self._octave(p[:, :m] * f, k)
            else:
                weight = np.clip((0.5 - f * footprint) / 0.25, 0.0, 1.0).astype(np.float32)
                active = weight > 0
                if active.any():
                    total[active] += (amp * weight[active]) * self._octave(p[:, active] * f, k)
            norm += amp
            amp *= gain
            f *= 2.0
        return total / np.float32(norm / 1.6)


def pulse(x: F64, period: float | F64, duty: float | F64, footprint: F64) -> F64:
    """Box-filtered pulse train: the share of ``[x - fp/2, x + fp/2]`` where ``frac(x / period) < duty``.

    ``x``, ``period`` and ``footprint`` in metres; returns values in [0, 1]
    that blur to the mean ``duty`` once a pixel covers many periods.
    """
    fp = np.maximum(footprint, 1e-4)

    def integral(y: F64) -> F64:
        k = np.floor(y / period)
        return k * duty * period + np.minimum(y - k * period, duty * period)

    return np.clip((integral(x + 0.5 * fp) - integral(x - 0.5 * fp)) / fp, 0.0, 1.0)
