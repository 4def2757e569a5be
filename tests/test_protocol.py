"""Wire protocol: test vectors, round trips, limits and bad-input errors."""

from __future__ import annotations

import json
import re
import zlib
from pathlib import Path

import numpy as np
import pytest

from skinmap import protocol as p
from skinmap.protocol import specgen
from skinmap.protocol.framing import HEADER, MAX_RAW_FRAME, encode_body
from cobs import cobs

PROTOCOL_DIR = Path(p.__file__).parent
VECTORS = json.loads((PROTOCOL_DIR / "test_vectors.json").read_text())
SPEC = (PROTOCOL_DIR / "PROTOCOL.md").read_text() if (PROTOCOL_DIR / "PROTOCOL.md").exists() else ""


# --- test vectors ----------------------------------------------------------------------------


def test_crc32_check_value() -> None:
    assert p.crc32(b"123456789") == 0xCBF43926
    assert VECTORS["crc32_check"]["crc32"] == "0xCBF43926"


def test_schema_hash_matches_vectors() -> None:
    assert VECTORS["schema_text"] == p.schema_text()
    assert VECTORS["schema_hash"] == f"0x{p.SCHEMA_HASH:08X}"
    assert p.SCHEMA_HASH == zlib.crc32(p.schema_text().encode("ascii"))


def test_every_message_type_has_a_vector() -> None:
    assert {v["type"] for v in VECTORS["messages"]} == {t.name for t in p.MsgType}


@pytest.mark.parametrize("vec", VECTORS["messages"], ids=lambda v: v["name"])
def test_vector_encode_equals_hex(vec: dict) -> None:
    msg = specgen.message_from_fields(vec["type"], vec["fields"])
    frame = p.encode_frame(msg, vec["seq"])
    assert frame.hex() == vec["frame_hex"]
    raw = cobs.decode(frame[:-1])
    assert raw.hex() == vec["raw_hex"]
    assert raw[p.HEADER_SIZE:-4].hex() == vec["payload_hex"]


@pytest.mark.parametrize("vec", VECTORS["messages"], ids=lambda v: v["name"])
def test_vector_decode_equals_fields(vec: dict) -> None:
    frame = p.decode_frame(bytes.fromhex(vec["frame_hex"]))
    assert frame.seq == vec["seq"]
    assert frame.msg_type.name == vec["type"]
    assert specgen.message_to_fields(frame.msg) == vec["fields"]
    assert frame.raw.hex() == vec["frame_hex"]


@pytest.mark.parametrize("vec", VECTORS["rejects"], ids=lambda v: v["name"])
def test_reject_vectors(vec: dict) -> None:
    data = bytes.fromhex(vec["frame_hex"])
    assert cobs.decode(data[:-1]).hex() == vec["raw_hex"]
    if vec["error"] is None:
        p.decode_frame(data)
    else:
        with pytest.raises(getattr(p, vec["error"])):
            p.decode_frame(data)
    decoder = p.StreamDecoder()
    decoder.feed(data)
    assert getattr(decoder, vec["counter"]) == 1


@pytest.mark.parametrize("vec", VECTORS["streams"], ids=lambda v: v["name"])
def test_stream_vectors(vec: dict) -> None:
    data = bytes.fromhex(vec["hex"])
    for chunk in (len(data), 1, 7):  # result must not depend on how reads split the stream
        decoder = p.StreamDecoder()
        frames = [f for i in range(0, len(data), chunk) for f in decoder.feed(data[i : i + chunk])]
        got = [{"type": f.msg_type.name, "seq": f.seq, "frame_hex": f.raw.hex()} for f in frames]
        assert got == vec["expected_frames"]
        assert decoder.counters() == vec["expected_counters"]


def test_vector_file_is_what_the_codec_builds() -> None:
    assert (PROTOCOL_DIR / "test_vectors.json").read_text() == specgen.vectors_json()


# --- the specification text ------------------------------------------------------------------


def test_spec_contains_every_layout_table() -> None:
    for mtype in p.MsgType:
        assert specgen.layout_table_markdown(mtype) in SPEC, mtype.name


