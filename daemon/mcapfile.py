"""One MCAP file being written, for the rotating logger (`skinmap.daemon.mcaplog`): the writer
over a stream that writes fully and counts its bytes, the schemas and channels registered in
the file, the messages of the chunk still open, and finishing (summary, fsync, rename).
"""
from __future__ import annotations

import errno
import os
from typing import IO, BinaryIO, cast

from mcap.writer import CompressionType, IndexType, Writer

from skinmap.daemon.mcapschema import TopicSpec
from skinmap.daemon.rotation import final_name

__all__ = ["McapFile", "CountingFile", "default_open", "finish_writer", "fsync_directory", "COMPRESSION"]

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def finish_writer(writer: Writer, attachments: int) -> None:
    """``writer.finish()``, leaving out the attachment index of a file without attachments:
    mcap's Writer writes a summary offset for the empty group, which ``pymcap-cli doctor``
    rightly reports as an error."""
    if not attachments:
        writer._Writer__index_types &= ~IndexType.ATTACHMENT  # type: ignore[attr-defined]
    writer.finish()


def default_open(path: str) -> BinaryIO:
    # Unbuffered: every write reaches the OS at once, so a storage error surfaces in the call
    # that caused it, never later from a buffer flush.
    return open(path, "xb", buffering=0)


def fsync_directory(directory: str) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # some file systems do not allow opening folders; the data is synced
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class CountingFile:
    """Write-only stream for mcap.Writer: writes fully (loops on short writes), counts bytes
    and keeps its own position so no OS call is needed for tell()."""

    def __init__(self, raw: BinaryIO):
        self.raw = raw
        self.position = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data).cast("B")
        total = len(view)
        while view:
            n = self.raw.write(view)
            if not n:
                raise OSError(errno.EIO, "short write: the file accepted no more bytes")
            view = view[n:]
        self.position += total
        return total

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        self.raw.flush()

    def fsync(self) -> None:
        self.raw.flush()
        os.fsync(self.raw.fileno())

    def close(self) -> None:
        self.raw.close()


class McapFile:
    """A file being written. Storage errors propagate as OSError; the owner then abandons it.

    `pending_messages` are in the open chunk (not on disk yet); `sync()` flushes, or fsyncs
    with `fsync_chunk`."""

    def __init__(self, path: str, raw: BinaryIO, *, chunk_size: int, compression: str, fsync_chunk: bool) -> None:
        self.path = path
        self.stream = CountingFile(raw)
        # mcap's Writer calls only write, tell and flush, which CountingFile provides.
        self.writer = Writer(cast(IO[bytes], self.stream), chunk_size=chunk_size,
                             compression=COMPRESSION[compression])
        self.fsync_chunk = fsync_chunk
        self.channels: dict[str, int] = {}
        self.schemas: dict[tuple[str, str, bytes], int] = {}
        self.opened_mono = 0
        self.chunk_opened_mono: int | None = None
        self.pending_bytes = 0
        self.pending_messages = 0
        self.attachments = 0

    def size(self) -> int:
        """Bytes written plus an estimate of the open chunk's."""
        return self.stream.position + self.pending_bytes

    def channel_id(self, spec: TopicSpec) -> int:
        channel = self.channels.get(spec.topic)
        if channel is None:
            key = (spec.schema_name, spec.schema_encoding, spec.schema_data)
            schema = self.schemas.get(key)
            if schema is None:
                schema = self.writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
                self.schemas[key] = schema
                self.pending_bytes += len(spec.schema_data) + 64
            channel = self.writer.register_channel(spec.topic, spec.message_encoding, schema,
                                                   spec.channel_metadata())
            self.channels[spec.topic] = channel
            self.pending_bytes += 64
        return channel

    def add(self, spec: TopicSpec, t_ns: int, data: bytes, seq: int | None) -> bool:
        """Add a message; True if the writer emitted a chunk (holding every pending message)."""
        channel = self.channel_id(spec)
        before = self.stream.position
        try:
            self.writer.add_message(channel_id=channel, log_time=t_ns, publish_time=t_ns, data=data,
                                    sequence=0 if seq is None else seq % 2**32)
        except OSError:
            self.pending_messages += 1  # it was in the chunk whose write failed
            raise
        self.pending_messages += 1
        self.pending_bytes += len(data) + 31
        return self.stream.position != before

    def chunk_done(self) -> int:
        """After a chunk was emitted: sync it; the number of messages it held."""
        held, self.pending_messages, self.pending_bytes = self.pending_messages, 0, 0
        self.chunk_opened_mono = None
        self.sync()
        return held

    def flush_chunk(self) -> int:
        """Emit the open chunk; the number of messages it held."""
        self.writer.flush()
        return self.chunk_done()

    def sync(self) -> None:
        if self.fsync_chunk:
            self.stream.fsync()
        else:
            self.stream.flush()

    def end_writer(self) -> int:
        """Write the summary and index; the number of messages that were pending."""
        finish_writer(self.writer, self.attachments)
        held, self.pending_messages, self.pending_bytes = self.pending_messages, 0, 0
        return held

    def close_and_rename(self, fsync: bool) -> str:
        """After `end_writer`: close, rename to the finished name; that name."""
        if fsync:
            self.stream.fsync()
        self.stream.close()
        done = final_name(self.path)
        os.replace(self.path, done)
        return done

    def close_quietly(self) -> None:
        """Close an abandoned file as far as possible (the cut file stays for recovery)."""
        try:
            self.stream.close()
        except OSError:
            pass
