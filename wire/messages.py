"""Binary and JSON message layouts published by skinmapd (pure encode/decode, no I/O).

Every binary message starts with the same 32-byte little-endian header:

=======  ====  ==============  =====================================================
offset   size  type            field
=======  ====  ==============  =====================================================
0        4     bytes           magic ``b"SKMP"``
4        1     u8              layout version (``LAYOUT_VERSION``)
5        1     u8              message kind (``MessageKind``)
6        2     u16             reserved, 0
8        4     u32             sequence number (scan counter, wraps at 2**32)
12       4     u32             total message length in bytes, header included
16       8     u64             device sample time, microseconds (scanner clock)
24       8     u64             host receive time, nanoseconds since the Unix epoch
=======  ====  ==============  =====================================================

A kind-specific block of counts follows, padded so that every float64 array starts on an
8-byte boundary (``np.frombuffer`` views are then aligned). Arrays are C-ordered and
little-endian. All lengths are in METRES in the sensor frame (docs/architecture.md).
The byte tables of every kind are ``LAYOUT_TABLES`` below; docs/zenoh.md shows them as
rendered by ``layout_table`` (a test keeps the two equal).

Status and info are UTF-8 JSON objects; their required fields are the TypedDicts
``StatusReport`` and ``DeviceInfo``, from which ``STATUS_FIELDS`` and ``INFO_FIELDS`` (accepted
JSON types and meaning of each) are derived; the probe pose the gateway takes in is
``POSE_FIELDS`` (``json_table``).
"""

from __future__ import annotations

import enum
import json
import math
import struct
from dataclasses import dataclass
from typing import Any, Callable, Mapping, TypedDict, cast, get_origin, get_type_hints

import numpy as np

MAGIC = b"SKMP"
LAYOUT_VERSION = 2
#: Versions the decoders read.  Layout 1 (up to skinmap 0.1's logs) had no scatter arrays: its
#: elements and surface messages decode with ``scatter`` None.
READABLE_VERSIONS = (1, 2)

_HEADER = struct.Struct("<4sBBHIIQQ")
HEADER_SIZE = _HEADER.size  # 32
_ELEMENTS_COUNTS = struct.Struct("<II")  # K, reserved
_SURFACE_COUNTS = struct.Struct("<IIIB3x")  # N, M, P, cloud bytes per coordinate
_STRAINS_COUNTS = struct.Struct("<II")  # N, M

_U32_MAX = 2**32 - 1
_U64_MAX = 2**64 - 1


class MessageKind(enum.IntEnum):
    ELEMENTS = 1
    SURFACE = 2
    STRAINS = 3


class ElementFlag(enum.IntFlag):
    """Per-element validity bits (u8)."""

    VALID = 0x01  # position/normal are a current estimate; NaN allowed only when clear
    EXTRAPOLATED = 0x02  # element lies outside the hull of the sensing cells
    DEGRADED = 0x04  # estimate made with missing or rejected gauge data nearby
    STALE = 0x08  # held over from an earlier scan (no fresh solution this frame)
    AMBIGUOUS = 0x10  # the strains fit a mirror-image shape as well (set on every element)


class GaugeFlag(enum.IntFlag):
    """Per sensing-unit validity bits (u8) in the strains message."""

    UPPER_VALID = 0x01
    LOWER_VALID = 0x02


class MessageError(ValueError):
    """A buffer is not a well-formed skinmap message (truncated, wrong magic, bad sizes...)."""


@dataclass(frozen=True)
class Header:
    kind: MessageKind
    version: int
    seq: int
    length: int
    device_time_us: int
    host_time_ns: int


