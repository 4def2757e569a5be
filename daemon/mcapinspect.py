"""Reading tools for skinmap MCAP logs: file-order reading of cut files, recovery, inspection
and a PNG snapshot of the logged surface.

All functions take paths and are used by the `skinmap` command-line tool. They read records in
FILE order with their own framing check, because a file cut by a crash has no summary and
mcap's time-ordered reader returns nothing for it. Every record is parsed with the classes of
`mcap.records`; chunks are checked against their CRC before any message in them is used, so
what is returned is always an exact prefix of what was written.

Hostile or damaged files cost bounded memory: a record (or a chunk's declared uncompressed
size) larger than `max_record_bytes` is skipped unread and named in `skipped`, chunks are
decompressed incrementally and never past their declared size, and only regular files are
opened (a FIFO, a device or a folder would block or never end).
"""

from __future__ import annotations

import io
import itertools
import json
import math
import os
import stat
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from skinmap.wire import messages as wire

from .foxglove_log import decode_protobuf
from .mcaplog import ACTIVE_SUFFIX, LOG_LEVELS, final_name, finish_writer

__all__ = [
    "NotMcapError",
    "NotRegularFileError",
    "DEFAULT_MAX_RECORD_BYTES",
    "ReadEnd",
    "LoggedMessage",
    "FileOrderMessages",
    "iter_messages_file_order",
    "RecoverReport",
    "recover",
    "TopicStats",
    "SequenceGap",
    "LogIssue",
    "InspectReport",
    "inspect",
    "SurfaceSnapshot",
    "find_surface",
    "render_surface_png",
]

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
_RECORD_HEAD = struct.Struct("<BQ")
_MiB = 1024 * 1024
# skinmapd writes chunks of `log.chunk_kb` (at most 64 MiB by its config check) and records far
# smaller, so anything larger is not from skinmapd and is refused unread.
DEFAULT_MAX_RECORD_BYTES = 64 * _MiB
_MAX_SKIPPED_LISTED = 1000

# Records that can appear in a data section and matter for reading; others are skipped.
_PARSERS: dict[int, Callable[[ReadDataStream, int], McapRecord]] = {
    Opcode.HEADER: lambda s, n: Header.read(s),
    Opcode.SCHEMA: lambda s, n: Schema.read(s),
    Opcode.CHANNEL: lambda s, n: Channel.read(s),
    Opcode.MESSAGE: lambda s, n: Message.read(s, n),
    Opcode.CHUNK: lambda s, n: Chunk.read(s),
    Opcode.ATTACHMENT: lambda s, n: Attachment.read(s),
    Opcode.METADATA: lambda s, n: Metadata.read(s),
    Opcode.DATA_END: lambda s, n: DataEnd.read(s),
    Opcode.FOOTER: lambda s, n: Footer.read(s),
}


class NotMcapError(ValueError):
    """The file does not start with the MCAP magic bytes."""


class NotRegularFileError(ValueError):
    """The path names a FIFO, a device, a socket or a folder, not a log file."""


_FILE_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
               (stat.S_ISSOCK, "a socket"))


def open_regular_file(path: str | os.PathLike[str]) -> io.BufferedReader:
    """Open `path` for reading only if it is a regular file; NotRegularFileError otherwise.

    O_NONBLOCK keeps the open itself from waiting for a FIFO's writer; the type is then
    checked on the open descriptor, so a path swapped after a check cannot slip through."""
    name = os.fspath(path)
    fd = os.open(name, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = next((what for test, what in _FILE_KINDS if test(mode)), "not a regular file")
            raise NotRegularFileError(f"{name}: is {kind}, not a regular MCAP log file")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _check_limit(max_record_bytes: int) -> int:
    if isinstance(max_record_bytes, bool) or not isinstance(max_record_bytes, int) \
            or max_record_bytes < 1024:
        raise ValueError(f"max_record_bytes must be an integer >= 1024, got {max_record_bytes!r}")
    return max_record_bytes


def _size(n: int) -> str:
    return f"{n / _MiB:.1f} MiB" if n >= _MiB else f"{n} bytes"


class _Refused(Exception):
    """A record that is skipped, the rest of the file still read."""


def _decompress_chunk(chunk: Chunk, limit: int) -> Chunk:
    """The chunk with its records uncompressed, never producing more than its declared
    uncompressed size (+1 byte, to notice a chunk that lies about it)."""
    size = chunk.uncompressed_size
    if size > limit:
        raise _Refused(f"declares {_size(size)} uncompressed, over the {_size(limit)} limit")
    want = size + 1
    if chunk.compression == "":
        data = chunk.data
    elif chunk.compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(chunk.data)
        parts, got = [], 0
        while got < want:
            piece = reader.read(want - got)
            if not piece:
                break
            parts.append(piece)
            got += len(piece)
        data = b"".join(parts)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=want)
    else:
        raise _Refused(f"unknown compression {chunk.compression!r}")
    if len(data) != size:
        what = "more than" if len(data) > size else f"{len(data)} bytes, not"
        raise _Refused(f"decompresses to {what} its declared {_size(size)}")
    return Chunk(compression="", data=data, message_end_time=chunk.message_end_time,
                 message_start_time=chunk.message_start_time,
                 uncompressed_crc=chunk.uncompressed_crc, uncompressed_size=size)


