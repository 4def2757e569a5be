"""Message types, their byte layouts and their pure pack/unpack functions.

Every layout here is normative and mirrored in PROTOCOL.md; the canonical text of all
layouts (``schema_text()``) is hashed into ``SCHEMA_HASH`` which the device reports in HELLO.
All multi-byte fields are little-endian; gauge arrays are C-ordered numpy arrays shaped
(2 layers, 2 directions, N, M): layer 0 upper, 1 lower; direction 0 row-direction gauge
(along u), 1 column-direction gauge (along v).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import ClassVar, Self

import numpy as np

from .errors import FieldError, LengthError
from .framing import PROTOCOL_MAJOR, PROTOCOL_MINOR, crc32
from .layout import HEADER_LAYOUT, NUMPY_DTYPE, TYPE_SIZE, FieldSpec, field_offset, fixed_struct, layout_size, schema_line

MIN_DIM = 2
MAX_DIM = 32
MAX_PING_ECHO = 255
SERIAL_LEN = 16

RES_OPEN = 0xFFFFFFFF  # open circuit
RES_SATURATED = 0xFFFFFFFE  # saturated / over range
RES_MAX_VALID = 0xFFFFFFFD

_U32_LE = np.dtype("<u4")
Buffer = bytes | bytearray | memoryview  # what a payload may be handed in as (decode passes views)


class MsgType(enum.IntEnum):
    # device -> host
    HELLO = 0x01
    SCAN = 0x02
    STATUS = 0x03
    ACK = 0x04
    NAK = 0x05
    # host -> device
    START = 0x10
    STOP = 0x11
    SET_SCAN_RATE = 0x12
    QUERY_INFO = 0x13
    PING = 0x14
    RESET = 0x15


class ScanFlag(enum.IntFlag):
    OPEN_GAUGE = 0x0001  # at least one gauge reads RES_OPEN
    SATURATED_GAUGE = 0x0002  # at least one gauge reads RES_SATURATED
    DROPPED_BEFORE = 0x0004  # the device dropped scans since the previous SCAN it sent
    FIRST_AFTER_START = 0x0008  # first scan after START (sample_index 0)


class FaultFlag(enum.IntFlag):
    GAUGE_OPEN = 0x0001
    GAUGE_SATURATED = 0x0002
    SCAN_BUFFER_OVERRUN = 0x0004
    BROWN_OUT = 0x0008
    OVER_TEMPERATURE = 0x0010
    CALIBRATION_INVALID = 0x0020
    WATCHDOG_RESET = 0x0040
    ADC_FAULT = 0x0080
    HOST_FRAME_ERRORS = 0x0100


class DeviceState(enum.IntEnum):
    IDLE = 0
    SCANNING = 1
    FAULT = 2


class ErrorCode(enum.IntEnum):
    UNKNOWN_COMMAND = 1
    BAD_LENGTH = 2
    BAD_ARGUMENT = 3
    BUSY = 4
    NOT_ALLOWED_IN_STATE = 5
    INTERNAL_ERROR = 6


# ---------------------------------------------------------------------------------------------
# Layout tables (normative; drive the schema hash and the tables in PROTOCOL.md)
# count: "" scalar, "k*N*M" an array of k·N·M elements, "ceil(k*N*M/8)" a bitmap in bytes,
# "*" the rest of the payload.
# ---------------------------------------------------------------------------------------------


_GAUGE_ORDER = "(2 layers, 2 directions, N, M) C order"

LAYOUTS: dict[MsgType, tuple[FieldSpec, ...]] = {
    MsgType.HELLO: (
        FieldSpec("u8", "protocol_major", "", "protocol major version"),
        FieldSpec("u8", "protocol_minor", "", "protocol minor version"),
        FieldSpec("u8", "n", "", "rows N, 2..32"),
        FieldSpec("u8", "m", "", "columns M, 2..32"),
        FieldSpec("u8", "fw_major", "", "firmware version major"),
        FieldSpec("u8", "fw_minor", "", "firmware version minor"),
        FieldSpec("u16", "fw_patch", "", "firmware version patch"),
        FieldSpec("char", "serial_number", "16", "ASCII, NUL-padded"),
        FieldSpec("u32", "schema_hash", "", "CRC-32 of the canonical layout text"),
        FieldSpec("u32", "pitch_um", "", "cell pitch, µm"),
        FieldSpec("u32", "gauge_length_um", "", "gauge length, µm"),
        FieldSpec("u16", "h_upper_um", "", "upper gauge offset from neutral plane, µm"),
        FieldSpec("u16", "h_lower_um", "", "lower gauge offset from neutral plane, µm"),
        FieldSpec("u32", "scan_rate_mhz", "", "current scan rate, mHz (scans/s × 1000)"),
        FieldSpec("u32", "max_scan_rate_mhz", "", "maximum scan rate, mHz"),
        FieldSpec("u32", "resistance_lsb_uohm", "", "measurement quantum, µΩ"),
        FieldSpec("u32", "gauge_factor_micro", "4*N*M", "GF × 10^6, " + _GAUGE_ORDER),
        FieldSpec("u32", "base_resistance_uohm", "4*N*M", "R0, µΩ, " + _GAUGE_ORDER),
        FieldSpec("u8", "drive_line", "2*N*M", "TDM drive line = step index, (2, N, M)"),
        FieldSpec("u8", "sense_channel", "4*N*M", "DAQ sense channel, " + _GAUGE_ORDER),
    ),
    MsgType.SCAN: (
        FieldSpec("u32", "sample_index", "", "scans since START, +1 per scan"),
        FieldSpec("u64", "timestamp_us", "", "device clock at TDM step 0, µs"),
        FieldSpec("u32", "step_period_ns", "", "TDM step period, ns"),
        FieldSpec("u8", "n", "", "rows N"),
        FieldSpec("u8", "m", "", "columns M"),
        FieldSpec("u16", "flags", "", "ScanFlag bits"),
        FieldSpec("u32", "resistance_uohm", "4*N*M", "µΩ; sentinels 0xFFFFFFFF/0xFFFFFFFE, " + _GAUGE_ORDER),
    ),
    MsgType.STATUS: (
        FieldSpec("u64", "timestamp_us", "", "device clock, µs"),
        FieldSpec("u32", "fault_flags", "", "FaultFlag bits"),
        FieldSpec("u32", "scans_sent", "", "SCAN messages sent since boot"),
        FieldSpec("u32", "scans_dropped", "", "scans acquired but not sent, since boot"),
        FieldSpec("u32", "frames_rejected", "", "host frames discarded, since boot"),
        FieldSpec("u16", "supply_mv", "", "supply voltage, mV"),
        FieldSpec("i16", "temperature_cdeg", "", "board temperature, 0.01 °C"),
        FieldSpec("u8", "state", "", "DeviceState"),
        FieldSpec("u8", "n", "", "rows N"),
        FieldSpec("u8", "m", "", "columns M"),
        FieldSpec("u8", "buffer_fill_pct", "", "scan buffer fill, %"),
        FieldSpec("u8", "open_bitmap", "ceil(4*N*M/8)", "bit g = gauge g open (LSB first)"),
        FieldSpec("u8", "saturated_bitmap", "ceil(4*N*M/8)", "bit g = gauge g saturated"),
    ),
    MsgType.ACK: (
        FieldSpec("u16", "request_id", "", "echoed request id"),
        FieldSpec("u8", "command", "", "echoed command type"),
        FieldSpec("u8", "result", "*", "command-specific result data"),
    ),
    MsgType.NAK: (
        FieldSpec("u16", "request_id", "", "echoed request id"),
        FieldSpec("u8", "command", "", "echoed command type"),
        FieldSpec("u8", "error", "", "ErrorCode"),
        FieldSpec("u8", "argument", "", "1-based index of the bad argument, 0 = none"),
    ),
    MsgType.START: (FieldSpec("u16", "request_id", "", "request id"),),
    MsgType.STOP: (FieldSpec("u16", "request_id", "", "request id"),),
    MsgType.SET_SCAN_RATE: (
        FieldSpec("u16", "request_id", "", "request id"),
        FieldSpec("u32", "scan_rate_mhz", "", "argument 1: scans/s × 1000, > 0"),
    ),
    MsgType.QUERY_INFO: (FieldSpec("u16", "request_id", "", "request id"),),
    MsgType.PING: (
        FieldSpec("u16", "request_id", "", "request id"),
        FieldSpec("u8", "echo", "*", "0..255 bytes, returned in the ACK"),
    ),
    MsgType.RESET: (FieldSpec("u16", "request_id", "", "request id"),),
}



def _fixed(mtype: MsgType) -> struct.Struct:
    """Struct of a message's fixed leading fields, derived from its layout."""
    return fixed_struct(LAYOUTS[mtype])


