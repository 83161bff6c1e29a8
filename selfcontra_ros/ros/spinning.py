"""Spin a node until its work is done or SIGINT/SIGTERM asks it to stop, without rclpy's signal handlers.

rclpy's own handlers shut the context down inside the signal handler and raise
``KeyboardInterrupt`` in whatever Python code runs at that moment. When that
code is a ``__del__`` (rclpy's ``Future.__del__``, for one) Python swallows the
interrupt, and the executor's next wait fails with ``RCLError: the given
context is not valid``: the player exited with code 1 on Ctrl-C that way. Here
a signal only sets an event, the loop looks at it between callbacks, and the
node is destroyed and the context shut down in order, so a node can still
publish while it stops. A second Ctrl-C interrupts at once (e.g. a long
flush), as Python's default handler would.

Nodes using this call ``rclpy.init(signal_handler_options=SignalHandlerOptions.NO)``.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType

from rclpy.executors import Executor

#: How long one ``spin_once`` waits for work before the stop condition is looked at again.
SPIN_PERIOD_S = 0.1


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """Within the block, SIGINT and SIGTERM set the yielded event; the previous handlers return afterwards."""
    stop = threading.Event()

    def request_stop(signum: int, frame: FrameType | None) -> None:
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def spin_until_stopped(executor: Executor, stop: threading.Event, done: Callable[[], bool] | None = None) -> bool:
    """Spin ``executor`` until ``stop`` is set, the context shuts down or ``done()`` holds.

    Returns:
        True when ``done()`` ended the loop, False for a stop request or a context shut down elsewhere.
    """
    while not stop.is_set() and executor.context.ok():
        if done is not None and done():
            return True
        executor.spin_once(timeout_sec=SPIN_PERIOD_S)
    return False