def test_spec_contains_schema_text_and_hash() -> None:
    assert p.schema_text().strip() in SPEC
    assert f"0x{p.SCHEMA_HASH:08X}" in SPEC


def test_spec_inline_hex_is_in_vectors() -> None:
    inline = re.findall(r"^frame_hex: ([0-9a-f]+)$", SPEC, flags=re.M)
    assert len(inline) >= 3
    known = {v["frame_hex"] for v in VECTORS["messages"]} | {v["frame_hex"] for v in VECTORS["rejects"]}
    known |= {v["hex"] for v in VECTORS["streams"]}
    for h in inline:
        assert h in known


# --- round trips -----------------------------------------------------------------------------


def _random_messages(rng: np.random.Generator, n: int, m: int) -> list:
    drive, sense = p.default_channel_map(n, m)
    g4 = (2, 2, n, m)
    return [
        p.Hello((rng.integers(256), rng.integers(256), rng.integers(65536)), "SN-" + str(rng.integers(1e9)),
                12000, 10000, 200, 180, 10000, 500000, 25,
                rng.integers(0, 2**32, g4, dtype=np.uint32), rng.integers(0, 2**32, g4, dtype=np.uint32),
                drive, sense),
        p.Scan(int(rng.integers(2**32)), int(rng.integers(2**63)), 5000,
               rng.integers(0, 2**32, g4, dtype=np.uint32), int(rng.integers(65536))),
        p.Status(int(rng.integers(2**63)), 0x1FF, 10, 2, 3, 3300, -1234, 2,
                 rng.random(g4) < 0.3, rng.random(g4) < 0.3, 100),
        p.Ack(65535, 0x14, bytes(rng.integers(0, 256, 255, dtype=np.uint8))),
        p.Nak(0, 0x99, 1, 0),
        p.Start(1), p.Stop(2), p.SetScanRate(3, 2**32 - 1), p.QueryInfo(4),
        p.Ping(5, b""), p.Ping(6, bytes(range(255))), p.Reset(7),
    ]


@pytest.mark.parametrize("n,m", [(2, 2), (5, 5), (3, 7), (32, 32), (32, 2)])
def test_round_trip_every_message(n: int, m: int) -> None:
    rng = np.random.default_rng(n * 100 + m)
    for seq, msg in enumerate(_random_messages(rng, n, m)):
        frame = p.encode_frame(msg, seq * 5000)
        assert frame.endswith(b"\x00") and frame.count(0) == 1
        back = p.decode_frame(frame)
        assert back.msg == msg and back.seq == seq * 5000 and back.msg_type is msg.TYPE


def test_scan_resistances_zero_copy_and_ohms() -> None:
    res = np.full((2, 2, 5, 5), 6_550_000, np.uint32)
    res[0, 0, 0, 0] = p.RES_OPEN
    res[1, 1, 4, 4] = p.RES_SATURATED
    frame = p.decode_frame(p.encode_frame(p.Scan(1, 2, 3, res), 0))
    arr = frame.msg.resistance_uohm
    assert arr.dtype == np.dtype("<u4") and arr.shape == (2, 2, 5, 5)
    assert not arr.flags.owndata and not arr.flags.writeable  # a view into the decoded frame
    ohm = frame.msg.resistances_ohm()
    assert np.isnan(ohm[0, 0, 0, 0]) and np.isnan(ohm[1, 1, 4, 4])
    assert np.count_nonzero(np.isnan(ohm)) == 2
    assert ohm[0, 1, 2, 3] == pytest.approx(6.55)
    assert frame.msg.open_mask().sum() == 1 and frame.msg.saturated_mask()[1, 1, 4, 4]


def test_scan_array_order_is_layer_direction_row_column() -> None:
    res = np.zeros((2, 2, 2, 3), np.uint32)
    res[1, 0, 1, 2] = 0xAABBCCDD  # lower layer, row-direction gauge, row 1, column 2
    payload = p.Scan(0, 0, 0, res).pack_payload()
    flat = 1 * (2 * 2 * 3) + 0 * (2 * 3) + 1 * 3 + 2
    assert payload[20 + 4 * flat : 24 + 4 * flat] == bytes.fromhex("ddccbbaa")


