"""Reading skinmap MCAP logs in FILE order, including files cut by a crash.

A file cut by a crash has no summary, and mcap's time-ordered reader returns nothing for it;
this reader reads records in file order with its own framing check. Every record is parsed
with the classes of `mcap.records`; chunks are checked against their CRC before any message in
them is used, so what is returned is always an exact prefix of what was written.

Hostile or damaged files cost bounded memory: a record (or a chunk's declared uncompressed
size) larger than `max_record_bytes` is skipped unread and named in `skipped`, chunks are
decompressed incrementally and never past their declared size, and only regular files are
opened (a FIFO, a device or a folder would block or never end).

Recovery of a cut file: `skinmap.daemon.mcaprecover`; inspection: `skinmap.daemon.mcapinspect`;
the PNG picture: `skinmap.daemon.mcapsnapshot`.
"""

from __future__ import annotations

import io
import os
import stat
import struct
import zlib
from dataclasses import dataclass, field
from typing import Callable, Iterator, NamedTuple

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

__all__ = [
    "NotMcapError",
    "NotRegularFileError",
    "DEFAULT_MAX_RECORD_BYTES",
    "ReadEnd",
    "LoggedMessage",
    "FileOrderReader",
    "FileOrderMessages",
    "iter_messages_file_order",
    "open_regular_file",
    "skipped_lines",
    "logged_message",
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


class FileOrderReader:
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
        self._reader = FileOrderReader(path, max_record_bytes=max_record_bytes)
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
                return logged_message(item)
        raise StopIteration


def logged_message(item: _Item) -> LoggedMessage:
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


def skipped_lines(skipped: list[str], count: int, indent: str = "  ") -> list[str]:
    shown = skipped[:10]
    lines = [f"{indent}{line}" for line in shown]
    if count > len(shown):
        lines.append(f"{indent}... and {count - len(shown)} more records skipped")
    return lines


