"""batch label on the session's local Ray cluster: the outputs of selfcontra label, failures, retries, resume."""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path
from typing import Any

import pytest

from selfcontra_ros.bags.reader import is_bag, open_bag
from selfcontra_ros.batch import label as batch_label_module
from selfcontra_ros.batch.engine import NOT_INSTALLED
from selfcontra_ros.batch.label import KILL_MARKER_ENV, SUMMARY_FILE, batch_label, partial_prefix
from selfcontra_ros.cli import main
from selfcontra_ros.errors import BatchError
from selfcontra_ros.interrupts import Interrupted

#: as in conftest.py: the parameters, the sequence's output name, the corrupt bag's
FLUSH = Path(__file__).parents[1] / "bags" / "flush_all.yaml"
SEQUENCE_NAME, CORRUPT = "seqroot_00", "corrupt"
LABELLED = ("street", "orbit", "room", SEQUENCE_NAME)


def _metrics(folder: Path) -> dict[str, Any]:
    """A result's metrics.json without what differs between two runs (run time, the output's own path)."""
    metrics = json.loads((folder / "metrics.json").read_text())
    metrics.pop("runtime_s")
    metrics.pop("output", None)
    return metrics


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.png"))}


def _messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with open_bag(bag) as opened:
        return [(m.topic, m.stamp_ns, bytes(m.data)) for m in opened.raw_messages()]


def assert_same_result(result: Path, reference: Path) -> None:
    """Every label image (a sequence's PNGs, or every message of a labelled bag) and the metrics are equal."""
    assert result.is_dir()
    if is_bag(reference):
        got, want = _messages(result), _messages(reference)
        assert any(topic.endswith("/labels") for topic, _, _ in want)
        assert got == want
    else:
        got_files, want_files = _files(result), _files(reference)
        assert len(want_files) > 0 and got_files.keys() == want_files.keys()
        for name, data in want_files.items():
            assert got_files[name] == data, name
    assert _metrics(result) == _metrics(reference)


def _partials(out: Path) -> list[Path]:
    return [p for p in out.iterdir() if ".partial-" in p.name]


def test_batch_gives_the_labels_and_metrics_of_label(
    batch_run: tuple[Path, dict[str, Any], Path, str], references: dict[str, Path]
) -> None:
    out, summary, _, _ = batch_run
    for name in LABELLED:
        assert_same_result(out / name, references[name])
    bag_metrics = json.loads((out / "street" / "metrics.json").read_text())
    assert bag_metrics["output"] == str(out / "street")  # the place the result was moved to, not the partial one
    assert summary["status"] == "complete"
    assert summary["engine"].startswith("a local Ray cluster: 2 CPUs")


def test_a_corrupt_bag_is_reported_and_the_others_finish(batch_run: tuple[Path, dict[str, Any], Path, str]) -> None:
    out, summary, _, table = batch_run
    entries = {e["name"]: e for e in summary["inputs"]}
    assert [e["name"] for e in summary["inputs"]] == ["street", "orbit", "room", SEQUENCE_NAME, CORRUPT]
    assert entries[CORRUPT]["status"] == "failed"
    assert entries[CORRUPT]["error"].startswith("BagError: ")
    assert not (out / CORRUPT).exists()
    assert all(entries[name]["status"] == "complete" for name in LABELLED)
    totals = summary["totals"]
    assert (totals["inputs"], totals["complete"], totals["failed"]) == (5, 4, 0 + 1)
    assert totals["labelled_frames"] == sum(entries[n]["labelled_frames"] for n in LABELLED)
    assert entries["street"]["frames"] == 6 and entries[SEQUENCE_NAME]["frames"] == 6
    # every input has ground truth: accuracy and coverage per input, and their frame-weighted totals
    for name in LABELLED:
        assert 0.0 < entries[name]["coverage"] <= 1.0 and 0.5 < entries[name]["accuracy"] <= 1.0
    weights = [entries[n]["labelled_frames"] for n in LABELLED]
    expected = sum(entries[n]["coverage"] * w for n, w in zip(LABELLED, weights, strict=True)) / sum(weights)
    assert totals["coverage"] == pytest.approx(expected, rel=1e-12)
    assert json.loads((out / SUMMARY_FILE).read_text())["totals"]["failed"] == 1
    assert re.search(r"^corrupt +failed +0 +0 +- +-", table, re.MULTILINE) and "corrupt: BagError: " in table
    assert table.count(" complete ") == 4 and re.search(r"^total +24 +24 ", table, re.MULTILINE)


