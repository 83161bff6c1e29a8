"""bench/soak.py's helpers: header stamps and image sizes read from real CDR, memory figures, /proc parsing."""

from __future__ import annotations

import os
from collections.abc import Callable
from types import ModuleType

import numpy as np
import pytest

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def soak(bench_script: Callable[[str], ModuleType]) -> ModuleType:
    return bench_script("soak")


@pytest.mark.parametrize("frame_id", ["", "c", "cam_left_optical", "abcd"])  # every CDR alignment of the size
def test_stamp_and_size_from_serialised_images(soak: ModuleType, frame_id: str) -> None:
    from rclpy.serialization import serialize_message

    from selfcontra_ros.ros.conversions import nanoseconds_to_stamp, numpy_to_image

    stamp_ns = 1_700_000_123_456_789_012
    msg = numpy_to_image(np.zeros((7, 13), np.uint8), "mono8", stamp=nanoseconds_to_stamp(stamp_ns), frame_id=frame_id)
    data = serialize_message(msg)
    assert soak._header_stamp(data) == stamp_ns
    assert soak._image_size(data) == "13x7"


def test_rss_figures_measure_growth_after_the_warmup(soak: ModuleType) -> None:
    # 10 minutes sampled every 2 s: 100 MiB during a 60 s warm-up, then 500 MiB growing 10 MiB a minute.
    times = np.arange(0.0, 600.0, 2.0)
    rss = np.where(times < 60.0, 100.0, 500.0 + 10.0 * (times - 60.0) / 60.0)
    samples = [(float(t), float(r), float(r)) for t, r in zip(times, rss, strict=True)]
    figures = soak._rss_figures(samples, 60.0)
    assert figures["slope"] == pytest.approx(10.0)
    # Medians over the first and the last 30 s after the warm-up (samples at 60..90 s and 568..598 s,
    # centred on 75 s and 583 s): 500 + 10 * 15/60 and 500 + 10 * 523/60.
    start, end = 500.0 + 10.0 * 15.0 / 60.0, 500.0 + 10.0 * 523.0 / 60.0
    assert figures["rss_start_mib"] == pytest.approx(start)
    assert figures["rss_end_mib"] == pytest.approx(end)
    assert figures["rss_growth_pct"] == pytest.approx(100.0 * (end - start) / start)


def test_memory_of_this_process_matches_its_own_status(soak: ModuleType) -> None:
    rss, hwm = soak._memory_mib(os.getpid())
    assert 0.0 < rss <= hwm
    ballast = np.ones(64 * 1024 * 1024 // 8)  # 64 MiB touched: resident
    rss_after, hwm_after = soak._memory_mib(os.getpid())
    assert rss_after - rss > 50.0 and hwm_after >= rss_after
    del ballast
