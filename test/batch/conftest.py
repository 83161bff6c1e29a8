"""One small local Ray cluster for the whole test session (2 CPUs, 200 MB object store, loopback only).

Ray starts once (about 15 s on a busy 2-core machine) and is shut down at the
end of the session; the teardown waits until none of its processes is left.
Its usage statistics are off (``RAY_USAGE_STATS_ENABLED=0``) before Ray is
imported. The inputs are tiny synthetic scenes: three bags, one sequence and
a corrupt bag, each labelled once by ``selfcontra label`` as the reference.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.batch.label import KILL_MARKER_ENV, batch_label
from selfcontra_ros.cli import main
from selfcontra_ros.datasets.synthetic import write_sequence

os.environ["RAY_USAGE_STATS_ENABLED"] = "0"  # before anything imports Ray

#: the package defaults, labelling the last views too (the test inputs are shorter than the window)
FLUSH = Path(__file__).parents[1] / "bags" / "flush_all.yaml"
FRAMES, WIDTH, HEIGHT = 6, 256, 80
#: (name, scene, seed) of the bags; the sequence is the street with another seed
BAGS = (("street", "street", 1), ("orbit", "orbit", 1), ("room", "room", 1))
SEQUENCE_NAME = "seqroot_00"  # input_name of the sequence root 'seqroot' (sequence 00)
CORRUPT = "corrupt"
OBJECT_STORE_BYTES = 200 * 1024 * 1024


def _descendants(root: int) -> set[int]:
    """Process ids below ``root`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found: set[int] = set()
    todo = [root]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def _alive(pids: set[int]) -> set[int]:
    alive = set()
    for pid in pids:
        try:
            state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.add(pid)
    return alive


#: The running cluster's ``ray`` module and process ids (empty when none runs); the last batch test stops it.
_CLUSTER: dict[str, Any] = {}
HERE = Path(__file__).resolve().parent


def _stop_cluster() -> None:
    """Shut Ray down and wait until none of its processes is left (assert)."""
    before = _CLUSTER.pop("pids", None)
    ray = _CLUSTER.pop("ray", None)  # kept: a test may hide the module (sys.modules["ray"] = None) until after this
    if before is None or ray is None:
        return
    started = before | _descendants(os.getpid())  # with the workers Ray started since (retries)
    ray.shutdown()
    deadline = time.monotonic() + 30
    while _alive(started) and time.monotonic() < deadline:
        time.sleep(0.2)
    left = _alive(started)
    assert not left, f"Ray processes left running after shutdown: {sorted(left)}"


@pytest.fixture(scope="session")
def ray_cluster() -> Iterator[set[int]]:
    """The session's local Ray cluster, started by the package's own :func:`start_local_cluster`.

    Yields the ids of the processes Ray started. It is stopped after the last test of this folder
    (:func:`pytest_runtest_teardown`), so the rest of the suite runs without it, and at the latest
    at the end of the session; after the shutdown none of its processes may be left.
    """
    if importlib.util.find_spec("ray") is None:  # not importorskip: Ray must not be imported before its environment
        pytest.skip("Ray is not installed (the [cluster] extra)")
    from selfcontra_ros.batch.engine import start_local_cluster

    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    start_local_cluster(2, object_store_bytes=OBJECT_STORE_BYTES)
    import ray

    _CLUSTER.update(pids=set(), ray=ray)
    try:
        ray.get(ray.remote(lambda: 0).remote())  # a worker is up: the process tree is complete
        _CLUSTER["pids"] = _descendants(os.getpid())
        yield _CLUSTER["pids"]
    finally:
        _stop_cluster()


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    """After the last test of this folder, stop the cluster: the tests after it (ROS timing) run without Ray.

    Last of the teardown hooks, after the test's own fixtures are undone: a test that hid the module
    (``sys.modules["ray"] = None``) has it back by then, and ``ray.shutdown`` imports parts of it.
    """
    if _CLUSTER and (nextitem is None or HERE not in Path(nextitem.path).resolve().parents):
        _stop_cluster()


def _label(source: Path, out: Path) -> None:
    assert main(["label", str(source), "--out", str(out), "--params", str(FLUSH)]) == 0


@pytest.fixture(scope="session")
def batch_inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Input name -> path: three bags, one sequence root and a corrupt bag (its MCAP magic overwritten)."""
    root = tmp_path_factory.mktemp("batch_inputs")
    inputs: dict[str, Path] = {}
    for name, scene, seed in BAGS:
        sequence = root / "scenes" / name
        write_sequence(sequence, scene=scene, frames=FRAMES, seed=seed, width=WIDTH, height=HEIGHT)
        inputs[name] = kitti_to_mcap(sequence, root / "bags" / name, progress=False)
    seqroot = root / "seqroot"
    write_sequence(seqroot, scene="street", frames=FRAMES, seed=2, width=WIDTH, height=HEIGHT)
    inputs[SEQUENCE_NAME] = seqroot
    corrupt = root / "bags" / CORRUPT
    shutil.copytree(inputs["street"], corrupt)
    for mcap in corrupt.glob("*.mcap"):
        data = bytearray(mcap.read_bytes())
        data[:64] = b"\0" * 64
        mcap.write_bytes(bytes(data))
    inputs[CORRUPT] = corrupt
    return inputs


@pytest.fixture(scope="session")
def references(batch_inputs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Input name -> the output of ``selfcontra label INPUT --out ...`` (not for the corrupt bag)."""
    root = tmp_path_factory.mktemp("batch_references")
    out = {}
    for name, source in batch_inputs.items():
        if name != CORRUPT:
            out[name] = root / name
            _label(source, out[name])
    return out


@pytest.fixture(scope="session")
def batch_run(
    ray_cluster: set[int], batch_inputs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, dict[str, Any], Path, str]:
    """The batch of all inputs on Ray, with the test hook killing one worker once: (OUT_DIR, summary, marker, table)."""
    out = tmp_path_factory.mktemp("batch") / "out"
    marker = out.parent / "killed.marker"
    printed: list[str] = []
    os.environ[KILL_MARKER_ENV] = str(marker)
    try:
        summary = batch_label(
            [str(p) for p in batch_inputs.values()], out, params_file=FLUSH, progress=False, echo=printed.append
        )
    finally:
        del os.environ[KILL_MARKER_ENV]
    return out, summary, marker, "\n".join(printed)
