"""Cut-short MCAP bags (power loss, killed recorder, incomplete copy) read up to their last complete chunk."""

from __future__ import annotations

import json
import logging
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import get_chunk_data_stream

from selfcontra_ros.bags import topics
from selfcontra_ros.bags import writer as writer_module
from selfcontra_ros.bags.kitti2mcap import kitti_to_mcap
from selfcontra_ros.bags.label_bag import label_bag
from selfcontra_ros.bags.reader import BagError, RawMessage, open_bag
from selfcontra_ros.bags.writer import BagWriter, default_typestore
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.ros.conversions import image_to_numpy

IMAGE, NOTE = "/camera/image", "/note"
FRAMES = 120
#: Chunks of 64 KiB (instead of 1 MiB) give the small test bags a dozen chunks.
SMALL_CHUNKS = 64 * 1024
FRACTIONS = (0.3, 0.6, 0.9)
LOGGER = "selfcontra_ros.bags.reader"


def _image(k: int) -> Any:
    types = default_typestore().types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=k, nanosec=7), frame_id="f")
    pixels = np.random.default_rng(k).integers(0, 64, 64 * 48, dtype=np.uint8)
    return types["sensor_msgs/msg/Image"](
        header=header, height=48, width=64, encoding="mono8", is_bigendian=0, step=64, data=pixels
    )


@pytest.fixture(scope="module", params=["zstd", "none"])
def bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp(request.param) / "bag"
    string = default_typestore().types["std_msgs/msg/String"]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(writer_module, "CHUNK_SIZE", SMALL_CHUNKS)
        with BagWriter(path, compress=request.param, custom_data={"who": "test"}) as out:
            for k in range(FRAMES):
                out.write(IMAGE, k * 10**8, _image(k))
                out.write(NOTE, k * 10**8 + 5, string(data=f"note {k}"))
    return path


@pytest.fixture(scope="module")
def reference(bag: Path) -> list[RawMessage]:
    with open_bag(bag) as reader:
        return list(reader.raw_messages())


def _mcap(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def _complete_before(mcap: Path, cut: int) -> int:
    """Messages in the chunks that end at or before byte ``cut`` of the intact file."""
    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        count = 0
        for index in summary.chunk_indexes:
            if index.chunk_start_offset + index.chunk_length > cut:
                continue
            f.seek(index.chunk_start_offset + 9)
            stream, size = get_chunk_data_stream(Chunk.read(ReadDataStream(f)))
            while stream.count < size:
                opcode, length = stream.read1(), stream.read8()
                stream.read(length)
                count += opcode == 0x05
    return count


def _seconds(stamp_ns: int) -> str:
    return f"{stamp_ns / 1e9:.3f}".rstrip("0").rstrip(".") + " s"


def _cut(bag: Path, tmp_path: Path, fraction: float, *, keep_metadata: bool, zero_fill: bool = False) -> Path:
    copy = tmp_path / "cut"
    shutil.copytree(bag, copy)
    mcap = _mcap(copy)
    data = mcap.read_bytes()
    cut = int(len(data) * fraction)
    # A power loss can leave the file at its full size with the unwritten part read as zeros.
    mcap.write_bytes(data[:cut] + (bytes(len(data) - cut) if zero_fill else b""))
    if not keep_metadata:
        (copy / "metadata.yaml").unlink()
    return copy


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == LOGGER and r.levelno == logging.WARNING]