def _payload_size(mtype: MsgType, n: int, m: int) -> int:
    return layout_size(LAYOUTS[mtype], n, m)


def schema_text() -> str:
    """Canonical text of all layouts: one line per message, hashed into SCHEMA_HASH."""
    lines = [
        f"skinmap-protocol {PROTOCOL_MAJOR}",
        "header: " + schema_line(HEADER_LAYOUT),
        "trailer: u32 crc32",
    ]
    for mtype, fields in LAYOUTS.items():
        lines.append(f"{mtype.name} 0x{mtype.value:02X}: " + schema_line(fields))
    return "\n".join(lines) + "\n"


SCHEMA_HASH = crc32(schema_text().encode("ascii"))


def layout_rows(mtype: MsgType) -> list[tuple[str, str, str, str, str]]:
    """(offset, size, type, name, units) rows of one layout, offsets relative to the payload."""
    const, nm_bytes, bitmaps = 0, 0, 0  # offset = const + nm_bytes·N·M + bitmaps·ceil(4·N·M/8)
    rows = []
    for f in LAYOUTS[mtype]:
        terms = [str(const)] if const or not (nm_bytes or bitmaps) else []
        if nm_bytes:
            terms.append(f"{nm_bytes}·N·M")
        if bitmaps:
            terms.append(("" if bitmaps == 1 else f"{bitmaps}·") + "ceil(4·N·M/8)")
        size = TYPE_SIZE[f.type]
        if f.count == "":
            size_text = str(size)
            const += size
        elif f.count.isdigit():
            size_text = str(size * int(f.count))
            const += size * int(f.count)
        elif f.count == "*":
            size_text = "rest"
        elif f.count.startswith("ceil("):
            size_text = "ceil(4·N·M/8)"
            bitmaps += 1
        else:
            k = int(f.count.split("*")[0]) * size
            size_text = f"{k}·N·M"
            nm_bytes += k
        ftype = f"{f.type}[{f.count}]" if f.count else f.type
        rows.append((" + ".join(terms), size_text, ftype, f.name, f.units))
    return rows


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def _check_dims(what: str, n: int, m: int) -> None:
    if not (MIN_DIM <= n <= MAX_DIM and MIN_DIM <= m <= MAX_DIM):
        raise FieldError(f"{what}: N={n}, M={m} outside {MIN_DIM}..{MAX_DIM}")


