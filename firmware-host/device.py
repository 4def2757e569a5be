"""The scanner firmware as a pure state machine: bytes and time in, bytes out, no I/O.

    dev = Device(ScannerSpec(n=5, m=5), shape, now_s=0.0)
    out = dev.poll(0.0)            # HELLO at boot
    out = dev.on_bytes(data, now)  # answers to host commands (ACK/NAK, HELLO for QUERY_INFO)
    out = dev.poll(now)            # SCANs that are due, periodic STATUS

Time is whatever monotonic clock the caller passes (seconds); the device clock in SCAN/STATUS
timestamps counts from the last boot, the shape's clock (``shape_time``) from the device's
creation, so the world keeps moving through reboots.

Acquisition follows the row-column time-division multiplexing of the hardware: a scan is
2·min(N, M) TDM steps at F_scan = 2·min(N, M)·scan_rate; step s samples the units on drive line
s at ``timestamp + s·step_period`` and a time-varying shape is evaluated at exactly that instant.
A scan is sent once its last step has completed.
"""
from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from skinmap.emulator.electrical import (
    ElectricalConfig,
    GaugeConstants,
    GaugeReadout,
    draw_calibration,
    draw_true_constants,
)
from skinmap.emulator.physics import GroundTruth, Shape, gauge_strains, ground_truth
from skinmap.protocol import (
    MAX_DIM,
    MIN_DIM,
    RES_OPEN,
    RES_SATURATED,
    Ack,
    DeviceState,
    ErrorCode,
    FaultFlag,
    FieldError,
    Hello,
    LengthError,
    Nak,
    Ping,
    ProtocolError,
    QueryInfo,
    Reset,
    Scan,
    ScanFlag,
    SetScanRate,
    Start,
    Status,
    Stop,
    UnknownMessageTypeError,
    decode_frame,
    default_channel_map,
    encode_frame,
    step_period_ns,
    tdm_steps,
)
from skinmap.protocol.framing import HEADER, decode_body, encode_body
from skinmap.strains import GAUGE_LENGTH_MM

__all__ = ["ScannerSpec", "Device", "HostileModes", "ScanRecord"]

FW_VERSION = (0, 1, 0)
STATUS_PERIOD_S = 1.0
RETRY_MEMORY = 8  # answered commands remembered for idempotent retries (PROTOCOL.md §8)
# Completed scans still sent when poll() comes late (the emulator's loop was busy, or a caller
# polls coarsely); older ones count as dropped.
MAX_BACKLOG_SCANS = 8
# fault bits that describe "since the previous STATUS" rather than a present condition
_TRANSIENT_FAULTS = int(FaultFlag.SCAN_BUFFER_OVERRUN | FaultFlag.HOST_FRAME_ERRORS)
_HOST_FRAME_LIMIT = 300  # receive buffer (PROTOCOL.md §13); longer bodies are skipped to the next 0x00


