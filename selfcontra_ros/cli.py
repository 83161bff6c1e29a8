"""The ``selfcontra`` command line: a thin adapter over the library.

Each subcommand parses its arguments here and delegates to one library
function; nothing of the algorithm lives in this file. Modules are imported
inside the handlers so that ``selfcontra --help`` stays fast and one
subcommand's optional dependencies never break another.
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from selfcontra_ros import interrupts
from selfcontra_ros.confidence.constants import FOREST, MAX_FOREST_SEED, TRAINING
from selfcontra_ros.datasets import SCENES
from selfcontra_ros.errors import SelfContraError

if TYPE_CHECKING:
    from selfcontra_ros.bags.stereo_input import StereoInput
    from selfcontra_ros.confidence.training import BandPrior

__all__ = ["add_band_prior_options", "band_prior", "build_parser", "main", "parse_frame_range", "parse_size"]


def parse_size(text: str) -> tuple[int, int]:
    """Parse ``WIDTHxHEIGHT`` (an argparse type)."""
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 1226x370, got {text!r}") from None
    if width < 16 or height < 16:
        raise argparse.ArgumentTypeError(f"image size {text!r} is too small (at least 16x16)")
    return width, height


def parse_seeds(text: str) -> list[int]:
    """Parse ``1-10`` or ``1,3,5`` (or both, e.g. ``1-3,7``) as a sorted list of seeds (an argparse type)."""
    seeds: set[int] = set()
    for part in text.split(","):
        first, _, last = part.partition("-")
        try:
            seeds.update(range(int(first), int(last or first) + 1))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected seeds such as 1-10 or 1,3,5, got {text!r}") from None
    return sorted(seeds)


def parse_frame_range(text: str) -> slice:
    """Parse ``A:B`` (either side optional) as a Python slice of frame indices."""
    parts = text.split(":")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected a frame range A:B, got {text!r}")
    try:
        start, stop = (int(p) if p.strip() else None for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"frame range bounds must be integers, got {text!r}") from None
    return slice(start, stop)


def _add_input_options(group: argparse._ArgumentGroup, *, poses: bool = True) -> None:
    """The options of :class:`~selfcontra_ros.bags.stereo_input.StereoInput`: a robot's own bag layout."""
    group.add_argument(
        "--remap",
        action="append",
        default=[],
        metavar="FROM:=TO",
        help="rename a topic the package reads, as a node's -r does (repeatable), e.g. "
        "left/image_rect:=/zed/zed_node/left/image_rect_color; relative TO lives in the namespace",
    )
    group.add_argument(
        "--image-transport",
        choices=("raw", "compressed"),
        default=None,
        help="raw: sensor_msgs/Image; compressed: sensor_msgs/CompressedImage on <image topic>/compressed "
        "(default: as a labelled bag records it, else raw)",
    )
    group.add_argument(
        "--rectify",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="read left/right image_raw and rectify them with their camera_info (D, K, R, P) "
        "(default: as a labelled bag records it, else no)",
    )
    if poses:
        group.add_argument(
            "--pose-source",
            choices=("pose", "tf"),
            default=None,
            help="pose: a PoseStamped/Odometry topic of the left camera; tf: /tf and /tf_static (default: pose)",
        )
        group.add_argument("--world-frame", default=None, help="fixed frame of the TF poses, e.g. odom or map")
        group.add_argument(
            "--camera-frame", default=None, help="left camera frame in TF (default: the left camera_info's frame_id)"
        )


