"""Shared fixtures: the real-data folder beside the repository, the numba kernels compiled once per session,
the benchmark scripts loaded as modules."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The ``../shared/data`` folder of real KITTI and Middlebury samples; skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it lives beside the repository as ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def compiled_kernels() -> float:
    """The numba kernels of labeling and online confidence compiled before the test times anything (seconds taken).

    On an empty numba cache the first labeling compiles for about a minute on a busy 2-core machine; a test
    that waits a few seconds for a labeler's first outputs would time out while the compiler runs. The kernels
    are cached on disk (``cache=True``) and the labeler processes the tests start inherit this process's
    environment (``NUMBA_CACHE_DIR`` included), so compiling here warms them as well: they load the machine
    code in about a second instead of compiling it again.
    """
    from selfcontra_ros.warmup import warm_up

    return warm_up()


@pytest.fixture(scope="session")
def bench_script() -> Iterator[Callable[[str], ModuleType]]:
    """A loader of ``bench/<name>.py`` as a module (loaded once per session, taken out of ``sys.modules`` after)."""
    loaded: dict[str, ModuleType] = {}

    def load(name: str) -> ModuleType:
        if name not in loaded:
            spec = importlib.util.spec_from_file_location(f"{name}_bench", BENCH / f"{name}.py")
            assert spec is not None and spec.loader is not None
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module  # dataclasses look their module up there
            spec.loader.exec_module(module)
            loaded[name] = module
        return loaded[name]

    try:
        yield load
    finally:
        for module in loaded.values():
            sys.modules.pop(module.__name__, None)
