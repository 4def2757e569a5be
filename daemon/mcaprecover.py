"""Recovery of a cut skinmap MCAP log: everything readable, written as a finished, indexed file."""

from __future__ import annotations

import itertools
import os
from collections import Counter
from dataclasses import dataclass
from typing import Iterator

from mcap.records import Attachment, Message, Metadata
from mcap.writer import CompressionType, Writer

from skinmap.daemon.mcapfile import finish_writer
from skinmap.daemon.mcapread import (DEFAULT_MAX_RECORD_BYTES, FileOrderReader, ReadEnd, _Item,
                                     skipped_lines)
from skinmap.daemon.rotation import ACTIVE_SUFFIX, final_name

__all__ = ["RecoverReport", "recover"]


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
            lines += skipped_lines(list(self.skipped), self.skipped_count, "    ")
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
    reader = FileOrderReader(source, max_record_bytes=max_record_bytes)
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


def _write_recovered(tmp: str, reader: FileOrderReader, items: Iterator[_Item],
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
