"""Rotating, crash-safe MCAP logger for skinmapd.

Everything the daemon sees and computes is written to chunked, compressed MCAP files so that a
session can be inspected afterwards and replayed bit-exactly (`/raw` holds the serial frames
exactly as received). See docs/logging.md for the topics, layouts and guarantees.

Layout of this module:

- the topics (`TOPICS`): binary payloads are the wire messages of `skinmap.wire.messages`,
  exactly as published; Foxglove views come from `skinmap.daemon.foxglove_log` (foxglove-sdk
  protobuf messages);
- `McapLogger`, the writing edge. It is synchronous and NOT thread-safe: the daemon calls it
  from one dedicated writer thread.
"""

from __future__ import annotations

import base64
import errno
import json
import os
import time
from dataclasses import dataclass, replace
from typing import Any, BinaryIO, Callable, Mapping

import numpy as np
from mcap.writer import CompressionType, IndexType, Writer

from skinmap.daemon import foxglove_log as fox
from skinmap.wire import messages

__all__ = [
    "LogStorageError",
    "McapLogger",
    "TopicSpec",
    "TOPICS",
    "LOG_LEVELS",
    "log_message",
    "topics_table",
    "final_name",
]

MiB = 1024 * 1024
ACTIVE_SUFFIX = ".mcap.active"
FINISHED_SUFFIX = ".mcap"
LIBRARY = "skinmap.daemon.mcaplog"


class LogStorageError(OSError):
    """The log storage refused a write: disk full, read-only or missing folder, I/O error.

    Raised by the logger call that hit the problem. `path` is the file or folder involved,
    `errno` / `strerror` are those of the underlying OS error. The logger stays usable.
    """

    def __init__(self, path: str, cause: OSError, action: str):
        code = cause.errno if cause.errno is not None else errno.EIO
        reason = cause.strerror or str(cause) or type(cause).__name__
        super().__init__(code, f"MCAP log storage failed while {action} {path!r}: {reason}")
        self.path = path
        self.action = action
        self.__cause__ = cause

    def __str__(self) -> str:
        return self.strerror or super().__str__()


# --------------------------------------------------------------------------------------------
# Topics. Binary payloads are the wire messages of skinmap.wire.messages, exactly as published;
# Foxglove views are the foxglove-sdk's protobuf messages (skinmap.daemon.foxglove_log).

LOG_LEVELS = {name: i for i, name in enumerate(fox.LOG_LEVEL_NAMES)}

RAW_LAYOUT = (
    "skinmap.cobs-frame: one scanner frame exactly as received on the serial port, "
    "COBS-encoded, including its 0x00 delimiter; see protocol/PROTOCOL.md. "
    "Replay writes these bytes back unchanged."
)


def _wire_layout(kind: str, what: str) -> bytes:
    header = messages.layout_table("header")
    body = messages.layout_table(kind)
    return (f"skinmap.{kind}/1: the {kind} message exactly as published on Zenoh ({what}; "
            "skinmap.wire.messages, little-endian, lengths in metres).\n\nCommon header:\n"
            f"{header}\n\n{kind}:\n{body}\n").encode()


LAYOUT_SCHEMA_ENCODING = "skinmap.layout-text"