def test_extended_payload_flag_allows_trailing_fields() -> None:
    payload = p.Start(9).pack_payload() + b"\x01\x02"
    with pytest.raises(p.LengthError, match="START payload is 4 bytes"):
        p.decode_frame(encode_body(p.MsgType.START, 0, payload))
    frame = p.decode_frame(encode_body(p.MsgType.START, 0, payload, compat_flags=p.COMPAT_EXTENDED_PAYLOAD))
    assert frame.msg == p.Start(9) and frame.compat_flags == 1


def test_ack_applied_scan_rate() -> None:
    ack = p.decode_frame(bytes.fromhex(next(v for v in VECTORS["messages"] if v["name"] == "ack_set_scan_rate")["frame_hex"])).msg
    assert ack.applied_scan_rate_mhz == 25000
    with pytest.raises(p.FieldError):
        _ = p.Ack(1, p.MsgType.START).applied_scan_rate_mhz


def test_tdm_map_and_sample_times() -> None:
    for n, m in [(5, 5), (3, 8), (8, 3)]:
        drive, sense = p.default_channel_map(n, m)
        steps = p.tdm_steps(n, m)
        assert sorted(np.unique(drive)) == list(range(steps))
        # every step reads max(N, M) units on distinct sense channels, 2·(N+M) channels in all
        for s in range(steps):
            chans = sense[:, drive == s]
            assert chans.size == 2 * max(n, m) and len(np.unique(chans)) == chans.size
        assert set(np.unique(sense)) | set(range(steps)) == set(range(2 * (n + m)))
    t = p.unit_sample_times_us(1000, p.step_period_ns(10000, 5, 5), p.default_channel_map(5, 5)[0])
    assert t.min() == 1000 and t.max() == pytest.approx(1000 + 9 * 10_000)  # 10 Hz, 10 steps of 10 ms


# --- limits and bad input --------------------------------------------------------------------


@pytest.mark.parametrize("n,m", [(1, 5), (5, 1), (33, 5), (5, 33)])
def test_scan_dimension_limits(n: int, m: int) -> None:
    with pytest.raises(p.FieldError, match=f"N={n}, M={m}"):
        p.encode_frame(p.Scan(0, 0, 0, np.zeros((2, 2, n, m), np.uint32)), 0)


def test_encode_bad_input_errors() -> None:
    g = np.zeros((2, 2, 3, 3), np.uint32)
    with pytest.raises(p.FieldError, match="shape"):
        p.encode_frame(p.Scan(0, 0, 0, np.zeros((2, 3, 3), np.uint32)), 0)
    with pytest.raises(p.FieldError, match="sample_index"):
        p.encode_frame(p.Scan(-1, 0, 0, g), 0)
    with pytest.raises(p.FieldError, match="values must lie"):
        p.encode_frame(p.Scan(0, 0, 0, g.astype(np.int64) - 1), 0)
    with pytest.raises(p.FieldError, match="integer array"):
        p.encode_frame(p.Scan(0, 0, 0, g.astype(float)), 0)
    with pytest.raises(ValueError, match="seq"):
        p.encode_frame(p.Start(1), 65536)
    with pytest.raises(p.FieldError, match="request_id"):
        p.encode_frame(p.Start(70000), 0)
    with pytest.raises(p.FieldError, match="PING echo"):
        p.encode_frame(p.Ping(1, bytes(256)), 0)
    with pytest.raises(p.FieldError, match="not a protocol message"):
        p.encode_frame("START", 0)  # type: ignore[arg-type]
    with pytest.raises(p.FieldError, match="buffer_fill_pct"):
        p.encode_frame(p.Status(0, 0, 0, 0, 0, 0, 0, 0, g.astype(bool), g.astype(bool), 101), 0)


