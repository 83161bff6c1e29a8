"""Read rosbag2 bags (MCAP or SQLite storage) without a ROS install.

:func:`open_bag` opens a bag folder (or a bare ``.mcap`` file) and returns a
:class:`Bag`: its topics with types and message counts, its time span, and
iterators over its messages in log-time order (messages of equal log time in
writing order), deserialised (rosbags message objects, duck-compatible with
:mod:`selfcontra_ros.ros.conversions`) or as raw CDR bytes (what a player
publishes unchanged).

**MCAP storage** is read record by record with the ``mcap`` library, every
checksum the file carries checked (a CRC of 0 means "not computed", MCAP
specification, and is skipped):

* **Chunks**: each chunk is decompressed and its CRC checked before any of its
  messages is returned. A chunk that fails its CRC, does not decompress or
  holds malformed records raises :class:`BagError` naming the bag, the
  chunk's topics, its time span and its bytes in the file; nothing of it is
  decoded.
* **Summary**: checked at open against the footer's CRC. A summary that fails
  it is ignored and the data section is scanned instead, as for a truncated
  file (below).
* **Data section**: checked by a full, unfiltered iteration (:meth:`Bag.raw_messages`
  or :meth:`Bag.messages` without arguments) once it has read the last
  message, when it read the chunks in file order (the usual case), and at
  open whenever the file is scanned. A mismatch raises :class:`BagError`.

**Truncated files.** An MCAP file without its summary or footer, or ending
inside a record (power loss, a killed recorder, an incomplete copy), is
scanned at open and read up to its last complete chunk (and complete message
records outside chunks): a chunk cut short is dropped whole, since its CRC
cannot vouch for it. The bag then describes what was recovered
(:attr:`Bag.topics`, :attr:`Bag.message_count`, start and end), one warning
on the logger ``selfcontra_ros.bags.reader`` says how much (messages per
topic, time span, readable bytes of the file's size), and :attr:`Bag.recovery`
holds the same text (None for an intact bag). A file with no complete message
(an empty file among them) raises :class:`BagError`.

**A folder without** ``metadata.yaml`` (its writer was killed before
finishing) is opened from its ``.mcap`` files, with the same warning;
:attr:`Bag.custom_data` is then empty. An intact MCAP file read with its
``metadata.yaml`` takes topic types and counts from ``metadata.yaml``.

**SQLite storage** (``.db3``) and MCAP bags written with rosbag2's legacy
per-file or per-message compression are read with rosbags' ``AnyReader``,
without recovery.

Messages are deserialised with the bag's own message definitions (its MCAP
schemas, registered into a fresh rosbags typestore as ``AnyReader`` does), so
types outside the ROS 2 store deserialise too; types without a stored
definition come from :func:`default_typestore`.

Every problem with the bag itself (missing, not a bag, corrupt, nothing
recoverable) raises :class:`BagError` naming the bag and what is wrong, never a
raw library traceback. A full, unfiltered iteration also checks that it
delivered as many messages per topic as the bag announces (``metadata.yaml``,
the MCAP statistics, or what a recovery scan found), so a chunk missing from
the index cannot silently shorten the data.
"""

from __future__ import annotations

import heapq
import io
import logging
import re
import struct
import zlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path, PurePath
from types import TracebackType
from typing import IO, Any, NamedTuple, Protocol

import lz4.frame
import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, MessageIndex, Schema, Statistics
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from selfcontra_ros.errors import SelfContraError

# Newest first: the first store this rosbags version knows is used.
_STORE_PREFERENCE = ("ROS2_KILTED", "ROS2_JAZZY", "ROS2_HUMBLE")

__all__ = ["Bag", "BagError", "BagMessage", "RawMessage", "TopicSummary", "default_typestore", "is_bag", "open_bag"]

_LOG = logging.getLogger(__name__)


class BagError(SelfContraError):
    """A bag is missing, unfinished, truncated or corrupt, or cannot be written.

    Defined here rather than in :mod:`selfcontra_ros.errors` so that the bag
    tools stay self-contained; it derives from :class:`SelfContraError` like
    every error of the package.
    """


class TopicSummary(NamedTuple):
    """One topic of a bag."""

    name: str
    msgtype: str
    message_count: int


class BagMessage(NamedTuple):
    """A deserialised message: ``(topic, stamp_ns, msg)`` with the log time in nanoseconds."""

    topic: str
    stamp_ns: int
    msg: Any


class RawMessage(NamedTuple):
    """A serialised (CDR) message as stored, with its topic's type."""

    topic: str
    stamp_ns: int
    data: bytes
    msgtype: str


@cache
def default_typestore() -> Typestore:
    """The rosbags typestore of ROS 2 Kilted (or the newest older ROS 2 store this rosbags version has)."""
    for name in _STORE_PREFERENCE:
        store = getattr(Stores, name, None)
        if store is not None:
            return get_typestore(store)
    raise BagError(f"the installed rosbags knows none of the ROS 2 type stores {_STORE_PREFERENCE}")


def _describe(exc: BaseException) -> str:
    text = " ".join(str(arg) for arg in exc.args) or type(exc).__name__
    return text.rstrip(".")


def _seconds(stamp_ns: int) -> str:
    """A log time for messages: seconds, at most three decimals (``1317.2 s``)."""
    return f"{stamp_ns / 1e9:.3f}".rstrip("0").rstrip(".") + " s"


def _per_topic(counts: dict[str, int]) -> str:
    return ", ".join(f"{topic}: {count}" for topic, count in sorted(counts.items()) if count) or "none"


# =========================================================================== MCAP records

_MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")  # record opcode and body length
_HEAD_SIZE = _HEAD.size
_FOOTER_SIZE = _HEAD_SIZE + 20  # summary start, summary offset start, summary CRC
_DATA_END_SIZE = _HEAD_SIZE + 4
#: A run of message records outside chunks is read in pieces of about this many bytes.
_LOOSE_RUN_BYTES = 4 << 20
#: Bytes read at a time when a CRC runs over records the iteration does not need.
_CRC_READ_BYTES = 4 << 20
#: Shortest run of zero bytes at the end of a file taken for data that never reached the disk.
_ZERO_TAIL_BYTES = 64
_PARSE_ERRORS = (McapError, struct.error, UnicodeDecodeError, ValueError, EOFError, IndexError)
_OPCODE_NAMES = {int(op): op.name.lower().replace("_", " ") for op in Opcode}


class _MalformedError(Exception):
    """A record that does not parse; the caller names the bag and place."""


def _records(buffer: bytes | memoryview) -> Iterator[tuple[int, int, memoryview]]:
    """``(opcode, offset, body)`` of each record of a buffer holding whole records.

    Raises:
        _MalformedError: a record overruns the buffer.
    """
    view = memoryview(buffer)
    size, pos = len(view), 0
    while pos < size:
        if pos + _HEAD_SIZE > size:
            raise _MalformedError(f"a record at byte {pos} is cut after {size - pos} bytes")
        opcode, length = _HEAD.unpack_from(view, pos)
        if opcode == 0:
            raise _MalformedError(f"the bytes at {pos} are no record (opcode 0)")
        end = pos + _HEAD_SIZE + length
        if end > size:
            raise _MalformedError(f"a record at byte {pos} announces {length} bytes, {size - pos - _HEAD_SIZE} follow")
        yield opcode, pos, view[pos + _HEAD_SIZE : end]
        pos = end


def _stream(body: bytes | memoryview) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


def _parse_message(body: memoryview) -> Message:
    try:
        return Message.read(_stream(body), len(body))
    except _PARSE_ERRORS as exc:
        raise _MalformedError(f"a message record does not parse ({_describe(exc)})") from exc


#: The records the reader uses, by opcode (messages apart: their reader takes the body length).
_READERS: dict[int, Any] = {
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.STATISTICS: Statistics.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
    Opcode.HEADER: Header.read,
}


def _parse(opcode: int, body: memoryview) -> Any:
    """The mcap record of a body (``Schema``, ``Channel``, ``ChunkIndex``, ...), or None for other records."""
    if opcode == Opcode.MESSAGE:
        return _parse_message(body)
    reader = _READERS.get(opcode)
    if reader is None:
        return None
    try:
        return reader(_stream(body))
    except _PARSE_ERRORS as exc:
        raise _MalformedError(f"a {_OPCODE_NAMES[opcode]} record does not parse ({_describe(exc)})") from exc


@dataclass
class _Block:
    """Where messages lie in an MCAP file: one chunk record, or a run of message records outside chunks.

    Times are log times in nanoseconds; ``channels`` are the channels with
    messages in the block, None when the file does not say (no message index).
    """

    offset: int
    length: int
    start_ns: int
    end_ns: int
    channels: set[int] | None
    chunk: bool


class _DataCrc:
    """The CRC of an MCAP data section, fed by the records a full iteration reads in file order."""

    def __init__(self, file: _McapFile) -> None:
        self.file = file
        self.position = 0
        self.crc = 0
        self.valid = file.data_crc != 0 and file.data_end is not None and not file.scanned

    def feed(self, offset: int, raw: bytes) -> None:
        if not self.valid:
            return
        if offset < self.position:  # blocks read out of file order: the CRC cannot be followed
            self.valid = False
            return
        self._skip_to(offset)
        self.crc = zlib.crc32(raw, self.crc)
        self.position = offset + len(raw)

    def check(self) -> None:
        """Raise BagError when the data section, now read to its end, fails its CRC."""
        if not self.valid or self.file.data_end is None:
            return
        self._skip_to(self.file.data_end)
        if self.crc != self.file.data_crc:
            raise BagError(
                f"bag {self.file.bag} is corrupt: the data section of {self.file.path.name} fails its CRC check "
                "(every chunk passes its own: the damage lies outside the messages, in an index or header record)"
            )

    def _skip_to(self, offset: int) -> None:
        while self.position < offset:
            piece = self.file.read(self.position, min(_CRC_READ_BYTES, offset - self.position))
            self.crc = zlib.crc32(piece, self.crc)
            self.position += len(piece)


@dataclass
class _Scan:
    """State of a sequential scan of an MCAP data section."""

    crc: int
    loose: _Block | None = None
    failure: tuple[_Block, str] | None = None
    stop: str | None = None
    complete: bool = False
    blocks: list[_Block] = field(default_factory=list)