@dataclass(frozen=True)
class ReadEnd:
    """How reading a file ended."""

    complete: bool  # footer and closing magic were read: a finished file
    reason: str  # human-readable: "finished", "cut inside record at offset 1234", ...
    valid_bytes: int  # length of the prefix that was used
    file_bytes: int


class LoggedMessage(NamedTuple):
    topic: str
    schema_name: str
    message_encoding: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


@dataclass
class _Item:
    """One useful record in file order, with the channel/schema context of messages."""

    record: McapRecord
    channel: Channel | None = None
    schema: Schema | None = None


class _FileOrderReader:
    """Generator of `_Item`s; sets `self.end` once the file has been read as far as possible."""

    def __init__(self, path: str | os.PathLike[str], *,
                 max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES):
        self.path = os.fspath(path)
        self.max_record_bytes = _check_limit(max_record_bytes)
        self.end: ReadEnd | None = None
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.header: Header | None = None
        self.skipped: list[str] = []  # the first _MAX_SKIPPED_LISTED records refused
        self.skipped_count = 0

    def _finish(self, complete: bool, reason: str, valid: int, size: int) -> None:
        self.end = ReadEnd(complete, reason, valid, size)

    def _skip(self, what: str) -> None:
        self.skipped_count += 1
        if len(self.skipped) < _MAX_SKIPPED_LISTED:
            self.skipped.append(what)

    def items(self) -> Iterator[_Item]:
        with open_regular_file(self.path) as f:
            size = os.fstat(f.fileno()).st_size
            magic = f.read(len(MAGIC))
            if magic != MAGIC:
                if MAGIC.startswith(magic) or not magic.strip(b"\0"):
                    # Cut inside the magic, or a zero-filled file left by a power loss.
                    self._finish(False, "no complete MCAP header (file cut at start)", 0, size)
                    return
                raise NotMcapError(f"{self.path}: not an MCAP file (magic bytes {magic!r})")
            pos = len(MAGIC)
            in_summary = False
            while True:
                head = f.read(_RECORD_HEAD.size)
                if len(head) < _RECORD_HEAD.size:
                    what = "at a record boundary" if not head else "inside a record header"
                    self._finish(False, f"file cut {what} at offset {pos}", pos, size)
                    return
                opcode, length = _RECORD_HEAD.unpack(head)
                if opcode == 0:
                    # Opcode 0 is reserved: a zero-filled tail after a power loss.
                    self._finish(False, f"zero bytes instead of a record at offset {pos}",
                                 pos, size)
                    return
                if length > size - pos - _RECORD_HEAD.size:
                    self._finish(False, f"file cut inside a {_opcode_name(opcode)} record "
                                 f"at offset {pos}", pos, size)
                    return
                parser = _PARSERS.get(opcode)
                if in_summary and opcode != Opcode.FOOTER:
                    parser = None  # the summary only repeats what was read already
                if parser is not None and length > self.max_record_bytes:
                    self._skip(f"{_opcode_name(opcode)} record at offset {pos} skipped: "
                               f"{_size(length)}, over the {_size(self.max_record_bytes)} "
                               "limit")
                    parser = None
                if parser is None:
                    # Seek, not read: a skipped record costs no memory, however long.
                    pos += _RECORD_HEAD.size + length
                    f.seek(pos)
                    continue
                body = f.read(length)
                try:
                    record = parser(ReadDataStream(io.BytesIO(body)), length)
                    contained = self._contained(record, body)
                except _Refused as exc:
                    self._skip(f"{_opcode_name(opcode)} record at offset {pos} skipped: {exc}")
                    pos += _RECORD_HEAD.size + length
                    continue
                except Exception as exc:  # any parse failure means corrupt bytes: stop here
                    self._finish(False, f"corrupt {_opcode_name(opcode)} record at offset "
                                 f"{pos}: {exc}", pos, size)
                    return
                pos += _RECORD_HEAD.size + length
                for item in contained:
                    yield item
                if isinstance(record, DataEnd):
                    in_summary = True
                elif isinstance(record, Footer):
                    tail = f.read(len(MAGIC))
                    if tail == MAGIC:
                        self._finish(True, "finished", pos + len(MAGIC), size)
                    else:
                        self._finish(False, "closing magic missing after the footer", pos,
                                     size)
                    return

    def _contained(self, record: McapRecord, body: bytes) -> list[_Item]:
        """The items a complete record yields; raises if the record is corrupt."""
        if isinstance(record, Chunk):
            # validate_crc: a chunk whose bytes did not all reach the disk is rejected whole.
            plain = _decompress_chunk(record, self.max_record_bytes)
            return [item for r in breakup_chunk(plain, validate_crc=True)
                    for item in self._contained(r, b"")]
        if isinstance(record, Attachment):
            stored = struct.unpack_from("<I", body, len(body) - 4)[0]
            if stored and stored != zlib.crc32(body[:-4]):
                raise ValueError("attachment CRC mismatch")
        if isinstance(record, Header):
            self.header = record
        elif isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, Message):
            channel = self.channels.get(record.channel_id)
            schema = self.schemas.get(channel.schema_id) if channel else None
            return [_Item(record, channel, schema)]
        return [_Item(record)]


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode 0x{opcode:02x}"