@pytest.mark.parametrize("fraction", FRACTIONS)
@pytest.mark.parametrize("damage", ["cut", "cut_and_no_metadata", "zero_filled"])
def test_a_cut_bag_yields_the_messages_of_its_complete_chunks(
    bag: Path,
    reference: list[RawMessage],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    fraction: float,
    damage: str,
) -> None:
    size = _mcap(bag).stat().st_size
    cut = int(size * fraction)
    expected = _complete_before(_mcap(bag), cut)
    assert 0 < expected < len(reference)
    keep_metadata = damage != "cut_and_no_metadata"
    copy = _cut(bag, tmp_path, fraction, keep_metadata=keep_metadata, zero_fill=damage == "zero_filled")
    with caplog.at_level(logging.WARNING, logger=LOGGER), open_bag(copy) as reader:
        got = list(reader.raw_messages())  # a full read: its count check compares with what was recovered
        assert got == reference[:expected]  # bit-exact, in order
        counts = Counter(m.topic for m in got)
        assert {n: t.message_count for n, t in reader.topics.items()} == {IMAGE: counts[IMAGE], NOTE: counts[NOTE]}
        assert reader.message_count == expected
        assert (reader.start_ns, reader.end_ns) == (got[0].stamp_ns, max(m.stamp_ns for m in got))
        last_note = [m for m in reader.messages([NOTE])][-1]
        assert last_note.msg.data == f"note {counts[NOTE] - 1}"
        recovery = reader.recovery
        custom_data = reader.custom_data
    assert recovery is not None
    assert _warnings(caplog) == [recovery]  # one warning, the text the CLI prints
    assert recovery.startswith(f"bag {copy} is incomplete: bag.mcap ")
    span = f"from {_seconds(reference[0].stamp_ns)} to {_seconds(reader.end_ns)}"
    assert f"recovered {expected} messages ({IMAGE}: {counts[IMAGE]}, {NOTE}: {counts[NOTE]}) {span}" in recovery
    readable_size = size if damage == "zero_filled" else cut
    assert f" of {readable_size:,} bytes readable" in recovery
    if damage == "zero_filled":
        assert "holds only zero bytes from byte" in recovery
    if keep_metadata:
        assert custom_data == {"who": "test"}
        assert f"metadata.yaml announced {len(reference)} messages" in recovery
    else:
        assert custom_data == {} and "no metadata.yaml" in recovery