@dataclass(frozen=True)
class ElementsMessage:
    """Per-element pose of the transducer array for one scan (arrays are read-only views)."""

    seq: int
    device_time_us: int
    host_time_ns: int
    positions: np.ndarray  # (K, 3) float64, metres
    normals: np.ndarray  # (K, 3) float64, unit vectors toward the upper side
    uncertainty: np.ndarray  # (K,) float64, metres, 1 s.d.
    flags: np.ndarray  # (K,) uint8, ElementFlag bits
    # (K,) float64, metres, 1 s.d.: the part of the uncertainty that repeated frames of a still
    # sheet scatter by (the rest is a bound on a bias, the same every frame); None in layout 1
    scatter: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def valid(self) -> np.ndarray:
        return (self.flags & int(ElementFlag.VALID)) != 0


@dataclass(frozen=True)
class SurfaceMessage:
    """Reconstructed sheet for one scan: node grid plus an optional dense point cloud."""

    seq: int
    device_time_us: int
    host_time_ns: int
    nodes: np.ndarray  # (N, M, 3) float64, metres
    normals: np.ndarray  # (N, M, 3) float64, unit
    uncertainty: np.ndarray  # (N, M) float64, metres, 1 s.d.
    cloud: np.ndarray  # (P, 3) float32 or float64, metres
    scatter: np.ndarray | None = None  # (N, M) float64, metres: as ElementsMessage.scatter

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.nodes.shape[0]), int(self.nodes.shape[1])


@dataclass(frozen=True)
class StrainsMessage:
    """Calibrated layer strains for one scan, indexed eps[k, i, j] (k=0 row gauge, 1 column)."""

    seq: int
    device_time_us: int
    host_time_ns: int
    eps_upper: np.ndarray  # (2, N, M) float64, engineering strain
    eps_lower: np.ndarray  # (2, N, M) float64
    gauge_flags: np.ndarray  # (2, N, M) uint8, GaugeFlag bits

    @property
    def valid_upper(self) -> np.ndarray:
        return (self.gauge_flags & int(GaugeFlag.UPPER_VALID)) != 0

    @property
    def valid_lower(self) -> np.ndarray:
        return (self.gauge_flags & int(GaugeFlag.LOWER_VALID)) != 0


# ---------------------------------------------------------------------------------------
# byte tables (the single description of every binary layout; docs/zenoh.md renders them)

# A size is {symbol: coefficient}; "" is the constant term. Offsets are the running sums.
Size = dict[str, int]

LAYOUT_TABLES: dict[str, list[tuple[Size, str, str]]] = {
    "header": [
        ({"": 4}, "bytes", "magic `SKMP` (`53 4B 4D 50`)"),
        ({"": 1}, "u8", "layout version, currently 2 (decoders also read 1: no scatter arrays)"),
        ({"": 1}, "u8", "kind: 1 elements, 2 surface, 3 strains"),
        ({"": 2}, "u16", "reserved, 0"),
        ({"": 4}, "u32", "sequence number: the scanner's `sample_index` of the scan (below)"),
        ({"": 4}, "u32", "total message length in bytes, header included"),
        ({"": 8}, "u64", "device sample time, µs (scanner clock)"),
        ({"": 8}, "u64", "host receive time, ns since the Unix epoch (UTC)"),
    ],
    "elements": [
        ({"": 4}, "u32", "K, number of elements"),
        ({"": 4}, "u32", "reserved, 0"),
        ({"K": 24}, "f64 (K, 3)", "positions x, y, z [m]"),
        ({"K": 24}, "f64 (K, 3)", "unit normals, toward the upper (+normal) side"),
        ({"K": 8}, "f64 (K)", "position uncertainty, 1 s.d. [m]"),
        ({"K": 8}, "f64 (K)", "position scatter, 1 s.d. [m]: the part of the uncertainty that "
                              "repeated frames of a still sheet scatter by (layout 2 on)"),
        ({"K": 1}, "u8 (K)", "flags (below)"),
    ],
    "surface": [
        ({"": 4}, "u32", "N, rows"),
        ({"": 4}, "u32", "M, columns"),
        ({"": 4}, "u32", "P, points in the dense cloud (may be 0)"),
        ({"": 1}, "u8", "s, bytes per cloud coordinate: 4 (f32) or 8 (f64)"),
        ({"": 3}, "–", "padding, 0"),
        ({"N·M": 24}, "f64 (N, M, 3)", "cell-centre nodes x, y, z [m]"),
        ({"N·M": 24}, "f64 (N, M, 3)", "unit normals at the nodes"),
        ({"N·M": 8}, "f64 (N, M)", "node position uncertainty, 1 s.d. [m]"),
        ({"N·M": 8}, "f64 (N, M)", "node position scatter, 1 s.d. [m] (layout 2 on)"),
        ({"P·s": 3}, "f32/f64 (P, 3)", "dense point cloud [m]"),
    ],
    "strains": [
        ({"": 4}, "u32", "N"),
        ({"": 4}, "u32", "M"),
        ({"N·M": 16}, "f64 (2, N, M)", "upper-layer strain `eps_upper[k, i, j]`"),
        ({"N·M": 16}, "f64 (2, N, M)", "lower-layer strain `eps_lower[k, i, j]`"),
        ({"N·M": 2}, "u8 (2, N, M)", "gauge flags: 0x01 upper gauge valid, 0x02 lower gauge valid"),
    ],
}


