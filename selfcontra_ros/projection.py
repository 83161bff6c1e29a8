"""Finding reference measurements between two views: lookup and splat.

Both directions of DESIGN section 3, on flattened pixel arrays (pixel index
``v * width + u``), vectorised over all points:

- :func:`lookup`: project query points into a reference view's left image and
  take the reference measurement at the nearest pixel;
- :func:`splat_nearest`: project reference points into the query image and
  keep, per query pixel, the one nearest to the query camera (a z-buffer);
- :func:`splat_all`: the same projection keeping every candidate per pixel
  (Stage 3's augmented depth map).

The per-point projection is one compiled kernel
(:func:`selfcontra_ros.stages.kernels.project_scalar`), shared with the fused
stage kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.stages import kernels

__all__ = ["Lookup", "Splat", "lookup", "pixel_rays", "project_to_pixels", "splat_all", "splat_nearest"]

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_IDENTITY = np.eye(4)


def transform(pose: FloatArray, points: NDArray[np.floating]) -> FloatArray:
    """Apply a 4x4 rigid transform to ``(..., 3)`` points, in float64."""
    # (3x3) @ (3, N) goes through BLAS; (N, 3) @ (3, 3) is several times slower in numpy.
    p = np.asarray(points, dtype=np.float64)
    return (pose[:3, :3] @ p.T).T + pose[:3, 3]


def pixel_rays(camera: StereoCamera) -> FloatArray:
    """Per-pixel ray directions ``((u - cx)/fx, (v - cy)/fy, 1)`` (``(H*W, 3)``): depth ``z`` -> point ``z * ray``."""
    u = np.arange(camera.width, dtype=np.float64)
    v = np.arange(camera.height, dtype=np.float64)
    uu, vv = np.meshgrid((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
    return np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=-1)


def project_to_pixels(points: FloatArray, camera: StereoCamera) -> tuple[IndexArray, BoolArray]:
    """Nearest pixel (flat index) of left-frame points (``(M, 3)``, metres) and whether it lies in the image.

    Points at ``z <= 0``, not finite or outside the image get ``ok = False`` (their index is 0).
    """
    _, index = _project(points, _IDENTITY, camera)
    ok = index >= 0
    return np.maximum(index, 0), ok


def _project(points: NDArray[np.floating], pose: FloatArray, camera: StereoCamera) -> tuple[FloatArray, IndexArray]:
    """Points moved by the 4x4 ``pose`` (float64) and their flat pixel index in ``camera`` (-1 where none)."""
    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    moved, index = kernels.project_rows(
        np.ascontiguousarray(p.reshape(-1, 3)),
        np.ascontiguousarray(pose, dtype=np.float64),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.width,
        camera.height,
    )
    return moved, index


@dataclass(frozen=True)
class Lookup:
    """Result of looking query points up in a reference view.

    Attributes:
        ok: the point projects into the reference image onto a valid reference measurement.
        ref_index: flat index of that reference pixel (0 where not ``ok``).
        points_in_ref: the query points in the reference left frame (metres).
    """

    ok: BoolArray
    ref_index: IndexArray
    points_in_ref: FloatArray


def lookup(
    query_points: NDArray[np.floating], ref_from_query: FloatArray, camera: StereoCamera, ref_valid: BoolArray
) -> Lookup:
    """Look query points (``(M, 3)``, query left frame) up in a reference view.

    Args:
        query_points: points in the query's left frame, metres.
        ref_from_query: 4x4 transform from the query's to the reference's left frame.
        camera: the stereo camera of both views.
        ref_valid: flat validity mask of the reference measurements (``(H*W,)``).
    """
    in_ref, index = _project(query_points, ref_from_query, camera)
    ok = index >= 0
    index = np.maximum(index, 0)
    ok &= ref_valid[index]
    return Lookup(ok=ok, ref_index=index, points_in_ref=in_ref)


@dataclass(frozen=True)
class Splat:
    """Reference points projected into the query image.

    Attributes:
        query_index: flat query pixel each point falls into.
        depth: the point's depth ``z`` in the query frame, metres.
        source: flat reference pixel index of the point.
    """

    query_index: IndexArray
    depth: FloatArray
    source: IndexArray


def splat_all(
    ref_points: NDArray[np.floating], ref_index: IndexArray, query_from_ref: FloatArray, camera: StereoCamera
) -> Splat:
    """Project reference points (``(K, 3)``, reference left frame) into the query image, keeping every one.

    ``ref_index`` gives each point's flat reference pixel; points in front of
    the query camera that fall inside its image are returned.
    """
    in_query, index = _project(ref_points, query_from_ref, camera)
    ok = index >= 0
    return Splat(query_index=index[ok], depth=in_query[ok, 2], source=np.asarray(ref_index, dtype=np.int64)[ok])


def splat_nearest(
    ref_points: NDArray[np.floating], ref_index: IndexArray, query_from_ref: FloatArray, camera: StereoCamera
) -> IndexArray:
    """Z-buffer splat: per query pixel, the flat reference index of the splatted point nearest the query camera.

    Returns a ``(H*W,)`` array, ``-1`` where no reference point falls.
    """
    p = np.asarray(ref_points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    # Exact depth ties are possible only for coincident points; either one is right (the later one is kept).
    return kernels.splat_nearest_kernel(
        np.ascontiguousarray(p.reshape(-1, 3)),
        np.ascontiguousarray(ref_index, dtype=np.int64),
        np.ascontiguousarray(query_from_ref, dtype=np.float64),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.width,
        camera.height,
    )
