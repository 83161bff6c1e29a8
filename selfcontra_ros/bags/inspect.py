"""What a bag holds and how to label it: the ``selfcontra inspect BAG`` command.

:func:`inspect_bag` reads a bag once (log times only, plus the camera infos,
the first image headers and the TF messages, which it decodes) and reports

* every topic with its type, message count and rate (messages per second of
  log time between its first and last message);
* the stereo pairs it finds: image topics (``sensor_msgs/Image`` or
  ``CompressedImage`` on ``.../compressed``) whose names differ only in
  ``left``/``right`` (also ``infra1``/``infra2``, ``cam0``/``cam1``), each with
  its ``camera_info`` (``<image topic's folder>/camera_info``), whether it
  looks raw (``raw`` but not ``rect`` in the name, with a non-zero
  distortion: rectify it; RealSense's ``image_rect_raw`` is rectified) or
  rectified, and how far apart the two cameras' stamps are;
* the TF frames (``/tf`` and ``/tf_static``), parent -> child, static or not;
* pose topics (PoseStamped, Odometry).

:func:`suggest_command` turns that into a ``selfcontra label`` command line
for the first pair: ``--namespace`` and ``--remap`` rules, ``--image-transport``,
``--rectify``, ``--sync approximate --slop`` when the stamps differ, and the
poses (a pose topic if there is one, else TF with the root of the camera's
tree as world frame). :func:`format_report` prints it all.
"""

from __future__ import annotations

import math
import posixpath
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from selfcontra_ros.bags import topics
from selfcontra_ros.bags.reader import open_bag
from selfcontra_ros.bags.tf import normalize_frame
from selfcontra_ros.ros.conversions import stamp_to_nanoseconds

__all__ = ["BagReport", "StereoPair", "format_report", "inspect_bag", "suggest_command"]

_NS_PER_S = 1_000_000_000
_IMAGE_TYPES = (topics.IMAGE_TYPE, topics.COMPRESSED_IMAGE_TYPE)
#: Name pairs that tell a left camera from a right one.
_SIDES = (("left", "right"), ("infra1", "infra2"), ("cam0", "cam1"))
#: Image headers compared per camera for the stamp offset.
_STAMP_SAMPLES = 20


@dataclass
class StereoPair:
    """A left/right pair of image topics (absolute names, ``/compressed`` included)."""

    left: str
    right: str
    left_info: str | None
    right_info: str | None
    compressed: bool
    raw: bool
    left_frame: str | None = None
    max_stamp_offset_s: float | None = None


@dataclass
class BagReport:
    """What :func:`inspect_bag` found (see the module docstring)."""

    path: Path
    topics: list[dict[str, Any]]
    pairs: list[StereoPair]
    tf_links: list[tuple[str, str, bool]] = field(default_factory=list)
    pose_topics: list[str] = field(default_factory=list)
    duration_s: float = 0.0


def _base(topic: str) -> str:
    return topic[: -len(topics.COMPRESSED_SUFFIX)] if topic.endswith(topics.COMPRESSED_SUFFIX) else topic


def _other_side(topic: str) -> str | None:
    for left, right in _SIDES:
        if left in topic:
            return topic.replace(left, right)
    return None


def inspect_bag(path: Path | str) -> BagReport:
    """Read a bag and describe it (see the module docstring).

    Raises:
        BagError: the bag cannot be read.
    """
    path = Path(path)
    with open_bag(path) as bag:
        summaries = dict(bag.topics)
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        image_topics = {t for t, s in summaries.items() if s.msgtype in _IMAGE_TYPES}
        info_topics = {t for t, s in summaries.items() if s.msgtype == topics.CAMERA_INFO_TYPE}
        tf_topics = {t for t, s in summaries.items() if s.msgtype == topics.TF_TYPE}
        stamps: dict[str, list[int]] = defaultdict(list)
        infos: dict[str, Any] = {}
        links: dict[tuple[str, str], bool] = {}
        for record in bag.raw_messages():
            name = record.topic
            first.setdefault(name, record.stamp_ns)
            last[name] = record.stamp_ns
            if name in image_topics and len(stamps[name]) < _STAMP_SAMPLES:
                stamps[name].append(stamp_to_nanoseconds(bag.deserialize(record.data, record.msgtype).header.stamp))
            elif name in info_topics and name not in infos:
                infos[name] = bag.deserialize(record.data, record.msgtype)
            elif name in tf_topics:
                static = name.endswith("tf_static")
                for item in bag.deserialize(record.data, record.msgtype).transforms:
                    key = (normalize_frame(item.header.frame_id), normalize_frame(item.child_frame_id))
                    links[key] = links.get(key, False) or static
        duration_s = bag.duration_ns / _NS_PER_S
    rows = []
    for name, summary in summaries.items():
        span = (last.get(name, 0) - first.get(name, 0)) / _NS_PER_S
        rate = (summary.message_count - 1) / span if span > 0 else math.nan
        rows.append({"topic": name, "type": summary.msgtype, "count": summary.message_count, "rate_hz": rate})
    pairs = []
    for left in sorted(image_topics):
        right = _other_side(left)
        if right is None or right not in image_topics or right == left:
            continue
        infos_of = [posixpath.dirname(_base(t)) + "/camera_info" for t in (left, right)]
        left_info, right_info = (t if t in info_topics else None for t in infos_of)
        info = infos.get(left_info) if left_info else None
        distorted = info is not None and bool(np.any(np.asarray(info.d, dtype=float)))
        # image_rect_raw (RealSense) is rectified: "raw" there means unprocessed colour, not distorted.
        name = posixpath.basename(_base(left))
        raw = "raw" in name and "rect" not in name and (distorted or info is None)
        offsets = [abs(a - b) for a, b in zip(stamps[left], stamps[right], strict=False)]
        pairs.append(
            StereoPair(
                left=left,
                right=right,
                left_info=left_info,
                right_info=right_info,
                compressed=summaries[left].msgtype == topics.COMPRESSED_IMAGE_TYPE,
                raw=raw,
                left_frame=normalize_frame(info.header.frame_id) if info is not None else None,
                max_stamp_offset_s=max(offsets) / _NS_PER_S if offsets else None,
            )
        )
    poses = sorted(t for t, s in summaries.items() if s.msgtype in topics.POSE_TYPES)
    tf_links = sorted((parent, child, static) for (parent, child), static in links.items())
    return BagReport(path, rows, pairs, tf_links, poses, duration_s)


