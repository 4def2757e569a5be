"""Fan-out of what the gateway receives and derives, after python-can's Listener/Notifier.

The scanner link's callbacks (on its receive thread), the processing thread and the main loop
hand each record to one `Notifier`, which passes it to every `Listener` in turn. A listener's
`on_record` runs on the caller's thread and must not block: listeners that do slow work
(reconstruction, the disk) are `QueuedListener`s, which only put the record on a bounded queue
of their own, served by a thread of their own, and count what does not fit. So a slow disk
never stalls the serial reader or the reconstruction (docs/reliability.md).

Records are small frozen dataclasses; those that belong in the log (`LoggedRecord`) know the
`LogSink` call that stores them.
"""
from __future__ import annotations

import logging
import queue
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Iterable, Literal, Mapping

from skinmap.protocol import Scan

if TYPE_CHECKING:
    from skinmap.daemon.logsink import LogSink

__all__ = ["Record", "LoggedRecord", "RawFrame", "ScanReceived", "Event", "ConfigRecord", "WireRecord",
           "StatusRecord", "ContactRecord", "PoseRecord", "Listener", "Notifier", "QueuedListener"]

log = logging.getLogger("skinmapd")


class Record:
    """Something received or derived, passed to every listener."""

    __slots__ = ()


class LoggedRecord(Record, ABC):
    """A record the log stores."""

    __slots__ = ()

    @abstractmethod
    def write_to(self, sink: LogSink) -> None:
        """Store this record with the sink's matching call."""


@dataclass(frozen=True, slots=True)
class ScanReceived(Record):
    """A scan from the link: its arrival time (wall clock, ns) and the host monotonic clock."""

    scan: Scan
    t_rx_ns: int
    t_mono_ns: int


@dataclass(frozen=True, slots=True)
class RawFrame(LoggedRecord):
    """One serial frame exactly as received (COBS-encoded, with its delimiter)."""

    t_ns: int
    data: bytes

    def write_to(self, sink: LogSink) -> None:
        sink.log_raw_frame(self.t_ns, self.data)


@dataclass(frozen=True, slots=True)
class Event(LoggedRecord):
    t_ns: int
    level: str
    text: str

    def write_to(self, sink: LogSink) -> None:
        sink.log_event(self.t_ns, self.level, self.text)


@dataclass(frozen=True, slots=True)
class ConfigRecord(LoggedRecord):
    t_ns: int
    config_text: str
    calibration: Mapping[str, Any]

    def write_to(self, sink: LogSink) -> None:
        sink.log_config(self.t_ns, self.config_text, self.calibration)


@dataclass(frozen=True, slots=True)
class WireRecord(LoggedRecord):
    """An encoded wire message (skinmap.wire.messages) of one processed scan; "lead": the
    strains message of a lead scan (reconstructed, not published)."""

    kind: Literal["strains", "lead", "elements", "surface"]
    t_ns: int
    payload: bytes
    latency_ms: float | None = None  # elements only: the scan's latency to publication

    def write_to(self, sink: LogSink) -> None:
        if self.kind in ("strains", "lead"):
            sink.log_strains(self.t_ns, self.payload, lead=self.kind == "lead")
        elif self.kind == "elements":
            sink.log_elements(self.t_ns, self.payload, self.latency_ms)
        else:
            sink.log_surface(self.t_ns, self.payload)


@dataclass(frozen=True, slots=True)
class StatusRecord(LoggedRecord):
    t_ns: int
    status: Mapping[str, Any]

    def write_to(self, sink: LogSink) -> None:
        sink.log_status(self.t_ns, self.status)


@dataclass(frozen=True, slots=True)
class ContactRecord(LoggedRecord):
    t_ns: int
    contact: Mapping[str, Any]

    def write_to(self, sink: LogSink) -> None:
        sink.log_contact(self.t_ns, self.contact)


