"""Where the labeler's time goes, per stage, at KITTI size (1241x376) and window sizes 10 and 20.

Renders a synthetic street, computes the StereoSGBM disparities once, then
feeds them to the :class:`~selfcontra_ros.labeler.Labeler` and times every
stage function the labeler calls (``make_view``, Stage 1 ``update_support``,
Stage 2 ``consistency_voting``, Stage 3 ``trivial_outliers``,
``augmented_depth``, ``outlier_negatives``). Times are per arriving view in
steady state: only the ``add_view`` calls made once the window is full and a
view is labelled per call count, so warm-up (short windows) and ``flush`` do
not dilute them. Numba kernels are compiled (or loaded from cache) on a
warm-up run at a small size first, so compilation is not timed.

Prints one table per window size (wall milliseconds per view and share, and
process CPU milliseconds of all threads, which other processes on the same
cores disturb less than wall time), then one JSON line per window::

    {"window": 10, "sgbm_ms": ..., "per_view_ms": ..., "ratio": ..., "stages_ms": {...}, "stages_cpu_ms": {...}}

``--cprofile N`` adds the N most expensive functions (cumulative time) of the
steady-state calls, from :mod:`cProfile`.

Usage: ``python bench/profile_labeler.py [--window N] [--frames F] [--size WxH] [--cprofile N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import dataclasses
import functools
import io
import json
import pstats
import sys
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

import selfcontra_ros.labeler as labeler_module
from selfcontra_ros.datasets.synthetic import SCENES, make_scene
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.labeler import Labeler, LabelerParams
from selfcontra_ros.matching.base import MatcherParams, make_matcher

DEFAULT_WINDOWS = (10, 20)

#: Labeler-module names timed, with the stage each belongs to (table rows, in pipeline order).
STAGE_FUNCTIONS = {
    "make_view": "views (depth, u)",
    "update_support": "stage 1 support",
    "consistency_voting": "stage 2 voting",
    "trivial_outliers": "stage 3 trivial",
    "augmented_depth": "stage 3 augmented depth",
    "outlier_negatives": "stage 3 negatives",
    "support_count": "support count",
}

Frames = list[tuple[NDArray[np.float32], NDArray[np.float64], float]]


def _size(text: str) -> tuple[int, int]:
    width, height = (int(part) for part in text.lower().split("x"))
    return width, height


@contextlib.contextmanager
def _timed_functions(module: types.ModuleType, totals: dict[str, float], cpu: dict[str, float]) -> Iterator[None]:
    """Replace the timed functions in ``module``'s namespace by wrappers adding wall seconds into ``totals``
    and process CPU seconds (all threads) into ``cpu``."""
    originals = {name: getattr(module, name) for name in STAGE_FUNCTIONS}

    def wrap(function: Callable[..., Any], name: str) -> Callable[..., Any]:
        @functools.wraps(function)
        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            start_cpu = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                totals[name] = totals.get(name, 0.0) + time.perf_counter() - start
                cpu[name] = cpu.get(name, 0.0) + time.process_time() - start_cpu

        return timed

    try:
        for name, function in originals.items():
            setattr(module, name, wrap(function, name))
        yield
    finally:
        for name, function in originals.items():
            setattr(module, name, function)


def _params(window: int) -> LabelerParams:
    """The package defaults with ``window`` views and a delay of half a window."""
    return dataclasses.replace(LabelerParams(), window_size=window, label_delay=window // 2)


def profile_window(
    window: int, frames: Frames, camera: StereoCamera, profiler: cProfile.Profile | None
) -> dict[str, Any]:
    """Per-stage milliseconds per arriving view in steady state for one window size."""
    labeler = Labeler(camera, _params(window))
    totals: dict[str, float] = {}
    cpu: dict[str, float] = {}
    steady_s = 0.0
    steady_views = 0
    with _timed_functions(labeler_module, totals, cpu):
        for index, (disparity, pose, stamp) in enumerate(frames):
            steady = len(labeler.window) >= window
            if steady:
                # Only steady-state calls count: reset the totals the warm-up accumulated.
                if steady_views == 0:
                    totals.clear()
                    cpu.clear()
                if profiler is not None:
                    profiler.enable()
            start = time.perf_counter()
            labelled = labeler.add_view(disparity, pose, stamp=stamp, key=index)
            elapsed = time.perf_counter() - start
            if steady:
                if profiler is not None:
                    profiler.disable()
                steady_s += elapsed
                steady_views += 1
                if len(labelled) != 1:
                    raise RuntimeError(f"window {window}: a steady-state view labelled {len(labelled)} views, not 1")
    if steady_views == 0:
        raise RuntimeError(f"window {window}: {len(frames)} frames never fill the window; use more --frames")
    stages = {name: 1000.0 * seconds / steady_views for name, seconds in totals.items()}
    stages["other"] = max(1000.0 * steady_s / steady_views - sum(stages.values()), 0.0)
    stages_cpu = {name: 1000.0 * seconds / steady_views for name, seconds in cpu.items()}
    return {
        "window": window,
        "views": steady_views,
        "per_view_ms": 1000.0 * steady_s / steady_views,
        "stages": stages,
        "stages_cpu": stages_cpu,
    }


def main(argv: list[str] | None = None) -> int:
    """Render, match once, profile each window size; prints tables and JSON lines."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--window", type=int, default=None, help="window size (default: 10 and 20)")
    parser.add_argument("--frames", type=int, default=None, help="frames (default: largest window + 6)")
    parser.add_argument("--size", type=_size, default=(1241, 376), help="image size WxH (default 1241x376)")
    parser.add_argument("--scene", choices=SCENES, default="street")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cprofile", type=int, default=0, metavar="N", help="print the N top cProfile entries")
    args = parser.parse_args(argv)
    windows = (args.window,) if args.window else DEFAULT_WINDOWS
    n_frames = args.frames if args.frames else max(windows) + 6
    width, height = args.size

    # Compile (or load cached) kernels on a tiny run so that compilation never lands in a timed stage.
    warm = make_scene(args.scene, args.seed, 160, 48, frames=4)
    warm_matcher = make_matcher(MatcherParams())
    warm_labeler = Labeler(warm.camera, _params(3))
    for k in range(4):
        f = warm.render(k)
        warm_labeler.add_view(warm_matcher.compute(f.left, f.right, with_right=False).left, f.pose, stamp=f.stamp)
    warm_labeler.flush()

    scene = make_scene(args.scene, args.seed, width, height, frames=n_frames)
    matcher = make_matcher(MatcherParams())
    frames: Frames = []
    sgbm_s = 0.0
    for k in range(n_frames):
        f = scene.render(k)
        start = time.perf_counter()
        disparity = matcher.compute(f.left, f.right, with_right=False).left
        sgbm_s += time.perf_counter() - start
        frames.append((disparity, f.pose, f.stamp))
    sgbm_ms = 1000.0 * sgbm_s / n_frames
    print(f"{n_frames} {args.scene} frames at {width}x{height}; StereoSGBM {sgbm_ms:.1f} ms/frame")

    records = []
    for window in windows:
        profiler = cProfile.Profile() if args.cprofile else None
        record = profile_window(window, frames, scene.camera, profiler)
        print(f"\nwindow {window}: {record['per_view_ms']:.1f} ms per arriving view ({record['views']} views timed)")
        print(f"  {'stage':28s} {'ms/view':>9s} {'share':>7s} {'cpu ms/view':>12s}")
        for name, label in {**STAGE_FUNCTIONS, "other": "other (labeler glue)"}.items():
            ms = record["stages"].get(name, 0.0)
            cpu_ms = record["stages_cpu"].get(name)
            cpu_text = f"{cpu_ms:12.1f}" if cpu_ms is not None else f"{'':12s}"
            print(f"  {label:28s} {ms:9.1f} {100.0 * ms / record['per_view_ms']:6.1f}% {cpu_text}")
        if profiler is not None:
            text = io.StringIO()
            pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(args.cprofile)
            print(text.getvalue())
        records.append(record)
    for record in records:
        line = {
            "window": record["window"],
            "sgbm_ms": round(sgbm_ms, 2),
            "per_view_ms": round(record["per_view_ms"], 2),
            "ratio": round(record["per_view_ms"] / sgbm_ms, 2),
            "stages_ms": {name: round(ms, 2) for name, ms in record["stages"].items()},
            "stages_cpu_ms": {name: round(ms, 2) for name, ms in record["stages_cpu"].items()},
        }
        print(json.dumps(line))
    return 0


if __name__ == "__main__":
    sys.exit(main())