def _root(links: list[tuple[str, str, bool]], frame: str) -> str:
    parents = {child: parent for parent, child, _ in links}
    seen = {frame}
    while frame in parents and parents[frame] not in seen:
        frame = parents[frame]
        seen.add(frame)
    return frame


def suggest_command(report: BagReport, out: str = "OUT") -> str | None:
    """A ``selfcontra label`` command line for the report's first stereo pair (None without a pair)."""
    if not report.pairs:
        return None
    pair = report.pairs[0]
    names = [_base(pair.left), _base(pair.right)] + [t for t in (pair.left_info, pair.right_info) if t]
    namespace = posixpath.commonpath(names)
    default_image = (topics.LEFT_RAW, topics.RIGHT_RAW) if pair.raw else (topics.LEFT_IMAGE, topics.RIGHT_IMAGE)
    wanted = {default_image[0]: _base(pair.left), default_image[1]: _base(pair.right)}
    if pair.left_info and pair.right_info:
        wanted.update({topics.LEFT_INFO: pair.left_info, topics.RIGHT_INFO: pair.right_info})
    parts = ["selfcontra", "label", str(report.path), "--out", out, "--namespace", namespace]
    for name, topic in wanted.items():
        relative = posixpath.relpath(topic, namespace)
        if relative != name:
            parts += ["--remap", f"{name}:={relative}"]
    if pair.compressed:
        parts += ["--image-transport", "compressed"]
    if pair.raw:
        parts.append("--rectify")
    if pair.max_stamp_offset_s:
        slop = max(0.005, math.ceil(pair.max_stamp_offset_s * 2000.0) / 1000.0)  # twice the offset, whole ms
        parts += ["--sync", "approximate", "--slop", f"{slop:g}"]
    if report.pose_topics:
        parts += ["--pose-topic", report.pose_topics[0]]
    elif report.tf_links and pair.left_frame:
        parts += ["--pose-source", "tf", "--world-frame", _root(report.tf_links, pair.left_frame)]
    return " ".join(parts)


def format_report(report: BagReport) -> str:
    """The report as text: topics table, stereo pairs, TF frames, pose topics and the suggested command."""
    width = max([len(row["topic"]) for row in report.topics] + [5])
    lines = [f"bag {report.path}: {len(report.topics)} topics, {report.duration_s:.3f} s", ""]
    lines.append(f"{'topic':<{width}}  {'type':<34} {'count':>7} {'rate':>9}")
    for row in report.topics:
        rate = f"{row['rate_hz']:.2f} Hz" if math.isfinite(row["rate_hz"]) else "-"
        lines.append(f"{row['topic']:<{width}}  {row['type']:<34} {row['count']:>7} {rate:>9}")
    lines.append("")
    if not report.pairs:
        lines.append("no stereo pair found (image topics differing only in left/right); name them with --remap")
    for pair in report.pairs:
        kind = ("compressed " if pair.compressed else "") + ("raw (distorted: --rectify)" if pair.raw else "rectified")
        offset = f", stamps up to {pair.max_stamp_offset_s * 1000:.1f} ms apart" if pair.max_stamp_offset_s else ""
        lines.append(f"stereo pair: {pair.left} | {pair.right} ({kind}{offset})")
        lines.append(f"  camera_info: {pair.left_info or 'none found'} | {pair.right_info or 'none found'}")
        if pair.left_frame:
            lines.append(f"  left camera frame: {pair.left_frame}")
    if report.tf_links:
        lines.append("TF: " + ", ".join(f"{p} -> {c}{' (static)' if s else ''}" for p, c, s in report.tf_links))
    if report.pose_topics:
        lines.append("pose topics: " + ", ".join(report.pose_topics))
    command = suggest_command(report)
    if command:
        lines += ["", "suggested command:", "  " + command]
    return "\n".join(lines) + "\n"