@dataclass(frozen=True)
class ScannerSpec:
    """Geometry, rates and identity of an emulated scanner."""

    n: int = 5
    m: int = 5
    pitch_mm: float = 12.0
    gauge_length_mm: float = GAUGE_LENGTH_MM
    h_upper_mm: float = 0.2
    h_lower_mm: float = 0.2
    scan_rate_hz: float = 10.0
    max_step_rate_hz: float = 4000.0  # the DAQ's TDM step rate limit
    seed: int = 0
    electrical: ElectricalConfig = field(default_factory=ElectricalConfig)
    serial_number: str | None = None
    # Gauss–Legendre panels of 8 points per gauge: one keeps the model within 2e-8 strain of the
    # converged value for every built-in shape, far below the 1 µΩ quantum (~1.2e-7)
    quadrature_panels: int = 1
    # Hidden truths (0 = none): the relative s.d. by which the gauges' true gauge factors depart
    # from the factory values in HELLO, and by which each unit's true layer offsets depart from
    # the nominal h_upper_mm / h_lower_mm.  Never on the wire; see Device.hidden_truth().
    gf_spread: float = 0.0
    offset_spread: float = 0.0

    def __post_init__(self):
        for name in ("gf_spread", "offset_spread"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v < 0.3):
                raise ValueError(f"DeviceConfig.{name} must be a relative spread in [0, 0.3), got {v!r}")
        for name in ("n", "m"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or not MIN_DIM <= v <= MAX_DIM:
                raise ValueError(f"ScannerSpec.{name} must be an integer in {MIN_DIM}..{MAX_DIM}, got {v!r}")
        for name in ("pitch_mm", "gauge_length_mm", "scan_rate_hz", "max_step_rate_hz"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ScannerSpec.{name} must be a positive number, got {v!r}")
        for name in ("h_upper_mm", "h_lower_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v < 65.535):
                raise ValueError(f"ScannerSpec.{name} must be in 0..65 mm, got {v!r}")
        if self.scan_rate_hz > self.max_scan_rate_hz:
            raise ValueError(
                f"ScannerSpec.scan_rate_hz {self.scan_rate_hz} exceeds the maximum "
                f"{self.max_scan_rate_hz:g} scans/s of a {self.n}x{self.m} array"
            )
        if self.serial_number is not None and (len(self.serial_number) > 16 or not self.serial_number.isascii()):
            raise ValueError(f"ScannerSpec.serial_number must be <= 16 ASCII characters, got {self.serial_number!r}")

    @property
    def steps(self) -> int:
        return tdm_steps(self.n, self.m)

    @property
    def max_scan_rate_hz(self) -> float:
        return self.max_step_rate_hz / self.steps


@dataclass(frozen=True)
class ScanRecord:
    """What the device knows about a scan it sent (for ground truth; never on the wire)."""

    sample_index: int
    boot: int  # boot counter: sample indices restart at every boot
    timestamp_us: int
    step_period_ns: int
    shape_time_s: float  # shape clock at TDM step 0

    def unit_times_s(self, drive_line: np.ndarray) -> np.ndarray:
        """Shape-clock sampling instant of every unit, shaped like ``drive_line`` (2, N, M)."""
        return self.shape_time_s + np.asarray(drive_line, dtype=float) * self.step_period_ns * 1e-9


@dataclass
class HostileModes:
    """Ways a scanner can break the protocol, for robustness tests (all off by default; they
    may be changed while running). A conforming device never does any of this."""

    hello_gauge_length_um: int | None = None  # HELLO reports this gauge length
    hello_protocol_major: int | None = None  # HELLO claims this protocol major version
    repeat_sample_index: bool = False  # every SCAN carries the same sample index
    scan_dims: tuple[int, int] | None = None  # SCANs of this N×M, whatever HELLO says
    hello_storm_hz: float = 0.0  # unsolicited HELLOs (seq continuing) per second, scanning goes on
    vendor_frame_hz: float = 0.0  # intact frames of vendor type 0x80 per second
    drop_every: int = 0  # the device drops every k-th scan itself (DROPPED_BEFORE, scans_dropped)
    lose_start_acks: int = 0  # the ACKs of the next k START commands never leave the device
    lose_boot_hello: bool = False  # the HELLO sent at boot is lost
    index_jump: int = 0  # added once to the next SCAN's sample index, then reset to 0


VENDOR_FRAME_TYPE = 0x80


class Device:
    """Emulated scanner firmware.  Faults are injected through :meth:`set_open`,
    :meth:`set_saturated`, :meth:`stall`, :meth:`reboot` (byte-level faults live in the link)."""

    def __init__(self, config: ScannerSpec, shape: Shape, now_s: float = 0.0):
        self.config = config
        self.shape = shape
        self._epoch = float(now_s)
        rng = np.random.default_rng(config.seed)
        self.calibration: GaugeConstants = draw_calibration(rng, config.n, config.m)
        truth_rng = np.random.default_rng([config.seed, 3])
        self._true_constants = draw_true_constants(truth_rng, self.calibration, config.gf_spread)
        rel = np.clip(truth_rng.standard_normal((2, 2, config.n, config.m)), -3.0, 3.0) * config.offset_spread
        self._true_h_upper = config.h_upper_mm * (1.0 + rel[0])  # (2, N, M) per unit
        self._true_h_lower = config.h_lower_mm * (1.0 + rel[1])
        self._noise_rng = np.random.default_rng([config.seed, 1])
        self.drive_line, self.sense_channel = default_channel_map(config.n, config.m)
        self.open_gauges = np.zeros((2, 2, config.n, config.m), dtype=bool)
        self.saturated_gauges = np.zeros((2, 2, config.n, config.m), dtype=bool)
        self.readout = GaugeReadout(
            self._true_constants, config.electrical, self._noise_rng, self.open_gauges, self.saturated_gauges
        )
        self.serial_number = config.serial_number or f"EMU-{config.seed & 0xFFFFFFFF:08X}"
        self.boot_count = 0
        self.history: OrderedDict[tuple[int, int], ScanRecord] = OrderedDict()
        self.history_limit = 4096
        self._static_strain: np.ndarray | None = None
        #: called with the ScanRecord of every scan sent (ground-truth logging)
        self.on_scan: Callable[[ScanRecord], None] | None = None
        #: fault injection: maps the true clock (µs since boot) to the one the firmware reports
        self.time_us: Callable[[int], int] | None = None
        # the first evaluation may build tables (key-framed elastic scenes): do it before the
        # scanner boots, not while the first scan falls due
        self.strains(0.0)
        self.hostile = HostileModes()
        self._next_storm = self._next_vendor = float(now_s)
        self._scan_count = 0
        self._boot(now_s, watchdog=False)

    # ------------------------------------------------------------------ state and clocks

    def _boot(self, now_s: float, watchdog: bool) -> None:
        self.boot_count += 1
        self._boot_time = float(now_s)
        self._seq = 0
        self.state = DeviceState.IDLE
        self.scan_rate_mhz = self._apply_rate_mhz(round(self.config.scan_rate_hz * 1000))
        self.sample_index = 0
        self._next_t0: float | None = None
        self.scans_sent = 0
        self.scans_dropped = 0
        self.frames_rejected = 0
        self._dropped_since_last = False
        self._answers: OrderedDict[tuple[int, int], list] = OrderedDict()
        self._rx = bytearray()
        self._rx_skipping = False
        self._stall_until = -math.inf
        self._watchdog = watchdog
        self._adc_fault = False
        self._hello_due = True  # boot: 0x00, HELLO (seq 0), then STATUS
        self._status_due = True
        self._next_status = float(now_s) + STATUS_PERIOD_S
        self._reported = (self.state, 0, 0, 0)  # state, faults, scans_dropped, frames_rejected
        self._last_open = np.zeros_like(self.open_gauges)
        self._last_saturated = np.zeros_like(self.saturated_gauges)
        self.readout.reset_state()

    def device_time_us(self, now_s: float) -> int:
        t = max(0, int(round((now_s - self._boot_time) * 1e6)))
        return t if self.time_us is None else max(0, int(self.time_us(t)))

    def shape_time(self, now_s: float) -> float:
        return now_s - self._epoch

    @property
    def step_period_ns(self) -> int:
        return step_period_ns(self.scan_rate_mhz, self.config.n, self.config.m)

    @property
    def scan_period_s(self) -> float:
        return self.config.steps * self.step_period_ns * 1e-9

    @property
    def max_scan_rate_mhz(self) -> int:
        return int(self.config.max_scan_rate_hz * 1000)

    def _apply_rate_mhz(self, requested_mhz: int) -> int:
        """The rate actually run: the TDM step period is a whole number of ns."""
        period = step_period_ns(requested_mhz, self.config.n, self.config.m)
        return int(round(1e12 / (period * self.config.steps)))

    def fault_flags(self) -> int:
        """Present fault bits; the two "since the previous STATUS" bits compare the counters
        with the values the last STATUS reported."""
        flags = 0
        if self._last_open.any() or (self.state != DeviceState.SCANNING and self.open_gauges.any()):
            flags |= FaultFlag.GAUGE_OPEN
        if self._last_saturated.any() or (
            self.state != DeviceState.SCANNING and self.saturated_gauges.any()
        ):
            flags |= FaultFlag.GAUGE_SATURATED
        if self.scans_dropped != self._reported[2]:
            flags |= FaultFlag.SCAN_BUFFER_OVERRUN
        if self._watchdog:
            flags |= FaultFlag.WATCHDOG_RESET
        if self._adc_fault:
            flags |= FaultFlag.ADC_FAULT
        if self.frames_rejected != self._reported[3]:
            flags |= FaultFlag.HOST_FRAME_ERRORS
        return int(flags)

    # ------------------------------------------------------------------ output

    def _frame(self, msg) -> bytes:
        data = encode_frame(msg, self._seq)
        self._seq = (self._seq + 1) & 0xFFFF
        return data

    def hello(self) -> Hello:
        gf, r0 = self.calibration.micro_units()
        c = self.config
        hello = Hello(
            fw_version=FW_VERSION,
            serial_number=self.serial_number,
            pitch_um=int(round(c.pitch_mm * 1000)),
            gauge_length_um=int(round(c.gauge_length_mm * 1000)),
            h_upper_um=int(round(c.h_upper_mm * 1000)),
            h_lower_um=int(round(c.h_lower_mm * 1000)),
            scan_rate_mhz=self.scan_rate_mhz,
            max_scan_rate_mhz=self.max_scan_rate_mhz,
            resistance_lsb_uohm=c.electrical.wire_lsb_uohm,
            gauge_factor_micro=gf,
            base_resistance_uohm=r0,
            drive_line=self.drive_line,
            sense_channel=self.sense_channel,
        )
        return dataclasses.replace(hello, **self._hostile_hello_fields()) if self._hostile_hello_fields() else hello

    def _hostile_hello_fields(self) -> dict:
        h, out = self.hostile, {}
        if h.hello_gauge_length_um is not None:
            out["gauge_length_um"] = h.hello_gauge_length_um
        if h.hello_protocol_major is not None:
            out["protocol_major"] = h.hello_protocol_major
        return out

    def status(self, now_s: float) -> Status:
        """The STATUS message now; bitmaps: gauges open/saturated in the latest scan (while
        not scanning, as the self-test sees them: the injected faults)."""
        scanning = self.state == DeviceState.SCANNING
        opened = self._last_open | (self.open_gauges if not scanning else False)
        saturated = self._last_saturated | (self.saturated_gauges if not scanning else False)
        return Status(
            timestamp_us=self.device_time_us(now_s),
            fault_flags=self.fault_flags(),
            scans_sent=self.scans_sent & 0xFFFFFFFF,
            scans_dropped=self.scans_dropped & 0xFFFFFFFF,
            frames_rejected=self.frames_rejected & 0xFFFFFFFF,
            supply_mv=5000,
            temperature_cdeg=3100,
            state=int(self.state),
            open_gauges=opened,
            saturated_gauges=saturated,
            buffer_fill_pct=0,
        )

    # ------------------------------------------------------------------ host input

    def on_bytes(self, data: bytes, now_s: float) -> bytes:
        """Feed bytes from the host; return the device's answers (already framed)."""
        if now_s < self._stall_until:
            return b""  # a stalled firmware does not service its UART
        # what fell due before these bytes arrived goes out first (scans completed before STOP)
        out = [self.poll(now_s)]
        if self._rx_skipping:
            end = data.find(0)
            if end < 0:
                return b"".join(out)
            data = data[end + 1 :]
            self._rx_skipping = False
            self.frames_rejected += 1
        self._rx += data
        while True:
            end = self._rx.find(0)
            if end < 0:
                break
            body = bytes(self._rx[: end + 1])
            del self._rx[: end + 1]
            if len(body) - 1 > _HOST_FRAME_LIMIT:
                self.frames_rejected += 1  # longer than any command: overflowed the buffer
            elif len(body) > 1:
                out.append(self._handle_body(body, now_s))
        if len(self._rx) > _HOST_FRAME_LIMIT:
            self._rx.clear()
            self._rx_skipping = True
        return b"".join(out)

    def _handle_body(self, body: bytes, now_s: float) -> bytes:
        try:
            frame = decode_frame(body)
        except ProtocolError as exc:
            return self._reject(body, exc)
        msg = frame.msg
        if not isinstance(msg, (Start, Stop, SetScanRate, QueryInfo, Ping, Reset)):
            # a device -> host message type sent to the device
            return self._nak_unattributed(body, ErrorCode.UNKNOWN_COMMAND)
        key = (int(msg.TYPE), msg.request_id)
        if key in self._answers:  # a retry: answer again, do not act twice
            self._answers.move_to_end(key)
            return b"".join(self._frame(m) for m in self._answers[key])
        answers, after = self._execute(msg, now_s)
        self._answers[key] = answers
        while len(self._answers) > RETRY_MEMORY:
            self._answers.popitem(last=False)
        out = b"".join(self._frame(m) for m in answers)
        if isinstance(msg, Start) and self.hostile.lose_start_acks > 0:
            self.hostile.lose_start_acks -= 1
            out = b""  # sent (its seq is used) but lost on the way; a retry gets the replay
        if after is not None:
            out += after()
        return out

    def _reject(self, body: bytes, exc: ProtocolError) -> bytes:
        """A frame that fails the checks: NAK it if it passed the framing checks (its header
        and CRC are intact), otherwise drop it silently; either way count it, except an
        unknown command, which is answered rather than discarded."""
        if isinstance(exc, UnknownMessageTypeError):
            return self._nak_unattributed(body, ErrorCode.UNKNOWN_COMMAND)
        self.frames_rejected += 1
        if isinstance(exc, LengthError):
            return self._nak_unattributed(body, ErrorCode.BAD_LENGTH)
        if isinstance(exc, FieldError):
            return self._nak_unattributed(body, ErrorCode.BAD_ARGUMENT)
        return b""

    def _nak_unattributed(self, body: bytes, code: ErrorCode) -> bytes:
        """NAK echoing the first two payload bytes as request_id (0 if shorter), §7.4."""
        try:
            header, raw = decode_body(body)
        except ProtocolError:
            return b""  # COBS, CRC or length damage: nothing trustworthy to answer
        payload = raw[HEADER.size : HEADER.size + header.payload_len]
        request_id = int.from_bytes(payload[:2], "little") if len(payload) >= 2 else 0
        return self._frame(Nak(request_id, header.msg_type, int(code), 0))

    def _execute(self, msg, now_s: float):
        """Run a new command; returns (answer messages, optional action after sending them)."""
        cmd = int(msg.TYPE)
        rid = msg.request_id
        if isinstance(msg, Start):
            if self.state == DeviceState.FAULT:
                return [Nak(rid, cmd, int(ErrorCode.NOT_ALLOWED_IN_STATE), 0)], None
            if self.state != DeviceState.SCANNING:
                self.state = DeviceState.SCANNING
                self.sample_index = 0
                self._next_t0 = now_s
                self._dropped_since_last = False
            return [Ack(rid, cmd)], None
        if isinstance(msg, Stop):
            if self.state == DeviceState.SCANNING:
                self.state = DeviceState.IDLE
            self._next_t0 = None
            return [Ack(rid, cmd)], None
        if isinstance(msg, SetScanRate):
            if self.state == DeviceState.SCANNING:
                return [Nak(rid, cmd, int(ErrorCode.NOT_ALLOWED_IN_STATE), 0)], None
            if not 0 < msg.scan_rate_mhz <= self.max_scan_rate_mhz:
                return [Nak(rid, cmd, int(ErrorCode.BAD_ARGUMENT), 1)], None
            self.scan_rate_mhz = self._apply_rate_mhz(msg.scan_rate_mhz)
            return [Ack(rid, cmd, self.scan_rate_mhz.to_bytes(4, "little"))], None
        if isinstance(msg, QueryInfo):
            return [Ack(rid, cmd), self.hello()], None
        if isinstance(msg, Ping):
            return [Ack(rid, cmd, msg.echo)], None
        if isinstance(msg, Reset):
            return [Ack(rid, cmd)], lambda: self._reboot_now(now_s, watchdog=False)
        return [Nak(rid, cmd, int(ErrorCode.UNKNOWN_COMMAND), 0)], None

    # ------------------------------------------------------------------ scheduled output

    def _pending(self, now_s: float) -> bytes:
        out = b""
        if self._hello_due:
            self._hello_due = False
            out = b"\x00" + self._frame(self.hello())
            if self.hostile.lose_boot_hello:
                out = b"\x00"
        h = self.hostile
        if h.hello_storm_hz > 0 and now_s >= self._next_storm:
            self._next_storm = max(self._next_storm + 1.0 / h.hello_storm_hz, now_s)
            out += self._frame(self.hello())
        if h.vendor_frame_hz > 0 and now_s >= self._next_vendor:
            self._next_vendor = max(self._next_vendor + 1.0 / h.vendor_frame_hz, now_s)
            out += encode_body(VENDOR_FRAME_TYPE, self._seq, b"vendor diagnostics")
            self._seq = (self._seq + 1) & 0xFFFF
        return out

    def poll(self, now_s: float, tx_ready: bool = True) -> bytes:
        """Everything the device sends by ``now_s``: HELLO after boot, due SCANs, STATUS.

        ``tx_ready=False`` says the link cannot take a scan now (the host is not reading):
        scans completing meanwhile are dropped whole, as the firmware's transmit path does.
        """
        if now_s < self._stall_until:
            return b""
        out = [self._pending(now_s)]
        if self.state == DeviceState.SCANNING and self._next_t0 is not None:
            period = self.scan_period_s
            if self._stall_until > self._next_t0:  # scans completed while hung are lost
                lost = int(math.floor((self._stall_until - self._next_t0) / period + 1e-9))
                self._drop(max(lost, 0), period)
            self._stall_until = -math.inf
            due = int(math.floor((now_s - self._next_t0) / period + 1e-9))  # scans completed
            if not tx_ready:
                self._drop(max(due, 0), period)
                due = 0
            elif due > MAX_BACKLOG_SCANS:
                self._drop(due - MAX_BACKLOG_SCANS, period)
                due = MAX_BACKLOG_SCANS
            for _ in range(max(due, 0)):
                self._scan_count += 1
                if self.hostile.drop_every and self._scan_count % self.hostile.drop_every == 0:
                    self._drop(1, period)  # acquired, not sent: counted, flagged on the next SCAN
                    continue
                out.append(self._scan(self._next_t0))
                self._next_t0 += period
        out.append(self._maybe_status(now_s))
        return b"".join(out)

    def _maybe_status(self, now_s: float) -> bytes:
        faults = self.fault_flags()
        state, last_faults = self._reported[:2]
        persistent = ~_TRANSIENT_FAULTS
        changed = (
            self.state != state
            or (faults & persistent) != (last_faults & persistent)
            or (faults & ~last_faults & _TRANSIENT_FAULTS)
        )
        if not (self._status_due or changed or now_s >= self._next_status):
            return b""
        self._status_due = False
        frame = self._frame(self.status(now_s))
        self._reported = (self.state, faults, self.scans_dropped, self.frames_rejected)
        if now_s >= self._next_status:
            self._next_status = max(self._next_status + STATUS_PERIOD_S, now_s)
        return frame

    def next_event_s(self) -> float:
        """When :meth:`poll` next has something to send (for the transport's select timeout)."""
        t = self._next_status
        if self.state == DeviceState.SCANNING and self._next_t0 is not None:
            t = min(t, self._next_t0 + self.scan_period_s)
        if self.hostile.hello_storm_hz > 0:
            t = min(t, self._next_storm)
        if self.hostile.vendor_frame_hz > 0:
            t = min(t, self._next_vendor)
        if self._hello_due or self._status_due:
            t = -math.inf
        return max(t, self._stall_until)

    def _drop(self, count: int, period: float) -> None:
        if count <= 0:
            return
        self.scans_dropped += count
        self.sample_index = (self.sample_index + count) & 0xFFFFFFFF
        assert self._next_t0 is not None  # scans are dropped only while scanning
        self._next_t0 += count * period
        self._dropped_since_last = True

    def strains(self, shape_times: np.ndarray | float) -> np.ndarray:
        """True layer strains (2 layers, 2 directions, N, M) at per-unit times (2, N, M)."""
        if not self.shape.time_varying:
            if self._static_strain is None:
                self._static_strain = self._strains(0.0)
            return self._static_strain
        return self._strains(shape_times)

    def _strains(self, t) -> np.ndarray:
        c = self.config
        if not c.offset_spread:
            eu, el = gauge_strains(
                self.shape, c.n, c.m, c.pitch_mm, c.h_upper_mm, c.h_lower_mm, c.gauge_length_mm,
                t=t, samples=8, panels=c.quadrature_panels,
            )
            return np.stack([eu, el])
        # Per-unit offsets: a layer's strain is a smooth function of its offset h (the length of
        # x + h·n), so the quadratic through h = +H, 0, −H gives every unit's own layers; the
        # cubic remainder is of order (H·κ)³, below 1e-9 for bends of 40 mm and more.
        big = 1.25 * max(c.h_upper_mm, c.h_lower_mm) * (1.0 + 3.0 * c.offset_spread)
        plus, minus = gauge_strains(self.shape, c.n, c.m, c.pitch_mm, big, big, c.gauge_length_mm,
                                    t=t, samples=8, panels=c.quadrature_panels)
        mid, _ = gauge_strains(self.shape, c.n, c.m, c.pitch_mm, 0.0, 0.0, c.gauge_length_mm,
                               t=t, samples=8, panels=c.quadrature_panels)

        def at(h: np.ndarray) -> np.ndarray:
            x = h / big
            return mid + 0.5 * (plus - minus) * x + 0.5 * (plus + minus - 2.0 * mid) * x * x

        return np.stack([at(self._true_h_upper), at(-self._true_h_lower)])

    def set_shape(self, shape: Shape) -> None:
        """Put the sheet into another shape (a calibration pose, a new scene); the next scans
        read it."""
        self.shape = shape
        self._static_strain = None
        self.strains(0.0)

    def hidden_truth(self) -> dict[str, np.ndarray]:
        """What the host cannot know and a calibration should find: the gauges' true gauge
        factors (2, 2, N, M) and each unit's true layer offsets (2, N, M) in mm.  Ground truth
        for tests and benchmarks only; never on the wire."""
        return {
            "gauge_factor": np.array(self._true_constants.gauge_factor, dtype=float),
            "base_resistance_ohm": np.array(self._true_constants.base_resistance_ohm, dtype=float),
            "h_upper_mm": self._true_h_upper.copy(),
            "h_lower_mm": self._true_h_lower.copy(),
        }

    def _scan(self, t0: float) -> bytes:
        record = ScanRecord(
            sample_index=self.sample_index,
            boot=self.boot_count,
            timestamp_us=self.device_time_us(t0),
            step_period_ns=self.step_period_ns,
            shape_time_s=self.shape_time(t0),
        )
        strain = self.strains(record.unit_times_s(self.drive_line))
        wire = self.readout.read(strain, t0 - self._boot_time)
        h = self.hostile
        if h.index_jump:
            self.sample_index = (self.sample_index + h.index_jump) & 0xFFFFFFFF
            record = dataclasses.replace(record, sample_index=self.sample_index)
            h.index_jump = 0
        if h.scan_dims is not None:
            wire = np.full((2, 2, *h.scan_dims), 6_550_000, dtype=np.uint32)
        flags = 0
        self._last_open = wire == RES_OPEN
        self._last_saturated = wire == RES_SATURATED
        if self._last_open.any():
            flags |= ScanFlag.OPEN_GAUGE
        if self._last_saturated.any():
            flags |= ScanFlag.SATURATED_GAUGE
        if self._dropped_since_last:
            flags |= ScanFlag.DROPPED_BEFORE
            self._dropped_since_last = False
        if self.sample_index == 0:
            flags |= ScanFlag.FIRST_AFTER_START
        msg = Scan(record.sample_index, record.timestamp_us, record.step_period_ns, wire, int(flags))
        self.history[(record.boot, record.sample_index)] = record
        while len(self.history) > self.history_limit:
            self.history.popitem(last=False)
        if not h.repeat_sample_index:
            self.sample_index = (self.sample_index + 1) & 0xFFFFFFFF
        self.scans_sent += 1
        frame = self._frame(msg)
        if self.on_scan is not None:
            self.on_scan(record)
        return frame

    # ------------------------------------------------------------------ faults and truth

    def set_open(self, mask: np.ndarray) -> None:
        """Open-circuit (dead) gauges: bool (2 layers, 2 directions, N, M)."""
        self.open_gauges[...] = self._mask(mask, "open")

    def set_saturated(self, mask: np.ndarray) -> None:
        """Gauges stuck at the top of the ADC range: bool (2 layers, 2 directions, N, M)."""
        self.saturated_gauges[...] = self._mask(mask, "saturated")

    def _mask(self, mask, what: str) -> np.ndarray:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != self.open_gauges.shape:
            raise ValueError(f"{what} gauge mask must have shape {self.open_gauges.shape}, got {mask.shape}")
        return mask

    def set_adc_fault(self, failed: bool) -> None:
        """The measurement front end fails (state FAULT, scanning stops) or recovers (IDLE)."""
        self._adc_fault = bool(failed)
        if failed:
            self.state = DeviceState.FAULT
            self._next_t0 = None
        elif self.state == DeviceState.FAULT:
            self.state = DeviceState.IDLE

    def stall(self, now_s: float, duration_s: float) -> None:
        """Firmware hangs for ``duration_s``: nothing is sent or answered; scans due during the
        stall are lost (counted as dropped, flagged DROPPED_BEFORE on the next one)."""
        if not duration_s >= 0:
            raise ValueError(f"stall duration must be >= 0 s, got {duration_s!r}")
        self._stall_until = max(self._stall_until, now_s + duration_s)

    def reboot(self, now_s: float, watchdog: bool = True) -> None:
        """Unexpected reboot (watchdog / brown-out): sequence numbers and sample index restart,
        scanning stops, HELLO is sent again; STATUS reports WATCHDOG_RESET when ``watchdog``."""
        self._boot(now_s, watchdog)

    def _reboot_now(self, now_s: float, watchdog: bool) -> bytes:
        self._boot(now_s, watchdog)
        return self._pending(now_s)

    def record(self, sample_index: int, boot: int | None = None) -> ScanRecord:
        key = (self.boot_count if boot is None else boot, sample_index)
        try:
            return self.history[key]
        except KeyError:
            raise KeyError(f"no record of scan {sample_index} (boot {key[0]}): not sent or too old") from None

    def ground_truth(
        self, sample_index: int, boot: int | None = None, element_uv: np.ndarray | None = None
    ) -> GroundTruth:
        """True geometry of a sent scan, at the shape time of its TDM step 0."""
        rec = self.record(sample_index, boot)
        c = self.config
        return ground_truth(self.shape, c.n, c.m, c.pitch_mm, rec.shape_time_s, element_uv)