def test_hello_bad_input_errors() -> None:
    hello = specgen.example_messages()[0][2]
    for field, value, match in [
        ("serial_number", "x" * 17, "serial_number"),
        ("serial_number", "Grüße", "ASCII"),
        ("fw_version", (1, 2), "fw_version"),
        ("drive_line", np.full((2, 2, 3), 4, np.uint8), "drive_line values"),
        ("sense_channel", np.full((2, 2, 2, 3), 10, np.uint8), "sense_channel values"),
        ("base_resistance_uohm", np.zeros((2, 2, 3, 2), np.uint32), "base_resistance_uohm has shape"),
    ]:
        bad = specgen.message_from_fields("HELLO", specgen.message_to_fields(hello))
        setattr(bad, field, value)
        with pytest.raises(p.FieldError, match=match):
            p.encode_frame(bad, 0)


def _frame(msg_type: int, payload: bytes, **kw) -> bytes:
    return encode_body(msg_type, 0, payload, **kw)


def test_decode_bad_input_errors() -> None:
    scan = p.Scan(0, 0, 0, np.zeros((2, 2, 4, 4), np.uint32)).pack_payload()
    with pytest.raises(p.LengthError, match="SCAN payload is 275 bytes, its layout needs exactly 276"):
        p.decode_frame(_frame(p.MsgType.SCAN, scan[:-1]))
    bad = bytearray(scan)
    bad[16] = 40
    with pytest.raises(p.FieldError, match="N=40"):
        p.decode_frame(_frame(p.MsgType.SCAN, bytes(bad)))
    with pytest.raises(p.LengthError, match="fixed part"):
        p.decode_frame(_frame(p.MsgType.STATUS, bytes(10)))
    with pytest.raises(p.LengthError, match="shorter than the minimum"):
        p.decode_frame(b"\x03\x01\x02")
    with pytest.raises(p.CobsError):
        p.decode_frame(b"\x05\x01\x02" + bytes(12))  # embedded zeros are never valid COBS
    with pytest.raises(p.LengthError, match="implies"):
        raw = HEADER.pack(1, 0, 0, 0x10, 0, 5) + b"\x01\x00" + bytes(4)
        p.decode_frame(cobs.encode(raw))
    with pytest.raises(p.LengthError, match="exceeds the maximum"):
        p.decode_frame(b"\x01" * (p.MAX_ENCODED_BODY + 1))
    with pytest.raises(p.LengthError, match="MAX_PAYLOAD"):
        encode_body(p.MsgType.ACK, 0, bytes(p.MAX_PAYLOAD + 1))
    hello = bytearray(specgen.example_messages()[0][2].pack_payload())
    hello[8:10] = b"\xff\xfe"  # non-ASCII serial number
    with pytest.raises(p.FieldError, match="serial_number is not ASCII"):
        p.decode_frame(_frame(p.MsgType.HELLO, bytes(hello)))


def test_max_sizes_fit_the_limits() -> None:
    assert p.Hello.payload_size(32, 32) <= p.MAX_PAYLOAD
    assert p.Scan.payload_size(32, 32) <= p.MAX_PAYLOAD
    assert p.Status.payload_size(32, 32) <= p.MAX_PAYLOAD
    assert MAX_RAW_FRAME + MAX_RAW_FRAME // 254 + 1 == p.MAX_ENCODED_BODY
    # the largest message really encodes within MAX_ENCODED_BODY
    rng = np.random.default_rng(3)
    hello = _random_messages(rng, 32, 32)[0]
    assert len(p.encode_frame(hello, 0)) - 1 <= p.MAX_ENCODED_BODY


def test_hello_compatibility_rules() -> None:
    hello = specgen.example_messages()[0][2]
    assert p.hello_compatibility(hello) == p.Compatibility(True, "")
    for major, minor, schema, usable, words in [
        (2, 0, p.SCHEMA_HASH, False, "major versions differ"),
        (1, p.PROTOCOL_MINOR, p.SCHEMA_HASH ^ 1, False, "schema hashes differ"),
        (1, p.PROTOCOL_MINOR + 1, 0x12345678, True, "newer"),
    ]:
        hello.protocol_major, hello.protocol_minor, hello.schema_hash = major, minor, schema
        verdict = p.hello_compatibility(hello)
        assert verdict.usable is usable and words in verdict.note