class FileOrderMessages:
    """Iterator of `LoggedMessage` in file order; `end` (a `ReadEnd`) is set when exhausted,
    `skipped` names the records refused as over `max_record_bytes` so far."""

    def __init__(self, path: str | os.PathLike[str], *,
                 max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES):
        self._reader = _FileOrderReader(path, max_record_bytes=max_record_bytes)
        self._items = self._reader.items()

    @property
    def end(self) -> ReadEnd | None:
        return self._reader.end

    @property
    def skipped(self) -> list[str]:
        return self._reader.skipped

    @property
    def skipped_count(self) -> int:
        return self._reader.skipped_count

    def __iter__(self) -> FileOrderMessages:
        return self

    def __next__(self) -> LoggedMessage:
        for item in self._items:
            if isinstance(item.record, Message):
                return _logged(item)
        raise StopIteration


def _logged(item: _Item) -> LoggedMessage:
    msg = item.record
    assert isinstance(msg, Message)
    topic = item.channel.topic if item.channel else f"<unknown channel {msg.channel_id}>"
    encoding = item.channel.message_encoding if item.channel else ""
    schema_name = item.schema.name if item.schema else ""
    return LoggedMessage(topic, schema_name, encoding, msg.log_time, msg.publish_time, msg.data)


def iter_messages_file_order(path: str | os.PathLike[str], *,
                             max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES
                             ) -> FileOrderMessages:
    """All messages of a finished or cut MCAP file in file order, never raising on a cut or
    corrupt tail (only on a file that is not MCAP at all, or not a regular file). After the
    loop, `.end` tells how the file ended and `.skipped` which records were too large."""
    return FileOrderMessages(path, max_record_bytes=max_record_bytes)


def _skipped_lines(skipped: list[str], count: int, indent: str = "  ") -> list[str]:
    shown = skipped[:10]
    lines = [f"{indent}{line}" for line in shown]
    if count > len(shown):
        lines.append(f"{indent}... and {count - len(shown)} more records skipped")
    return lines


# --------------------------------------------------------------------------------------------
# recovery


@dataclass(frozen=True)
class RecoverReport:
    source: str
    output: str
    messages: int
    topics: dict[str, int]
    attachments: int
    metadata: int
    end: ReadEnd
    skipped: tuple[str, ...] = ()
    skipped_count: int = 0

    def format(self) -> str:
        state = "finished file" if self.end.complete else f"cut file ({self.end.reason})"
        lines = [f"recovered {self.messages} messages, {self.attachments} attachments, "
                 f"{self.metadata} metadata records from {self.source} ({state}; used "
                 f"{self.end.valid_bytes} of {self.end.file_bytes} bytes)",
                 f"written to {self.output}"]
        lines += [f"  {topic}: {count}" for topic, count in sorted(self.topics.items())]
        if self.skipped_count:
            lines.append(f"  {self.skipped_count} record(s) not recovered (too large):")
            lines += _skipped_lines(list(self.skipped), self.skipped_count, "    ")
        return "\n".join(lines)


def _default_recovered_path(path: str) -> str:
    if path.endswith(ACTIVE_SUFFIX) and not os.path.exists(final_name(path)):
        return final_name(path)
    stem = path[: -len(ACTIVE_SUFFIX)] if path.endswith(ACTIVE_SUFFIX) else (
        path[:-5] if path.endswith(".mcap") else path)
    return stem + ".recovered.mcap"


def recover(path: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None,
            *, compression: str = "zstd",
            max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES) -> RecoverReport:
    """Write a finished, indexed MCAP holding everything readable from `path` (typically a
    `.mcap.active` left by a crash). Default output: `x.mcap.active` -> `x.mcap` when that
    name is free, else `<stem>.recovered.mcap`. The source file is left untouched."""
    source = os.fspath(path)
    output = os.fspath(out_path) if out_path is not None else _default_recovered_path(source)
    if os.path.abspath(output) == os.path.abspath(source):
        raise ValueError(f"recover output {output!r} would overwrite its source")
    codecs = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
              "none": CompressionType.NONE}
    if compression not in codecs:
        raise ValueError(f"compression must be one of {sorted(codecs)}, got {compression!r}")
    reader = _FileOrderReader(source, max_record_bytes=max_record_bytes)
    items = reader.items()
    first = next(items, None)  # parse before creating anything, so a non-MCAP file fails clean
    tmp = output + ".partial"
    topics: Counter[str] = Counter()
    counts: Counter[str] = Counter()
    try:
        _write_recovered(tmp, reader, itertools.chain([first] if first else [], items),
                         codecs[compression], os.path.basename(source), topics, counts)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    os.replace(tmp, output)
    assert reader.end is not None
    return RecoverReport(source, output, sum(topics.values()), dict(topics),
                         counts["attachments"], counts["metadata"], reader.end,
                         tuple(reader.skipped), reader.skipped_count)