@dataclass(frozen=True, slots=True)
class PoseRecord(LoggedRecord):
    """A probe pose taken in from Zenoh ([tactile]; skinmap.daemon.poses)."""

    t_ns: int
    pose: Mapping[str, Any]

    def write_to(self, sink: LogSink) -> None:
        sink.log_pose(self.t_ns, self.pose)


class Listener(ABC):
    """Receives every record a Notifier is given. `on_record` runs on the notifying thread
    and must return at once."""

    @abstractmethod
    def on_record(self, record: Record) -> None: ...

    def stop(self, timeout: float = 10.0) -> None:
        """Stop work of the listener's own (nothing for a plain listener)."""


class Notifier:
    """Passes records to its listeners, in the order they were added. Thread-safe: records
    may come from several threads; listeners may be added and removed at any time."""

    def __init__(self, listeners: Iterable[Listener] = ()) -> None:
        self._lock = threading.Lock()
        self._listeners: tuple[Listener, ...] = tuple(listeners)

    def add_listener(self, listener: Listener) -> None:
        with self._lock:
            self._listeners = (*self._listeners, listener)

    def remove_listener(self, listener: Listener) -> None:
        with self._lock:
            self._listeners = tuple(x for x in self._listeners if x is not listener)

    def notify(self, record: Record) -> None:
        for listener in self._listeners:  # a snapshot: no lock is held while listeners run
            listener.on_record(record)

    def stop(self, timeout: float = 10.0) -> None:
        for listener in self._listeners:
            listener.stop(timeout)


class QueuedListener(Listener):
    """A listener with a bounded queue and a thread of its own that handles the records.

    `keep="newest"`: a full queue loses its oldest record (latest wins: processing);
    `keep="oldest"`: a full queue refuses the new record (the log keeps what it has). Either
    way `dropped` counts the loss. With `drain=True` the thread handles what is queued before
    it ends (the log); otherwise it ends at once (processing).
    """

    idle_s = 0.2  # the thread wakes this often when nothing arrives, to call `idle()`

    def __init__(self, name: str, maxsize: int, *, keep: Literal["newest", "oldest"], drain: bool) -> None:
        if maxsize < 1:
            raise ValueError(f"{name}: queue size must be at least 1, got {maxsize}")
        self.name = name
        self.keep = keep
        self.drain = drain
        self.dropped = 0
        self._queue: queue.Queue[Record] = queue.Queue(maxsize=maxsize)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- on the notifying thread ------------------------------------------------------------

    def accepts(self, record: Record) -> bool:
        """Whether to queue `record` (runs on the notifying thread: keep it cheap)."""
        return True

    def on_record(self, record: Record) -> None:
        if not self.accepts(record):
            return
        try:
            self._queue.put_nowait(record)
            return
        except queue.Full:
            pass
        if self.keep == "oldest":
            self.dropped += 1
            return
        try:
            self._queue.get_nowait()
            self.dropped += 1
        except queue.Empty:
            pass
        try:
            self._queue.put_nowait(record)
        except queue.Full:  # another thread filled the place just freed
            self.dropped += 1

    # -- the listener's thread --------------------------------------------------------------

    @abstractmethod
    def handle(self, record: Record) -> None:
        """Handle one record (the listener's thread)."""

    def idle(self) -> None:
        """Called after every record and whenever the queue stayed empty for `idle_s`."""

    def finish(self) -> None:
        """Called once on the listener's thread when it ends."""

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        try:
            while True:
                if self._stop.is_set() and not self.drain:
                    break
                try:
                    record: Record | None = self._queue.get(timeout=self.idle_s)
                except queue.Empty:
                    record = None
                    if self._stop.is_set():
                        break
                if record is not None:
                    self._guarded(self.handle, record)
                self._guarded(self.idle)
        finally:
            self._guarded(self.finish)

    def _guarded(self, fn: Callable[..., None], *args: Record) -> None:
        try:
            fn(*args)
        except Exception:  # noqa: BLE001 - the thread must outlive any one record
            log.exception("%s: unexpected failure", self.name)