def test_a_folder_without_metadata_opens_from_its_mcap(
    bag: Path, reference: list[RawMessage], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    copy = _cut(bag, tmp_path, 1.0, keep_metadata=False)
    with caplog.at_level(logging.WARNING, logger=LOGGER), open_bag(copy) as reader:
        assert list(reader.raw_messages()) == reference
        assert reader.custom_data == {}
        recovery = reader.recovery
    assert recovery is not None and _warnings(caplog) == [recovery]
    assert "no metadata.yaml" in recovery and "complete with 240 messages" in recovery


def test_an_intact_bag_opens_without_warning(bag: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger=LOGGER), open_bag(bag) as reader:
        assert reader.recovery is None
    assert _warnings(caplog) == []


def test_nothing_complete_is_refused(bag: Path, tmp_path: Path) -> None:
    with _mcap(bag).open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    first = summary.chunk_indexes[0]
    inside = (first.chunk_start_offset + first.chunk_length // 2) / _mcap(bag).stat().st_size
    copy = _cut(bag, tmp_path, inside, keep_metadata=False)
    with pytest.raises(BagError, match=r"is truncated and holds no complete message: bag\.mcap has no MCAP footer"):
        open_bag(copy)
    mcap = _mcap(copy)
    mcap.write_bytes(mcap.read_bytes()[:20])
    with pytest.raises(BagError, match="ends inside its MCAP header"):
        open_bag(copy)


def test_an_empty_file_is_refused_clearly(tmp_path: Path) -> None:
    folder = tmp_path / "bag"
    folder.mkdir()
    (folder / "bag.mcap").write_bytes(b"")
    for path in (folder, folder / "bag.mcap"):
        with pytest.raises(BagError, match=r"bag\.mcap is an empty file \(0 bytes"):
            open_bag(path)


# --------------------------------------------------------------------------- end to end: labelling a cut bag

LABEL_FRAMES = 14
WINDOW, DELAY = 4, 2
NS = topics.STEREO_NAMESPACE
LABELS, DEPTH = topics.bag_topic(topics.LABELS), topics.bag_topic(topics.DEPTH)
LEFT = topics.bag_topic(topics.LEFT_IMAGE)


@pytest.fixture(scope="module")
def stereo_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("street")
    write_sequence(root / "seq", scene="street", frames=LABEL_FRAMES, seed=1, width=320, height=96)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(writer_module, "CHUNK_SIZE", SMALL_CHUNKS)  # about one frame per chunk
        return kitti_to_mcap(root / "seq", root / "street", progress=False)


@pytest.fixture(scope="module")
def params(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short window, so that most views of the short sequence get their labels before its end."""
    path = tmp_path_factory.mktemp("params") / "params.yaml"
    path.write_text(
        "labeler:\n  ros__parameters:\n"
        f"    labeler: {{window_size: {WINDOW}, label_delay: {DELAY}, flush_incomplete: true}}\n"
    )
    return path


def _outputs(out: Path) -> tuple[list[int], dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Left stamps of the input copy, and the label and depth images by stamp."""
    with open_bag(out) as reader:
        stamps = [m.stamp_ns for m in reader.raw_messages([LEFT])]
        labels = {m.stamp_ns: image_to_numpy(m.msg) for m in reader.messages([LABELS])}
        depths = {m.stamp_ns: image_to_numpy(m.msg) for m in reader.messages([DEPTH])}
    return stamps, labels, depths


@pytest.fixture(scope="module")
def intact_labels(
    stereo_bag: Path, params: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[list[int], dict[int, np.ndarray], dict[int, np.ndarray]]:
    out = tmp_path_factory.mktemp("intact") / "labelled"
    report = label_bag(stereo_bag, out, params_file=params, progress=False)
    assert report["recovered"] is None and report["skipped_frames"] == [] and report["dropped"] == {}
    outputs = _outputs(out)
    assert len(outputs[1]) == LABEL_FRAMES
    return outputs


@pytest.mark.parametrize("fraction", FRACTIONS)
def test_labelling_a_cut_bag_labels_the_frames_before_the_cut(
    stereo_bag: Path,
    params: Path,
    intact_labels: tuple[list[int], dict[int, np.ndarray], dict[int, np.ndarray]],
    tmp_path: Path,
    fraction: float,
) -> None:
    """Frames before the cut get the intact run's depth, and its labels where their window was complete.

    A view is labelled once ``label_delay`` newer views arrived, with the
    views of the window then: the same as in the intact run. The last
    ``label_delay`` views the cut bag still holds are labelled at its end
    (``flush_incomplete``) with fewer newer views, so their labels may differ.
    """
    stamps, labels, depths = intact_labels
    cut = _cut(stereo_bag, tmp_path, fraction, keep_metadata=False)  # what a killed recorder leaves
    out = tmp_path / "labelled"
    report = label_bag(cut, out, params_file=params, progress=False)
    assert report["status"] == "complete"
    assert isinstance(report["recovered"], str) and "recovered" in report["recovered"]
    assert json.loads((out / "metrics.json").read_text())["recovered"] == report["recovered"]
    cut_stamps, cut_labels, cut_depths = _outputs(out)
    assert cut_stamps == stamps[: len(cut_stamps)]  # the copy holds the first frames' images
    processed = sorted(cut_depths)
    count = len(processed)
    assert 0 < count < LABEL_FRAMES and processed == stamps[:count]  # every frame before the cut, in order
    for stamp in processed:
        np.testing.assert_array_equal(cut_depths[stamp], depths[stamp])
    assert sorted(cut_labels) == processed  # each processed frame is labelled (flush_incomplete) ...
    complete = processed[: max(0, count - DELAY)]
    assert complete, "the cut leaves no frame with a complete window"
    for stamp in complete:  # ... exactly as in the intact run when its window was complete
        np.testing.assert_array_equal(cut_labels[stamp], labels[stamp], err_msg=f"frame {stamps.index(stamp)}")
