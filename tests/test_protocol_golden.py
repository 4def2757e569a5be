"""Golden frames written by hand from PROTOCOL.md's byte tables, field by field.

Nothing here is produced by the codec: the header and payload bytes are literals read off the
tables (sections 4, 7 and 8), the CRC is zlib's CRC-32 (section 3 names it) and COBS is the
reference algorithm written out below. The codec must encode each message to exactly these
bytes and decode them back to the same fields.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from skinmap import protocol as p


def h(text: str) -> bytes:
    """Hex with spaces and '#' comments allowed, one field a line."""
    return bytes.fromhex("".join(line.split("#")[0] for line in text.splitlines()))


def cobs_reference(data: bytes) -> bytes:
    """Basic COBS (PROTOCOL.md section 3): each block is a code byte (distance to the next zero,
    0xFF = 254 data bytes and no zero) followed by its non-zero bytes; no code after a final
    full block."""
    out, block, ended_full = bytearray(), bytearray(), False
    for byte in data:
        ended_full = False
        if byte == 0:
            out += bytes([len(block) + 1]) + block
            block.clear()
        else:
            block.append(byte)
            if len(block) == 254:
                out += b"\xff" + block
                block.clear()
                ended_full = True
    if not ended_full:
        out += bytes([len(block) + 1]) + block
    return bytes(out)


def wire(header: bytes, payload: bytes) -> bytes:
    raw = header + payload
    return cobs_reference(raw + zlib.crc32(raw).to_bytes(4, "little")) + b"\x00"


# START (0x10), seq 5, request_id 0x1234. The whole frame, COBS included, by hand.
START_FRAME = h("""
    02 01          # COBS code 2: one byte (version 0x01), then a zero
    01             # COBS code 1: incompat_flags = 0x00
    03 10 05       # COBS code 3: compat_flags = 0x00 before it ... msg_type 0x10, seq low byte 0x05
    02 02          # seq high byte 0x00 before it; payload_len low byte 0x02
    07 34 12       # payload_len high byte 0x00 before it; request_id 0x1234 little-endian
       01 44 c1 d9 # CRC-32 0xD9C14401 of header + payload, little-endian
    00             # delimiter
""")
START_RAW = h("""
    01     # version 1
    00     # incompat_flags
    00     # compat_flags
    10     # msg_type START
    05 00  # seq 5
    02 00  # payload_len 2
    34 12  # request_id 0x1234
    01 44 c1 d9  # crc32 0xD9C14401
