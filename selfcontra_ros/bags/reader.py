"""Read rosbag2 bags (MCAP or SQLite storage) without a ROS install.

:func:`open_bag` opens a bag folder (or a bare ``.mcap`` file) with
``rosbags`` and returns a :class:`Bag`: its topics with types and message
counts, its time span, and iterators over its messages in log-time order,
deserialised (rosbags message objects, duck-compatible with
:mod:`selfcontra_ros.ros.conversions`) or as raw CDR bytes (what a player
publishes unchanged).

Every problem with the bag itself (missing, not a bag, unfinished, truncated,
corrupt) raises :class:`BagError` naming the bag and what is wrong, never a
raw rosbags traceback. A full, unfiltered iteration also checks that it
delivered as many messages per topic as the bag's index announces, so a
damaged chunk cannot silently shorten the data.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from functools import cache
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

import yaml
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from selfcontra_ros.errors import SelfContraError

# Newest first: the first store this rosbags version knows is used.
_STORE_PREFERENCE = ("ROS2_KILTED", "ROS2_JAZZY", "ROS2_HUMBLE")

__all__ = ["Bag", "BagError", "BagMessage", "RawMessage", "TopicSummary", "default_typestore", "open_bag"]


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


class Bag:
    """An open rosbag2 bag; create it with :func:`open_bag` and close it (or use ``with``).

    Attributes:
        path: the bag folder or ``.mcap`` file.
        topics: topic name -> :class:`TopicSummary`, sorted by name.
        message_count: messages in the bag.
        start_ns: log time of the first message, nanoseconds (0 for an empty bag).
        end_ns: log time of the last message, nanoseconds (0 for an empty bag).
        custom_data: the ``custom_data`` of ``metadata.yaml`` (empty when absent).
    """

    def __init__(self, path: Path, reader: AnyReader) -> None:
        """Wrap an opened rosbags ``AnyReader``; use :func:`open_bag` instead."""
        self.path = path
        self._reader: AnyReader | None = reader
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        for connection in reader.connections:
            counts[connection.topic] = counts.get(connection.topic, 0) + connection.msgcount
            types[connection.topic] = connection.msgtype
        self.topics = {name: TopicSummary(name, types[name], counts[name]) for name in sorted(counts)}
        self.message_count = sum(counts.values())
        self.start_ns = int(reader.start_time) if self.message_count else 0
        # rosbags reports the time just after the last message.
        self.end_ns = int(reader.end_time) - 1 if self.message_count else 0
        self.custom_data = _custom_data(path)

    @property
    def duration_ns(self) -> int:
        """Time between the first and the last message, nanoseconds."""
        return self.end_ns - self.start_ns

    def _open_reader(self) -> AnyReader:
        if self._reader is None:
            raise BagError(f"bag {self.path} is closed")
        return self._reader

    def _connections(self, topics: Iterable[str] | None) -> list[Connection]:
        reader = self._open_reader()
        if topics is None:
            return list(reader.connections)
        wanted = set(topics)
        missing = sorted(wanted - set(self.topics))
        if missing:
            raise BagError(f"bag {self.path} has no topic {', '.join(missing)} (topics: {', '.join(self.topics)})")
        return [c for c in reader.connections if c.topic in wanted]

    def raw_messages(
        self, topics: Iterable[str] | None = None, *, start_ns: int | None = None, stop_ns: int | None = None
    ) -> Iterator[RawMessage]:
        """Serialised messages in log-time order (messages of equal time in writing order).

        Args:
            topics: topic names to read; all when None.
            start_ns: only messages at or after this log time (nanoseconds).
            stop_ns: only messages before this log time (nanoseconds).

        Raises:
            BagError: an unknown topic, a closed bag, unreadable data, or (full
                iteration only) fewer messages than the bag's index announces.
        """
        reader = self._open_reader()
        connections = self._connections(topics)
        seen: dict[str, int] = dict.fromkeys(self.topics, 0)
        try:
            for connection, stamp, data in reader.messages(connections=connections, start=start_ns, stop=stop_ns):
                seen[connection.topic] += 1
                yield RawMessage(connection.topic, int(stamp), bytes(data), connection.msgtype)
        except (AnyReaderError, OSError, EOFError, ValueError, KeyError, IndexError) as exc:
            raise BagError(f"bag {self.path} is corrupt or truncated: {_describe(exc)}") from exc
        except Exception as exc:  # the storage decoders raise assorted errors on damaged data
            if type(exc).__module__.split(".")[0] not in ("rosbags", "backports", "compression", "zstd", "lz4"):
                raise
            raise BagError(f"bag {self.path} is corrupt or truncated: {_describe(exc)}") from exc
        if topics is None and start_ns is None and stop_ns is None:
            short = {t: (seen[t], s.message_count) for t, s in self.topics.items() if seen[t] != s.message_count}
            if short:
                detail = ", ".join(f"{t}: {got} of {want}" for t, (got, want) in short.items())
                raise BagError(f"bag {self.path} is corrupt: read {detail} messages announced by its index")

    def messages(
        self, topics: Iterable[str] | None = None, *, start_ns: int | None = None, stop_ns: int | None = None
    ) -> Iterator[BagMessage]:
        """Deserialised ``(topic, stamp_ns, msg)`` in log-time order; arguments as :meth:`raw_messages`.

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
        reader = self._open_reader()
        try:
            return reader.deserialize(data, msgtype)
        except Exception as exc:  # rosbags raises SerdeError, struct.error, IndexError, ... on bad bytes
            where = f" on {topic}" if topic else ""
            raise BagError(
                f"bag {self.path}: a {msgtype} message{where} does not deserialise: {_describe(exc)}"
            ) from exc

    def close(self) -> None:
        """Close the bag; calling it again does nothing."""
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Bag({str(self.path)!r}, {self.message_count} messages on {len(self.topics)} topics)"


def _custom_data(path: Path) -> dict[str, str]:
    """``custom_data`` of a bag folder's metadata.yaml (empty for a bare file or when absent)."""
    metadata = path / "metadata.yaml"
    if not metadata.is_file():
        return {}
    try:
        info = yaml.safe_load(metadata.read_text()) or {}
        custom = info.get("rosbag2_bagfile_information", {}).get("custom_data") or {}
    except (OSError, yaml.YAMLError, AttributeError):
        return {}
    return {str(k): str(v) for k, v in custom.items()} if isinstance(custom, dict) else {}


def open_bag(path: Path | str) -> Bag:
    """Open a rosbag2 bag folder (``metadata.yaml`` + storage files) or a bare ``.mcap`` file.

    Raises:
        BagError: the path does not exist, is not a bag, is unfinished (no
            ``metadata.yaml``: its writer was killed), or its storage is
            missing, truncated or corrupt.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        if any(path.glob("*.mcap")) or any(path.glob("*.db3")):
            raise BagError(f"bag {path} has no metadata.yaml: it is unfinished (its writer was interrupted) or damaged")
        raise BagError(f"{path} is not a rosbag2 bag (no metadata.yaml)")
    if path.is_file() and path.suffix != ".mcap":
        raise BagError(f"{path} is not a bag: expected a rosbag2 folder or an .mcap file")
    reader = AnyReader([path], default_typestore=default_typestore())
    try:
        reader.open()
    except (AnyReaderError, OSError, EOFError, ValueError, KeyError, IndexError) as exc:
        raise BagError(f"cannot open bag {path}: it is truncated, corrupt or not a bag ({_describe(exc)})") from exc
    return Bag(path, reader)
