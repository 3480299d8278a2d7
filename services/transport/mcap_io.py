"""MCAP files in the project's protobuf schemas: a crash-tolerant writer and a reader that survives truncation.

Writer: chunked and zstd-compressed; a chunk is completed (and handed to the OS) at least every ``flush_interval_s``,
so a recorder killed with SIGKILL leaves a file whose completed chunks are readable. Each topic is one channel whose
schema is msk.proto's FileDescriptorSet, so Foxglove decodes every message. ``log_time`` is the host receive time
and ``publish_time`` the device time (host time when the message has none).

Rejected payloads: what the recorder received but could not use as its topic's type (garbage, another type's bytes,
a message failing its type's checks, a key outside the topic table: ``services.nodes.node_runtime.check_payload``) goes
into a channel of its own per (key, reason): topic the key, no schema, message encoding
:data:`REJECTED_ENCODING`, channel metadata :data:`REJECTED_REASON` (the reason) and :data:`REJECTED_DETAIL` (why the
first one was refused). :func:`read_messages` leaves those channels out, and any other channel that does not carry an
msk protobuf type, and counts what it left out in :class:`ReadReport`; ``include_rejected=True`` yields them with
``rejected`` set and no type.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload

from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary
from mcap.writer import CompressionType, Writer

from msk_core.errors import FileFormatError, InputError
from services.transport import messages, topics

PROFILE = ""  # protobuf over MCAP has no profile; "ros1"/"ros2" would be wrong
LIBRARY = "msk-live"
PROTOBUF = "protobuf"
#: Message encoding of the channels that hold rejected payloads: bytes, no schema.
REJECTED_ENCODING = "application/octet-stream"
#: Channel metadata of a rejected channel: why its payloads were refused (a ``DropReason`` value) ...
REJECTED_REASON = "msk.rejected"
#: ... and the check's words for the first payload of the channel.
REJECTED_DETAIL = "msk.rejected_detail"
MAX_DETAIL_CHARS = 500


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    type_name: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    #: why the recorder refused this payload ("" for a message of its topic's type; ``type_name`` is then "")
    rejected: str = ""

    @overload
    def decode(self) -> messages.AnyMessage: ...
    @overload
    def decode(self, kind: type[messages.M]) -> messages.M: ...
    def decode(self, kind: type[messages.AnyMessage] | None = None) -> messages.AnyMessage:
        """The message; with ``kind`` (``messages.EmgChunk``), typed as it, and a :class:`MessageDecodeError` when the
        recorded message is of another type."""
        if self.rejected:
            raise messages.MessageDecodeError(
                f"{self.topic}: a payload the recorder rejected ({self.rejected}), not a message"
            )
        if kind is None:
            return messages.decode(self.type_name, self.data)
        if kind.DESCRIPTOR.full_name != self.type_name:
            raise messages.MessageDecodeError(f"{self.topic}: a {self.type_name}, not a {kind.DESCRIPTOR.full_name}")
        return messages.decode(kind, self.data)


class McapRecorderWriter:
    """Append protobuf messages to an MCAP file, one channel per topic.

    ``with McapRecorderWriter(path) as writer: writer.write(topic, type_name, payload, log_time_ns, publish_time_ns)``
    """

    def __init__(
        self,
        path: str | Path,
        *,
        # 1 MiB: a live session's chunks then close on the flush interval, once a second, rather than about twice on
        # size; the writer keeps each chunk's index until close (the file's summary), 8.8 -> 5.3 MB/h on msk live --sim
        chunk_size: int = 1024 * 1024,
        flush_interval_s: float = 1.0,
        compression: CompressionType = CompressionType.ZSTD,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # Buffered (mcap's Writer needs it); flush() pushes completed chunks to the OS every flush_interval_s.
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=compression)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._rejected_channel_ids: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}  # per channel
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._descriptor_set = messages.file_descriptor_set()
        self.message_count = 0
        self._unflushed = 0
        self._closed = False

    def _channel_id(self, topic: str, type_name: str) -> int:
        channel_id = self._channel_ids.get(topic)
        if channel_id is None:
            messages.message_class(type_name)
            schema_id = self._schema_ids.get(type_name)
            if schema_id is None:
                schema_id = self._writer.register_schema(name=type_name, encoding="protobuf", data=self._descriptor_set)
                self._schema_ids[type_name] = schema_id
            channel_id = self._writer.register_channel(topic=topic, message_encoding=PROTOBUF, schema_id=schema_id)
            self._channel_ids[topic] = channel_id
        return channel_id

    def _rejected_channel_id(self, topic: str, reason: str, detail: str) -> int:
        channel_id = self._rejected_channel_ids.get((topic, reason))
        if channel_id is None:
            channel_id = self._writer.register_channel(
                topic=topic,
                message_encoding=REJECTED_ENCODING,
                schema_id=0,
                metadata={REJECTED_REASON: reason, REJECTED_DETAIL: detail[:MAX_DETAIL_CHARS]},
            )
            self._rejected_channel_ids[(topic, reason)] = channel_id
        return channel_id

    def write(self, topic: str, type_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        self._add(self._channel_id(topic, type_name), payload, log_time_ns, publish_time_ns)

    def write_rejected(self, topic: str, reason: str, detail: str, payload: bytes, log_time_ns: int) -> None:
        """Keep a payload that is not a usable message of ``topic``'s type, in the (topic, reason) channel of its own
        (see the module docstring); ``detail`` labels the channel when this is its first payload."""
        if not reason:
            raise ValueError(f"{topic}: a rejected payload needs the reason it was rejected")
        self._add(self._rejected_channel_id(topic, reason, detail), payload, log_time_ns, log_time_ns)

    def _add(self, channel_id: int, payload: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        sequence = self._sequence.get(channel_id, 0)
        self._sequence[channel_id] = sequence + 1
        self._writer.add_message(
            channel_id=channel_id,
            log_time=int(log_time_ns),
            data=bytes(payload),
            publish_time=int(publish_time_ns),
            sequence=sequence,
        )
        self.message_count += 1
        self._unflushed += 1
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval_s:
            self.flush()

    def write_message(self, topic: str, message, log_time_ns: int | None = None) -> None:
        """Convenience: serialise a protobuf message; publish time from its device clock."""
        log_time = messages.now_ns() if log_time_ns is None else log_time_ns
        self.write(
            topic, messages.type_name(message), messages.encode(message), log_time, device_time_ns(message, log_time)
        )

    def flush(self) -> None:
        self._writer.flush()
        self._last_flush = time.monotonic()
        self._unflushed = 0

    def flush_if_due(self) -> None:
        """Flush when messages wait in the open chunk for longer than the interval (data paused: nothing else would)."""
        if self._unflushed and time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> McapRecorderWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def device_time_ns(message, fallback_ns: int) -> int:
    """The device-clock time of a message (MCAP publish_time), or ``fallback_ns`` when it carries none."""
    for name in ("device_time_ns", "host_time_ns"):
        if hasattr(message, name):
            value = int(getattr(message, name))
            if value:
                return value
    if hasattr(message, "time_s") and message.time_s:
        return int(round(message.time_s * 1e9))
    return int(fallback_ns)


@dataclass
class ReadReport:
    """What :func:`read_messages` found besides the messages."""

    truncated: bool = False
    error: str = ""
    #: messages :func:`read_messages` left out, their channel carrying no msk protobuf type: (topic, reason) -> count
    left_out: Counter = field(default_factory=Counter)
    #: chunks whose bytes are damaged (CRC, compression): skipped, the chunks after them still read
    damaged_chunks: int = 0
    #: messages read, and those the file's summary says it holds (None without a readable summary)
    messages_read: int = 0
    messages_expected: int | None = None

    @property
    def messages_lost(self) -> int | None:
        """Messages the summary counts that could not be read (None when the file has no readable summary)."""
        if self.messages_expected is None:
            return None
        return max(self.messages_expected - self.messages_read - sum(self.left_out.values()), 0)

    def damage_text(self) -> str:
        """What was not read, in words ("" when everything was)."""
        said = []
        if self.damaged_chunks:
            said.append(f"{self.damaged_chunks} damaged chunk(s) skipped")
        if self.truncated:
            said.append("cut short")
        lost = self.messages_lost
        if said and lost is not None:
            said.append(f"{lost} of {self.messages_expected} messages lost")
        return "; ".join(said)


MCAP_MAGIC = b"\x89MCAP0\r\n"


def check_mcap_magic(path: Path, *, allow_cut_header: bool = False) -> None:
    """A file that does not start with MCAP's magic bytes is not a recording cut short but not a recording at all.
    ``allow_cut_header``: an empty file or a part of the magic passes (a recording being written, or killed before its
    header reached the disk)."""
    if not Path(path).is_file():
        raise InputError("MCAP file not found", path=path)
    with open(path, "rb") as stream:
        head = stream.read(len(MCAP_MAGIC))
    if allow_cut_header and MCAP_MAGIC.startswith(head):
        return
    if head != MCAP_MAGIC:
        shown = "an empty file" if not head else f"it starts with {head!r}"
        raise FileFormatError(f"not an MCAP recording ({shown}; MCAP files start with {MCAP_MAGIC!r})", path=path)


def read_messages(
    path: str | Path,
    *,
    report: ReadReport | None = None,
    tolerate_truncation: bool = True,
    include_rejected: bool = False,
) -> Iterator[RecordedMessage]:
    """Every message of an MCAP file in file order (which is recording order for files this project writes).

    A file cut short (recorder killed) yields every message of its completed chunks; ``report.truncated`` tells.
    Messages of a channel that carries no msk protobuf type (the recorder's rejected payloads, a foreign channel) are
    left out and counted in ``report.left_out``; ``include_rejected`` yields them too, with ``rejected`` saying why.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("MCAP file not found", path=path)
    check_mcap_magic(path, allow_cut_header=tolerate_truncation)
    report = report if report is not None else ReadReport()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    kinds: dict[int, tuple[str, str]] = {}  # channel id -> (type name, rejected reason)
    summary_read = False  # the file's summary, read once if a damaged chunk took channel records with it
    with open(path, "rb") as stream:
        for record in _records(stream, path, report, tolerate_truncation):
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                kinds.pop(record.id, None)
            elif isinstance(record, (DataEnd, Footer)):
                break
            elif isinstance(record, Message):
                kind = kinds.get(record.channel_id)
                if kind is None:
                    channel = channels.get(record.channel_id)
                    if channel is None and report.damaged_chunks:  # its record was in a damaged chunk
                        if not summary_read:
                            summary_read = True
                            if (summary := file_summary(path)) is not None:
                                channels = {**summary.channels, **channels}
                                schemas = {**summary.schemas, **schemas}
                        channel = channels.get(record.channel_id)
                        if channel is None:
                            continue  # no summary to name it: lost (counted as lost against the summary, if any)
                    if channel is None:
                        raise FileFormatError(f"message on unknown channel {record.channel_id}", path=path)
                    kind = kinds[record.channel_id] = channel_kind(channel, schemas.get(channel.schema_id))
                type_name, rejected = kind
                topic = channels[record.channel_id].topic
                if rejected and not include_rejected:
                    report.left_out[(topic, rejected)] += 1
                    continue
                report.messages_read += 1
                yield RecordedMessage(
                    topic=topic,
                    type_name=type_name,
                    data=bytes(record.data),
                    log_time_ns=record.log_time,
                    publish_time_ns=record.publish_time,
                    sequence=record.sequence,
                    rejected=rejected,
                )
    if report.damaged_chunks or report.truncated:  # how much that cost, when the file's summary can say
        summary = file_summary(path)
        if summary is not None and summary.statistics is not None:
            report.messages_expected = int(summary.statistics.message_count)


def _records(stream, path: Path, report: ReadReport, tolerate_truncation: bool) -> Iterator[Any]:
    """The file's records in order, each chunk's unpacked. A chunk whose bytes are damaged (its CRC or compression
    fails) is skipped and counted, and the chunks after it are read (they are whole records of known length); a
    record that cannot be read at all ends the file there (cut short)."""
    records = StreamReader(stream, validate_crcs=True, emit_chunks=True).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as error:  # noqa: BLE001 - truncation shows as various errors of the mcap package
            if not tolerate_truncation:
                raise FileFormatError(f"unreadable MCAP record: {error}", path=path) from error
            report.truncated = True
            report.error = f"{type(error).__name__}: {error}"
            return
        if not isinstance(record, Chunk):
            yield record
            continue
        try:
            unpacked = breakup_chunk(record, validate_crc=True)
        except Exception as error:  # noqa: BLE001 - a CRC mismatch or a decompression error
            if not tolerate_truncation:
                raise FileFormatError(f"damaged MCAP chunk: {error}", path=path) from error
            report.damaged_chunks += 1
            report.error = f"{type(error).__name__}: {error}"
            continue
        yield from unpacked


def file_summary(path: Path) -> Summary | None:
    """The file's summary (channels, schemas, statistics); None when it has no readable one (a file cut short: a
    summary cut short fails in many ways, struct.error, McapError, ...)."""
    try:
        with open(path, "rb") as stream:
            return make_reader(stream).get_summary()
    except Exception:  # noqa: BLE001
        return None


def recorded_sessions(path: str | Path) -> dict[str, int]:
    """The sessions whose ``msk/<session>/...`` topics a recording holds, with their message counts, in the order
    their channels appear. From the file's summary; a file cut short (no summary) is read through."""
    path = Path(path)
    if not path.is_file():
        raise InputError("MCAP file not found", path=path)
    counts: Counter[str] = Counter()
    summary = file_summary(path)
    if summary is not None and summary.statistics is not None:
        per_channel = summary.statistics.channel_message_counts
        for channel in sorted(summary.channels.values(), key=lambda c: c.id):
            if channel.topic.startswith(f"{topics.ROOT}/"):
                counts[topics.split_key(channel.topic)[0]] += per_channel.get(channel.id, 0)
        return dict(counts)
    for recorded in read_messages(path, include_rejected=True):
        if recorded.topic.startswith(f"{topics.ROOT}/"):
            counts[topics.split_key(recorded.topic)[0]] += 1
    return dict(counts)


def sessions_text(sessions: dict[str, int]) -> str:
    """e.g. ``"'rack1' (5210 messages), 'rack2' (5188 messages)"``."""
    return ", ".join(f"{name!r} ({n} messages)" for name, n in sessions.items())


def chosen_session(path: str | Path, session: str | None, flag: str = "--session") -> str | None:
    """The recorded session to report or replay: ``session``, or the only one the recording holds (None: it holds no
    msk topic). Raises :class:`InputError` naming them, and ``flag`` as the field, when ``session`` is not among them,
    or when there are several and none is named (two racks recorded into one file would otherwise be mixed into one
    athlete's sets)."""
    sessions = recorded_sessions(path)
    if session is not None and session not in sessions:
        raise InputError(
            f"the recording holds no session {session!r}; it holds {sessions_text(sessions) or 'no msk topic'}",
            path=path,
            field=flag,
            value=session,
        )
    if session is None and len(sessions) > 1:
        raise InputError(
            f"the recording holds {len(sessions)} sessions: {sessions_text(sessions)}; name one with {flag}",
            path=path,
            field=flag,
        )
    return session if session is not None else next(iter(sessions), None)


def channel_kind(channel: Channel, schema: Schema | None) -> tuple[str, str]:
    """``(type name, "")`` for a channel of an msk protobuf type; ``("", reason)`` for any other: the recorder's
    reason for a channel of rejected payloads, else what the channel carries instead."""
    reason = channel.metadata.get(REJECTED_REASON, "")
    if reason:
        return "", reason
    name = schema.name if schema is not None else ""
    if channel.message_encoding != PROTOBUF or name not in messages.MESSAGE_TYPES:
        return "", f"no msk type (encoding {channel.message_encoding!r}, schema {name!r})"
    return name, ""
