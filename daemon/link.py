"""The scanner link: owns the serial port, does the HELLO handshake, streams, and recovers.

One thread reads the port and does nothing slow: every decoded frame goes to a callback that
must only enqueue. Unplug, stalls and reboots are detected here and handled in-process with
exponential backoff; the port is opened by its stable path each time, so a device that returns
behind the same symlink (udev, /dev/serial/by-id, the emulator's link) is found again.

What the link holds the device to (PROTOCOL.md sections 5, 7.2, 8 and 13): the scan rate it
confirmed, the array size of its HELLO, a sample index that advances plausibly, and answers
only to requests this host sent. Every departure is counted, named in `last_error` and in
rate-limited events, and turns the status unhealthy while it lasts.
"""
from __future__ import annotations

import collections
import functools
import random
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from skinmap.daemon.config import DeviceConfig
from skinmap.ports import PortError, PortFactory, PortWriteTimeout, ScannerPort, SerialScannerPort
from skinmap.protocol import (
    Ack,
    DeviceState,
    Frame,
    Hello,
    Message,
    MsgType,
    Nak,
    Ping,
    QueryInfo,
    Scan,
    ScanFlag,
    SetScanRate,
    Start,
    Status,
    Stop,
    StreamDecoder,
    encode_frame,
    step_period_ns,
)
from skinmap.protocol import ErrorCode, hello_compatibility

__all__ = ["LinkError", "LinkStats", "ScannerLink", "serial_port_factory", "validate_hello"]

READ_TIMEOUT_S = 0.02
# StreamDecoder counters of damaged frames it refused (the decoder's last_error says why).
# Intact frames of an unknown type are not damage: they are `unknown_frames`.
_REJECT_COUNTERS = ("cobs_errors", "crc_errors", "length_errors", "version_errors", "incompat_flag_drops",
                    "field_errors", "oversize_frames")
FRAME_ERROR_REPORT_S = 1.0  # at most one event per kind of fault per this interval
# A sign of trouble (a foreign answer, an unsolicited HELLO, refused scans) keeps the link
# unhealthy this long after the last one.
CONDITION_HOLD_S = 3.0
PING_PERIOD_S = 1.0  # liveness probe while streaming; answers to other hosts' probes reveal them
REBOOT_WINDOW_S = 10.0
REBOOT_LIMIT = 3  # more reboots than this within REBOOT_WINDOW_S: stop and back off
# A session must stream this long before the reconnect backoff starts again from its minimum
# (a device that fails right after every handshake is retried ever more slowly).
BACKOFF_RESET_AFTER_S = 5.0
# A device the host refuses (incompatible, absurd HELLO) is retried up to this many times more
# slowly than a vanished one: it will not change by itself, yet must be found once replaced.
REFUSED_BACKOFF_FACTOR = 8
RATE_TOLERANCE = 0.02  # applied rate / step period may differ this much from the request (TDM rounding)
INDEX_SLACK = 64  # sample-index jumps plausible beyond elapsed time × rate (buffering, clock drift)
SENT_IDS_REMEMBERED = 64
# A port lost this often is unstable (a loose cable, or another host taking a socket:// port
# over in turn): the link says so while it streams in between.
FLAP_WINDOW_S = 30.0
FLAP_LIMIT = 3
FLAP_HOLD_S = 10.0


class LinkError(RuntimeError):
    """The scanner did not behave as the protocol requires (no HELLO, NAK, absurd values)."""


class DeviceRefused(LinkError):
    """The host will not serve this device now: it describes itself unacceptably, or it keeps
    rebooting. Retried more slowly than a vanished port."""


def serial_port_factory(cfg: DeviceConfig) -> PortFactory:
    """Opens ``cfg.port`` (a device path or a pyserial URL) afresh at every call; exclusive
    access on real ttys when ``cfg.exclusive``."""
    return functools.partial(SerialScannerPort, cfg.port, cfg.baudrate, exclusive=cfg.exclusive)


