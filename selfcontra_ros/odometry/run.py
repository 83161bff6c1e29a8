"""Offline stereo visual odometry over a KITTI-layout sequence or a bag: the ``selfcontra odometry`` command.

:func:`odometry_command` estimates the pose of every stereo pair with
:class:`~selfcontra_ros.odometry.stereo_vo.StereoOdometry` and writes

- ``OUT`` (e.g. ``poses.txt``): KITTI pose format, one row-major 3x4
  ``T_world_left`` per frame, world = left camera of the first frame;
- ``OUT`` with suffix ``.quality.csv`` and ``.quality.json``: the per-frame
  quality (status, reliable, feature/match/inlier counts, RMS reprojection
  error, motion), and in the JSON also the run's summary and, when the input
  has ground-truth poses, the KITTI odometry metrics of
  :mod:`selfcontra_ros.odometry.metrics`.

Unreliable frames keep a constant-velocity guess in ``poses.txt`` (KITTI
files need one line per frame; ``isolated`` and ``uncertain`` frames keep
their measured pose) and ``reliable: false`` in the quality files:
callers must not label them (:func:`poses_for_sequence` returns the mask).
A sequence in which no frame after the first gives a pose with motion raises
:class:`~selfcontra_ros.odometry.stereo_vo.OdometryError` with the reason
(too little texture, too few matches, no motion).

The functions are pure in the sense of DESIGN section 9: they read their
arguments' files and write only the output paths given.
"""

from __future__ import annotations

import csv
import itertools
import logging
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.bags import topics
from selfcontra_ros.bags.reader import BagError, is_bag, open_bag
from selfcontra_ros.bags.stereo_input import ImageError, StereoImages, StereoInput, TFPoses, TopicPoses
from selfcontra_ros.bags.sync import StampSynchronizer
from selfcontra_ros.bags.tf import TFBuffer
from selfcontra_ros.datasets.kitti import OdometrySequence, StereoScene, open_sequence, write_poses
from selfcontra_ros.geometry import StereoCamera, invert_pose
from selfcontra_ros.odometry.metrics import SHORT_LENGTHS, OdometryMetrics, evaluate_odometry
from selfcontra_ros.odometry.stereo_vo import (
    FrameQuality,
    IsolationGate,
    OdometryError,
    StereoCache,
    StereoOdometry,
    VOParams,
    judge_spread,
    mark_isolated,
    mark_uncertain,
    smooth_step_lengths,
    step_length_spread,
)
from selfcontra_ros.reports import write_json
from selfcontra_ros.ros.conversions import stamp_to_nanoseconds

__all__ = [
    "OnlineDecision",
    "OnlineOdometry",
    "bag_reference_poses",
    "bag_stereo_frames",
    "check_usable",
    "estimate_bag_poses",
    "estimate_poses",
    "estimate_sequence_poses",
    "final_poses",
    "next_pass_params",
    "odometry_command",
    "poses_for_sequence",
    "quality_paths",
    "run_passes",
    "write_quality",
]

_LOG = logging.getLogger(__name__)
_Odometry = TypeVar("_Odometry", bound=StereoOdometry)
_Triple = tuple[float, NDArray[np.uint8], NDArray[np.uint8]]
_NS_PER_S = 1_000_000_000
#: Frames (before the newest) over which :class:`OnlineOdometry` smooths the step lengths.
_SMOOTHING_SPAN = 60
_LEFT, _RIGHT = "left", "right"


