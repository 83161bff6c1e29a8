"""Accuracy of the stereo visual odometry: KITTI metrics on KITTI 06 and on synthetic street, orbit and highway.

Runs :class:`~selfcontra_ros.odometry.stereo_vo.StereoOdometry` (package
defaults, or ``--set name=value`` overrides of
:class:`~selfcontra_ros.odometry.stereo_vo.VOParams`) over

* the real KITTI odometry 06 sample (``--kitti``, frames 0-50), and
* ``--scenes`` x ``--seeds`` synthetic sequences (``--frames`` frames at
  ``--size``, KITTI size by default), rendered in this process so that the
  vehicles' pixels are known (``SyntheticFrame.moving``),

and prints one row per sequence:

* the KITTI odometry metrics (:mod:`selfcontra_ros.odometry.metrics`, the
  devkit's sub-sequence definition over 5-50 m, every frame a start):
  translation (%) and rotation (deg/m) error;
* the scale error: estimated path length / true path length - 1 (%);
* reliable frames, and among them the *bad* ones: frames whose motion from
  the previous frame is off by more than 2 % of its true length (the issue's
  acceptance rule); the worst per-frame error of a reliable frame;
* the share of stereo features and of pose inliers on moving vehicles
  (highway; the odometry must not use them);
* the disparity offset the odometry applied (``VOParams.estimate_disparity_offset``:
  a sequence whose estimate ends significantly away from 0 is run a second
  time with it, as ``selfcontra odometry`` does);
* the odometry's time per frame (images in memory, rendering excluded;
  every pass).

``--right-shift PX`` moves every right image's content PX to the right, so
every disparity is PX smaller: a rectification offset, to measure what one
costs and how much of it the estimate takes back (``--right-shift-method``:
bilinear, as the earlier rounds, or fourier, the same shift at every
frequency).

Then per scene the mean, standard deviation and worst of each figure, and
last one JSON line with all of it. Rendered frames are kept in ``--cache``
(``.npz``, no pickle) so that parameter comparisons render once.
Examples::

    python bench/odometry_accuracy.py --cache /tmp/vo_cache
    python bench/odometry_accuracy.py --scenes highway --seeds 6-10 --cache /tmp/vo_cache
    python bench/odometry_accuracy.py --scenes highway --seeds 1-5 --set subpixel=lk --cache /tmp/vo_cache
    python bench/odometry_accuracy.py --scenes highway --seeds 1-40 --kitti '' --oracle stereo --cache /tmp/vo_cache

``--oracle`` (synthetic only, a diagnosis) takes stereo features away by the
ground truth before the odometry sees them: those on moving vehicles
(``static``), those with a gross disparity error (``stereo``), or both;
see :class:`OracleOdometry`.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from selfcontra_ros.cli import parse_seeds, parse_size
from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.geometry import StereoCamera
from selfcontra_ros.odometry.metrics import evaluate_odometry, path_lengths
from selfcontra_ros.odometry.run import OnlineOdometry, final_poses, run_passes
from selfcontra_ros.odometry.stereo_vo import StereoCache, StereoOdometry, VOParams, _Features

DEFAULT_KITTI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "kitti_odometry"
#: A reliable frame whose motion from the previous frame is off by more than this share of its length is bad.
BAD_STEP = 0.02
#: ``--oracle`` choices: which stereo features the ground truth takes away before the odometry sees them.
ORACLES = ("none", "static", "stereo", "both")
#: The stereo oracle drops a feature whose disparity is further than this (px) from every true one in 3x3 pixels.
GROSS_STEREO_PX = 0.7

Frames = list[tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.bool_] | None]]


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``name=value`` pairs as VOParams keyword arguments, each converted to the field's type (a grid: ``3x8``)."""
    fields = {f.name: f for f in dataclasses.fields(VOParams)}
    defaults = VOParams()
    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            raise SystemExit(f"--set expects NAME=VALUE with NAME one of {', '.join(fields)}, got {item!r}")
        kind = type(getattr(defaults, name))
        if kind is bool:
            out[name] = value.lower() in ("1", "true", "yes")
        elif kind is tuple:  # influence_grid=3x8
            out[name] = tuple(int(v) for v in value.split("x"))
        else:
            out[name] = kind(value)
    return out