def validate_hello(hello: Hello, cfg: DeviceConfig) -> None:
    """Refuse a device description the daemon cannot or should not serve."""
    compat = hello_compatibility(hello)
    if not compat.usable:
        raise DeviceRefused(f"incompatible scanner: {compat.note}")
    n, m = hello.n, hello.m
    if n * m > cfg.max_cells:
        raise DeviceRefused(f"scanner reports {n}×{m} = {n * m} cells, more than device.max_cells = {cfg.max_cells}")
    if not 1_000 <= hello.pitch_um <= 100_000:
        raise DeviceRefused(f"scanner reports pitch {hello.pitch_um} µm, outside 1–100 mm")
    if not 0 < hello.gauge_length_um <= hello.pitch_um:
        # A gauge longer than the pitch would overlap its neighbours; the strain model needs
        # 0 < length <= pitch, and every scan would fail to reconstruct.
        raise DeviceRefused(f"scanner reports gauge length {hello.gauge_length_um} µm, "
                            f"outside (0, pitch {hello.pitch_um}] µm")
    if not (0 < hello.h_upper_um <= 10_000 and 0 < hello.h_lower_um <= 10_000):
        raise DeviceRefused(f"scanner reports layer offsets {hello.h_upper_um}/{hello.h_lower_um} µm, outside (0, 10] mm")
    gf = hello.gauge_factor()
    r0 = hello.base_resistance_ohm()
    if not ((gf > 0.05).all() and (gf < 20).all()):
        raise DeviceRefused("scanner reports a gauge factor outside 0.05–20")
    if not ((r0 > 1e-3).all() and (r0 < 1e5).all()):
        raise DeviceRefused("scanner reports a base resistance outside 1 mΩ–100 kΩ")


@dataclass
class LinkStats:
    connects: int = 0
    reconnects: int = 0
    disconnects: int = 0
    stalls: int = 0
    reboots: int = 0
    scans: int = 0
    scans_lost: int = 0  # missing sample indices not explained by the device (lost on the link)
    handshake_failures: int = 0
    bytes_in: int = 0
    state: str = "starting"
    last_error: str = ""
    frames_rejected: int = 0  # damaged frames the decoder refused (sum of its error counters)
    last_frame_error: str = ""
    decoder: dict[str, int] = field(default_factory=dict)
    # Link accounting beyond the decoder's (published inside `decoder`, docs/zenoh.md):
    unknown_frames: int = 0  # intact frames of a type this host does not know (vendor, newer minor)
    scans_dropped_by_device: int = 0  # missing indices the device flagged DROPPED_BEFORE
    scans_repeated_index: int = 0  # SCANs repeating the previous sample index (refused)
    scans_wrong_size: int = 0  # SCANs whose N×M disagrees with HELLO (refused)
    index_resyncs: int = 0  # implausible sample-index jumps and unexplained restarts
    unsolicited_hellos: int = 0  # HELLOs with seq != 0 that answer no QUERY_INFO of this host
    foreign_answers: int = 0  # ACK/NAKs for request ids this host never sent
    rate_mismatches: int = 0  # SCANs whose step period contradicts the confirmed scan rate
    applied_scan_rate_mhz: int = 0  # the rate the device confirmed in its ACK of SET_SCAN_RATE
    backoff_s: float = 0.0  # the wait before the latest reopen attempt

    EXTRA = ("unknown_frames", "scans_dropped_by_device", "scans_repeated_index", "scans_wrong_size",
             "index_resyncs", "unsolicited_hellos", "foreign_answers", "rate_mismatches",
             "applied_scan_rate_mhz")

    def as_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "decoder"}
        d.update({f"decoder_{k}": v for k, v in self.decoder.items()})
        return d


