"""Relative pose error between the node's reliable frames, by the failure between them.

The labeling window keeps views from before a failure; a view after it is
labelled against them through the failed frames' guessed (then
interpolated) motion. For every pair of reliable frames at most ``--reach``
frames apart, over synthetic sequences run through ``OnlineOdometry`` as the
labeler node runs it, this prints the relative translation error against
the truth (percent of the distance between them) grouped by the longest
run of unreliable frames between the two, ending with one JSON line.

    python bench/odometry_spans.py --cache /tmp/vo_cache --scene highway --seeds 1-30
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from odometry_accuracy import synthetic_frames  # bench/ is the script's folder, first on sys.path
from tqdm import tqdm

from selfcontra_ros.geometry import invert_pose
from selfcontra_ros.odometry.run import OnlineOdometry

#: Groups by unreliable frames between the pair (inclusive bounds).
GROUPS = ((0, 0), (1, 1), (2, 3), (4, 7), (8, 10_000))


def pair_errors(scene: str, seed: int, frames: int, size: tuple[int, int], cache: Path | None, reach: int):
    """(unreliable frames between, translation error %) per pair of reliable frames at most ``reach`` apart."""
    camera, rendered, truth = synthetic_frames(scene, seed, frames, size, cache)
    online = OnlineOdometry(camera)
    decisions = [d for k, (left, right, _) in enumerate(rendered) for d in online.add(k, left, right)]
    decisions += online.finish()
    reliable = [k for k, d in enumerate(decisions) if d.pose is not None]
    out = []
    for a, i in enumerate(reliable):
        for b in range(a + 1, len(reliable)):
            j = reliable[b]
            if j - i > reach:
                break
            estimated = invert_pose(decisions[i].pose) @ decisions[j].pose
            true = invert_pose(truth[i]) @ truth[j]
            error = 100.0 * np.linalg.norm(estimated[:3, 3] - true[:3, 3]) / np.linalg.norm(true[:3, 3])
            failed = max(reliable[c + 1] - reliable[c] for c in range(a, b)) - 1
            out.append((failed, float(error)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="highway")
    parser.add_argument("--seeds", default="1-30", help="first-last")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--size", default="1226x370")
    parser.add_argument("--cache", type=Path, default=None, help="folder of rendered frames (.npz)")
    parser.add_argument("--reach", type=int, default=20, help="frames between a pair at most (default 20)")
    args = parser.parse_args()
    first, last = (int(v) for v in args.seeds.split("-"))
    size = tuple(int(v) for v in args.size.lower().split("x"))
    pairs = []
    for seed in tqdm(range(first, last + 1), desc=args.scene, unit="sequence"):
        pairs += pair_errors(args.scene, seed, args.frames, size, args.cache, args.reach)
    failed = np.array([p[0] for p in pairs])
    errors = np.array([p[1] for p in pairs])
    summary = []
    print("| unreliable frames between | pairs | mean % | median % | 95th pct % | worst % |")
    print("|---|---|---|---|---|---|")
    for lo, hi in GROUPS:
        chosen = errors[(failed >= lo) & (failed <= hi)]
        if chosen.size == 0:
            continue
        stats = (chosen.mean(), np.median(chosen), np.percentile(chosen, 95), chosen.max())
        row = {"failed": [lo, hi], "pairs": int(chosen.size)} | dict(
            zip(("mean", "median", "p95", "worst"), map(float, stats), strict=True)
        )
        summary.append(row)
        label = f"{lo}" if lo == hi else f"{lo}+" if hi >= 10_000 else f"{lo}-{hi}"
        print(f"| {label} | {chosen.size} | " + " | ".join(f"{v:.2f}" for v in stats) + " |")
    print(json.dumps({"scene": args.scene, "seeds": args.seeds, "reach": args.reach, "groups": summary}))


if __name__ == "__main__":
    main()