""")

GOLDEN: list[tuple[str, p.Message, int, bytes, bytes]] = [
    ("set_scan_rate", p.SetScanRate(request_id=7, scan_rate_mhz=25_000), 6,
     h("01 00 00 12  06 00  06 00   # version, flags, SET_SCAN_RATE, seq 6, payload_len 6"),
     h("""07 00         # request_id 7
          a8 61 00 00   # scan_rate_mhz 25 000 = 0x61A8"""), ),
    ("nak", p.Nak(request_id=7, command=0x12, error=int(p.ErrorCode.BAD_ARGUMENT), argument=1), 8,
     h("01 00 00 05  08 00  05 00   # NAK, seq 8, payload_len 5"),
     h("""07 00   # request_id 7
          12      # command SET_SCAN_RATE
          03      # error BAD_ARGUMENT
          01      # argument 1"""), ),
    ("ack_ping", p.Ack(request_id=9, command=0x14, result=b"skin"), 9,
     h("01 00 00 04  09 00  07 00   # ACK, seq 9, payload_len 7"),
     h("""09 00         # request_id 9
          14            # command PING
          73 6b 69 6e   # result: the echo 'skin'"""), ),
    ("ping", p.Ping(request_id=9, echo=b"skin"), 6,
     h("01 00 00 14  06 00  06 00   # PING, seq 6, payload_len 6"),
     h("""09 00         # request_id 9
          73 6b 69 6e   # echo 'skin'"""), ),
    ("scan_2x2", p.Scan(
        sample_index=41, timestamp_us=1_000_000, step_period_ns=25_000_000,
        resistance_uohm=np.array([0xFFFFFFFF if g == 5 else 6_550_000 + g for g in range(16)],
                                 dtype=np.uint32).reshape(2, 2, 2, 2),
        flags=int(p.ScanFlag.OPEN_GAUGE)), 300,
     h("01 00 00 02  2c 01  54 00   # SCAN, seq 300 = 0x012C, payload_len 20 + 16·4 = 84"),
     h("""29 00 00 00                # sample_index 41
          40 42 0f 00 00 00 00 00    # timestamp_us 1 000 000 = 0x0F4240
          40 78 7d 01                # step_period_ns 25 000 000 = 0x017D7840
          02 02                      # n, m
          01 00                      # flags OPEN_GAUGE
          f0 f1 63 00  f1 f1 63 00  f2 f1 63 00  f3 f1 63 00   # gauges 0-3: 6 550 000 + g µΩ
          f4 f1 63 00  ff ff ff ff  f6 f1 63 00  f7 f1 63 00   # gauge 5 open (0xFFFFFFFF)
          f8 f1 63 00  f9 f1 63 00  fa f1 63 00  fb f1 63 00
          fc f1 63 00  fd f1 63 00  fe f1 63 00  ff f1 63 00"""), ),
    ("status_2x2", p.Status(
        timestamp_us=2_000_000, fault_flags=int(p.FaultFlag.GAUGE_OPEN | p.FaultFlag.GAUGE_SATURATED),
        scans_sent=42, scans_dropped=3, frames_rejected=1, supply_mv=3300, temperature_cdeg=-250,
        state=int(p.DeviceState.SCANNING),
        open_gauges=(np.arange(16) == 5).reshape(2, 2, 2, 2),
        saturated_gauges=(np.arange(16) == 9).reshape(2, 2, 2, 2), buffer_fill_pct=3), 1,
     h("01 00 00 03  01 00  24 00   # STATUS, seq 1, payload_len 32 + 2·2 = 36"),
     h("""80 84 1e 00 00 00 00 00    # timestamp_us 2 000 000 = 0x1E8480
          03 00 00 00                # fault_flags GAUGE_OPEN | GAUGE_SATURATED
          2a 00 00 00                # scans_sent 42
          03 00 00 00                # scans_dropped 3
          01 00 00 00                # frames_rejected 1
          e4 0c                      # supply_mv 3300 = 0x0CE4
          06 ff                      # temperature_cdeg -250 (two's complement 0xFF06)
          01                         # state SCANNING
          02 02                      # n, m
          03                         # buffer_fill_pct 3
          20 00                      # open_bitmap: gauge 5 = byte 0, bit 5
          00 02                      # saturated_bitmap: gauge 9 = byte 1, bit 1"""), ),
    ("hello_2x2", p.Hello(
        fw_version=(1, 4, 2), serial_number="SKM-TEST-0001", pitch_um=12_000,
        gauge_length_um=10_000, h_upper_um=200, h_lower_um=200, scan_rate_mhz=10_000,
        max_scan_rate_mhz=200_000, resistance_lsb_uohm=25,
        gauge_factor_micro=np.full((2, 2, 2, 2), 1_240_000, dtype=np.uint32),
        base_resistance_uohm=np.full((2, 2, 2, 2), 6_550_000, dtype=np.uint32),
        drive_line=np.array([0, 1, 2, 3, 3, 2, 1, 0], dtype=np.uint8).reshape(2, 2, 2),
        sense_channel=np.array(list(range(8)) * 2, dtype=np.uint8).reshape(2, 2, 2, 2)), 0,
     h("01 00 00 01  00 00  cc 00   # HELLO, seq 0, payload_len 52 + 38·4 = 204"),
     h("""01 00                      # protocol_major 1, protocol_minor 0
          02 02                      # n, m
          01 04 02 00                # fw_major 1, fw_minor 4, fw_patch 2
          53 4b 4d 2d 54 45 53 54 2d 30 30 30 31 00 00 00   # serial 'SKM-TEST-0001', NUL-padded
          53 3a 1c 32                # schema_hash 0x321C3A53 (PROTOCOL.md 7.1)
          e0 2e 00 00                # pitch_um 12 000
          10 27 00 00                # gauge_length_um 10 000
          c8 00  c8 00               # h_upper_um 200, h_lower_um 200
          10 27 00 00                # scan_rate_mhz 10 000
          40 0d 03 00                # max_scan_rate_mhz 200 000 = 0x030D40
          19 00 00 00                # resistance_lsb_uohm 25
    """) + h("c0 eb 12 00") * 16       # gauge_factor_micro 1 240 000 = 0x12EBC0, 16 gauges
         + h("f0 f1 63 00") * 16       # base_resistance_uohm 6 550 000 = 0x63F1F0
         + h("00 01 02 03  03 02 01 00")  # drive_line, 8 units
         + h("00 01 02 03 04 05 06 07  00 01 02 03 04 05 06 07"),  # sense_channel, 16 gauges
     ),
]