class ScannerLink:
    """Runs the scanner connection in its own thread.

    Callbacks (called from the link thread; they must not block):
      on_hello(hello)                 after every successful handshake
      on_scan(scan, frame, t_rx_ns)   every SCAN accepted (right size, new sample index)
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
        port_factory: PortFactory | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.cfg = cfg
        self._on_hello, self._on_scan, self._on_frame = on_hello, on_scan, on_frame
        self._on_event, self._on_alive = on_event, on_alive
        # Opened by its path each time: a device that returns behind the same name is found again.
        self._port_factory = port_factory or serial_port_factory(cfg)
        self._clock_ns = clock_ns
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._port: ScannerPort | None = None
        self._decoder = StreamDecoder()
        self._tx_seq = 0
        # A device that was not power-cycled remembers its last answers by request id and replays
        # them without executing (PROTOCOL.md §8): a host restarting its counter at 0 would have
        # its new commands taken for retries of the previous session's.
        self._request_id = random.randrange(0x10000)
        self._sent_ids: collections.deque[int] = collections.deque(maxlen=SENT_IDS_REMEMBERED)
        self.stats = LinkStats()
        self.hello: Hello | None = None
        self.device_status: Status | None = None
        self.streaming = threading.Event()
        self._last_sample: int | None = None
        self._last_sample_mono = 0.0
        self._last_sample_us = 0
        self._last_scan_mono = 0.0  # last accepted scan
        self._last_rx_scan_mono = 0.0  # last SCAN frame of any kind
        self._rejected_reported = 0
        self._garbage_reported = 0
        self._next_reject_report = 0.0
        self._next_report: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._query_until = 0.0  # a HELLO before this answers a QUERY_INFO of ours
        self._reboot_times: collections.deque[float] = collections.deque()
        self._drop_times: collections.deque[float] = collections.deque()
        self._trouble_until = 0.0  # while now < this, the link reports `_trouble` instead of streaming
        self._trouble_state = ""
        self._trouble = ""
        self._scan_problem = ""  # why arriving scans are refused (names the stall)
        self._scan_problem_mono = 0.0
        self._expected_step_ns = 0

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
            cap = self.cfg.reconnect_max_s
            session_start = time.monotonic()
            streamed_s = 0.0
            try:
                self._connect()
                if not first:
                    self.stats.reconnects += 1
                first = False
                self._handshake()
                session_start = time.monotonic()
                self._stream()
            except OSError as exc:  # a PortError, or an OS error a port implementation let through
                self._fault("warning", "disconnected", f"serial port {self.cfg.port}: {exc}")
                self.stats.disconnects += 1
                if self.streaming.is_set() or self._trouble_until:
                    self._drop_times.append(time.monotonic())  # a streaming port lost (not a failed reopen)
            except LinkError as exc:
                if isinstance(exc, DeviceRefused):
                    cap = self.cfg.reconnect_max_s * REFUSED_BACKOFF_FACTOR
                self._fault("error", "handshake-failed", str(exc))
                self.stats.handshake_failures += 1
            finally:
                if self.streaming.is_set():
                    streamed_s = time.monotonic() - session_start
                self.streaming.clear()
                self._close_port()
            if self._stop.is_set():
                break
            if streamed_s >= BACKOFF_RESET_AFTER_S:
                backoff = self.cfg.reconnect_min_s
            self.stats.state = "reconnecting"
            self.stats.backoff_s = backoff
            self._on_alive()
            self._stop.wait(backoff)
            if backoff >= 1.0:
                self._on_event("info", f"retrying {self.cfg.port} after {backoff:g} s")
            backoff = min(backoff * 2, cap)
        self.stats.state = "stopped"

    def _fault(self, level: str, state: str, text: str) -> None:
        self.stats.state = state
        self.stats.last_error = text
        self._on_event(level, text)

    def _report(self, key: str, level: str, text: str) -> None:
        """An event at most once per FRAME_ERROR_REPORT_S per kind; repeats are counted into
        the next one (the counters hold the exact totals)."""
        now = time.monotonic()
        if now < self._next_report.get(key, 0.0):
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        more = self._suppressed.pop(key, 0)
        self._next_report[key] = now + FRAME_ERROR_REPORT_S
        self._on_event(level, text + (f" (+{more} more since the last report)" if more else ""))

    def _connect(self) -> None:
        self.stats.state = "connecting"
        self._port = port = self._port_factory()
        self._decoder.reset()
        self._last_sample = None
        self._tx_seq = 0  # PROTOCOL.md §5: the host numbers its frames from 0 on every open
        self._query_until = 0.0
        self.stats.connects += 1
        try:
            port.reset_input()  # bytes of an earlier session are not this one's
        except PortError:
            pass  # a port gone already says so at the first recv
        self._on_event("info", f"opened {self.cfg.port}")

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            port.close()  # never raises, whatever state the device is in

    # -- I/O helpers -----------------------------------------------------------------------

    def _send(self, msg: Message) -> None:
        rid = getattr(msg, "request_id", None)
        if rid is not None and (not self._sent_ids or self._sent_ids[-1] != rid):
            self._sent_ids.append(rid)
        if isinstance(msg, QueryInfo):
            # HELLOs within the handshake timeout answer it (retries are answered from the
            # device's memory, ACK and HELLO again).
            self._query_until = time.monotonic() + self.cfg.handshake_timeout_s
        if self._port is None:
            raise PortError(f"serial port {self.cfg.port} is not open")
        self._port.send(encode_frame(msg, self._tx_seq))
        self._tx_seq = (self._tx_seq + 1) & 0xFFFF

    def _next_request_id(self) -> int:
        self._request_id = (self._request_id + 1) & 0xFFFF
        return self._request_id

    def _read_frames(self) -> list[Frame]:
        if self._port is None:
            raise PortError(f"serial port {self.cfg.port} is not open")
        data = self._port.recv(READ_TIMEOUT_S)  # b"" on a timeout; PortVanished when unplugged
        if not data:
            return []
        self.stats.bytes_in += len(data)
        t_rx = self._clock_ns()
        frames = self._decoder.feed(data)
        self._report_frame_errors()
        reboot: _Rebooted | None = None
        answered: Hello | None = None  # the answer to our own QUERY_INFO
        for f in frames:
            self._on_frame(f, t_rx)
            msg = f.msg
            if isinstance(msg, Scan):
                if self.streaming.is_set() or self._trouble_until:
                    self._handle_scan(f, t_rx)
            elif isinstance(msg, Status):
                self.device_status = msg
            elif isinstance(msg, (Ack, Nak)):
                self._check_answer(msg)
            elif isinstance(msg, Hello):
                solicited = time.monotonic() < self._query_until
                if f.seq == 0:
                    # PROTOCOL.md §5: a HELLO with seq 0 is a device that (re)booted.
                    if self.stats.state not in ("handshake", "connecting"):
                        reboot = _Rebooted(msg)
                elif self.streaming.is_set() or self._trouble_until:
                    if solicited:
                        answered = msg
                    elif self._unsolicited_hello(f):
                        reboot = _Rebooted(msg, booted=False)
        self.stats.decoder = self._decoder.counters()
        self.stats.frames_rejected = self._rejected_frames()
        self.stats.unknown_frames = self._decoder.unknown_type
        self.stats.last_frame_error = self._decoder.last_error or ""
        self._publish_extra()
        if reboot is None and answered is not None:
            # The answer to a stall's QUERY_INFO: handshake again if the device is not scanning
            # (it rebooted unseen: its STATUS says IDLE), or describes itself differently; not
            # after a firmware hang, whose scans resume by themselves.
            scanning = (time.monotonic() - self._last_rx_scan_mono < self.cfg.stall_timeout_s
                        or (self.device_status is not None and self.device_status.state == DeviceState.SCANNING))
            if not scanning or answered != self.hello:
                reboot = _Rebooted(answered, booted=False)
        if reboot is not None:
            raise reboot
        return frames

    def _publish_extra(self) -> None:
        # The status message publishes the `decoder` dict whole: the link's own accounting
        # travels in it (docs/zenoh.md).
        d = self.stats.decoder
        for name in LinkStats.EXTRA:
            d[name] = int(getattr(self.stats, name))

    def _report_frame_errors(self) -> None:
        """Name damaged input in the event log, at most once per FRAME_ERROR_REPORT_S (the
        decoder's counters hold the exact totals)."""
        rejected = self._rejected_frames()
        now = time.monotonic()
        unknown = self._decoder.unknown_type
        if unknown != self.stats.unknown_frames:
            self._report("unknown", "info", f"serial link: {unknown} frame(s) of unknown type ignored so far "
                                            f"(last: {self._decoder.last_error})")
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

    # -- signs of another host, or of a device that misbehaves -----------------------------

    def _trouble_begin(self, state: str, text: str, hold_s: float = CONDITION_HOLD_S) -> None:
        """Mark the link unhealthy for `hold_s`: `streaming` is cleared (status `connected`
        false, warning "scanner not streaming (<state>): <text>"), scans still flow."""
        self._trouble_until = max(self._trouble_until, time.monotonic() + hold_s)
        self._trouble_state, self._trouble = state, text
        if self.streaming.is_set() or self.stats.state != state:
            self.streaming.clear()
            self.stats.state = state
        self.stats.last_error = text

    def _trouble_tick(self) -> None:
        if self._trouble_until and time.monotonic() >= self._trouble_until:
            self._trouble_until = 0.0
            self.stats.state = "streaming"
            self.streaming.set()
            self._on_event("info", f"{self._trouble_state} condition over; streaming")

    def _check_flapping(self) -> None:
        now = time.monotonic()
        drops = self._drop_times
        while drops and now - drops[0] > FLAP_WINDOW_S:
            drops.popleft()
        if len(drops) >= FLAP_LIMIT:
            text = (f"serial link unstable: lost {len(drops)} times in the last {FLAP_WINDOW_S:g} s (last: "
                    f"{self.stats.last_error}); a loose connection, or another host taking the port over")
            self._trouble_begin("unstable", text, FLAP_HOLD_S)
            self._report("unstable", "error", text)

    def _check_answer(self, reply: Ack | Nak) -> None:
        if reply.request_id in self._sent_ids or not (self.streaming.is_set() or self._trouble_until):
            return
        self.stats.foreign_answers += 1
        what = "ACK" if isinstance(reply, Ack) else "NAK"
        try:
            cmd = MsgType(reply.command).name
        except ValueError:
            cmd = f"0x{reply.command:02X}"
        text = (f"another host is commanding the scanner on {self.cfg.port}: {what} of {cmd} for request id "
                f"{reply.request_id}, which this host never sent ({self.stats.foreign_answers} so far)")
        self._trouble_begin("contended", text)
        self._report("foreign", "error", text)

    def _unsolicited_hello(self, frame: Frame) -> bool:
        """Count and report a HELLO nobody here asked for; True if it describes another device
        than the one being served (then it is served anew)."""
        self.stats.unsolicited_hellos += 1
        text = (f"unsolicited HELLO (seq {frame.seq}, not a reboot): another host sent QUERY_INFO, or the "
                f"scanner misbehaves ({self.stats.unsolicited_hellos} so far)")
        self._trouble_begin("contended", text)
        self._report("hello", "warning", text)
        return self.hello is not None and frame.msg != self.hello

    # -- commands --------------------------------------------------------------------------

    def _request(self, msg: Stop | SetScanRate | Start, what: str, retries: int = 3) -> Ack:
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

    def _stop_device(self) -> None:
        """Best effort STOP for a device the host will not serve: it must not keep streaming
        into a port nobody reads (no wait for the ACK: the device may not understand us)."""
        try:
            if self._port is not None:
                self._send(Stop(self._next_request_id()))
        except OSError:
            pass

    # -- protocol steps --------------------------------------------------------------------

    def _query_hello(self) -> Hello:
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
                self._stop_device()
                raise DeviceRefused(f"no HELLO from {self.cfg.port} within {self.cfg.handshake_timeout_s:g} s{why}")
            raise LinkError(f"no HELLO from {self.cfg.port} within {self.cfg.handshake_timeout_s:g} s")
        return hello

    def _handshake(self, hello: Hello | None = None) -> None:
        """QUERY_INFO (unless `hello` just arrived), validate, STOP, SET_SCAN_RATE (confirmed),
        START. Nothing is started on a device whose rate was not confirmed."""
        self.streaming.clear()
        self._trouble_until = 0.0
        self.stats.state = "handshake"
        if hello is None:
            hello = self._query_hello()
        try:
            validate_hello(hello, self.cfg)
        except LinkError:
            self._stop_device()
            raise
        self.hello = hello
        self._on_hello(hello)
        rate_mhz = int(round(self.cfg.scan_rate_hz * 1000))
        if hello.max_scan_rate_mhz and rate_mhz > hello.max_scan_rate_mhz:
            self._on_event("warning", f"requested {self.cfg.scan_rate_hz:g} scans/s, scanner allows {hello.max_scan_rate_mhz / 1000:g}")
            rate_mhz = hello.max_scan_rate_mhz
        # A scanner that kept running (host restarted, port glitch without a power cycle) is
        # still SCANNING and refuses SET_SCAN_RATE there; STOP is accepted in every state.
        self._request(Stop(self._next_request_id()), "STOP")
        ack = self._request(SetScanRate(self._next_request_id(), rate_mhz), "SET_SCAN_RATE")
        applied = int.from_bytes(ack.result, "little") if len(ack.result) == 4 else None
        if applied is None:
            raise LinkError(f"scanner's ACK of SET_SCAN_RATE carries {len(ack.result)} result byte(s), "
                            "not the 4-byte applied rate: the rate cannot be confirmed")
        if abs(applied - rate_mhz) > RATE_TOLERANCE * rate_mhz:
            raise LinkError(f"scanner applied {applied / 1000:g} scans/s for the requested {rate_mhz / 1000:g} "
                            "(ACK of SET_SCAN_RATE)")
        self.stats.applied_scan_rate_mhz = applied
        self._expected_step_ns = step_period_ns(applied, hello.n, hello.m)
        # START restarts the scan index: scans before it (a still-running device) and after it
        # continue no count, and a retried START (lost ACK) must not read as a restart.
        self._last_sample = None
        self._request(Start(self._next_request_id()), "START")
        self._scan_problem = ""
        self._last_scan_mono = self._last_rx_scan_mono = time.monotonic()
        self.streaming.set()
        self.stats.state = "streaming"
        self._on_event("info", f"scanner {hello.serial_number} {hello.n}×{hello.m} streaming at {applied / 1000:g} scans/s")
        self._check_flapping()

    def _refuse_scan(self, key: str, text: str) -> None:
        self._scan_problem, self._scan_problem_mono = text, time.monotonic()
        self._report(key, "warning", text)

    def _handle_scan(self, frame: Frame, t_rx: int) -> None:
        scan: Scan = frame.msg  # type: ignore[assignment]
        now = time.monotonic()
        self._last_rx_scan_mono = now
        hello = self.hello
        if hello is None:
            return
        if (scan.n, scan.m) != (hello.n, hello.m):
            self.stats.scans_wrong_size += 1
            self._refuse_scan("size", f"scan size {scan.n}×{scan.m} disagrees with HELLO {hello.n}×{hello.m}: "
                                      f"{self.stats.scans_wrong_size} scan(s) refused")
            # It arrived: its index still counts, so the gap after it is no loss.
            self._last_sample, self._last_sample_mono, self._last_sample_us = scan.sample_index, now, scan.timestamp_us
            return
        if self._expected_step_ns and abs(scan.step_period_ns - self._expected_step_ns) > RATE_TOLERANCE * self._expected_step_ns:
            self.stats.rate_mismatches += 1
            running = 1e12 / (scan.step_period_ns * 2 * min(scan.n, scan.m)) if scan.step_period_ns else 0.0
            text = (f"scanner scans at {running:.4g} scans/s (step period {scan.step_period_ns} ns), not the "
                    f"{self.stats.applied_scan_rate_mhz / 1000:g} it confirmed")
            if not self._trouble_until:
                raise LinkError(text)  # set the rate again with a fresh handshake (after backoff)
            self._report("rate", "warning", text)
        last = self._last_sample
        index = scan.sample_index
        if last is not None:
            gap = (index - last) & 0xFFFFFFFF
            if gap == 0:
                # The same index again: a duplicate or a stuck counter, not a restart and no loss.
                self.stats.scans_repeated_index += 1
                self._refuse_scan("repeat", f"scan index {index} repeated: {self.stats.scans_repeated_index} "
                                            "scan(s) with a repeated index refused (stuck or duplicated index)")
                return
            # Time passed by the host's clock or by the device's (scans read late arrive in a burst:
            # the device clock then says how far apart they were taken).
            device_elapsed = (scan.timestamp_us - self._last_sample_us) * 1e-6
            elapsed = max(now - self._last_sample_mono, device_elapsed, 0.0)
            plausible = elapsed * self.stats.applied_scan_rate_mhz / 1000 * 2 + INDEX_SLACK
            if index == 0 or scan.flags & ScanFlag.FIRST_AFTER_START or gap > 0x7FFFFFFF or gap - 1 > plausible:
                # A restart this host did not ask for, or a jump no elapsed time explains:
                # resynchronise on the new index; nothing is counted as lost.
                self.stats.index_resyncs += 1
                text = (f"scan index went from {last} to {index} after {elapsed:.2f} s without a START from this "
                        f"host: not a plausible advance; resynchronised, not counted as lost "
                        f"({self.stats.index_resyncs} so far)")
                self._trouble_begin("resynced", text)
                self._report("resync", "warning", text)
            elif gap > 1:
                if scan.flags & ScanFlag.DROPPED_BEFORE:
                    self.stats.scans_dropped_by_device += gap - 1
                else:
                    self.stats.scans_lost += gap - 1
        self._last_sample, self._last_sample_mono, self._last_sample_us = index, now, scan.timestamp_us
        self.stats.scans += 1
        self._last_scan_mono = now
        self._on_scan(scan, frame, t_rx)

    def _note_reboot(self) -> None:
        now = time.monotonic()
        self.stats.reboots += 1
        times = self._reboot_times
        times.append(now)
        while times and now - times[0] > REBOOT_WINDOW_S:
            times.popleft()
        if len(times) > REBOOT_LIMIT:
            # The window is kept: while the storm lasts every further reboot backs off at once.
            raise DeviceRefused(f"scanner rebooted {len(times)} times within {REBOOT_WINDOW_S:g} s (HELLO storm); "
                                "backing off before the next handshake")

    def _stream(self) -> None:
        stalled = False
        next_kick = 0.0
        next_ping = time.monotonic() + PING_PERIOD_S
        while not self._stop.is_set():
            try:
                self._read_frames()
            except _Rebooted as rb:
                self.streaming.clear()
                if rb.booted:
                    self._on_event("warning", "scanner rebooted (HELLO with seq 0); handshaking again")
                    self._note_reboot()
                else:
                    self._on_event("info", "scanner described itself anew (HELLO); handshaking again")
                self._handshake(rb.hello)
                stalled = False
                continue
            now = time.monotonic()
            self._trouble_tick()
            self._on_alive()
            if now >= next_ping:
                next_ping = now + PING_PERIOD_S
                self._send_quietly(Ping(self._next_request_id()))
            idle = now - self._last_scan_mono
            if idle < self.cfg.stall_timeout_s:
                if stalled:
                    stalled = False
                    self.stats.state = "streaming"
                    self._on_event("info", "scans resumed")
                continue
            why = f"no scan for {idle:.2f} s"
            if self._scan_problem and now - self._scan_problem_mono < self.cfg.stall_timeout_s:
                why = f"{why}; {self._scan_problem}"
            if not stalled:
                stalled = True
                self.stats.stalls += 1
                self._fault("warning", "stalled", why)
                next_kick = now
            else:
                self.stats.last_error = why
                if self.stats.state != "stalled" and not self._trouble_until:
                    self.stats.state = "stalled"
            if now >= next_kick and not (self._trouble_until and self._trouble_state == "contended"):
                # Keep the port open (data resumes at once when the device does) and ask who is
                # there: its HELLO leads to a full handshake (rate set and confirmed, then START),
                # never a bare START that would run the device at whatever rate it has.
                next_kick = now + self.cfg.stall_timeout_s
                if now - self._last_rx_scan_mono >= self.cfg.stall_timeout_s:
                    self._send_quietly(QueryInfo(self._next_request_id()))

    def _send_quietly(self, msg: Message) -> None:
        try:
            self._send(msg)
        except PortWriteTimeout:
            pass  # a stuck device: the stall handling deals with it


class _Rebooted(Exception):
    def __init__(self, hello: Hello, booted: bool = True) -> None:
        super().__init__("HELLO mid-stream")
        self.hello = hello
        self.booted = booted
