"""Memory growth of the labeler node's odometry (``OnlineOdometry``) over a long stream.

A synthetic street is played forwards and backwards (the reversals are
frames the odometry finds implausible, as it would a real failure) through
one ``OnlineOdometry``; ``tracemalloc`` samples the Python heap every 5
frames. The slope of the second half's samples is what a node running for
hours would add per frame. Prints the heap, the slope and the frames the
odometry holds, and one JSON line.

    python bench/odometry_memory.py --frames 600 --size 640x192
"""

from __future__ import annotations

import argparse
import json
import time
import tracemalloc

import numpy as np
from tqdm import tqdm

from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.odometry.run import OnlineOdometry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600, help="frames streamed (default 600)")
    parser.add_argument("--size", default="640x192", help="image size WxH (default 640x192)")
    parser.add_argument("--scene", default="street")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--rendered", type=int, default=30, help="distinct frames rendered (default 30)")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    scene = make_scene(args.scene, args.seed, width, height, frames=args.rendered)
    rendered = [scene.render(k) for k in tqdm(range(args.rendered), desc="render", unit="frame")]
    order = list(range(args.rendered)) + list(range(args.rendered - 2, 0, -1))
    online = OnlineOdometry(scene.camera)
    half = args.frames // 2
    tracemalloc.start(1)
    samples: list[tuple[int, int]] = []  # (frame, traced heap bytes), every 5 frames
    start = time.perf_counter()
    for i in tqdm(range(args.frames), desc="odometry", unit="frame"):
        frame = rendered[order[i % len(order)]]
        online.add(int(i * 1e8), frame.left, frame.right)
        if (i + 1) % 5 == 0:
            samples.append((i + 1, tracemalloc.get_traced_memory()[0]))
    tracemalloc.stop()
    # The heap swings by tens of KiB with what the window and the reference hold (features per frame), so the
    # growth is the slope of a line through the second half's samples, not the difference of two of them.
    late = np.array([s for s in samples if s[0] > half], dtype=np.float64)
    slope, _ = np.polyfit(late[:, 0], late[:, 1], 1)
    swing = float(late[:, 1].max() - late[:, 1].min())
    held = len(online._vo.poses.held())
    print(
        f"heap after {half} frames: {samples[half // 5 - 1][1] / 1024:.1f} KiB; after {args.frames}: "
        f"{samples[-1][1] / 1024:.1f} KiB; swing over the second half {swing / 1024:.1f} KiB"
    )
    print(
        f"growth (slope over frames {half}-{args.frames}): {slope:.0f} B per frame "
        f"({slope * 36000 / 2**20:.1f} MiB an hour at 10 Hz)"
    )
    print(f"frames the odometry holds: {held} of {args.frames}; {time.perf_counter() - start:.0f} s")
    print(json.dumps({"frames": args.frames, "size": args.size, "growth_bytes_per_frame": float(slope),
                      "swing_bytes": swing, "held": held}))  # fmt: skip


if __name__ == "__main__":
    main()
