"""Where the gateway's log goes: the `LogSink` interface, a null sink, an in-memory sink for
tests, and `LogListener`, the log thread that feeds a sink from the gateway's Notifier.

The MCAP writer (`skinmap.daemon.mcaplog.McapLogger`) is the sink skinmapd uses. A sink is
synchronous and called from one thread only (the LogListener's); storage failures raise
`LogStorageError` from the call that hit them and the sink stays usable.
"""
from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from typing import Any, Callable, Mapping

from skinmap.daemon.fanout import LoggedRecord, QueuedListener, Record

__all__ = ["LogSink", "LogStorageError", "NullLogSink", "MemoryLogSink", "LogListener"]

log = logging.getLogger("skinmapd")


class LogStorageError(OSError):
    """The log storage refused a write: disk full, read-only or missing folder, I/O error.

    Raised by the sink call that hit the problem. `path` is the file or folder involved,
    `errno` / `strerror` are those of the underlying OS error. The sink stays usable.
    """

    def __init__(self, path: str, cause: OSError, action: str):
        import errno

        code = cause.errno if cause.errno is not None else errno.EIO
        reason = cause.strerror or str(cause) or type(cause).__name__
        super().__init__(code, f"MCAP log storage failed while {action} {path!r}: {reason}")
        self.path = path
        self.action = action
        self.__cause__ = cause

    def __str__(self) -> str:
        return self.strerror or super().__str__()


class LogSink(ABC):
    """What the gateway logs, one call per kind of record (docs/logging.md names the topics).

    Counters: `messages_dropped` (refused while storage is down), `messages_lost` (may not
    have reached storage because of an error)."""

    messages_dropped: int = 0
    messages_lost: int = 0

    @abstractmethod
    def log_raw_frame(self, t_ns: int, data: bytes) -> None: ...

    @abstractmethod
    def log_strains(self, t_ns: int, payload: bytes, lead: bool = False) -> None:
        """``lead``: the strains of a lead scan, reconstructed and not published."""

    @abstractmethod
    def log_elements(self, t_ns: int, payload: bytes, latency_ms: float | None = None) -> None: ...

    @abstractmethod
    def log_surface(self, t_ns: int, payload: bytes) -> None: ...

    @abstractmethod
    def log_status(self, t_ns: int, status: Mapping[str, Any]) -> None: ...

    @abstractmethod
    def log_contact(self, t_ns: int, contact: Mapping[str, Any]) -> None: ...

    @abstractmethod
    def log_pose(self, t_ns: int, pose: Mapping[str, Any]) -> None: ...

    @abstractmethod
    def log_event(self, t_ns: int, level: int | str, message: str, name: str = "skinmapd") -> None: ...

    @abstractmethod
    def log_config(self, t_ns: int, config_text: str, calibration: Mapping[str, Any]) -> None: ...

    def tick(self) -> None:
        """Housekeeping, about once a second (close old chunks, rotate on time)."""

    @abstractmethod
    def close(self) -> None: ...

    @property
    def healthy(self) -> bool:
        """False after a storage error until storage works again."""
        return True

    @property
    def current_path(self) -> str | None:
        """The file being written, or None."""
        return None

    @property
    def bytes_written(self) -> int:
        return 0


class NullLogSink(LogSink):
    """Logs nothing (logging disabled)."""

    def log_raw_frame(self, t_ns: int, data: bytes) -> None:
        pass

    def log_strains(self, t_ns: int, payload: bytes, lead: bool = False) -> None:
        pass

    def log_elements(self, t_ns: int, payload: bytes, latency_ms: float | None = None) -> None:
        pass

    def log_surface(self, t_ns: int, payload: bytes) -> None:
        pass

    def log_status(self, t_ns: int, status: Mapping[str, Any]) -> None:
        pass

    def log_contact(self, t_ns: int, contact: Mapping[str, Any]) -> None:
        pass

    def log_pose(self, t_ns: int, pose: Mapping[str, Any]) -> None:
        pass

    def log_event(self, t_ns: int, level: int | str, message: str, name: str = "skinmapd") -> None:
        pass

    def log_config(self, t_ns: int, config_text: str, calibration: Mapping[str, Any]) -> None:
        pass

    def close(self) -> None:
        pass


