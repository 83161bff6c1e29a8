"""Write rosbag2 bags with MCAP storage, message by message, without a ROS install.

:class:`BagWriter` writes a rosbag2 folder (``metadata.yaml`` and one
``<name>.mcap``) with the ``mcap`` library. The MCAP file is what rosbag2's
MCAP storage plugin writes: profile ``ros2``, one schema per message type
(encoding ``ros2msg`` or ``ros2idl``, the full message definition text),
channels with message encoding ``cdr`` and the metadata ``offered_qos_profiles``
and ``topic_type_hash`` (RIHS01), messages in chunks, a ``rosbag2`` metadata
record holding the serialised ``metadata.yaml``, and a summary (schemas,
channels, statistics, chunk and metadata indexes, summary offsets).
``ros2 bag``, Foxglove, rosbags and the ``mcap`` libraries read it. What the
writer guarantees:

* **Checksums everywhere.** Every chunk carries the CRC-32 of its
  uncompressed records, the DataEnd record the CRC-32 of the whole data
  section, and the footer the CRC-32 of the summary, so
  :func:`selfcontra_ros.bags.reader.open_bag` (and any MCAP reader that
  validates CRCs) detects a damaged byte instead of decoding garbage.
* **Small chunks.** A chunk is closed once its uncompressed records pass
  :data:`CHUNK_SIZE` (1 MiB; a larger single message makes a chunk of its
  own), and each closed chunk goes to the file at once: a bag cut short
  (power loss, SIGKILL) loses at most the open chunk, and the reader recovers
  every complete chunk before the cut.
* **Closing always yields a valid bag.** Use it as a context manager (or call
  :meth:`BagWriter.close` in a ``finally``): the MCAP summary and
  ``metadata.yaml`` are written on close, also when an exception or Ctrl-C
  ended the writing early, so a long offline run that is interrupted leaves a
  readable bag holding every message written so far. Only a hard kill
  (SIGKILL, power loss) leaves a bag without ``metadata.yaml`` and MCAP
  summary; :func:`~selfcontra_ros.bags.reader.open_bag` recovers its complete
  chunks, with a warning.
* **Atomic mode** (``atomic=True``) for conversions that must be complete or
  absent: the bag is written in a hidden staging folder beside the target
  (``.<name>.<random>.partial/<name>``) and moved to ``path`` only when
  :meth:`BagWriter.close` succeeds; leaving the ``with`` block by an exception
  deletes the staging folder, so no half-written bag ever sits at ``path``.
* **Never overwriting**: an existing ``path`` is refused.
* Messages are rosbags message objects serialised with the writer's
  typestore (ROS 2 Kilted definitions), or raw CDR bytes.
* ``compress="zstd"`` compresses the MCAP chunks (what ``ros2 bag record
  --storage-preset-profile zstd_fast`` does); ``"none"`` stores them as they are.

``metadata.yaml`` is rosbag2 version 9 with the content rosbags' writer gave
it (``ros_distro: rosbags`` included): storage ``mcap``, one file, topics with
type, serialisation ``cdr``, QoS, type hash and message count, start and
duration, ``custom_data``; compression fields are empty, as for rosbag2
storage compression.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal

import yaml
from mcap.exceptions import McapError
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys.store import Typestore

from selfcontra_ros.bags.reader import BagError, default_typestore

__all__ = ["CHUNK_SIZE", "COMPRESSIONS", "BagWriter", "default_typestore"]

#: Accepted values of ``compress``.
COMPRESSIONS = ("zstd", "none")
#: Uncompressed bytes after which a chunk is closed and written (1 MiB, as rosbags and rosbag2 do).
CHUNK_SIZE = 1 << 20
#: rosbag2 metadata version written (9: Jazzy and later).
_ROSBAG2_VERSION: Literal[9] = 9
_MAX_STAMP_NS = 2**63 - 1
_IDL_PREFIX = "=" * 80 + "\nIDL: "
_LIBRARY = f"selfcontra_ros; {LIBRARY_IDENTIFIER}"
_WRITE_ERRORS = (OSError, ValueError, McapError)


@dataclass(frozen=True)
class _Topic:
    """A declared topic: its MCAP channel and what ``metadata.yaml`` says of it."""

    channel_id: int
    msgtype: str
    rihs01: str
    qos: tuple[Qos, ...]


def _dump_qos(qos: Sequence[Qos]) -> str:
    """QoS profiles as the YAML text rosbag2 stores in a channel's ``offered_qos_profiles``."""
    return str(yaml.safe_dump(dump_qos_v9(list(qos)), default_flow_style=False)).strip()