def _write_recovered(tmp: str, reader: _FileOrderReader, items: Iterator[_Item],
                     compression: CompressionType, source_name: str, topics: Counter[str],
                     counts: Counter[str]) -> None:
    with open(tmp, "wb") as out:
        writer = Writer(out, compression=compression)
        header = reader.header
        writer.start(profile=header.profile if header else "",
                     library=f"skinmap recover of {source_name}")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for item in items:
            rec = item.record
            if isinstance(rec, Message) and item.channel is not None:
                channel = item.channel
                if channel.id not in channel_ids:
                    schema_id = 0
                    if item.schema is not None:
                        if item.schema.id not in schema_ids:
                            schema_ids[item.schema.id] = writer.register_schema(
                                item.schema.name, item.schema.encoding, item.schema.data)
                        schema_id = schema_ids[item.schema.id]
                    channel_ids[channel.id] = writer.register_channel(
                        channel.topic, channel.message_encoding, schema_id, channel.metadata)
                writer.add_message(channel_ids[channel.id], rec.log_time, rec.data,
                                   rec.publish_time, rec.sequence)
                topics[channel.topic] += 1
            elif isinstance(rec, Attachment):
                writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type,
                                      rec.data)
                counts["attachments"] += 1
            elif isinstance(rec, Metadata):
                writer.add_metadata(rec.name, rec.metadata)
                counts["metadata"] += 1
        finish_writer(writer, counts["attachments"])
        out.flush()
        os.fsync(out.fileno())


# --------------------------------------------------------------------------------------------
# inspection


@dataclass(frozen=True)
class SequenceGap:
    topic: str
    after_seq: int
    next_seq: int
    missing: int  # messages missing at the expected step; 0 repeat, negative jump back
    t_ns: int
    expected_step: int = 1  # seq step between two messages of this topic when none is lost


@dataclass(frozen=True)
class LogIssue:
    t_ns: int
    source: str  # "/log" or "/status"
    level: str  # "WARNING", "ERROR", "FATAL"
    text: str


@dataclass
class TopicStats:
    topic: str
    schema_name: str
    message_encoding: str
    count: int = 0
    bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    time_gaps: list[tuple[int, int]] = field(default_factory=list)  # (from, to) log times
    out_of_order: int = 0
    expected_hz: float | None = None  # the topic's rate by the logged config (None: unknown)
    gap_threshold_s: float = 0.0  # the silence that counts as a gap on this topic

    @property
    def rate_hz(self) -> float:
        span = self.last_ns - self.first_ns
        return (self.count - 1) / (span * 1e-9) if self.count > 1 and span > 0 else 0.0


