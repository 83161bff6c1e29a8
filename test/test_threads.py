"""limit_threads caps numba, OpenCV and BLAS/OpenMP for real; the node's ``threads`` key is in the package YAML.

The caps are process-global state, so the tests that apply them run in a
subprocess of their own and report what they observed as JSON.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
import yaml

from selfcontra_ros import threads
from selfcontra_ros.config import NODE_PARAMETERS, read_node_parameters, read_parameter_file
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.resources import config_file

# A prange kernel that records which numba thread ran each iteration: the threads really used. It lives in a
# module file so that numba caches it (``cache=True``): the second subprocess loads it instead of compiling.
_PROBE = """
import json, os, threading
import numpy as np
import numba
from numba import njit, prange
import cv2
import scipy.linalg, sklearn.ensemble  # load their BLAS / OpenMP libraries, as the package does
from threadpoolctl import threadpool_info
from selfcontra_ros.threads import apply_thread_limit, limit_threads

@njit(parallel=True, cache=True)
def thread_ids(n):
    out = np.empty(n, np.int64)
    for i in prange(n):
        acc = 0.0
        for j in range(20000):  # enough work per iteration that every pool thread takes some
            acc += np.sqrt(i + j)
        out[i] = numba.get_thread_id() + 0 * int(acc)
    return out

def observe():
    return {
        "numba": numba.get_num_threads(),
        "kernel_threads": sorted(set(thread_ids(256).tolist())),
        "pools": sorted({(i["internal_api"], i["num_threads"]) for i in threadpool_info()}),
    }
"""


@pytest.fixture(scope="module")
def probe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder of ``thread_probe.py`` (``_PROBE``), numba's cache beside it."""
    folder = tmp_path_factory.mktemp("thread_probe")
    (folder / "thread_probe.py").write_text(_PROBE)
    return folder


def _run(probe: Path, script: str) -> dict[str, Any]:
    """Run ``script`` after ``from thread_probe import *`` in a fresh interpreter; return the JSON it prints last."""
    prelude = f"import sys\nsys.path.insert(0, {str(probe)!r})\nfrom thread_probe import *\n"
    done = subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(script)],
        capture_output=True,
        text=True,
        timeout=120,
        env=os.environ.copy(),
        check=False,
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def test_limit_threads_caps_every_pool_in_this_and_later_threads(probe: Path) -> None:
    out = _run(
        probe,
        """
        result = {"pool": numba.config.NUMBA_NUM_THREADS, "uncapped": observe()}
        result["applied"] = limit_threads(1)
        result["cv2"] = cv2.getNumThreads()
        result["main"] = observe()
        def worker(name, apply):
            if apply:
                result[name + "_returned"] = apply_thread_limit()
            result[name] = observe()
        for name, apply in (("thread_without_apply", False), ("thread", True)):
            t = threading.Thread(target=worker, args=(name, apply))
            t.start()
            t.join()
        print(json.dumps(result))
        """,
    )
    assert out["applied"] == 1
    assert out["cv2"] == 1
    for where in ("main", "thread"):
        assert out[where]["numba"] == 1, where
        assert out[where]["kernel_threads"] == [0], where  # every iteration ran on one thread
        assert out[where]["pools"] and all(n == 1 for _, n in out[where]["pools"]), (where, out[where]["pools"])
    assert out["thread_returned"] == 1
    if out["pool"] >= 2:
        # The control: uncapped, the same kernel spreads over several threads, and a new thread starts
        # with numba's whole pool again (its count is thread-local), which is why apply_thread_limit exists.
        assert len(out["uncapped"]["kernel_threads"]) >= 2
        assert out["thread_without_apply"]["numba"] == out["pool"]


def test_zero_means_the_cores_of_the_affinity_mask(probe: Path) -> None:
    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity API on this platform")
    out = _run(
        probe,
        """
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        result = {"zero": limit_threads(0), "cv2": cv2.getNumThreads(), "main": observe()}
        result["above"] = limit_threads(64)  # lowered to the one core given
        print(json.dumps(result))
        """,
    )
    assert out["zero"] == 1 and out["above"] == 1 and out["cv2"] == 1
    assert out["main"]["numba"] == 1 and out["main"]["kernel_threads"] == [0]


@pytest.mark.parametrize("bad", [-1, -8, True, 1.5, "2", None])
def test_invalid_thread_counts_are_refused_with_the_value(bad: object) -> None:
    # Validation comes before any pool is touched, so this runs in the test process.
    with pytest.raises(SelfContraError, match=r"threads is .*expected an integer >= 0"):
        threads.limit_threads(bad)  # type: ignore[arg-type]


def test_cap_jobs_follows_joblib_semantics_within_the_cap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(threads, "available_cores", lambda: 8)
    monkeypatch.setattr(threads, "_cap", None)
    assert threads.cap_jobs(-1) == -1 and threads.cap_jobs(16) == 16 and threads.cap_jobs(None) is None
    monkeypatch.setattr(threads, "_cap", 3)
    assert threads.cap_jobs(None) is None  # scikit-learn's default, one job
    assert threads.cap_jobs(1) == 1
    assert threads.cap_jobs(16) == 3
    assert threads.cap_jobs(-1) == 3  # all 8 cores, capped
    assert threads.cap_jobs(-7) == 2  # 8 + 1 - 7
    assert threads.cap_jobs(-20) == 1
    for bad in (0, True, 2.0):
        with pytest.raises(SelfContraError, match="n_jobs"):
            threads.cap_jobs(bad)  # type: ignore[arg-type]


def test_package_yaml_has_the_node_threads_default() -> None:
    document = yaml.safe_load(config_file("labeler.yaml").read_text())
    (body,) = document.values()
    assert body["ros__parameters"]["threads"] == NODE_PARAMETERS["threads"] == 0
    assert read_node_parameters(None) == NODE_PARAMETERS
    assert "threads" not in read_parameter_file(config_file("labeler.yaml"))  # not a section


def test_node_parameters_of_a_file_are_read_and_checked(tmp_path: Path) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"labeler": {"ros__parameters": {"threads": 3, "labeler": {"window_size": 5}}}}))
    assert read_node_parameters(path) == {"threads": 3}
    assert read_parameter_file(path)["labeler"] == {"window_size": 5}
    path.write_text(yaml.safe_dump({"labeler": {"ros__parameters": {"labeler": {}}}}))
    assert read_node_parameters(path) == NODE_PARAMETERS
    for bad in (-1, "two", True):
        path.write_text(yaml.safe_dump({"labeler": {"ros__parameters": {"threads": bad}}}))
        with pytest.raises(SelfContraError, match=rf"{path}.*'threads'"):
            read_node_parameters(path)