def test_reference_cobs_reproduces_the_hand_written_start_frame() -> None:
    assert zlib.crc32(START_RAW[:-4]) == 0xD9C14401
    assert cobs_reference(START_RAW) + b"\x00" == START_FRAME


def test_start_frame_written_by_hand() -> None:
    assert p.encode_frame(p.Start(request_id=0x1234), 5) == START_FRAME
    frame = p.decode_frame(START_FRAME)
    assert (frame.seq, frame.msg) == (5, p.Start(request_id=0x1234))


@pytest.mark.parametrize("name, msg, seq, header, payload", GOLDEN, ids=[g[0] for g in GOLDEN])
def test_golden_frame(name: str, msg: p.Message, seq: int, header: bytes, payload: bytes) -> None:
    assert int.from_bytes(header[6:8], "little") == len(payload), "payload_len in the literal"
    assert msg.pack_payload() == payload
    expected = wire(header, payload)
    assert p.encode_frame(msg, seq) == expected
    frame = p.decode_frame(expected)
    assert frame.seq == seq
    assert frame.msg == msg
    decoder = p.StreamDecoder()
    (got,) = decoder.feed(b"\x00" + expected)
    assert got.msg == msg and decoder.counters()["frames_ok"] == 1


def test_scan_golden_frame_decodes_the_open_gauge_as_nan() -> None:
    _, msg, seq, header, payload = next(g for g in GOLDEN if g[0] == "scan_2x2")
    scan = p.decode_frame(wire(header, payload)).msg
    ohm = scan.resistances_ohm().ravel()
    assert np.isnan(ohm[5]) and ohm[0] == pytest.approx(6.55) and ohm[15] == pytest.approx(6.550015)


def test_request_only_commands_share_one_layout() -> None:
    from skinmap.protocol.payloads import LAYOUTS

    layouts = {LAYOUTS[t] for t in (p.MsgType.START, p.MsgType.STOP, p.MsgType.QUERY_INFO, p.MsgType.RESET)}
    assert len(layouts) == 1


def test_header_table_in_protocol_md_matches_the_header_layout() -> None:
    import re
    from pathlib import Path

    from skinmap.protocol.layout import HEADER_LAYOUT, TYPE_SIZE

    spec = (Path(p.__file__).parent / "PROTOCOL.md").read_text()
    section = spec[spec.index("## 4. Header and limits"):spec.index("Flag rules")]
    rows = re.findall(r"^\| (\d+) \| (\d+) \| (\w+) \| `(\w+)` \|", section, flags=re.M)
    offsets = np.cumsum([0] + [TYPE_SIZE[f.type] for f in HEADER_LAYOUT])[:-1]
    assert rows == [(str(o), str(TYPE_SIZE[f.type]), f.type, f.name) for o, f in zip(offsets, HEADER_LAYOUT)]
