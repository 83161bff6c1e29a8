"""Batch labeling on a local Ray cluster against one process: speed-up, Ray's per-task overhead, resume.

Renders four synthetic bags (street, orbit, room, street with another seed;
``selfcontra_ros.datasets.synthetic`` -> ``kitti2mcap``), then times
``selfcontra batch label`` on them three times:

1. ``sequential``: this process, one bag after another, the labeler's thread
   pools at 2 threads (what ``selfcontra label`` does per bag with ``--threads 2``);
2. ``ray``: a local Ray cluster of 2 CPUs started here (its start is timed
   apart as ``ray_start_s``), 2 tasks of 1 CPU each at a time;
3. ``resume``: the same batch again with ``--resume`` on that cluster, which
   finds every result complete and labels nothing.

It prints per run the wall time and the labeler's own run time summed over
the bags (``labeler_s``, each bag's ``metrics.json`` ``runtime_s``), then

- ``speedup`` = sequential wall / Ray wall (cluster start not counted) and
  ``speedup_with_start`` (counted);
- ``overhead_per_task_s`` = (Ray wall x tasks at a time - Ray's ``labeler_s``) / bags:
  what a task costs beyond labelling (scheduling, a worker process importing
  the package and loading the compiled kernels, moving the result into place);

and one JSON line with all figures. The outputs of the two labelling runs are
checked to be the same (label images of every bag) before any figure is printed.

Usage: ``python bench/batch_speed.py [--frames 20] [--size 1226x370] [--keep DIR]``
(the defaults take a few minutes on 2 cores; ``--frames 4 --size 256x80`` shows it works).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.batch.engine import SequentialEngine, local_ray_environment, start_local_cluster
from selfcontra_ros.batch.label import batch_label
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.threads import limit_threads

BAGS = (("street", "street", 1), ("orbit", "orbit", 1), ("room", "room", 1), ("street2", "street", 2))
CPUS = 2
FLUSH = Path(__file__).resolve().parents[1] / "test" / "bags" / "flush_all.yaml"


def _make_bags(root: Path, frames: int, width: int, height: int) -> list[Path]:
    bags = []
    for name, scene, seed in BAGS:
        sequence = write_sequence(
            root / "scenes" / name, scene=scene, frames=frames, seed=seed, width=width, height=height
        )
        bags.append(kitti_to_mcap(sequence, root / "bags" / name, progress=False))
    return bags


def _labels(bag: Path) -> list[bytes]:
    with open_bag(bag) as opened:
        wanted = {t for t in opened.topics if t.endswith("/" + topics.LABELS)}
        return [bytes(m.data) for m in opened.raw_messages(wanted)]


def _run(name: str, bags: list[Path], out: Path, **options: Any) -> dict[str, Any]:
    started = time.perf_counter()
    summary = batch_label([str(b) for b in bags], out, progress=False, echo=None, **options)
    wall = time.perf_counter() - started
    failed = [e["name"] for e in summary["inputs"] if e["status"] == "failed"]
    if failed:
        raise SystemExit(f"{name}: labelling failed for {failed}")
    labeler = sum(e["runtime_s"] for e in summary["inputs"] if e["status"] == "complete")
    return {"wall_s": wall, "labeler_s": labeler, "statuses": sorted({e["status"] for e in summary["inputs"]})}


def main() -> None:
    """Run the benchmark (module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20, help="frames per bag (default 20)")
    parser.add_argument("--size", default="1226x370", help="image size WxH (default KITTI's 1226x370)")
    parser.add_argument("--keep", default=None, help="folder for the bags and outputs (default: a temporary one)")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    local_ray_environment()  # before Ray is imported anywhere
    with tempfile.TemporaryDirectory(prefix="batch_speed_") as scratch:
        root = Path(args.keep) if args.keep else Path(scratch)
        bags = _make_bags(root, args.frames, width, height)
        limit_threads(CPUS)  # the sequential run: this process's pools at 2 threads
        sequential = _run("sequential", bags, root / "sequential", params_file=FLUSH, engine=SequentialEngine())
        started = time.perf_counter()
        start_local_cluster(CPUS)
        ray_start = time.perf_counter() - started
        import ray

        try:
            ray_run = _run("ray", bags, root / "ray", params_file=FLUSH, cpus_per_task=1)
            resumed = _run("resume", bags, root / "ray", params_file=FLUSH, cpus_per_task=1, resume=True)
        finally:
            ray.shutdown()
        for bag in bags:
            if _labels(root / "sequential" / bag.name) != _labels(root / "ray" / bag.name):
                raise SystemExit(f"the Ray run's labels of {bag.name} differ from the sequential run's")
    figures = {
        "bags": len(bags),
        "frames_per_bag": args.frames,
        "size": f"{width}x{height}",
        "cpus": CPUS,
        "cores_visible": len(os.sched_getaffinity(0)),
        "sequential": sequential,
        "ray_start_s": ray_start,
        "ray": ray_run,
        "resume": resumed,
        "speedup": sequential["wall_s"] / ray_run["wall_s"],
        "speedup_with_start": sequential["wall_s"] / (ray_run["wall_s"] + ray_start),
        "overhead_per_task_s": (ray_run["wall_s"] * CPUS - ray_run["labeler_s"]) / len(bags),
    }
    print(f"{len(bags)} bags x {args.frames} frames at {width}x{height}, {CPUS} CPUs")
    print(f"{'run':<12}{'wall s':>9}{'labeler s':>11}  statuses")
    for name in ("sequential", "ray", "resume"):
        run = figures[name]
        print(f"{name:<12}{run['wall_s']:>9.2f}{run['labeler_s']:>11.2f}  {', '.join(run['statuses'])}")
    print(
        f"Ray cluster start {ray_start:.1f} s; speed-up {figures['speedup']:.2f}x "
        f"({figures['speedup_with_start']:.2f}x with the start); Ray overhead per task "
        f"{figures['overhead_per_task_s']:.2f} s"
    )
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
