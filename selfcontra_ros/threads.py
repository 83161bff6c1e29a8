"""One cap on every thread pool the package uses: numba, OpenCV, BLAS/OpenMP and scikit-learn.

The labeler runs several pools side by side: numba's ``prange`` kernels,
OpenCV's StereoSGBM (its own pthreads pool), numpy/scipy BLAS (OpenBLAS) and
OpenMP (scikit-learn's Cython code), plus scikit-learn's ``n_jobs`` workers.
Left alone each one starts a thread per core, so a labeler sharing a robot's
computer with other nodes would take all of it. :func:`limit_threads` caps
them all at one number, e.g. from the node's ``threads`` parameter or the
command line's ``--threads``::

    from selfcontra_ros.threads import limit_threads
    applied = limit_threads(2)       # 0 = every core this process may run on

**Which caps are process-wide and which are per thread.** OpenCV's and
OpenBLAS's thread counts are global to the process. numba's
(``numba.set_num_threads``) and OpenMP's (``omp_set_num_threads``) are
*thread-local*: a thread started later begins with all of numba's threads
and OpenMP's process default again. A thread that runs numba or OpenMP code
therefore calls :func:`apply_thread_limit` once when it starts; it re-applies
the cap :func:`limit_threads` recorded (and does nothing when none was set).
scikit-learn's ``n_jobs`` is an argument of each call: :func:`cap_jobs`
turns a requested ``n_jobs`` into one within the cap.
"""

from __future__ import annotations

import os
import threading

import cv2
import numba
from threadpoolctl import threadpool_limits

from selfcontra_ros.errors import SelfContraError

__all__ = ["apply_thread_limit", "available_cores", "cap_jobs", "limit_threads", "thread_limit"]

# The cap recorded by limit_threads (None: never called), shared by every thread of the process.
_cap: int | None = None
_cap_lock = threading.Lock()
# Kept alive so that the BLAS/OpenMP limits stay applied (threadpoolctl restores the originals only on request).
_blas_limits: threadpool_limits | None = None


def available_cores() -> int:
    """Number of CPU cores this process may run on (its affinity mask, e.g. from ``taskset`` or a cgroup cpuset)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):  # no affinity API (macOS, Windows)
        return max(os.cpu_count() or 1, 1)


def _checked(n: object) -> int:
    # bool is an int subclass, but threads=True is surely a mistake.
    if isinstance(n, bool) or not isinstance(n, int):
        raise SelfContraError(f"threads is {n!r} ({type(n).__name__}); expected an integer >= 0 (0 = all cores)")
    if n < 0:
        raise SelfContraError(f"threads is {n}; expected an integer >= 0 (0 = all cores)")
    return n


def limit_threads(n: int = 0) -> int:
    """Cap every thread pool of the package at ``n`` threads, for this process and the threads it starts.

    Applies the cap to OpenCV (``cv2.setNumThreads``), to BLAS and OpenMP
    through threadpoolctl, and to numba in the calling thread
    (``numba.set_num_threads``, at most ``numba.config.NUMBA_NUM_THREADS``, the
    pool numba launched); records it for :func:`apply_thread_limit` (numba and
    OpenMP in threads started later) and :func:`cap_jobs` (scikit-learn).
    Calling it again replaces the cap.

    Args:
        n: threads per pool; 0 = the cores this process may run on
            (:func:`available_cores`). A value above that is lowered to it:
            more threads than cores only adds switching.

    Returns:
        The cap applied, in threads (1..available cores).

    Raises:
        SelfContraError: ``n`` is negative or not an integer.
    """
    global _cap, _blas_limits
    requested = _checked(n)
    cores = available_cores()
    applied = cores if requested == 0 else min(requested, cores)
    with _cap_lock:
        _cap = applied
        cv2.setNumThreads(applied)
        # numba first: launching its OpenMP pool resets this thread's OpenMP count, which threadpoolctl then sets.
        _set_numba_threads(applied)
        # OpenBLAS's count is global; OpenMP's applies to this thread (apply_thread_limit covers the others).
        _blas_limits = threadpool_limits(limits=applied)
    return applied


def _set_numba_threads(n: int) -> None:
    # numba refuses more than the pool it launched (NUMBA_NUM_THREADS, fixed at import).
    pool = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]  # set at runtime from the environment
    numba.set_num_threads(min(n, pool))


def thread_limit() -> int | None:
    """The cap set by the last :func:`limit_threads`, in threads; None when it was never called."""
    return _cap


def apply_thread_limit() -> int | None:
    """Apply the recorded cap to the calling thread's numba and OpenMP thread counts (both thread-local).

    Call it first thing in a thread that runs numba ``prange`` kernels or
    OpenMP code, e.g. a worker thread started after :func:`limit_threads`.

    Returns:
        The cap applied, in threads; None (and nothing changed) when
        :func:`limit_threads` was never called.
    """
    cap = _cap
    if cap is None:
        return None
    _set_numba_threads(cap)
    threadpool_limits(limits=cap, user_api="openmp")
    return cap


def cap_jobs(n_jobs: int | None) -> int | None:
    """A scikit-learn/joblib ``n_jobs`` within the recorded cap.

    Args:
        n_jobs: as scikit-learn takes it: None (one job, unless a joblib
            context says otherwise), a positive count, or a negative one
            (``-1`` = all cores, ``-2`` = all but one, ...).

    Returns:
        ``n_jobs`` unchanged when no cap is set or it is None; otherwise a
        positive count of at most the cap (a negative ``n_jobs`` counts from
        the available cores, as joblib does, and is at least 1).

    Raises:
        SelfContraError: ``n_jobs`` is 0 (scikit-learn refuses it too) or not an integer.
    """
    if n_jobs is None:
        return None
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, int) or n_jobs == 0:
        raise SelfContraError(f"n_jobs is {n_jobs!r}; expected None, a positive or a negative integer")
    cap = _cap
    if cap is None:
        return n_jobs
    wanted = n_jobs if n_jobs > 0 else max(available_cores() + 1 + n_jobs, 1)
    return min(wanted, cap)