class _McapFile:
    """One MCAP storage file, indexed at open: schemas, channels, message blocks, counts.

    ``truncation`` says why the file had to be recovered (None when it is
    intact); ``readable`` is how many of its ``size`` bytes hold complete records.
    """

    def __init__(self, path: Path, bag: Path) -> None:
        self.path, self.bag = path, bag
        try:
            self._file: IO[bytes] | None = path.open("rb")
            self.size = path.stat().st_size
        except OSError as exc:
            raise BagError(f"cannot open bag {bag}: {path.name} is unreadable ({exc.strerror or exc})") from exc
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.blocks: list[_Block] = []
        self.counts: dict[int, int] = {}
        self.start_ns, self.end_ns = 0, 0
        self.data_end: int | None = None
        self.data_crc = 0
        self.truncation: str | None = None
        self.readable = self.size
        self.scanned = False
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def read(self, offset: int, length: int) -> bytes:
        """``length`` bytes at ``offset`` (fewer at the end of the file)."""
        if self._file is None:
            raise BagError(f"bag {self.bag} is closed")
        try:
            self._file.seek(offset)
            return self._file.read(length)
        except OSError as exc:
            raise BagError(f"cannot read bag {self.bag}: {self.path.name}: {exc.strerror or exc}") from exc

    def close(self) -> None:
        file, self._file = self._file, None
        if file is not None:
            file.close()

    # ------------------------------------------------------------------ opening

    def _open(self) -> None:
        name = self.path.name
        if self.size == 0:
            raise BagError(
                f"bag {self.bag} holds no message: {name} is an empty file (0 bytes; "
                "its writer stopped before writing anything)"
            )
        if self.read(0, len(_MAGIC)) != _MAGIC[: min(self.size, len(_MAGIC))]:
            raise BagError(
                f"cannot open bag {self.bag}: {name} is not an MCAP file (it does not start with the MCAP magic)"
            )
        head = self.read(len(_MAGIC), _HEAD_SIZE)
        length = _HEAD.unpack(head)[1] if len(head) == _HEAD_SIZE else 0
        self.data_start = len(_MAGIC) + _HEAD_SIZE + length
        if len(head) < _HEAD_SIZE or self.data_start > self.size:
            raise BagError(
                f"bag {self.bag} is truncated and holds no message: {name} ends inside its MCAP header "
                f"({self.size:,} bytes)"
            )
        if head[0] != Opcode.HEADER:
            raise BagError(f"bag {self.bag} is corrupt: {name} does not start with an MCAP header record")
        self._head = self.read(0, self.data_start)
        try:
            header = _parse(Opcode.HEADER, memoryview(self._head)[len(_MAGIC) + _HEAD_SIZE :])
        except _MalformedError as exc:
            raise BagError(f"bag {self.bag} is corrupt: the MCAP header of {name} is malformed ({exc})") from exc
        if header.profile != "ros2":
            raise BagError(
                f"cannot open bag {self.bag}: {name} is an MCAP file of profile {header.profile!r}, "
                "not a ROS 2 bag (profile 'ros2')"
            )
        indexed = self._read_summary()
        if indexed is not True:
            self._scan(indexed or None)
        for channel in self.channels.values():
            if channel.message_encoding != "cdr":
                raise BagError(
                    f"cannot open bag {self.bag}: topic {channel.topic} has message encoding "
                    f"{channel.message_encoding!r}; only 'cdr' (ROS 2) is read"
                )

    def _read_summary(self) -> bool | str:
        """Index the file from its summary: True when done, False when it needs a scan, else why it is damaged."""
        footer_at = self.size - len(_MAGIC) - _FOOTER_SIZE
        if footer_at < self.data_start:
            return "has no MCAP footer"
        tail = self.read(footer_at, _FOOTER_SIZE + len(_MAGIC))
        opcode, length = _HEAD.unpack_from(tail)
        if tail[-len(_MAGIC) :] != _MAGIC or opcode != Opcode.FOOTER or length != _FOOTER_SIZE - _HEAD_SIZE:
            return "has no MCAP footer"
        footer: Footer = _parse(Opcode.FOOTER, memoryview(tail)[_HEAD_SIZE:_FOOTER_SIZE])
        if footer.summary_start == 0:
            return False
        if not self.data_start <= footer.summary_start <= footer_at:
            return "has a footer pointing outside the file"
        summary = self.read(footer.summary_start, footer_at - footer.summary_start)
        if footer.summary_crc and zlib.crc32(tail[: _FOOTER_SIZE - 4], zlib.crc32(summary)) != footer.summary_crc:
            return "has a summary that fails its CRC check"
        statistics: Statistics | None = None
        indexes: list[ChunkIndex] = []
        try:
            for opcode, _, body in _records(summary):
                record = _parse(opcode, body)
                if isinstance(record, Schema):
                    self.schemas[record.id] = record
                elif isinstance(record, Channel):
                    self.channels[record.id] = record
                elif isinstance(record, ChunkIndex):
                    indexes.append(record)
                elif isinstance(record, Statistics):
                    statistics = record
        except _MalformedError:
            return "has a malformed summary"
        self._find_data_end(footer.summary_start)
        data_end = self.data_end if self.data_end is not None else footer.summary_start
        if statistics is None or any(c not in self.channels for c in statistics.channel_message_counts):
            return False
        if statistics.message_count and not indexes:
            return False  # messages outside chunks: only a scan finds them
        for index in indexes:
            if index.chunk_start_offset < self.data_start or index.chunk_start_offset + index.chunk_length > data_end:
                return "has a chunk index pointing outside its data section"
            channels = set(index.message_index_offsets) or None
            self.blocks.append(
                _Block(
                    index.chunk_start_offset,
                    index.chunk_length,
                    index.message_start_time,
                    index.message_end_time,
                    channels,
                    chunk=True,
                )
            )
        self.counts = {cid: count for cid, count in statistics.channel_message_counts.items() if count}
        if self.counts:
            self.start_ns, self.end_ns = statistics.message_start_time, statistics.message_end_time
        return True

    def _find_data_end(self, summary_start: int) -> None:
        """Locate the DataEnd record just before the summary (or footer) and take its CRC."""
        at = summary_start - _DATA_END_SIZE
        if at < self.data_start:
            return
        raw = self.read(at, _DATA_END_SIZE)
        opcode, length = _HEAD.unpack_from(raw)
        if opcode == Opcode.DATA_END and length == _DATA_END_SIZE - _HEAD_SIZE:
            self.data_end = at
            self.data_crc = struct.unpack_from("<I", raw, _HEAD_SIZE)[0]

    def _scan(self, damage: str | None) -> None:
        """Index the file by reading its data section record by record, up to its end or its last whole record.

        Args:
            damage: why the summary could not be used; None when the file simply has no index.
        """
        self.scanned = True
        self.readable = self.data_start
        self.schemas, self.channels, self.blocks, self.counts = {}, {}, [], {}
        self.start_ns, self.end_ns = 2**63 - 1, 0
        self.data_end, self.data_crc = None, 0
        scan = _Scan(crc=zlib.crc32(self._head))
        pos = self.data_start
        while True:
            head = self.read(pos, _HEAD_SIZE)
            if len(head) < _HEAD_SIZE:
                scan.stop = (
                    f"ends after its last complete record, at byte {pos:,}"
                    if not head
                    else f"ends inside a record header at byte {pos:,}"
                )
                break
            opcode, length = _HEAD.unpack(head)
            if opcode == 0:  # no record has opcode 0: what follows was never written, or is garbage
                scan.stop = self._zeros(pos) or f"holds no valid record from byte {pos:,} on"
                break
            end = pos + _HEAD_SIZE + length
            if end > self.size:
                kind = _OPCODE_NAMES.get(opcode, f"opcode {opcode:#04x}")
                scan.stop = f"ends inside a {kind} record that starts at byte {pos:,}"
                break
            raw = head + self.read(pos + _HEAD_SIZE, length)
            if opcode == Opcode.DATA_END:
                self._end_scan(scan, pos, memoryview(raw)[_HEAD_SIZE:])
                break
            try:
                self._scan_record(scan, pos, opcode, memoryview(raw)[_HEAD_SIZE:])
            except BagError:
                # A record whose end (and everything after it) is zeros was cut by a power loss, not damaged.
                scan.stop = self._zeros(pos + len(raw.rstrip(b"\0")))
                if scan.stop is None:
                    raise
                break
            if scan.failure is not None and scan.failure[0].offset == pos:
                scan.stop = self._zeros(pos + len(raw.rstrip(b"\0")))
                if scan.stop is not None:
                    scan.failure = None
                    break
            scan.crc = zlib.crc32(raw, scan.crc)
            pos = end
            self.readable = pos
            if opcode == Opcode.FOOTER:
                scan.complete = True
                break
        if scan.failure is not None:
            raise self._chunk_error(*scan.failure)
        self._close_loose(scan)
        self.blocks = scan.blocks
        if not self.counts:
            self.start_ns = 0
        if not scan.complete:
            self.truncation = scan.stop if damage is None else f"{damage} and {scan.stop}"
        elif damage is not None:
            self.truncation = f"{damage}; its data section is complete"

    def _zeros(self, offset: int) -> str | None:
        """Why the scan stops when the file holds only zero bytes from ``offset`` on; None when it does not.

        A power loss leaves such a tail (blocks allocated, never written); a run
        shorter than :data:`_ZERO_TAIL_BYTES` may be data and does not count.
        """
        if self.size - offset < _ZERO_TAIL_BYTES:
            return None
        at = offset
        while at < self.size:
            piece = self.read(at, min(_CRC_READ_BYTES, self.size - at))
            if piece.strip(b"\0"):
                return None
            at += len(piece)
        return f"holds only zero bytes from byte {offset:,} on (data that never reached the disk)"

    def _end_scan(self, scan: _Scan, pos: int, body: memoryview) -> None:
        try:
            crc = _parse(Opcode.DATA_END, body).data_section_crc
        except _MalformedError as exc:
            raise BagError(f"bag {self.bag} is corrupt: {self.path.name}: {exc}") from exc
        if scan.failure is not None:
            raise self._chunk_error(*scan.failure)
        if crc and crc != scan.crc:
            raise BagError(f"bag {self.bag} is corrupt: the data section of {self.path.name} fails its CRC check")
        self.data_end, self.data_crc = pos, crc
        self.readable = pos + _HEAD_SIZE + len(body)
        scan.complete = True

    def _scan_record(self, scan: _Scan, pos: int, opcode: int, body: memoryview) -> None:
        if scan.failure is not None:
            if opcode != Opcode.MESSAGE_INDEX:
                raise self._chunk_error(*scan.failure)
            block = scan.failure[0]
            try:
                index = _parse(opcode, body)
            except _MalformedError:
                return
            block.channels = (block.channels or set()) | {index.channel_id}
            return
        if opcode != Opcode.MESSAGE:
            self._close_loose(scan)
        try:
            record = _parse(opcode, body)
        except _MalformedError as exc:
            raise BagError(f"bag {self.bag} is corrupt: {self.path.name}, byte {pos:,}: {exc}") from exc
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, Message):
            self._count(record, f"byte {pos:,}")
            loose = scan.loose
            if loose is None:
                scan.loose = _Block(pos, 0, record.log_time, record.log_time, set(), chunk=False)
                loose = scan.loose
            loose.length = pos + _HEAD_SIZE + len(body) - loose.offset
            loose.start_ns, loose.end_ns = min(loose.start_ns, record.log_time), max(loose.end_ns, record.log_time)
            assert loose.channels is not None
            loose.channels.add(record.channel_id)
            if loose.length >= _LOOSE_RUN_BYTES:
                self._close_loose(scan)
        elif isinstance(record, Chunk):
            block = _Block(
                pos, _HEAD_SIZE + len(body), record.message_start_time, record.message_end_time, set(), chunk=True
            )
            try:
                data = self._unpack(record)
            except _MalformedError as exc:
                scan.failure = (block, str(exc))  # raised after its message indexes named its topics
                block.channels = None
                return
            self._scan_chunk(block, data)
            scan.blocks.append(block)

    def _scan_chunk(self, block: _Block, data: bytes) -> None:
        """Take a chunk's schemas and channels, and count its messages once all its records parsed."""
        messages: list[Message] = []
        try:
            for opcode, _, body in _records(data):
                record = _parse(opcode, body)
                if isinstance(record, Schema):
                    self.schemas[record.id] = record
                elif isinstance(record, Channel):
                    self.channels[record.id] = record
                elif isinstance(record, Message):
                    messages.append(record)
        except _MalformedError as exc:
            raise self._chunk_error(block, f"holds a malformed record ({exc})") from exc
        for message in messages:
            self._count(message, f"a chunk at byte {block.offset:,}")
        block.channels = {message.channel_id for message in messages}

    def _count(self, message: Message, where: str) -> None:
        if message.channel_id not in self.channels:
            raise BagError(
                f"bag {self.bag} is corrupt: {self.path.name}, {where}: a message on channel "
                f"{message.channel_id}, which no channel record declares"
            )
        self.counts[message.channel_id] = self.counts.get(message.channel_id, 0) + 1
        self.start_ns, self.end_ns = min(self.start_ns, message.log_time), max(self.end_ns, message.log_time)

    @staticmethod
    def _close_loose(scan: _Scan) -> None:
        if scan.loose is not None:
            scan.blocks.append(scan.loose)
            scan.loose = None

    # ------------------------------------------------------------------ chunks and messages

    def _unpack(self, chunk: Chunk) -> bytes:
        """The records of a chunk, decompressed and checked against its CRC.

        Raises:
            _MalformedError: it does not decompress, has the wrong size, or fails its CRC check.
        """
        try:
            if chunk.compression == "zstd":
                data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
            elif chunk.compression == "lz4":
                data = lz4.frame.decompress(chunk.data)
            elif chunk.compression == "":
                data = chunk.data
            else:
                raise _MalformedError(f"uses the compression {chunk.compression!r}, which is not supported")
        except (zstandard.ZstdError, RuntimeError, ValueError) as exc:
            raise _MalformedError(f"does not decompress ({chunk.compression}: {_describe(exc)})") from exc
        if len(data) != chunk.uncompressed_size:
            raise _MalformedError(
                f"decompresses to {len(data):,} bytes, not the {chunk.uncompressed_size:,} it announces"
            )
        if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
            raise _MalformedError("fails its CRC check")
        return bytes(data)

    def _chunk_error(self, block: _Block, problem: str) -> BagError:
        topics = sorted({self._topic(cid) for cid in block.channels or ()})
        what = f"a chunk with {', '.join(topics)} messages" if topics else "a chunk of messages"
        return BagError(
            f"bag {self.bag} is corrupt: {what} from {_seconds(block.start_ns)} to {_seconds(block.end_ns)} "
            f"{problem} (bytes {block.offset:,}-{block.offset + block.length:,} of {self.path.name})"
        )

    def _topic(self, channel_id: int) -> str:
        channel = self.channels.get(channel_id)
        return channel.topic if channel is not None else f"channel {channel_id}"

    def load(
        self, block: _Block, wanted: set[int], start_ns: int | None, stop_ns: int | None, crc: _DataCrc | None
    ) -> list[tuple[int, int, bytes]]:
        """The messages of a block that pass the filters: ``(log_time, channel_id, data)`` in file order."""
        raw = self.read(block.offset, block.length)
        if len(raw) != block.length:
            raise BagError(
                f"bag {self.bag} is truncated: {self.path.name} ends at byte {block.offset + len(raw):,}, inside the "
                f"records it held at bytes {block.offset:,}-{block.offset + block.length:,} when it was opened"
            )
        if crc is not None:
            crc.feed(block.offset, raw)
        records: Iterable[tuple[int, int, memoryview]]
        try:
            if block.chunk:
                records = _records(self._unpack(_parse(Opcode.CHUNK, memoryview(raw)[_HEAD_SIZE:])))
            else:
                records = _records(raw)
            messages = []
            for opcode, _, body in records:
                if opcode != Opcode.MESSAGE:
                    continue
                message = _parse_message(body)
                if message.channel_id not in self.channels:
                    raise _MalformedError(
                        f"holds a message on channel {message.channel_id}, which no channel record declares"
                    )
                if message.channel_id not in wanted:
                    continue
                if (start_ns is not None and message.log_time < start_ns) or (
                    stop_ns is not None and message.log_time >= stop_ns
                ):
                    continue
                messages.append((message.log_time, message.channel_id, message.data))
        except _MalformedError as exc:
            if block.chunk:
                raise self._chunk_error(block, str(exc)) from exc
            raise BagError(
                f"bag {self.bag} is corrupt: the message records at bytes {block.offset:,}-"
                f"{block.offset + block.length:,} of {self.path.name} do not parse ({exc})"
            ) from exc
        return messages


