"""BagWriter / open_bag: round trips, closing guarantees, and clear errors on damaged bags."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from selfcontra_ros.bags.reader import BagError, open_bag
from selfcontra_ros.bags.writer import BagWriter, default_typestore

STRING = "std_msgs/msg/String"


def _string(text: str) -> Any:
    return default_typestore().types[STRING](data=text)


def _image(k: int) -> Any:
    types = default_typestore().types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=k, nanosec=7), frame_id="f")
    pixels = (np.arange(64 * 48, dtype=np.int64) * (k + 3) % 251).astype(np.uint8)
    return types["sensor_msgs/msg/Image"](
        header=header, height=48, width=64, encoding="mono8", is_bigendian=0, step=64, data=pixels
    )


def _write_sample(path: Path, *, compress: str = "zstd", frames: int = 40) -> Path:
    """A bag with an image topic (big enough for several MCAP chunks) and a string topic."""
    with BagWriter(path, compress=compress) as bag:
        for k in range(frames):
            bag.write("/camera/image", k * 10**8, _image(k))
            bag.write("/note", k * 10**8 + 5, _string(f"note {k}"))
    return path


def test_round_trip_in_time_order(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag", custom_data={"who": "test"}) as bag:
        # Out of order on purpose: the reader returns log-time order, ties in writing order.
        for stamp, topic in ((3, "/a"), (1, "/a"), (2, "/b"), (2, "/a"), (0, "/b")):
            bag.write(topic, stamp, _string(f"{topic}{stamp}"))
        bag.add_topic("/raw", STRING)
        bag.write_raw("/raw", 4, default_typestore().serialize_cdr(_string("raw"), STRING))
        assert bag.counts == {"/a": 3, "/b": 2, "/raw": 1}
    with open_bag(tmp_path / "bag") as bag:
        assert [(t, s, m.data) for t, s, m in bag.messages()] == [
            ("/b", 0, "/b0"),
            ("/a", 1, "/a1"),
            ("/b", 2, "/b2"),
            ("/a", 2, "/a2"),
            ("/a", 3, "/a3"),
            ("/raw", 4, "raw"),
        ]
        assert {n: (t.msgtype, t.message_count) for n, t in bag.topics.items()} == {
            "/a": (STRING, 3),
            "/b": (STRING, 2),
            "/raw": (STRING, 1),
        }
        assert (bag.start_ns, bag.end_ns, bag.message_count) == (0, 4, 6)
        assert bag.custom_data == {"who": "test"}
        assert [m.data for _, _, m in bag.messages(["/b"], start_ns=1)] == ["/b2"]
        assert [r.stamp_ns for r in bag.raw_messages(start_ns=2, stop_ns=4)] == [2, 2, 3]
        with pytest.raises(BagError, match="no topic /c"):
            list(bag.messages(["/c"]))


def test_images_survive_several_chunks_bit_exact(tmp_path: Path) -> None:
    path = _write_sample(tmp_path / "bag", frames=400)  # 400 x 3 KiB images: more than one 1 MiB chunk
    with (path / "bag.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 2
    with open_bag(path) as bag:
        images = [(s, m) for t, s, m in bag.messages() if t == "/camera/image"]
    assert len(images) == 400
    for k, (stamp, msg) in enumerate(images):
        assert stamp == k * 10**8 and msg.header.stamp.sec == k
        assert np.array_equal(msg.data, _image(k).data)


def test_closing_after_an_interruption_leaves_a_valid_bag(tmp_path: Path) -> None:
    """The offline labeler's guarantee: Ctrl-C inside ``with`` still finishes the bag."""
    path = tmp_path / "bag"
    with pytest.raises(KeyboardInterrupt), BagWriter(path) as bag:
        for k in range(10):
            bag.write("/note", k, _string(str(k)))
            if k == 6:
                raise KeyboardInterrupt
    assert bag.closed
    with open_bag(path) as reader:
        assert [m.data for _, _, m in reader.messages()] == [str(k) for k in range(7)]
    with pytest.raises(BagError, match="closed"):
        bag.write("/note", 99, _string("late"))
    assert bag.close() == path  # closing again is harmless