@dataclass
class InspectReport:
    path: str
    end: ReadEnd
    library: str
    topics: dict[str, TopicStats]
    sequence_gaps: list[SequenceGap]
    issues: list[LogIssue]
    metadata: dict[str, dict[str, str]]
    attachments: list[str]
    gap_threshold_s: float
    skipped: list[str] = field(default_factory=list)  # records refused as too large
    skipped_count: int = 0
    rates_source: str = ""  # where the expected rates come from

    @property
    def first_ns(self) -> int | None:
        return min((s.first_ns for s in self.topics.values()), default=None)

    @property
    def last_ns(self) -> int | None:
        return max((s.last_ns for s in self.topics.values()), default=None)

    def format(self, max_lines: int = 20) -> str:
        """The report: state, then what is wrong (errors and warnings from /log and /status,
        messages missing beyond the configured decimation, silences beyond each topic's own
        rate), then the topic table. At most `max_lines` lines of each kind are listed."""
        e = self.end
        state = "finished" if e.complete else f"NOT finished: {e.reason}"
        out = [f"{self.path}", f"  state: {state} ({e.valid_bytes} of {e.file_bytes} bytes "
               f"readable)", f"  writer: {self.library or '?'}"]
        if self.first_ns is not None and self.last_ns is not None:
            out.append(f"  span: {_utc(self.first_ns)} .. {_utc(self.last_ns)} "
                       f"({(self.last_ns - self.first_ns) * 1e-9:.3f} s)")
        t0 = self.first_ns or 0

        def capped(lines: list[str], what: str) -> list[str]:
            if len(lines) <= max_lines:
                return lines
            return lines[:max_lines] + [f"  ... and {len(lines) - max_lines} more {what}"]

        ranked = sorted(self.issues, key=lambda i: (-_LEVEL_RANK.get(i.level, 0), i.t_ns))
        out += capped([f"  {i.level} in {i.source} at t+{(i.t_ns - t0) * 1e-9:.3f} s: {i.text}"
                       for i in ranked], "warnings/errors")
        seq_lines = []
        for g in self.sequence_gaps:
            what = (f"{g.missing} missing" if g.missing > 0 else
                    "repeated" if g.missing == 0 else "jumped back: scanner restarted")
            step = f", expected step {g.expected_step}" if g.expected_step != 1 else ""
            seq_lines.append(f"  seq gap on {g.topic}: {g.after_seq} -> {g.next_seq} ({what}"
                             f"{step}) at t+{(g.t_ns - t0) * 1e-9:.3f} s")
        out += capped(seq_lines, "seq gaps")
        gap_lines = []
        for st in sorted(self.topics.values(), key=lambda st: st.topic):
            for a, b in st.time_gaps:
                gap_lines.append(f"  time gap on {st.topic}: {(b - a) * 1e-9:.3f} s after "
                                 f"t+{(a - t0) * 1e-9:.3f} s (threshold "
                                 f"{st.gap_threshold_s:.3g} s)")
            if st.out_of_order:
                gap_lines.append(f"  {st.topic}: {st.out_of_order} messages earlier than the "
                                 "one before")
        out += capped(gap_lines, "time gaps")
        if self.skipped_count:
            out.append(f"  {self.skipped_count} record(s) skipped unread:")
            out += _skipped_lines(self.skipped, self.skipped_count, "    ")
        if not (self.sequence_gaps or self.issues or self.skipped_count or
                any(st.time_gaps or st.out_of_order for st in self.topics.values())):
            out.append("  no gaps, warnings or errors found")
        if self.rates_source:
            out.append(f"  expected rates: {self.rates_source}")
        if self.metadata:
            out.append("  metadata: " + ", ".join(sorted(self.metadata)))
        if self.attachments:
            out.append("  attachments: " + ", ".join(self.attachments))
        out.append(f"  {'topic':<18} {'count':>7} {'rate Hz':>9} {'expect':>7} {'bytes':>11}  "
                   "schema")
        for st in sorted(self.topics.values(), key=lambda st: st.topic):
            expect = "" if st.expected_hz is None else f"{st.expected_hz:g}"
            out.append(f"  {st.topic:<18} {st.count:>7} {st.rate_hz:>9.2f} {expect:>7} "
                       f"{st.bytes:>11}  {st.schema_name} ({st.message_encoding})")
        return "\n".join(out)


_LEVEL_RANK = {"FATAL": 5, "ERROR": 4, "WARNING": 3}


def _utc(t_ns: int) -> str:
    import datetime as dt

    return dt.datetime.fromtimestamp(t_ns / 1e9, dt.timezone.utc).isoformat(
        timespec="milliseconds").replace("+00:00", "Z")


_LEVEL_NAMES = {v: k for k, v in LOG_LEVELS.items()}
_BAD_STATES = {"error", "fault", "failed", "warning", "degraded", "fatal"}


def _status_issues(t_ns: int, status: Any) -> list[LogIssue]:
    """Warnings/errors a /status object reports: non-empty error/warning fields, a false
    health flag, or a state/level naming an error."""
    if not isinstance(status, dict):
        return []
    found = []
    for key, level in (("error", "ERROR"), ("errors", "ERROR"), ("last_error", "ERROR"),
                       ("warning", "WARNING"), ("warnings", "WARNING")):
        if status.get(key):
            found.append(LogIssue(t_ns, "/status", level, f"{key}: {status[key]}"))
    for key in ("healthy", "ok"):
        if status.get(key) is False:
            found.append(LogIssue(t_ns, "/status", "WARNING", f"{key} is false"))
    for key in ("state", "level"):
        value = status.get(key)
        if isinstance(value, str) and value.lower() in _BAD_STATES:
            level = "WARNING" if value.lower() in ("warning", "degraded") else "ERROR"
            found.append(LogIssue(t_ns, "/status", level, f"{key}: {value}"))
    return found