def estimate_poses(
    camera: StereoCamera,
    frames: Iterable[_Triple] | Callable[[], Iterable[_Triple]],
    *,
    params: VOParams | None = None,
) -> tuple[NDArray[np.float64], list[FrameQuality]]:
    """Run the odometry over ``(stamp, left, right)`` triples.

    ``frames`` may be a function that returns the triples afresh at each
    call. Then, when the odometry's disparity offset estimate
    (``VOParams.estimate_disparity_offset``) ended away from
    ``VOParams.disparity_offset_px``, the sequence is run again: once more
    estimating, around the first estimate, then with the second estimate
    applied from the first frame on and estimation off (:func:`next_pass_params`).
    The later passes reuse the first one's stereo matching
    (:class:`~selfcontra_ros.odometry.stereo_vo.StereoCache`: the same
    poses as measuring it again, in about half the time), so the triples
    must be the same at each call.

    Returns:
        (N, 4, 4) poses ``T_world_left`` (metres, after the windowed
        refinement, step lengths smoothed over the sequence:
        :func:`~selfcontra_ros.odometry.stereo_vo.smooth_step_lengths`) and
        the per-frame quality (:func:`final_poses`: reliable frames among
        unreliable ones reported ``isolated``, frames whose smoothed step
        length the sequence pins down too loosely ``uncertain``).

    Raises:
        OdometryError: no frame at all, or no usable frame (see :func:`check_usable`).
    """
    params = params or VOParams()
    if not callable(frames):
        vo = _run_odometry(camera, frames, params)
    else:
        vo = run_passes(lambda run_params, cache: _run_odometry(camera, frames(), run_params, cache), params)[-1]
    poses, qualities = final_poses(vo)
    check_usable(qualities)
    return poses, qualities


def final_poses(vo: StereoOdometry) -> tuple[NDArray[np.float64], list[FrameQuality]]:
    """A whole sequence's poses and qualities as :func:`estimate_poses` reports them.

    The step lengths smoothed over the sequence
    (:func:`~selfcontra_ros.odometry.stereo_vo.smooth_step_lengths`); a
    reliable frame with no reliable neighbour reported ``isolated``
    (:func:`~selfcontra_ros.odometry.stereo_vo.mark_isolated`); an ``ok``
    frame whose smoothed step length the sequence pins down only to worse
    than ``VOParams.max_length_spread_pct`` reported ``uncertain``
    (:func:`~selfcontra_ros.odometry.stereo_vo.step_length_spread`,
    :func:`~selfcontra_ros.odometry.stereo_vo.mark_uncertain`). Unreliable
    frames keep their poses.
    """
    measured = vo.qualities[:]
    qualities = mark_isolated(measured, vo.params)
    spread = step_length_spread(measured, vo.params)
    qualities = mark_uncertain(qualities, spread, vo.params, vo.camera.focal_baseline)
    return vo.smoothed_poses(), qualities


def run_passes(run_pass: Callable[[VOParams, StereoCache | None], _Odometry], params: VOParams) -> list[_Odometry]:
    """Every pass over one sequence, first to final (:func:`next_pass_params` chooses them).

    ``run_pass(run_params, cache)`` runs the odometry over the whole
    sequence once; ``cache`` (None when ``params`` does not estimate the
    offset, so that no later pass can come) carries the first pass's stereo
    matching to the later ones.
    """
    cache = StereoCache() if params.estimate_disparity_offset else None
    runs = [run_pass(params, cache)]
    following = next_pass_params(runs[-1], params, params)
    while following is not None:
        _, error, windows = runs[-1].offset_estimate()
        _LOG.info(
            "disparity offset %+.3f px (standard error %.3f px over %d windows): %s",
            following.disparity_offset_px, error, windows,
            "estimated again around it" if following.estimate_disparity_offset else "final pass with it",
        )  # fmt: skip
        runs.append(run_pass(following, cache))
        following = next_pass_params(runs[-1], following, params)
    return runs


def next_pass_params(vo: StereoOdometry, run_params: VOParams, params: VOParams) -> VOParams | None:
    """The parameters of the next pass over a sequence that ``vo`` ran with ``run_params`` (the caller's
    ``params`` in the first pass), or None when ``vo``'s run is the final one.

    1. A first pass whose disparity offset never left ``params.disparity_offset_px`` is final.
    2. Otherwise the sequence is run again estimating, from the first pass's offset. The first pass chose
       its features (the gates on disparity change and reprojection error, the tracks the offset estimate
       keeps) under the offset it had, mostly the configured one, which pulls its estimate towards it: a
       simulated 0.3 px read +0.11 to +0.24 px; estimated again around that, +0.21 to +0.29 px
       (docs/visual_odometry.md).
    3. That pass's estimate (the mean of its windows; its starting offset with fewer than
       ``offset_min_windows``) is applied from the first frame on, estimation off: the final pass.
    """
    if not run_params.estimate_disparity_offset:
        return None  # a fixed-offset pass is final
    if run_params.disparity_offset_px == params.disparity_offset_px:  # the first pass
        if vo.disparity_offset == params.disparity_offset_px:
            return None
        return replace(run_params, disparity_offset_px=vo.disparity_offset)
    mean, _, windows = vo.offset_estimate()
    offset = mean if windows >= run_params.offset_min_windows and np.isfinite(mean) else run_params.disparity_offset_px
    return replace(run_params, disparity_offset_px=float(offset), estimate_disparity_offset=False)