def synthetic_frames(
    scene: str, seed: int, frames: int, size: tuple[int, int], cache: Path | None
) -> tuple[StereoCamera, Frames, NDArray[np.float64]]:
    """Camera, ``(left, right, moving)`` per frame and true poses of a synthetic sequence (cached as .npz)."""
    built = make_scene(scene, seed, size[0], size[1], frames=frames)
    path = None if cache is None else cache / f"{scene}_{seed}_{frames}_{size[0]}x{size[1]}.npz"
    if path is not None and path.exists():
        with np.load(path, allow_pickle=False) as data:
            # Each key once: an NpzFile reads (and decompresses) the whole array at every access, and a frame
            # sliced from it keeps that copy alive (300 frames took 24 GiB).
            left, right, moving_all = data["left"], data["right"], data["moving"]
        moving = moving_all if moving_all.size else None
        out: Frames = [(left[k], right[k], None if moving is None else moving[k]) for k in range(frames)]
        return built.camera, out, built.poses(frames)
    out = []
    for k in range(frames):
        f = built.render(k)
        out.append((f.left, f.right, f.moving))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        moving_all = np.stack([m for _, _, m in out]) if out[0][2] is not None else np.zeros(0, bool)
        np.savez_compressed(
            path, left=np.stack([a for a, _, _ in out]), right=np.stack([b for _, b, _ in out]), moving=moving_all
        )
    return built.camera, out, built.poses(frames)


def true_disparities(
    scene: str, seed: int, frames: int, size: tuple[int, int], cache: Path | None
) -> NDArray[np.float32]:
    """The true left disparity (frames, H, W; NaN where nothing is hit) of a synthetic sequence, cached as .npz."""
    path = None if cache is None else cache / f"{scene}_{seed}_{frames}_{size[0]}x{size[1]}_disparity.npz"
    if path is not None and path.exists():
        with np.load(path, allow_pickle=False) as data:
            return np.asarray(data["disparity"], dtype=np.float32)
    built = make_scene(scene, seed, size[0], size[1], frames=frames)
    out = np.stack([built.render(k).disparity for k in range(frames)]).astype(np.float32)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, disparity=out)
    return out