def inspect(path: str | os.PathLike[str], *, gap_threshold_s: float = 1.0,
            max_issues: int = 1000,
            max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES) -> InspectReport:
    """Summarise a finished or cut log: per-topic counts, rates, first/last times, time gaps
    longer than `gap_threshold_s`, sequence gaps on topics that carry a frame seq, and
    warnings/errors from /log and /status (at most `max_issues` listed). Records over
    `max_record_bytes` are skipped and listed."""
    if not gap_threshold_s > 0:
        raise ValueError(f"gap_threshold_s must be > 0, got {gap_threshold_s!r}")
    reader = _FileOrderReader(path, max_record_bytes=max_record_bytes)
    topics: dict[str, TopicStats] = {}
    times: dict[str, list[int]] = {}
    seqs: dict[str, list[tuple[int, int]]] = {}  # topic -> [(seq, log time)]
    issues: list[LogIssue] = []
    metadata: dict[str, dict[str, str]] = {}
    attachments: list[str] = []
    config_text: str | None = None
    for item in reader.items():
        rec = item.record
        if isinstance(rec, Metadata):
            metadata[rec.name] = rec.metadata
            continue
        if isinstance(rec, Attachment):
            attachments.append(rec.name)
            continue
        if not isinstance(rec, Message):
            continue
        m = _logged(item)
        stats = topics.get(m.topic)
        if stats is None:
            stats = topics[m.topic] = TopicStats(m.topic, m.schema_name, m.message_encoding,
                                                 first_ns=m.log_time_ns, last_ns=m.log_time_ns)
        elif m.log_time_ns < stats.last_ns:
            stats.out_of_order += 1
        times.setdefault(m.topic, []).append(m.log_time_ns)
        stats.count += 1
        stats.bytes += len(m.data)
        stats.first_ns = min(stats.first_ns, m.log_time_ns)
        stats.last_ns = max(stats.last_ns, m.log_time_ns)
        if item.channel is not None and item.channel.metadata.get("sequence") == "frame":
            seqs.setdefault(m.topic, []).append((rec.sequence, m.log_time_ns))
        if m.topic == "/config" and config_text is None:
            config_text = _config_text(m.data)
        if len(issues) < max_issues:
            issues.extend(_message_issues(m))
    assert reader.end is not None
    rates, source = expected_rates(config_text)
    seq_gaps: list[SequenceGap] = []
    for topic, stats in topics.items():
        hz = rates.get(topic)
        stats.expected_hz = hz
        if topic in _EVENT_TOPICS:
            continue
        t = np.asarray(times[topic], dtype=np.int64)
        dt = np.diff(t)
        if hz:
            period_s = 1.0 / hz
        elif dt.size:
            period_s = float(np.median(dt)) * 1e-9  # unknown topic: its own typical interval
        else:
            period_s = 0.0
        # A silence counts when it is longer than the threshold and than 2.5 periods of the
        # topic's own rate: a 1 Hz topic is not "gapped" every second.
        stats.gap_threshold_s = max(gap_threshold_s, 2.5 * period_s)
        for k in np.flatnonzero(dt > stats.gap_threshold_s * 1e9):
            stats.time_gaps.append((int(t[k]), int(t[k + 1])))
        if topic in seqs:
            seq_gaps += _sequence_gaps(topic, seqs[topic], rates.get(("seq_step", topic)))
    seq_gaps.sort(key=lambda g: (g.t_ns, g.topic))
    return InspectReport(os.fspath(path), reader.end,
                         reader.header.library if reader.header else "", topics, seq_gaps,
                         issues[:max_issues], metadata, attachments, gap_threshold_s,
                         reader.skipped, reader.skipped_count, source)


_EVENT_TOPICS = {"/log", "/config"}


def _config_text(data: bytes) -> str | None:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):
        return None
    text = doc.get("config_text") if isinstance(doc, dict) else None
    return text if isinstance(text, str) else None


def expected_rates(config_text: str | None) -> tuple[dict[Any, float], str]:
    """Each topic's rate (Hz) and each seq topic's step under the logged config (the daemon's
    decimation): ({topic: hz, ("seq_step", topic): step}, where that came from). Without a
    usable config the rates are unknown and gaps are judged by each topic's own median."""
    if config_text is None:
        return {}, "unknown (no /config in the file): each topic judged by its own median"
    try:
        import tomllib

        from skinmap.daemon.config import ConfigError, parse_config

        cfg = parse_config(tomllib.loads(config_text), source="<logged config>",
                           text=config_text)
    except (ValueError, ConfigError, RecursionError) as exc:
        return {}, (f"unknown (the logged config does not parse: {exc}); each topic judged "
                    "by its own median")
    scan = float(cfg.device.scan_rate_hz)
    out_hz = min(float(cfg.output.rate_hz) or scan, scan)  # 0 = every scan
    surf_hz = min(float(cfg.log.surface_rate_hz) or out_hz, out_hz)
    status_hz = float(cfg.output.status_rate_hz)
    rates: dict[Any, float] = {"/raw": scan, "/status": status_hz}
    for topic in ("/elements", "/elements/poses", "/elements/plot", "/strains", "/strains/plot",
                  "/scene"):
        rates[topic] = out_hz
    for topic in ("/surface", "/surface/nodes", "/tf"):
        rates[topic] = surf_hz
    for topic in ("/strains", "/strains/plot"):
        rates[("seq_step", topic)] = max(1, round(scan / out_hz))
    for topic in ("/surface", "/surface/nodes"):
        rates[("seq_step", topic)] = max(1, round(scan / surf_hz))
    return rates, (f"from the logged config: scans {scan:g} Hz, processed {out_hz:g} Hz (seq "
                   f"step {rates[('seq_step', '/strains')]}), logged surfaces {surf_hz:g} Hz "
                   f"(seq step {rates[('seq_step', '/surface')]}), status {status_hz:g} Hz")


