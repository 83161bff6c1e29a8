"""Where the tasks of a batch run: a Ray cluster (local by default), or this process when Ray is not installed.

:func:`open_engine` returns an engine whose :meth:`~RayEngine.run` takes one
plain function and its argument tuples and yields ``(position, result)`` as
the calls finish, in completion order:

- :class:`RayEngine`: one Ray task per call with ``num_cpus=cpus_per_task``
  and ``max_retries`` (Ray re-runs a task whose worker process died, at most
  that many times; an exception the function raises is not retried). Where it
  runs, by ``address``:

  * ``None`` or ``"local"``: a Ray cluster already started in this process is
    reused (and left running); else a **local cluster** on this machine's
    cores is started (:func:`start_local_cluster`) and shut down at the end.
    It binds to the loopback interface only, has no dashboard, and Ray's
    usage statistics (which Ray would send to the internet) are off.
  * ``"auto"``: the cluster this machine joined (``ray start --head`` here, or
    ``ray start --address HEAD:6379`` as a worker node).
  * ``"ray://HOST:PORT"``: a remote cluster through Ray Client.

  The inputs' paths must then be readable on every node (a shared file system),
  and the package installed there.

- :class:`SequentialEngine`: the calls one after another in this process,
  when Ray cannot be imported; :func:`open_engine` says so on ``echo``.

The functions run must be importable module-level functions of plain
arguments (Ray ships them by reference); their results travel back through
Ray's object store.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from types import ModuleType
from typing import Any, Protocol

from selfcontra_ros import interrupts
from selfcontra_ros.errors import BatchError
from selfcontra_ros.threads import available_cores

__all__ = [
    "LOCAL",
    "LOOPBACK",
    "MAX_RETRIES",
    "NOT_INSTALLED",
    "Engine",
    "RayEngine",
    "SequentialEngine",
    "TaskLostError",
    "import_ray",
    "local_ray_environment",
    "open_engine",
    "start_local_cluster",
]

#: ``--address`` value (and default) of a local cluster on this machine.
LOCAL = "local"
#: The only interface a local cluster binds to.
LOOPBACK = "127.0.0.1"
#: Ray re-runs a task whose worker process died at most this many times.
MAX_RETRIES = 2
#: What the fallback prints.
NOT_INSTALLED = (
    "Ray is not installed (pip install 'selfcontra_ros[cluster]'): running the {n} input(s) one after another"
)
# Environment of a local cluster, set before Ray is imported (Ray reads some of it at import time):
# no usage statistics sent to the internet, and every address Ray picks is the loopback
# (Ray's single-machine mode, otherwise only the default on macOS and Windows).
_LOCAL_ENVIRONMENT = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
#: How long the driver waits for a result before it looks at pending signals (Ctrl-C), seconds.
_POLL_S = 0.5


class TaskLostError(Exception):
    """A task that ended without a result: its worker died more often than Ray retries, or Ray lost it."""


class Engine(Protocol):
    """Runs a function over argument tuples; see the module docstring.

    Attributes:
        description: where the tasks run, for the log and the summary.
        remote: each task runs in a worker process of its own (Ray), not in this one.
    """

    description: str
    remote: bool

    def run(self, function: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
        """Yield ``(position in calls, result)`` as the calls finish; a :class:`TaskLostError` for a lost one."""
        ...

    def close(self) -> None:
        """Release the engine (shut down the local cluster it started)."""
        ...


def local_ray_environment() -> None:
    """Set the environment of a local Ray cluster (no usage statistics, loopback only) in this process.

    Call before Ray is imported; :func:`start_local_cluster` does. The Ray processes it starts inherit it.
    """
    for key, value in _LOCAL_ENVIRONMENT.items():
        os.environ[key] = value


def import_ray() -> ModuleType | None:
    """The ``ray`` module, or None when it is not installed (the ``[cluster]`` extra)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # a driver never reports usage either
    try:
        import ray
    except ImportError:
        return None
    return ray