def _run_odometry(
    camera: StereoCamera, frames: Iterable[_Triple], params: VOParams, cache: StereoCache | None = None
) -> StereoOdometry:
    vo = StereoOdometry(camera, params, stereo_cache=cache)
    for stamp, left, right in frames:
        vo.add(left, right, stamp)
    if not vo.poses:
        raise OdometryError("the input holds no stereo frame")
    return vo


def check_usable(qualities: list[FrameQuality], *, source: str = "the sequence") -> None:
    """Raise unless at least one frame after the first has a reliable pose with motion.

    Raises:
        OdometryError: naming the reason: a single frame, no reliable frame
            (with the most frequent failure and its message), or no motion.
    """
    if len(qualities) < 2:
        raise OdometryError(f"{source} has {len(qualities)} frame(s); visual odometry needs at least two")
    statuses = Counter(q.status for q in qualities[1:])
    if statuses["ok"] > 0:
        return
    if statuses["static"] > 0 and statuses["static"] >= sum(statuses.values()) - statuses["static"]:
        raise OdometryError(
            f"{source}: no motion: the camera did not move measurably in any of its {len(qualities)} frames "
            f"(median feature motion below the static threshold); poses cannot support labeling"
        )
    failures = [q for q in qualities if not q.reliable]
    if failures:
        worst, _ = Counter(q.status for q in failures).most_common(1)[0]
        example = next(q for q in failures if q.status == worst)
        hint = "the images may have too little texture"
        if worst == "uncertain":
            hint = (
                "too few well measured steps to pin the step lengths down (a short sequence's every step is near "
                "an end); VOParams.max_length_spread_pct: 0 turns this check off"
            )
        raise OdometryError(
            f"{source}: no usable frame: {len(failures)} of {len(qualities)} frames unreliable "
            f"(mostly '{worst}', e.g. frame {example.index}: {example.message}); {hint}"
        )
    raise OdometryError(f"{source}: no frame with motion")


def _sequence_frames(
    sequence: OdometrySequence | StereoScene, indices: range, progress: bool
) -> Iterator[tuple[float, NDArray[np.uint8], NDArray[np.uint8]]]:
    for i in tqdm(indices, desc="odometry", unit="frame", disable=not progress):
        interrupts.check()
        frame = sequence[i]
        yield frame.stamp, frame.left, frame.right