def _input_options(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`StereoInput` fields the user gave on the command line (none: an empty dict)."""
    given: dict[str, Any] = {}
    if args.remap:
        given["remaps"] = tuple(args.remap)
    for option in ("image_transport", "rectify", "pose_source", "world_frame", "camera_frame"):
        value = getattr(args, option, None)
        if value is not None:
            given[option] = value
    return given


def _add_bag_data_options(parser: argparse.ArgumentParser, which: str) -> None:
    """``--namespace`` and the robot-bag options of ``train`` / ``evaluate-confidence`` (bag data only)."""
    group = parser.add_argument_group(f"a robot's own bag ({which}; see 'selfcontra inspect BAG')")
    group.add_argument("--namespace", default=None, help="stereo topic namespace (default: found in the bag)")
    group.add_argument(
        "--slop",
        type=float,
        default=None,
        help="pair left/right images within S seconds (default: as a labelled bag records it, else equal stamps)",
    )
    _add_input_options(group, poses=False)


def _stereo_input(args: argparse.Namespace, bag: Path) -> StereoInput | None:
    """How to read ``bag``: the input it records (a labelled bag's), with the options given replacing theirs.

    None when no option was given: the library then reads the bag's own record.
    """
    given = _input_options(args)
    if not given:
        return None
    from selfcontra_ros.bags.reader import open_bag
    from selfcontra_ros.bags.stereo_input import StereoInput

    with open_bag(bag) as opened:
        stored = StereoInput.of_bag(opened.custom_data)
    return stored.with_options(**given)


def _refuse_input_options(args: argparse.Namespace, data: str | Path) -> None:
    """The robot-bag options apply to bags only."""
    from selfcontra_ros.bags.reader import is_bag

    given = _input_options(args)
    if given and not is_bag(Path(data)):
        flags = ", ".join("--remap" if name == "remaps" else "--" + name.replace("_", "-") for name in given)
        raise SelfContraError(f"{flags} apply to bag input, not to {data}")


def _cmd_synth(args: argparse.Namespace) -> int:
    from selfcontra_ros.datasets.synthetic import write_sequence

    width, height = args.size
    root = write_sequence(
        Path(args.out), scene=args.scene, frames=args.frames, seed=args.seed, width=width, height=height
    )
    print(f"wrote {args.frames} frames of the {args.scene!r} scene (seed {args.seed}) to {root}")
    return 0


def _cmd_label(args: argparse.Namespace) -> int:
    from selfcontra_ros.pipeline import BAG, input_kind, label_input
    from selfcontra_ros.reports import METRICS_FILE

    source, out = Path(args.input), Path(args.out)
    bag = input_kind(source) == BAG
    if not bag:
        _refuse_input_options(args, source)
    metrics = label_input(
        source,
        out,
        params_file=args.params,
        frames=args.frames,
        estimate_poses=args.estimate_poses,
        sync=args.sync,
        slop=args.slop,
        namespace=args.namespace,
        pose_topic=args.pose_topic,
        disparity_topic=args.disparity_topic,
        model_out=Path(args.model_out) if args.model_out else None,
        stereo_input=_stereo_input(args, source) if bag else None,
    )
    if bag:
        written = f"wrote the labelled bag {out} and {out / METRICS_FILE}"
        if args.model_out:
            written += f"; confidence model {args.model_out}"
    else:
        written = f"wrote labels and metrics.json to {out}"
        if metrics["skipped_frames"]:
            written += (
                f" ({len(metrics['frames'])} frames labelled; not labelled: {len(metrics['skipped_frames'])}, "
                "the keyframe rule's skips and the last views without label_delay newer ones, which "
                "labeler.flush_incomplete: true labels too)"
            )
    mean = metrics.get("mean", {})
    if mean:
        print("mean: " + ", ".join(f"{k}={v:.4f}" for k, v in mean.items() if isinstance(v, float)))
    if metrics.get("dropped"):
        print("dropped messages: " + ", ".join(f"{k}={v}" for k, v in metrics["dropped"].items()))
    print(written)
    return 0


def _cmd_kitti2mcap(args: argparse.Namespace) -> int:
    from selfcontra_ros.bags.kitti2mcap import DEFAULT_STAMP_OFFSET_NS, kitti_to_mcap
    from selfcontra_ros.bags.reader import open_bag

    offset_ns = DEFAULT_STAMP_OFFSET_NS if args.stamp_offset is None else round(args.stamp_offset * 1e9)
    out = kitti_to_mcap(
        Path(args.input),
        Path(args.out),
        frames=args.frames,
        compress=args.compress,
        color=args.color,
        sequence=args.sequence,
        stamp_offset_ns=offset_ns,
        estimate_poses=args.estimate_poses,
        compress_images=args.compress_images,
    )
    with open_bag(out) as bag:
        topics = ", ".join(f"{t.name} ({t.message_count})" for t in bag.topics.values())
    print(f"wrote {out}: {topics}")
    return 0


def _cmd_inspect(args: argparse.Namespace) -> int:
    from selfcontra_ros.bags.inspect import format_report, inspect_bag

    print(format_report(inspect_bag(Path(args.input))), end="")
    return 0


def _cmd_odometry(args: argparse.Namespace) -> int:
    from selfcontra_ros.bags.reader import is_bag
    from selfcontra_ros.odometry.run import odometry_command
    from selfcontra_ros.odometry.stereo_vo import VOParams

    _refuse_input_options(args, args.input)
    odometry_command(
        Path(args.input),
        Path(args.out),
        sequence=args.sequence,
        namespace=args.namespace,
        step=args.step,
        stereo_input=_stereo_input(args, Path(args.input)) if is_bag(Path(args.input)) else None,
        reference_poses=args.pose_source is not None,
        slop=args.slop,
        params=VOParams(
            disparity_offset_px=args.disparity_offset,
            estimate_disparity_offset=not args.fixed_offset,
            road_steps=not args.no_road,
        ),
    )
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from selfcontra_ros.bags.reader import is_bag
    from selfcontra_ros.confidence.commands import train_command
    from selfcontra_ros.matching.base import MatcherParams
    from selfcontra_ros.threads import cap_jobs

    if len(args.data) != len(args.labels):
        raise SelfContraError(f"give one --labels per --data ({len(args.data)} --data, {len(args.labels)} --labels)")
    matcher = MatcherParams(algorithm=args.algorithm) if args.algorithm else None
    if _input_options(args) and not any(is_bag(Path(d)) for d in args.data):
        _refuse_input_options(args, args.data[0])
    summary = train_command(
        list(zip(args.data, args.labels, strict=True)),
        args.features,
        Path(args.out),
        matcher=matcher,
        n_jobs=cap_jobs(args.jobs),
        namespace=args.namespace,
        slop=args.slop,
        stereo_inputs=[_stereo_input(args, Path(d)) if is_bag(Path(d)) else None for d in args.data],
        band=band_prior(args),
        forest={"random_state": args.forest_seed},
    )
    print(
        f"trained {summary['feature_set']} forest on {summary['samples']} samples from {summary['frames']} frames "
        f"in {summary['seconds']:.0f} s: {summary['model']}"
    )
    return 0


def _cmd_evaluate_confidence(args: argparse.Namespace) -> int:
    from selfcontra_ros.bags.reader import is_bag
    from selfcontra_ros.confidence.commands import evaluate_command
    from selfcontra_ros.matching.base import MatcherParams

    matcher = MatcherParams(algorithm=args.algorithm) if args.algorithm else None
    _refuse_input_options(args, args.data)
    stereo_input = _stereo_input(args, Path(args.data)) if is_bag(Path(args.data)) else None
    results = evaluate_command(
        args.model,
        args.data,
        Path(args.out),
        matcher=matcher,
        namespace=args.namespace,
        stereo_input=stereo_input,
        slop=args.slop,
    )
    for name, record in results.items():
        if name != "table":
            mean = record["mean"]
            print(f"{name}: AUSC {mean['ausc']:.4f}, optimal {mean['optimal']:.4f}, ratio {mean['ausc_ratio']:.3f}")
    print(results["table"], end="")
    return 0


def _cmd_batch_label(args: argparse.Namespace) -> int:
    from selfcontra_ros.batch.label import batch_label

    summary = batch_label(
        args.inputs,
        Path(args.out),
        params_file=args.params,
        address=args.address,
        cpus_per_task=args.cpus_per_task,
        resume=args.resume,
    )
    return 0 if summary["totals"]["failed"] == 0 else 1


def _cmd_batch_train(args: argparse.Namespace) -> int:
    from selfcontra_ros.batch.train import batch_train
    from selfcontra_ros.matching.base import MatcherParams
    from selfcontra_ros.threads import cap_jobs

    summary = batch_train(
        args.features,
        Path(args.labels_from),
        args.data,
        Path(args.out),
        address=args.address,
        cpus_per_task=args.cpus_per_task,
        matcher=MatcherParams(algorithm=args.algorithm) if args.algorithm else None,
        max_per_input=args.max_per_input,
        band=band_prior(args),
        n_jobs=cap_jobs(args.jobs),
        forest={"random_state": args.forest_seed},
    )
    print(
        f"trained {summary['feature_set']} forest on {summary['samples']} samples from {summary['frames']} frames "
        f"of {len(summary['inputs'])} input(s) in {summary['seconds']:.0f} s: {summary['model']}"
    )
    return 0


def _forest_seed(text: str) -> int:
    """``--forest-seed``: scikit-learn takes a random state in 0 .. ``MAX_FOREST_SEED`` (2**32 - 1)."""
    seed = int(text)
    if not 0 <= seed <= MAX_FOREST_SEED:
        raise argparse.ArgumentTypeError(f"a forest seed is in 0 .. {MAX_FOREST_SEED} (2**32 - 1), not {seed}")
    return seed


def add_band_prior_options(parser: argparse.ArgumentParser, *, prefix: str = "self labels only") -> None:
    """``--band-negatives``, ``--band-look``, ``--band-cue`` and ``--band-texture``: the band prior of training on
    self labels.

    :func:`band_prior` turns them into a :class:`~selfcontra_ros.confidence.training.BandPrior`; ``prefix``
    starts each help text (the label benchmark says where it applies).
    """
    parser.add_argument(
        "--band-negatives",
        type=float,
        default=float(TRAINING["band_negatives"]),
        metavar="SHARE",
        help=f"{prefix}: the share of the unlabelled pixels of the query's fattening band drawn as negatives "
        f"(default {float(TRAINING['band_negatives']):g}; 0 = the paper: unknown pixels are ignored)",
    )
    parser.add_argument(
        "--band-look",
        type=float,
        default=float(TRAINING["band_look"]),
        metavar="SCORE",
        help=f"{prefix}: band pixels that look at least this much more like the object at their disparity "
        "than like the background beyond their drop are not drawn as negatives (a z-score difference; default "
        f"{float(TRAINING['band_look']):g}; inf = off)",
    )
    parser.add_argument(
        "--band-cue",
        type=float,
        default=float(TRAINING["band_cue"]),
        metavar="PROB",
        help=f"{prefix}: band pixels the package's band cue calls right with at least this probability are "
        f"not drawn as negatives (default {float(TRAINING['band_cue']):g}; inf = off)",
    )
    parser.add_argument(
        "--band-texture",
        type=float,
        default=float(TRAINING["band_texture"]),
        metavar="GREY",
        help=f"{prefix}: band pixels whose thin vertical strip (1x9) varies by less than this many grey levels "
        f"(mean absolute deviation) are not drawn as negatives (default {float(TRAINING['band_texture']):g}; "
        "0 = off)",
    )


def band_prior(args: argparse.Namespace) -> BandPrior:
    """The :class:`~selfcontra_ros.confidence.training.BandPrior` of :func:`add_band_prior_options`' arguments."""
    from selfcontra_ros.confidence.training import BandPrior

    return BandPrior(share=args.band_negatives, look=args.band_look, cue=args.band_cue, texture=args.band_texture)


def _add_training_options(parser: argparse.ArgumentParser) -> None:
    """The band prior's options (:func:`add_band_prior_options`) and ``--forest-seed`` of ``train``, ``batch train``."""
    add_band_prior_options(parser)
    default_seed = _forest_seed(str(FOREST["random_state"]))
    parser.add_argument(
        "--forest-seed",
        type=_forest_seed,
        default=default_seed,
        metavar="N",
        help="random state of the forest (bootstrap draws and split features; default "
        f"{default_seed}): retrain with other seeds to see how much of a difference between two "
        "models is the forest's own spread",
    )


def _add_batch_parser(sub: Any) -> None:
    """``selfcontra batch label`` / ``batch train`` (:mod:`selfcontra_ros.batch`)."""
    batch = sub.add_parser(
        "batch",
        help="label or train on many bags / sequences at once, one Ray task per input (local Ray cluster by default)",
        description="Without Ray installed (pip install '.[cluster]') the inputs run one after another here.",
    )
    jobs = batch.add_subparsers(dest="batch_command", required=True)
    label = jobs.add_parser(
        "label",
        help="label every input as 'selfcontra label' does, into OUT_DIR/<input name>/, with summary.json",
        description="Each input (bag, bag folder, KITTI sequence, odometry root; globs) is one task writing "
        "OUT_DIR/<name>/ atomically. A failed input is reported and the others go on (exit status 1).",
    )
    label.add_argument("inputs", nargs="+", metavar="INPUT", help="bags, sequence folders, odometry roots, globs")
    label.add_argument("--out", required=True, metavar="OUT_DIR", help="output folder (one subfolder per input)")
    label.add_argument("--params", default=None, help="parameter YAML (default: the package's config/labeler.yaml)")
    label.add_argument("--resume", action="store_true", help="skip inputs with a complete result in OUT_DIR")
    label.set_defaults(handler=_cmd_batch_label)
    train = jobs.add_parser(
        "train",
        help="train a confidence forest on batch-labelled inputs, their samples drawn in parallel",
        description="The same model as 'selfcontra train' with --labels OUT_DIR/<name> per --data (same seed).",
    )
    train.add_argument("--features", required=True, choices=("ensemble", "gcp", "park"), help="feature set")
    train.add_argument("--labels-from", required=True, metavar="OUT_DIR", help="the output folder of 'batch label'")
    train.add_argument("--data", nargs="+", required=True, metavar="INPUT", help="the labelled inputs (globs)")
    train.add_argument("--out", required=True, help="model file to write (.npz)")
    train.add_argument(
        "--algorithm", choices=("sgbm", "bm", "census_sgm"), default=None, help="query algorithm if labels name none"
    )
    train.add_argument("--max-per-input", type=int, default=None, help="cap on one input's samples (default none)")
    _add_training_options(train)
    train.add_argument("--jobs", type=int, default=None, help="scikit-learn worker processes of the training")
    train.set_defaults(handler=_cmd_batch_train)
    for parser in (label, train):
        parser.add_argument(
            "--address",
            default=None,
            help="Ray cluster: local (default: start one on this machine, loopback only), auto (the cluster "
            "'ray start' joined) or ray://HOST:PORT",
        )
        parser.add_argument("--cpus-per-task", type=int, default=1, help="CPUs (and threads) per task (default 1)")


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of the ``selfcontra`` command."""
    parser = argparse.ArgumentParser(
        prog="selfcontra",
        description="Stereo confidence labels from self-contradiction (Mostegel et al., CVPR 2016).",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=0,
        help="threads per pool (numba, OpenCV, BLAS, scikit-learn jobs); 0 = every core this process may use",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    synth = sub.add_parser("synth", help="render a synthetic stereo sequence in the KITTI odometry layout")
    synth.add_argument("--scene", choices=SCENES, default="street")
    synth.add_argument("--frames", type=int, default=30, help="number of stereo frames (default 30)")
    synth.add_argument("--seed", type=int, default=1, help="random seed; output is deterministic per seed")
    synth.add_argument("--size", type=parse_size, default=(1226, 370), help="image size WxH (default 1226x370)")
    synth.add_argument("--out", required=True, help="output dataset root (sequences/00, poses/00.txt)")
    synth.set_defaults(handler=_cmd_synth)

    label = sub.add_parser(
        "label",
        help="label a KITTI-layout sequence or a rosbag2 bag with the self-contradiction labeler",
        description="A sequence folder gives label PNGs and metrics.json in OUT; a bag (folder with "
        "metadata.yaml, or .mcap) gives a new MCAP bag OUT with the input and the labeler's output topics.",
    )
    label.add_argument("input", help="sequence folder (dataset root or sequences/XX) or a rosbag2 bag")
    label.add_argument("--out", required=True, help="output folder (sequence) or output bag (bag input)")
    label.add_argument("--params", default=None, help="parameter YAML (default: the package's config/labeler.yaml)")
    label.add_argument("--frames", type=parse_frame_range, default=None, help="frame range A:B (sequences only)")
    label.add_argument(
        "--estimate-poses",
        action="store_true",
        help="sequence without poses: estimate them with stereo visual odometry (unreliable frames are not labelled)",
    )
    bag_options = label.add_argument_group("bag input")
    bag_options.add_argument("--sync", choices=("exact", "approximate"), default="exact", help="image pairing")
    bag_options.add_argument("--slop", type=float, default=0.0, help="approximate sync tolerance, seconds")
    bag_options.add_argument("--namespace", default=None, help="input namespace (default: found in the bag)")
    bag_options.add_argument("--pose-topic", default=None, help="PoseStamped or Odometry topic (default NS/pose)")
    bag_options.add_argument("--disparity-topic", default=None, help="external DisparityImage topic")
    bag_options.add_argument(
        "--model-out", default=None, help="save the confidence forest trained online on the labels (.npz)"
    )
    _add_input_options(label.add_argument_group("a robot's own bag (see 'selfcontra inspect BAG')"))
    label.set_defaults(handler=_cmd_label)

    k2m = sub.add_parser("kitti2mcap", help="convert a KITTI odometry sequence to a rosbag2 bag (MCAP storage)")
    k2m.add_argument("input", help="KITTI odometry root (with sequences/XX) or a sequence folder")
    k2m.add_argument("--out", required=True, help="bag folder to create (an existing path is never overwritten)")
    k2m.add_argument(
        "--frames", type=parse_frame_range, default=None, help="frame range A:B (Python slice; default all)"
    )
    k2m.add_argument("--sequence", default=None, help="sequence to take from a root holding several (e.g. 06)")
    k2m.add_argument("--color", action="store_true", help="convert the colour pair image_2/image_3 (rgb8)")
    k2m.add_argument("--compress", choices=("zstd", "none"), default="zstd", help="MCAP chunk compression")
    k2m.add_argument(
        "--stamp-offset",
        type=float,
        default=None,
        help="seconds added to the sequence stamps (default 2011-09-26T00:00:00Z; 0 keeps times.txt as is)",
    )
    k2m.add_argument(
        "--estimate-poses", action="store_true", help="no poses in the sequence: estimate them with visual odometry"
    )
    k2m.add_argument(
        "--compress-images",
        choices=("jpeg", "png"),
        default=None,
        help="write the images as sensor_msgs/CompressedImage on .../image_rect/compressed (image_transport)",
    )
    k2m.set_defaults(handler=_cmd_kitti2mcap)

    inspect = sub.add_parser(
        "inspect",
        help="a bag's topics, types, counts and rates, its stereo pairs and TF frames, and a suggested label command",
    )
    inspect.add_argument("input", help="rosbag2 bag (folder or .mcap)")
    inspect.set_defaults(handler=_cmd_inspect)

    odo = sub.add_parser(
        "odometry",
        help="estimate poses with stereo visual odometry (KITTI pose file, quality report, KITTI metrics)",
        description="Writes OUT (KITTI pose format) and OUT's quality report beside it; with ground-truth poses, "
        "prints the KITTI odometry metrics (relative translation %% and rotation deg/m over 5-50 m sub-sequences).",
    )
    odo.add_argument("input", help="sequence folder (dataset root or sequences/XX) or a rosbag2 bag")
    odo.add_argument("--out", required=True, help="pose file to write (KITTI format)")
    odo.add_argument("--sequence", default=None, help="sequence of a root holding several (e.g. 06)")
    odo.add_argument("--namespace", default=None, help="stereo topic namespace of a bag (default: found in the bag)")
    odo.add_argument("--step", type=int, default=1, help="metrics: a first frame every STEP frames (KITTI devkit: 10)")
    odo.add_argument(
        "--disparity-offset", type=float, default=0.0, metavar="PX",
        help="the rig's known disparity offset, added to every disparity (default 0; estimated unless --fixed-offset)",
    )  # fmt: skip
    odo.add_argument(
        "--fixed-offset", action="store_true", help="do not estimate the disparity offset: keep --disparity-offset"
    )
    odo.add_argument(
        "--no-road",
        action="store_true",
        help="do not measure the steps a second time on the road ahead (their lengths, rotations and directions; "
        "a camera that sees no ground plane below it)",
    )
    odo_bag = odo.add_argument_group("a robot's own bag")
    odo_bag.add_argument("--slop", type=float, default=0.0, help="pair left/right images within S seconds")
    _add_input_options(odo_bag, poses=False)
    odo_bag.add_argument(
        "--pose-source",
        choices=("pose", "tf"),
        default=None,
        help="the bag's own poses (pose topic or TF) as the reference for the KITTI metrics (default: none)",
    )
    odo_bag.add_argument("--world-frame", default=None, help="fixed frame of the TF poses, e.g. odom")
    odo_bag.add_argument("--camera-frame", default=None, help="left camera frame in TF (default: camera_info's)")
    odo.set_defaults(handler=_cmd_odometry)

    train = sub.add_parser(
        "train",
        help="train a confidence forest on self-generated or ground-truth labels",
        description="Each --data (sequence folder, KITTI stereo split, Middlebury scenes or bag) pairs with the "
        "--labels at the same position: a 'selfcontra label' output folder, the output bag of 'selfcontra label BAG' "
        "(matched to the --data bag's left images by header stamp; the labelled bag itself may be the --data), or "
        "'gt' for labels from the ground-truth disparity (3 px). The model file (.npz) holds plain arrays only.",
    )
    train.add_argument("--features", required=True, choices=("ensemble", "gcp", "park"), help="feature set")
    train.add_argument(
        "--data",
        action="append",
        required=True,
        help="sequence, KITTI stereo split, Middlebury 2003/2014 or ETH3D scenes, or bag (repeatable)",
    )
    train.add_argument(
        "--labels", action="append", required=True, help="label folder, labelled bag or 'gt' (repeatable)"
    )
    train.add_argument(
        "--out", required=True, help="model file to write, as given (.npz is added only to a name without suffix)"
    )
    train.add_argument(
        "--algorithm",
        choices=("sgbm", "bm", "census_sgm"),
        default=None,
        help="query algorithm for 'gt' labels (label folders bring their own; default sgbm)",
    )
    train.add_argument("--jobs", type=int, default=None, help="scikit-learn worker processes (default 1)")
    _add_training_options(train)
    _add_bag_data_options(train, "every --data bag")
    train.set_defaults(handler=_cmd_train)

    evaluate = sub.add_parser(
        "evaluate-confidence",
        help="sparsification curves, AUSC and AUSC/optimal of confidence models against ground truth",
        description="Writes OUT/metrics.json (one model) or OUT/<model>/metrics.json (several), "
        "OUT/sparsification.png, OUT/table.md (paper Table 1 layout) and OUT/summary.json.",
    )
    evaluate.add_argument(
        "--model",
        action="append",
        required=True,
        help="model file as 'train --out' wrote it, 'lrd' (left-right difference) or 'wls' (OpenCV's WLS filter "
        "confidence on the same disparity maps) (repeatable)",
    )
    evaluate.add_argument(
        "--data",
        required=True,
        help="frames with ground truth (sequence, KITTI stereo, Middlebury 2003/2014, ETH3D or bag)",
    )
    evaluate.add_argument("--out", required=True, help="output folder")
    evaluate.add_argument(
        "--algorithm",
        choices=("sgbm", "bm", "census_sgm"),
        default=None,
        help="query algorithm when only 'lrd' / 'wls' are evaluated (models bring their own; default sgbm)",
    )
    _add_bag_data_options(evaluate, "a --data bag")
    evaluate.set_defaults(handler=_cmd_evaluate_confidence)
    _add_batch_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``selfcontra`` command; returns the process exit code."""
    args = build_parser().parse_args(argv)
    with interrupts.handle_signals():
        try:
            from selfcontra_ros.threads import limit_threads

            limit_threads(args.threads)
            status = int(args.handler(args))
            late = interrupts.pending_signal()
            if late is not None:  # arrived after the last safe point: the output is whole, the user still asked
                return _interrupted(args.command, late, "it had just finished: its output is complete")
            return status
        except interrupts.Interrupted as exc:
            return _interrupted(args.command, exc.signum, exc.done)
        except SelfContraError as exc:
            if interrupts.pending_signal() is not None:  # a forced second signal surfaced as an error
                return _interrupted(args.command, interrupts.pending_signal(), "")
            print(f"selfcontra {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except BaseException as exc:
            # A forced second Ctrl-C inside a numba kernel or C callback comes out as SystemError,
            # RuntimeError, or a plain KeyboardInterrupt: still an interrupt, not a crash to report.
            signum = interrupts.pending_signal()
            if signum is None and isinstance(exc, KeyboardInterrupt):
                signum = signal.SIGINT
            if signum is None:
                raise
            return _interrupted(args.command, signum, "")


def _interrupted(command: str, signum: int | None, done: str) -> int:
    """Print the one line of an interrupted command and return its exit status (128 + signal)."""
    signum = signal.SIGINT if signum is None else signum
    what = done or "it wrote no complete output"
    print(f"selfcontra {command}: interrupted by {signal.Signals(signum).name}; {what}", file=sys.stderr)
    return 128 + int(signum)


if __name__ == "__main__":
    sys.exit(main())