def _sequence_gaps(topic: str, seq_times: list[tuple[int, int]],
                   expected: float | None) -> list[SequenceGap]:
    """Messages missing on a seq topic at the expected step (the config's decimation, or the
    topic's median step when the config is unknown). The decimation goes by host time, so a
    step of 4 or 6 where 5 is expected loses nothing: messages count as missing only when the
    step is nearer two or more expected steps than one."""
    seq = np.array([sq for sq, _ in seq_times], dtype=np.int64)
    steps = np.diff(seq) % 2**32
    if expected is None:
        forward = steps[(steps > 0) & (steps < 2**31)]
        expected = float(np.median(forward)) if forward.size else 1.0
    expected_step = max(1, int(round(expected)))
    gaps = []
    for k, step in enumerate(steps.tolist()):
        if step == 0:
            missing = 0
        elif step >= 2**31:
            missing = step - 2**32 - 1  # backwards: a restarted scanner
        else:
            missing = int(round(step / expected_step)) - 1
            if missing <= 0:
                continue
        gaps.append(SequenceGap(topic, int(seq[k]), int(seq[k + 1]), missing,
                                seq_times[k + 1][1], expected_step))
    return gaps


_MAX_ISSUE_TEXT = 500


def _clip(text: str) -> str:
    return text if len(text) <= _MAX_ISSUE_TEXT else text[:_MAX_ISSUE_TEXT] + "..."


def _message_issues(m: LoggedMessage) -> list[LogIssue]:
    if m.topic == "/log" and m.message_encoding == "protobuf":
        try:
            entry = decode_protobuf(m.schema_name, m.data)
        except Exception:  # noqa: BLE001 - protobuf raises its own DecodeError
            return [LogIssue(m.log_time_ns, m.topic, "ERROR", "message is not a valid "
                             f"{m.schema_name or 'protobuf'} record")]
        if entry.level >= LOG_LEVELS["WARNING"]:
            name = _LEVEL_NAMES.get(entry.level, str(entry.level))
            return [LogIssue(m.log_time_ns, "/log", name, _clip(f"[{entry.name}] {entry.message}"))]
        return []
    if m.topic not in ("/log", "/status") or m.message_encoding != "json":
        return []
    try:
        obj = json.loads(m.data)
        if m.topic == "/status":
            return [LogIssue(i.t_ns, i.source, i.level, _clip(i.text))
                    for i in _status_issues(m.log_time_ns, obj)]
        level = obj.get("level", 0) if isinstance(obj, dict) else 0
        if isinstance(level, int) and level >= LOG_LEVELS["WARNING"]:
            name = _LEVEL_NAMES.get(level, str(level))
            return [LogIssue(m.log_time_ns, "/log", name,
                             _clip(f"[{obj.get('name', '')}] {obj.get('message', '')}"))]
        return []
    except RecursionError:
        # json and str() recurse per nesting level: one such record must not end the report.
        return [LogIssue(m.log_time_ns, m.topic, "ERROR", f"unreadable record "
                         f"({len(m.data)} bytes): JSON nested too deeply to read")]
    except ValueError:
        return [LogIssue(m.log_time_ns, m.topic, "ERROR", "message is not valid JSON")]


# --------------------------------------------------------------------------------------------
# surface snapshot


@dataclass(frozen=True)
class SurfaceSnapshot:
    t_ns: int
    t_rel_s: float  # seconds after the first message of the file
    seq: int | None
    nodes: np.ndarray | None  # (N, M, 3) mm
    points: np.ndarray | None  # (P, 3) mm
    sigma: np.ndarray | None = None  # (N, M) mm, node 1-s.d. uncertainty
    elements: wire.ElementsMessage | None = None  # the elements logged nearest that time


