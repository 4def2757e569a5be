"""Test vectors and layout tables of PROTOCOL.md, generated from the codec.

`python -m skinmap.protocol.specgen` rewrites protocol/test_vectors.json and prints the
markdown layout tables. The test suite checks that the committed JSON and the tables in
PROTOCOL.md equal what this module builds, so the specification and the code cannot drift.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
from cobs import cobs

from .codec import encode_frame
from .framing import HEADER, HEADER_SIZE, MAX_ENCODED_BODY, MAX_PAYLOAD, crc32
from .payloads import (
    LAYOUTS,
    MESSAGE_CLASSES,
    SCHEMA_HASH,
    Ack,
    ErrorCode,
    FaultFlag,
    Hello,
    Message,
    MsgType,
    Nak,
    Ping,
    QueryInfo,
    Reset,
    Scan,
    ScanFlag,
    SetScanRate,
    Start,
    Status,
    Stop,
    layout_rows,
    schema_text,
)
from .stream import StreamDecoder
from .tdm import default_channel_map, step_period_ns

VECTORS_PATH = Path(__file__).with_name("test_vectors.json")

_ARRAY_DTYPES: dict[str, dict[str, Any]] = {
    "Hello": {"gauge_factor_micro": np.uint32, "base_resistance_uohm": np.uint32,
              "drive_line": np.uint8, "sense_channel": np.uint8},
    "Scan": {"resistance_uohm": np.uint32},
    "Status": {"open_gauges": bool, "saturated_gauges": bool},
}
_BYTES_FIELDS = {"result", "echo"}


def message_to_fields(msg: Message) -> dict[str, Any]:
    """JSON-ready field values of a message (arrays as nested lists, bytes as hex)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        if isinstance(value, np.ndarray):
            value = value.astype(int).tolist() if value.dtype == bool else value.tolist()
        elif isinstance(value, (bytes, bytearray)):
            value = bytes(value).hex()
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def message_from_fields(type_name: str, fields: dict[str, Any]) -> Message:
    """Inverse of message_to_fields; `type_name` is a MsgType name such as "SCAN"."""
    cls = MESSAGE_CLASSES[MsgType[type_name]]
    dtypes = _ARRAY_DTYPES.get(cls.__name__, {})
    kwargs: dict[str, Any] = {}
    for name, value in fields.items():
        if name in dtypes:
            value = np.array(value, dtype=dtypes[name])
        elif name in _BYTES_FIELDS:
            value = bytes.fromhex(value)
        elif name == "fw_version":
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def example_messages() -> list[tuple[str, int, Message]]:
    """(vector name, seq, message) for every message type, on a 2 × 3 array."""
    n, m = 2, 3
    idx = np.arange(4 * n * m).reshape(2, 2, n, m)
    drive, sense = default_channel_map(n, m)
    hello = Hello(
        fw_version=(1, 4, 2), serial_number="SKM-2026-000017", pitch_um=12000,
        gauge_length_um=10000, h_upper_um=200, h_lower_um=200, scan_rate_mhz=10000,
        max_scan_rate_mhz=200000, resistance_lsb_uohm=25,
        gauge_factor_micro=(1_240_000 + 7_500 * idx).astype(np.uint32),
        base_resistance_uohm=(6_550_000 + 12_345 * idx).astype(np.uint32),
        drive_line=drive, sense_channel=sense,
    )
    res = (6_550_000 + 1_000 * idx).astype(np.uint32)
    res[0, 1, 1, 2] = 0xFFFFFFFF
    res[1, 0, 0, 1] = 0xFFFFFFFE
    scan = Scan(sample_index=41, timestamp_us=1_234_567_890, step_period_ns=step_period_ns(10000, n, m),
                resistance_uohm=res, flags=int(ScanFlag.OPEN_GAUGE | ScanFlag.SATURATED_GAUGE))
    status = Status(
        timestamp_us=1_235_000_000, fault_flags=int(FaultFlag.GAUGE_OPEN | FaultFlag.GAUGE_SATURATED),
        scans_sent=42, scans_dropped=0, frames_rejected=1, supply_mv=3298, temperature_cdeg=2731,
        state=1, open_gauges=res == 0xFFFFFFFF, saturated_gauges=res == 0xFFFFFFFE, buffer_fill_pct=3,
    )
    return [
        ("hello", 0, hello),
        ("scan", 7, scan),
        ("status", 8, status),
        ("ack_set_scan_rate", 9, Ack(request_id=3, command=int(MsgType.SET_SCAN_RATE), result=(25000).to_bytes(4, "little"))),
        ("ack_ping", 10, Ack(request_id=5, command=int(MsgType.PING), result=b"skin")),
        ("nak_bad_argument", 11, Nak(request_id=4, command=int(MsgType.SET_SCAN_RATE), error=int(ErrorCode.BAD_ARGUMENT), argument=1)),
        ("start", 0, Start(request_id=1)),
        ("stop", 1, Stop(request_id=2)),
        ("set_scan_rate", 2, SetScanRate(request_id=3, scan_rate_mhz=25000)),
        ("query_info", 3, QueryInfo(request_id=4)),
        ("ping", 4, Ping(request_id=5, echo=b"skin")),
        ("reset", 5, Reset(request_id=6)),
    ]


