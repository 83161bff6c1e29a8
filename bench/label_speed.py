"""Labeling speed against the query algorithm's own speed, at KITTI resolution.

Renders a synthetic street (``selfcontra_ros.datasets.synthetic``), runs
OpenCV StereoSGBM (the package's default query algorithm, left disparity only,
as the labeler uses it) and the self-contradiction labeler on the same
frames, and prints per query frame (a frame that received labels):

- ``sgbm_ms``: StereoSGBM time per frame;
- ``label_ms``: labeler time per arriving view in steady state: the
  ``add_view`` calls made once the window is full, each of which adds a view
  (depth, covariances, Stage 1 against the window in both directions) and
  labels one (Stages 2 and 3); warm-up views and ``flush`` are not counted;
- ``ratio``: ``label_ms / sgbm_ms``;
- ``stages_ms``: ``label_ms`` split by the stage functions the labeler calls
  (views = depth and covariance, stage1_support, stage2_voting,
  stage3_outliers, other = the rest of ``add_view``).

The numba kernels are compiled (or loaded from their cache) by a small
warm-up run first, so compilation is never timed.

The stage split wraps the stage functions as the labeler module imported
them, for the duration of the run only; nested calls inside a stage count for
that stage. Each window size ends with one JSON line::

    {"window": 10, "sgbm_ms": ..., "label_ms": ..., "ratio": ..., "stages_ms": {...}}

Usage: ``python bench/label_speed.py [--window N] [--frames F] [--size WxH]``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import sys
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.datasets.synthetic import SCENES, make_scene
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import Labeler, LabelerParams
from selfcontra_ros.matching.base import MatcherParams, make_matcher

DEFAULT_WINDOWS = (10, 20)

#: Stage name of each library module whose functions the labeler calls.
_STAGE_OF_MODULE = {
    "selfcontra_ros.stages.support": "stage1_support",
    "selfcontra_ros.stages.voting": "stage2_voting",
    "selfcontra_ros.stages.outliers": "stage3_outliers",
    "selfcontra_ros.window": "views",
    "selfcontra_ros.uncertainty": "views",
    "selfcontra_ros.projection": "views",
}


def _size(text: str) -> tuple[int, int]:
    width, height = (int(part) for part in text.lower().split("x"))
    return width, height


@contextlib.contextmanager
def _stage_timers(module: types.ModuleType, totals: dict[str, float]) -> Iterator[None]:
    """Wrap the stage functions referenced by ``module`` with timers adding seconds into ``totals``."""
    originals: dict[str, Any] = {}
    depth = [0]  # a stage function calling another wrapped one must not count twice

    def wrap(function: Callable[..., Any], stage: str) -> Callable[..., Any]:
        @functools.wraps(function)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if depth[0]:
                return function(*args, **kwargs)
            depth[0] += 1
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                totals[stage] = totals.get(stage, 0.0) + time.perf_counter() - start
                depth[0] -= 1

        return timed

    for name, value in vars(module).items():
        stage = _STAGE_OF_MODULE.get(getattr(value, "__module__", ""))
        if stage is not None and isinstance(value, types.FunctionType):
            originals[name] = value
    try:
        for name, value in originals.items():
            setattr(module, name, wrap(value, _STAGE_OF_MODULE[value.__module__]))
        yield
    finally:
        for name, value in originals.items():
            setattr(module, name, value)


def _labeler_params(window: int) -> LabelerParams:
    """The package defaults with ``window`` views and the usual delay of half a window."""
    return dataclasses.replace(LabelerParams(), window_size=window, label_delay=window // 2)


def run(
    window: int,
    frames: list[tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.float64], float]],
    camera: StereoCamera,
) -> dict[str, Any]:
    """Time SGBM and the labeler with ``window`` views on ``frames``; returns the JSON record."""
    import selfcontra_ros.labeler as labeler_module

    matcher = make_matcher(MatcherParams())
    labeler = Labeler(camera, _labeler_params(window))
    sgbm_s = 0.0
    label_s = 0.0
    labelled = 0
    steady = 0
    stages: dict[str, float] = {}
    with _stage_timers(labeler_module, stages):
        for index, (left, right, pose, stamp) in enumerate(frames):
            start = time.perf_counter()
            disparity = matcher.compute(left, right, with_right=False).left
            sgbm_s += time.perf_counter() - start
            full = len(labeler.window) >= window
            if full and steady == 0:
                stages.clear()  # only steady-state calls count
            start = time.perf_counter()
            ready = len(labeler.add_view(disparity, pose, stamp=stamp, key=index, image=left))
            elapsed = time.perf_counter() - start
            labelled += ready
            if full:
                label_s += elapsed
                steady += 1
        stages = dict(stages)  # the steady-state split; flush below is not part of it
        labelled += len(labeler.flush())
    if steady == 0 or labelled == 0:
        raise RuntimeError(f"window {window}: {len(frames)} frames never fill the window; use more --frames")
    stages["other"] = max(label_s - sum(stages.values()), 0.0)
    sgbm_ms = 1000.0 * sgbm_s / len(frames)
    label_ms = 1000.0 * label_s / steady
    return {
        "window": window,
        "frames": len(frames),
        "labelled": labelled,
        "steady_views": steady,
        "skipped": labeler.skipped_views,
        "sgbm_ms": round(sgbm_ms, 2),
        "label_ms": round(label_ms, 2),
        "ratio": round(label_ms / sgbm_ms, 2),
        "stages_ms": {name: round(1000.0 * seconds / steady, 2) for name, seconds in stages.items()},
    }


def _warm_up(scene_name: str, seed: int) -> None:
    """Run the labeler on a few tiny frames so that every numba kernel is compiled or loaded before timing."""
    scene = make_scene(scene_name, seed, 160, 48, frames=4)
    matcher = make_matcher(MatcherParams())
    labeler = Labeler(scene.camera, dataclasses.replace(LabelerParams(), window_size=3, label_delay=1))
    for k in range(4):
        frame = scene.render(k)
        labeler.add_view(matcher.compute(frame.left, frame.right, with_right=False).left, frame.pose, stamp=frame.stamp)


def main(argv: list[str] | None = None) -> int:
    """Render the frames once, then time each window size; prints a table and one JSON line per window."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--window", type=int, default=None, help="window size (default: 10 and 20)")
    parser.add_argument("--frames", type=int, default=30, help="frames to render and label (default 30)")
    parser.add_argument("--size", type=_size, default=(1241, 376), help="image size WxH (default 1241x376)")
    parser.add_argument("--scene", choices=SCENES, default="street")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    windows = (args.window,) if args.window else DEFAULT_WINDOWS
    width, height = args.size

    _warm_up(args.scene, args.seed)
    scene = make_scene(args.scene, args.seed, width, height, frames=args.frames)
    start = time.perf_counter()
    rendered = [scene.render(k) for k in range(args.frames)]
    frames = [(f.left, f.right, f.pose, f.stamp) for f in rendered]
    print(f"rendered {args.frames} {args.scene} frames at {width}x{height} in {time.perf_counter() - start:.1f} s")

    records = [run(window, frames, scene.camera) for window in windows]
    for record in records:
        stages = ", ".join(f"{k} {v:.1f}" for k, v in record["stages_ms"].items())
        print(
            f"window {record['window']:3d}: SGBM {record['sgbm_ms']:.1f} ms/frame, labeling {record['label_ms']:.1f} "
            f"ms/arriving view ({record['steady_views']} timed), ratio {record['ratio']:.2f}; stages (ms): {stages}"
        )
    for record in records:
        keys = ("window", "sgbm_ms", "label_ms", "ratio", "stages_ms")
        print(json.dumps({key: record[key] for key in keys}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