def poses_for_sequence(
    sequence: OdometrySequence | StereoScene, *, params: VOParams | None = None, progress: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Estimated poses of every frame of an opened sequence and the mask of reliable ones.

    The hook for callers that need poses where a sequence has none
    (``selfcontra label --estimate-poses``, ``kitti2mcap --estimate-poses``):
    frames whose mask entry is False must not be labelled.

    Returns:
        (N, 4, 4) ``T_world_left`` (metres, world = left camera of frame 0) and (N,) booleans.

    Raises:
        OdometryError: no usable frame (too little texture, no motion).
    """
    poses, qualities = estimate_poses(
        sequence.camera, lambda: _sequence_frames(sequence, range(len(sequence)), progress), params=params
    )
    return poses, np.array([q.reliable for q in qualities], dtype=bool)


def estimate_sequence_poses(
    seq_dir: Path | str,
    *,
    sequence: str | None = None,
    frames: slice | None = None,
    params: VOParams | None = None,
    progress: bool = False,
) -> tuple[NDArray[np.float64], list[FrameQuality]]:
    """Estimate the poses of a KITTI-layout sequence folder (real or synthetic).

    Args:
        seq_dir: dataset root holding ``sequences/XX`` or a ``sequences/XX`` folder.
        sequence: which sequence of a root holding several.
        frames: the frames to use (a slice); all when None. Poses are
            relative to the first frame used.
        params: odometry parameters; defaults when None.
        progress: show a progress bar.

    Returns:
        (N, 4, 4) poses ``T_world_left`` and the per-frame quality.

    Raises:
        DatasetError: the folder is not a KITTI odometry sequence.
        OdometryError: no usable frame.
    """
    seq = open_sequence(seq_dir, sequence=sequence)
    indices = range(len(seq))[frames] if frames is not None else range(len(seq))
    return estimate_poses(seq.camera, lambda: _sequence_frames(seq, indices, progress), params=params)


# --------------------------------------------------------------------------- bags


def _read_camera(bag_path: Path | str, topic: dict[str, str], images: StereoImages) -> StereoCamera:
    infos: dict[str, Any] = {}
    wanted = {topic[topics.LEFT_INFO]: _LEFT, topic[topics.RIGHT_INFO]: _RIGHT}
    with open_bag(bag_path) as bag:
        missing = [t for t in wanted if t not in bag.topics]
        if missing:
            raise BagError(f"bag {bag_path} has no {', '.join(missing)}: the odometry needs both camera infos")
        for message in bag.messages(wanted):
            infos.setdefault(wanted[message.topic], message.msg)
            if len(infos) == 2:
                break
    return images.camera_from_infos(infos[_LEFT], infos[_RIGHT])


def _bag_input(
    bag_path: Path | str, stereo_input: StereoInput | None, namespace: str | None
) -> tuple[StereoInput, str]:
    """The input description (given, else the bag's record) and the namespace of a bag."""
    with open_bag(bag_path) as bag:
        read_as = stereo_input if stereo_input is not None else StereoInput.of_bag(bag.custom_data)
        return read_as, read_as.namespace(list(bag.topics), namespace)


def bag_stereo_frames(
    bag_path: Path | str,
    *,
    namespace: str | None = None,
    slop: float = 0.0,
    stereo_input: StereoInput | None = None,
    dropped: Counter[str] | None = None,
) -> tuple[StereoCamera, Iterator[tuple[int, NDArray[np.uint8], NDArray[np.uint8]]]]:
    """The stereo camera of a bag and an iterator over its synchronised ``(stamp_ns, left, right)`` pairs.

    Images are paired by header stamp (exactly, or within ``slop`` seconds),
    read as ``stereo_input`` says (remapped names, compressed, rectified;
    see :mod:`selfcontra_ros.bags.stereo_input`); colour images come as RGB.
    A pair with an image that cannot be used (corrupt compressed data, a bad
    encoding, a size other than the camera_info's) is skipped: counted in
    ``dropped`` by :class:`~selfcontra_ros.bags.stereo_input.ImageError` reason,
    with one warning per reason.

    Raises:
        BagError: missing or corrupt bag, missing topics.
        CalibrationError: camera infos that do not describe a (rectifiable) pair.
    """
    read_as, ns = _bag_input(bag_path, stereo_input, namespace)
    topic = read_as.topics(ns)
    images = StereoImages(read_as)
    camera = _read_camera(bag_path, topic, images)
    sides = {topic[read_as.left_image]: _LEFT, topic[read_as.right_image]: _RIGHT}
    skipped: Counter[str] = dropped if dropped is not None else Counter()

    def pairs() -> Iterator[tuple[int, NDArray[np.uint8], NDArray[np.uint8]]]:
        sync = StampSynchronizer((_LEFT, _RIGHT), mode="approximate" if slop > 0 else "exact", slop=slop)
        with open_bag(bag_path) as bag:
            missing = [t for t in sides if t not in bag.topics]
            if missing:
                raise BagError(f"bag {bag_path} has no {', '.join(missing)}: the odometry needs both images")
            for message in bag.messages(sides):
                stamp_ns = stamp_to_nanoseconds(message.msg.header.stamp)
                for match in sync.push(sides[message.topic], stamp_ns, message.msg).matches:
                    try:
                        left, right = images.pixels(match.items[0], _LEFT), images.pixels(match.items[1], _RIGHT)
                    except ImageError as exc:
                        if not skipped[exc.reason]:
                            _LOG.warning(
                                "bag %s: skipping the pair at %d ns (%s): %s; further ones are only counted",
                                bag_path,
                                match.stamp_ns,
                                exc.reason,
                                exc,
                            )
                        skipped[exc.reason] += 1
                        continue
                    yield match.stamp_ns, left, right

    return camera, pairs()


def bag_reference_poses(
    bag_path: Path | str,
    stamps_ns: Sequence[int] | NDArray[np.int64],
    *,
    namespace: str | None = None,
    stereo_input: StereoInput | None = None,
) -> NDArray[np.float64] | None:
    """The bag's own poses of the (rectified) left camera at ``stamps_ns``: its pose topic, or TF.

    Returns:
        (N, 4, 4) poses, or None when one of the stamps has none (the reason is logged).

    Raises:
        BagError: the pose (or ``/tf``) topic is missing.
    """
    read_as, ns = _bag_input(bag_path, stereo_input, namespace)
    topic = read_as.topics(ns)
    images = StereoImages(read_as)
    camera_frame = None
    if read_as.rectify or read_as.pose_source == "tf":
        with open_bag(bag_path) as bag:
            wanted = [topic[topics.LEFT_INFO], topic[topics.RIGHT_INFO]]
            infos = {m.topic: m.msg for m in itertools.islice(bag.messages(wanted), 0, 64)}
        if len(infos) == 2:
            images.camera_from_infos(infos[wanted[0]], infos[wanted[1]])
            camera_frame = str(infos[wanted[0]].header.frame_id)
    poses: TopicPoses | TFPoses
    tf = None
    if read_as.pose_source == "tf":
        assert read_as.world_frame is not None
        tf = TFBuffer(cache_time_s=1e6, capacity=10_000_000)
        poses = TFPoses(tf, read_as.world_frame, read_as.camera_frame)
        poses.set_camera(camera_frame or "", images.raw_from_rectified)
        sources = [topic["tf"], topic["tf_static"]]
    else:
        poses = TopicPoses()
        sources = [topic[topics.POSE]]
    with open_bag(bag_path) as bag:
        present = [t for t in sources if t in bag.topics]
        if not present or sources[0] not in present:
            raise BagError(f"bag {bag_path} has no {sources[0]}: no reference poses ({read_as.pose_source})")
        for message in bag.messages(present):
            if tf is not None:
                tf.add_message(message.msg, static=message.topic == topic["tf_static"])
            elif isinstance(poses, TopicPoses):
                poses.buffer.add_message(message.msg)
    out = []
    for stamp in stamps_ns:
        found = poses.pose_at(int(stamp))
        if found.pose is None:
            _LOG.warning("no reference pose at %d ns: %s; the KITTI metrics are skipped", stamp, found.detail)
            return None
        out.append(found.pose)
    return np.stack(out) if out else None


def estimate_bag_poses(
    bag_path: Path | str,
    *,
    namespace: str | None = None,
    params: VOParams | None = None,
    progress: bool = False,
    stereo_input: StereoInput | None = None,
    slop: float = 0.0,
    dropped: Counter[str] | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.float64], list[FrameQuality]]:
    """Estimate the pose of every synchronised stereo pair of a bag.

    Pairs with unusable images are skipped and counted in ``dropped`` (see :func:`bag_stereo_frames`).

    Returns:
        (N,) stamps in nanoseconds, (N, 4, 4) poses and the per-frame quality
        (its ``stamp`` in seconds).

    Raises:
        BagError, CalibrationError: see :func:`bag_stereo_frames`.
        OdometryError: no usable frame.
    """
    camera, pairs = bag_stereo_frames(
        bag_path, namespace=namespace, stereo_input=stereo_input, slop=slop, dropped=dropped
    )
    stamps: list[int] = []
    first = [pairs]

    def frames() -> Iterator[tuple[float, NDArray[np.uint8], NDArray[np.uint8]]]:
        # Later passes (see estimate_poses) read the bag again; its drops were counted in the first.
        source = first.pop() if first else bag_stereo_frames(
            bag_path, namespace=namespace, stereo_input=stereo_input, slop=slop
        )[1]  # fmt: skip
        stamps.clear()
        for stamp_ns, left, right in tqdm(source, desc="odometry", unit="frame", disable=not progress):
            interrupts.check()
            stamps.append(stamp_ns)
            yield stamp_ns / _NS_PER_S, left, right

    poses, qualities = estimate_poses(camera, frames, params=params)
    return np.array(stamps, dtype=np.int64), poses, qualities


# --------------------------------------------------------------------------- online use (the node)


@dataclass(frozen=True)
class OnlineDecision:
    """The final decision on one frame of :class:`OnlineOdometry`: ``pose`` (4x4, metres) or None when unreliable.

    ``chained`` is the pose the online chain carries for the frame: ``pose`` when reliable, else a guess
    (for scoring a whole sequence; never to be labelled with).
    """

    stamp_ns: int
    pose: NDArray[np.float64] | None
    quality: FrameQuality
    chained: NDArray[np.float64]


class OnlineOdometry:
    """Poses for the labeler node when no pose topic is configured (``pose_source: odometry``).

    ``add(stamp_ns, left, right)`` returns the frames whose pose is now
    final, oldest first: each frame's pose ``T_world_left``, or None when it
    is unreliable (the node then skips it, as for a missing pose). The
    decisions are those of the offline :func:`estimate_poses` as far as the
    frames seen so far allow:

    * a frame's pose comes once ``VOParams.smoothing_lag_frames`` frames
      after it have arrived; its step from the frame before is the
      measured one with the length smoothed over the frames up to then
      (at least the last ``_SMOOTHING_SPAN`` frames, back to the last reliable frame released within them;
      :func:`smooth_step_lengths`,
      which ``estimate_poses`` runs over the whole sequence);
    * a reliable frame alone among unreliable ones is reported ``isolated``
      (:class:`~selfcontra_ros.odometry.stereo_vo.IsolationGate`), decided
      up to ``VOParams.isolated_frames`` frames later;
    * an ``ok`` frame whose smoothed step length the frames up to then pin
      down too loosely is reported ``uncertain``
      (:func:`~selfcontra_ros.odometry.stereo_vo.step_length_spread` over
      the same frames as the smoother).

    :meth:`finish` releases the frames still held at the end of a stream.
    :attr:`last_quality` is the newest frame's quality as measured.
    """

    def __init__(self, camera: StereoCamera, params: VOParams | None = None) -> None:
        self._vo = StereoOdometry(camera, params)
        p = self._vo.params
        self._gate = IsolationGate(p)
        self._lag = int(p.smoothing_lag_frames) if p.smooth_lengths else 0
        self._stamps: dict[int, int] = {}  # frame index -> stamp, of the frames not released yet
        self._decided: deque[FrameQuality] = deque()  # decided by the gate, waiting for the lag
        # Index and pose of the last frame released, and of the last reliable one (the anchor of the next).
        self._released: tuple[int, NDArray[np.float64]] | None = None
        self._anchor: tuple[int, NDArray[np.float64]] | None = None
        self.last_quality: FrameQuality | None = None

    @property
    def camera(self) -> StereoCamera:
        """The stereo camera the odometry was built for."""
        return self._vo.camera

    def add(self, stamp_ns: int, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> list[OnlineDecision]:
        """Take a new pair; return the decisions now final (earlier frames', this frame's, or none yet)."""
        result = self._vo.add(left, right, stamp_ns / _NS_PER_S)
        self.last_quality = result.quality
        self._stamps[result.quality.index] = int(stamp_ns)
        self._decided.extend(self._gate.add(result.quality))
        decisions = self._release(result.quality.index - self._lag)
        # Memory stays bounded on a stream of hours: the odometry forgets what the smoother will not read again
        # (and keeps what it reads itself).
        self._vo.forget_before(self._smoothing_window(len(self._vo.poses) - 1)[1])
        return decisions

    def finish(self) -> list[OnlineDecision]:
        """The end of the stream: decide and release every frame still held (as :func:`estimate_poses` would)."""
        self._decided.extend(self._gate.finish())
        return self._release(len(self._vo.poses) - 1)

    def undecided(self) -> list[int]:
        """Stamps of the frames added whose decision has not come out yet."""
        return sorted(self._stamps.values())

    @property
    def max_hold(self) -> int:
        """The most frames a frame waits for its decision (the smoothing lag, or the isolation reach)."""
        return max(self._lag, int(self._vo.params.isolated_frames))

    def _smoothing_window(self, newest: int) -> tuple[tuple[int, NDArray[np.float64]] | None, int]:
        """The anchor of the next poses released, and the first frame the smoother reads.

        A frame's pose is the anchor's (the last reliable frame released) and
        the measured motion since, with the step lengths smoothed: the
        odometry still rewrites the guessed poses of unreliable frames between
        them when a measured frame follows, so they are not chained through.
        Once the last reliable frame lies more than the smoothing span back
        (a failure of about span - lag frames), the anchor is the last frame
        released instead, so the smoother's window stays bounded.
        """
        anchor = self._anchor
        if anchor is None or anchor[0] < newest - _SMOOTHING_SPAN:
            anchor = self._released
        return anchor, 0 if anchor is None else max(0, min(anchor[0], newest - _SMOOTHING_SPAN))

    def _release(self, last: int) -> list[OnlineDecision]:
        """Release the decided frames up to index ``last``, with their smoothed poses."""
        out: list[OnlineDecision] = []
        if not self._decided or self._decided[0].index > last:
            return out
        vo = self._vo
        newest = len(vo.poses) - 1
        anchor, base = self._smoothing_window(newest)
        # The smoother sees the frames base..newest; references are renumbered from base (further back: none).
        qualities = [replace(q, reference=q.reference - base) for q in vo.qualities[base:]]
        smoothed = smooth_step_lengths(np.stack(vo.poses[base:]), qualities, vo.params)
        spread = step_length_spread(qualities, vo.params)
        while self._decided and self._decided[0].index <= last:
            quality = self._decided.popleft()
            k = quality.index
            quality = judge_spread(quality, float(spread[k - base]), vo.params, vo.camera.focal_baseline)
            if anchor is None:  # frame 0, the world's origin
                pose = vo.poses[k]
            else:
                assert base <= anchor[0] < k
                pose = anchor[1] @ invert_pose(smoothed[anchor[0] - base]) @ smoothed[k - base]
            self._released = (k, pose)
            if quality.reliable or anchor is None:
                self._anchor = anchor = (k, pose)
            stamp = self._stamps.pop(k)
            out.append(OnlineDecision(stamp, pose.copy() if quality.reliable else None, quality, pose.copy()))
        return out


# --------------------------------------------------------------------------- files and the command


def quality_paths(out: Path | str) -> tuple[Path, Path]:
    """Where :func:`odometry_command` writes the quality of ``out``: ``<out stem>.quality.csv`` and ``.json``."""
    out = Path(out)
    base = out.with_suffix("") if out.suffix else out
    return base.with_name(base.name + ".quality.csv"), base.with_name(base.name + ".quality.json")


def write_quality(csv_path: Path | str, qualities: list[FrameQuality]) -> None:
    """Write the per-frame quality as CSV (one row per frame, the fields of :class:`FrameQuality`; a
    vector field, ``road_motion``, as its numbers separated by spaces, empty when there is none)."""
    names = list(asdict(qualities[0])) if qualities else list(FrameQuality.__dataclass_fields__)
    with Path(csv_path).open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=names)
        writer.writeheader()
        for q in qualities:
            row = asdict(q)
            writer.writerow({k: " ".join(f"{x:.9g}" for x in v) if isinstance(v, tuple) else v for k, v in row.items()})


def odometry_command(
    input_path: Path | str,
    out: Path | str,
    *,
    sequence: str | None = None,
    namespace: str | None = None,
    params: VOParams | None = None,
    lengths: tuple[float, ...] = SHORT_LENGTHS,
    step: int = 1,
    progress: bool = True,
    echo: Callable[[str], None] | None = print,
    stereo_input: StereoInput | None = None,
    reference_poses: bool = False,
    slop: float = 0.0,
) -> dict[str, Any]:
    """Estimate poses of a sequence folder or a bag, write them and their quality, evaluate against ground truth.

    Args:
        input_path: KITTI-layout root/sequence folder, or a rosbag2 folder / ``.mcap`` file.
        out: pose file to write (KITTI format); the quality goes beside it (:func:`quality_paths`).
        sequence: sequence of a root holding several.
        namespace: stereo topic namespace of a bag (default: detected).
        params: odometry parameters.
        lengths: sub-sequence lengths (metres) of the KITTI metrics.
        step: first frames every ``step`` frames for the metrics.
        progress: show a progress bar.
        echo: where the summary lines go (None: silent).
        stereo_input: how a bag is read (remaps, compressed or raw images, rectification, pose source);
            None: as the bag records it, else the package's layout.
        reference_poses: evaluate a bag against its own poses (``stereo_input.pose_source``: the pose
            topic or TF) with the KITTI metrics.
        slop: a bag's left and right images are paired within this many seconds (0: equal stamps).

    Returns:
        The content of the quality JSON: ``input``, ``frames``, ``reliable_frames``,
        ``unreliable`` (list of ``{frame, status, message}``), ``dropped`` (a bag's stereo
        pairs skipped for unusable images, reason -> count), ``runtime_s``,
        ``ms_per_frame``, ``metrics`` (None without ground truth) and ``quality`` (per frame).

    Raises:
        DatasetError, BagError: unreadable input.
        OdometryError: no usable frame (too little texture, no motion).
    """
    input_path, out = Path(input_path), Path(out)
    started = time.perf_counter()
    ground_truth = None
    dropped: Counter[str] = Counter()
    if is_bag(input_path):
        stamps, poses, qualities = estimate_bag_poses(
            input_path,
            namespace=namespace,
            params=params,
            progress=progress,
            stereo_input=stereo_input,
            slop=slop,
            dropped=dropped,
        )
        if reference_poses:
            ground_truth = bag_reference_poses(input_path, stamps, namespace=namespace, stereo_input=stereo_input)
    else:
        seq = open_sequence(input_path, sequence=sequence)
        poses, qualities = estimate_poses(
            seq.camera, lambda: _sequence_frames(seq, range(len(seq)), progress), params=params
        )
        ground_truth = seq.poses
    runtime = time.perf_counter() - started
    out.parent.mkdir(parents=True, exist_ok=True)
    write_poses(out, poses)
    csv_path, json_path = quality_paths(out)
    write_quality(csv_path, qualities)
    metrics: OdometryMetrics | None = None
    if ground_truth is not None:
        # World = first frame's left camera for both, as the metrics compare relative motions only.
        metrics = evaluate_odometry(poses, ground_truth, lengths=lengths, step=step)
    unreliable = [{"frame": q.index, "status": q.status, "message": q.message} for q in qualities if not q.reliable]
    report: dict[str, Any] = {
        "input": str(input_path),
        "poses": str(out),
        "frames": len(qualities),
        "reliable_frames": len(qualities) - len(unreliable),
        "unreliable": unreliable,
        "dropped": dict(sorted(dropped.items())),
        "runtime_s": runtime,
        "ms_per_frame": 1000.0 * runtime / max(len(qualities), 1),
        "disparity_offset_px": qualities[-1].disparity_offset_px if qualities else 0.0,
        "metrics": None if metrics is None else asdict(metrics),
        "quality": [asdict(q) for q in qualities],
    }
    write_json(json_path, report)
    if echo is not None:
        echo(f"{len(qualities)} frames, {report['reliable_frames']} reliable, {report['ms_per_frame']:.0f} ms/frame")
        if report["disparity_offset_px"] != 0.0:
            echo(f"disparity offset applied: {report['disparity_offset_px']:+.3f} px (added to every disparity)")
        for item in unreliable:
            echo(f"  frame {item['frame']}: {item['status']}: {item['message']}")
        if dropped:
            echo("skipped stereo pairs: " + ", ".join(f"{k}={v}" for k, v in sorted(dropped.items())))
        if metrics is not None:
            echo("against ground truth: " + metrics.summary())
        echo(f"wrote {out}, {csv_path}, {json_path}")
    return report
