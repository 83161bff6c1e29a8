"""Soak benchmark: resident memory and per-frame latency of the labeler node over a long replay.

Replays a synthetic stereo bag in a loop (player node, ``loop:=true``) through
the labeler node (a separate process, as on a robot) for ``--minutes`` and
samples, every ``--sample`` seconds:

- the labeler process's resident memory (``VmRSS`` of ``/proc/PID/status``)
  and its peak (``VmHWM``), MiB;
- progress from the node's ``~/stats`` (frames matched, views labelled, drops)
  and the label images received;
- per-frame latency, measured by this process, which subscribes to the
  node's input and outputs (raw CDR, only the header stamp is read):
  ``latency`` = receipt of a frame's ``confidence`` minus receipt of the same
  stamp's left image (matching + confidence, the node's immediate outputs);
  ``label latency`` = receipt of a view's ``labels`` minus receipt of the
  left image ``label_delay`` frames later, the one that completes its window.

Each pass of the loop sends the stamps back in time, so the node resets its
session every pass (``time_jump_reset``), as with any looped bag: the soak
exercises those resets too. The labels of each pass's last ``label_delay``
views are never published (their window goes with the session). A node that
cannot keep up skips frames (its queues are bounded); those are counted in
the node's drops, not hidden.

It prints a table (one row per ``--report`` seconds) and ends with one JSON
line::

    {"minutes": M, "window": W, "size": "1242x375", "rss_start_mib": ..., "rss_end_mib": ...,
     "rss_growth_pct": ..., "rss_slope_mib_per_min": ..., "peak_mib": ..., "latency_ms_mean": ...,
     "latency_ms_p95": ..., "label_latency_ms_mean": ..., "label_latency_ms_p95": ..., "frames": ...,
     "views_labelled": ..., "drops": {...}}

``rss_start_mib`` is the median RSS over the first 30 s after the warm-up
(``--warmup`` s, default the first minute, or the first third of shorter
runs), ``rss_end_mib`` the median over the last 30 s (a quarter of the
measured span each, if shorter than 2 minutes); growth is their relative
difference and the slope a least-squares fit over all samples after the
warm-up. Targets (issue #7): growth within 5 % over a 10-minute soak, peak
under 2 GiB at window 20.

Network safety: ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a
``ROS_DOMAIN_ID`` of its own (``--domain``, default derived from the pid, in
1..101) and the packaged loopback Fast DDS profile, for this process and the
two it starts.

Usage::

    python bench/soak.py --minutes 10 [--window 20] [--bag PATH] [--size 1242x375] [--rate 0.2] [--threads 0]

The default rate (0.2: 2 frames/s, 30 s a pass) lets the labeler fill its
window of 20 views at KITTI size on a small machine within each pass; at the
camera's own 10 Hz most views are skipped (``label_queue_full``), each 6-s
pass resets the session before the window is full, and the soak no longer
measures a full window. ``--bag`` names a bag to replay; when it does not exist, the synthetic bag is
rendered there (and reused by the next run); without it the bag goes to a
temporary folder.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import struct
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.resources import config_file
from selfcontra_ros.ros.environment import start_python, stop_process

_MIB = 1024 * 1024
# Environment variables that could make a participant talk to other machines.
_OFF_LOOPBACK_VARIABLES = ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "ROS_LOCALHOST_ONLY")
# Seconds averaged for the start and the end RSS.
_RSS_SPAN_S = 30.0
_STARTUP_TIMEOUT_S = 120.0


def _isolate_ros(domain: int | None) -> int:
    """Loopback-only discovery and a domain of our own, in os.environ (the child processes inherit it)."""
    from selfcontra_ros.ros.environment import prepare_ros_environment

    chosen = domain if domain is not None else 1 + (os.getpid() * 7919) % 101
    os.environ["ROS_DOMAIN_ID"] = str(chosen)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    for name in _OFF_LOOPBACK_VARIABLES:
        os.environ.pop(name, None)
    prepare_ros_environment()
    return chosen


def _make_bag(path: Path, *, frames: int, size: tuple[int, int], seed: int) -> None:
    """Render the synthetic street and convert it to the bag folder ``path``."""
    with tempfile.TemporaryDirectory(prefix="soak_sequence_") as tmp:
        write_sequence(Path(tmp), scene="street", frames=frames, seed=seed, width=size[0], height=size[1])
        kitti_to_mcap(Path(tmp), path, progress=False)


def _bag_facts(path: Path) -> tuple[list[int], str]:
    """Sorted left-image stamps (ns) of the bag and its image size ``WxH``."""
    left = topics.bag_topic(topics.LEFT_IMAGE)
    stamps: list[int] = []
    size = "?"
    with open_bag(path) as bag:
        for message in bag.raw_messages():
            if message.topic == left:
                stamps.append(_header_stamp(message.data))
                if size == "?":
                    size = _image_size(message.data)
    return sorted(stamps), size


def _header_stamp(cdr: bytes) -> int:
    """Header stamp (ns) of a serialised message that starts with std_msgs/Header (Image, CameraInfo, ...)."""
    # 4-byte encapsulation header; its second byte says the byte order (1 = little endian).
    order = "<" if cdr[1] == 1 else ">"
    sec, nanosec = struct.unpack_from(order + "iI", cdr, 4)
    return sec * 1_000_000_000 + nanosec


def _image_size(cdr: bytes) -> str:
    """``WxH`` of a serialised sensor_msgs/Image (after the header's stamp and frame id)."""
    order = "<" if cdr[1] == 1 else ">"
    (length,) = struct.unpack_from(order + "I", cdr, 12)
    offset = 16 + length
    offset += (-offset) % 4  # CDR aligns the uint32 fields (relative to the 4-byte encapsulation header)
    height, width = struct.unpack_from(order + "II", cdr, offset)
    return f"{width}x{height}"


def _write_params(path: Path, *, window: int, delay: int, threads: int) -> None:
    """The package's labeler.yaml with this window, under ``/**`` so that it reaches the namespaced node."""
    document = yaml.safe_load(config_file("labeler.yaml").read_text())
    body = next(iter(document.values()))
    body["ros__parameters"]["threads"] = threads
    body["ros__parameters"]["labeler"].update(window_size=window, label_delay=delay)
    path.write_text(yaml.safe_dump({"/**": body}, sort_keys=False))


def _memory_mib(pid: int) -> tuple[float, float]:
    """``(VmRSS, VmHWM)`` of process ``pid`` in MiB (resident now, resident peak)."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            fields[name] = int(value.split()[0]) / 1024.0  # kB
    return fields["VmRSS"], fields["VmHWM"]


@dataclass
class _Monitor:
    """Receipt times of the node's input and outputs, by header stamp (this process's monotonic clock, s)."""

    stamps: list[int]
    delay: int
    inputs: dict[int, float] = field(default_factory=dict)
    latencies_ms: list[tuple[float, float]] = field(default_factory=list)  # (receipt time, latency)
    label_latencies_ms: list[tuple[float, float]] = field(default_factory=list)
    stats: dict[str, Any] | None = None
    labels_received: int = 0

    def __post_init__(self) -> None:
        self._index = {stamp: k for k, stamp in enumerate(self.stamps)}

    def on_input(self, data: bytes) -> None:
        self.inputs[_header_stamp(data)] = time.monotonic()

    def on_confidence(self, data: bytes) -> None:
        now = time.monotonic()
        sent = self.inputs.get(_header_stamp(data))
        if sent is not None and sent <= now:
            self.latencies_ms.append((now, 1e3 * (now - sent)))

    def on_labels(self, data: bytes) -> None:
        now = time.monotonic()
        self.labels_received += 1
        k = self._index.get(_header_stamp(data))
        if k is None or k + self.delay >= len(self.stamps):
            return
        trigger = self.inputs.get(self.stamps[k + self.delay])
        if trigger is not None and trigger <= now:
            self.label_latencies_ms.append((now, 1e3 * (now - trigger)))

    def on_stats(self, msg: Any) -> None:
        self.stats = json.loads(msg.data)


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, np.float64), q)) if values else math.nan


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def _round(value: float, digits: int = 1) -> float | None:
    return None if not math.isfinite(value) else round(value, digits)


def _rss_figures(samples: list[tuple[float, float, float]], warmup_s: float) -> dict[str, float]:
    """Start/end RSS, growth and slope over the samples ``(t_s, rss_mib, hwm_mib)`` after the warm-up."""
    after = [(t, rss) for t, rss, _ in samples if t >= warmup_s]
    if len(after) < 2:
        return {"rss_start_mib": math.nan, "rss_end_mib": math.nan, "rss_growth_pct": math.nan, "slope": math.nan}
    t0, t_end = after[0][0], after[-1][0]
    span = min(_RSS_SPAN_S, (t_end - t0) / 4.0)  # short runs: the two means must not share samples
    # Medians: a transient peak (a census volume of the confidence trainer) must not pass for growth.
    start = float(np.median([rss for t, rss in after if t <= t0 + span]))
    end = float(np.median([rss for t, rss in after if t >= t_end - span]))
    times = np.array([t for t, _ in after]) / 60.0
    values = np.array([rss for _, rss in after])
    slope = float(np.polyfit(times, values, 1)[0]) if np.ptp(times) > 0 else math.nan
    return {"rss_start_mib": start, "rss_end_mib": end, "rss_growth_pct": 100.0 * (end - start) / start, "slope": slope}


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run the soak; return the final figures (the JSON line's content)."""
    domain = _isolate_ros(args.domain)
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    work = Path(tempfile.mkdtemp(prefix="selfcontra_soak_"))
    bag = Path(args.bag) if args.bag else work / "bag"
    if not bag.exists():
        print(f"rendering {args.frames} frames of the synthetic street at {args.size[0]}x{args.size[1]} into {bag} ...")
        _make_bag(bag, frames=args.frames, size=args.size, seed=args.seed)
    stamps, size = _bag_facts(bag)
    delay = args.window // 2
    params = work / "labeler.yaml"
    _write_params(params, window=args.window, delay=delay, threads=args.threads)
    print(
        f"soak: {args.minutes:g} min, window {args.window} (delay {delay}), bag {bag} ({len(stamps)} frames, {size}), "
        f"rate {args.rate:g}, threads {args.threads}, ROS domain {domain}, logs in {work}",
        flush=True,
    )

    rclpy.init()
    node = rclpy.create_node("selfcontra_soak_monitor", namespace=topics.STEREO_NAMESPACE)
    monitor = _Monitor(stamps, delay)
    labeler = player = None
    try:
        # Best effort on the input: the monitor must never slow the player down.
        qos_in = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        qos_out = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        node.create_subscription(Image, topics.LEFT_IMAGE, monitor.on_input, qos_in, raw=True)
        outputs = [
            node.create_subscription(Image, topics.CONFIDENCE, monitor.on_confidence, qos_out, raw=True),
            node.create_subscription(Image, topics.LABELS, monitor.on_labels, qos_out, raw=True),
        ]
        stats_qos = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        node.create_subscription(String, "labeler/stats", monitor.on_stats, stats_qos)

        labeler = start_python(
            [
                "-m",
                "selfcontra_ros.ros.labeler_node",
                "--ros-args",
                "--params-file",
                str(params),
                "-r",
                f"__ns:={topics.STEREO_NAMESPACE}",
                "-p",
                "stats_period:=1.0",
            ],
            work / "labeler.log",
        )
        deadline = time.monotonic() + _STARTUP_TIMEOUT_S
        while not all(s.get_publisher_count() for s in outputs):
            if labeler.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"soak: the labeler did not come up; see {work / 'labeler.log'}")
            rclpy.spin_once(node, timeout_sec=0.1)
        player = start_python(
            [
                "-m",
                "selfcontra_ros.ros.player_node",
                "--ros-args",
                "-p",
                f"bag:={bag}",
                "-p",
                "loop:=true",
                "-p",
                f"rate:={args.rate}",
                "-p",
                "wait_for_subscribers:=6",  # the labeler's five inputs and the monitor's left image
            ],
            work / "player.log",
        )

        samples: list[tuple[float, float, float]] = []
        started = time.monotonic()
        end = started + 60.0 * args.minutes
        next_sample = started
        next_report = started + args.report
        print(
            f"{'minute':>6} {'rss_mib':>8} {'peak_mib':>8} {'frames':>7} {'labelled':>8} {'labels':>6} {'lat_mean':>8} "
            f"{'lat_p95':>8} {'lbl_mean':>8} {'lbl_p95':>8}  (latencies in ms, over the row's interval)",
            flush=True,
        )
        while time.monotonic() < end:
            for process, name in ((labeler, "labeler"), (player, "player")):
                if process.poll() is not None:
                    raise RuntimeError(
                        f"soak: the {name} exited with {process.returncode}; see {work / (name + '.log')}"
                    )
            rclpy.spin_once(node, timeout_sec=0.05)
            now = time.monotonic()
            if now >= next_sample:
                rss, hwm = _memory_mib(labeler.pid)
                samples.append((now - started, rss, hwm))
                next_sample += args.sample
            if now >= next_report and samples:
                since = next_report - args.report
                lat = [v for t, v in monitor.latencies_ms if t >= since]
                lbl = [v for t, v in monitor.label_latencies_ms if since <= t]
                counts = (monitor.stats or {}).get("counts", {})
                print(
                    f"{(now - started) / 60.0:6.2f} {samples[-1][1]:8.1f} {samples[-1][2]:8.1f} "
                    f"{counts.get('frames', 0):7d} {counts.get('views_labelled', 0):8d} {monitor.labels_received:6d} "
                    f"{_mean(lat):8.1f} {_percentile(lat, 95):8.1f} {_mean(lbl):8.1f} {_percentile(lbl, 95):8.1f}",
                    flush=True,
                )
                next_report += args.report
        elapsed = time.monotonic() - started
    finally:
        stop_process(player, timeout=15.0)
        stop_process(labeler, timeout=15.0)
        node.destroy_node()
        rclpy.try_shutdown()

    warmup = args.warmup if args.warmup is not None else min(60.0, 60.0 * args.minutes / 3.0)
    memory = _rss_figures(samples, warmup)
    after = [v for t, v in monitor.latencies_ms if t - started >= warmup]
    after_labels = [v for t, v in monitor.label_latencies_ms if t - started >= warmup]
    stats = monitor.stats or {}
    return {
        "minutes": round(elapsed / 60.0, 2),
        "window": args.window,
        "size": size,
        "threads": stats.get("threads"),
        "warmup_s": warmup,
        "rss_start_mib": _round(memory["rss_start_mib"]),
        "rss_end_mib": _round(memory["rss_end_mib"]),
        "rss_growth_pct": _round(memory["rss_growth_pct"], 2),
        "rss_slope_mib_per_min": _round(memory["slope"], 2),
        "peak_mib": _round(max((hwm for _, _, hwm in samples), default=math.nan)),
        "latency_ms_mean": _round(_mean(after)),
        "latency_ms_p95": _round(_percentile(after, 95)),
        "label_latency_ms_mean": _round(_mean(after_labels)),
        "label_latency_ms_p95": _round(_percentile(after_labels, 95)),
        "frames": stats.get("counts", {}).get("frames"),
        "views_labelled": stats.get("counts", {}).get("views_labelled"),
        "labels_received": monitor.labels_received,
        "confidence_forest": stats.get("counts", {}).get("confidence_forest"),
        "time_jumps": stats.get("counts", {}).get("time_jumps"),
        "drops": {k: v for k, v in stats.get("drops", {}).items() if v},
    }