@dataclass(frozen=True)
class TopicSpec:
    """How one topic is stored: schema and message encoding, and whether it carries a seq."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    has_sequence: bool = False

    def channel_metadata(self) -> dict[str, str]:
        return {"sequence": "frame"} if self.has_sequence else {}


def _json_schema(schema: Mapping[str, Any]) -> bytes:
    return json.dumps(schema, separators=(",", ":")).encode()


def _foxglove(topic: str, key: str, has_sequence: bool = False) -> TopicSpec:
    schema = fox.SCHEMAS[key]
    return TopicSpec(topic, schema.name, schema.encoding, bytes(schema.data), "protobuf",
                     has_sequence)


TOPICS: dict[str, TopicSpec] = {
    spec.topic: spec
    for spec in (
        TopicSpec("/raw", "skinmap.CobsFrame", LAYOUT_SCHEMA_ENCODING, RAW_LAYOUT.encode(),
                  "skinmap.cobs-frame"),
        TopicSpec("/strains", "skinmap.Strains", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("strains", "every processed scan"), "skinmap.strains/1",
                  has_sequence=True),
        TopicSpec("/strains/plot", "skinmap.StrainsPlot", "jsonschema",
                  _json_schema(fox.STRAINS_PLOT_SCHEMA), "json", has_sequence=True),
        TopicSpec("/surface", "foxglove.PointCloud", "protobuf",
                  bytes(fox.SCHEMAS["cloud"].data), "protobuf", has_sequence=True),
        TopicSpec("/surface/nodes", "skinmap.Surface", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("surface", "nodes, normals, σ and the dense cloud"),
                  "skinmap.surface/1", has_sequence=True),
        TopicSpec("/elements", "skinmap.Elements", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("elements", "unchanged"), "skinmap.elements/1"),
        _foxglove("/elements/poses", "poses"),
        TopicSpec("/elements/plot", "skinmap.ElementsPlot", "jsonschema",
                  _json_schema(fox.ELEMENTS_PLOT_SCHEMA), "json"),
        _foxglove("/scene", "scene"),
        _foxglove("/tf", "tf"),
        TopicSpec("/contact", "skinmap.Contact", "jsonschema",
                  _json_schema({"title": "skinmap.Contact", "type": "object"}), "json"),
        TopicSpec("/pose", "skinmap.Pose", "jsonschema", _json_schema(messages.pose_json_schema()), "json"),
        TopicSpec("/status", "skinmap.Status", "jsonschema", _json_schema(fox.status_schema()),
                  "json"),
        _foxglove("/log", "log"),
        TopicSpec("/config", "skinmap.Config", "jsonschema",
                  _json_schema({
                      "title": "skinmap.Config",
                      "type": "object",
                      "properties": {
                          "config_text": {"type": "string"},
                          "calibration": {"type": "object"},
                          "logged_at_ns": {"type": "integer"},
                      },
                  }), "json"),
    )
}
TOPICS["/surface"] = _foxglove("/surface", "cloud", has_sequence=True)


def topics_table() -> str:
    """The markdown table of logged topics (docs/logging.md shows it; a test keeps them equal)."""
    lines = ["| topic | schema name (encoding) | message encoding |", "|---|---|---|"]
    for spec in TOPICS.values():
        lines.append(f"| `{spec.topic}` | `{spec.schema_name}` (`{spec.schema_encoding}`) | "
                     f"`{spec.message_encoding}` |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Pure payload helpers.


def _check_seq(seq: int) -> int:
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or not 0 <= seq < 2**64:
        raise ValueError(f"seq must be an integer in [0, 2**64), got {seq!r}")
    return int(seq)


def _level_number(level: int | str) -> int:
    if isinstance(level, str):
        key = level.strip().upper()
        key = {"WARN": "WARNING", "CRITICAL": "FATAL"}.get(key, key)
        if key not in LOG_LEVELS:
            raise ValueError(f"unknown log level {level!r}; use one of {sorted(LOG_LEVELS)}")
        return LOG_LEVELS[key]
    if isinstance(level, (int, np.integer)) and not isinstance(level, bool):
        if 0 <= level <= 5:
            return int(level)
        # Python logging numbers (10 DEBUG .. 50 CRITICAL) map onto Foxglove's 1..5.
        if level in (10, 20, 30, 40, 50):
            return int(level) // 10
    raise ValueError(f"log level must be a name, 0..5 or a logging level, got {level!r}")


def log_message(t_ns: int, level: int | str, message: str, name: str = "skinmapd") -> bytes:
    """A foxglove.Log message (protobuf)."""
    return fox.log_entry(t_ns, _level_number(level), message, name)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(bytes(value)).decode("ascii")
    raise TypeError(f"value of type {type(value).__name__} cannot be logged as JSON")


def _to_json(value: Any, what: str) -> bytes:
    try:
        return json.dumps(value, default=_json_default, separators=(",", ":"),
                          allow_nan=True).encode()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} is not JSON-serialisable: {exc}") from None


def device_topic(topic: str, device: str | None = None) -> TopicSpec:
    """The spec of `topic`, under `/<device>` when several devices share a file or a server."""
    spec = TOPICS[topic]
    return spec if device is None else replace(spec, topic=f"/{device}{spec.topic}")


def wire_views(kind: str, payload: bytes, t_ns: int, device: str | None = None,
               latency_ms: float | None = None) -> list[tuple[TopicSpec, bytes, int | None, int]]:
    """A wire message and its Foxglove views as (topic spec, data, seq or None, time) —
    what the log stores and the live bridge serves. `kind` is elements, surface or strains;
    raises MessageError (bad layout) or ValueError (non-finite surface)."""
    frame = device or fox.FRAME_ID
    t = device_topic
    if kind == "strains":
        st = messages.decode_strains(payload)
        return [(t("/strains", device), payload, st.seq, t_ns),
                (t("/strains/plot", device), fox.strains_plot(st), st.seq, t_ns)]
    if kind == "surface":
        sf = messages.decode_surface(payload)
        if not (np.isfinite(sf.nodes).all() and np.isfinite(sf.cloud).all()):
            raise ValueError("surface nodes or cloud contain NaN or infinite values")
        points = sf.cloud if len(sf.cloud) else sf.nodes.reshape(-1, 3)
        cloud = fox.point_cloud(points, t_ns, frame)
        scene = fox.scene_sheet(sf, t_ns, frame)
        return [(t("/surface/nodes", device), payload, sf.seq, t_ns),
                (t("/surface", device), cloud, sf.seq, t_ns),
                (t("/tf", device), fox.frame_transform(t_ns, frame), None, t_ns),
                (t("/scene", device), scene, None, t_ns)]
    if kind == "elements":
        el = messages.decode_elements(payload)
        views = (fox.element_poses(el, t_ns, frame), fox.scene_elements(el, t_ns, frame),
                 fox.elements_plot(el, latency_ms))
        return [(t("/elements", device), payload, None, t_ns),
                (t("/elements/poses", device), views[0], None, t_ns),
                (t("/scene", device), views[1], None, t_ns),
                (t("/elements/plot", device), views[2], None, t_ns)]
    raise ValueError(f"unknown wire kind {kind!r}; expected elements, surface or strains")


def _payload(kind: str, payload: Any) -> bytes:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise TypeError(f"{kind} payload must be bytes, got {type(payload).__name__}")
    return bytes(payload)


def finish_writer(writer: Writer, attachments: int) -> None:
    """``writer.finish()``, leaving out the attachment index of a file without attachments:
    mcap's Writer writes a summary offset for the empty group, which ``pymcap-cli doctor``
    rightly reports as an error."""
    if not attachments:
        writer._Writer__index_types &= ~IndexType.ATTACHMENT  # type: ignore[attr-defined]
    writer.finish()


def final_name(path: str) -> str:
    """The finished name of a file being written: `x.mcap.active` -> `x.mcap`."""
    if not path.endswith(ACTIVE_SUFFIX):
        raise ValueError(f"{path!r} does not end with {ACTIVE_SUFFIX!r}")
    return path[: -len(ACTIVE_SUFFIX)] + FINISHED_SUFFIX


# --------------------------------------------------------------------------------------------
# The writing edge.


class _CountingFile:
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


def _default_open(path: str) -> BinaryIO:
    # Unbuffered: every write reaches the OS at once, so a storage error surfaces in the call
    # that caused it, never later from a buffer flush.
    return open(path, "xb", buffering=0)


_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}
_FSYNC_POLICIES = ("chunk", "close", "never")


class McapLogger:
    """Rotating MCAP writer. Synchronous and not thread-safe: call it from one thread.

    Files are named `<basename>-<UTC yyyymmddThhmmssZ>-<index:04d>.mcap.active` while being
    written and renamed to `.mcap` when finished (rotation or close). The first file is opened
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
    readable with `skinmap.daemon.mcapinspect.recover`.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        basename: str = "skinmap",
        max_bytes: int = 256 * MiB,
        max_seconds: float = 3600.0,
        chunk_size: int = 512 * 1024,
        max_chunk_age_s: float = 1.0,
        compression: str = "zstd",
        fsync: str = "chunk",
        metadata: Mapping[str, Any] | None = None,
        retry_interval_s: float = 5.0,
        create_directory: bool = False,
        clock: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], int] = time.monotonic_ns,
        open_file: Callable[[str], BinaryIO] = _default_open,
    ):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, "
                             f"got {compression!r}")
        if compression == "lz4":
            try:
                import lz4.frame  # noqa: F401
            except ImportError:
                raise ValueError("compression 'lz4' needs the lz4 package, which is not "
                                 "installed; use 'zstd'") from None
        if fsync not in _FSYNC_POLICIES:
            raise ValueError(f"fsync must be one of {_FSYNC_POLICIES}, got {fsync!r}")
        if not basename or os.sep in basename or (os.altsep and os.altsep in basename):
            raise ValueError(f"basename must be a plain file-name prefix, got {basename!r}")
        for name, value, low in (("max_bytes", max_bytes, 4096), ("chunk_size", chunk_size, 1)):
            if not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        for name, value in (("max_seconds", max_seconds), ("max_chunk_age_s", max_chunk_age_s),
                            ("retry_interval_s", retry_interval_s)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        self.directory = os.fspath(directory)
        self.basename = basename
        self.max_bytes = max_bytes
        self.max_seconds = float(max_seconds)
        self.chunk_size = chunk_size
        self.max_chunk_age_s = float(max_chunk_age_s)
        self.compression = compression
        self.fsync_policy = fsync
        # MCAP metadata values are strings; anything else is stored as JSON.
        self.metadata = {
            str(k): v if isinstance(v, str) else _to_json(v, f"metadata[{k!r}]").decode()
            for k, v in (metadata or {}).items()
        }
        self.retry_interval_s = float(retry_interval_s)
        self.create_directory = create_directory
        self._clock = clock
        self._monotonic = monotonic
        self._open_file = open_file

        self._extra_topics: dict[str, TopicSpec] = {}
        self._config: tuple[int, str, Any] | None = None
        self._file_index = 0

        # Per-file state.
        self._writer: Writer | None = None
        self._stream: _CountingFile | None = None
        self._path: str | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._opened_mono = 0
        self._chunk_opened_mono: int | None = None
        self._pending_bytes = 0
        self._pending_messages = 0
        self._attachments_in_file = 0

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
        return self._bytes_in_closed_files + (self._stream.position if self._stream else 0)

    @property
    def current_path(self) -> str | None:
        """The `.mcap.active` file being written, or None."""
        return self._path

    # ---------------------------------------------------------------- typed helpers

    def log_raw_frame(self, t_ns: int, data: bytes) -> None:
        """`/raw`: one serial frame, bytes exactly as received."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"raw frame must be bytes, got {type(data).__name__}")
        self._log(TOPICS["/raw"], t_ns, bytes(data))

    def log_strains(self, t_ns: int, payload: bytes, *, device: str | None = None) -> None:
        """`/strains`: a wire strains message (skinmap.wire.messages.encode_strains), and its
        plottable view `/strains/plot`. With `device`, under `/<device>/...`."""
        self._log_views(wire_views("strains", _payload("strains", payload), t_ns, device))

    def log_surface(self, t_ns: int, payload: bytes, *, device: str | None = None) -> None:
        """`/surface/nodes`: a wire surface message (nodes, normals, σ, dense cloud; metres);
        with its Foxglove views `/surface` (PointCloud of the cloud, or the nodes when the
        cloud is empty), `/scene` (the sheet as a mesh coloured by σ, legend) and `/tf`.
        With `device`, under `/<device>/...` in frame `<device>`."""
        self._log_views(wire_views("surface", _payload("surface", payload), t_ns, device))

    def log_elements(self, t_ns: int, payload: bytes, latency_ms: float | None = None, *,
                     device: str | None = None) -> None:
        """`/elements`: a wire elements message, unchanged; with its views `/elements/poses`
        (PosesInFrame), `/scene` (entity `elements`: arrows coloured by validity) and
        `/elements/plot` (per-element σ and flags, the frame's latency). With `device`, under
        `/<device>/...` in frame `<device>`."""
        self._log_views(wire_views("elements", _payload("elements", payload), t_ns, device,
                                   latency_ms))

    def _log_views(self, views: list[tuple[TopicSpec, bytes, int | None, int]]) -> None:
        for spec, data, seq, t_ns in views:
            self._log(spec, t_ns, data, seq)

    def log_status(self, t_ns: int, status: Mapping[str, Any], *,
                   device: str | None = None) -> None:
        """`/status`: a JSON object (under `/<device>` with `device`)."""
        if not isinstance(status, Mapping):
            raise TypeError(f"status must be a mapping, got {type(status).__name__}")
        self._log(device_topic("/status", device), t_ns, _to_json(dict(status), "status"))

    def log_contact(self, t_ns: int, contact: Mapping[str, Any]) -> None:
        """`/contact`: a JSON object (docs/tactile.md)."""
        if not isinstance(contact, Mapping):
            raise TypeError(f"contact must be a mapping, got {type(contact).__name__}")
        self._log(TOPICS["/contact"], t_ns, _to_json(dict(contact), "contact"))

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
        _to_json(dict(calibration), "calibration")  # fail now, not at the next rotation
        self._check_time(t_ns)
        self._config = (int(t_ns), config_text, dict(calibration))
        path_before = self._path
        if not self._ready(t_ns):
            return
        if self._path == path_before:  # a freshly opened file already holds it
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
        if self._writer is None:
            return
        self._guard("flushing", self._flush_chunk)

    def tick(self) -> None:
        """Housekeeping for idle periods (call about once a second when nothing is logged):
        close a chunk older than `max_chunk_age_s` and finish a file whose time is up, so
        data does not sit in memory while no messages arrive."""
        if self._writer is None:
            return
        if self._rotation_due():
            self._guard("finishing", self._finish_file)
        elif self._chunk_opened_mono is not None and \
                self._monotonic() - self._chunk_opened_mono >= self.max_chunk_age_s * 1e9:
            self._guard("flushing", self._flush_chunk)

    def close(self) -> None:
        """Finish the current file (summary and index, rename to .mcap). Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._writer is not None:
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
            _check_seq(seq)
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
        if self._writer is None:
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
            where = path or self._path or self.directory
            error = LogStorageError(where, exc, action)
            self._abandon_file()
            self.last_error = error
            if self._retry_at is None:
                self._retry_at = self._monotonic() + int(self.retry_interval_s * 1e9)
            raise error from exc

    def _abandon_file(self) -> None:
        # The writer's state no longer matches the disk; keep the cut file for recovery.
        if self._stream is not None:
            self._bytes_in_closed_files += self._stream.position
            try:
                self._stream.close()
            except OSError:
                pass
        if self._path is not None:
            self.abandoned_paths.append(self._path)
        # Messages of the unfinished chunk may not have reached the disk.
        self.messages_lost += self._pending_messages
        self._writer = self._stream = self._path = None
        self._channels.clear()
        self._schemas.clear()
        self._chunk_opened_mono = None
        self._pending_bytes = self._pending_messages = 0

    def _rotation_due(self) -> bool:
        assert self._stream is not None
        if self._stream.position + self._pending_bytes >= self.max_bytes:
            return True
        return self._monotonic() - self._opened_mono >= self.max_seconds * 1e9

    def _next_path(self) -> str:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(self._clock() / 1e9))
        while True:
            self._file_index += 1
            path = os.path.join(self.directory,
                                f"{self.basename}-{stamp}-{self._file_index:04d}{ACTIVE_SUFFIX}")
            if not os.path.exists(path) and not os.path.exists(final_name(path)):
                return path

    def _open_file_now(self, t_ns: int) -> None:
        if self.create_directory:
            os.makedirs(self.directory, exist_ok=True)
        path = self._next_path()
        raw = self._open_file(path)
        stream = _CountingFile(raw)
        # Set at once so a failure below abandons (and closes) this file.
        self._stream, self._path = stream, path
        writer = Writer(stream, chunk_size=self.chunk_size,
                        compression=_COMPRESSION[self.compression])
        self._writer = writer
        self._attachments_in_file = 0
        writer.start(profile="", library=LIBRARY)
        start = dict(self.metadata)
        start.update({"basename": self.basename, "file_index": str(self._file_index),
                      "created_unix_ns": str(self._clock()), "writer": LIBRARY})
        writer.add_metadata("skinmap.start", start)
        if self._config is not None:
            self._write_config(t_ns)
        self._opened_mono = self._monotonic()
        self._chunk_opened_mono = None
        self._pending_bytes = self._pending_messages = 0
        self._sync(force=self.fsync_policy == "chunk")
        if self.fsync_policy == "chunk":
            self._fsync_directory()
        self._retry_at = None
        self.last_error = None

    def _write_config(self, t_ns: int) -> None:
        assert self._writer is not None
        logged_at, text, calibration = self._config  # type: ignore[misc]
        calib_json = _to_json(calibration, "calibration")
        self._attachments_in_file += 2
        self._writer.add_attachment(create_time=logged_at, log_time=t_ns, name="config.toml",
                                    media_type="application/toml", data=text.encode())
        self._writer.add_attachment(create_time=logged_at, log_time=t_ns,
                                    name="calibration.json", media_type="application/json",
                                    data=calib_json)
        self._writer.add_metadata("skinmap.config", {"config_text": text,
                                                     "calibration": calib_json.decode(),
                                                     "logged_at_ns": str(logged_at)})
        self._sync(force=self.fsync_policy == "chunk")
        message = json.dumps({"config_text": text, "calibration": json.loads(calib_json),
                              "logged_at_ns": logged_at}, separators=(",", ":")).encode()
        self._add(TOPICS["/config"], t_ns, message, None)

    def _channel_id(self, spec: TopicSpec) -> int:
        channel = self._channels.get(spec.topic)
        if channel is None:
            assert self._writer is not None
            key = (spec.schema_name, spec.schema_encoding, spec.schema_data)
            schema = self._schemas.get(key)
            if schema is None:
                schema = self._writer.register_schema(spec.schema_name, spec.schema_encoding,
                                                      spec.schema_data)
                self._schemas[key] = schema
                self._pending_bytes += len(spec.schema_data) + 64
            channel = self._writer.register_channel(spec.topic, spec.message_encoding, schema,
                                                    spec.channel_metadata())
            self._channels[spec.topic] = channel
            self._pending_bytes += 64
        return channel

    def _add(self, spec: TopicSpec, t_ns: int, data: bytes, seq: int | None) -> None:
        assert self._writer is not None and self._stream is not None
        channel = self._channel_id(spec)
        before = self._stream.position
        try:
            self._writer.add_message(channel_id=channel, log_time=t_ns, publish_time=t_ns,
                                     data=data, sequence=0 if seq is None else seq % 2**32)
        except OSError:
            self._pending_messages += 1  # it was in the chunk whose write failed
            raise
        self.messages_written += 1
        self._pending_messages += 1
        self._pending_bytes += len(data) + 31
        if self._stream.position != before:
            # The writer emitted a chunk, which held every pending message including this one.
            self._chunk_written()
        elif self._chunk_opened_mono is None:
            self._chunk_opened_mono = self._monotonic()
        elif self._monotonic() - self._chunk_opened_mono >= self.max_chunk_age_s * 1e9:
            self._flush_chunk()

    def _chunk_written(self) -> None:
        self.messages_flushed += self._pending_messages
        self._pending_messages = self._pending_bytes = 0
        self._chunk_opened_mono = None
        self._sync(force=self.fsync_policy == "chunk")

    def _flush_chunk(self) -> None:
        assert self._writer is not None and self._stream is not None
        self._writer.flush()
        self._chunk_written()

    def _sync(self, force: bool) -> None:
        assert self._stream is not None
        if force:
            self._stream.fsync()
        else:
            self._stream.flush()

    def _fsync_directory(self) -> None:
        try:
            fd = os.open(self.directory, os.O_RDONLY)
        except OSError:
            return  # some file systems do not allow opening folders; the data is synced
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)

    def _finish_file(self) -> None:
        assert self._writer is not None and self._stream is not None and self._path
        finish_writer(self._writer, self._attachments_in_file)
        self.messages_flushed += self._pending_messages
        self._pending_messages = self._pending_bytes = 0
        if self.fsync_policy != "never":
            self._stream.fsync()
        self._stream.close()
        done = final_name(self._path)
        os.replace(self._path, done)
        if self.fsync_policy != "never":
            self._fsync_directory()
        self.finished_paths.append(done)
        self.files_finished += 1
        self._bytes_in_closed_files += self._stream.position
        self._writer = self._stream = self._path = None
        self._channels.clear()
        self._schemas.clear()
        self._chunk_opened_mono = None