def test_atomic_writer_publishes_only_complete_bags(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(RuntimeError), BagWriter(out / "bag", atomic=True) as bag:
        bag.write("/note", 1, _string("x"))
        assert not (out / "bag").exists()  # still in the staging folder
        raise RuntimeError("conversion failed")
    assert list(out.iterdir()) == []
    with BagWriter(out / "bag", atomic=True) as bag:
        bag.write("/note", 1, _string("x"))
    assert [p.name for p in out.iterdir()] == ["bag"]
    with open_bag(out / "bag") as reader:
        assert reader.message_count == 1


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    (tmp_path / "taken").mkdir()
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "taken")
    with pytest.raises(BagError, match="does not exist"):
        BagWriter(tmp_path / "missing" / "bag")
    with pytest.raises(BagError, match="compress"):
        BagWriter(tmp_path / "bag", compress="gzip")
    with BagWriter(tmp_path / "bag") as bag:
        with pytest.raises(BagError, match="outside"):
            bag.write("/note", -1, _string("negative time"))
        bag.write("/note", 0, _string("ok"))
        with pytest.raises(BagError, match="carries std_msgs/msg/String"):
            bag.write("/note", 1, _image(0))
        with pytest.raises(BagError, match="not added"):
            bag.write_raw("/unknown", 1, b"\x00\x01\x00\x00")
        with pytest.raises(BagError, match="unknown"):
            bag.add_topic("/custom", "my_msgs/msg/Thing")
    with open_bag(tmp_path / "bag") as reader:
        assert reader.message_count == 1


# --------------------------------------------------------------------------- damaged bags


@pytest.fixture(scope="module")
def sample_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_sample(tmp_path_factory.mktemp("sample") / "bag")


def _damaged_copy(sample: Path, tmp_path: Path) -> tuple[Path, Path]:
    copy = tmp_path / "bag"
    shutil.copytree(sample, copy)
    return copy, copy / "bag.mcap"


def _read_all(path: Path) -> int:
    with open_bag(path) as bag:
        return sum(1 for _ in bag.messages())


def test_sample_bag_reads(sample_bag: Path) -> None:
    assert _read_all(sample_bag) == 80  # the control for the damaged copies below


def test_missing_and_not_a_bag(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="does not exist"):
        open_bag(tmp_path / "nothing")
    (tmp_path / "folder").mkdir()
    with pytest.raises(BagError, match="not a rosbag2 bag"):
        open_bag(tmp_path / "folder")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(BagError, match="not a bag"):
        open_bag(tmp_path / "notes.txt")


