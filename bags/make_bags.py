"""Build the sample rosbag2 (MCAP) bags: the script behind ``make bags``.

Writes into ``--out`` (default: this folder):

* ``synthetic_street/`` and ``synthetic_orbit/``: the package's synthetic
  scenes (seed 1, 30 frames at 620x188 by default, with exact poses and
  ground-truth disparity), rendered into a temporary KITTI-layout folder by
  :func:`selfcontra_ros.datasets.synthetic.write_sequence` and converted by
  :func:`selfcontra_ros.bags.kitti2mcap.kitti_to_mcap`;
* ``kitti_<sequence>/`` when ``--kitti PATH`` names a KITTI odometry root or
  sequence folder (e.g. ``../shared/data/kitti_odometry``): its grey pair and
  poses (``--kitti-frames`` to take a part).

A bag that exists already is skipped (never overwritten); delete it to
rebuild it. Each bag written is listed with its topics and size. Label one
with ``selfcontra label-bag bags/synthetic_street --out OUT``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.cli import parse_frame_range, parse_size
from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.datasets.synthetic import SCENES, write_sequence
from selfcontra_ros.errors import SelfContraError

DEFAULT_OUT = Path(__file__).resolve().parent


def _describe(bag_path: Path) -> str:
    with open_bag(bag_path) as bag:
        topics = ", ".join(f"{t.name} ({t.message_count})" for t in bag.topics.values())
    size_mb = sum(f.stat().st_size for f in bag_path.rglob("*") if f.is_file()) / 1e6
    return f"wrote {bag_path} ({size_mb:.1f} MB): {topics}"


def make_synthetic_bag(out: Path, scene: str, *, frames: int, seed: int, size: tuple[int, int]) -> Path | None:
    """Render ``scene`` and convert it to the bag folder ``out``; None (nothing done) if ``out`` exists."""
    if out.exists():
        return None
    with tempfile.TemporaryDirectory(prefix=f"synthetic_{scene}_") as tmp:
        write_sequence(Path(tmp), scene=scene, frames=frames, seed=seed, width=size[0], height=size[1])
        return kitti_to_mcap(Path(tmp), out)


def main(argv: Sequence[str] | None = None) -> int:
    """Build the sample bags; returns the exit code (2 on a package error)."""
    parser = argparse.ArgumentParser(prog="make_bags", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder of the bags (default: bags/)")
    parser.add_argument("--kitti", type=Path, default=None, help="KITTI odometry root or sequence folder to convert")
    parser.add_argument(
        "--kitti-frames", type=parse_frame_range, default=None, help="frame range A:B of the KITTI sequence"
    )
    parser.add_argument("--sequence", default=None, help="KITTI sequence of a root holding several (e.g. 06)")
    parser.add_argument("--frames", type=int, default=30, help="frames per synthetic scene (default 30)")
    parser.add_argument(
        "--size", type=parse_size, default=(620, 188), help="synthetic image size WxH (default 620x188)"
    )
    parser.add_argument("--seed", type=int, default=1, help="synthetic scene seed (default 1)")
    args = parser.parse_args(argv)

    try:
        args.out.mkdir(parents=True, exist_ok=True)
        for scene in SCENES:
            target = args.out / f"synthetic_{scene}"
            written = make_synthetic_bag(target, scene, frames=args.frames, seed=args.seed, size=args.size)
            print(_describe(written) if written is not None else f"skipped {target}: exists already")
        if args.kitti is not None:
            sequence = open_sequence(args.kitti, sequence=args.sequence)
            target = args.out / f"kitti_{sequence.sequence}"
            if target.exists():
                print(f"skipped {target}: exists already")
            else:
                print(_describe(kitti_to_mcap(args.kitti, target, frames=args.kitti_frames, sequence=args.sequence)))
    except SelfContraError as exc:
        print(f"make_bags: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
