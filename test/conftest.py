"""Shared fixtures: the real-data folder beside the repository, the numba kernels compiled once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


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