def _size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the arguments, run the soak, print the JSON line; returns the exit code."""
    parser = argparse.ArgumentParser(prog="soak", description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, required=True, help="soak duration, minutes")
    parser.add_argument("--window", type=int, default=20, help="labeler window size (default 20; delay = half)")
    parser.add_argument("--bag", default=None, help="bag to replay; rendered there when absent (default: temporary)")
    parser.add_argument("--frames", type=int, default=60, help="frames of a rendered bag (default 60)")
    parser.add_argument("--size", type=_size, default=(1242, 375), help="size WxH of a rendered bag (default KITTI)")
    parser.add_argument("--seed", type=int, default=1, help="synthetic scene seed (default 1)")
    parser.add_argument(
        "--rate", type=float, default=0.2, help="playback rate factor (default 0.2: 2 Hz, 30 s a pass of 60 frames)"
    )
    parser.add_argument("--threads", type=int, default=0, help="the node's threads parameter (default 0: all cores)")
    parser.add_argument("--sample", type=float, default=2.0, help="seconds between memory samples (default 2)")
    parser.add_argument("--report", type=float, default=30.0, help="seconds between table rows (default 30)")
    parser.add_argument("--warmup", type=float, default=None, help="seconds before growth is measured")
    parser.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: from the pid, 1..101)")
    args = parser.parse_args(argv)
    figures = run(args)
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