def _format_size(size: Size) -> str:
    terms = [str(size[""])] if size.get("") else []
    terms += [sym if c == 1 else f"{c}·{sym}" for sym, c in size.items() if sym and c]
    return " + ".join(terms) or "0"


def layout_size(kind: str) -> Size:
    """Total length of a ``kind`` message as {symbol: coefficient}, header included."""
    total: Size = {}
    rows = LAYOUT_TABLES["header"] + ([] if kind == "header" else LAYOUT_TABLES[kind])
    for size, _type, _field in rows:
        for sym, c in size.items():
            total[sym] = total.get(sym, 0) + c
    return total


def layout_table(kind: str) -> str:
    """The markdown byte table of ``kind`` ('header', 'elements', 'surface', 'strains')."""
    if kind not in LAYOUT_TABLES:
        raise ValueError(f"unknown layout {kind!r}; expected one of {tuple(LAYOUT_TABLES)}")
    offset: Size = {} if kind == "header" else {"": HEADER_SIZE}
    lines = ["| offset | size | type | field |", "|---|---|---|---|"]
    for size, type_, field in LAYOUT_TABLES[kind]:
        lines.append(f"| {_format_size(offset)} | {_format_size(size)} | {type_} | {field} |")
        for sym, c in size.items():
            offset[sym] = offset.get(sym, 0) + c
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------
# helpers