def start_local_cluster(num_cpus: int | None = None, *, object_store_bytes: int | None = None) -> None:
    """Start a Ray cluster on this machine for this process: loopback only, no dashboard, no usage statistics.

    Args:
        num_cpus: CPUs Ray may schedule (None: the cores this process may use).
        object_store_bytes: size of Ray's shared-memory object store (None: Ray's default share of memory).

    Raises:
        BatchError: Ray is not installed, is already running in this process, or bound to another
            address than the loopback (Ray was imported before :func:`local_ray_environment`).
    """
    local_ray_environment()
    ray = import_ray()
    if ray is None:
        raise BatchError("Ray is not installed (pip install 'selfcontra_ros[cluster]')")
    if ray.is_initialized():
        raise BatchError("Ray is already running in this process; reuse it instead of starting another cluster")
    ray.init(
        num_cpus=available_cores() if num_cpus is None else int(num_cpus),
        object_store_memory=object_store_bytes,
        include_dashboard=False,
        _node_ip_address=LOOPBACK,
        configure_logging=False,
    )
    address = str(ray.get_runtime_context().gcs_address)
    if not address.startswith(LOOPBACK + ":"):
        ray.shutdown()
        raise BatchError(
            f"the local Ray cluster bound to {address}, not to {LOOPBACK}: Ray was imported before its "
            "environment was set; set RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 before importing ray"
        )


class SequentialEngine:
    """The calls one after another in this process (no Ray)."""

    description = "this process, one input after another (Ray is not installed)"
    remote = False

    def run(self, function: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
        """Yield ``(position, function(*call))`` in order."""
        for position, call in enumerate(calls):
            interrupts.check()
            yield position, function(*call)

    def close(self) -> None:
        """Nothing to release."""


class RayEngine:
    """Ray tasks on the cluster of ``address`` (module docstring)."""

    remote = True

    def __init__(
        self, ray: ModuleType, address: str | None, *, cpus_per_task: int = 1, max_retries: int = MAX_RETRIES
    ) -> None:
        if cpus_per_task < 1:
            raise BatchError(f"--cpus-per-task is {cpus_per_task}; expected at least 1")
        self._ray = ray
        self._cpus = int(cpus_per_task)
        self._retries = int(max_retries)
        self._started = False
        if address in (None, LOCAL):
            if not ray.is_initialized():
                start_local_cluster()
                self._started = True
        elif ray.is_initialized():
            raise BatchError(f"Ray is already running in this process; cannot connect to {address} too")
        else:
            try:
                ray.init(address=address, configure_logging=False)
            except Exception as exc:  # Ray raises ConnectionError, ValueError, RuntimeError, ...
                raise BatchError(f"cannot connect to the Ray cluster at {address}: {exc}") from exc
            self._started = True
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if cpus < self._cpus:
            self.close()
            raise BatchError(f"--cpus-per-task {self._cpus} is more than the Ray cluster's {cpus} CPUs")
        where = "a local Ray cluster" if address in (None, LOCAL) else f"the Ray cluster at {address}"
        self.description = f"{where}: {cpus} CPUs, {cpus // self._cpus} task(s) at a time"

    def run(self, function: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
        """Submit one task per call; yield results as they finish; cancel what is left on an interrupt."""
        ray = self._ray
        remote = ray.remote(function).options(num_cpus=self._cpus, max_retries=self._retries)
        positions = {remote.remote(*call): position for position, call in enumerate(calls)}
        pending = list(positions)
        try:
            while pending:
                interrupts.check()
                ready, pending = ray.wait(pending, num_returns=1, timeout=_POLL_S)
                for ref in ready:
                    try:
                        result: Any = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        result = TaskLostError(
                            f"{type(exc).__name__} after at most {self._retries} retries: {_first_line(exc)}"
                        )
                    yield positions[ref], result
        finally:
            for ref in pending:  # interrupted, or the caller stopped early: the rest does not run
                ray.cancel(ref, force=True)

    def close(self) -> None:
        """Shut down the cluster (or connection) this engine started; a cluster it found keeps running."""
        if self._started:
            self._ray.shutdown()
            self._started = False


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def open_engine(
    address: str | None, *, cpus_per_task: int = 1, inputs: int = 0, echo: Callable[[str], None] | None = print
) -> Engine:
    """The engine of a batch: Ray at ``address`` (module docstring), or :class:`SequentialEngine` without Ray.

    Args:
        address: ``None``/``"local"``, ``"auto"`` or ``"ray://HOST:PORT"``.
        cpus_per_task: CPUs (and threads) per task.
        inputs: number of inputs, for the fallback's message.
        echo: where the fallback's message goes.

    Raises:
        BatchError: ``address`` names a cluster but Ray is not installed, or the cluster cannot be reached.
    """
    if address in (None, LOCAL):
        local_ray_environment()  # before the first import of Ray, which reads part of it then
    ray = import_ray()
    if ray is None:
        if address not in (None, LOCAL):
            raise BatchError(f"--address {address} needs Ray: pip install 'selfcontra_ros[cluster]'")
        if echo is not None:
            echo(NOT_INSTALLED.format(n=inputs))
        return SequentialEngine()
    return RayEngine(ray, address, cpus_per_task=cpus_per_task)
