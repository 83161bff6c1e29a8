"""A small TF buffer without ROS: the pose of one frame in another from ``/tf`` and ``/tf_static``.

Robots publish their poses as a tree of transforms (REP 105): ``odom ->
base_link`` on ``/tf`` at the odometry's rate and ``base_link ->
camera_left_optical_frame`` once on ``/tf_static``. :class:`TFBuffer` keeps
those transforms (``tf2_msgs/TFMessage`` of rclpy or rosbags alike, each a
duck-typed ``geometry_msgs/TransformStamped``) and answers, like tf2's
``Buffer.lookup_transform(target, source, time)``, with the 4x4 transform
``T_target_source`` that maps points of ``source`` into ``target``, i.e. the
pose of ``source`` in ``target``: ``lookup("odom", "camera_left_optical_frame",
stamp)`` is ``T_odom_camera``.

* **The tree** is walked between any two frames: from each frame up to its
  root, then down from their lowest common ancestor, so either frame may be
  the parent (``lookup(child, parent)`` gives the inverse).
* **Time.** Every dynamic link is a :class:`~selfcontra_ros.bags.sync.PoseBuffer`
  (translation interpolated linearly, rotation by slerp, a little
  extrapolation allowed at the ends, gaps refused); static links hold at every
  stamp. A lookup interpolates each dynamic link of the chain at the same stamp.
* **Bounded history**: each dynamic link keeps the last ``cache_time_s`` seconds
  (tf2's default, 10 s), and at most ``capacity`` transforms.
* **Errors** are :class:`~selfcontra_ros.errors.TransformError` with a
  ``reason`` for drop counters and a message naming what is missing: an
  unknown frame (with the frames known), two trees with no link between them
  (naming the two roots the missing link would join), or a link without data
  at the stamp (how far the stamp lies outside its history).

:class:`TransformSource` is the interface the labelers need, so that the ROS
node can satisfy it with tf2_ros's ``Buffer`` on an install that has it and
with this buffer (fed by ``/tf`` subscriptions) where it has not.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.bags.sync import PoseBuffer, PoseMiss, matrix_from_pose, validate_pose
from selfcontra_ros.errors import PoseError, TransformError
from selfcontra_ros.geometry import invert_pose
from selfcontra_ros.ros.conversions import stamp_to_nanoseconds

__all__ = [
    "TFBuffer",
    "TransformSource",
    "matrix_from_transform",
    "normalize_frame",
]

_NS_PER_S = 1_000_000_000
#: Stamp reported as the newest of a chain made of static links only (they hold at every time).
_FOREVER_NS = 2**63 - 1
#: ``PoseMiss`` of a dynamic link -> the ``TransformError.reason`` of the lookup.
_MISS_REASONS = {
    PoseMiss.EMPTY: "tf_none_yet",
    PoseMiss.BEFORE: "tf_before_buffer",
    PoseMiss.AFTER: "tf_after_buffer",
    PoseMiss.GAP: "tf_gap",
}


class TransformSource(Protocol):
    """What the labelers ask of TF: the pose of ``source_frame`` in ``target_frame`` at a stamp.

    :class:`TFBuffer` implements it; a tf2_ros ``Buffer`` adapter can too.
    """

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int) -> NDArray[np.float64]:
        """4x4 ``T_target_source`` (metres) at ``stamp_ns``.

        Raises:
            TransformError: no such transform at that stamp (``reason`` says why).
        """
        ...


def normalize_frame(frame_id: str) -> str:
    """A frame id as tf2 stores it: without a leading ``/`` (ROS 1 bags wrote ``/base_link``)."""
    return str(frame_id).strip().lstrip("/")


def matrix_from_transform(transform: Any, *, what: str = "transform") -> NDArray[np.float64]:
    """4x4 matrix of a ``geometry_msgs/Transform`` (``translation`` in metres, unit quaternion ``rotation``).

    Duck-typed: rclpy and rosbags messages alike.

    Raises:
        PoseError: non-finite numbers or a quaternion far from unit length (``what`` names the input).
    """
    pose = SimpleNamespace(position=transform.translation, orientation=transform.rotation)
    return matrix_from_pose(pose, what=what)


def _seconds(stamp_ns: int) -> str:
    return f"{stamp_ns / _NS_PER_S:.3f} s"


@dataclass
class _Link:
    """The transform ``T_parent_child`` of one child frame: static (one matrix) or dynamic (a pose history)."""

    parent: str
    static: NDArray[np.float64] | None
    history: PoseBuffer | None


class TFBuffer:
    """Static and dynamic transforms of a TF tree, looked up between any two frames (see the module docstring).

    Args:
        cache_time_s: seconds of history kept per dynamic link, counted back from its newest transform.
        capacity: most transforms kept per dynamic link.
        max_gap_s: largest time between the two transforms of a link that are interpolated, seconds.
        max_extrapolation_s: how far before the oldest or after the newest transform of a link
            a stamp may lie, seconds (0 refuses any extrapolation, as tf2 does).

    Attributes:
        refused: reason -> transforms not stored (``out_of_order``: stamp not newer than the
            link's newest; ``reparented``: a child given a second parent; ``static_and_dynamic``:
            a link published on both topics; ``bad_transform``: non-finite or not rigid;
            ``self_parent``: a frame its own parent; ``loop``: the transform would close a cycle).
    """

    def __init__(
        self,
        *,
        cache_time_s: float = 10.0,
        capacity: int = 10_000,
        max_gap_s: float = 0.5,
        max_extrapolation_s: float = 0.05,
    ) -> None:
        for name, value in (
            ("cache_time_s", cache_time_s),
            ("max_gap_s", max_gap_s),
            ("max_extrapolation_s", max_extrapolation_s),
        ):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number of seconds >= 0, got {value!r}")
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 2:
            raise ValueError(f"capacity must be an integer >= 2, got {capacity!r}")
        self.cache_ns = round(cache_time_s * _NS_PER_S)
        self.capacity = capacity
        self.max_gap_s, self.max_extrapolation_s = max_gap_s, max_extrapolation_s
        self._links: dict[str, _Link] = {}
        self.refused: Counter[str] = Counter()

    # ------------------------------------------------------------------ adding

    def add(self, parent: str, child: str, stamp_ns: int, transform: ArrayLike, *, static: bool = False) -> bool:
        """Store ``T_parent_child`` at ``stamp_ns``; returns False (and counts why in :attr:`refused`) if refused.

        A static link replaces the previous static transform of ``child``
        (``/tf_static`` is republished whole by every static broadcaster).

        Raises:
            PoseError: ``transform`` is not a finite rigid 4x4 matrix (also counted as ``bad_transform``).
        """
        parent, child = normalize_frame(parent), normalize_frame(child)
        try:
            matrix = validate_pose(transform, what=f"transform {parent} -> {child}")
        except PoseError:
            self.refused["bad_transform"] += 1
            raise
        if not parent or not child or parent == child:
            self.refused["self_parent"] += 1
            return False
        link = self._links.get(child)
        if link is not None and link.parent != parent:
            self.refused["reparented"] += 1
            return False
        if link is None and child in self._ancestors(parent):
            self.refused["loop"] += 1
            return False
        if static:
            if link is not None and link.history is not None:
                self.refused["static_and_dynamic"] += 1
                return False
            self._links[child] = _Link(parent, matrix, None)
            return True
        if link is not None and link.static is not None:
            self.refused["static_and_dynamic"] += 1
            return False
        if link is None:
            link = self._links[child] = _Link(parent, None, PoseBuffer(self.capacity))
        history = link.history
        assert history is not None  # a dynamic link
        if not history.add(stamp_ns, matrix):
            self.refused["out_of_order"] += 1
            return False
        history.discard_before(int(stamp_ns) - self.cache_ns)
        return True

    def add_message(self, msg: Any, *, static: bool = False) -> list[str]:
        """Store every transform of a ``tf2_msgs/TFMessage`` (``static`` for ``/tf_static``).

        Each ``msg.transforms[i]`` is read as a ``geometry_msgs/TransformStamped``:
        ``header.frame_id`` (parent), ``child_frame_id``, ``header.stamp``,
        ``transform.translation`` and ``transform.rotation``. A bad transform
        does not stop the others of the message.

        Returns:
            One line per transform that was not stored (bad numbers, or a reason of
            :attr:`refused`); empty when all were.
        """
        problems: list[str] = []
        for item in msg.transforms:
            parent, child = normalize_frame(item.header.frame_id), normalize_frame(item.child_frame_id)
            stamp_ns = stamp_to_nanoseconds(item.header.stamp)
            before = self.refused.copy()
            try:
                matrix = matrix_from_transform(item.transform, what=f"transform {parent} -> {child}")
            except PoseError as exc:
                self.refused["bad_transform"] += 1
                problems.append(str(exc))
                continue
            if not self.add(parent, child, stamp_ns, matrix, static=static):
                reason = next(iter((self.refused - before).keys()), "refused")
                if reason != "out_of_order":  # a repeated stamp is routine (several broadcasters), not a problem
                    problems.append(f"transform {parent} -> {child} at {stamp_ns} ns refused: {reason}")
        return problems

    # ------------------------------------------------------------------ the tree

    @property
    def frames(self) -> list[str]:
        """Every frame the buffer knows (as a child or a parent), sorted."""
        return sorted(set(self._links) | {link.parent for link in self._links.values()})

    def _ancestors(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root, nearest first."""
        chain = [frame]
        while frame in self._links:
            frame = self._links[frame].parent
            chain.append(frame)
        return chain

    def _tree(self, frame: str) -> list[str]:
        """The frames of ``frame``'s tree (those with its root), root first, then sorted."""
        root = self._ancestors(frame)[-1]
        members = sorted(f for f in self._links if self._ancestors(f)[-1] == root)
        return [root, *members]

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The frames from ``source`` up to the common ancestor and from ``target`` up to it (ancestor excluded).

        Raises:
            TransformError: a frame is unknown or the two lie in different trees.
        """
        known = self.frames
        unknown = [frame for frame in (target, source) if frame not in known]
        if len(unknown) == 1:
            missing = unknown[0]
            other = source if missing == target else target
            tree = self._tree(other)
            leaves = [frame for frame in tree if not any(link.parent == frame for link in self._links.values())]
            raise TransformError(
                f"no transform from {target} to {source}: frame {missing!r} is unknown: no transform has child "
                f"{missing!r} (nor parent); missing link: {leaves[0] if leaves else other} -> {missing} (a transform "
                f"from a frame of {other}'s tree, {', '.join(tree)}, to {missing}; frames known: {', '.join(known)})",
                "tf_unknown_frame",
            )
        if unknown:
            raise TransformError(
                f"no transform from {target} to {source}: frames {target!r} and {source!r} are unknown "
                f"(frames known: {', '.join(known) or 'none yet'})",
                "tf_unknown_frame",
            )
        up_source, up_target = self._ancestors(source), self._ancestors(target)
        common = next((frame for frame in up_source if frame in set(up_target)), None)
        if common is None:
            root_s, root_t = up_source[-1], up_target[-1]
            raise TransformError(
                f"no transform from {target} to {source}: they lie in two unconnected trees, "
                f"{' -> '.join(reversed(up_target))} and {' -> '.join(reversed(up_source))}; missing link: a "
                f"transform with child {root_s} (the root of {source}'s tree) and a parent in {target}'s tree, "
                f"e.g. {target} -> {root_s} (or with child {root_t}; frames known: {', '.join(known)})",
                "tf_not_connected",
            )
        return up_source[: up_source.index(common)], up_target[: up_target.index(common)]

    def _to_parent(self, child: str, stamp_ns: int) -> NDArray[np.float64]:
        """``T_parent_child`` of one link at ``stamp_ns``."""
        link = self._links[child]
        if link.static is not None:
            return link.static
        history = link.history
        assert history is not None
        found = history.lookup(stamp_ns, max_gap_s=self.max_gap_s, max_extrapolation_s=self.max_extrapolation_s)
        if found.pose is not None:
            return found.pose
        reason = _MISS_REASONS.get(found.reason, "tf_lookup_failed") if found.reason else "tf_lookup_failed"
        span = (
            f"it holds {len(history)} transforms from {_seconds(history.oldest_ns)} to {_seconds(history.newest_ns)}"
            if history.oldest_ns is not None and history.newest_ns is not None
            else "it holds none"
        )
        raise TransformError(
            f"transform {link.parent} -> {child} is not known at {_seconds(stamp_ns)} "
            f"({found.reason.value if found.reason else 'miss'}): {span} "
            f"(max_gap_s {self.max_gap_s}, max_extrapolation_s {self.max_extrapolation_s})",
            reason,
        )

    # ------------------------------------------------------------------ lookups

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int) -> NDArray[np.float64]:
        """4x4 ``T_target_source`` at ``stamp_ns``: the pose of ``source_frame`` in ``target_frame``, metres.

        Raises:
            TransformError: an unknown frame, unconnected trees, or a link of the chain
                without data at the stamp (see the module docstring).
        """
        target, source = normalize_frame(target_frame), normalize_frame(source_frame)
        if target == source and target in self.frames:
            return np.eye(4)
        up_source, up_target = self._path(target, source)
        stamp = int(stamp_ns)
        common_source = np.eye(4)  # T_common_source
        for frame in up_source:
            common_source = self._to_parent(frame, stamp) @ common_source
        common_target = np.eye(4)  # T_common_target
        for frame in up_target:
            common_target = self._to_parent(frame, stamp) @ common_target
        return invert_pose(common_target) @ common_source

    def chain(self, target_frame: str, source_frame: str) -> list[tuple[str, str, bool]]:
        """The links between two frames as ``(parent, child, static)``, source side first.

        Raises:
            TransformError: as :meth:`lookup` for frames or trees.
        """
        up_source, up_target = self._path(normalize_frame(target_frame), normalize_frame(source_frame))
        return [(self._links[f].parent, f, self._links[f].static is not None) for f in (*up_source, *up_target)]

    def newest_ns(self, target_frame: str, source_frame: str) -> int | None:
        """The latest stamp at which every dynamic link between the frames has data (tf2's "latest common time").

        A chain of static links only holds at every stamp: ``2**63 - 1``. None when
        the frames are not (yet) connected.
        """
        try:
            links = self.chain(target_frame, source_frame)
        except TransformError:
            return None
        newest = _FOREVER_NS
        for _, child, static in links:
            if not static:
                history = self._links[child].history
                stamp = history.newest_ns if history is not None else None
                if stamp is None:
                    return None
                newest = min(newest, stamp)
        return newest

    def discard_before(self, stamp_ns: int) -> None:
        """Forget dynamic transforms not needed for stamps at or after ``stamp_ns`` (one before it is kept)."""
        for link in self._links.values():
            if link.history is not None:
                link.history.discard_before(stamp_ns)
