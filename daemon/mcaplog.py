"""Rotating, crash-safe MCAP logger for skinmapd: `McapLogger`, the MCAP `LogSink`.

Everything the daemon sees and computes is written to chunked, compressed MCAP files so that a
session can be inspected afterwards and replayed bit-exactly (`/raw` holds the serial frames
exactly as received). See docs/logging.md for the topics, layouts and guarantees.

What is written is defined in `skinmap.daemon.mcapschema` (topics, schemas, payload codecs);
when a file ends and what it is called, by a `skinmap.daemon.rotation.RotationPolicy`. The
writer is synchronous and NOT thread-safe: the daemon calls it from one log thread.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any, BinaryIO, Callable, Mapping

import numpy as np

from skinmap.wire import messages
from skinmap.daemon.logsink import LogSink, LogStorageError
from skinmap.daemon.mcapfile import COMPRESSION, McapFile, default_open, fsync_directory
from skinmap.daemon.mcapschema import TOPICS, TopicSpec, as_payload, check_seq, device_topic, log_message, \
    to_json, wire_views
from skinmap.daemon.rotation import RotationPolicy

__all__ = ["LogStorageError", "McapLogger"]

MiB = 1024 * 1024
LIBRARY = "skinmap.daemon.mcaplog"


_FSYNC_POLICIES = ("chunk", "close", "never")


class McapLogger(LogSink):
    """Rotating MCAP writer. Synchronous and not thread-safe: call it from one thread.

    `rotation` decides when a file ends and names the files (`basename`, `max_bytes` and
    `max_seconds` are a shorthand for `RotationPolicy(basename, max_bytes, max_seconds)`):
    `<basename>-<UTC yyyymmddThhmmssZ>-<index:04d>.mcap.active` while being written, renamed
    to `.mcap` when finished (rotation or close). The first file is opened
    lazily by the first logging call. Each file stands alone: it repeats the start metadata,
    the last configuration/calibration and every schema/channel it uses.

    Crash safety: with `fsync="chunk"` every chunk is flushed and fsynced as soon as it is
    written, and an open chunk is closed once it is `max_chunk_age_s` old (checked on each
    call, by `tick()` and by `flush()`), so a SIGKILL or power loss loses at most the
    unfinished chunk.

    Storage errors raise `LogStorageError` from the call that hit them; the logger then drops
    messages (counted in `messages_dropped`) until `retry_interval_s` has passed, when the next
    call tries to open a fresh file. Messages that may not have reached the disk because of
    the error (the unfinished chunk of the abandoned file, the message being written) are
    counted in `messages_lost`. A file cut by an error stays as `.mcap.active` and is
    readable with `skinmap.daemon.mcaprecover.recover`.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        rotation: RotationPolicy | None = None,
        basename: str | None = None,
        max_bytes: int | None = None,
        max_seconds: float | None = None,
        chunk_size: int = 512 * 1024,
        max_chunk_age_s: float = 1.0,
        compression: str = "zstd",
        fsync: str = "chunk",
        metadata: Mapping[str, Any] | None = None,
        retry_interval_s: float = 5.0,
        create_directory: bool = False,
        clock: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], int] = time.monotonic_ns,
        open_file: Callable[[str], BinaryIO] = default_open,
    ):
        if compression not in COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(COMPRESSION)}, "
                             f"got {compression!r}")
        if compression == "lz4":
            try:
                import lz4.frame  # noqa: F401
            except ImportError:
                raise ValueError("compression 'lz4' needs the lz4 package, which is not "
                                 "installed; use 'zstd'") from None
        if fsync not in _FSYNC_POLICIES:
            raise ValueError(f"fsync must be one of {_FSYNC_POLICIES}, got {fsync!r}")
        if rotation is None:
            rotation = RotationPolicy("skinmap" if basename is None else basename,
                                      256 * MiB if max_bytes is None else max_bytes,
                                      3600.0 if max_seconds is None else max_seconds)
        elif (basename, max_bytes, max_seconds) != (None, None, None):
            raise ValueError("give either rotation or basename/max_bytes/max_seconds, not both")
        if not isinstance(chunk_size, int) or chunk_size < 1:
            raise ValueError(f"chunk_size must be an integer >= 1, got {chunk_size!r}")
        for name, value in (("max_chunk_age_s", max_chunk_age_s),
                            ("retry_interval_s", retry_interval_s)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        self.directory = os.fspath(directory)
        self.rotation = rotation
        self.chunk_size = chunk_size
        self.max_chunk_age_s = float(max_chunk_age_s)
        self.compression = compression
        self.fsync_policy = fsync
        # MCAP metadata values are strings; anything else is stored as JSON.
        self.metadata = {
            str(k): v if isinstance(v, str) else to_json(v, f"metadata[{k!r}]").decode()
            for k, v in (metadata or {}).items()
        }
        self.retry_interval_s = float(retry_interval_s)
        self.create_directory = create_directory
        self._clock = clock
        self._monotonic = monotonic
        self._open_file = open_file

        self._extra_topics: dict[str, TopicSpec] = {}
        self._config: tuple[int, str, Any] | None = None

        self._file: McapFile | None = None  # the file being written

        self._retry_at: int | None = None
        self.last_error: LogStorageError | None = None

        self._bytes_in_closed_files = 0
        self.messages_written = 0
        self.messages_flushed = 0
        self.messages_dropped = 0
        self.messages_lost = 0
        self.files_finished = 0
        self.finished_paths: list[str] = []
        self.abandoned_paths: list[str] = []
        self._closed = False

    # ---------------------------------------------------------------- properties

    @property
    def healthy(self) -> bool:
        """False after a storage error until a file has been opened again."""
        return self.last_error is None

    @property
    def bytes_written(self) -> int:
        """Bytes written to log files so far (all files, including the current one)."""
        return self._bytes_in_closed_files + (self._file.stream.position if self._file else 0)

    @property
    def current_path(self) -> str | None:
        """The `.mcap.active` file being written, or None."""
        return self._file.path if self._file else None

    # ---------------------------------------------------------------- typed helpers

    def log_raw_frame(self, t_ns: int, data: bytes) -> None:
        """`/raw`: one serial frame, bytes exactly as received."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"raw frame must be bytes, got {type(data).__name__}")
        self._log(TOPICS["/raw"], t_ns, bytes(data))

    def log_strains(self, t_ns: int, payload: bytes, lead: bool = False, *, device: str | None = None) -> None:
        """`/strains`: a wire strains message (skinmap.wire.messages.encode_strains), and its
        plottable view `/strains/plot`; ``lead``: a lead scan's, `/strains/lead` alone. With
        `device`, under `/<device>/...`."""
        kind = "lead" if lead else "strains"
        self._log_views(wire_views(kind, as_payload(kind, payload), t_ns, device))

    def log_surface(self, t_ns: int, payload: bytes, *, device: str | None = None) -> None:
        """`/surface/nodes`: a wire surface message (nodes, normals, σ, dense cloud; metres);
        with its Foxglove views `/surface` (PointCloud of the cloud, or the nodes when the
        cloud is empty), `/scene` (the sheet as a mesh coloured by σ, legend) and `/tf`.
        With `device`, under `/<device>/...` in frame `<device>`."""
        self._log_views(wire_views("surface", as_payload("surface", payload), t_ns, device))

    def log_elements(self, t_ns: int, payload: bytes, latency_ms: float | None = None, *,
                     device: str | None = None) -> None:
        """`/elements`: a wire elements message, unchanged; with its views `/elements/poses`
        (PosesInFrame), `/scene` (entity `elements`: arrows coloured by validity) and
        `/elements/plot` (per-element σ and flags, the frame's latency). With `device`, under
        `/<device>/...` in frame `<device>`."""
        self._log_views(wire_views("elements", as_payload("elements", payload), t_ns, device,
                                   latency_ms))

    def _log_views(self, views: list[tuple[TopicSpec, bytes, int | None, int]]) -> None:
        for spec, data, seq, t_ns in views:
            self._log(spec, t_ns, data, seq)

    def log_status(self, t_ns: int, status: Mapping[str, Any], *,
                   device: str | None = None) -> None:
        """`/status`: a JSON object (under `/<device>` with `device`)."""
        if not isinstance(status, Mapping):
            raise TypeError(f"status must be a mapping, got {type(status).__name__}")
        self._log(device_topic("/status", device), t_ns, to_json(dict(status), "status"))

    def log_contact(self, t_ns: int, contact: Mapping[str, Any]) -> None:
        """`/contact`: a JSON object (docs/tactile.md)."""
        if not isinstance(contact, Mapping):
            raise TypeError(f"contact must be a mapping, got {type(contact).__name__}")
        self._log(TOPICS["/contact"], t_ns, to_json(dict(contact), "contact"))

    def log_pose(self, t_ns: int, pose: Mapping[str, Any]) -> None:
        """`/pose`: a probe pose as received (skinmap.wire.messages.POSE_FIELDS; docs/tactile.md)."""
        self._log(TOPICS["/pose"], t_ns, messages.encode_pose(pose))

    def log_event(self, t_ns: int, level: int | str, message: str,
                  name: str = "skinmapd") -> None:
        """`/log`: a foxglove.Log. `level` is a name (debug..fatal), 0..5 or a logging level."""
        self._log(TOPICS["/log"], t_ns, log_message(t_ns, level, message, name))

    def log_config(self, t_ns: int, config_text: str, calibration: Mapping[str, Any]) -> None:
        """Configuration and calibration: a `/config` message, `config.toml` and
        `calibration.json` attachments and a `skinmap.config` metadata record. Repeated at the
        start of every later file."""
        if not isinstance(config_text, str):
            raise TypeError(f"config_text must be str, got {type(config_text).__name__}")
        if not isinstance(calibration, Mapping):
            raise TypeError(f"calibration must be a mapping, got {type(calibration).__name__}")
        to_json(dict(calibration), "calibration")  # fail now, not at the next rotation
        self._check_time(t_ns)
        self._config = (int(t_ns), config_text, dict(calibration))
        path_before = self.current_path
        if not self._ready(t_ns):
            return
        if self.current_path == path_before:  # a freshly opened file already holds it
            self._guard("writing to", lambda: self._write_config(int(t_ns)))

    def write(self, topic: str, t_ns: int, data: bytes, *, schema_name: str,
              schema_encoding: str, schema_data: bytes, message_encoding: str,
              sequence: int | None = None) -> None:
        """Log any message. The topic's schema/encoding is fixed by its first use."""
        if not isinstance(topic, str) or not topic:
            raise ValueError(f"topic must be a non-empty string, got {topic!r}")
        spec = TopicSpec(topic, schema_name, schema_encoding, bytes(schema_data),
                         message_encoding, has_sequence=sequence is not None)
        known = TOPICS.get(topic) or self._extra_topics.get(topic)
        if known is None:
            self._extra_topics[topic] = spec
        elif (known.schema_name, known.schema_encoding, known.schema_data,
              known.message_encoding) != (spec.schema_name, spec.schema_encoding,
                                          spec.schema_data, spec.message_encoding):
            raise ValueError(f"topic {topic!r} is already logged with schema "
                             f"{known.schema_name!r} / encoding {known.message_encoding!r}")
        else:
            spec = known
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"data must be bytes, got {type(data).__name__}")
        self._log(spec, t_ns, bytes(data), sequence)

    # ---------------------------------------------------------------- lifecycle

    def flush(self) -> None:
        """Close the open chunk and make everything written so far durable (per policy)."""
        if self._file is None:
            return
        self._guard("flushing", self._flush_chunk)

    def tick(self) -> None:
        """Housekeeping for idle periods (call about once a second when nothing is logged):
        close a chunk older than `max_chunk_age_s` and finish a file whose time is up, so
        data does not sit in memory while no messages arrive."""
        if self._file is None:
            return
        if self._rotation_due():
            self._guard("finishing", self._finish_file)
        elif self._chunk_too_old(self._file):
            self._guard("flushing", self._flush_chunk)

    def close(self) -> None:
        """Finish the current file (summary and index, rename to .mcap). Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._file is not None:
            self._guard("finishing", self._finish_file)

    def __enter__(self) -> McapLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- internals

    @staticmethod
    def _check_time(t_ns: int) -> None:
        if isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)) \
                or not 0 <= t_ns < 2**64:
            raise ValueError(f"t_ns must be an integer nanosecond time in [0, 2**64), "
                             f"got {t_ns!r}")

    def _log(self, spec: TopicSpec, t_ns: int, data: bytes, seq: int | None = None) -> None:
        self._check_time(t_ns)
        if seq is not None:
            check_seq(seq)
        try:
            if not self._ready(t_ns):
                return
        except LogStorageError:
            self.messages_lost += 1  # no file could take it
            raise
        self._guard("writing to", lambda: self._add(spec, int(t_ns), data, seq))

    def _ready(self, t_ns: int) -> bool:
        """Make sure a file is open (rotating if due). False: drop this message."""
        if self._closed:
            raise ValueError("the MCAP logger is closed")
        if self._file is None:
            now = self._monotonic()
            if self._retry_at is not None and now < self._retry_at:
                self.messages_dropped += 1
                return False
            self._retry_at = now + int(self.retry_interval_s * 1e9)
            self._guard("opening a log file in", lambda: self._open_file_now(int(t_ns)),
                        path=self.directory)
            return True
        if self._rotation_due():
            self._guard("finishing", self._finish_file)
            return self._ready(t_ns)
        return True

    def _guard(self, action: str, op: Callable[[], None], path: str | None = None) -> None:
        """Run a storage operation; turn OS errors into LogStorageError and drop the file."""
        try:
            op()
        except OSError as exc:
            if isinstance(exc, LogStorageError):
                raise
            where = path or self.current_path or self.directory
            error = LogStorageError(where, exc, action)
            self._abandon_file()
            self.last_error = error
            if self._retry_at is None:
                self._retry_at = self._monotonic() + int(self.retry_interval_s * 1e9)
            raise error from exc

    def _abandon_file(self) -> None:
        # The writer's state no longer matches the disk; keep the cut file for recovery.
        f, self._file = self._file, None
        if f is None:
            return
        self._bytes_in_closed_files += f.stream.position
        f.close_quietly()
        self.abandoned_paths.append(f.path)
        self.messages_lost += f.pending_messages  # the unfinished chunk may not be on disk

    def _rotation_due(self) -> bool:
        assert self._file is not None
        return self.rotation.due(self._file.size(), self._monotonic() - self._file.opened_mono)

    def _chunk_too_old(self, f: McapFile) -> bool:
        return f.chunk_opened_mono is not None and \
            self._monotonic() - f.chunk_opened_mono >= self.max_chunk_age_s * 1e9

    def _open_file_now(self, t_ns: int) -> None:
        if self.create_directory:
            os.makedirs(self.directory, exist_ok=True)
        path = self.rotation.next_path(self.directory, self._clock())
        # Set at once so a failure below abandons (and closes) this file.
        f = self._file = McapFile(path, self._open_file(path), chunk_size=self.chunk_size,
                                  compression=self.compression, fsync_chunk=self.fsync_policy == "chunk")
        f.writer.start(profile="", library=LIBRARY)
        start = dict(self.metadata)
        start.update({"basename": self.rotation.basename, "file_index": str(self.rotation.file_index),
                      "created_unix_ns": str(self._clock()), "writer": LIBRARY})
        f.writer.add_metadata("skinmap.start", start)
        if self._config is not None:
            self._write_config(t_ns)
        f.opened_mono = self._monotonic()
        f.chunk_opened_mono = None
        f.pending_bytes = f.pending_messages = 0
        f.sync()
        if self.fsync_policy == "chunk":
            fsync_directory(self.directory)
        self._retry_at = None
        self.last_error = None

    def _write_config(self, t_ns: int) -> None:
        f = self._file
        assert f is not None and self._config is not None
        logged_at, text, calibration = self._config
        calib_json = to_json(calibration, "calibration")
        f.attachments += 2
        f.writer.add_attachment(create_time=logged_at, log_time=t_ns, name="config.toml",
                                media_type="application/toml", data=text.encode())
        f.writer.add_attachment(create_time=logged_at, log_time=t_ns, name="calibration.json",
                                media_type="application/json", data=calib_json)
        f.writer.add_metadata("skinmap.config", {"config_text": text, "calibration": calib_json.decode(),
                                                 "logged_at_ns": str(logged_at)})
        f.sync()
        message = json.dumps({"config_text": text, "calibration": json.loads(calib_json),
                              "logged_at_ns": logged_at}, separators=(",", ":")).encode()
        self._add(TOPICS["/config"], t_ns, message, None)

    def _add(self, spec: TopicSpec, t_ns: int, data: bytes, seq: int | None) -> None:
        f = self._file
        assert f is not None
        emitted = f.add(spec, t_ns, data, seq)
        self.messages_written += 1
        if emitted:
            self.messages_flushed += f.chunk_done()
        elif f.chunk_opened_mono is None:
            f.chunk_opened_mono = self._monotonic()
        elif self._chunk_too_old(f):
            self.messages_flushed += f.flush_chunk()

    def _flush_chunk(self) -> None:
        assert self._file is not None
        self.messages_flushed += self._file.flush_chunk()

    def _finish_file(self) -> None:
        f = self._file
        assert f is not None
        self.messages_flushed += f.end_writer()
        done = f.close_and_rename(fsync=self.fsync_policy != "never")
        if self.fsync_policy != "never":
            fsync_directory(self.directory)
        self.finished_paths.append(done)
        self.files_finished += 1
        self._bytes_in_closed_files += f.stream.position
        self._file = None
