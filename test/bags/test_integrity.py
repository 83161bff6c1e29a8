"""MCAP checksums: BagWriter writes every CRC, other readers read them, open_bag reports damage (never decodes it)."""

from __future__ import annotations

import io
import logging
import shutil
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from mcap.data_stream import ReadDataStream
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, get_chunk_data_stream
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from selfcontra_ros.bags import writer as writer_module
from selfcontra_ros.bags.reader import BagError, RawMessage, open_bag
from selfcontra_ros.bags.writer import BagWriter, default_typestore

IMAGE, NOTE = "/camera/image", "/note"
FRAMES = 120
#: Chunks of 64 KiB (instead of 1 MiB) give the small test bags several chunks.
SMALL_CHUNKS = 64 * 1024
QOS = Qos(
    QosHistory.KEEP_LAST,
    5,
    QosReliability.BEST_EFFORT,
    QosDurability.VOLATILE,
    QosTime(0, 0),
    QosTime(0, 0),
    QosLiveliness.AUTOMATIC,
    QosTime(0, 0),
    False,
)


def _image(k: int) -> Any:
    types = default_typestore().types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=k, nanosec=7), frame_id="f")
    pixels = np.random.default_rng(k).integers(0, 64, 64 * 48, dtype=np.uint8)  # compresses, but not to nothing
    return types["sensor_msgs/msg/Image"](
        header=header, height=48, width=64, encoding="mono8", is_bigendian=0, step=64, data=pixels
    )


def _note(k: int) -> Any:
    return default_typestore().types["std_msgs/msg/String"](data=f"note {k}")


def _content(k: int) -> list[tuple[str, int, Any]]:
    return [(IMAGE, k * 10**8, _image(k)), (NOTE, k * 10**8 + 5, _note(k))]


def _write(path: Path, compress: str) -> Path:
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(writer_module, "CHUNK_SIZE", SMALL_CHUNKS)
        with BagWriter(path, compress=compress, custom_data={"who": "test"}) as bag:
            bag.add_topic(IMAGE, "sensor_msgs/msg/Image", qos=[QOS])
            for k in range(FRAMES):
                for topic, stamp, msg in _content(k):
                    bag.write(topic, stamp, msg)
    return path


@pytest.fixture(scope="module", params=["zstd", "none"])
def bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write(tmp_path_factory.mktemp(request.param) / "bag", request.param)


@pytest.fixture(scope="module")
def reference(bag: Path) -> list[RawMessage]:
    with open_bag(bag) as reader:
        assert reader.recovery is None
        return list(reader.raw_messages())


def _mcap(bag: Path) -> Path:
    return bag / f"{bag.name}.mcap"


def _chunks(mcap: Path) -> list[tuple[ChunkIndex, Chunk]]:
    """Every chunk of a file with its index, in file order."""
    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        out = []
        for index in summary.chunk_indexes:
            f.seek(index.chunk_start_offset + 9)
            out.append((index, Chunk.read(ReadDataStream(f))))
    return out


def _chunk_payload(index: ChunkIndex, chunk: Chunk) -> int:
    """File offset of a chunk's (compressed) records: opcode, length, 3 x u64, CRC, compression name, size."""
    return index.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(chunk.compression) + 8


def _messages_in(chunk: Chunk) -> int:
    stream, size = get_chunk_data_stream(chunk)
    count = 0
    while stream.count < size:
        opcode, length = stream.read1(), stream.read8()
        stream.read(length)
        count += opcode == 0x05
    return count


def _seconds(stamp_ns: int) -> str:
    return f"{stamp_ns / 1e9:.3f}".rstrip("0").rstrip(".") + " s"


def _copy(bag: Path, tmp_path: Path) -> tuple[Path, Path]:
    copy = tmp_path / bag.name
    shutil.copytree(bag, copy)
    return copy, _mcap(copy)


def _read(bag: Path, got: list[RawMessage]) -> None:
    with open_bag(bag) as reader:
        for message in reader.raw_messages():
            got.append(message)


# --------------------------------------------------------------------------- what the writer writes