def _check_int(what: str, value: int, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise FieldError(f"{what} must be an integer in {lo}..{hi}, got {value!r}")


def _gauge_array(what: str, values: np.ndarray, shape: tuple[int, ...], dtype: str) -> np.ndarray:
    """Validate an integer array's shape and range; return it C-contiguous little-endian."""
    arr = np.asarray(values)
    if arr.shape != shape:
        raise FieldError(f"{what} has shape {arr.shape}, expected {shape}")
    if arr.dtype.kind not in "ui":
        raise FieldError(f"{what} must be an integer array, got dtype {arr.dtype}")
    info = np.iinfo(np.dtype(dtype))
    if arr.size and (arr.min() < info.min or arr.max() > info.max):
        raise FieldError(f"{what} values must lie in {info.min}..{info.max}")
    return np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<"))


def _expect_len(mtype: MsgType, payload_len: int, expected: int, extended: bool) -> None:
    if payload_len < expected or (payload_len > expected and not extended):
        raise LengthError(
            f"{mtype.name} payload is {payload_len} bytes, its layout needs exactly {expected}"
        )


def _dims_from(mtype: MsgType, payload: Buffer, fixed: int) -> tuple[int, int]:
    if len(payload) < fixed:
        raise LengthError(
            f"{mtype.name} payload is {len(payload)} bytes, shorter than its fixed part {fixed}"
        )
    fields = LAYOUTS[mtype]
    n, m = payload[field_offset(fields, "n")], payload[field_offset(fields, "m")]
    _check_dims(mtype.name, n, m)
    return n, m


def _array_field(mtype: MsgType, payload: Buffer, name: str, shape: tuple[int, ...],
                 base: int = 0) -> np.ndarray:
    """Zero-copy view of an N·M array field, placed and typed by the layout (`base`: where the
    payload starts in `payload`)."""
    fields = LAYOUTS[mtype]
    spec = next(f for f in fields if f.name == name)
    n, m = shape[-2], shape[-1]
    offset = base + field_offset(fields, name, n, m)
    count = int(np.prod(shape))
    return np.frombuffer(payload, np.dtype(NUMPY_DTYPE[spec.type]), count, offset).reshape(shape)


def _arrays_equal(a: object, b: object, names: tuple[str, ...]) -> bool:
    if type(a) is not type(b):
        return NotImplemented
    for name in names:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not np.array_equal(np.asarray(x), np.asarray(y)):
                return False
        elif x != y:
            return False
    return True


# ---------------------------------------------------------------------------------------------
# device -> host
# ---------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Hello:
    """Device info: identity, geometry, rates, channel map and per-gauge calibration."""

    TYPE: ClassVar[MsgType] = MsgType.HELLO
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.HELLO)

    fw_version: tuple[int, int, int]
    serial_number: str
    pitch_um: int
    gauge_length_um: int
    h_upper_um: int
    h_lower_um: int
    scan_rate_mhz: int
    max_scan_rate_mhz: int
    resistance_lsb_uohm: int
    gauge_factor_micro: np.ndarray  # uint32 (2, 2, N, M), GF × 1e6
    base_resistance_uohm: np.ndarray  # uint32 (2, 2, N, M)
    drive_line: np.ndarray  # uint8 (2, N, M)
    sense_channel: np.ndarray  # uint8 (2, 2, N, M)
    protocol_major: int = PROTOCOL_MAJOR
    protocol_minor: int = PROTOCOL_MINOR
    schema_hash: int = SCHEMA_HASH

    @property
    def n(self) -> int:
        return int(np.shape(self.gauge_factor_micro)[2])

    @property
    def m(self) -> int:
        return int(np.shape(self.gauge_factor_micro)[3])

    def gauge_factor(self) -> np.ndarray:
        """Gauge factors as float64, shaped (2, 2, N, M)."""
        return np.asarray(self.gauge_factor_micro, dtype=np.float64) * 1e-6

    def base_resistance_ohm(self) -> np.ndarray:
        """Base resistances R0 in ohms as float64, shaped (2, 2, N, M)."""
        return np.asarray(self.base_resistance_uohm, dtype=np.float64) * 1e-6

    def pack_payload(self) -> bytes:
        gf = np.asarray(self.gauge_factor_micro)
        if gf.ndim != 4:
            raise FieldError(f"HELLO gauge_factor_micro must be 4-D (2, 2, N, M), got shape {gf.shape}")
        n, m = gf.shape[2], gf.shape[3]
        _check_dims("HELLO", n, m)
        g4, g2 = (2, 2, n, m), (2, n, m)
        gf = _gauge_array("HELLO gauge_factor_micro", gf, g4, "u4")
        r0 = _gauge_array("HELLO base_resistance_uohm", self.base_resistance_uohm, g4, "u4")
        drive = _gauge_array("HELLO drive_line", self.drive_line, g2, "u1")
        sense = _gauge_array("HELLO sense_channel", self.sense_channel, g4, "u1")
        channels = 2 * (n + m)
        if drive.max() >= 2 * min(n, m):
            raise FieldError(f"HELLO drive_line values must be < 2·min(N, M) = {2 * min(n, m)}")
        if sense.max() >= channels:
            raise FieldError(f"HELLO sense_channel values must be < 2·(N + M) = {channels}")
        if len(self.fw_version) != 3:
            raise FieldError(f"HELLO fw_version must be (major, minor, patch), got {self.fw_version!r}")
        major, minor, patch = self.fw_version
        _check_int("HELLO fw_version major", major, 0, 0xFF)
        _check_int("HELLO fw_version minor", minor, 0, 0xFF)
        _check_int("HELLO fw_version patch", patch, 0, 0xFFFF)
        try:
            serial = self.serial_number.encode("ascii")
        except UnicodeEncodeError:
            raise FieldError(f"HELLO serial_number must be ASCII, got {self.serial_number!r}") from None
        if len(serial) > SERIAL_LEN or b"\x00" in serial:
            raise FieldError(f"HELLO serial_number must be at most {SERIAL_LEN} ASCII characters without NUL")
        _check_int("HELLO protocol_major", self.protocol_major, 0, 0xFF)
        _check_int("HELLO protocol_minor", self.protocol_minor, 0, 0xFF)
        _check_int("HELLO schema_hash", self.schema_hash, 0, 0xFFFFFFFF)
        for name in ("pitch_um", "gauge_length_um", "scan_rate_mhz", "max_scan_rate_mhz", "resistance_lsb_uohm"):
            _check_int(f"HELLO {name}", getattr(self, name), 0, 0xFFFFFFFF)
        _check_int("HELLO h_upper_um", self.h_upper_um, 0, 0xFFFF)
        _check_int("HELLO h_lower_um", self.h_lower_um, 0, 0xFFFF)
        fixed = self._FIXED.pack(
            self.protocol_major, self.protocol_minor, n, m, major, minor, patch, serial,
            self.schema_hash, self.pitch_um, self.gauge_length_um, self.h_upper_um,
            self.h_lower_um, self.scan_rate_mhz, self.max_scan_rate_mhz, self.resistance_lsb_uohm,
        )
        return b"".join((fixed, gf.tobytes(), r0.tobytes(), drive.tobytes(), sense.tobytes()))

    @classmethod
    def payload_size(cls, n: int, m: int) -> int:
        return _payload_size(MsgType.HELLO, n, m)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> Hello:
        n, m = _dims_from(MsgType.HELLO, payload, cls._FIXED.size)
        _expect_len(MsgType.HELLO, len(payload), cls.payload_size(n, m), extended)
        (pmaj, pmin, _, _, major, minor, patch, serial, schema, pitch, glen, hu, hl, rate,
         max_rate, lsb) = cls._FIXED.unpack_from(payload)
        try:
            serial_text = serial.rstrip(b"\x00").decode("ascii")
        except UnicodeDecodeError:
            raise FieldError(f"HELLO serial_number is not ASCII: {serial!r}") from None
        g4, g2 = (2, 2, n, m), (2, n, m)
        gf = _array_field(MsgType.HELLO, payload, "gauge_factor_micro", g4)
        r0 = _array_field(MsgType.HELLO, payload, "base_resistance_uohm", g4)
        drive = _array_field(MsgType.HELLO, payload, "drive_line", g2)
        sense = _array_field(MsgType.HELLO, payload, "sense_channel", g4)
        if drive.max() >= 2 * min(n, m):
            raise FieldError(f"HELLO drive_line values must be < 2·min(N, M) = {2 * min(n, m)}")
        if sense.max() >= 2 * (n + m):
            raise FieldError(f"HELLO sense_channel values must be < 2·(N + M) = {2 * (n + m)}")
        return cls(
            fw_version=(major, minor, patch), serial_number=serial_text, pitch_um=pitch,
            gauge_length_um=glen, h_upper_um=hu, h_lower_um=hl, scan_rate_mhz=rate,
            max_scan_rate_mhz=max_rate, resistance_lsb_uohm=lsb, gauge_factor_micro=gf,
            base_resistance_uohm=r0, drive_line=drive, sense_channel=sense,
            protocol_major=pmaj, protocol_minor=pmin, schema_hash=schema,
        )

    def __eq__(self, other: object) -> bool:
        return _arrays_equal(self, other, (
            "fw_version", "serial_number", "pitch_um", "gauge_length_um", "h_upper_um",
            "h_lower_um", "scan_rate_mhz", "max_scan_rate_mhz", "resistance_lsb_uohm",
            "gauge_factor_micro", "base_resistance_uohm", "drive_line", "sense_channel",
            "protocol_major", "protocol_minor", "schema_hash",
        ))