def test_a_killed_worker_is_retried_and_its_result_is_whole(
    batch_run: tuple[Path, dict[str, Any], Path, str], references: dict[str, Path]
) -> None:
    out, summary, marker, _ = batch_run
    assert marker.is_file(), "the test hook did not kill a worker"
    killed = int(marker.read_text())
    assert killed not in {e.get("pid") for e in summary["inputs"]}  # the killed process returned nothing
    assert _partials(out) == []  # the dead attempt's partial folder was removed by its retry
    for name in LABELLED:
        assert_same_result(out / name, references[name])


def test_existing_results_are_never_overwritten(batch_run: tuple[Path, dict[str, Any], Path, str]) -> None:
    out, _, _, _ = batch_run
    inputs = [e["input"] for e in json.loads((out / SUMMARY_FILE).read_text())["inputs"]]
    with pytest.raises(BatchError, match="pass --resume"):
        batch_label(inputs, out, params_file=FLUSH, progress=False, echo=None)
    with pytest.raises(BatchError, match="other parameters"):
        batch_label(inputs, out, resume=True, progress=False, echo=None)  # the defaults, not flush_all.yaml


def test_resume_labels_only_what_is_missing(
    batch_run: tuple[Path, dict[str, Any], Path, str], references: dict[str, Path], tmp_path: Path
) -> None:
    done, _, _, _ = batch_run
    out = tmp_path / "out"
    shutil.copytree(done, out, symlinks=True)
    shutil.rmtree(out / "orbit")
    (out / (partial_prefix("orbit") + "dead")).mkdir()  # what a killed run leaves
    kept = {name: (out / name / "metrics.json").stat().st_mtime_ns for name in ("street", "room", SEQUENCE_NAME)}
    inputs = [e["input"] for e in json.loads((done / SUMMARY_FILE).read_text())["inputs"]]

    summary = batch_label(inputs, out, params_file=FLUSH, resume=True, progress=False, echo=None)

    status = {e["name"]: e["status"] for e in summary["inputs"]}
    assert status == {"street": "resumed", "orbit": "complete", "room": "resumed", SEQUENCE_NAME: "resumed",
                      CORRUPT: "failed"}  # fmt: skip
    assert {name: (out / name / "metrics.json").stat().st_mtime_ns for name in kept} == kept
    assert_same_result(out / "orbit", references["orbit"])
    assert _partials(out) == []
    assert summary["totals"]["resumed"] == 3 and summary["totals"]["labelled_frames"] > 0


def test_without_ray_inputs_run_one_after_another_and_resume_after_an_interrupt(
    batch_inputs: dict[str, Path],
    references: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    monkeypatch.setenv(KILL_MARKER_ENV, str(tmp_path / "marker"))  # ignored here: it would end this process
    real = batch_label_module.label_input

    def interrupted_on_the_sequence(source: Any, out: Path, **kwargs: Any) -> dict[str, Any]:
        metrics = real(source, out, **kwargs)  # a whole result, in its partial folder
        if Path(source) == batch_inputs[SEQUENCE_NAME]:
            raise Interrupted(2)
        return metrics

    monkeypatch.setattr(batch_label_module, "label_input", interrupted_on_the_sequence)
    inputs = [str(batch_inputs[name]) for name in ("street", SEQUENCE_NAME, "room")]
    out = tmp_path / "out"
    with pytest.raises(Interrupted) as caught:
        batch_label(inputs, out, params_file=FLUSH, progress=False)
    assert "1 of 3 inputs have a complete result" in caught.value.done
    assert NOT_INSTALLED.format(n=3) in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["street", SUMMARY_FILE]  # no partial folder left
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["status"] == "interrupted"
    assert [e["status"] for e in summary["inputs"]] == ["complete", "not run", "not run"]
    assert not (tmp_path / "marker").exists()

    monkeypatch.setattr(batch_label_module, "label_input", real)
    assert main(["batch", "label", *inputs, "--out", str(out), "--params", str(FLUSH), "--resume"]) == 0
    printed = capsys.readouterr().out
    assert NOT_INSTALLED.format(n=2) in printed
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert [e["status"] for e in summary["inputs"]] == ["resumed", "complete", "complete"]
    for name in ("street", SEQUENCE_NAME, "room"):
        assert_same_result(out / name, references[name])


def test_a_failed_input_gives_exit_status_1_without_ray(
    batch_inputs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)
    assert main(["batch", "label", str(batch_inputs[CORRUPT]), "--out", str(tmp_path / "out")]) == 1
    assert "corrupt: BagError: " in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["batch", "label", "--out", str(tmp_path / "out")])  # no input
    assert main(["batch", "label", str(tmp_path / "nothing*"), "--out", str(tmp_path / "o")]) == 2
    assert "matches nothing" in capsys.readouterr().err
    corrupt = str(batch_inputs[CORRUPT])
    assert main(["batch", "label", corrupt, "--out", str(tmp_path / "o"), "--address", "auto"]) == 2
    assert "--address auto needs Ray" in capsys.readouterr().err
