"""Stamp synchronisation of stereo streams and pose interpolation, without ROS.

Both the offline bag labeler (:mod:`selfcontra_ros.bags.label_bag`) and the
ROS labeler node feed their messages through these classes, so a bag gives
the same frames whichever way it is replayed. Everything here is pure Python
and numpy: stamps are integer nanoseconds (``builtin_interfaces/Time`` as
``sec * 1e9 + nanosec``), poses are 4x4 ``T_world_left`` matrices in metres.

* :class:`StampSynchronizer` pairs the left and right images (and optionally
  an external disparity) by header stamp, exactly or within a ``slop``.
* :class:`PoseBuffer` keeps the recent poses of a PoseStamped or Odometry
  stream and gives the pose at an image stamp: translation interpolated
  linearly, rotation by quaternion slerp.
* :func:`pose_from_message` and :func:`matrix_from_pose` read those messages
  (duck-typed: rclpy and rosbags messages alike).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selfcontra_ros.errors import PoseError
from selfcontra_ros.geometry import quaternion_from_rotation, rotation_from_quaternion

__all__ = [
    "SYNC_MODES",
    "Match",
    "PoseBuffer",
    "PoseLookup",
    "PoseMiss",
    "PushResult",
    "StampSynchronizer",
    "matrix_from_pose",
    "pose_from_message",
    "validate_pose",
]

_NS_PER_S = 1_000_000_000
#: Accepted synchronisation modes.
SYNC_MODES = ("exact", "approximate")
#: Largest deviation of ``R^T R`` from the identity (and of ``det R`` from 1) accepted as rigid.
_RIGID_TOLERANCE = 1e-3
#: Largest deviation of a message quaternion's norm from 1: ROS senders normalise, a zero or
#: badly scaled quaternion is a bug upstream (e.g. a default-constructed message).
_QUATERNION_NORM_TOLERANCE = 1e-3


def _seconds_to_ns(seconds: float, name: str) -> int:
    if not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"{name} must be a finite number of seconds >= 0, got {seconds!r}")
    return round(seconds * _NS_PER_S)


# --------------------------------------------------------------------------- stamp synchronisation


class Match(NamedTuple):
    """One synchronised set of messages.

    Attributes:
        stamp_ns: stamp of the first (pivot) key's message, nanoseconds: the frame's stamp.
        stamps_ns: stamps of all messages, in the synchroniser's key order.
        items: the messages (whatever the caller pushed), in key order.
    """

    stamp_ns: int
    stamps_ns: tuple[int, ...]
    items: tuple[Any, ...]


class PushResult(NamedTuple):
    """What :meth:`StampSynchronizer.push` did with a message.

    Attributes:
        matches: sets that became complete, oldest first.
        accepted: False when the message was refused because its stamp is not
            newer than the previous one on its key (stamps went backwards or
            repeated, e.g. a bag loop or a restarted driver); the caller logs
            and drops it, and may :meth:`StampSynchronizer.reset` on a time jump.
    """

    matches: list[Match]
    accepted: bool


def _nearest(queue: deque[tuple[int, Any]], stamp: int) -> tuple[int, Any]:
    """The queued ``(stamp, item)`` nearest to ``stamp`` (the earlier on a tie); ``queue`` is sorted, non-empty."""
    stamps = [entry[0] for entry in queue]
    i = bisect.bisect_left(stamps, stamp)
    if i == len(stamps):
        return queue[-1]
    if i > 0 and stamp - stamps[i - 1] <= stamps[i] - stamp:
        return queue[i - 1]
    return queue[i]


class StampSynchronizer:
    """Groups messages of several keys (topics) by header stamp.

    The first key is the *pivot* (the left image): every pivot message is
    matched with, on each other key, the queued message whose stamp is nearest
    to the pivot's (the earlier one on a tie), provided it lies within
    ``slop`` seconds (``exact`` mode: equal stamps). Stamps must increase on
    each key, so the choice is final as soon as every other key holds a
    message stamped at or after the pivot's: no later message can be nearer.
    A pivot with no partner within the slop is dropped; messages used by a
    match, or too old to match any later pivot, leave the queues.

    Memory is bounded: each key queues at most ``queue_size`` messages; the
    oldest is dropped (and counted) when a new one would exceed it, e.g. when
    one stream stopped.

    Args:
        keys: the keys to synchronise, pivot first, e.g. ``("left", "right")``
            or ``("left", "right", "disparity")``; at least two, distinct.
        mode: ``"exact"`` (equal stamps) or ``"approximate"``.
        slop: largest stamp difference to the pivot, seconds; must be 0 in
            ``exact`` mode.
        queue_size: messages queued per key (>= 1).

    Attributes:
        dropped: key -> messages dropped unmatched (queue overflow, no partner
            within the slop, or superseded by a newer match).
        backwards: key -> messages refused because their stamp was not newer
            than the previous one on the key.
        matched: number of matches emitted.
    """

    def __init__(
        self, keys: Sequence[Hashable], *, mode: str = "exact", slop: float = 0.0, queue_size: int = 10
    ) -> None:
        self.keys: tuple[Hashable, ...] = tuple(keys)
        if len(self.keys) < 2 or len(set(self.keys)) != len(self.keys):
            raise ValueError(f"keys must be at least two distinct keys, got {self.keys!r}")
        if mode not in SYNC_MODES:
            raise ValueError(f"sync mode is {mode!r}; expected one of {', '.join(SYNC_MODES)}")
        slop_ns = _seconds_to_ns(float(slop), "slop")
        if mode == "exact" and slop_ns != 0:
            raise ValueError(f"slop is {slop} s but sync mode is 'exact' (equal stamps); use mode 'approximate'")
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f"queue_size must be an integer >= 1, got {queue_size!r}")
        self.mode = mode
        self.slop_ns = slop_ns
        self.queue_size = queue_size
        self._queues: dict[Hashable, deque[tuple[int, Any]]] = {key: deque() for key in self.keys}
        self._last: dict[Hashable, int | None] = dict.fromkeys(self.keys)
        self.dropped: dict[Hashable, int] = dict.fromkeys(self.keys, 0)
        self.backwards: dict[Hashable, int] = dict.fromkeys(self.keys, 0)
        self.matched = 0

    def push(self, key: Hashable, stamp_ns: int, item: Any) -> PushResult:
        """Queue one message and return the matches it completes.

        Raises:
            KeyError: ``key`` is not one of the synchroniser's keys.
        """
        queue = self._queues[key]
        stamp = int(stamp_ns)
        last = self._last[key]
        if last is not None and stamp <= last:
            self.backwards[key] += 1
            return PushResult([], False)
        self._last[key] = stamp
        queue.append((stamp, item))
        if len(queue) > self.queue_size:
            queue.popleft()
            self.dropped[key] += 1
        return PushResult(self._match(), True)

    def _match(self) -> list[Match]:
        matches: list[Match] = []
        pivot_queue = self._queues[self.keys[0]]
        while pivot_queue:
            pivot_stamp, pivot_item = pivot_queue[0]
            chosen: list[tuple[int, Any]] = [(pivot_stamp, pivot_item)]
            complete = True
            for key in self.keys[1:]:
                queue = self._queues[key]
                # Entries too old for this pivot are too old for every later one (pivot stamps increase).
                while queue and queue[0][0] < pivot_stamp - self.slop_ns:
                    queue.popleft()
                    self.dropped[key] += 1
                if not queue or queue[-1][0] < pivot_stamp:
                    complete = False  # a nearer message may still come on this key
                    continue
                best = _nearest(queue, pivot_stamp)
                if abs(best[0] - pivot_stamp) > self.slop_ns:
                    chosen.append((-1, None))  # no partner within the slop: the pivot is dropped
                else:
                    chosen.append(best)
            if not complete:
                break
            pivot_queue.popleft()
            if any(stamp < 0 for stamp, _ in chosen[1:]):
                self.dropped[self.keys[0]] += 1
                continue
            for key, (stamp, _) in zip(self.keys[1:], chosen[1:], strict=True):
                queue = self._queues[key]
                # The partner and everything older leave: a later pivot prefers newer partners.
                while queue and queue[0][0] <= stamp:
                    used = queue.popleft()[0] == stamp
                    if not used:
                        self.dropped[key] += 1
            self.matched += 1
            matches.append(Match(pivot_stamp, tuple(s for s, _ in chosen), tuple(i for _, i in chosen)))
        return matches

    def pending(self, key: Hashable) -> int:
        """Messages currently queued on ``key``."""
        return len(self._queues[key])

    def reset(self) -> int:
        """Forget every queued message and the last stamps (after a time jump); returns how many were queued.

        The forgotten messages are counted in :attr:`dropped`.
        """
        total = 0
        for key, queue in self._queues.items():
            self.dropped[key] += len(queue)
            total += len(queue)
            queue.clear()
            self._last[key] = None
        return total


# --------------------------------------------------------------------------- poses from messages


def validate_pose(pose: ArrayLike, *, what: str = "pose") -> NDArray[np.float64]:
    """Return ``pose`` as a float64 4x4 rigid transform, or raise naming the problem.

    Raises:
        PoseError: not 4x4, not finite, bottom row not ``(0, 0, 0, 1)``, or a
            rotation block that is not orthonormal with determinant +1.
    """
    matrix = np.asarray(pose, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise PoseError(f"{what} must be a 4x4 matrix, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise PoseError(f"{what} holds NaN or inf values")
    if not np.allclose(matrix[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9):
        raise PoseError(f"{what} bottom row is {matrix[3].tolist()}; expected [0, 0, 0, 1]")
    rotation = matrix[:3, :3]
    orthogonality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    det = float(np.linalg.det(rotation))
    if orthogonality > _RIGID_TOLERANCE or abs(det - 1.0) > _RIGID_TOLERANCE:
        raise PoseError(
            f"{what} is not rigid: |R^T R - I| = {orthogonality:.2e}, det R = {det:.6f}; expected a rotation"
        )
    return matrix.copy()


def matrix_from_pose(pose: Any, *, what: str = "pose") -> NDArray[np.float64]:
    """4x4 transform of a ``geometry_msgs/Pose`` (any object with ``position.x/y/z`` and ``orientation.x/y/z/w``).

    Raises:
        PoseError: a non-finite component, or a quaternion whose norm is not 1
            (within 1e-3): an all-zero orientation is a default-constructed
            message, not a rotation.
    """
    p, o = pose.position, pose.orientation
    position = np.array([float(p.x), float(p.y), float(p.z)])
    quaternion = np.array([float(o.x), float(o.y), float(o.z), float(o.w)])
    if not np.all(np.isfinite(position)):
        raise PoseError(f"{what}.position holds NaN or inf: {position.tolist()}")
    if not np.all(np.isfinite(quaternion)):
        raise PoseError(f"{what}.orientation holds NaN or inf: {quaternion.tolist()}")
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > _QUATERNION_NORM_TOLERANCE:
        raise PoseError(f"{what}.orientation (x, y, z, w) = {quaternion.tolist()} has norm {norm:.6f}; expected 1")
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_from_quaternion(quaternion)
    matrix[:3, 3] = position
    return matrix


def pose_from_message(msg: Any) -> tuple[int, NDArray[np.float64]]:
    """Header stamp (nanoseconds) and 4x4 pose of a PoseStamped or Odometry message.

    ``geometry_msgs/PoseStamped`` holds the pose in ``msg.pose``;
    ``nav_msgs/Odometry`` in ``msg.pose.pose`` (its covariance and twist are
    ignored). The pose is taken as ``T_world_left``: the child frame of an
    Odometry message must be the left camera's optical frame (no tf lookup).

    Raises:
        PoseError: see :func:`matrix_from_pose`; also a negative stamp.
    """
    stamp = msg.header.stamp
    stamp_ns = int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)
    if stamp_ns < 0:
        raise PoseError(f"pose header stamp is negative ({stamp.sec} s, {stamp.nanosec} ns)")
    pose = msg.pose
    what = "PoseStamped.pose"
    if hasattr(pose, "pose"):  # PoseWithCovariance of nav_msgs/Odometry
        pose, what = pose.pose, "Odometry.pose.pose"
    return stamp_ns, matrix_from_pose(pose, what=what)


# --------------------------------------------------------------------------- pose buffer


class PoseMiss(str, Enum):
    """Why :meth:`PoseBuffer.lookup` found no pose."""

    EMPTY = "pose_none_yet"
    """No pose has arrived yet."""
    BEFORE = "pose_before_buffer"
    """The stamp precedes the oldest buffered pose by more than the tolerance."""
    AFTER = "pose_after_buffer"
    """The stamp follows the newest pose by more than the tolerance (the pose stream stopped or lags)."""
    GAP = "pose_gap"
    """The poses around the stamp are further apart than ``max_gap_s``."""


@dataclass(frozen=True)
class PoseLookup:
    """Result of :meth:`PoseBuffer.lookup`: a pose, or why there is none."""

    pose: NDArray[np.float64] | None
    reason: PoseMiss | None = None


def _interpolate(pose0: NDArray[np.float64], pose1: NDArray[np.float64], fraction: float) -> NDArray[np.float64]:
    """Pose at ``fraction`` of the way from ``pose0`` to ``pose1`` (outside [0, 1] extrapolates).

    Translation is linear; the rotation follows the shorter great arc between
    the two unit quaternions (slerp), at constant angular speed.
    """
    q0 = quaternion_from_rotation(pose0[:3, :3])
    q1 = quaternion_from_rotation(pose1[:3, :3])
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are the same rotation: take the shorter arc
        q1, dot = -q1, -dot
    theta = math.acos(min(dot, 1.0))
    if theta < 1e-9:
        q = q0 + fraction * (q1 - q0)  # rotations equal to rounding: slerp degenerates to a lerp
    else:
        q = (math.sin((1.0 - fraction) * theta) * q0 + math.sin(fraction * theta) * q1) / math.sin(theta)
    out = np.eye(4)
    out[:3, :3] = rotation_from_quaternion(q)
    out[:3, 3] = pose0[:3, 3] + fraction * (pose1[:3, 3] - pose0[:3, 3])
    return out


class PoseBuffer:
    """The recent poses of one stream, for the pose at an image stamp.

    Args:
        capacity: poses kept (oldest dropped first); 1000 poses cover 10 s of a 100 Hz odometry.

    Attributes:
        out_of_order: poses refused because their stamp was not newer than the newest one.
    """

    def __init__(self, capacity: int = 1000) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be an integer >= 1, got {capacity!r}")
        self.capacity = capacity
        self._stamps: list[int] = []
        self._poses: list[NDArray[np.float64]] = []
        self.out_of_order = 0

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_ns(self) -> int | None:
        """Stamp of the newest pose, nanoseconds (None when empty)."""
        return self._stamps[-1] if self._stamps else None

    @property
    def oldest_ns(self) -> int | None:
        """Stamp of the oldest pose kept, nanoseconds (None when empty)."""
        return self._stamps[0] if self._stamps else None

    def add(self, stamp_ns: int, pose: ArrayLike) -> bool:
        """Append a pose; returns False (and counts it) if its stamp is not newer than the newest.

        Raises:
            PoseError: the pose is not a finite rigid 4x4 transform (the problem named).
        """
        matrix = validate_pose(pose, what=f"pose at {int(stamp_ns)} ns")
        stamp = int(stamp_ns)
        if self._stamps and stamp <= self._stamps[-1]:
            self.out_of_order += 1
            return False
        self._stamps.append(stamp)
        self._poses.append(matrix)
        if len(self._stamps) > self.capacity:
            del self._stamps[0], self._poses[0]
        return True

    def add_message(self, msg: Any) -> bool:
        """:meth:`add` the pose of a PoseStamped or Odometry message (see :func:`pose_from_message`)."""
        return self.add(*pose_from_message(msg))

    def lookup(self, stamp_ns: int, *, max_gap_s: float = 0.5, max_extrapolation_s: float = 0.05) -> PoseLookup:
        """The pose at ``stamp_ns``, or why there is none.

        Inside the buffer, the two poses bracketing the stamp are interpolated
        (a pose at exactly the stamp is returned unchanged). Outside it, by at
        most ``max_extrapolation_s``, the end segment is extended at constant
        velocity (a single pose is held). The bracketing (or end) poses must
        be at most ``max_gap_s`` apart.

        Args:
            stamp_ns: the image stamp, nanoseconds.
            max_gap_s: largest time between the two poses used, seconds.
            max_extrapolation_s: how far before the oldest or after the newest pose a stamp may lie, seconds.
        """
        max_gap = _seconds_to_ns(float(max_gap_s), "max_gap_s")
        max_extra = _seconds_to_ns(float(max_extrapolation_s), "max_extrapolation_s")
        stamps = self._stamps
        if not stamps:
            return PoseLookup(None, PoseMiss.EMPTY)
        stamp = int(stamp_ns)
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            return PoseLookup(self._poses[i].copy())
        if i == 0 and stamps[0] - stamp > max_extra:
            return PoseLookup(None, PoseMiss.BEFORE)
        if i == len(stamps) and stamp - stamps[-1] > max_extra:
            return PoseLookup(None, PoseMiss.AFTER)
        if len(stamps) == 1:
            return PoseLookup(self._poses[0].copy())
        lo = min(max(i - 1, 0), len(stamps) - 2)  # the bracketing pair, or the end segment outside
        t0, t1 = stamps[lo], stamps[lo + 1]
        if t1 - t0 > max_gap:
            return PoseLookup(None, PoseMiss.GAP)
        return PoseLookup(_interpolate(self._poses[lo], self._poses[lo + 1], (stamp - t0) / (t1 - t0)))

    def at(
        self, stamp_ns: int, max_gap_s: float = 0.5, max_extrapolation_s: float = 0.05
    ) -> NDArray[np.float64] | None:
        """The pose at ``stamp_ns`` (see :meth:`lookup`), or None; :meth:`lookup` tells why."""
        return self.lookup(stamp_ns, max_gap_s=max_gap_s, max_extrapolation_s=max_extrapolation_s).pose

    def discard_before(self, stamp_ns: int) -> None:
        """Forget poses not needed for stamps at or after ``stamp_ns`` (the one just before it is kept)."""
        keep_from = max(bisect.bisect_right(self._stamps, int(stamp_ns)) - 1, 0)
        del self._stamps[:keep_from], self._poses[:keep_from]