@dataclass(eq=False)
class Scan:
    """One whole scan: all 4·N·M gauge resistances, fixed point µΩ."""

    TYPE: ClassVar[MsgType] = MsgType.SCAN
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.SCAN)

    sample_index: int
    timestamp_us: int
    step_period_ns: int
    resistance_uohm: np.ndarray  # uint32 (2, 2, N, M), read-only view into the frame on decode
    flags: int = 0

    @property
    def n(self) -> int:
        return int(np.shape(self.resistance_uohm)[2])

    @property
    def m(self) -> int:
        return int(np.shape(self.resistance_uohm)[3])

    def resistances_ohm(self) -> np.ndarray:
        """Resistances in ohms (float64, shaped (2, 2, N, M)); NaN where open or saturated."""
        raw = np.asarray(self.resistance_uohm)
        out = raw.astype(np.float64) * 1e-6
        out[raw > RES_MAX_VALID] = np.nan
        return out

    def open_mask(self) -> np.ndarray:
        return np.asarray(self.resistance_uohm) == RES_OPEN

    def saturated_mask(self) -> np.ndarray:
        return np.asarray(self.resistance_uohm) == RES_SATURATED

    def pack_payload(self) -> bytes:
        res = np.asarray(self.resistance_uohm)
        if res.ndim != 4 or res.shape[:2] != (2, 2):
            raise FieldError(f"SCAN resistance_uohm must be shaped (2, 2, N, M), got {res.shape}")
        n, m = res.shape[2], res.shape[3]
        _check_dims("SCAN", n, m)
        if res.dtype != _U32_LE or not res.flags.c_contiguous:
            res = _gauge_array("SCAN resistance_uohm", res, res.shape, "u4")
        _check_int("SCAN sample_index", self.sample_index, 0, 0xFFFFFFFF)
        _check_int("SCAN timestamp_us", self.timestamp_us, 0, 0xFFFFFFFFFFFFFFFF)
        _check_int("SCAN step_period_ns", self.step_period_ns, 0, 0xFFFFFFFF)
        _check_int("SCAN flags", self.flags, 0, 0xFFFF)
        fixed = self._FIXED.pack(self.sample_index, self.timestamp_us, self.step_period_ns, n, m, self.flags)
        return fixed + res.tobytes()

    @classmethod
    def payload_size(cls, n: int, m: int) -> int:
        return _payload_size(MsgType.SCAN, n, m)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False, offset: int = 0) -> Scan:
        """Decode; `payload` may be a larger buffer with the payload at `offset` (zero copy)."""
        view = memoryview(payload)[offset:]
        n, m = _dims_from(MsgType.SCAN, view, cls._FIXED.size)
        size = cls.payload_size(n, m)
        _expect_len(MsgType.SCAN, len(view), size, extended)
        index, stamp, period, _, _, flags = cls._FIXED.unpack_from(view)
        res = _array_field(MsgType.SCAN, payload, "resistance_uohm", (2, 2, n, m), offset)
        return cls(index, stamp, period, res, flags)

    def __eq__(self, other: object) -> bool:
        return _arrays_equal(self, other, ("sample_index", "timestamp_us", "step_period_ns", "resistance_uohm", "flags"))


