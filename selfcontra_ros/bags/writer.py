"""Write rosbag2 bags with MCAP storage, message by message, without a ROS install.

:class:`BagWriter` wraps ``rosbags.rosbag2.Writer``. What it adds:

* **Closing always yields a valid bag.** Use it as a context manager (or call
  :meth:`BagWriter.close` in a ``finally``): the MCAP summary (schemas,
  channels, chunk indexes, statistics) and ``metadata.yaml`` are written on
  close, also when an exception or Ctrl-C ended the writing early, so a long
  offline run that is interrupted leaves a readable bag holding every message
  written so far. Only a hard kill (SIGKILL, power loss) leaves a bag without
  ``metadata.yaml`` and MCAP footer; :func:`selfcontra_ros.bags.reader.open_bag`
  reports such a bag as unfinished.
* **Atomic mode** (``atomic=True``) for conversions that must be complete or
  absent: the bag is written in a hidden staging folder beside the target
  (``.<name>.<random>.partial/<name>``) and moved to ``path`` only when
  :meth:`BagWriter.close` succeeds; leaving the ``with`` block by an exception
  deletes the staging folder, so no half-written bag ever sits at ``path``.
* Messages are rosbags message objects serialised with the writer's
  typestore (ROS 2 Kilted definitions), or raw CDR bytes.
* ``compress="zstd"`` compresses the MCAP chunks (what ``ros2 bag record
  --storage-preset-profile zstd_fast`` does); Foxglove, ``ros2 bag`` and the
  ``mcap`` libraries read such files.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer, WriterError
from rosbags.typesys.store import Typestore

from selfcontra_ros.bags.reader import BagError, default_typestore

__all__ = ["COMPRESSIONS", "BagWriter", "default_typestore"]

#: Accepted values of ``compress``.
COMPRESSIONS = ("zstd", "none")
#: rosbag2 metadata version written (9: Jazzy and later).
_ROSBAG2_VERSION: Literal[9] = 9
_MAX_STAMP_NS = 2**63 - 1


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
        self._staging: Path | None = None
        if atomic:
            self._staging = Path(
                tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent)
            )
            target = self._staging / self.path.name
        else:
            target = self.path
        self._writer: Writer | None = Writer(target, version=_ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
        if compress == "zstd":
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        for key, value in (custom_data or {}).items():
            self._writer.set_custom_data(str(key), str(value))
        try:
            self._writer.open()
        except (OSError, WriterError) as exc:
            self._remove_staging()
            raise BagError(f"cannot create bag {self.path}: {exc}") from exc
        self._connections: dict[str, Connection] = {}
        self._counts: dict[str, int] = {}

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

        Args:
            topic: absolute topic name, e.g. ``/stereo/left/image_rect``.
            msgtype: ``package/msg/Type``.
            qos: offered QoS profiles recorded in the metadata (what ``ros2 bag play`` offers).
            msgdef: message definition text (``ros2msg``), with ``rihs01``, for a
                type the typestore does not know (e.g. copied from another bag).
            rihs01: type hash matching ``msgdef``.

        Raises:
            BagError: the bag is closed, the topic exists already, or the type is unknown.
        """
        writer = self._open_writer()
        if topic in self._connections:
            raise BagError(f"topic {topic} was already added to bag {self.path}")
        if (msgdef is None or rihs01 is None) and msgtype not in self.typestore.types:
            raise BagError(f"message type {msgtype!r} of topic {topic} is unknown; pass msgdef and rihs01")
        try:
            connection = writer.add_connection(
                topic, msgtype, typestore=self.typestore, msgdef=msgdef, rihs01=rihs01, offered_qos_profiles=qos
            )
        except WriterError as exc:
            raise BagError(f"cannot add topic {topic} ({msgtype}) to bag {self.path}: {exc}") from exc
        self._connections[topic] = connection
        self._counts[topic] = 0

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialise a rosbags message (CDR) and append it with log time ``stamp_ns``.

        A topic not yet added is added with the message's own type (``msg.__msgtype__``).

        Args:
            topic: absolute topic name.
            stamp_ns: log time, integer nanoseconds since the epoch (>= 0).
            msg: a message object of the writer's typestore.

        Raises:
            BagError: the bag is closed, the stamp is out of range, the message
                does not match the topic's type, or writing fails.
        """
        connection = self._connections.get(topic)
        if connection is None:
            msgtype = getattr(msg, "__msgtype__", None)
            if not isinstance(msgtype, str):
                raise BagError(
                    f"cannot tell the message type of {type(msg).__name__} for topic {topic}; add_topic first"
                )
            self.add_topic(topic, msgtype)
            connection = self._connections[topic]
        elif getattr(msg, "__msgtype__", connection.msgtype) != connection.msgtype:
            raise BagError(f"topic {topic} carries {connection.msgtype}, got a {msg.__msgtype__} message")
        try:
            data = self.typestore.serialize_cdr(msg, connection.msgtype)
        except Exception as exc:  # rosbags raises several types for malformed messages
            raise BagError(f"cannot serialise a {connection.msgtype} message for {topic}: {exc}") from exc
        self._write(topic, connection, stamp_ns, data)

    def write_raw(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> None:
        """Append an already serialised (CDR) message to a topic declared with :meth:`add_topic`.

        Raises:
            BagError: the bag is closed, the topic was not added, or the stamp is out of range.
        """
        connection = self._connections.get(topic)
        if connection is None:
            raise BagError(f"topic {topic} was not added to bag {self.path}; call add_topic first")
        self._write(topic, connection, stamp_ns, data)

    def _write(self, topic: str, connection: Connection, stamp_ns: int, data: bytes | memoryview) -> None:
        writer = self._open_writer()
        stamp = int(stamp_ns)
        if not 0 <= stamp <= _MAX_STAMP_NS:
            raise BagError(f"log time {stamp_ns} ns of a {topic} message is outside 0..2^63-1")
        try:
            writer.write(connection, stamp, data)
        except (OSError, WriterError) as exc:
            raise BagError(f"cannot write to bag {self.path}: {exc}") from exc
        self._counts[topic] += 1

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return dict(self._counts)

    @property
    def closed(self) -> bool:
        """True once the bag was closed or discarded."""
        return self._writer is None

    # ------------------------------------------------------------------ closing

    def close(self) -> Path:
        """Finish the bag: MCAP summary and footer, ``metadata.yaml``; in atomic mode move it to ``path``.

        Calling it again does nothing.

        Returns:
            The bag folder ``path``.

        Raises:
            BagError: writing the summary failed, or (atomic mode) ``path``
                appeared meanwhile; the staging folder is then removed.
        """
        writer, self._writer = self._writer, None
        if writer is None:
            return self.path
        try:
            writer.close()
        except (OSError, WriterError) as exc:
            self._remove_staging()
            raise BagError(f"cannot finish bag {self.path}: {exc}") from exc
        if self._staging is not None:
            if self.path.exists() or self.path.is_symlink():
                self._remove_staging()
                raise BagError(f"output bag {self.path} appeared while writing it; not overwriting (output discarded)")
            (self._staging / self.path.name).replace(self.path)
            self._remove_staging()
        return self.path

    def discard(self) -> None:
        """Stop writing and delete everything written (the staging folder, or the bag folder itself)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.abort()
            if self._staging is None:
                shutil.rmtree(self.path, ignore_errors=True)
        self._remove_staging()

    def _remove_staging(self) -> None:
        staging, self._staging = self._staging, None
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)

    def _open_writer(self) -> Writer:
        if self._writer is None:
            raise BagError(f"bag {self.path} is closed")
        return self._writer

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