# =========================================================================== storages


class _Storage(Protocol):
    """What :class:`Bag` reads from: an opened storage back end."""

    topics: dict[str, TopicSummary]
    start_ns: int
    end_ns: int
    recovery: str | None

    def messages(
        self, topics: set[str] | None, start_ns: int | None, stop_ns: int | None, full: bool
    ) -> Iterator[RawMessage]: ...

    def deserialize(self, data: bytes, msgtype: str) -> Any: ...

    def close(self) -> None: ...


class _Metadata(NamedTuple):
    """What the reader uses of a rosbag2 ``metadata.yaml``."""

    storage: str
    files: list[str]
    topics: dict[str, tuple[str, int, str]]  # name -> (type, message count, type hash)
    compression_mode: str
    custom_data: dict[str, str]


def _read_metadata(path: Path) -> _Metadata | None:
    """The ``metadata.yaml`` of a bag folder; None when the folder has none.

    Raises:
        BagError: it is unreadable, not YAML, or not rosbag2 bag information.
    """
    file = path / "metadata.yaml"
    if not file.is_file():
        return None
    try:
        content = yaml.safe_load(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise BagError(f"cannot open bag {path}: its metadata.yaml is unreadable ({_describe(exc)})") from exc
    try:
        info = content["rosbag2_bagfile_information"]
        topics: dict[str, tuple[str, int, str]] = {}
        for entry in info.get("topics_with_message_count") or []:
            meta = entry["topic_metadata"]
            name = str(meta["name"])
            count = int(entry["message_count"]) + (topics[name][1] if name in topics else 0)
            topics[name] = (str(meta["type"]), count, str(meta.get("type_description_hash") or ""))
        custom = info.get("custom_data") or {}
        return _Metadata(
            storage=str(info.get("storage_identifier") or ""),
            files=[PurePath(str(name)).name for name in info["relative_file_paths"]],
            topics=topics,
            compression_mode=str(info.get("compression_mode") or "").lower(),
            custom_data={str(k): str(v) for k, v in custom.items()} if isinstance(custom, dict) else {},
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise BagError(
            f"cannot open bag {path}: its metadata.yaml is not rosbag2 bag information ({_describe(exc)})"
        ) from exc


def _bag_typestore(bag: Path, schemas: Iterable[Schema], msgtypes: set[str], digests: dict[str, str]) -> Typestore:
    """A typestore of the bag's own message definitions (and the default store's for types it lacks).

    Raises:
        BagError: a stored definition does not parse, or does not match its type hash in ``metadata.yaml``.
    """
    definitions: dict[str, Any] = {}
    defined: set[str] = set()
    for schema in schemas:
        if schema.name in defined or schema.encoding not in ("ros2msg", "ros2idl", "omgidl"):
            continue
        try:
            text = bytes(schema.data).decode()
            if schema.encoding == "ros2msg":
                definitions.update(get_types_from_msg(text, schema.name))
            else:
                separator = "=" * 80 + "\n"
                sections = text.split(separator)[1:] if text.startswith(f"{separator}IDL: ") else [f"\n{text}"]
                for section in sections:
                    definitions.update(get_types_from_idl(section.split("\n", 1)[1]))
        except Exception as exc:  # rosbags' parsers raise several types on bad text
            raise BagError(
                f"cannot open bag {bag}: the message definition of {schema.name} stored in it does not parse "
                f"({_describe(exc)})"
            ) from exc
        defined.add(schema.name)
    default = default_typestore()
    if not definitions:
        return default
    if msgtypes - definitions.keys():
        definitions = {**default.fielddefs, **definitions}
    store = get_typestore(Stores.EMPTY)
    try:
        store.register(definitions)
    except Exception as exc:  # TypesysError and code generation errors
        raise BagError(f"cannot open bag {bag}: its message definitions do not register ({_describe(exc)})") from exc
    for msgtype, digest in digests.items():
        if msgtype not in defined or not digest:
            continue
        try:
            have = store.hash_rihs01(msgtype)
        except Exception:  # a definition rosbags cannot hash: nothing to compare
            continue
        if have != digest:
            raise BagError(
                f"cannot open bag {bag}: the stored definition of {msgtype} does not match its type hash "
                f"in metadata.yaml ({have} != {digest})"
            )
    return store


class _McapStorage:
    """One or more MCAP files of a bag, merged in log-time order."""

    def __init__(self, bag: Path, paths: Sequence[Path], metadata: _Metadata | None, folder: bool) -> None:
        self.bag = bag
        self.files: list[_McapFile] = []
        try:
            for path in paths:
                self.files.append(_McapFile(path, bag))
            self._index(metadata, folder)
        except BaseException:
            self.close()
            raise

    def _index(self, metadata: _Metadata | None, folder: bool) -> None:
        self._channels: list[dict[int, tuple[str, str]]] = []  # per file: channel -> (topic, msgtype)
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        for file in self.files:
            channels = {}
            for cid, channel in file.channels.items():
                schema = file.schemas.get(channel.schema_id)
                msgtype = schema.name if schema is not None else None
                if msgtype is None and metadata is not None and channel.topic in metadata.topics:
                    msgtype = metadata.topics[channel.topic][0]
                if msgtype is None:
                    raise BagError(f"cannot open bag {self.bag}: topic {channel.topic} has no message type (no schema)")
                channels[cid] = (channel.topic, msgtype)
                types[channel.topic] = msgtype
                counts[channel.topic] = counts.get(channel.topic, 0) + file.counts.get(cid, 0)
            self._channels.append(channels)
        recovered = [file for file in self.files if file.truncation is not None]
        found = dict(counts)
        if metadata is not None:
            for name, (msgtype, count, _) in metadata.topics.items():
                types.setdefault(name, msgtype)
                if not recovered:
                    counts[name] = count  # the bag's own account, checked by a full iteration
                counts.setdefault(name, 0)
        self.topics = {name: TopicSummary(name, types[name], counts[name]) for name in sorted(types)}
        with_messages = [file for file in self.files if file.message_count]
        self.start_ns = min((file.start_ns for file in with_messages), default=0)
        self.end_ns = max((file.end_ns for file in with_messages), default=0)
        total = sum(found.values())
        if recovered and not total:
            file = recovered[0]
            raise BagError(
                f"bag {self.bag} is truncated and holds no complete message: {file.path.name} {file.truncation} "
                f"({file.readable:,} of {file.size:,} bytes readable)"
            )
        self.recovery = self._recovery_text(recovered, found, metadata, folder)
        digests = {msgtype: digest for msgtype, _, digest in (metadata.topics.values() if metadata else ()) if digest}
        self._typestore = _bag_typestore(
            self.bag, [s for file in self.files for s in file.schemas.values()], set(types.values()), digests
        )

    def _recovery_text(
        self, recovered: list[_McapFile], found: dict[str, int], metadata: _Metadata | None, folder: bool
    ) -> str | None:
        no_metadata = folder and metadata is None
        if not recovered and not no_metadata:
            return None
        names = ", ".join(file.path.name for file in self.files)
        span = f"from {_seconds(self.start_ns)} to {_seconds(self.end_ns)}"
        total = sum(found.values())
        what = f"{total} messages ({_per_topic(found)}) {span}"
        if recovered:
            damage = "; ".join(
                f"{file.path.name} {file.truncation} ({file.readable:,} of {file.size:,} bytes readable)"
                for file in recovered
            )
            text = f"bag {self.bag} is incomplete: {damage}; recovered {what}"
            if metadata is not None:
                text += f"; its metadata.yaml announced {sum(c for _, c, _ in metadata.topics.values())} messages"
        else:
            text = f"bag {self.bag} was opened from {names}, complete with {what}"
        if no_metadata:
            text += "; it has no metadata.yaml (its writer did not finish), so custom_data is empty"
        return text

    def messages(
        self, topics: set[str] | None, start_ns: int | None, stop_ns: int | None, full: bool
    ) -> Iterator[RawMessage]:
        """Messages of all files in log-time order, ties in file and writing order."""
        wanted = [
            {cid for cid, (topic, _) in channels.items() if topics is None or topic in topics}
            for channels in self._channels
        ]
        # Heap entries: (log time, file, block offset, index in block, channel or block number, data);
        # index -1 marks a block not yet read, which sorts before its own messages.
        heap: list[tuple[int, int, int, int, int, bytes]] = []
        for f, file in enumerate(self.files):
            for b, block in enumerate(file.blocks):
                if (start_ns is not None and block.end_ns < start_ns) or (
                    stop_ns is not None and block.start_ns >= stop_ns
                ):
                    continue
                if block.channels is not None and not block.channels & wanted[f]:
                    continue
                heap.append((block.start_ns, f, block.offset, -1, b, b""))
        heapq.heapify(heap)
        crcs = [_DataCrc(file) for file in self.files] if full else None
        while heap:
            stamp, f, offset, index, key, data = heapq.heappop(heap)
            if index < 0:
                file = self.files[f]
                loaded = file.load(file.blocks[key], wanted[f], start_ns, stop_ns, crcs[f] if crcs else None)
                loaded.sort(key=lambda message: message[0])  # stable: ties keep their writing order
                for i, (log_time, channel_id, payload) in enumerate(loaded):
                    heapq.heappush(heap, (log_time, f, offset, i, channel_id, payload))
                continue
            topic, msgtype = self._channels[f][key]
            yield RawMessage(topic, stamp, data, msgtype)
        for crc in crcs or ():
            crc.check()

    def deserialize(self, data: bytes, msgtype: str) -> Any:
        return self._typestore.deserialize_cdr(data, msgtype)

    def close(self) -> None:
        for file in self.files:
            file.close()


class _RosbagsStorage:
    """A bag read with rosbags' ``AnyReader`` (SQLite storage, legacy rosbag2 compression modes)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.recovery: str | None = None
        reader = AnyReader([path], default_typestore=default_typestore())
        try:
            reader.open()
        except (AnyReaderError, OSError, EOFError, ValueError, KeyError, IndexError) as exc:
            raise BagError(f"cannot open bag {path}: it is truncated, corrupt or not a bag ({_describe(exc)})") from exc
        self._reader: AnyReader = reader
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        for connection in reader.connections:
            counts[connection.topic] = counts.get(connection.topic, 0) + connection.msgcount
            types[connection.topic] = connection.msgtype
        self.topics = {name: TopicSummary(name, types[name], counts[name]) for name in sorted(counts)}
        total = sum(counts.values())
        self.start_ns = int(reader.start_time) if total else 0
        self.end_ns = int(reader.end_time) - 1 if total else 0  # rosbags reports the time just after the last message

    def messages(
        self, topics: set[str] | None, start_ns: int | None, stop_ns: int | None, full: bool
    ) -> Iterator[RawMessage]:
        connections: list[Connection] = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if not connections:
            return
        try:
            for connection, stamp, data in self._reader.messages(connections=connections, start=start_ns, stop=stop_ns):
                yield RawMessage(connection.topic, int(stamp), bytes(data), connection.msgtype)
        except (AnyReaderError, OSError, EOFError, ValueError, KeyError, IndexError) as exc:
            raise BagError(f"bag {self.path} is corrupt or truncated: {_describe(exc)}") from exc
        except Exception as exc:  # the storage decoders raise assorted errors on damaged data
            if type(exc).__module__.split(".")[0] not in ("rosbags", "backports", "compression", "zstd", "lz4", "apsw"):
                raise
            raise BagError(f"bag {self.path} is corrupt or truncated: {_describe(exc)}") from exc

    def deserialize(self, data: bytes, msgtype: str) -> Any:
        return self._reader.deserialize(data, msgtype)

    def close(self) -> None:
        self._reader.close()


# =========================================================================== the bag


class Bag:
    """An open rosbag2 bag; create it with :func:`open_bag` and close it (or use ``with``).

    Attributes:
        path: the bag folder or ``.mcap`` file.
        topics: topic name -> :class:`TopicSummary`, sorted by name.
        message_count: messages in the bag (what was recovered, for a recovered bag).
        start_ns: log time of the first message, nanoseconds (0 for an empty bag).
        end_ns: log time of the last message, nanoseconds (0 for an empty bag).
        custom_data: the ``custom_data`` of ``metadata.yaml`` (empty when absent).
        recovery: for a bag opened despite damage (truncated MCAP, no
            ``metadata.yaml``), what was recovered (the text of the warning
            logged at open); None for an intact bag.
    """

    def __init__(self, path: Path, storage: _Storage, custom_data: dict[str, str]) -> None:
        """Wrap an opened storage; use :func:`open_bag` instead."""
        self.path = path
        self._storage: _Storage | None = storage
        self.topics = dict(storage.topics)
        self.message_count = sum(topic.message_count for topic in self.topics.values())
        self.start_ns = storage.start_ns if self.message_count else 0
        self.end_ns = storage.end_ns if self.message_count else 0
        self.custom_data = dict(custom_data)
        self.recovery = storage.recovery

    @property
    def duration_ns(self) -> int:
        """Time between the first and the last message, nanoseconds."""
        return self.end_ns - self.start_ns

    def _open_storage(self) -> _Storage:
        if self._storage is None:
            raise BagError(f"bag {self.path} is closed")
        return self._storage

    def raw_messages(
        self, topics: Iterable[str] | None = None, *, start_ns: int | None = None, stop_ns: int | None = None
    ) -> Iterator[RawMessage]:
        """Serialised messages in log-time order (messages of equal time in writing order).

        A full iteration (no argument) checks, after the last message, the MCAP
        data-section CRC and that it delivered as many messages per topic as
        :attr:`topics` announces.

        Args:
            topics: topic names to read; all when None.
            start_ns: only messages at or after this log time (nanoseconds).
            stop_ns: only messages before this log time (nanoseconds).

        Raises:
            BagError: an unknown topic, a closed bag, a corrupt chunk (failing
                its CRC, not decompressing), unreadable data, or (full
                iteration only) a data section failing its CRC or fewer
                messages than announced.
        """
        storage = self._open_storage()
        wanted: set[str] | None = None
        if topics is not None:
            wanted = set(topics)
            missing = sorted(wanted - set(self.topics))
            if missing:
                raise BagError(f"bag {self.path} has no topic {', '.join(missing)} (topics: {', '.join(self.topics)})")
        full = topics is None and start_ns is None and stop_ns is None
        seen: dict[str, int] = dict.fromkeys(self.topics, 0)
        for message in storage.messages(wanted, start_ns, stop_ns, full):
            seen[message.topic] = seen.get(message.topic, 0) + 1
            yield message
        if full:
            short = {t: (seen[t], s.message_count) for t, s in self.topics.items() if seen[t] != s.message_count}
            if short:
                detail = ", ".join(f"{t}: {got} of {want}" for t, (got, want) in short.items())
                raise BagError(f"bag {self.path} is corrupt: read {detail} messages announced by its index")

    def messages(
        self, topics: Iterable[str] | None = None, *, start_ns: int | None = None, stop_ns: int | None = None
    ) -> Iterator[BagMessage]:
        """Deserialised ``(topic, stamp_ns, msg)`` in log-time order; arguments and checks as :meth:`raw_messages`.

        Raises:
            BagError: as :meth:`raw_messages`, or a message that does not deserialise.
        """
        for raw in self.raw_messages(topics, start_ns=start_ns, stop_ns=stop_ns):
            yield BagMessage(raw.topic, raw.stamp_ns, self.deserialize(raw.data, raw.msgtype, topic=raw.topic))

    def deserialize(self, data: bytes, msgtype: str, *, topic: str = "") -> Any:
        """Deserialise CDR bytes of type ``msgtype`` with the bag's own message definitions.

        Raises:
            BagError: the data does not hold such a message.
        """
        storage = self._open_storage()
        try:
            return storage.deserialize(data, msgtype)
        except Exception as exc:  # rosbags raises SerdeError, struct.error, IndexError, ... on bad bytes
            where = f" on {topic}" if topic else ""
            raise BagError(
                f"bag {self.path}: a {msgtype} message{where} does not deserialise: {_describe(exc)}"
            ) from exc

    def close(self) -> None:
        """Close the bag; calling it again does nothing."""
        storage, self._storage = self._storage, None
        if storage is not None:
            storage.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Bag({str(self.path)!r}, {self.message_count} messages on {len(self.topics)} topics)"


def _storage_order(path: Path) -> tuple[str, int]:
    """Sort key of rosbag2 storage files: ``bag_2.mcap`` before ``bag_10.mcap``."""
    match = re.fullmatch(r"(.*?)(\d*)", path.stem)
    assert match is not None  # the pattern matches every string
    return match.group(1), int(match.group(2) or -1)


def _storage_kind(metadata: _Metadata) -> str:
    """``metadata.yaml``'s storage identifier, or the one its file names imply when it has none."""
    if metadata.storage:
        return metadata.storage
    suffixes = {PurePath(name).suffix for name in metadata.files}
    return {".mcap": "mcap", ".db3": "sqlite3"}.get(suffixes.pop(), "") if len(suffixes) == 1 else ""


def is_bag(path: Path | str) -> bool:
    """Whether ``path`` is for :func:`open_bag`: an ``.mcap`` file, or a folder with ``metadata.yaml`` or storage files.

    A folder holding ``.mcap`` (or ``.db3``) files but no ``metadata.yaml`` counts: its writer was killed,
    and :func:`open_bag` recovers it (or says why it cannot).
    """
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(path.glob("*.mcap")) or any(path.glob("*.db3"))
    return path.suffix == ".mcap"


def open_bag(path: Path | str) -> Bag:
    """Open a rosbag2 bag folder (``metadata.yaml`` + storage files) or a bare ``.mcap`` file.

    A damaged MCAP bag that still holds complete messages (truncated file, no
    ``metadata.yaml``) is opened with a warning, also kept in :attr:`Bag.recovery`
    (module docstring).

    Raises:
        BagError: the path does not exist or is not a bag, its storage is
            missing, an empty file, corrupt, or holds no complete message, or
            it is an SQLite bag without ``metadata.yaml``.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    custom_data: dict[str, str] = {}
    storage: _Storage
    if path.is_file():
        if path.suffix != ".mcap":
            raise BagError(f"{path} is not a bag: expected a rosbag2 folder or an .mcap file")
        storage = _McapStorage(path, [path], None, folder=False)
    else:
        metadata = _read_metadata(path)
        if metadata is None:
            files = sorted(path.glob("*.mcap"), key=_storage_order)
            if not files:
                if any(path.glob("*.db3")):
                    raise BagError(
                        f"bag {path} has no metadata.yaml: it is unfinished (its writer was interrupted) or damaged"
                    )
                raise BagError(f"{path} is not a rosbag2 bag (no metadata.yaml)")
            storage = _McapStorage(path, files, None, folder=True)
        elif _storage_kind(metadata) == "sqlite3" or metadata.compression_mode in ("file", "message"):
            storage = _RosbagsStorage(path)
            custom_data = metadata.custom_data
        elif _storage_kind(metadata) == "mcap":
            files = [path / name for name in metadata.files]
            missing = [file.name for file in files if not file.is_file()]
            if missing:
                raise BagError(
                    f"cannot open bag {path}: its storage file {', '.join(missing)} listed in metadata.yaml is missing"
                )
            if not files:
                raise BagError(f"cannot open bag {path}: its metadata.yaml lists no storage file")
            storage = _McapStorage(path, files, metadata, folder=True)
            custom_data = metadata.custom_data
        else:
            raise BagError(f"cannot open bag {path}: its storage {metadata.storage!r} is not supported (mcap, sqlite3)")
    if storage.recovery is not None:
        _LOG.warning("%s", storage.recovery)
    return Bag(path, storage, custom_data)
