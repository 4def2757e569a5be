"""The scanner link: owns the serial port, does the HELLO handshake, streams, and recovers.

One thread reads the port and does nothing slow: every decoded frame goes to a callback that
must only enqueue. Unplug, stalls and reboots are detected here and handled in-process with
exponential backoff; the port is opened by its stable path each time, so a device that returns
behind the same symlink (udev, /dev/serial/by-id, the emulator's link) is found again.
"""
from __future__ import annotations

import random
import select
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import serial

from skinmap.daemon.config import DeviceConfig
from skinmap.protocol import (
    Ack,
    Frame,
    Hello,
    Message,
    Nak,
    QueryInfo,
    Scan,
    SetScanRate,
    Start,
    Status,
    Stop,
    StreamDecoder,
    encode_frame,
)
from skinmap.protocol import ErrorCode, hello_compatibility

__all__ = ["LinkError", "LinkStats", "ScannerLink", "open_serial", "validate_hello"]

READ_CHUNK = 65536
READ_TIMEOUT_S = 0.02
# StreamDecoder counters of frames it refused (the decoder's last_error says why).
_REJECT_COUNTERS = ("cobs_errors", "crc_errors", "length_errors", "version_errors", "incompat_flag_drops",
                    "unknown_type", "field_errors", "oversize_frames")
FRAME_ERROR_REPORT_S = 1.0


class LinkError(RuntimeError):
    """The scanner did not behave as the protocol requires (no HELLO, NAK, absurd values)."""


def open_serial(port: str, baudrate: int, exclusive: bool) -> serial.SerialBase:
    """Open a device path or a pyserial URL; exclusive access on real ttys (flock)."""
    # Non-blocking reads: the link waits with select() itself, then takes everything available
    # at once (a blocking read(n) would sit out its timeout, and `in_waiting` of socket://
    # ports only says 0 or 1).
    kwargs: dict[str, Any] = {"baudrate": baudrate, "timeout": 0, "write_timeout": 1.0}
    if exclusive and "://" not in port:
        kwargs["exclusive"] = True
    return serial.serial_for_url(port, **kwargs)


def validate_hello(hello: Hello, cfg: DeviceConfig) -> None:
    """Refuse a device description the daemon cannot or should not serve."""
    compat = hello_compatibility(hello)
    if not compat.usable:
        raise LinkError(f"incompatible scanner: {compat.note}")
    n, m = hello.n, hello.m
    if n * m > cfg.max_cells:
        raise LinkError(f"scanner reports {n}×{m} = {n * m} cells, more than device.max_cells = {cfg.max_cells}")
    if not 1_000 <= hello.pitch_um <= 100_000:
        raise LinkError(f"scanner reports pitch {hello.pitch_um} µm, outside 1–100 mm")
    if not (0 < hello.h_upper_um <= 10_000 and 0 < hello.h_lower_um <= 10_000):
        raise LinkError(f"scanner reports layer offsets {hello.h_upper_um}/{hello.h_lower_um} µm, outside (0, 10] mm")
    gf = hello.gauge_factor()
    r0 = hello.base_resistance_ohm()
    if not ((gf > 0.05).all() and (gf < 20).all()):
        raise LinkError("scanner reports a gauge factor outside 0.05–20")
    if not ((r0 > 1e-3).all() and (r0 < 1e5).all()):
        raise LinkError("scanner reports a base resistance outside 1 mΩ–100 kΩ")


@dataclass
class LinkStats:
    connects: int = 0
    reconnects: int = 0
    disconnects: int = 0
    stalls: int = 0
    reboots: int = 0
    scans: int = 0
    scans_lost: int = 0
    handshake_failures: int = 0
    bytes_in: int = 0
    state: str = "starting"
    last_error: str = ""
    frames_rejected: int = 0  # damaged frames the decoder refused (sum of its error counters)
    last_frame_error: str = ""
    decoder: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "decoder"}
        d.update({f"decoder_{k}": v for k, v in self.decoder.items()})
        return d