class OracleOdometry(StereoOdometry):
    """The odometry with some stereo features taken away by the ground truth (a diagnosis, not a method).

    ``oracle``: ``static`` drops features on moving vehicles (their pixels
    dilated by 4); ``stereo`` drops features whose disparity is further than
    :data:`GROSS_STEREO_PX` from every true disparity of the 3x3 pixels around
    them (gross stereo errors: a window that took a neighbour's depth at an
    edge, a wrong match); ``both`` does both. Set :attr:`moving` and
    :attr:`disparity` to the frame's truth before each :meth:`add`. Only each
    frame's detected features are checked; a matched feature's stereo,
    measured again where its track points to, is not.
    """

    def __init__(
        self, camera: StereoCamera, params: VOParams, oracle: str, stereo_cache: StereoCache | None = None
    ) -> None:
        super().__init__(camera, params, stereo_cache=stereo_cache)
        self.oracle = oracle
        self.moving: NDArray[np.bool_] | None = None
        self.disparity: NDArray[np.float32] | None = None
        self.offered = self.dropped = 0

    def _stereo(self, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> tuple[_Features, int]:
        features, detected = super()._stereo(left, right)
        if self.oracle == "none" or len(features.uv) == 0:
            return features, detected
        h, w = left.shape[:2]
        uv = np.rint(features.uv).astype(np.int64)
        rows, cols = np.clip(uv[:, 1], 1, h - 2), np.clip(uv[:, 0], 1, w - 2)
        keep = np.ones(len(uv), dtype=bool)
        if self.oracle in ("static", "both") and self.moving is not None:
            keep &= ~ndimage.binary_dilation(self.moving, iterations=4)[rows, cols]
        if self.oracle in ("stereo", "both") and self.disparity is not None:
            near = np.stack([self.disparity[rows + dr, cols + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], axis=1)
            off = np.abs(near - features.disparity[:, None])
            keep &= np.nan_to_num(off, nan=np.inf).min(axis=1) <= GROSS_STEREO_PX
        self.offered += len(keep)
        self.dropped += int((~keep).sum())
        straddle = features.straddle[keep] if features.straddle.size else features.straddle
        return _Features(features.uv[keep], features.disparity[keep], features.descriptors[keep],
                         features.points[keep], straddle=straddle), detected  # fmt: skip


def kitti_frames(root: Path) -> tuple[StereoCamera, Frames, NDArray[np.float64]]:
    """Camera, frames and ground-truth poses of a KITTI odometry sequence folder."""
    seq = open_sequence(root)
    if seq.poses is None:
        raise SystemExit(f"{root} has no ground-truth poses")
    frames: Frames = [(f.left, f.right, None) for f in seq]
    return seq.camera, frames, seq.poses


def step_errors(estimated: NDArray[np.float64], truth: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per frame (from 1): |error of the motion from the previous frame| / its true length (0 for frame 0)."""
    d_gt = np.linalg.inv(truth[:-1]) @ truth[1:]
    d_est = np.linalg.inv(estimated[:-1]) @ estimated[1:]
    error = np.linalg.inv(d_gt) @ d_est
    length = np.maximum(np.linalg.norm(d_gt[:, :3, 3], axis=1), 1e-9)
    return np.concatenate([[0.0], np.linalg.norm(error[:, :3, 3], axis=1) / length])


def run_sequence(
    name: str,
    camera: StereoCamera,
    frames: Frames,
    truth: NDArray[np.float64],
    params: VOParams,
    oracle: str = "none",
    disparities: NDArray[np.float32] | None = None,
) -> dict[str, Any]:
    """Run the odometry over one sequence and measure it against the true poses (``oracle``: see OracleOdometry).

    As :func:`~selfcontra_ros.odometry.run.estimate_poses` does, a sequence whose disparity offset estimate
    ended away from ``params.disparity_offset_px`` is run again (:func:`~selfcontra_ros.odometry.run.next_pass_params`:
    estimating around it, then with the second estimate applied), reusing the first pass's stereo
    matching; the time per frame counts every pass.
    """
    counts: dict[str, int] = {}
    median_disparity: list[float] = []

    elapsed = 0.0  # every pass's odometry time, seconds

    def run_pass(run_params: VOParams, cache: StereoCache | None) -> OracleOdometry:
        nonlocal elapsed
        vo = OracleOdometry(camera, run_params, oracle, cache)
        counts.update(moving_features=0, moving_inliers=0, features=0, inliers=0)
        median_disparity.clear()
        for k, (left, right, moving) in enumerate(frames):
            vo.moving = moving
            vo.disparity = None if disparities is None else disparities[k]
            started = time.perf_counter()
            result = vo.add(left, right)
            elapsed += time.perf_counter() - started
            d = vo.last_inlier_disparity
            median_disparity.append(float(np.median(d)) if len(d) else math.nan)
            if moving is not None and result.quality.reliable and len(vo.last_inliers):
                uv = np.rint(vo.last_inliers).astype(np.int64)
                uv[:, 0] = np.clip(uv[:, 0], 0, camera.width - 1)
                uv[:, 1] = np.clip(uv[:, 1], 0, camera.height - 1)
                counts["moving_inliers"] += int(moving[uv[:, 1], uv[:, 0]].sum())
                counts["inliers"] += len(uv)
            if moving is not None and len(vo.last_features):
                fuv = np.rint(vo.last_features).astype(np.int64)
                counts["moving_features"] += int(moving[fuv[:, 1], fuv[:, 0]].sum())
                counts["features"] += len(fuv)
        return vo

    runs = run_passes(run_pass, params)  # as estimate_poses runs them
    vo, passes = runs[-1], len(runs)
    # The first pass's offset; the later ones estimate again around it (docs/visual_odometry.md).
    first_offset = runs[0].disparity_offset
    # The last pass that estimated the offset (the first when none did: no windows, NaN).
    estimating = next((r for r in reversed(runs) if r.params.estimate_disparity_offset), runs[0])
    estimate, error, windows = estimating.offset_estimate()
    moving_features, moving_inliers = counts["moving_features"], counts["moving_inliers"]
    features, inliers = counts["features"], counts["inliers"]
    poses, qualities = final_poses(vo)  # as estimate_poses returns them
    reliable = np.array([q.reliable for q in qualities])
    metrics = evaluate_odometry(poses, truth)
    steps = step_errors(poses, truth)
    true_length = float(path_lengths(truth)[-1])
    est_length = float(path_lengths(poses)[-1])
    bad = reliable & (steps > BAD_STEP)
    bad[0] = False
    # Per frame: the frame-to-frame step (before the window adjustment) against the truth, signed.
    true_steps = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    f2f = np.array([q.translation_m for q in vo.qualities[1:]])
    measured = np.array([q.inliers > 0 and not math.isnan(q.reprojection_error_px) for q in vo.qualities[1:]])
    return {
        "sequence": name,
        "frames": len(frames),
        "path_m": true_length,
        "translation_pct": metrics.translation_error_pct,
        "rotation_deg_per_m": metrics.rotation_error_deg_per_m,
        "scale_pct": 100.0 * (est_length / true_length - 1.0),
        "reliable": int(reliable.sum()),
        "bad_reliable": int(bad.sum()),
        "worst_reliable_step_pct": float(100.0 * steps[1:][reliable[1:]].max()) if reliable[1:].any() else math.nan,
        "moving_feature_pct": 100.0 * moving_features / features if features else math.nan,
        "moving_inlier_pct": 100.0 * moving_inliers / inliers if inliers else math.nan,
        "ms_per_frame": 1000.0 * elapsed / len(frames),
        "statuses": sorted({q.status for q in qualities}),
        "oracle": oracle,
        "disparity_offset_px": vo.disparity_offset,
        "offset_estimate_px": estimate,
        "first_pass_offset_px": first_offset,
        "offset_error_px": error,
        "offset_windows": windows,
        "passes": passes,
        "oracle_dropped_pct": 100.0 * vo.dropped / vo.offered if vo.offered else 0.0,
        "per_frame": {
            "f2f_scale_error_pct": [float(v) for v in 100.0 * (f2f / np.maximum(true_steps, 1e-9) - 1.0)],
            "measured": [bool(v) for v in measured],
            "median_inlier_disparity": median_disparity[1:],
            "step_error_pct": [float(v) for v in 100.0 * steps[1:]],
            "reliable": [bool(v) for v in reliable[1:]],
            "scale_bias_pct": [q.scale_bias_pct for q in vo.qualities[1:]],
        },
    }


DISPARITY_BINS = (0.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 1000.0)


def stereo_bias(
    scenes: list[str], seeds: list[int], size: tuple[int, int], methods: list[str], right_shift: float = 0.0
) -> dict[str, Any]:
    """Disparity error of the odometry's stereo features against the ground truth, per sub-pixel method.

    Every 6th frame of 30 of each sequence is rendered; features on a smooth
    static surface (ground-truth disparity range < 0.25 px + 10 % within
    11x11 pixels) are compared with the bilinear ground-truth disparity. Per
    disparity bin: mean and standard deviation of the error (px) and the
    depth bias it causes (mean of ``d_gt / d - 1``, %); overall: the share
    of right sub-pixel phases within 0.2 px of an integer (0.4 without
    pixel locking). ``right_shift``: as ``--right-shift`` (every right image moved, disparities smaller).
    """
    import cv2

    out: dict[str, Any] = {}
    for method in methods:
        errors, truths, phases = [], [], []
        for scene in scenes:
            for seed in seeds:
                built = make_scene(scene, seed, size[0], size[1], frames=30)
                vo = StereoOdometry(built.camera, VOParams(subpixel=method))
                for k in range(0, 30, 6):
                    f = built.render(k)
                    ((_, right, _),) = shift_right_images([(f.left, f.right, None)], right_shift)
                    feats, _ = vo._stereo(f.left, right)
                    gt = np.nan_to_num(f.disparity, nan=-1e3).astype(np.float32)
                    u, v = feats.uv[:, 0].astype(np.float32), feats.uv[:, 1].astype(np.float32)
                    d_gt = cv2.remap(gt, u.reshape(-1, 1), v.reshape(-1, 1), cv2.INTER_LINEAR).ravel()
                    high, low = cv2.dilate(gt, np.ones((11, 11))), cv2.erode(gt, np.ones((11, 11)))
                    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
                    smooth = (high[vi, ui] - low[vi, ui] < 0.25 + 0.1 * np.maximum(gt[vi, ui], 0)) & (low[vi, ui] > 0)
                    if f.moving is not None:
                        smooth &= ~f.moving[vi, ui]
                    errors.append((feats.disparity - d_gt)[smooth])
                    truths.append(d_gt[smooth])
                    phases.append(((feats.uv[:, 0] - feats.disparity) % 1.0)[smooth])
        e, d, ph = np.concatenate(errors), np.concatenate(truths), np.concatenate(phases)
        gross = np.abs(e) >= 2.0
        bins = []
        for lo, hi in itertools.pairwise(DISPARITY_BINS):
            m = (d >= lo) & (d < hi) & ~gross
            if m.sum() < 10:
                continue
            bias = float(100.0 * np.mean(d[m] / (d[m] + e[m]) - 1))
            bins.append({"disparity": [lo, hi], "features": int(m.sum()), "mean_px": float(e[m].mean()),
                         "std_px": float(e[m].std()), "depth_bias_pct": bias})  # fmt: skip
        near_integer = np.minimum(ph, 1.0 - ph) < 0.2
        out[method] = {"features": int(e.size), "gross_pct": float(100.0 * gross.mean()),
                       "mean_px": float(e[~gross].mean()), "near_integer_share": float(near_integer[~gross].mean()),
                       "bins": bins}  # fmt: skip
        print(f"subpixel={method}: {e.size} features, {100 * gross.mean():.1f} % off by >= 2 px, mean error "
              f"{e[~gross].mean():+.3f} px, sub-pixel phases within 0.2 px of an integer "
              f"{near_integer[~gross].mean():.2f} (0.40 unbiased)")  # fmt: skip
        print("| disparity px | features | mean error px | std px | depth bias % |")
        print("|---|---|---|---|---|")
        for b in bins:
            lo, hi = b["disparity"]
            print(f"| {lo:g}-{hi:g} | {b['features']} | {b['mean_px']:+.3f} | {b['std_px']:.3f} | "
                  f"{b['depth_bias_pct']:+.2f} |")  # fmt: skip
    return out


COLUMNS = (
    ("translation_pct", "transl. %", "{:.2f}"),
    ("rotation_deg_per_m", "rot. deg/m", "{:.4f}"),
    ("scale_pct", "scale %", "{:+.2f}"),
    ("reliable", "reliable", "{:d}"),
    ("bad_reliable", "bad rel.", "{:d}"),
    ("worst_reliable_step_pct", "worst step %", "{:.2f}"),
    ("moving_feature_pct", "moving feat. %", "{:.1f}"),
    ("moving_inlier_pct", "moving inl. %", "{:.1f}"),
    ("disparity_offset_px", "offset px", "{:+.3f}"),
    ("ms_per_frame", "ms/frame", "{:.0f}"),
)


def run_online(
    name: str, camera: StereoCamera, frames: Frames, truth: NDArray[np.float64], params: VOParams
) -> dict[str, Any]:
    """The labeler node's odometry (:class:`OnlineOdometry`: one pass, step lengths smoothed with
    ``smoothing_lag_frames`` frames after each, ``isolated`` and ``uncertain`` decided online) over one
    sequence.

    Bad reliable frames as in :func:`run_sequence`; the first frame is not counted as reliable. Also the
    time of each frame's :meth:`OnlineOdometry.add` (95th percentile and worst): the stalls the node sees.
    """
    online = OnlineOdometry(camera, params)
    decisions = []
    latency = []  # per frame, seconds: what the node's odometry thread spends on it (its stalls)
    for k, (left, right, _) in enumerate(frames):
        started = time.perf_counter()
        decisions += online.add(k, left, right)
        latency.append(time.perf_counter() - started)
    started = time.perf_counter()
    decisions += online.finish()
    elapsed = sum(latency) + time.perf_counter() - started
    poses = np.stack([d.chained for d in decisions])
    reliable = np.array([d.pose is not None for d in decisions])
    reliable[0] = False
    steps = step_errors(poses, truth)
    return {
        "sequence": name,
        "frames": len(frames),
        "translation_pct": evaluate_odometry(poses, truth).translation_error_pct,
        "reliable": int(reliable.sum()),
        "bad_reliable": int((reliable & (steps > BAD_STEP)).sum()),
        "ms_per_frame": 1000.0 * elapsed / len(frames),
        "p95_frame_ms": 1000.0 * float(np.percentile(latency, 95)),
        "worst_frame_ms": 1000.0 * max(latency),
    }


def _cell(value: Any, fmt: str) -> str:
    if isinstance(value, float) and math.isnan(value):
        return "-"
    return fmt.format(value)


def print_table(rows: list[dict[str, Any]]) -> None:
    """One row per sequence (markdown)."""
    print("| sequence | frames | path m | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 3) + "|")
    for r in rows:
        cells = [_cell(r[key], fmt) for key, _, fmt in COLUMNS]
        print(f"| {r['sequence']} | {r['frames']} | {r['path_m']:.1f} | " + " | ".join(cells) + " |")


def scale_by_disparity(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Measured frames binned by their inliers' median disparity: mean and mean absolute f2f scale error."""
    d, e, err, rel = [], [], [], []
    for r in rows:
        f = r["per_frame"]
        for k, ok in enumerate(f["measured"]):
            if ok and not math.isnan(f["median_inlier_disparity"][k]):
                d.append(f["median_inlier_disparity"][k])
                e.append(f["f2f_scale_error_pct"][k])
                err.append(f["step_error_pct"][k])
                rel.append(f["reliable"][k])
    if not d:
        return []
    da, ea, erra, rela = np.array(d), np.array(e), np.array(err), np.array(rel)
    out = []
    for lo, hi in itertools.pairwise((0.0, 2.0, 3.0, 4.0, 6.0, 10.0, 20.0, 1000.0)):
        m = (da >= lo) & (da < hi)
        if m.any():
            out.append({"disparity": [lo, hi], "frames": int(m.sum()), "mean_pct": float(ea[m].mean()),
                        "mean_abs_pct": float(np.abs(ea[m]).mean()), "over_2pct": int((erra[m] > 100 * BAD_STEP).sum()),
                        "reliable": int(rela[m].sum())})  # fmt: skip
    return out


def summarise(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per scene (the sequence name before '/'): mean, standard deviation and worst of the error figures."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r["sequence"].split("/")[0], []).append(r)
    out: dict[str, dict[str, Any]] = {}
    for scene, members in groups.items():
        entry: dict[str, Any] = {"sequences": len(members)}
        for key in ("translation_pct", "rotation_deg_per_m", "worst_reliable_step_pct", "ms_per_frame"):
            values = np.array([m[key] for m in members], dtype=np.float64)
            entry[key] = {"mean": float(np.nanmean(values)), "std": float(np.nanstd(values)),
                          "worst": float(np.nanmax(values))}  # fmt: skip
        scale = np.array([m["scale_pct"] for m in members])
        entry["scale_pct"] = {"mean": float(scale.mean()), "std": float(scale.std()),
                              "worst": float(scale[np.argmax(np.abs(scale))])}  # fmt: skip
        entry["bad_reliable"] = int(sum(m["bad_reliable"] for m in members))
        entry["unreliable"] = int(sum(m["frames"] - m["reliable"] for m in members))
        out[scene] = entry
    return out


Sequence = tuple[str, StereoCamera, Frames, NDArray[np.float64], NDArray[np.float32] | None]


def shift_right_images(frames: Frames, shift_px: float, method: str = "bilinear") -> Frames:
    """The frames with every right image's content moved ``shift_px`` to the right: every disparity
    ``shift_px`` smaller, as a rectification off by that much (``--right-shift``).

    ``bilinear`` (edges repeated) is the earlier rounds' shift; bilinear interpolation moves fine texture by
    less than the shift (its phase lags at high frequencies) and blurs it. ``fourier`` moves each row by a
    phase ramp of its spectrum (edges reflected over 64 px, rounded back to uint8): the same shift at every
    frequency.
    """
    if shift_px == 0.0:
        return frames
    if method == "fourier":
        pad = 64
        out: Frames = []
        for left, right, moving in frames:
            rows = np.pad(right.astype(np.float64), ((0, 0), (pad, pad)), mode="reflect")
            spectrum = np.fft.rfft(rows, axis=1) * np.exp(-2j * np.pi * np.fft.rfftfreq(rows.shape[1]) * shift_px)
            moved = np.fft.irfft(spectrum, n=rows.shape[1], axis=1)[:, pad:-pad]
            out.append((left, np.clip(np.rint(moved), 0, 255).astype(np.uint8), moving))
        return out
    import cv2

    matrix = np.array([[1.0, 0.0, shift_px], [0.0, 1.0, 0.0]])
    return [
        (left, cv2.warpAffine(right, matrix, right.shape[::-1], flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE), moving)
        for left, right, moving in frames
    ]  # fmt: skip


def _sequences(args: argparse.Namespace) -> Iterator[Sequence]:
    """Name, camera, frames, true poses and (stereo oracle only) true disparities of each sequence."""
    if args.kitti is not None and Path(args.kitti).exists():
        camera, frames, truth = kitti_frames(Path(args.kitti))
        yield "kitti06", camera, shift_right_images(frames, args.right_shift, args.right_shift_method), truth, None
    elif args.kitti is not None:
        print(f"(no KITTI sample at {args.kitti}: skipped)", file=sys.stderr)
    for scene in args.scenes:
        for seed in args.seeds:
            camera, frames, truth = synthetic_frames(scene, seed, args.frames, args.size, args.cache)
            disparities = None
            if args.oracle in ("stereo", "both"):
                disparities = true_disparities(scene, seed, args.frames, args.size, args.cache)
            yield (
                f"{scene}/{seed}",
                camera,
                shift_right_images(frames, args.right_shift, args.right_shift_method),
                truth,
                disparities,
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kitti", default=str(DEFAULT_KITTI), help="KITTI odometry sequence with poses ('' skips it)")
    parser.add_argument(
        "--scenes", nargs="*", default=["street", "orbit", "highway"], help="synthetic scenes (none: KITTI only)"
    )
    parser.add_argument("--seeds", type=parse_seeds, default=parse_seeds("1-5"))
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--size", type=parse_size, default=(1226, 370), help="synthetic image size WxH")
    parser.add_argument("--cache", type=Path, default=None, help="folder for rendered frames (.npz)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a VOParams override")
    parser.add_argument(
        "--right-shift-method", choices=("bilinear", "fourier"), default="bilinear",
        help="how --right-shift moves the right images (see shift_right_images)",
    )  # fmt: skip
    parser.add_argument(
        "--right-shift", type=float, default=0.0, metavar="PX",
        help="move every right image's content PX to the right (disparities PX smaller: a rectification offset)",
    )  # fmt: skip
    parser.add_argument(
        "--stereo-bias", nargs="+", metavar="METHOD", help="only measure the stereo features' disparity error "
        "against ground truth for these sub-pixel methods (lk, parabola, none)"
    )  # fmt: skip
    parser.add_argument(
        "--oracle", choices=ORACLES, default="none", help="take features away by the ground truth before the "
        "odometry sees them (synthetic only): static = not on moving vehicles, stereo = no gross disparity error"
    )  # fmt: skip
    parser.add_argument(
        "--online", action="store_true", help="the labeler node's odometry (OnlineOdometry: one pass, "
        "fixed-lag smoothing, isolated frames decided as frames arrive) instead of estimate_poses' two passes"
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.stereo_bias:
        print(
            json.dumps(
                {"stereo_bias": stereo_bias(args.scenes, args.seeds, args.size, args.stereo_bias, args.right_shift)}
            )
        )
        return 0
    if args.kitti == "":
        args.kitti = None
    params = VOParams(**parse_overrides(args.set))
    if args.online:
        return _main_online(args, params)
    rows = []
    for name, camera, frames, truth, disparities in _sequences(args):
        row = run_sequence(name, camera, frames, truth, params, args.oracle, disparities)
        rows.append(row)
        print(
            f"{name}: {row['translation_pct']:.2f} %, scale {row['scale_pct']:+.2f} %, "
            f"{row['reliable']}/{row['frames']} reliable, {row['bad_reliable']} bad, "
            f"{row['ms_per_frame']:.0f} ms/frame, disparity offset {row['disparity_offset_px']:+.3f} px "
            f"(estimate {row['offset_estimate_px']:+.3f} +- {row['offset_error_px']:.3f} px, "
            f"{row['offset_windows']} windows, {row['passes']} passes)"
            + (
                f", oracle {args.oracle} dropped {row['oracle_dropped_pct']:.1f} % of the features"
                if args.oracle != "none"
                else ""
            ),
            file=sys.stderr,
            flush=True,
        )
    print_table(rows)
    binned = scale_by_disparity(rows)
    print("\nFrame-to-frame scale error by the inliers' median disparity (measured frames):")
    print("| median disparity px | frames | mean % | mean abs % | step error > 2 % | reliable |")
    print("|---|---|---|---|---|---|")
    for b in binned:
        lo, hi = b["disparity"]
        print(f"| {lo:g}-{hi:g} | {b['frames']} | {b['mean_pct']:+.2f} | {b['mean_abs_pct']:.2f} | {b['over_2pct']} | "
              f"{b['reliable']} |")  # fmt: skip
    summary = summarise(rows)
    for scene, entry in summary.items():
        t = entry["translation_pct"]
        print(
            f"{scene}: translation {t['mean']:.2f} +- {t['std']:.2f} % (worst {t['worst']:.2f}), scale "
            f"{entry['scale_pct']['mean']:+.2f} % (worst {entry['scale_pct']['worst']:+.2f}), "
            f"{entry['bad_reliable']} bad reliable frames, {entry['unreliable']} unreliable"
        )
    overrides = {k: v for k, v in parse_overrides(args.set).items()}
    print(json.dumps({"params": dataclasses.asdict(params), "overrides": overrides, "sequences": rows,
                      "summary": summary, "scale_by_disparity": binned}))  # fmt: skip
    return 0


def _main_online(args: argparse.Namespace, params: VOParams) -> int:
    """``--online``: per sequence and per scene (mean +- std, median, worst, above 2 %), then one JSON line."""
    rows = []
    for name, camera, frames, truth, _ in _sequences(args):
        row = run_online(name, camera, frames, truth, params)
        rows.append(row)
        print(f"{name}: {row['translation_pct']:.2f} %, {row['reliable']} reliable, {row['bad_reliable']} bad, "
              f"{row['ms_per_frame']:.0f} ms/frame (95th percentile {row['p95_frame_ms']:.0f}, worst "
              f"{row['worst_frame_ms']:.0f})", file=sys.stderr, flush=True)  # fmt: skip
    summary: dict[str, Any] = {}
    for scene in sorted({r["sequence"].split("/")[0] for r in rows}):
        group = [r for r in rows if r["sequence"].split("/")[0] == scene]
        t = np.array([r["translation_pct"] for r in group])
        summary[scene] = {"mean": float(t.mean()), "std": float(t.std()), "median": float(np.median(t)),
                          "worst": float(t.max()), "above_2pct": int((t > 2.0).sum()),
                          "bad_reliable": sum(r["bad_reliable"] for r in group),
                          "reliable": sum(r["reliable"] for r in group)}  # fmt: skip
        s = summary[scene]
        print(f"{scene} (online): translation {s['mean']:.2f} +- {s['std']:.2f} % (median {s['median']:.2f}, "
              f"worst {s['worst']:.2f}, above 2 %: {s['above_2pct']}), bad reliable {s['bad_reliable']} / "
              f"{s['reliable']}")  # fmt: skip
    print(json.dumps({"online": True, "params": dataclasses.asdict(params), "sequences": rows, "summary": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
