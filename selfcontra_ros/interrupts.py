"""Ctrl-C and SIGTERM for the offline commands: stop at a safe point, say what was written.

A signal that interrupts a numba kernel, its compilation or a C callback
(llvmlite, OpenCV) turns into a ``SystemError`` or ``RuntimeError`` with a
long traceback, or is swallowed and the run goes on. So :func:`handle_signals`
(the ``selfcontra`` command installs it) only *records* SIGINT and SIGTERM,
and the long loops call :func:`check` between frames, where stopping is safe:
it raises :class:`Interrupted`, which unwinds through the ``with``/``finally``
blocks that close bags and write ``metrics.json``. Code that may block for
long without Python-level loops and has no such problem (a scikit-learn fit)
runs inside :func:`immediate`, where the signal raises at once. A second
signal raises at once anywhere: a user who presses Ctrl-C twice means it.

:class:`Interrupted` derives from ``KeyboardInterrupt``, for SIGTERM too, so
that cleanup written for Ctrl-C also runs on SIGTERM, and ``except
Exception`` never swallows it. Its ``done`` says how far the run got; the
function that knows (e.g. the bag labeler) sets it on the way out.

The state is per process (signals are): without :func:`handle_signals`, as in
a library caller or a worker process, :func:`check` never raises and a
signal keeps Python's default behaviour.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = ["HANDLED_SIGNALS", "Interrupted", "check", "handle_signals", "immediate", "pending_signal"]

#: Signals turned into :class:`Interrupted`.
HANDLED_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal at a safe point.

    Attributes:
        signum: the signal (``signal.SIGINT`` or ``signal.SIGTERM``).
        done: how far the run got and what it wrote, one phrase (empty until a caller sets it).
    """

    def __init__(self, signum: int, done: str = "") -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)
        self.done = done

    @property
    def signal_name(self) -> str:
        """``SIGINT`` or ``SIGTERM``."""
        return signal.Signals(self.signum).name

    @property
    def exit_status(self) -> int:
        """The shell's status for death by this signal: 130 for SIGINT, 143 for SIGTERM."""
        return 128 + self.signum


class _State:
    def __init__(self) -> None:
        self.installed = False
        self.signum: int | None = None
        self.immediate_depth = 0


_STATE = _State()


def _handler(signum: int, frame: FrameType | None) -> None:
    first = _STATE.signum is None
    _STATE.signum = signum
    if _STATE.immediate_depth > 0 or not first:
        raise Interrupted(signum)


def pending_signal() -> int | None:
    """The signal received so far (SIGINT or SIGTERM), or None."""
    return _STATE.signum


def check() -> None:
    """Raise :class:`Interrupted` if a signal arrived since :func:`handle_signals` was entered.

    Call it between units of work (frames, messages) where stopping leaves the output consistent.
    """
    if _STATE.signum is not None:
        raise Interrupted(_STATE.signum)


@contextmanager
def immediate() -> Iterator[None]:
    """Let a signal raise at once inside this block (long calls with no safe point of their own).

    Only on the main thread, where signal handlers run: a background thread
    (the node's retraining) entering it must not make the main thread raise
    inside a kernel.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    check()
    _STATE.immediate_depth += 1
    try:
        yield
    finally:
        _STATE.immediate_depth -= 1


@contextmanager
def handle_signals() -> Iterator[None]:
    """Record SIGINT and SIGTERM for :func:`check` while the block runs; restore the old handlers after.

    A signal that the process inherited as ignored (a job started with ``&``
    from a script ignores SIGINT; ``nohup`` ignores SIGHUP) stays ignored.
    Outside the main thread, or nested, it does nothing.
    """
    if _STATE.installed or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for signum in HANDLED_SIGNALS:
        old = signal.getsignal(signum)
        if old is not signal.SIG_IGN:
            previous[signum] = old
            signal.signal(signum, _handler)
    _STATE.installed, _STATE.signum, _STATE.immediate_depth = True, None, 0
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)
        _STATE.installed, _STATE.signum = False, None