def test_every_chunk_the_data_section_and_the_summary_carry_their_crc(bag: Path) -> None:
    mcap = _mcap(bag)
    data = mcap.read_bytes()
    chunks = _chunks(mcap)
    assert len(chunks) >= 4
    for index, chunk in chunks:
        stream, size = get_chunk_data_stream(chunk)
        assert chunk.uncompressed_crc != 0
        assert chunk.uncompressed_crc == zlib.crc32(stream.read(size))
        assert index.chunk_length < 2 * SMALL_CHUNKS  # chunks stay small: a cut file loses little
    footer_at = len(data) - 8 - 29
    footer = Footer.read(ReadDataStream(io.BytesIO(data[footer_at + 9 : footer_at + 29])))
    assert footer.summary_crc != 0
    assert footer.summary_crc == zlib.crc32(data[footer.summary_start : footer_at + 9 + 16])
    data_end_at = footer.summary_start - 13
    assert data[data_end_at] == 0x0F
    data_end = DataEnd.read(ReadDataStream(io.BytesIO(data[data_end_at + 9 : data_end_at + 13])))
    assert data_end.data_section_crc != 0
    assert data_end.data_section_crc == zlib.crc32(data[:data_end_at])


def test_mcap_and_rosbags_readers_read_the_bag(bag: Path, reference: list[RawMessage]) -> None:
    with _mcap(bag).open("rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        decoded = list(reader.iter_decoded_messages())
    assert len(decoded) == len(reference) == 2 * FRAMES
    notes = [(d.message.log_time, d.decoded_message.data) for d in decoded if d.channel.topic == NOTE]
    assert notes == [(k * 10**8 + 5, f"note {k}") for k in range(FRAMES)]
    images = [d.decoded_message for d in decoded if d.channel.topic == IMAGE]
    assert all(np.array_equal(np.frombuffer(m.data, np.uint8), _image(k).data) for k, m in enumerate(images))
    with _mcap(bag).open("rb") as f:  # reads the whole data section, checking its CRC
        assert sum(1 for _ in NonSeekingReader(f, validate_crcs=True).iter_messages()) == 2 * FRAMES
    for path in (bag, _mcap(bag)):
        with AnyReader([path], default_typestore=default_typestore()) as rosbags:
            got = [(c.topic, t, bytes(d)) for c, t, d in rosbags.messages()]
            assert got == [(m.topic, m.stamp_ns, m.data) for m in reference]
            qos = {c.topic: c.ext.offered_qos_profiles for c in rosbags.connections}
            assert qos == {IMAGE: [QOS], NOTE: []}


def _rosbags_bag(path: Path, compress: str) -> Path:
    """The same content written by rosbags' own writer (what BagWriter used before)."""
    typestore = default_typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress == "zstd":
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.set_custom_data("who", "test")
    with writer:
        image = writer.add_connection(IMAGE, "sensor_msgs/msg/Image", typestore=typestore, offered_qos_profiles=[QOS])
        note = writer.add_connection(NOTE, "std_msgs/msg/String", typestore=typestore)
        for k in range(FRAMES):
            for topic, stamp, msg in _content(k):
                connection = image if topic == IMAGE else note
                writer.write(connection, stamp, typestore.serialize_cdr(msg, connection.msgtype))
    return path


def _records(mcap: Path) -> Iterator[Any]:
    with mcap.open("rb") as f:
        yield from StreamReader(f, validate_crcs=True).records


def test_the_file_holds_what_rosbags_wrote_record_by_record(bag: Path, tmp_path: Path) -> None:
    compress = "zstd" if _chunks(_mcap(bag))[0][1].compression == "zstd" else "none"
    ours = list(_records(_mcap(bag)))
    theirs = list(_records(_mcap(_rosbags_bag(tmp_path / "bag", compress))))

    def of(kind: type, records: list[Any]) -> list[Any]:
        return [r for r in records if isinstance(r, kind)]

    # Schemas and channels appear in the first chunk and again in the summary.
    assert [(s.id, s.name, s.encoding, s.data) for s in of(Schema, ours)] == [
        (s.id, s.name, s.encoding, s.data) for s in of(Schema, theirs)
    ]
    hashes = {
        topic: default_typestore().hash_rihs01(msgtype)
        for topic, msgtype in ((IMAGE, "sensor_msgs/msg/Image"), (NOTE, "std_msgs/msg/String"))
    }
    for mine, other in zip(of(Channel, ours), of(Channel, theirs), strict=True):
        assert (mine.id, mine.topic, mine.schema_id, mine.message_encoding) == (
            other.id,
            other.topic,
            other.schema_id,
            other.message_encoding,
        )
        qos = {k: yaml.safe_load(v) for k, v in mine.metadata.items() if k == "offered_qos_profiles"}
        assert qos == {k: yaml.safe_load(v) for k, v in other.metadata.items()}
        assert mine.metadata["topic_type_hash"] == hashes[mine.topic]  # what rosbag2 (Jazzy and later) adds

    def messages(records: list[Any]) -> list[tuple[int, int, int, int, bytes]]:
        return [(m.channel_id, m.sequence, m.log_time, m.publish_time, m.data) for m in of(Message, records)]

    assert messages(ours) == messages(theirs)
    compressions = {chunk.compression for _, chunk in _chunks(_mcap(bag))}
    assert compressions == {chunk.compression for _, chunk in _chunks(_mcap(tmp_path / "bag"))}

    def metadata(records: list[Any]) -> list[tuple[str, Any]]:
        return [(m.name, {k: yaml.safe_load(v) for k, v in m.metadata.items()}) for m in of(Metadata, records)]

    assert bag.name == "bag"  # both bags are called bag: their metadata name the same file
    assert metadata(ours) == metadata(theirs)
    assert yaml.safe_load((bag / "metadata.yaml").read_text()) == yaml.safe_load(
        (tmp_path / "bag" / "metadata.yaml").read_text()
    )


# --------------------------------------------------------------------------- damage is reported, not decoded


@pytest.mark.parametrize("which", [1, -2])
def test_a_flipped_byte_in_a_chunk_names_its_topics_and_time(
    bag: Path, reference: list[RawMessage], tmp_path: Path, which: int
) -> None:
    copy, mcap = _copy(bag, tmp_path)
    chunks = _chunks(mcap)
    index, chunk = chunks[which]
    data = bytearray(mcap.read_bytes())
    data[_chunk_payload(index, chunk) + len(chunk.data) // 2] ^= 0x10
    mcap.write_bytes(bytes(data))
    before = sum(_messages_in(c) for _, c in chunks[: which % len(chunks)])
    got: list[RawMessage] = []
    with pytest.raises(BagError) as error:
        _read(copy, got)
    text = str(error.value)
    assert text.startswith(f"bag {copy} is corrupt: a chunk with {IMAGE}, {NOTE} messages ")
    span = f"from {_seconds(index.message_start_time)} to {_seconds(index.message_end_time)}"
    assert span in text and ("fails its CRC check" in text or "does not decompress" in text)
    assert f"bytes {index.chunk_start_offset:,}-" in text
    assert got == reference[:before]  # every message before the chunk, none of it
    with open_bag(copy) as reader:
        with pytest.raises(BagError, match=r"fails its CRC check|does not decompress"):
            list(reader.raw_messages([NOTE]))
        # Reads that do not touch the chunk still work.
        after = index.message_end_time + 1
        tail = [m for m in reference if m.stamp_ns >= after]
        assert list(reader.raw_messages(start_ns=after)) == tail


def test_a_crc_of_zero_is_not_checked(tmp_path: Path) -> None:
    """MCAP: CRC 0 means "not computed"; a bag from a writer that computes none reads as it is."""
    (tmp_path / "plain").mkdir()
    bag = _write(tmp_path / "plain" / "bag", "none")  # uncompressed: a payload byte can be changed in place
    with open_bag(bag) as reader:
        reference = list(reader.raw_messages())
    copy, mcap = _copy(bag, tmp_path)
    index, chunk = _chunks(mcap)[2]
    data = bytearray(mcap.read_bytes())
    struct.pack_into("<I", data, index.chunk_start_offset + 9 + 24, 0)  # the chunk's CRC
    footer = Footer.read(ReadDataStream(io.BytesIO(bytes(data[-37 + 9 : -8]))))
    struct.pack_into("<I", data, footer.summary_start - 4, 0)  # the data section's CRC
    # 100 bytes before the chunk's end: in the pixels of its last image (a note record is shorter).
    data[_chunk_payload(index, chunk) + len(chunk.data) - 100] ^= 0x01
    mcap.write_bytes(bytes(data))
    with open_bag(copy) as reader:
        got = list(reader.raw_messages())
    changed = [k for k, (a, b) in enumerate(zip(got, reference, strict=True)) if a != b]
    assert len(changed) == 1 and got[changed[0]].topic == IMAGE


def test_damage_outside_the_chunks_fails_the_data_section_crc(
    bag: Path, reference: list[RawMessage], tmp_path: Path
) -> None:
    copy, mcap = _copy(bag, tmp_path)
    index, _ = _chunks(mcap)[1]
    data = bytearray(mcap.read_bytes())
    message_index = index.chunk_start_offset + index.chunk_length  # the message indexes follow the chunk
    assert data[message_index] == 0x07
    data[message_index + 9 + 2 + 4 + 3] ^= 0x01  # a log time in the index; the chunks stay intact
    mcap.write_bytes(bytes(data))
    got: list[RawMessage] = []
    with pytest.raises(BagError, match=r"corrupt: the data section of bag\.mcap fails its CRC check"):
        _read(copy, got)
    assert got == reference  # every message came from a chunk that passed its own CRC
    with open_bag(copy) as reader:
        assert list(reader.raw_messages([IMAGE, NOTE])) == reference  # only a full read checks the whole section


def test_a_summary_failing_its_crc_is_ignored(
    bag: Path, reference: list[RawMessage], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    copy, mcap = _copy(bag, tmp_path)
    data = bytearray(mcap.read_bytes())
    footer = Footer.read(ReadDataStream(io.BytesIO(bytes(data[-37 + 9 : -8]))))
    data[footer.summary_start + 20] ^= 0x01  # inside the first summary record
    mcap.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="selfcontra_ros.bags.reader"), open_bag(copy) as reader:
        assert reader.recovery is not None
        assert "summary that fails its CRC check; its data section is complete" in reader.recovery
        assert f"recovered {2 * FRAMES} messages ({IMAGE}: {FRAMES}, {NOTE}: {FRAMES})" in reader.recovery
        assert list(reader.raw_messages()) == reference
        assert reader.custom_data == {"who": "test"}
    assert [r.getMessage() for r in caplog.records] == [reader.recovery]


def test_bags_without_crcs_from_rosbags_still_read(tmp_path: Path) -> None:
    old = _rosbags_bag(tmp_path / "old", "zstd")
    with open_bag(old) as reader:
        assert reader.recovery is None and reader.custom_data == {"who": "test"}
        notes = [m.msg.data for m in reader.messages([NOTE])]
        assert notes == [f"note {k}" for k in range(FRAMES)]


def test_a_type_outside_the_store_deserialises_with_the_bag_definition(tmp_path: Path) -> None:
    text = "int32 x\nstring name\n"
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(text, "my_msgs/msg/Thing"))
    thing = store.types["my_msgs/msg/Thing"](x=7, name="seven")
    with BagWriter(tmp_path / "bag") as out:
        out.add_topic("/thing", "my_msgs/msg/Thing", msgdef=text, rihs01=store.hash_rihs01("my_msgs/msg/Thing"))
        out.write_raw("/thing", 1, store.serialize_cdr(thing, "my_msgs/msg/Thing"))
        out.write("/note", 2, _note(0))
    with open_bag(tmp_path / "bag") as reader:
        (message,) = list(reader.messages(["/thing"]))
        assert (message.msg.x, message.msg.name) == (7, "seven")
        assert [m.msg.data for m in reader.messages(["/note"])] == ["note 0"]
