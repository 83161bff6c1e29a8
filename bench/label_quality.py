"""Label quality over many synthetic sequences: mean, spread and worst case per scene, and the forest they train.

Renders ``--scenes`` x ``--seeds`` sequences (``--frames`` frames at
``--size``), labels each with the package defaults (or ``--params`` /
``--set``) exactly as ``selfcontra label`` does, and prints:

* one row per sequence: accuracy, coverage, positive and negative precision,
  bad recall (share of the query's wrong pixels labelled negative) and the
  query algorithm's bad-pixel rate, each the mean over the labelled frames;
* per scene the mean, standard deviation and worst value of each;
* with ``--confidence``: per scene, the default forest (``ensemble``) trained
  on the self-generated labels of the first half of the seeds and on their
  ground truth, both evaluated on the second half (AUSC / optimal), and the
  ratio self / ground truth (the paper's Table 1 comparison); with
  ``--forest-seeds N`` both forests are trained with N forest seeds and the
  figures are means, with the ratio per forest seed (the forest's own seed
  moves one AUSC by a few percent); ``--first-forest-seed K`` makes them
  seeds K .. K + N - 1 (one other seed alone: ``--forest-seeds 1
  --first-forest-seed K``);
* with ``--oracles`` too: forests trained on the self labels mended with the
  ground truth (:data:`ORACLES`: the labelled pixels' true labels; only the
  positives mended; only the negatives; the wrong positives or all wrong
  labels left out), which tell whether the choice of pixels or the wrong
  positives or negatives cost the forest; and the ground truth of the labelled
  frames alone (``gt_labelled_frames``: the labeller leaves the last
  ``label_delay`` frames of a sequence unlabelled, a third of 30 frames, so
  the ``gt`` forest learns from half as many images again);
* a PNG (``--plot``) of positive precision and accuracy against the query
  bad rate, one point per sequence;
* last, one JSON line with all of it.

Rendered sequences are kept in ``--cache`` (default a temporary folder) so
that parameter sweeps render once. Examples::

    python bench/label_quality.py --seeds 1-10 --size 613x185 --cache /tmp/lq --confidence
    python bench/label_quality.py --scenes street --seeds 1-10 --set labeler.stage2_positive_sigma=1.0 --cache /tmp/lq
    python bench/label_quality.py --seeds 11-20 --cache /tmp/lq --out /tmp/lqk          # labels kept in --out
    python bench/label_quality.py --seeds 11-20 --cache /tmp/lq --labels-from /tmp/lqk --confidence  # no relabelling
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray
from tqdm import tqdm

from selfcontra_ros.batch.label import COMPLETE
from selfcontra_ros.cli import add_band_prior_options, band_prior, parse_seeds, parse_size
from selfcontra_ros.confidence.constants import MAX_FOREST_SEED
from selfcontra_ros.confidence.training import BandPrior
from selfcontra_ros.datasets import SCENES
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.reports import METRICS_FILE
from selfcontra_ros.threads import limit_threads

# The label benchmark's scenes: the defaults were tuned on their seeds 1-10 (a scene added to
# SCENES later, e.g. for odometry, joins only when named with --scenes).
LABEL_SCENES = ("street", "orbit", "room")

#: Figures per sequence: (metrics key, column title, True if larger is better).
FIGURES = (
    ("accuracy", "accuracy", True),
    ("coverage", "coverage", True),
    ("positive_precision", "pos. prec.", True),
    ("negative_precision", "neg. prec.", True),
    ("bad_recall", "bad recall", True),
    ("query_bad_rate", "query bad", False),
)


def _parameter_file(params: str | None, overrides: list[str], work: Path) -> Path | None:
    """The labeler parameter file: ``params`` with ``--set section.key=value`` overrides applied."""
    if not overrides:
        return Path(params) if params else None
    if params:
        document = yaml.safe_load(Path(params).read_text())
        body = next(iter(document.values()))["ros__parameters"]
    else:
        document = {"labeler": {"ros__parameters": {}}}
        body = document["labeler"]["ros__parameters"]
    for item in overrides:
        key, sep, value = item.partition("=")
        section, dot, name = key.partition(".")
        if not sep or not dot:
            raise SystemExit(f"--set expects section.key=value, got {item!r}")
        body.setdefault(section, {})[name] = yaml.safe_load(value)
    path = work / "params.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def _sequence(cache: Path, scene: str, seed: int, frames: int, size: tuple[int, int]) -> Path:
    """The rendered sequence, rendered once per cache (into a temporary name, then renamed: never half a sequence)."""
    root = cache / f"{scene}_s{seed}_f{frames}_{size[0]}x{size[1]}"
    if not root.is_dir():
        partial = root.with_name(f".{root.name}.{os.getpid()}.partial")
        shutil.rmtree(partial, ignore_errors=True)
        write_sequence(partial, scene=scene, frames=frames, seed=seed, width=size[0], height=size[1])
        partial.rename(root)
    return root


def _reused_metrics(labels: Path, data: Path) -> dict[str, Any]:
    """The metrics of an earlier run's complete label folder, which must have labelled ``data`` (``--labels-from``).

    The file stores a NaN figure (e.g. a sequence without negatives) as null: it is read back as NaN, as
    :func:`~selfcontra_ros.pipeline.label_sequence` returns it.
    """
    path = labels / METRICS_FILE
    if not path.is_file():
        raise SystemExit(f"--labels-from: no labels at {labels} (run the benchmark with --out first)")
    metrics: dict[str, Any] = json.loads(path.read_text())
    if Path(str(metrics.get("sequence", ""))).resolve() != data.resolve():
        raise SystemExit(f"--labels-from: {labels} labelled {metrics.get('sequence')}, not {data}")
    if metrics.get("status") != COMPLETE:
        raise SystemExit(f"--labels-from: {labels} is {metrics.get('status')!r}, not {COMPLETE!r} (relabel it)")
    metrics["mean"] = {k: math.nan if v is None else v for k, v in metrics.get("mean", {}).items()}
    return metrics


def _summary(values: list[float], larger_is_better: bool) -> dict[str, float]:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return {"mean": math.nan, "std": math.nan, "worst": math.nan}
    worst = min(finite) if larger_is_better else max(finite)
    return {"mean": float(np.mean(finite)), "std": float(np.std(finite)), "worst": float(worst)}


def _pct(value: float) -> str:
    return "   -  " if not math.isfinite(value) else f"{100 * value:6.2f}"


#: ``--oracles``: training labels that mend one part of the self labels with the ground truth, to tell what in
#: them costs the forest. Each maps (self label image, ground-truth label image, the query's fattening band as
#: the labeler drew it) to the training labels; the self forest's band prior then draws from what is left unknown.
ORACLES: dict[str, Callable[[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.bool_]], NDArray[Any]]] = {
    # The labelled pixels, each with its true label: what the choice of pixels costs, without label errors.
    "gt_at_labels": lambda own, gt, band: np.where(own != UNKNOWN, gt, UNKNOWN),
    # Only the positives mended (a wrong one becomes negative): what the wrong positives cost.
    "gt_positives": lambda own, gt, band: np.where(own == POSITIVE, gt, own),
    # Only the negatives mended (a wrong one becomes positive): what the wrong negatives cost.
    "gt_negatives": lambda own, gt, band: np.where(own == NEGATIVE, gt, own),
    # The wrong positives left out (unknown): their cost without adding negatives, which the balanced
    # draw (as many positives as negatives per image) would turn into more samples of both classes.
    "no_wrong_positives": lambda own, gt, band: np.where((own == POSITIVE) & (gt == NEGATIVE), UNKNOWN, own),
    # Every wrong label left out.
    "no_wrong_labels": lambda own, gt, band: np.where((own != UNKNOWN) & (gt != UNKNOWN) & (gt != own), UNKNOWN, own),
    # The unlabelled pixels of the fattening band with their true labels (the rest as labelled): what a perfect
    # band cue, in place of the band prior and its look, could reach.
    "gt_in_band": lambda own, gt, band: np.where((own == UNKNOWN) & band, gt, own),
    # Every unlabelled pixel with its true label, the labelled ones as they are: what any labelling signal on the
    # pixels the consistency test leaves unknown could reach, its own errors kept.
    "gt_at_unknown": lambda own, gt, band: np.where(own == UNKNOWN, gt, own),
    # Every pixel with its true label, on the frames the labeler labelled only: the ground-truth forest of the
    # self forest's own images. The ground-truth forest ("gt") learns from every frame of a sequence, the
    # labels miss its last ``label_delay`` frames (a third of a 30-frame sequence, a few frames of a user's
    # bag): the ratio to this one is the labels' quality alone, without the images they lack.
    "gt_labelled_frames": lambda own, gt, band: gt,
}

#: :data:`ORACLES` that label every pixel with ground truth are trained as the ground-truth forest is, without
#: the self forest's band prior (which would draw the pixels without ground truth in the band as negatives).
WHOLE_TRUTH = frozenset({"gt_labelled_frames"})


def _oracle_folders(row: dict[str, Any], work: Path, names: list[str]) -> dict[str, Path]:
    """One label folder per :data:`ORACLES` entry in ``names`` for a labelled sequence, the query matched again."""
    import cv2

    from selfcontra_ros.confidence.commands import _label_source, iter_frames, training_matcher
    from selfcontra_ros.confidence.training import prior_band
    from selfcontra_ros.evaluation.metrics import ground_truth_labels
    from selfcontra_ros.matching.base import make_matcher

    own_root = Path(row["labels"])
    matcher = make_matcher(training_matcher([(row["data"], own_root)]))  # the labels' own query algorithm
    labeler = _label_source(own_root, row["data"]).labeler  # the band prior's band: the labels' labeler's
    folders = {name: work / "oracles" / name / own_root.name for name in names}
    for folder in folders.values():
        (folder / "labels").mkdir(parents=True, exist_ok=True)
        shutil.copy(own_root / "metrics.json", folder / "metrics.json")  # the query algorithm travels with them
    for frame in iter_frames(row["data"]):
        name = f"{frame.index:06d}.png"
        own_path = own_root / "labels" / name
        if not own_path.is_file() or frame.gt_disparity is None:
            continue  # a frame the labeler did not label (the last label_delay of a sequence)
        own = np.asarray(cv2.imread(str(own_path), cv2.IMREAD_UNCHANGED), dtype=np.uint8)
        disparity = matcher.compute(frame.left, frame.right, with_right=False).left
        gt = ground_truth_labels(disparity, frame.gt_disparity)
        band = prior_band(disparity, labeler)
        for oracle in names:
            cv2.imwrite(str(folders[oracle] / "labels" / name), ORACLES[oracle](own, gt, band).astype(np.uint8))
    return folders


def _forest_suffix(seed: int) -> str:
    """Model file suffix of a forest seed: none for seed 0 (the package's forest), ``_f<k>`` otherwise."""
    return "" if seed == 0 else f"_f{seed}"


def forest_figures(scores: dict[str, float], forest_seeds: int, first_forest_seed: int = 0) -> dict[str, Any]:
    """The summary of :func:`_confidence`'s mean AUSC / optimal per model (keyed by model file stem).

    ``self`` / ``gt`` (and ``self_f1``, ``gt_f1``, ...) are the forests of each forest seed
    ``first_forest_seed .. first_forest_seed + forest_seeds - 1``: their means are ``ausc_ratio_self`` /
    ``ausc_ratio_gt`` and their ratios per seed ``self_over_gt_by_forest_seed`` (mean ``self_over_gt``);
    every other model (``lrd``, the oracles) keeps its own ``ausc_ratio_<name>``.
    """
    suffixes = [_forest_suffix(k) for k in range(first_forest_seed, first_forest_seed + forest_seeds)]
    # The oracles' names start with "gt_" too, so the self and ground-truth forests are named one by one.
    forests = {f"{kind}{x}" for kind in ("self", "gt") for x in suffixes}
    # The means come last: from another first seed, seed 0's "self" / "gt" are not this run's forests.
    out: dict[str, Any] = {
        **{f"ausc_ratio_{k}": v for k, v in scores.items() if k not in forests},
        "ausc_ratio_self": float(np.mean([scores[f"self{x}"] for x in suffixes])),
        "ausc_ratio_gt": float(np.mean([scores[f"gt{x}"] for x in suffixes])),
    }
    by_seed = [scores[f"self{x}"] / scores[f"gt{x}"] for x in suffixes if scores.get(f"gt{x}")]
    if by_seed:
        out["self_over_gt"] = float(np.mean(by_seed))
        out["self_over_gt_by_forest_seed"] = by_seed
    return out


def _confidence(
    scene: str,
    rows: list[dict[str, Any]],
    work: Path,
    *,
    oracles: list[str] | None = None,
    forest_seeds: int = 1,
    first_forest_seed: int = 0,
    band: BandPrior | None = None,
) -> dict[str, Any]:
    """Ensemble forests trained on self labels / ground truth of the first half of the seeds, scored on the rest.

    Both forests are trained once per forest seed ``first_forest_seed .. first_forest_seed + forest_seeds -
    1`` (the forest's ``random_state``; the sample draw stays the same) and the figures are means over them,
    with the self / ground-truth ratio per forest seed: one forest's AUSC moves by a few percent with its
    seed alone, which a label change must exceed to be seen. With ``oracles`` also on each of these
    :data:`ORACLES` mendings of the self labels (the first forest seed). ``band``: the
    self forests' band prior (``train --band-*``); the ground-truth forest takes none.
    """
    from selfcontra_ros.confidence.commands import evaluate_command, train_command

    ordered = sorted(rows, key=lambda r: r["seed"])
    half = len(ordered) // 2
    train, test = ordered[:half], ordered[half:]
    if not train or not test or forest_seeds < 1:
        return {}
    folder = work / f"confidence_{scene}"
    models: list[Path | str] = []
    for k in range(first_forest_seed, first_forest_seed + forest_seeds):
        suffix, forest = _forest_suffix(k), {"random_state": k}  # merged into FOREST: seed 0 is its own
        self_model, gt_model = folder / f"self{suffix}.npz", folder / f"gt{suffix}.npz"
        train_command(
            [(r["data"], r["labels"]) for r in train],
            "ensemble",
            self_model,
            forest=forest,
            band=band,
        )
        train_command([(r["data"], "gt") for r in train], "ensemble", gt_model, forest=forest)
        models += [self_model, gt_model]
    models.append("lrd")
    if oracles:
        mended = [_oracle_folders(r, work, oracles) for r in train]
        for name in oracles:
            model = folder / f"{name}.npz"
            pairs = [(r["data"], m[name]) for r, m in zip(train, mended, strict=True)]
            train_command(
                pairs,
                "ensemble",
                model,
                forest={"random_state": first_forest_seed},
                band=BandPrior(share=0.0) if name in WHOLE_TRUTH else band,
            )
            models.append(model)
    # Results are keyed by the model files' stems: "self", "gt" (and "self_f1", "gt_f1", ...), "lrd" and the
    # oracles' names.
    ratios: dict[str, list[float]] = {Path(str(m)).stem: [] for m in models}
    for r in test:
        results = evaluate_command(models, r["data"], folder / f"eval_s{r['seed']}")
        for key, values in ratios.items():
            values.append(float(results[key]["mean"]["ausc_ratio"]))
    out = forest_figures({k: float(np.mean(v)) for k, v in ratios.items() if v}, forest_seeds, first_forest_seed)
    out["train_seeds"] = [r["seed"] for r in train]
    out["test_seeds"] = [r["seed"] for r in test]
    return out


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharex=True)
    for scene, marker in zip(dict.fromkeys(r["scene"] for r in rows), itertools.cycle("os^Dv"), strict=False):
        mine = [r for r in rows if r["scene"] == scene]
        bad = [100 * r["query_bad_rate"] for r in mine]
        for ax, key in zip(axes, ("positive_precision", "accuracy"), strict=True):
            ax.scatter(bad, [100 * r[key] for r in mine], marker=marker, label=scene)
            for r, x in zip(mine, bad, strict=True):
                ax.annotate(str(r["seed"]), (x, 100 * r[key]), fontsize=6, xytext=(2, 2), textcoords="offset points")
    for ax, title, target in zip(axes, ("positive precision", "accuracy"), (99.0, 97.0), strict=True):
        ax.axhline(target, color="grey", lw=0.8, ls="--")
        ax.set_xlabel("query algorithm bad-pixel rate (%)")
        ax.set_ylabel(f"{title} (%)")
        ax.set_title(f"{title} per sequence")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=list(LABEL_SCENES))
    parser.add_argument("--seeds", type=parse_seeds, default=parse_seeds("1-10"), help="e.g. 1-10 (default)")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--size", type=parse_size, default=(1226, 370), help="WxH (default KITTI size 1226x370)")
    parser.add_argument("--params", default=None, help="labeler parameter YAML (default: the package's)")
    parser.add_argument("--set", action="append", default=[], help="override section.key=value (repeatable)")
    parser.add_argument("--cache", default=None, help="folder for rendered sequences (kept between runs)")
    parser.add_argument("--out", default=None, help="folder for labels, models and the plot (default: temporary)")
    parser.add_argument("--plot", default=None, help="PNG of precision / accuracy vs query bad rate")
    parser.add_argument(
        "--labels-from",
        default=None,
        help="reuse the labels of an earlier run's --out folder instead of labelling (its --set is not re-applied)",
    )
    parser.add_argument("--confidence", action="store_true", help="also train and score the Ensemble forest")
    parser.add_argument(
        "--oracles",
        nargs="?",
        const=",".join(ORACLES),
        default=None,
        metavar="NAMES",
        help="also (implies --confidence) train on the self labels mended with ground truth: the comma-separated "
        f"ORACLES given, or all without a value ({', '.join(ORACLES)})",
    )
    parser.add_argument(
        "--forest-seeds",
        type=int,
        default=1,
        help="with --confidence: train both forests with this many forest seeds and report means (default 1)",
    )
    parser.add_argument(
        "--first-forest-seed",
        type=int,
        default=0,
        metavar="K",
        help="with --confidence: the forest seeds are K .. K + forest-seeds - 1 (default 0, the package's forest)",
    )
    add_band_prior_options(parser, prefix="with --confidence, the self forests' as in train")
    parser.add_argument("--threads", type=int, default=0)
    args = parser.parse_args(argv)
    if args.forest_seeds < 1 or not 0 <= args.first_forest_seed <= MAX_FOREST_SEED + 1 - args.forest_seeds:
        parser.error(f"--forest-seeds must be at least 1 and the forest seeds within 0 .. {MAX_FOREST_SEED}")
    oracles = [name for name in args.oracles.split(",") if name] if args.oracles is not None else None
    if oracles is not None and (not oracles or set(oracles) - set(ORACLES)):
        parser.error(f"--oracles takes names of {', '.join(ORACLES)}, not {args.oracles!r}")
    limit_threads(args.threads)

    from selfcontra_ros.pipeline import label_sequence

    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="label_quality_") as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        cache = Path(args.cache) if args.cache else work / "sequences"
        params = _parameter_file(args.params, args.set, work)
        rows: list[dict[str, Any]] = []
        jobs = [(scene, seed) for scene in args.scenes for seed in args.seeds]
        for scene, seed in tqdm(jobs, desc="label quality", unit="seq", file=sys.stderr):
            data = _sequence(cache, scene, seed, args.frames, args.size)
            tick = time.perf_counter()
            if args.labels_from:
                labels = Path(args.labels_from) / "labels" / f"{scene}_s{seed}"
                metrics = _reused_metrics(labels, data)
            else:
                labels = work / "labels" / f"{scene}_s{seed}"
                metrics = label_sequence(data, labels, params_file=params)
            mean = metrics["mean"]
            rows.append(
                {
                    "scene": scene,
                    "seed": seed,
                    "frames": len(metrics["frames"]),
                    "seconds": time.perf_counter() - tick,
                    "data": str(data),
                    "labels": str(labels),
                    **{key: float(mean.get(key, math.nan)) for key, _, _ in FIGURES},
                }
            )
        scenes: dict[str, Any] = {}
        print(f"{'scene':<7} {'seed':>4} " + " ".join(f"{title:>10}" for _, title, _ in FIGURES))
        for scene in args.scenes:
            mine = [r for r in rows if r["scene"] == scene]
            for r in mine:
                print(f"{scene:<7} {r['seed']:>4} " + " ".join(f"{_pct(r[k]):>10}" for k, _, _ in FIGURES))
            scenes[scene] = {key: _summary([r[key] for r in mine], better) for key, _, better in FIGURES}
            for stat in ("mean", "std", "worst"):
                print(f"{scene:<7} {stat:>4} " + " ".join(f"{_pct(scenes[scene][k][stat]):>10}" for k, _, _ in FIGURES))
        if args.confidence or args.oracles:
            for scene in tqdm(args.scenes, desc="confidence", unit="scene", file=sys.stderr):
                mine = [r for r in rows if r["scene"] == scene]
                result = _confidence(
                    scene,
                    mine,
                    work,
                    oracles=oracles,
                    forest_seeds=args.forest_seeds,
                    first_forest_seed=args.first_forest_seed,
                    band=band_prior(args),
                )
                scenes[scene]["confidence"] = result
                if result:
                    print(
                        f"{scene}: Ensemble AUSC/optimal on seeds {result['test_seeds']}: self-labels "
                        f"{result['ausc_ratio_self']:.3f}, ground truth {result['ausc_ratio_gt']:.3f}, "
                        f"ratio {result['self_over_gt']:.3f} (LRD {result['ausc_ratio_lrd']:.3f})"
                    )
                    if args.forest_seeds > 1:
                        spread = result["self_over_gt_by_forest_seed"]
                        print(
                            f"{scene}:   ratio per forest seed {' '.join(f'{v:.3f}' for v in spread)} "
                            f"(min {min(spread):.3f}, max {max(spread):.3f})"
                        )
                    for name in oracles or ():
                        value, versus = result[f"ausc_ratio_{name}"], ""
                        if name in WHOLE_TRUTH:  # trained with the first forest seed only; self is the seeds' mean
                            mean = ", self the forest seeds' mean" if args.forest_seeds > 1 else ""
                            versus = f" (self / it {result['ausc_ratio_self'] / value:.3f}{mean})"
                        print(f"{scene}:   trained on {name}: {value:.3f}{versus}")
        if args.plot:
            _plot(rows, Path(args.plot))
            print(f"plot: {args.plot}")
        summary = {
            "size": f"{args.size[0]}x{args.size[1]}",
            "frames": args.frames,
            "seeds": args.seeds,
            "params": str(args.params) if args.params else None,
            "set": args.set,
            "scenes": scenes,
            "sequences": [{k: v for k, v in r.items() if k not in ("data", "labels")} for r in rows],
            "seconds": time.perf_counter() - started,
        }
    print(json.dumps(summary, allow_nan=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
