"""Fixtures for tests that start ROS 2: isolation, rclpy lifecycle, helper processes.

Network safety: every test in this folder runs with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, its own ``ROS_DOMAIN_ID`` and
the packaged Fast DDS profile (UDP on loopback only; in the variable that the
installed Fast DDS, 2.x or 3.x, reads), with static peers and
discovery servers removed from the environment; subprocesses started through
:func:`ros_process` inherit exactly that environment.

Tests marked ``@pytest.mark.ros`` (and every test using :func:`rclpy_context`)
are skipped with the import error as reason when rclpy cannot be imported.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from selfcontra_ros.resources import config_file
from selfcontra_ros.ros.environment import FASTDDS_PROFILE_VARIABLES, fastdds_profile_variables

# Fast DDS maps a domain to UDP ports 7400 + 250 * domain + ...; 0..101 keeps every port below the
# Linux ephemeral range whatever the participant count. Domain 0 (the default) is left to other users.
_DOMAIN_MIN = 1
_DOMAIN_COUNT = 101
# A stride coprime with 101 walks through every domain before repeating; the pid scatters the start,
# so that two test runs in parallel (pytest-xdist workers, CI jobs) rarely pick the same domain at once.
_DOMAIN_STRIDE = 37
_domain_counter = itertools.count()

# Environment variables that could make a participant talk to other machines.
_OFF_LOOPBACK_VARIABLES = ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "ROS_LOCALHOST_ONLY")


@cache
def _rclpy_import_error() -> str | None:
    """Why rclpy cannot be imported here, or None when it can."""
    try:
        import rclpy  # noqa: F401
    except Exception as exc:  # ImportError, but also OSError from a missing shared library
        return f"rclpy cannot be imported ({type(exc).__name__}: {exc}); install the [ros] extra to run ROS tests"
    return None


def _skip_without_rclpy() -> None:
    reason = _rclpy_import_error()
    if reason is not None:
        pytest.skip(reason)


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Skip tests marked ``ros`` when rclpy is unavailable."""
    if item.get_closest_marker("ros") is not None:
        _skip_without_rclpy()


def next_domain_id() -> int:
    """A ROS domain id in 1..101, different for each call within a run (until all 101 are used)."""
    return _DOMAIN_MIN + (os.getpid() * 7919 + next(_domain_counter) * _DOMAIN_STRIDE) % _DOMAIN_COUNT


@pytest.fixture(autouse=True)
def ros_environment(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Isolate the test's ROS 2 graph: own domain, localhost discovery, packaged loopback profile.

    Applied to every test of this folder, before any rclpy.init. Returns the variables set.
    """
    variables = {
        "ROS_DOMAIN_ID": str(next_domain_id()),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    }
    # Forced, not only defaulted as prepare_ros_environment does: a user profile might open network
    # interfaces, and the transport test is meant to exercise the packaged profile. Set in the variables
    # this Fast DDS reads; any other is removed (Kilted's rmw would read a user's FASTRTPS_ one as well).
    profile = str(config_file("fastdds_profile.xml"))
    variables.update(dict.fromkeys(fastdds_profile_variables(), profile))
    for name, value in variables.items():
        monkeypatch.setenv(name, value)
    for name in (*_OFF_LOOPBACK_VARIABLES, *FASTDDS_PROFILE_VARIABLES):
        if name not in variables:
            monkeypatch.delenv(name, raising=False)
    return variables


@pytest.fixture
def rclpy_context(ros_environment: dict[str, str]) -> Iterator[Any]:
    """An initialised ``rclpy.Context`` of its own, shut down at teardown."""
    _skip_without_rclpy()
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        context.try_shutdown()


@pytest.fixture
def ros_node(rclpy_context: Any, request: pytest.FixtureRequest) -> Iterator[Any]:
    """An rclpy node in :func:`rclpy_context`, destroyed at teardown."""
    import rclpy

    name = "test_" + "".join(ch if ch.isalnum() else "_" for ch in request.node.name)[:60]
    node = rclpy.create_node(name, context=rclpy_context)
    try:
        yield node
    finally:
        node.destroy_node()


def _spin_until(node: Any, predicate: Callable[[], bool], timeout: float) -> bool:
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout
    try:
        while not predicate() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.remove_node(node)
        executor.shutdown()
    return predicate()


@pytest.fixture
def spin_until(rclpy_context: Any) -> Callable[[Any, Callable[[], bool], float], bool]:
    """``spin_until(node, predicate, timeout)``: spin the node until ``predicate()`` holds or ``timeout`` s pass.

    Returns the predicate's last value. (A fixture, because ``--import-mode=importlib`` keeps
    conftest functions out of the tests' import path.)
    """
    return _spin_until


@dataclass
class RosProcess:
    """A Python subprocess started by :func:`ros_process`, with its output in files."""

    popen: subprocess.Popen[bytes]
    stdout_path: Path
    stderr_path: Path

    def stdout(self) -> str:
        """Everything the process wrote to stdout so far."""
        return self.stdout_path.read_text(errors="replace")

    def stderr(self) -> str:
        """Everything the process wrote to stderr so far."""
        return self.stderr_path.read_text(errors="replace")

    def stop(self, timeout: float = 5.0) -> int:
        """Stop the process (SIGINT, then SIGTERM, then SIGKILL, to its own process group); return its exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if self.popen.poll() is not None:
                break
            try:
                # The process leads its own group (start_new_session), so this reaches only it and its children.
                os.killpg(self.popen.pid, sig)
            except ProcessLookupError:
                break
            try:
                self.popen.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                continue
        return self.popen.wait()


@pytest.fixture
def ros_process(ros_environment: dict[str, str], tmp_path: Path) -> Iterator[Callable[..., RosProcess]]:
    """Factory starting ``python <args>`` with the test's full environment; every process is stopped at teardown.

    The child gets ``os.environ`` as the test sees it (so the ROS wheels' ``LD_LIBRARY_PATH`` and the
    isolation variables above) plus ``extra_env``. Output goes to files in ``tmp_path``.
    """
    started: list[RosProcess] = []

    def start(args: list[str], *, extra_env: dict[str, str] | None = None, name: str = "proc") -> RosProcess:
        env = os.environ.copy()
        env.update(extra_env or {})
        index = len(started)
        stdout_path = tmp_path / f"{name}_{index}.stdout"
        stderr_path = tmp_path / f"{name}_{index}.stderr"
        with stdout_path.open("wb") as out, stderr_path.open("wb") as err:
            popen = subprocess.Popen([sys.executable, *args], env=env, stdout=out, stderr=err, start_new_session=True)
        process = RosProcess(popen, stdout_path, stderr_path)
        started.append(process)
        return process

    yield start
    for process in started:
        process.stop()