def _raw_frame(msg_type: int, seq: int, payload: bytes, *, version: int = 1,
               incompat: int = 0, compat: int = 0, crc_xor: int = 0) -> bytes:
    head = HEADER.pack(version, incompat, compat, msg_type, seq, len(payload))
    crc = crc32(head + payload) ^ crc_xor
    return head + payload + crc.to_bytes(4, "little")


def _reject_vectors() -> list[dict[str, Any]]:
    """Bodies a receiver must reject, with the error class and stream counter."""
    start = Start(request_id=1).pack_payload()
    examples = {name: msg for name, _, msg in example_messages()}
    hello_payload = bytearray(examples["hello"].pack_payload())
    hello_payload[2] = 33  # N beyond 32
    scan_payload = examples["scan"].pack_payload()
    cases = [
        ("bad_crc", _raw_frame(0x10, 0, start, crc_xor=0x1), "CrcError", "crc_errors"),
        ("unknown_incompat_flag", _raw_frame(0x10, 0, start, incompat=0x80), "IncompatibleFlagsError", "incompat_flag_drops"),
        ("unknown_compat_flag_is_ignored", _raw_frame(0x10, 0, start, compat=0x80), None, "frames_ok"),
        ("major_version_2", _raw_frame(0x10, 0, start, version=2), "VersionError", "version_errors"),
        ("unknown_type_0x7f", _raw_frame(0x7F, 0, start), "UnknownMessageTypeError", "unknown_type"),
        ("hello_n_33", _raw_frame(0x01, 0, bytes(hello_payload)), "FieldError", "field_errors"),
        ("scan_payload_short_by_4", _raw_frame(0x02, 0, scan_payload[:-4]), "LengthError", "length_errors"),
        ("start_payload_too_long", _raw_frame(0x10, 0, start + b"\x00"), "LengthError", "length_errors"),
    ]
    out = []
    for name, raw, error, counter in cases:
        frame = cobs.encode(raw) + b"\x00"
        out.append({"name": name, "raw_hex": raw.hex(), "frame_hex": frame.hex(),
                    "error": error, "counter": counter})
    return out


def _stream_vectors() -> list[dict[str, Any]]:
    examples = {name: msg for name, _, msg in example_messages()}
    # consecutive sequence numbers, as a device sends them
    ack = encode_frame(examples["ack_set_scan_rate"], 9)
    scan = encode_frame(examples["scan"], 10)
    status = encode_frame(examples["status"], 8)
    garbage = bytes.fromhex("1337deadbeef00c0ffee")  # a delimiter inside, no delimiter at its end
    truncated = status[: len(status) // 2]  # e.g. a reset mid-frame
    streams = {
        "garbage_then_two_frames": garbage + ack + scan,
        "truncated_frame_then_delimiter_then_frame": truncated + b"\x00" + ack,
        "bit_flip_in_first_of_two_frames": bytes([ack[0], ack[1] ^ 0x10]) + ack[2:] + scan,
    }
    out = []
    for name, data in streams.items():
        decoder = StreamDecoder()
        got = decoder.feed(data)
        out.append({
            "name": name,
            "hex": data.hex(),
            "expected_frames": [{"type": f.msg_type.name, "seq": f.seq, "frame_hex": f.raw.hex()} for f in got],
            "expected_counters": decoder.counters(),
        })
    return out


def build_vectors() -> dict[str, Any]:
    messages = []
    for name, seq, msg in example_messages():
        frame = encode_frame(msg, seq)
        raw = cobs.decode(frame[:-1])
        messages.append({
            "name": name, "type": msg.TYPE.name, "seq": seq, "compat_flags": 0, "incompat_flags": 0,
            "fields": message_to_fields(msg),
            "payload_hex": raw[HEADER_SIZE:-4].hex(),
            "raw_hex": raw.hex(),
            "frame_hex": frame.hex(),
        })
    return {
        "protocol_version": "1.0",
        "crc32_check": {"ascii": "123456789", "crc32": f"0x{crc32(b'123456789'):08X}"},
        "limits": {"max_payload": MAX_PAYLOAD, "max_encoded_body": MAX_ENCODED_BODY},
        "schema_hash": f"0x{SCHEMA_HASH:08X}",
        "schema_text": schema_text(),
        "messages": messages,
        "rejects": _reject_vectors(),
        "streams": _stream_vectors(),
    }


def layout_table_markdown(mtype: MsgType) -> str:
    lines = ["| offset | size | type | name | units / meaning |", "|---|---|---|---|---|"]
    for offset, size, ftype, name, units in layout_rows(mtype):
        lines.append(f"| {offset} | {size} | {ftype} | `{name}` | {units} |")
    return "\n".join(lines)


def vectors_json() -> str:
    return json.dumps(build_vectors(), indent=1) + "\n"


def main() -> None:
    VECTORS_PATH.write_text(vectors_json())
    for mtype in LAYOUTS:
        print(f"#### {mtype.name} (0x{mtype.value:02X})\n\n{layout_table_markdown(mtype)}\n")


if __name__ == "__main__":
    main()
