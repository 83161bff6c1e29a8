"""Memory growth of the labeler node's odometry (``OnlineOdometry``) over a long stream.

A synthetic street is played forwards and backwards (the reversals are
frames the odometry finds implausible, as it would a real failure) through
one ``OnlineOdometry``; ``tracemalloc`` counts the Python heap after the
first half of the frames and at the end. The growth per frame of the second
half is what a node running for hours would add (the heap's own
bookkeeping of the first snapshot is subtracted). Prints one line per
snapshot, the largest growing allocation sites, and one JSON line.

    python bench/odometry_memory.py --frames 600 --size 640x192
"""

from __future__ import annotations

import argparse
import json
import time
import tracemalloc

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
    tracemalloc.start(4)
    first = None
    heap = {}
    start = time.perf_counter()
    for i in tqdm(range(args.frames), desc="odometry", unit="frame"):
        frame = rendered[order[i % len(order)]]
        online.add(int(i * 1e8), frame.left, frame.right)
        if i + 1 == half:
            first = tracemalloc.take_snapshot()
            heap["half"] = tracemalloc.get_traced_memory()[0]
    heap["end"] = tracemalloc.get_traced_memory()[0]
    last = tracemalloc.take_snapshot()
    tracemalloc.stop()
    assert first is not None
    # The first snapshot lives on the heap too: take its own allocations out of the growth.
    diffs = last.compare_to(first, "filename")
    own = sum(s.size_diff for s in diffs if s.traceback[0].filename == tracemalloc.__file__)
    frames = args.frames - half
    per_frame = (heap["end"] - heap["half"] - own) / frames
    held = len(online._vo.poses.held())
    print(f"heap after {half} frames: {heap['half'] / 1024:.1f} KiB; after {args.frames}: {heap['end'] / 1024:.1f} KiB")
    print(f"growth: {per_frame:.0f} B per frame ({per_frame * 36000 / 2**20:.1f} MiB an hour at 10 Hz)")
    print(f"frames the odometry holds: {held} of {args.frames}; {time.perf_counter() - start:.0f} s")
    print("largest growing allocation sites (B per frame):")
    stats = [s for s in last.compare_to(first, "lineno") if s.traceback[0].filename != tracemalloc.__file__]
    for stat in stats[:5]:
        print(f"  {stat.size_diff / frames:8.1f}  {stat.traceback[0]}")
    print(json.dumps({"frames": args.frames, "size": args.size, "growth_bytes_per_frame": per_frame, "held": held}))


if __name__ == "__main__":
    main()