@dataclass(eq=False)
class Status:
    """Periodic (1 Hz) and on-change fault report with counters and per-gauge bitmaps."""

    TYPE: ClassVar[MsgType] = MsgType.STATUS
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.STATUS)

    timestamp_us: int
    fault_flags: int
    scans_sent: int
    scans_dropped: int
    frames_rejected: int
    supply_mv: int
    temperature_cdeg: int
    state: int
    open_gauges: np.ndarray  # bool (2, 2, N, M)
    saturated_gauges: np.ndarray  # bool (2, 2, N, M)
    buffer_fill_pct: int = 0

    @property
    def n(self) -> int:
        return int(np.shape(self.open_gauges)[2])

    @property
    def m(self) -> int:
        return int(np.shape(self.open_gauges)[3])

    @staticmethod
    def bitmap_size(n: int, m: int) -> int:
        return (4 * n * m + 7) // 8

    @classmethod
    def payload_size(cls, n: int, m: int) -> int:
        return _payload_size(MsgType.STATUS, n, m)

    def pack_payload(self) -> bytes:
        opened = np.asarray(self.open_gauges)
        if opened.ndim != 4 or opened.shape[:2] != (2, 2):
            raise FieldError(f"STATUS open_gauges must be shaped (2, 2, N, M), got {opened.shape}")
        n, m = opened.shape[2], opened.shape[3]
        _check_dims("STATUS", n, m)
        sat = np.asarray(self.saturated_gauges)
        if sat.shape != opened.shape:
            raise FieldError(f"STATUS saturated_gauges has shape {sat.shape}, expected {opened.shape}")
        _check_int("STATUS timestamp_us", self.timestamp_us, 0, 0xFFFFFFFFFFFFFFFF)
        for name in ("fault_flags", "scans_sent", "scans_dropped", "frames_rejected"):
            _check_int(f"STATUS {name}", getattr(self, name), 0, 0xFFFFFFFF)
        _check_int("STATUS supply_mv", self.supply_mv, 0, 0xFFFF)
        _check_int("STATUS temperature_cdeg", self.temperature_cdeg, -0x8000, 0x7FFF)
        _check_int("STATUS state", self.state, 0, 0xFF)
        _check_int("STATUS buffer_fill_pct", self.buffer_fill_pct, 0, 100)
        fixed = self._FIXED.pack(
            self.timestamp_us, self.fault_flags, self.scans_sent, self.scans_dropped,
            self.frames_rejected, self.supply_mv, self.temperature_cdeg, self.state, n, m,
            self.buffer_fill_pct,
        )
        bits = [np.packbits(a.astype(bool).ravel(), bitorder="little").tobytes() for a in (opened, sat)]
        return fixed + bits[0] + bits[1]

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> Status:
        n, m = _dims_from(MsgType.STATUS, payload, cls._FIXED.size)
        _expect_len(MsgType.STATUS, len(payload), cls.payload_size(n, m), extended)
        (stamp, faults, sent, dropped, rejected, supply, temp, state, _, _, fill) = cls._FIXED.unpack_from(payload)
        nb, count = cls.bitmap_size(n, m), 4 * n * m
        off = cls._FIXED.size
        raw = np.frombuffer(payload, np.uint8, 2 * nb, off)
        opened = np.unpackbits(raw[:nb], count=count, bitorder="little").astype(bool).reshape(2, 2, n, m)
        sat = np.unpackbits(raw[nb:], count=count, bitorder="little").astype(bool).reshape(2, 2, n, m)
        return cls(stamp, faults, sent, dropped, rejected, supply, temp, state, opened, sat, fill)

    def __eq__(self, other: object) -> bool:
        return _arrays_equal(self, other, (
            "timestamp_us", "fault_flags", "scans_sent", "scans_dropped", "frames_rejected",
            "supply_mv", "temperature_cdeg", "state", "open_gauges", "saturated_gauges",
            "buffer_fill_pct",
        ))