def test_a_cut_through_the_only_chunk_leaves_nothing_to_read(sample_bag: Path, tmp_path: Path) -> None:
    """The sample's 80 messages fit one chunk: cut in half, the bag holds no complete message (test_truncated.py
    covers bags with complete chunks before the cut)."""
    copy, mcap = _damaged_copy(sample_bag, tmp_path)
    size = mcap.stat().st_size
    mcap.write_bytes(mcap.read_bytes()[: size // 2])
    with pytest.raises(BagError, match=rf"truncated and holds no complete message: .* \(\d+ of {size // 2:,} bytes"):
        _read_all(copy)


def test_a_killed_writer_before_its_first_chunk(sample_bag: Path, tmp_path: Path) -> None:
    """What a writer killed early leaves: a storage file without summary, no metadata.yaml."""
    copy, mcap = _damaged_copy(sample_bag, tmp_path)
    (copy / "metadata.yaml").unlink()
    mcap.write_bytes(mcap.read_bytes()[:5000])
    with pytest.raises(
        BagError, match=r"holds no complete message: bag\.mcap has no MCAP footer and ends inside a chunk"
    ):
        open_bag(copy)


def test_corrupt_chunk(sample_bag: Path, tmp_path: Path) -> None:
    copy, mcap = _damaged_copy(sample_bag, tmp_path)
    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[0]
    data = bytearray(mcap.read_bytes())
    # Chunk record: opcode(1) length(8) start(8) end(8) uncompressed size(8) crc(4) compression(4+n) size(8) data.
    start = chunk.chunk_start_offset + 1 + 8 + 8 + 8 + 8 + 4
    (name_length,) = struct.unpack_from("<I", data, start)
    payload = start + 4 + name_length + 8
    data[payload : payload + 32] = bytes(32)  # destroys the zstd frame header
    mcap.write_bytes(bytes(data))
    with pytest.raises(
        BagError, match=r"is corrupt: a chunk with /camera/image, /note messages from 0 s to 3\.9 s does "
    ):
        _read_all(copy)


def test_fewer_messages_than_the_index_announces(sample_bag: Path, tmp_path: Path) -> None:
    copy, _ = _damaged_copy(sample_bag, tmp_path)
    meta = copy / "metadata.yaml"
    info = yaml.safe_load(meta.read_text())
    for topic in info["rosbag2_bagfile_information"]["topics_with_message_count"]:
        if topic["topic_metadata"]["name"] == "/note":
            topic["message_count"] += 3  # as if a chunk had gone missing
    meta.write_text(yaml.safe_dump(info))
    with pytest.raises(BagError, match="/note: 40 of 43"):
        _read_all(copy)


def test_garbage_metadata_and_missing_storage(sample_bag: Path, tmp_path: Path) -> None:
    copy, _ = _damaged_copy(sample_bag, tmp_path)
    (copy / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    with pytest.raises(BagError, match="cannot open bag"):
        open_bag(copy)
    copy2, mcap2 = _damaged_copy(sample_bag, tmp_path / "second")
    mcap2.unlink()
    with pytest.raises(BagError, match="cannot open bag"):
        open_bag(copy2)


# --------------------------------------------------------------------------- other layouts


def test_split_storage_files_merge_in_time_order(tmp_path: Path) -> None:
    """A bag of several MCAP files (``ros2 bag record --max-bag-size``): one time line, ties in file order."""
    bag = tmp_path / "bag"
    bag.mkdir()
    infos = []
    for part in range(2):
        with BagWriter(tmp_path / f"part{part}") as out:
            for k in range(4):
                out.write("/a", (2 * k + part) * 10, _string(f"{part}-{k}"))
            out.write("/b", 25, _string(f"tie {part}"))
        shutil.copy(tmp_path / f"part{part}" / f"part{part}.mcap", bag / f"bag_{part}.mcap")
        infos.append(yaml.safe_load((tmp_path / f"part{part}" / "metadata.yaml").read_text()))
    info = infos[0]["rosbag2_bagfile_information"]
    info["relative_file_paths"] = ["bag_0.mcap", "bag_1.mcap"]
    for topic in info["topics_with_message_count"]:
        topic["message_count"] *= 2
    (bag / "metadata.yaml").write_text(yaml.safe_dump(infos[0]))
    with open_bag(bag) as reader:
        assert reader.recovery is None and reader.message_count == 10
        assert [m.msg.data for m in reader.messages()] == [
            "0-0", "1-0", "0-1", "tie 0", "tie 1", "1-1", "0-2", "1-2", "0-3", "1-3"
        ]  # fmt: skip


def test_sqlite_bags_are_read_with_rosbags(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    typestore = default_typestore()
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection("/note", STRING, typestore=typestore)
        for k in (2, 0, 1):
            writer.write(connection, k, typestore.serialize_cdr(_string(str(k)), STRING))
    with open_bag(tmp_path / "bag") as reader:
        assert (reader.message_count, reader.start_ns, reader.end_ns, reader.recovery) == (3, 0, 2, None)
        assert [(s, m.data) for _, s, m in reader.messages()] == [(0, "0"), (1, "1"), (2, "2")]
