"""``selfcontra batch label``: every input labelled as ``selfcontra label`` labels it, one Ray task per input.

:func:`batch_label` expands the inputs (:mod:`selfcontra_ros.batch.inputs`),
runs :func:`label_one` on each through an engine
(:mod:`selfcontra_ros.batch.engine`: a Ray cluster, local by default, or this
process without Ray) and writes ``OUT_DIR/summary.json``.

**Outputs.** ``OUT_DIR/<name>/`` is exactly what ``selfcontra label INPUT --out
OUT_DIR/<name>`` writes (a label folder for a sequence, a labelled MCAP bag for
a bag; :func:`selfcontra_ros.pipeline.label_input` picks the front end), with
its ``metrics.json``. A task labels into ``OUT_DIR/.<name>.partial-XXXX/<name>``
and moves the finished result into place with one ``os.replace``: a task that
fails, is interrupted or whose worker dies leaves no ``OUT_DIR/<name>``, only
a hidden partial folder, which the next attempt at that input removes (so
one batch at a time writes into an ``OUT_DIR``).

**Resume.** With ``resume=True`` an input whose ``OUT_DIR/<name>/metrics.json``
says ``"status": "complete"`` is not labelled again (it can only be there
after the rename); its parameters must be the ones given. Without it an
existing ``OUT_DIR/<name>`` stops the batch before anything runs: results are
never overwritten.

**Failures.** An input that raises (a corrupt bag, a sequence without poses)
is reported with its error in the summary and the table; the other inputs go
on. A worker process that dies is retried by Ray
(:data:`~selfcontra_ros.batch.engine.MAX_RETRIES` times).

**summary.json**::

    {
      "out_dir": "...", "status": "complete",          # or "interrupted"
      "engine": "a local Ray cluster: 2 CPUs, 2 task(s) at a time",
      "cpus_per_task": 1, "params": "<parameter file or null>", "wall_s": 12.3,
      "inputs": [{"name", "input", "kind", "status": "complete" | "resumed" | "failed" | "not run",
                  "error", "output", "frames", "labelled_frames", "has_ground_truth",
                  "label_positive_share", "label_negative_share", "label_unknown_share",
                  "accuracy", "coverage", "runtime_s"}, ...],
      "totals": {"inputs", "complete", "resumed", "failed", "not_run", "frames", "labelled_frames",
                 "label_positive_share", ..., "accuracy", "coverage", "runtime_s"}
    }

Per input, ``frames`` counts the frames read (a bag's synchronised stereo
pairs; a sequence's frames in range), ``labelled_frames`` those with a label
image, the shares and ``accuracy``/``coverage`` are the means over its
labelled frames (``metrics.json``'s ``mean``; accuracy and coverage only with
ground truth, else null) and ``runtime_s`` the labeler's run time. The totals
weight each input's means by its labelled frames; ``runtime_s`` is their sum
(CPU-side work; ``wall_s`` is the batch's own time).

**Test hook** (for the test suite only): when the environment variable
:data:`KILL_MARKER_ENV` names a file that does not exist, the first task to
create it kills its own worker process (``os._exit``) after labelling and
before the rename, so that Ray's retry is exercised; on the local fallback
(no Ray) the hook is ignored.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from selfcontra_ros import interrupts
from selfcontra_ros.batch.engine import LOCAL, Engine, TaskLostError, open_engine
from selfcontra_ros.batch.inputs import BatchInput, expand_inputs
from selfcontra_ros.config import load_params, params_to_dict
from selfcontra_ros.errors import BatchError
from selfcontra_ros.pipeline import label_input
from selfcontra_ros.reports import METRICS_FILE, json_safe, write_json
from selfcontra_ros.threads import limit_threads

__all__ = [
    "KILL_MARKER_ENV",
    "SUMMARY_FILE",
    "batch_label",
    "complete_result",
    "format_table",
    "label_one",
    "partial_prefix",
    "summarise_metrics",
]

SUMMARY_FILE = "summary.json"
#: Test-only: names a marker file; the task that creates it kills its worker once (module docstring).
KILL_MARKER_ENV = "SELFCONTRA_BATCH_TEST_KILL_MARKER"
COMPLETE, RESUMED, FAILED, NOT_RUN = "complete", "resumed", "failed", "not run"
#: The figures of an input's metrics.json mean that the summary keeps.
_FIGURES = (
    "label_positive_share",
    "label_negative_share",
    "label_unknown_share",
    "query_valid_share",
    "accuracy",
    "coverage",
)


def partial_prefix(name: str) -> str:
    """The name prefix of the hidden folders input ``name`` is labelled in before the rename."""
    return f".{name}.partial-"


def _remove_partials(out_dir: Path, name: str) -> None:
    """Remove what earlier attempts at ``name`` left (a dead worker's or an interrupted run's partial folders)."""
    for stale in out_dir.glob(partial_prefix(name) + "*"):
        shutil.rmtree(stale, ignore_errors=True)


def _kill_once(marker: str | None) -> None:
    """The test hook: the first caller to create ``marker`` kills its own process (module docstring)."""
    if not marker:
        return
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return
    os.write(fd, f"{os.getpid()}\n".encode())
    os.close(fd)
    os._exit(1)


def summarise_metrics(metrics: dict[str, Any]) -> dict[str, Any]:
    """The summary figures of one input from its ``metrics.json`` content (module docstring)."""
    labelled = len(metrics.get("frames", []))
    if "frames_synchronised" in metrics:  # a bag: every synchronised stereo pair
        frames = int(metrics["frames_synchronised"])
    else:
        frames = labelled + len(metrics.get("skipped_frames", [])) + len(metrics.get("unreliable_pose_frames", []))
    mean = metrics.get("mean", {}) or {}
    figures = {key: _number(mean.get(key)) for key in _FIGURES}
    return {
        "frames": frames,
        "labelled_frames": labelled,
        "has_ground_truth": bool(metrics.get("has_ground_truth", False)),
        **figures,
        "runtime_s": _number(metrics.get("runtime_s")),
    }


def _number(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def label_one(
    source: str,
    name: str,
    out_dir: str,
    params_file: str | None,
    threads: int | None,
    kill_marker: str | None = None,
) -> dict[str, Any]:
    """Label one input into ``out_dir/name``, atomically; the body of one batch task (pure but for its output).

    Args:
        source: the bag or sequence folder.
        name: its output name (:func:`~selfcontra_ros.batch.inputs.input_name`).
        out_dir: the batch's output folder (exists).
        params_file: parameter YAML; None: the package's defaults.
        threads: thread cap of the labeler's pools (a Ray task's CPUs); None keeps the process's cap
            (in this process: ``selfcontra --threads``).
        kill_marker: the test hook's marker file (module docstring); None off.

    Returns:
        The input's summary entry (:func:`summarise_metrics`, with ``status`` ``complete``, ``output``,
        ``pid``) or, when labelling raised, ``status`` ``failed`` and ``error``.
    """
    started = time.perf_counter()
    if threads is not None:
        limit_threads(threads)
    out = Path(out_dir)
    final = out / name
    _remove_partials(out, name)
    staging = Path(tempfile.mkdtemp(prefix=partial_prefix(name), dir=out))
    target = staging / name
    try:
        metrics = label_input(source, target, params_file=params_file, progress=False)
        if "output" in metrics:  # a bag's metrics name the output bag: the place it is moved to
            metrics["output"] = str(final)
            write_json(target / METRICS_FILE, metrics)
        _kill_once(kill_marker)
        target.replace(final)
    except Exception as exc:  # one input's failure, whatever it is, is reported and the others go on
        return {"status": FAILED, "error": f"{type(exc).__name__}: {exc}", "task_s": time.perf_counter() - started}
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {
        "status": COMPLETE,
        "output": str(final),
        **summarise_metrics(metrics),
        "task_s": time.perf_counter() - started,
        "pid": os.getpid(),
    }


def _current_params(params_file: str | None) -> Any:
    """The parameters a run with ``params_file`` records in its metrics.json, as read back from JSON."""
    return json.loads(json.dumps(json_safe(params_to_dict(*load_params(params_file)))))


def complete_result(out_dir: Path, item: BatchInput) -> dict[str, Any] | None:
    """The metrics of a complete earlier result of ``item`` in ``out_dir``, or None when there is none.

    Raises:
        BatchError: ``OUT_DIR/<name>`` exists but holds no complete result (not written by a batch).
    """
    final = out_dir / item.name
    if not (final.exists() or final.is_symlink()):
        return None
    try:
        metrics = json.loads((final / METRICS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        metrics = None
    if not isinstance(metrics, dict) or metrics.get("status") != COMPLETE:
        raise BatchError(
            f"{final} exists but holds no complete result (no {METRICS_FILE} of status complete); remove it"
        )
    return metrics


def _plan(
    items: Sequence[BatchInput], out_dir: Path, params_file: str | None, resume: bool
) -> dict[str, dict[str, Any]]:
    """The inputs already done (name -> summary entry); raise on results that must not be overwritten."""
    done: dict[str, dict[str, Any]] = {}
    existing = [item for item in items if (out_dir / item.name).exists() or (out_dir / item.name).is_symlink()]
    if existing and not resume:
        names = ", ".join(item.name for item in existing)
        raise BatchError(
            f"{out_dir} already holds results of {names}: pass --resume to skip complete ones, "
            "or choose another --out (results are never overwritten)"
        )
    params = _current_params(params_file) if existing else None
    for item in existing:
        metrics = complete_result(out_dir, item)
        assert metrics is not None
        if metrics.get("params") != params:
            raise BatchError(
                f"{out_dir / item.name} was labelled with other parameters than {params_file or 'the defaults'}; "
                "remove it or choose another --out"
            )
        done[item.name] = {"status": RESUMED, "output": str(out_dir / item.name), **summarise_metrics(metrics)}
    return done


def _weighted(entries: Sequence[dict[str, Any]], key: str) -> float:
    pairs = [(e[key], e["labelled_frames"]) for e in entries if math.isfinite(e.get(key, math.nan))]
    weight = sum(n for _, n in pairs)
    return sum(v * n for v, n in pairs) / weight if weight else math.nan


def _totals(entries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    labelled = [e for e in entries if e["status"] in (COMPLETE, RESUMED)]
    totals: dict[str, Any] = {
        "inputs": len(entries),
        "complete": sum(e["status"] == COMPLETE for e in entries),
        "resumed": sum(e["status"] == RESUMED for e in entries),
        "failed": sum(e["status"] == FAILED for e in entries),
        "not_run": sum(e["status"] == NOT_RUN for e in entries),
        "frames": sum(int(e["frames"]) for e in labelled),
        "labelled_frames": sum(int(e["labelled_frames"]) for e in labelled),
    }
    totals.update({key: _weighted(labelled, key) for key in _FIGURES})
    totals["runtime_s"] = sum(e["runtime_s"] for e in labelled if math.isfinite(e.get("runtime_s", math.nan)))
    return totals


def _percent(value: Any) -> str:
    return f"{100 * value:.1f}" if isinstance(value, float) and math.isfinite(value) else "-"


def format_table(summary: dict[str, Any]) -> str:
    """The summary as a plain-text table: one row per input and a total row; failures listed below it."""
    header = ("input", "status", "frames", "labelled", "pos %", "neg %", "unk %", "acc %", "cov %", "time s")
    rows = []
    for entry in [*summary["inputs"], {"name": "total", "status": "", **summary["totals"]}]:
        seconds = entry.get("runtime_s")
        rows.append(
            (
                str(entry["name"]),
                str(entry["status"]),
                str(entry.get("frames", "-")),
                str(entry.get("labelled_frames", "-")),
                *(_percent(entry.get(key)) for key in _FIGURES[:3]),
                _percent(entry.get("accuracy")),
                _percent(entry.get("coverage")),
                f"{seconds:.1f}" if isinstance(seconds, float) and math.isfinite(seconds) else "-",
            )
        )
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]

    def line(row: Sequence[str]) -> str:
        cells = [row[0].ljust(widths[0]), row[1].ljust(widths[1])]
        cells += [cell.rjust(width) for cell, width in zip(row[2:], widths[2:], strict=True)]
        return "  ".join(cells).rstrip()

    lines = [line(header), line(["-" * w for w in widths]), *(line(row) for row in rows[:-1])]
    lines += [line(["-" * w for w in widths]), line(rows[-1])]
    lines += [f"{e['name']}: {e['error']}" for e in summary["inputs"] if e["status"] == FAILED]
    return "\n".join(lines) + "\n"


def _write_summary(out_dir: Path, summary: dict[str, Any]) -> None:
    """Write ``summary.json`` atomically (a temporary file beside it, then a rename)."""
    temporary = out_dir / f".{SUMMARY_FILE}.{os.getpid()}.partial"
    try:
        write_json(temporary, summary)
        temporary.replace(out_dir / SUMMARY_FILE)
    finally:
        with contextlib.suppress(FileNotFoundError):
            temporary.unlink()


def batch_label(
    inputs: Sequence[str | Path],
    out_dir: str | Path,
    *,
    params_file: str | Path | None = None,
    address: str | None = None,
    cpus_per_task: int = 1,
    resume: bool = False,
    progress: bool = True,
    echo: Callable[[str], None] | None = print,
    engine: Engine | None = None,
) -> dict[str, Any]:
    """Label every input into ``out_dir/<name>`` (module docstring); return the summary.

    Args:
        inputs: bags, sequence folders, odometry roots or globs (:func:`~selfcontra_ros.batch.inputs.expand_inputs`).
        out_dir: the batch's output folder (created).
        params_file: parameter YAML of every input; None: the package's defaults.
        address: Ray cluster (:func:`~selfcontra_ros.batch.engine.open_engine`): None/``"local"``, ``"auto"``,
            ``"ray://HOST:PORT"``.
        cpus_per_task: CPUs Ray reserves per task; the labeler's thread pools are capped at it (on Ray;
            without Ray the process's own cap applies).
        resume: skip inputs with a complete result in ``out_dir``.
        progress: a progress bar over the finished inputs.
        echo: where the engine line and the table go (None: silent).
        engine: run on this engine instead of opening one for ``address`` (left open).

    Returns:
        The content of ``summary.json``.

    Raises:
        BatchError: bad inputs (:func:`~selfcontra_ros.batch.inputs.expand_inputs`), results that exist
            already (without ``resume``, or made with other parameters), a cluster that cannot be reached.
        Interrupted: SIGINT/SIGTERM under the ``selfcontra`` command, after ``summary.json`` is written
            (status interrupted; the tasks still running are cancelled, their inputs ``not run``).
    """
    started = time.perf_counter()
    out = Path(out_dir)
    params = None if params_file is None else str(params_file)
    items = expand_inputs(inputs)
    out.mkdir(parents=True, exist_ok=True)
    entries: dict[str, dict[str, Any]] = _plan(items, out, params, resume)
    todo = [item for item in items if item.name not in entries]
    own_engine = engine is None
    if engine is None:
        engine = open_engine(address, cpus_per_task=cpus_per_task, inputs=len(todo), echo=echo)
    # A Ray task's pools get its CPUs; in this process they keep the cap the caller set (selfcontra --threads).
    threads = cpus_per_task if engine.remote else None
    kill_marker = os.environ.get(KILL_MARKER_ENV) or None
    if not engine.remote:  # the hook kills a Ray worker; in this process it would end the batch
        kill_marker = None
    calls = [(str(item.path), item.name, str(out), params, threads, kill_marker) for item in todo]
    status = "interrupted"
    bar = tqdm(total=len(items), initial=len(entries), desc="batch label", unit="input", disable=not progress)
    try:
        if echo is not None and todo:
            echo(f"labelling {len(todo)} input(s) on {engine.description}")
        for position, result in engine.run(label_one, calls):
            if isinstance(result, TaskLostError):
                result = {"status": FAILED, "error": f"the task was lost: {result}"}
            entries[todo[position].name] = result
            bar.update(1)
        status = COMPLETE
    except KeyboardInterrupt as exc:
        if isinstance(exc, interrupts.Interrupted):
            done = sum(e["status"] in (COMPLETE, RESUMED) for e in entries.values())
            exc.done = f"{done} of {len(items)} inputs have a complete result in {out}; --resume labels the rest"
        raise
    finally:
        bar.close()
        if own_engine:
            engine.close()
        summary = _summary(items, entries, out, status, engine.description, address, cpus_per_task, params, started)
        _write_summary(out, summary)
    if echo is not None:
        echo(format_table(summary) + f"wrote {out / SUMMARY_FILE}")
    return summary


def _summary(
    items: Sequence[BatchInput],
    entries: dict[str, dict[str, Any]],
    out: Path,
    status: str,
    engine: str,
    address: str | None,
    cpus_per_task: int,
    params: str | None,
    started: float,
) -> dict[str, Any]:
    ordered = []
    for item in items:
        entry = entries.get(item.name, {"status": NOT_RUN})
        ordered.append(
            {
                "name": item.name,
                "input": str(item.path),
                "kind": item.kind,
                "error": None,
                "frames": 0,
                "labelled_frames": 0,
                "has_ground_truth": False,
                **{key: math.nan for key in _FIGURES},
                "runtime_s": math.nan,
                **entry,
            }
        )
    return {
        "out_dir": str(out),
        "status": status,
        "engine": engine,
        "address": address or LOCAL,
        "cpus_per_task": cpus_per_task,
        "params": params,
        "wall_s": time.perf_counter() - started,
        "inputs": ordered,
        "totals": _totals(ordered),
    }