class BagWriter:
    """A rosbag2 bag (MCAP storage) being written; see the module docstring for the guarantees.

    Example::

        with BagWriter(out, atomic=True) as bag:
            bag.write("/stereo/left/image_rect", stamp_ns, image_msg)

    Attributes:
        path: the bag folder (its final place in atomic mode).
        typestore: the rosbags typestore that serialises messages; use its
            ``types`` to build messages.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        compress: str = "zstd",
        atomic: bool = False,
        typestore: Typestore | None = None,
        custom_data: Mapping[str, str] | None = None,
    ) -> None:
        """Create the bag folder and open it for writing.

        Args:
            path: bag folder to create; it holds ``<name>.mcap`` and ``metadata.yaml``.
            compress: ``"zstd"`` (MCAP chunk compression) or ``"none"``.
            atomic: write in a staging folder and move the bag to ``path`` on a successful close.
            typestore: message definitions; :func:`default_typestore` when None.
            custom_data: string key/values stored in ``metadata.yaml`` (``custom_data``).

        Raises:
            BagError: ``path`` exists already (bags are never overwritten), its
                parent folder is missing, ``compress`` is unknown, or the folder
                cannot be created.
        """
        self.path = Path(path)
        if compress not in COMPRESSIONS:
            raise BagError(f"compress is {compress!r}; expected one of {', '.join(COMPRESSIONS)}")
        if self.path.exists() or self.path.is_symlink():
            raise BagError(f"output bag {self.path} exists already; remove it or choose another path (not overwriting)")
        if not self.path.parent.is_dir():
            raise BagError(f"cannot create bag {self.path}: folder {self.path.parent} does not exist")
        self.typestore = typestore if typestore is not None else default_typestore()
        self._atomic = atomic
        self._custom_data = {str(key): str(value) for key, value in (custom_data or {}).items()}
        self._staging: Path | None = None
        if atomic:
            self._staging = Path(
                tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent)
            )
            self._folder = self._staging / self.path.name
        else:
            self._folder = self.path
        self._file_name = f"{self.path.name}.mcap"
        self._file: IO[bytes] | None = None
        try:
            self._folder.mkdir(mode=0o755)
            self._file = (self._folder / self._file_name).open("xb")
            self._mcap: McapWriter | None = McapWriter(
                self._file,
                chunk_size=CHUNK_SIZE,
                compression=CompressionType.ZSTD if compress == "zstd" else CompressionType.NONE,
                index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA,
                enable_crcs=True,
                enable_data_crcs=True,
            )
            self._mcap.start(profile="ros2", library=_LIBRARY)
        except _WRITE_ERRORS as exc:
            if self._file is not None:
                self._file.close()
            if not atomic:
                shutil.rmtree(self._folder, ignore_errors=True)
            self._remove_staging()
            raise BagError(f"cannot create bag {self.path}: {exc}") from exc
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._counts: dict[str, int] = {}
        self._first_ns = _MAX_STAMP_NS
        self._last_ns = 0

    # ------------------------------------------------------------------ topics and messages

    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        qos: Sequence[Qos] = (),
        msgdef: str | None = None,
        rihs01: str | None = None,
    ) -> None:
        """Declare a topic before its first message (optional for types of the typestore).

        The first topic of a message type stores the type's schema (its message
        definition); later topics of the same type share it.

        Args:
            topic: absolute topic name, e.g. ``/stereo/left/image_rect``.
            msgtype: ``package/msg/Type``.
            qos: offered QoS profiles recorded in the metadata (what ``ros2 bag play`` offers).
            msgdef: message definition text (``ros2msg``, or ``ros2idl`` sections), with
                ``rihs01``, for a type the typestore does not know (e.g. copied from another bag).
            rihs01: type hash matching ``msgdef``.

        Raises:
            BagError: the bag is closed, the topic exists already, or the type is unknown.
        """
        writer = self._open_writer()
        if topic in self._topics:
            raise BagError(f"topic {topic} was already added to bag {self.path}")
        if msgdef is None or rihs01 is None:
            if msgtype not in self.typestore.types:
                raise BagError(f"message type {msgtype!r} of topic {topic} is unknown; pass msgdef and rihs01")
            try:
                msgdef, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
                rihs01 = self.typestore.hash_rihs01(msgtype)
            except Exception as exc:  # rosbags raises several types for definitions it cannot render
                raise BagError(f"cannot describe message type {msgtype} of topic {topic}: {exc}") from exc
        qos = tuple(qos)
        try:
            schema_id = self._schemas.get(msgtype)
            if schema_id is None:
                encoding = "ros2idl" if msgdef.startswith(_IDL_PREFIX) else "ros2msg"
                schema_id = writer.register_schema(msgtype, encoding, msgdef.encode())
                self._schemas[msgtype] = schema_id
            channel_id = writer.register_channel(
                topic,
                "cdr",
                schema_id,
                metadata={"offered_qos_profiles": _dump_qos(qos), "topic_type_hash": rihs01},
            )
        except _WRITE_ERRORS as exc:
            raise BagError(f"cannot add topic {topic} ({msgtype}) to bag {self.path}: {exc}") from exc
        self._topics[topic] = _Topic(channel_id, msgtype, rihs01, qos)
        self._counts[topic] = 0

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialise a rosbags message (CDR) and append it with log time ``stamp_ns``.

        A topic not yet added is added with the message's own type (``msg.__msgtype__``).

        Args:
            topic: absolute topic name.
            stamp_ns: log time (and publish time), integer nanoseconds since the epoch (>= 0).
            msg: a message object of the writer's typestore.

        Raises:
            BagError: the bag is closed, the stamp is out of range, the message
                does not match the topic's type, or writing fails.
        """
        declared = self._topics.get(topic)
        if declared is None:
            msgtype = getattr(msg, "__msgtype__", None)
            if not isinstance(msgtype, str):
                raise BagError(
                    f"cannot tell the message type of {type(msg).__name__} for topic {topic}; add_topic first"
                )
            self.add_topic(topic, msgtype)
            declared = self._topics[topic]
        elif getattr(msg, "__msgtype__", declared.msgtype) != declared.msgtype:
            raise BagError(f"topic {topic} carries {declared.msgtype}, got a {msg.__msgtype__} message")
        try:
            data = self.typestore.serialize_cdr(msg, declared.msgtype)
        except Exception as exc:  # rosbags raises several types for malformed messages
            raise BagError(f"cannot serialise a {declared.msgtype} message for {topic}: {exc}") from exc
        self._write(topic, declared, stamp_ns, data)

    def write_raw(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> None:
        """Append an already serialised (CDR) message to a topic declared with :meth:`add_topic`.

        Raises:
            BagError: the bag is closed, the topic was not added, or the stamp is out of range.
        """
        declared = self._topics.get(topic)
        if declared is None:
            raise BagError(f"topic {topic} was not added to bag {self.path}; call add_topic first")
        self._write(topic, declared, stamp_ns, data)

    def _write(self, topic: str, declared: _Topic, stamp_ns: int, data: bytes | memoryview) -> None:
        writer = self._open_writer()
        stamp = int(stamp_ns)
        if not 0 <= stamp <= _MAX_STAMP_NS:
            raise BagError(f"log time {stamp_ns} ns of a {topic} message is outside 0..2^63-1")
        try:
            writer.add_message(declared.channel_id, log_time=stamp, data=bytes(data), publish_time=stamp)
        except _WRITE_ERRORS as exc:
            raise BagError(f"cannot write to bag {self.path}: {exc}") from exc
        self._counts[topic] += 1
        self._first_ns = min(self._first_ns, stamp)
        self._last_ns = max(self._last_ns, stamp)

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return dict(self._counts)

    @property
    def closed(self) -> bool:
        """True once the bag was closed or discarded."""
        return self._mcap is None

    # ------------------------------------------------------------------ closing

    def close(self) -> Path:
        """Finish the bag: MCAP metadata, summary and footer, ``metadata.yaml``; in atomic mode move it to ``path``.

        Calling it again does nothing.

        Returns:
            The bag folder ``path``.

        Raises:
            BagError: writing the summary failed, or (atomic mode) ``path``
                appeared meanwhile; the staging folder is then removed.
        """
        writer, self._mcap = self._mcap, None
        if writer is None:
            return self.path
        info = self._bag_information()
        try:
            writer.flush()  # the last chunk, so that the metadata record follows every chunk (as rosbag2 writes it)
            serialized = str(yaml.safe_dump(info, default_flow_style=False)).strip()
            writer.add_metadata("rosbag2", {"serialized_metadata": serialized})
            writer.finish()
            file, self._file = self._file, None
            if file is not None:
                file.close()
            metadata = self._folder / "metadata.yaml"
            partial = metadata.with_suffix(".yaml.tmp")
            partial.write_text(
                yaml.safe_dump({"rosbag2_bagfile_information": info}, default_flow_style=False), encoding="utf-8"
            )
            partial.replace(metadata)
        except _WRITE_ERRORS as exc:
            self._close_file()
            self._remove_staging()
            raise BagError(f"cannot finish bag {self.path}: {exc}") from exc
        if self._staging is not None:
            if self.path.exists() or self.path.is_symlink():
                self._remove_staging()
                raise BagError(f"output bag {self.path} appeared while writing it; not overwriting (output discarded)")
            self._folder.replace(self.path)
            self._remove_staging()
        return self.path

    def discard(self) -> None:
        """Stop writing and delete everything written (the staging folder, or the bag folder itself)."""
        writer, self._mcap = self._mcap, None
        if writer is not None:
            self._close_file()
            if self._staging is None:
                shutil.rmtree(self.path, ignore_errors=True)
        self._remove_staging()

    def _bag_information(self) -> dict[str, Any]:
        """``rosbag2_bagfile_information`` of ``metadata.yaml``, as rosbags' writer filled it."""
        count = sum(self._counts.values())
        duration = max(0, self._last_ns - self._first_ns)

        def span() -> dict[str, Any]:  # fresh dicts each time: shared ones would become YAML anchors
            return {"duration": {"nanoseconds": duration}, "starting_time": {"nanoseconds_since_epoch": self._first_ns}}

        return {
            "version": _ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "relative_file_paths": [self._file_name],
            **span(),
            "message_count": count,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": declared.msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": dump_qos_v9(list(declared.qos)),
                        "type_description_hash": declared.rihs01,
                    },
                    "message_count": self._counts[topic],
                }
                for topic, declared in self._topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [{"path": self._file_name, **span(), "message_count": count}],
            "custom_data": self._custom_data or None,
            "ros_distro": "rosbags",
        }

    def _close_file(self) -> None:
        file, self._file = self._file, None
        if file is not None:
            with contextlib.suppress(OSError):  # the caller reports its own failure, or discards the data
                file.close()

    def _remove_staging(self) -> None:
        staging, self._staging = self._staging, None
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)

    def _open_writer(self) -> McapWriter:
        if self._mcap is None:
            raise BagError(f"bag {self.path} is closed")
        return self._mcap

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Close the bag; in atomic mode an exception discards it instead (see the module docstring)."""
        if exc_type is not None and self._atomic:
            self.discard()
        else:
            self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"BagWriter({str(self.path)!r}, {state}, {sum(self._counts.values())} messages)"