class MemoryLogSink(LogSink):
    """Keeps every call as (kind, t_ns, value) in `records`, for tests.

    `before_write(kind)` runs before each record is kept: a test makes it block (a slow disk)
    or raise LogStorageError (a failing one); a refused record is counted in `messages_lost`.
    """

    def __init__(self, before_write: Callable[[str], None] | None = None) -> None:
        self.records: list[tuple[str, int, Any]] = []
        self.before_write = before_write
        self.closed = False
        self._error: LogStorageError | None = None

    def _keep(self, kind: str, t_ns: int, value: Any) -> None:
        if self.closed:
            raise ValueError("the log sink is closed")
        if self.before_write is not None:
            try:
                self.before_write(kind)
            except LogStorageError as exc:
                self._error = exc
                self.messages_lost += 1
                raise
        self._error = None
        self.records.append((kind, int(t_ns), value))

    def kinds(self, kind: str) -> list[Any]:
        """The values logged under `kind` ("raw", "strains", "lead", "elements", "surface", "status",
        "contact", "pose", "event", "config"), in order."""
        return [value for k, _t, value in self.records if k == kind]

    def log_raw_frame(self, t_ns: int, data: bytes) -> None:
        self._keep("raw", t_ns, bytes(data))

    def log_strains(self, t_ns: int, payload: bytes, lead: bool = False) -> None:
        self._keep("lead" if lead else "strains", t_ns, bytes(payload))

    def log_elements(self, t_ns: int, payload: bytes, latency_ms: float | None = None) -> None:
        self._keep("elements", t_ns, (bytes(payload), latency_ms))

    def log_surface(self, t_ns: int, payload: bytes) -> None:
        self._keep("surface", t_ns, bytes(payload))

    def log_status(self, t_ns: int, status: Mapping[str, Any]) -> None:
        self._keep("status", t_ns, dict(status))

    def log_contact(self, t_ns: int, contact: Mapping[str, Any]) -> None:
        self._keep("contact", t_ns, dict(contact))

    def log_pose(self, t_ns: int, pose: Mapping[str, Any]) -> None:
        self._keep("pose", t_ns, dict(pose))

    def log_event(self, t_ns: int, level: int | str, message: str, name: str = "skinmapd") -> None:
        self._keep("event", t_ns, (level, message))

    def log_config(self, t_ns: int, config_text: str, calibration: Mapping[str, Any]) -> None:
        self._keep("config", t_ns, (config_text, dict(calibration)))

    def close(self) -> None:
        self.closed = True

    @property
    def healthy(self) -> bool:
        return self._error is None


class LogListener(QueuedListener):
    """The log thread: takes every LoggedRecord from the Notifier (queue of `queue_size`; a
    full queue refuses records, counted in `dropped`) and writes it to the sink.

    A storage failure sets `state` "error" and `last_error` (publishing goes on); the sink's
    own retry brings it back to "recording". On stop, what is queued is written, then the
    sink is closed."""

    tick_s = 1.0

    def __init__(self, sink: LogSink, queue_size: int) -> None:
        super().__init__("skinmap-log", queue_size, keep="oldest", drain=True)
        self.idle_s = 0.5
        self.sink = sink
        self.state = "recording"
        self.last_error = ""
        self._last_tick = time.monotonic()

    def accepts(self, record: Record) -> bool:
        return isinstance(record, LoggedRecord)

    def handle(self, record: Record) -> None:
        assert isinstance(record, LoggedRecord)
        self._storage(lambda: record.write_to(self.sink))

    def idle(self) -> None:
        if time.monotonic() - self._last_tick >= self.tick_s:
            self._last_tick = time.monotonic()
            self._storage(self.sink.tick)
        if self.sink.healthy and self.state == "error":
            self.state = "recording"
            log.info("logging resumed: %s", self.sink.current_path)

    def finish(self) -> None:
        try:
            self.sink.close()
        except LogStorageError as exc:
            log.error("closing the log failed: %s", exc)

    def _storage(self, op: Callable[[], None]) -> None:
        try:
            op()
        except LogStorageError as exc:
            if self.state != "error":
                log.error("logging failed, publishing continues: %s", exc)
            self.state = "error"
            self.last_error = str(exc)
        except Exception as exc:  # noqa: BLE001 - a record the sink refuses must not stop the log
            log.warning("log write failed: %s", exc)