class ScannerLink:
    """Runs the scanner connection in its own thread.

    Callbacks (called from the link thread; they must not block):
      on_hello(hello)                 after every successful handshake
      on_scan(scan, frame, t_rx_ns)   every SCAN
      on_frame(frame, t_rx_ns)        every decoded frame (for raw logging)
      on_event(level, text)           state changes and faults
      on_alive()                      the link is working (data or an active retry loop)
    """

    def __init__(
        self,
        cfg: DeviceConfig,
        *,
        on_hello: Callable[[Hello], None],
        on_scan: Callable[[Scan, Frame, int], None],
        on_frame: Callable[[Frame, int], None] = lambda f, t: None,
        on_event: Callable[[str, str], None] = lambda level, text: None,
        on_alive: Callable[[], None] = lambda: None,
        opener: Callable[[str, int, bool], Any] = open_serial,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.cfg = cfg
        self._on_hello, self._on_scan, self._on_frame = on_hello, on_scan, on_frame
        self._on_event, self._on_alive = on_event, on_alive
        self._opener = opener
        self._clock_ns = clock_ns
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._port: Any = None
        self._decoder = StreamDecoder()
        self._tx_seq = 0
        # A device that was not power-cycled remembers its last answers by request id and replays
        # them without executing (PROTOCOL.md §8): a host restarting its counter at 0 would have
        # its new commands taken for retries of the previous session's.
        self._request_id = random.randrange(0x10000)
        self.stats = LinkStats()
        self.hello: Hello | None = None
        self.device_status: Status | None = None
        self.streaming = threading.Event()
        self._last_sample: int | None = None
        self._rejected_reported = 0
        self._garbage_reported = 0
        self._next_reject_report = 0.0

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="skinmap-link", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 3.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._close_port()

    # -- the loop --------------------------------------------------------------------------

    def _run(self) -> None:
        backoff = self.cfg.reconnect_min_s
        first = True
        while not self._stop.is_set():
            try:
                self._connect()
                if not first:
                    self.stats.reconnects += 1
                first = False
                self._handshake()
                backoff = self.cfg.reconnect_min_s  # a good handshake resets the backoff
                self._stream()
            except (serial.SerialException, OSError) as exc:
                self._fault("warning", "disconnected", f"serial port {self.cfg.port}: {exc}")
                self.stats.disconnects += 1
            except LinkError as exc:
                self._fault("error", "handshake-failed", str(exc))
                self.stats.handshake_failures += 1
            finally:
                self.streaming.clear()
                self._close_port()
            if self._stop.is_set():
                break
            self.stats.state = "reconnecting"
            self._on_alive()
            self._stop.wait(backoff)
            backoff = min(backoff * 2, self.cfg.reconnect_max_s)
        self.stats.state = "stopped"

    def _fault(self, level: str, state: str, text: str) -> None:
        self.stats.state = state
        self.stats.last_error = text
        self._on_event(level, text)

    def _connect(self) -> None:
        self.stats.state = "connecting"
        self._port = self._opener(self.cfg.port, self.cfg.baudrate, self.cfg.exclusive)
        self._decoder.reset()
        self._last_sample = None
        self.stats.connects += 1
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError, AttributeError):
            pass
        self._on_event("info", f"opened {self.cfg.port}")

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing a vanished port may fail in many ways
                pass

    # -- I/O helpers -----------------------------------------------------------------------

    def _send(self, msg: Message) -> None:
        self._port.write(encode_frame(msg, self._tx_seq))
        self._tx_seq = (self._tx_seq + 1) & 0xFFFF

    def _next_request_id(self) -> int:
        self._request_id = (self._request_id + 1) & 0xFFFF
        return self._request_id

    def _read_frames(self) -> list[Frame]:
        port = self._port
        fileno = getattr(port, "fileno", None)
        if fileno is not None:
            readable, _, _ = select.select([fileno()], [], [], READ_TIMEOUT_S)
            # pyserial raises SerialException when a readable port yields nothing (unplugged).
            data = port.read(READ_CHUNK) if readable else b""
        else:
            data = port.read(min(max(port.in_waiting, 1), READ_CHUNK))
        if not data:
            return []
        self.stats.bytes_in += len(data)
        t_rx = self._clock_ns()
        frames = self._decoder.feed(data)
        self._report_frame_errors()
        for f in frames:
            self._on_frame(f, t_rx)
            if isinstance(f.msg, Scan):
                self._handle_scan(f, t_rx)
            elif isinstance(f.msg, Status):
                self.device_status = f.msg
            elif isinstance(f.msg, Hello) and self.streaming.is_set():
                # An unsolicited HELLO mid-stream means the device rebooted.
                raise _Rebooted(f.msg)
        self.stats.decoder = self._decoder.counters()
        self.stats.frames_rejected = self._rejected_frames()
        self.stats.last_frame_error = self._decoder.last_error or ""
        return frames

    def _report_frame_errors(self) -> None:
        """Name damaged input in the event log, at most once per FRAME_ERROR_REPORT_S (the
        decoder's counters hold the exact totals)."""
        rejected = self._rejected_frames()
        now = time.monotonic()
        if rejected == self._rejected_reported or now < self._next_reject_report:
            return
        garbage = self._decoder.garbage_bytes
        self._on_event("warning", f"serial link: {rejected - self._rejected_reported} damaged frame(s) rejected, "
                                  f"{garbage - self._garbage_reported} byte(s) discarded (last: {self._decoder.last_error})")
        self._rejected_reported, self._garbage_reported = rejected, garbage
        self._next_reject_report = now + FRAME_ERROR_REPORT_S

    def _rejected_frames(self) -> int:
        d = self._decoder
        return sum(getattr(d, name) for name in _REJECT_COUNTERS)

    def _request(self, msg: Message, what: str, retries: int = 3) -> Ack:
        """Send a command and wait for its ACK; retries reuse the request id (idempotent)."""
        deadline_each = self.cfg.handshake_timeout_s / retries
        for attempt in range(retries):
            self._send(msg)
            until = time.monotonic() + deadline_each
            while time.monotonic() < until and not self._stop.is_set():
                for f in self._read_frames():
                    reply = f.msg
                    if isinstance(reply, (Ack, Nak)) and reply.request_id == msg.request_id:
                        if isinstance(reply, Nak):
                            try:
                                code = ErrorCode(reply.error).name
                            except ValueError:
                                code = f"error {reply.error}"
                            raise LinkError(f"scanner refused {what}: {code} (argument {reply.argument})")
                        return reply
        raise LinkError(f"scanner did not answer {what} within {self.cfg.handshake_timeout_s:g} s")

    # -- protocol steps --------------------------------------------------------------------

    def _handshake(self) -> None:
        self.stats.state = "handshake"
        hello: Hello | None = None
        rejected_before = self._rejected_frames()
        request = QueryInfo(self._next_request_id())
        for _ in range(3):
            self._send(request)
            until = time.monotonic() + self.cfg.handshake_timeout_s / 3
            while hello is None and time.monotonic() < until and not self._stop.is_set():
                for f in self._read_frames():
                    if isinstance(f.msg, Hello):
                        hello = f.msg
            if hello is not None or self._stop.is_set():
                break
        if hello is None:
            why = ""
            if self._rejected_frames() > rejected_before:
                # Say what the device did send: an absurd HELLO is refused by the decoder, and
                # "no HELLO" alone would hide that the scanner is there but talking nonsense.
                why = f"; frames received but rejected, last: {self._decoder.last_error}"
            raise LinkError(f"no HELLO from {self.cfg.port} within {self.cfg.handshake_timeout_s:g} s{why}")
        validate_hello(hello, self.cfg)
        self.hello = hello
        self._on_hello(hello)
        rate_mhz = int(round(self.cfg.scan_rate_hz * 1000))
        if hello.max_scan_rate_mhz and rate_mhz > hello.max_scan_rate_mhz:
            self._on_event("warning", f"requested {self.cfg.scan_rate_hz:g} scans/s, scanner allows {hello.max_scan_rate_mhz / 1000:g}")
            rate_mhz = hello.max_scan_rate_mhz
        # A scanner that kept running (host restarted, port glitch without a power cycle) is
        # still SCANNING and refuses SET_SCAN_RATE there; STOP is accepted in every state.
        self._request(Stop(self._next_request_id()), "STOP")
        self._request(SetScanRate(self._next_request_id(), rate_mhz), "SET_SCAN_RATE")
        self._request(Start(self._next_request_id()), "START")
        self._last_sample = None  # START restarts the scan index: not a reboot, nothing lost
        self.streaming.set()
        self.stats.state = "streaming"
        self._on_event("info", f"scanner {hello.serial_number} {hello.n}×{hello.m} streaming at {rate_mhz / 1000:g} scans/s")

    def _handle_scan(self, frame: Frame, t_rx: int) -> None:
        scan: Scan = frame.msg  # type: ignore[assignment]
        if self.hello is None or (scan.n, scan.m) != (self.hello.n, self.hello.m):
            return  # not ours to interpret until a matching HELLO
        last = self._last_sample
        if last is not None:
            gap = (scan.sample_index - last) & 0xFFFFFFFF
            if gap == 0 or gap > 0x7FFFFFFF:
                # Index went backwards: the device restarted its scan counter.
                self.stats.reboots += 1
                self._on_event("warning", f"scan index went from {last} to {scan.sample_index}: scanner restarted")
            elif gap > 1:
                self.stats.scans_lost += gap - 1
        self._last_sample = scan.sample_index
        self.stats.scans += 1
        self._last_scan_mono = time.monotonic()
        self._on_scan(scan, frame, t_rx)

    def _stream(self) -> None:
        self._last_scan_mono = time.monotonic()
        stalled = False
        next_kick = 0.0
        while not self._stop.is_set():
            try:
                self._read_frames()
            except _Rebooted:
                self.stats.reboots += 1
                self._on_event("warning", "scanner rebooted (unsolicited HELLO); handshaking again")
                self.streaming.clear()
                self._handshake()
                continue
            now = time.monotonic()
            idle = now - self._last_scan_mono
            self._on_alive()
            if idle < self.cfg.stall_timeout_s:
                if stalled:
                    stalled = False
                    self.stats.state = "streaming"
                    self._on_event("info", "scans resumed")
                continue
            if not stalled:
                stalled = True
                self.stats.stalls += 1
                self._fault("warning", "stalled", f"no scan for {idle:.2f} s")
                next_kick = now
            if now >= next_kick:
                # Keep the port open (data resumes at once when the device does) and ask
                # again: START is idempotent on the device, and revives one that lost it.
                next_kick = now + self.cfg.stall_timeout_s
                try:
                    self._send(Start(self._next_request_id()))
                except serial.SerialTimeoutException:
                    pass


class _Rebooted(Exception):
    def __init__(self, hello: Hello) -> None:
        super().__init__("unsolicited HELLO")
        self.hello = hello