def _check_uint(name: str, value: int, maximum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    value = int(value)
    if not 0 <= value <= maximum:
        raise ValueError(f"{name}={value} is outside 0..{maximum}")
    return value


def _as_array(name: str, value: Any, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if np.dtype(dtype).kind == "u":
        if arr.dtype.kind not in "uib":
            raise TypeError(f"{name} must be an integer array, got dtype {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(dtype).max):
            raise ValueError(f"{name} values must fit in {np.dtype(dtype).name}")
    elif arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=dtype)


def _header_bytes(kind: MessageKind, seq: int, length: int, device_time_us: int,
                  host_time_ns: int) -> bytes:
    seq = _check_uint("seq", seq, _U32_MAX)
    device_time_us = _check_uint("device_time_us", device_time_us, _U64_MAX)
    host_time_ns = _check_uint("host_time_ns", host_time_ns, _U64_MAX)
    if length > _U32_MAX:
        raise ValueError(f"message of {length} bytes exceeds the 4 GiB layout limit")
    return _HEADER.pack(MAGIC, LAYOUT_VERSION, int(kind), 0, seq, length, device_time_us,
                        host_time_ns)


def _as_buffer(buf: Any) -> memoryview:
    if type(buf) is memoryview and buf.format == "B" and buf.ndim == 1:
        return buf
    if type(buf).__name__ == "ZBytes":  # zenoh payloads, without importing zenoh here
        buf = buf.to_bytes()
    try:
        view = memoryview(buf)
    except TypeError:
        raise TypeError(f"expected a bytes-like message, got {type(buf).__name__}") from None
    return view.cast("B") if view.format != "B" or view.ndim != 1 else view


def decode_header(buf: Any) -> Header:
    """Parse and check the common header; raises MessageError naming what is wrong."""
    view = _as_buffer(buf)
    if len(view) < HEADER_SIZE:
        raise MessageError(f"truncated message: {len(view)} bytes, header needs {HEADER_SIZE}")
    magic, version, kind, _reserved, seq, length, dev_us, host_ns = _HEADER.unpack_from(view, 0)
    if magic != MAGIC:
        raise MessageError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version not in READABLE_VERSIONS:
        raise MessageError(f"unsupported layout version {version} (this decoder reads "
                           f"{', '.join(map(str, READABLE_VERSIONS))})")
    try:
        kind = MessageKind(kind)
    except ValueError:
        raise MessageError(f"unknown message kind {kind}") from None
    if length != len(view):
        what = "truncated" if len(view) < length else "oversized"
        raise MessageError(f"{what} {kind.name.lower()} message: header says {length} bytes, "
                           f"buffer has {len(view)}")
    return Header(kind, version, seq, length, dev_us, host_ns)


def _expect(header: Header, kind: MessageKind) -> None:
    if header.kind != kind:
        raise MessageError(f"expected a {kind.name.lower()} message, got "
                           f"{header.kind.name.lower()}")


def _read_arrays(view: memoryview, offset: int, specs: list[tuple[str, str, tuple[int, ...]]],
                 header: Header) -> list[np.ndarray]:
    total = offset + sum(math.prod(s) * np.dtype(d).itemsize for _, d, s in specs)
    if total != header.length:
        raise MessageError(f"{header.kind.name.lower()} message counts imply {total} bytes, "
                           f"message has {header.length}")
    out = []
    for _name, dtype, shape in specs:
        count = math.prod(shape)
        arr = np.frombuffer(view, dtype=dtype, count=count, offset=offset).reshape(shape)
        offset += arr.nbytes
        out.append(arr)
    return out


# ---------------------------------------------------------------------------------------
# elements


def encode_elements(seq: int, device_time_us: int, host_time_ns: int, positions: Any,
                    normals: Any, uncertainty: Any, flags: Any, scatter: Any = None) -> bytes:
    """Encode per-element positions (K,3) m, unit normals (K,3), 1-s.d. uncertainty (K,) m,
    ElementFlag bits (K,) and the uncertainty's scatter part (K,) m (None: the whole
    uncertainty, never less than the scatter) into an elements message."""
    positions = np.asarray(positions)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must have shape (K, 3), got {positions.shape}")
    k = positions.shape[0]
    _check_uint("element count K", k, _U32_MAX)
    pos = _as_array("positions", positions, "<f8", (k, 3))
    nrm = _as_array("normals", normals, "<f8", (k, 3))
    unc = _as_array("uncertainty", uncertainty, "<f8", (k,))
    sca = unc if scatter is None else _as_array("scatter", scatter, "<f8", (k,))
    flg = _as_array("flags", flags, "u1", (k,))
    length = HEADER_SIZE + _ELEMENTS_COUNTS.size + 65 * k
    return b"".join((_header_bytes(MessageKind.ELEMENTS, seq, length, device_time_us,
                                   host_time_ns),
                     _ELEMENTS_COUNTS.pack(k, 0), pos.tobytes(), nrm.tobytes(), unc.tobytes(),
                     sca.tobytes(), flg.tobytes()))


def decode_elements(buf: Any) -> ElementsMessage:
    """Decode an elements message; arrays are zero-copy read-only views of ``buf``."""
    view = _as_buffer(buf)
    header = decode_header(view)
    _expect(header, MessageKind.ELEMENTS)
    if len(view) < HEADER_SIZE + _ELEMENTS_COUNTS.size:
        raise MessageError("truncated elements message: no element count")
    (k, _reserved) = _ELEMENTS_COUNTS.unpack_from(view, HEADER_SIZE)
    scatter = [("scatter", "<f8", (k,))] if header.version >= 2 else []
    pos, nrm, unc, *sca, flg = _read_arrays(
        view, HEADER_SIZE + _ELEMENTS_COUNTS.size,
        [("positions", "<f8", (k, 3)), ("normals", "<f8", (k, 3)),
         ("uncertainty", "<f8", (k,)), *scatter, ("flags", "u1", (k,))], header)
    return ElementsMessage(header.seq, header.device_time_us, header.host_time_ns,
                           pos, nrm, unc, flg, sca[0] if sca else None)


# ---------------------------------------------------------------------------------------
# surface


def encode_surface(seq: int, device_time_us: int, host_time_ns: int, nodes: Any, normals: Any,
                   uncertainty: Any, cloud: Any = None, *, cloud_dtype: str = "float32",
                   scatter: Any = None) -> bytes:
    """Encode the node grid (N,M,3) m, node normals (N,M,3), node uncertainty (N,M) m, a dense
    point cloud (P,3) m stored as ``cloud_dtype`` ('float32' or 'float64') and the
    uncertainty's scatter part (N,M) m (None: the whole uncertainty)."""
    nodes = np.asarray(nodes)
    if nodes.ndim != 3 or nodes.shape[2] != 3:
        raise ValueError(f"nodes must have shape (N, M, 3), got {nodes.shape}")
    n, m = nodes.shape[:2]
    nd = _as_array("nodes", nodes, "<f8", (n, m, 3))
    nr = _as_array("normals", normals, "<f8", (n, m, 3))
    un = _as_array("uncertainty", uncertainty, "<f8", (n, m))
    sc = un if scatter is None else _as_array("scatter", scatter, "<f8", (n, m))
    if cloud_dtype not in ("float32", "float64"):
        raise ValueError(f"cloud_dtype must be 'float32' or 'float64', got {cloud_dtype!r}")
    cloud = np.zeros((0, 3)) if cloud is None else np.asarray(cloud)
    if cloud.ndim != 2 or cloud.shape[1] != 3:
        raise ValueError(f"cloud must have shape (P, 3), got {cloud.shape}")
    p = cloud.shape[0]
    itemsize = 4 if cloud_dtype == "float32" else 8
    cl = _as_array("cloud", cloud, f"<f{itemsize}", (p, 3))
    _check_uint("point count P", p, _U32_MAX)
    length = HEADER_SIZE + _SURFACE_COUNTS.size + n * m * 64 + p * 3 * itemsize
    return b"".join((_header_bytes(MessageKind.SURFACE, seq, length, device_time_us,
                                   host_time_ns),
                     _SURFACE_COUNTS.pack(n, m, p, itemsize), nd.tobytes(), nr.tobytes(),
                     un.tobytes(), sc.tobytes(), cl.tobytes()))


def decode_surface(buf: Any) -> SurfaceMessage:
    """Decode a surface message; arrays are zero-copy read-only views of ``buf``."""
    view = _as_buffer(buf)
    header = decode_header(view)
    _expect(header, MessageKind.SURFACE)
    if len(view) < HEADER_SIZE + _SURFACE_COUNTS.size:
        raise MessageError("truncated surface message: no grid counts")
    n, m, p, itemsize = _SURFACE_COUNTS.unpack_from(view, HEADER_SIZE)
    if itemsize not in (4, 8):
        raise MessageError(f"surface cloud coordinate size must be 4 or 8 bytes, got {itemsize}")
    scatter = [("scatter", "<f8", (n, m))] if header.version >= 2 else []
    nd, nr, un, *sc, cl = _read_arrays(
        view, HEADER_SIZE + _SURFACE_COUNTS.size,
        [("nodes", "<f8", (n, m, 3)), ("normals", "<f8", (n, m, 3)),
         ("uncertainty", "<f8", (n, m)), *scatter, ("cloud", f"<f{itemsize}", (p, 3))], header)
    return SurfaceMessage(header.seq, header.device_time_us, header.host_time_ns,
                          nd, nr, un, cl, sc[0] if sc else None)


# ---------------------------------------------------------------------------------------
# strains


def encode_strains(seq: int, device_time_us: int, host_time_ns: int, eps_upper: Any,
                   eps_lower: Any, gauge_flags: Any) -> bytes:
    """Encode upper/lower layer strains (2,N,M) and GaugeFlag bits (2,N,M)."""
    eps_upper = np.asarray(eps_upper)
    if eps_upper.ndim != 3 or eps_upper.shape[0] != 2:
        raise ValueError(f"eps_upper must have shape (2, N, M), got {eps_upper.shape}")
    shape = eps_upper.shape
    up = _as_array("eps_upper", eps_upper, "<f8", shape)
    lo = _as_array("eps_lower", eps_lower, "<f8", shape)
    fl = _as_array("gauge_flags", gauge_flags, "u1", shape)
    n, m = shape[1:]
    length = HEADER_SIZE + _STRAINS_COUNTS.size + 2 * n * m * 17
    return b"".join((_header_bytes(MessageKind.STRAINS, seq, length, device_time_us,
                                   host_time_ns),
                     _STRAINS_COUNTS.pack(n, m), up.tobytes(), lo.tobytes(), fl.tobytes()))


def decode_strains(buf: Any) -> StrainsMessage:
    """Decode a strains message; arrays are zero-copy read-only views of ``buf``."""
    view = _as_buffer(buf)
    header = decode_header(view)
    _expect(header, MessageKind.STRAINS)
    if len(view) < HEADER_SIZE + _STRAINS_COUNTS.size:
        raise MessageError("truncated strains message: no grid counts")
    n, m = _STRAINS_COUNTS.unpack_from(view, HEADER_SIZE)
    up, lo, fl = _read_arrays(
        view, HEADER_SIZE + _STRAINS_COUNTS.size,
        [("eps_upper", "<f8", (2, n, m)), ("eps_lower", "<f8", (2, n, m)),
         ("gauge_flags", "u1", (2, n, m))], header)
    return StrainsMessage(header.seq, header.device_time_us, header.host_time_ns, up, lo, fl)


_DECODERS: dict[MessageKind, Callable[[Any], "ElementsMessage | SurfaceMessage | StrainsMessage"]] = {
    MessageKind.ELEMENTS: decode_elements, MessageKind.SURFACE: decode_surface, MessageKind.STRAINS: decode_strains}


def decode(buf: Any) -> ElementsMessage | SurfaceMessage | StrainsMessage:
    """Decode any binary message by its header kind."""
    view = _as_buffer(buf)
    return _DECODERS[decode_header(view).kind](view)


# ---------------------------------------------------------------------------------------
# JSON status and info

STATUS_SCHEMA = "skinmap.status/1"
INFO_SCHEMA = "skinmap.info/1"

class _StatusReportRequired(TypedDict):
    device: str
    host_time_ns: int
    connected: bool
    seq: int
    scan_rate_hz: float
    publish_rate_hz: float
    frames_dropped: int
    crc_errors: int
    reconnects: int
    solver_time_ms: float
    log_state: str


class StatusReport(_StatusReportRequired, total=False):
    """A status report: the required fields (STATUS_FIELDS says what each means) and what else
    the gateway sends (counters, conditions; kept by decoding) as far as tools read it."""

    link_state: str  # the gateway's link state machine


class DeviceInfo(TypedDict):
    """The device description: the required fields (INFO_FIELDS says what each means); more
    are allowed and kept."""

    device: str
    rows: int
    cols: int
    pitch_m: float
    elements: dict[str, Any]
    calibration: dict[str, Any]
    versions: dict[str, Any]


_STATUS_MEANINGS = {
    "device": "device name (the <device> key segment)",
    "host_time_ns": "host time of this report, ns since the Unix epoch",
    "connected": "scanner link is up",
    "seq": "sequence number of the last published scan",
    "scan_rate_hz": "scans received per second (recent mean)",
    "publish_rate_hz": "shapes published per second (recent mean)",
    "frames_dropped": "scans skipped since start (sequence gaps + solver overruns)",
    "crc_errors": "frames rejected by CRC since start",
    "reconnects": "serial reconnections since start",
    "solver_time_ms": "reconstruction time of the last scan, ms",
    "log_state": "MCAP logger: 'off', 'recording' or 'error'",
}

_INFO_MEANINGS = {
    "device": "device name",
    "rows": "N, cell rows",
    "cols": "M, cell columns",
    "pitch_m": "cell pitch, metres",
    "elements": "element layout: {'count': K, 'width_m', 'height_m', 'material_uv_m': K x [u, v] on the flat sheet}",
    "calibration": "{'gauge_factor': [...], 'r0_ohm': [...], 'source': ...}",
    "versions": "{'skinmap': ..., 'protocol': ..., 'firmware': ...}",
}


def _fields(payload: Any, meanings: dict[str, str]) -> dict[str, tuple[tuple[type, ...], str]]:
    """field -> (accepted JSON types, meaning) of a payload's required fields, from its
    TypedDict (a float field also takes a JSON integer)."""
    hints = get_type_hints(payload)
    required = [name for name in hints if name in payload.__required_keys__]
    if sorted(required) != sorted(meanings):
        raise RuntimeError(f"{payload.__name__}: meanings for {sorted(meanings)}, fields {sorted(required)}")
    accepted = {str: (str,), int: (int,), bool: (bool,), float: (int, float), dict: (dict,)}
    return {name: (accepted[get_origin(hints[name]) or hints[name]], meanings[name]) for name in required}


# field -> (accepted types, meaning). Required fields; extra fields are allowed and kept.
STATUS_FIELDS = _fields(StatusReport, _STATUS_MEANINGS)
INFO_FIELDS = _fields(DeviceInfo, _INFO_MEANINGS)


def _check_fields(kind: str, obj: Mapping[str, Any],
                  fields: dict[str, tuple[tuple[type, ...], str]]) -> None:
    if not isinstance(obj, Mapping):
        raise TypeError(f"{kind} must be a mapping, got {type(obj).__name__}")
    missing = [f for f in fields if f not in obj]
    if missing:
        raise ValueError(f"{kind} is missing field(s): {', '.join(missing)}")
    for name, (types, _doc) in fields.items():
        value = obj[name]
        ok = isinstance(value, types) and not (isinstance(value, bool) and bool not in types)
        if not ok:
            raise ValueError(f"{kind} field {name!r} must be {'/'.join(t.__name__ for t in types)}"
                             f", got {type(value).__name__}")


def _encode_json(kind: str, schema: str, obj: Mapping[str, Any],
                 fields: dict[str, tuple[tuple[type, ...], str]]) -> bytes:
    _check_fields(kind, obj, fields)
    body = {"schema": schema, **obj}
    try:
        return json.dumps(body, allow_nan=False, separators=(",", ":")).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{kind} is not JSON-serialisable: {exc}") from None


def _decode_json(kind: str, schema: str, buf: Any,
                 fields: dict[str, tuple[tuple[type, ...], str]]) -> dict[str, Any]:
    raw = bytes(_as_buffer(buf))
    try:
        obj = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise MessageError(f"{kind} is not UTF-8: {exc}") from None
    except json.JSONDecodeError as exc:
        raise MessageError(f"{kind} is not valid JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise MessageError(f"{kind} must be a JSON object, got {type(obj).__name__}")
    if obj.get("schema") != schema:
        raise MessageError(f"{kind} schema is {obj.get('schema')!r}, expected {schema!r}")
    try:
        _check_fields(kind, obj, fields)
    except ValueError as exc:
        raise MessageError(str(exc)) from None
    return obj


def encode_status(status: Mapping[str, Any]) -> bytes:
    """Encode a status report (fields in STATUS_FIELDS) as UTF-8 JSON."""
    return _encode_json("status", STATUS_SCHEMA, status, STATUS_FIELDS)


def decode_status(buf: Any) -> StatusReport:
    return cast(StatusReport, _decode_json("status", STATUS_SCHEMA, buf, STATUS_FIELDS))


def encode_info(info: Mapping[str, Any]) -> bytes:
    """Encode the device description (fields in INFO_FIELDS) as UTF-8 JSON."""
    return _encode_json("info", INFO_SCHEMA, info, INFO_FIELDS)


def decode_info(buf: Any) -> DeviceInfo:
    return cast(DeviceInfo, _decode_json("info", INFO_SCHEMA, buf, INFO_FIELDS))


# ---------------------------------------------------------------------------------------
# JSON probe pose (an input of the gateway: docs/tactile.md)

POSE_SCHEMA = "skinmap.pose/1"

#: Where the probe is for the press that follows: put by whatever moves the probe, before the
#: press, on ``keys.pose_key``; the gateway logs it as ``/pose`` and ``skinmap map`` gives each
#: contact event the latest pose logged before it began.
POSE_FIELDS: dict[str, tuple[tuple[type, ...], str]] = {
    "x_mm": ((int, float), "wall x of the probe frame's origin (the balloon's apex, the sheet's centre), mm"),
    "y_mm": ((int, float), "wall y of the probe frame's origin, mm"),
    "angle_deg": ((int, float), "turn of the probe frame about the wall normal, degrees"),
    "depth_mm": ((int, float), "how far the wall's base plane is pressed in beyond the apex, mm"),
}


def json_table(kind: str) -> str:
    """The markdown field table of a JSON message (docs/zenoh.md shows it; a test keeps them equal)."""
    schema, fields = {"pose": (POSE_SCHEMA, POSE_FIELDS)}[kind]
    lines = ["| field | type | meaning |", "|---|---|---|", f'| `schema` | string | `"{schema}"` |']
    for name, (types, doc) in fields.items():
        kind_name = "number" if float in types else "/".join(t.__name__ for t in types)
        lines.append(f"| `{name}` | {kind_name} | {doc} |")
    return "\n".join(lines)


def pose_json_schema() -> dict[str, Any]:
    """JSON Schema of the pose message (the MCAP `/pose` channel's schema)."""
    return {"title": "skinmap.Pose", "type": "object", "required": ["schema", *POSE_FIELDS],
            "properties": {"schema": {"const": POSE_SCHEMA},
                           **{name: {"type": "number", "description": doc} for name, (_t, doc) in POSE_FIELDS.items()}}}


def encode_pose(pose: Mapping[str, Any]) -> bytes:
    """Encode a probe pose (fields in POSE_FIELDS, finite numbers) as UTF-8 JSON."""
    _check_pose_values(pose, ValueError)
    return _encode_json("pose", POSE_SCHEMA, pose, POSE_FIELDS)


def decode_pose(buf: Any) -> dict[str, Any]:
    """A probe pose; MessageError names what is wrong (not JSON, schema, a missing or
    non-numeric or non-finite field)."""
    obj = _decode_json("pose", POSE_SCHEMA, buf, POSE_FIELDS)
    _check_pose_values(obj, MessageError)
    return obj


def _check_pose_values(pose: Mapping[str, Any], error: type[Exception]) -> None:
    if not isinstance(pose, Mapping):
        raise TypeError(f"pose must be a mapping, got {type(pose).__name__}")
    for name in POSE_FIELDS:
        value = pose.get(name)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isfinite(value):
            raise error(f"pose field {name!r} must be finite, got {value!r}")