@dataclass
class Ack:
    """Positive answer to a command; `result` is command specific (PROTOCOL.md, ACK)."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.ACK)

    request_id: int
    command: int
    result: bytes = b""

    def pack_payload(self) -> bytes:
        _check_int("ACK request_id", self.request_id, 0, 0xFFFF)
        _check_int("ACK command", self.command, 0, 0xFF)
        if len(self.result) > MAX_PING_ECHO:
            raise FieldError(f"ACK result of {len(self.result)} bytes exceeds {MAX_PING_ECHO}")
        return self._FIXED.pack(self.request_id, self.command) + bytes(self.result)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> Ack:
        if not cls._FIXED.size <= len(payload) <= cls._FIXED.size + MAX_PING_ECHO:
            raise LengthError(f"ACK payload is {len(payload)} bytes, allowed 3..{3 + MAX_PING_ECHO}")
        rid, cmd = cls._FIXED.unpack_from(payload)
        return cls(rid, cmd, bytes(payload[cls._FIXED.size:]))

    @property
    def applied_scan_rate_mhz(self) -> int:
        """For an ACK of SET_SCAN_RATE: the rate the device applied (it may round)."""
        if self.command != MsgType.SET_SCAN_RATE or len(self.result) != 4:
            raise FieldError("applied_scan_rate_mhz exists only on an ACK of SET_SCAN_RATE with a 4-byte result")
        return int.from_bytes(self.result, "little")


@dataclass
class Nak:
    """Negative answer to a command: error code and which argument (1-based, 0 = none)."""

    TYPE: ClassVar[MsgType] = MsgType.NAK
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.NAK)

    request_id: int
    command: int
    error: int
    argument: int = 0

    def pack_payload(self) -> bytes:
        _check_int("NAK request_id", self.request_id, 0, 0xFFFF)
        _check_int("NAK command", self.command, 0, 0xFF)
        _check_int("NAK error", self.error, 0, 0xFF)
        _check_int("NAK argument", self.argument, 0, 0xFF)
        return self._FIXED.pack(self.request_id, self.command, self.error, self.argument)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> Nak:
        _expect_len(MsgType.NAK, len(payload), cls._FIXED.size, extended)
        return cls(*cls._FIXED.unpack_from(payload))


# ---------------------------------------------------------------------------------------------
# host -> device commands (each starts with a u16 request id)
# ---------------------------------------------------------------------------------------------


@dataclass
class _RequestOnly:
    # START, STOP, QUERY_INFO and RESET share this one-field layout (checked by the tests)
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.START)

    request_id: int

    def pack_payload(self) -> bytes:
        _check_int(f"{self.TYPE.name} request_id", self.request_id, 0, 0xFFFF)  # type: ignore[attr-defined]
        return self._FIXED.pack(self.request_id)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> Self:
        _expect_len(cls.TYPE, len(payload), cls._FIXED.size, extended)  # type: ignore[attr-defined]
        return cls(*cls._FIXED.unpack_from(payload))


@dataclass
class Start(_RequestOnly):
    TYPE: ClassVar[MsgType] = MsgType.START


@dataclass
class Stop(_RequestOnly):
    TYPE: ClassVar[MsgType] = MsgType.STOP


@dataclass
class QueryInfo(_RequestOnly):
    TYPE: ClassVar[MsgType] = MsgType.QUERY_INFO


@dataclass
class Reset(_RequestOnly):
    TYPE: ClassVar[MsgType] = MsgType.RESET


@dataclass
class SetScanRate:
    """Set complete scans per second (× 1000); the TDM step rate is 2·min(N, M) times that."""

    TYPE: ClassVar[MsgType] = MsgType.SET_SCAN_RATE
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.SET_SCAN_RATE)

    request_id: int
    scan_rate_mhz: int

    def pack_payload(self) -> bytes:
        _check_int("SET_SCAN_RATE request_id", self.request_id, 0, 0xFFFF)
        _check_int("SET_SCAN_RATE scan_rate_mhz", self.scan_rate_mhz, 0, 0xFFFFFFFF)
        return self._FIXED.pack(self.request_id, self.scan_rate_mhz)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> SetScanRate:
        _expect_len(MsgType.SET_SCAN_RATE, len(payload), cls._FIXED.size, extended)
        return cls(*cls._FIXED.unpack_from(payload))


@dataclass
class Ping:
    TYPE: ClassVar[MsgType] = MsgType.PING
    _FIXED: ClassVar[struct.Struct] = _fixed(MsgType.PING)

    request_id: int
    echo: bytes = b""

    def pack_payload(self) -> bytes:
        _check_int("PING request_id", self.request_id, 0, 0xFFFF)
        if len(self.echo) > MAX_PING_ECHO:
            raise FieldError(f"PING echo of {len(self.echo)} bytes exceeds {MAX_PING_ECHO}")
        return self._FIXED.pack(self.request_id) + bytes(self.echo)

    @classmethod
    def unpack_payload(cls, payload: Buffer, extended: bool = False) -> Ping:
        if not 2 <= len(payload) <= 2 + MAX_PING_ECHO:
            raise LengthError(f"PING payload is {len(payload)} bytes, allowed 2..{2 + MAX_PING_ECHO}")
        return cls(int.from_bytes(payload[:2], "little"), bytes(payload[2:]))


Message = Hello | Scan | Status | Ack | Nak | Start | Stop | SetScanRate | QueryInfo | Ping | Reset
COMMANDS = (Start, Stop, SetScanRate, QueryInfo, Ping, Reset)
MESSAGE_CLASSES: dict[MsgType, type[Message]] = {
    cls.TYPE: cls for cls in (Hello, Scan, Status, Ack, Nak, *COMMANDS)
}


@dataclass(frozen=True)
class Compatibility:
    """Outcome of comparing a device's HELLO with this codec (PROTOCOL.md, "Versioning")."""

    usable: bool  # False: the host must not START the device
    note: str  # why not, or what differs although usable; "" when identical


def hello_compatibility(hello: Hello) -> Compatibility:
    """Apply the host-side versioning rules to a device's HELLO."""
    device = f"{hello.protocol_major}.{hello.protocol_minor}"
    host = f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"
    if hello.protocol_major != PROTOCOL_MAJOR:
        return Compatibility(False, f"device speaks protocol {device}, host speaks {host}: major versions differ")
    if hello.protocol_minor == PROTOCOL_MINOR and hello.schema_hash != SCHEMA_HASH:
        return Compatibility(False, (
            f"device and host both claim protocol {device} but schema hashes differ "
            f"(device 0x{hello.schema_hash:08X}, host 0x{SCHEMA_HASH:08X}): message layouts disagree"
        ))
    if hello.protocol_minor > PROTOCOL_MINOR:
        return Compatibility(True, f"device protocol {device} is newer than host {host}: unknown additions are ignored")
    if hello.protocol_minor < PROTOCOL_MINOR:
        return Compatibility(True, f"device protocol {device} is older than host {host}: only its commands are used")
    return Compatibility(True, "")
