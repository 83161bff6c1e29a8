"""The nodes' own signal handling: a signal sets an event between callbacks instead of interrupting them."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

import pytest


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_sets_the_event_and_a_second_ctrl_c_interrupts(signum: int) -> None:
    from selfcontra_ros.ros.spinning import stop_on_signals

    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    with stop_on_signals() as stop:
        assert not stop.is_set()
        os.kill(os.getpid(), signum)  # delivered to the main thread before kill returns to Python code
        assert stop.is_set()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
    assert {sig: signal.getsignal(sig) for sig in before} == before


def test_spin_until_stopped_runs_callbacks_until_done_or_stop(rclpy_context: Any) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from selfcontra_ros.ros.spinning import spin_until_stopped

    node = rclpy.create_node("test_spin_until_stopped", context=rclpy_context)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    try:
        ticks: list[int] = []
        node.create_timer(0.01, lambda: ticks.append(1))
        assert spin_until_stopped(executor, threading.Event(), lambda: len(ticks) >= 3) is True
        assert len(ticks) == 3  # done() is looked at after every callback

        stop = threading.Event()
        node.create_timer(0.02, stop.set)
        assert spin_until_stopped(executor, stop) is False  # no done(): only the stop request ends it
        assert stop.is_set()

        rclpy_context.try_shutdown()
        assert spin_until_stopped(executor, threading.Event()) is False  # a shut-down context ends it at once
    finally:
        executor.shutdown()
        node.destroy_node()
