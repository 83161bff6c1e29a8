"""The odometry after a stop and a failure: does it measure again, how soon, and how well.

Each synthetic sequence is changed into a stop and a lost view: frame 4 is
repeated ``--stopped`` times (``static`` frames, the velocity zero), then
``--blank`` textureless frames follow, then the sequence drives on from
frame 5. Per sequence and per ``stale_velocity_frames`` value it prints the
frames after the failure until the first ``ok`` one, the reliable frames
after the failure, and the worst relative translation error of their steps
against the truth; ending with one JSON line.

    python bench/odometry_stop.py --scenes street orbit --seeds 1-10 --stale 0 5 10
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from tqdm import tqdm

from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.geometry import invert_pose
from selfcontra_ros.odometry.stereo_vo import StereoOdometry, VOParams


def run(scene: str, seed: int, args: argparse.Namespace, stale: int) -> dict:
    """One sequence with the stop and the failure, at one ``stale_velocity_frames``."""
    width, height = (int(v) for v in args.size.lower().split("x"))
    built = make_scene(scene, seed, width, height, frames=args.frames)
    frames = [(f.left, f.right) for f in (built.render(k) for k in range(args.frames))]
    truth = built.poses(args.frames)
    grey = np.full((height, width), 128, np.uint8)
    pairs = frames[:5] + [frames[4]] * args.stopped + [(grey, grey)] * args.blank + frames[5:]
    original = list(range(5)) + [4] * args.stopped + [-1] * args.blank + list(range(5, args.frames))
    vo = StereoOdometry(built.camera, VOParams(stale_velocity_frames=stale))
    qualities = [vo.add(left, right).quality for left, right in pairs]
    first = 5 + args.stopped + args.blank
    after = [q.status for q in qualities[first:]]
    errors = []
    for q in qualities[first:]:
        if q.reliable and q.reference >= first:
            measured = invert_pose(vo.poses[q.reference]) @ vo.poses[q.index]
            true = invert_pose(truth[original[q.reference]]) @ truth[original[q.index]]
            errors.append(100.0 * np.linalg.norm(measured[:3, 3] - true[:3, 3]) / np.linalg.norm(true[:3, 3]))
    return {
        "sequence": f"{scene}/{seed}",
        "stale_velocity_frames": stale,
        "recovered_after": after.index("ok") if "ok" in after else None,
        "reliable_after": sum(q.reliable for q in qualities[first:]),
        "frames_after": len(after),
        "worst_step_pct": float(max(errors)) if errors else None,
        "steps_above_2pct": int(sum(e > 2.0 for e in errors)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["street", "orbit"])
    parser.add_argument("--seeds", default="1-10", help="first-last")
    parser.add_argument("--frames", type=int, default=36, help="frames of each sequence before the change")
    parser.add_argument("--size", default="640x192")
    parser.add_argument("--stopped", type=int, default=8)
    parser.add_argument("--blank", type=int, default=2)
    parser.add_argument("--stale", type=int, nargs="+", default=[0, 10], help="stale_velocity_frames values")
    args = parser.parse_args()
    first, last = (int(v) for v in args.seeds.split("-"))
    rows = []
    jobs = [(scene, seed) for scene in args.scenes for seed in range(first, last + 1)]
    for scene, seed in tqdm(jobs, desc="sequences", unit="sequence"):
        for stale in args.stale:
            row = run(scene, seed, args, stale)
            rows.append(row)
            worst = "-" if row["worst_step_pct"] is None else f"{row['worst_step_pct']:.2f} %"
            tqdm.write(
                f"{row['sequence']} stale {stale}: first ok {row['recovered_after']} frames after the failure, "
                f"{row['reliable_after']} / {row['frames_after']} reliable, worst step {worst}, "
                f"{row['steps_above_2pct']} above 2 %"
            )
    for stale in args.stale:
        chosen = [r for r in rows if r["stale_velocity_frames"] == stale]
        recovered = [r["recovered_after"] for r in chosen if r["recovered_after"] is not None]
        worst = [r["worst_step_pct"] for r in chosen if r["worst_step_pct"] is not None]
        print(
            f"stale {stale}: {len(recovered)} of {len(chosen)} measure again"
            + (f", after {min(recovered)}-{max(recovered)} frames" if recovered else "")
            + (f"; worst step {max(worst):.2f} %" if worst else "")
        )
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