def find_surface(path: str | os.PathLike[str], t_s: float | None = None) -> SurfaceSnapshot:
    """The logged surface nearest `t_s` seconds after the file's first message (the last one
    when `t_s` is None): nodes from `/surface/nodes`, points from `/surface` at that time."""
    if t_s is not None and not math.isfinite(t_s):
        raise ValueError(f"t_s must be a finite number of seconds, got {t_s!r}")
    first_ns: int | None = None
    best: dict[str, LoggedMessage] = {}
    best_err: dict[str, float] = {}
    for m in iter_messages_file_order(path):
        if first_ns is None:
            first_ns = m.log_time_ns
        if m.topic not in ("/surface/nodes", "/surface", "/elements"):
            continue
        err = 0.0 if t_s is None else abs((m.log_time_ns - first_ns) * 1e-9 - t_s)
        if t_s is None or err <= best_err.get(m.topic, math.inf):
            best[m.topic], best_err[m.topic] = m, err
    elements_msg = best.pop("/elements", None)
    key = "/surface/nodes" if "/surface/nodes" in best else "/surface"
    if key not in best or first_ns is None:
        raise ValueError(f"{os.fspath(path)}: no /surface or /surface/nodes messages")
    chosen = best[key]
    nodes = seq = points = sigma = None
    if key == "/surface/nodes":
        surface = wire.decode_surface(chosen.data)
        seq, nodes = surface.seq, surface.nodes * 1e3
        points = surface.cloud.astype(np.float64) * 1e3 if len(surface.cloud) else None
        sigma = surface.uncertainty * 1e3
    else:
        cloud = decode_protobuf(chosen.schema_name, chosen.data)
        raw = np.frombuffer(cloud.data, dtype="<f4")
        points = raw[: len(raw) // 3 * 3].reshape(-1, 3).astype(np.float64) * 1e3
    elements = None
    if elements_msg is not None:
        try:
            elements = wire.decode_elements(elements_msg.data)
        except wire.MessageError:
            elements = None  # drawn without elements; inspect names unusable records
    return SurfaceSnapshot(chosen.log_time_ns, (chosen.log_time_ns - first_ns) * 1e-9, seq,
                           nodes, points, sigma, elements)


def render_surface_png(path: str | os.PathLike[str], t_s: float | None,
                       out_png: str | os.PathLike[str]) -> SurfaceSnapshot:
    """Draw the logged surface nearest `t_s` (seconds after the first message; None = last)
    in 3D to `out_png`. Returns the snapshot drawn."""
    snap = find_surface(path, t_s)
    # Figure + Agg canvas directly: no global backend switch, works without a display.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 5.5), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    every = np.concatenate([a.reshape(-1, 3) for a in (snap.nodes, snap.points)
                            if a is not None])
    if snap.nodes is not None:
        x, y, z = (snap.nodes[..., k] for k in range(3))
        if snap.sigma is not None and min(snap.nodes.shape[:2]) >= 2:
            # Faces coloured by node σ (µm), with a colorbar: where the shape is less certain.
            from matplotlib import cm, colors

            sig_um = snap.sigma * 1e3
            norm = colors.Normalize(vmin=0.0, vmax=max(float(np.nanmax(sig_um)), 1e-3))
            ax.plot_surface(x, y, z, facecolors=cm.viridis(norm(sig_um)), edgecolor="k",
                            linewidth=0.3, alpha=0.85, shade=False)
            mappable = cm.ScalarMappable(norm=norm, cmap="viridis")
            fig.colorbar(mappable, ax=ax, shrink=0.6, pad=0.1, label="node σ, 1 s.d. (µm)")
        elif min(snap.nodes.shape[:2]) >= 2:
            ax.plot_surface(x, y, z, cmap="viridis", edgecolor="k", linewidth=0.3, alpha=0.85)
        else:
            ax.plot(x.ravel(), y.ravel(), z.ravel(), "o-")
    if snap.points is not None:
        p = snap.points[:: max(1, len(snap.points) // 5000)]
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=1.5, c="tab:red", alpha=0.3)
    el = snap.elements
    if el is not None and el.count:
        pos, nrm = el.positions * 1e3, el.normals
        ok = np.isfinite(pos).all(axis=1) & np.isfinite(nrm).all(axis=1)
        valid = ok & el.valid
        span = float(np.ptp(every, axis=0).max()) if len(every) else 1.0
        arrow = 0.08 * max(span, 1.0)
        for mask, colour, label in ((valid, "tab:green", "element, VALID"),
                                    (ok & ~el.valid, "tab:orange", "element, not VALID")):
            if mask.any():
                ax.quiver(pos[mask, 0], pos[mask, 1], pos[mask, 2], nrm[mask, 0], nrm[mask, 1],
                          nrm[mask, 2], length=arrow, color=colour, linewidth=0.8, label=label)
                ax.scatter(pos[mask, 0], pos[mask, 1], pos[mask, 2], s=6, c=colour)
        if ok.any():
            every = np.concatenate([every, pos[ok]])
            ax.legend(loc="upper left", fontsize=7)
    lo, hi = every.min(axis=0), every.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        setter(c - half, c + half)  # equal scale so curvature is not distorted
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    seq = "" if snap.seq is None else f", seq {snap.seq}"
    if snap.sigma is not None and np.isfinite(snap.sigma).any():
        seq += f", node σ {np.nanmin(snap.sigma) * 1e3:.1f}..{np.nanmax(snap.sigma) * 1e3:.1f} µm"
    if snap.elements is not None:
        seq += f", {int(snap.elements.valid.sum())}/{snap.elements.count} elements VALID"
    ax.set_title(f"{os.path.basename(os.fspath(path))}\nt+{snap.t_rel_s:.3f} s{seq}",
                 fontsize=9)
    fig.savefig(os.fspath(out_png), format="png")
    return snap
