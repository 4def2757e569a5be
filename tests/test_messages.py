"""Round trips and error cases of the skinmapd message layouts."""

import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from skinmap.wire import messages as msg


def _elements(k=5, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(k, 3)) * 0.01
    nrm = rng.normal(size=(k, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    unc = rng.uniform(1e-5, 1e-3, size=k)
    flags = rng.integers(0, 16, size=k).astype(np.uint8)
    return pos, nrm, unc, flags


def test_elements_round_trip_is_exact_and_zero_copy():
    pos, nrm, unc, flags = _elements(7)
    scatter = 0.5 * unc
    buf = msg.encode_elements(42, 123_456_789, 1_700_000_000_123_456_789, pos, nrm, unc, flags, scatter)
    assert len(buf) == msg.HEADER_SIZE + 8 + 65 * 7
    out = msg.decode_elements(buf)
    assert (out.seq, out.device_time_us, out.host_time_ns) == (42, 123_456_789,
                                                               1_700_000_000_123_456_789)
    np.testing.assert_array_equal(out.positions, pos)
    np.testing.assert_array_equal(out.normals, nrm)
    np.testing.assert_array_equal(out.uncertainty, unc)
    np.testing.assert_array_equal(out.scatter, scatter)
    np.testing.assert_array_equal(out.flags, flags)
    assert out.count == 7
    np.testing.assert_array_equal(out.valid, (flags & 1) != 0)
    # views into the buffer, not copies; the buffer is immutable so are the arrays
    assert not out.positions.flags.owndata and not out.positions.flags.writeable
    assert msg.decode(buf).seq == 42


def test_elements_header_layout_is_as_documented():
    pos, nrm, unc, flags = _elements(2)
    buf = msg.encode_elements(7, 8, 9, pos, nrm, unc, flags)
    magic, ver, kind, _r, seq, length, dev, host = struct.unpack_from("<4sBBHIIQQ", buf)
    assert (magic, ver, kind, seq, length, dev, host) == (b"SKMP", 2, 1, 7, len(buf), 8, 9)
    assert struct.unpack_from("<I", buf, 32)[0] == 2
    assert np.frombuffer(buf, "<f8", 3, 40).tolist() == pos[0].tolist()
    # without a scatter given, the whole uncertainty stands for it (never less than it is)
    assert np.frombuffer(buf, "<f8", 2, 40 + 96 + 16).tolist() == unc.tolist()
    assert buf[-2:] == flags.tobytes()


def _layout_1(buf: bytes, cut: tuple[int, int]) -> bytes:
    """A layout-2 message as layout 1 wrote it: the scatter block (bytes ``cut``) removed."""
    old = bytearray(buf[:cut[0]] + buf[cut[1]:])
    old[4] = 1
    struct.pack_into("<I", old, 12, len(old))
    return bytes(old)


def test_layout_1_messages_of_earlier_logs_still_decode_without_scatter():
    pos, nrm, unc, flags = _elements(3)
    k = 3
    start = msg.HEADER_SIZE + 8 + 56 * k
    old = _layout_1(msg.encode_elements(5, 6, 7, pos, nrm, unc, flags, unc / 2), (start, start + 8 * k))
    assert len(old) == msg.HEADER_SIZE + 8 + 57 * k
    out = msg.decode_elements(old)
    assert out.scatter is None
    np.testing.assert_array_equal(out.uncertainty, unc)
    np.testing.assert_array_equal(out.flags, flags)
    nodes, unc_n = np.zeros((2, 3, 3)), np.full((2, 3), 1e-4)
    buf = msg.encode_surface(1, 2, 3, nodes, nodes + [0.0, 0.0, 1.0], unc_n, np.ones((4, 3)), scatter=unc_n / 3)
    start = msg.HEADER_SIZE + 16 + 56 * 6
    surf = msg.decode_surface(_layout_1(buf, (start, start + 8 * 6)))
    assert surf.scatter is None and surf.cloud.shape == (4, 3)
    np.testing.assert_array_equal(surf.uncertainty, unc_n)
    np.testing.assert_array_equal(msg.decode_surface(buf).scatter, unc_n / 3)


def test_empty_element_set_round_trips():
    z = np.zeros((0, 3))
    out = msg.decode_elements(msg.encode_elements(0, 0, 0, z, z, np.zeros(0), np.zeros(0, int)))
    assert out.positions.shape == (0, 3) and out.flags.shape == (0,)


@settings(max_examples=40, deadline=None)
@given(k=st.integers(0, 50), seq=st.integers(0, 2**32 - 1), t=st.integers(0, 2**64 - 1))
def test_elements_round_trip_property(k, seq, t):
    pos, nrm, unc, flags = _elements(k, seed=k)
    out = msg.decode_elements(msg.encode_elements(seq, t, t, pos, nrm, unc, flags))
    assert out.seq == seq and out.device_time_us == t and out.host_time_ns == t
    np.testing.assert_array_equal(out.positions, pos)


def test_elements_encode_rejects_bad_input():
    pos, nrm, unc, flags = _elements(4)
    with pytest.raises(ValueError, match="positions"):
        msg.encode_elements(0, 0, 0, pos[:, :2], nrm, unc, flags)
    with pytest.raises(ValueError, match="normals"):
        msg.encode_elements(0, 0, 0, pos, nrm[:3], unc, flags)
    with pytest.raises(ValueError, match="uncertainty"):
        msg.encode_elements(0, 0, 0, pos, nrm, unc[:, None], flags)
    with pytest.raises(ValueError, match="flags"):
        msg.encode_elements(0, 0, 0, pos, nrm, unc, np.full(4, 300))
    with pytest.raises(ValueError, match="seq"):
        msg.encode_elements(2**32, 0, 0, pos, nrm, unc, flags)
    with pytest.raises(ValueError, match="device_time_us"):
        msg.encode_elements(0, -1, 0, pos, nrm, unc, flags)
    with pytest.raises(TypeError, match="host_time_ns"):
        msg.encode_elements(0, 0, 1.5, pos, nrm, unc, flags)
    with pytest.raises(TypeError, match="positions"):
        msg.encode_elements(0, 0, 0, np.full((4, 3), "a"), nrm, unc, flags)


@pytest.mark.parametrize("cut", [0, 10, 31, 32, 39, 40, 100])
def test_elements_decode_rejects_truncation(cut):
    pos, nrm, unc, flags = _elements(4)
    buf = msg.encode_elements(1, 2, 3, pos, nrm, unc, flags)
    with pytest.raises(msg.MessageError, match="truncated"):
        msg.decode_elements(buf[:cut])


def test_decode_rejects_bad_headers():
    pos, nrm, unc, flags = _elements(3)
    buf = bytearray(msg.encode_elements(1, 2, 3, pos, nrm, unc, flags))
    bad = bytearray(buf); bad[0:4] = b"XXXX"
    with pytest.raises(msg.MessageError, match="magic"):
        msg.decode_elements(bad)
    bad = bytearray(buf); bad[4] = 99
    with pytest.raises(msg.MessageError, match="version 99 .this decoder reads 1, 2"):
        msg.decode_elements(bad)
    bad = bytearray(buf); bad[4] = 1  # layout 1 of the same length: its counts imply fewer bytes
    with pytest.raises(msg.MessageError, match="counts imply"):
        msg.decode_elements(bad)
    bad = bytearray(buf); bad[5] = 77
    with pytest.raises(msg.MessageError, match="kind 77"):
        msg.decode(bad)
    with pytest.raises(msg.MessageError, match="oversized"):
        msg.decode_elements(bytes(buf) + b"\0")
    # count field disagreeing with the length
    bad = bytearray(buf); struct.pack_into("<I", bad, 32, 4)
    with pytest.raises(msg.MessageError, match="counts imply"):
        msg.decode_elements(bad)
    with pytest.raises(msg.MessageError, match="expected a surface"):
        msg.decode_surface(buf)
    with pytest.raises(TypeError, match="bytes-like"):
        msg.decode_elements(12345)


def test_surface_round_trip_float32_and_float64_cloud():
    rng = np.random.default_rng(1)
    nodes = rng.normal(size=(3, 4, 3))
    normals = rng.normal(size=(3, 4, 3))
    unc = rng.uniform(size=(3, 4))
    cloud = rng.normal(size=(50, 3))
    buf = msg.encode_surface(5, 6, 7, nodes, normals, unc, cloud)
    out = msg.decode_surface(buf)
    assert out.shape == (3, 4) and out.cloud.dtype == np.float32
    np.testing.assert_array_equal(out.nodes, nodes)
    np.testing.assert_array_equal(out.normals, normals)
    np.testing.assert_array_equal(out.uncertainty, unc)
    np.testing.assert_array_equal(out.cloud, cloud.astype(np.float32))
    out64 = msg.decode_surface(msg.encode_surface(5, 6, 7, nodes, normals, unc, cloud,
                                                  cloud_dtype="float64"))
    np.testing.assert_array_equal(out64.cloud, cloud)
    no_cloud = msg.decode_surface(msg.encode_surface(5, 6, 7, nodes, normals, unc))
    assert no_cloud.cloud.shape == (0, 3)
    assert isinstance(msg.decode(buf), msg.SurfaceMessage)


def test_surface_errors():
    nodes = np.zeros((2, 2, 3))
    with pytest.raises(ValueError, match="nodes"):
        msg.encode_surface(0, 0, 0, np.zeros((2, 2)), nodes, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="uncertainty"):
        msg.encode_surface(0, 0, 0, nodes, nodes, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="cloud_dtype"):
        msg.encode_surface(0, 0, 0, nodes, nodes, np.zeros((2, 2)), cloud_dtype="float16")
    with pytest.raises(ValueError, match="cloud"):
        msg.encode_surface(0, 0, 0, nodes, nodes, np.zeros((2, 2)), np.zeros((4, 2)))
    buf = bytearray(msg.encode_surface(0, 0, 0, nodes, nodes, np.zeros((2, 2))))
    buf[44] = 2
    with pytest.raises(msg.MessageError, match="4 or 8"):
        msg.decode_surface(buf)
    with pytest.raises(msg.MessageError, match="truncated"):
        msg.decode_surface(bytes(buf)[:40])


def test_strains_round_trip_and_flags():
    rng = np.random.default_rng(2)
    up = rng.normal(size=(2, 3, 5)) * 1e-3
    lo = rng.normal(size=(2, 3, 5)) * 1e-3
    fl = rng.integers(0, 4, size=(2, 3, 5))
    out = msg.decode_strains(msg.encode_strains(9, 10, 11, up, lo, fl))
    np.testing.assert_array_equal(out.eps_upper, up)
    np.testing.assert_array_equal(out.eps_lower, lo)
    np.testing.assert_array_equal(out.gauge_flags, fl)
    np.testing.assert_array_equal(out.valid_upper, (fl & 1) != 0)
    np.testing.assert_array_equal(out.valid_lower, (fl & 2) != 0)
    with pytest.raises(ValueError, match="eps_upper"):
        msg.encode_strains(0, 0, 0, up[0], lo, fl)
    with pytest.raises(ValueError, match="eps_lower"):
        msg.encode_strains(0, 0, 0, up, lo[:, :2], fl)
    with pytest.raises(ValueError, match="gauge_flags"):
        msg.encode_strains(0, 0, 0, up, lo, fl[:1])
    with pytest.raises(msg.MessageError, match="truncated"):
        msg.decode_strains(msg.encode_strains(0, 0, 0, up, lo, fl)[:-1])


def _status():
    return {"device": "skin0", "host_time_ns": 1, "connected": True, "seq": 3,
            "scan_rate_hz": 20.0, "publish_rate_hz": 19.5, "frames_dropped": 0, "crc_errors": 2,
            "reconnects": 0, "solver_time_ms": 12.5, "log_state": "recording", "extra": [1]}


def _info():
    return {"device": "skin0", "rows": 8, "cols": 8, "pitch_m": 0.012,
            "elements": {"count": 64, "width_m": 0.002, "height_m": 0.01},
            "calibration": {"gauge_factor": [1.24] * 4}, "versions": {"skinmap": "0.1.0"}}


def test_status_and_info_json_round_trip():
    s = msg.decode_status(msg.encode_status(_status()))
    assert s["schema"] == msg.STATUS_SCHEMA and s["crc_errors"] == 2 and s["extra"] == [1]
    i = msg.decode_info(msg.encode_info(_info()))
    assert i["schema"] == msg.INFO_SCHEMA and i["elements"]["count"] == 64


def test_status_and_info_errors():
    bad = _status(); del bad["crc_errors"]
    with pytest.raises(ValueError, match="crc_errors"):
        msg.encode_status(bad)
    bad = _status(); bad["connected"] = "yes"
    with pytest.raises(ValueError, match="connected"):
        msg.encode_status(bad)
    bad = _status(); bad["frames_dropped"] = True
    with pytest.raises(ValueError, match="frames_dropped"):
        msg.encode_status(bad)
    bad = _status(); bad["solver_time_ms"] = float("nan")
    with pytest.raises(ValueError, match="JSON"):
        msg.encode_status(bad)
    with pytest.raises(TypeError, match="mapping"):
        msg.encode_info([1, 2])
    with pytest.raises(msg.MessageError, match="UTF-8"):
        msg.decode_status(b"\xff\xfe")
    with pytest.raises(msg.MessageError, match="valid JSON"):
        msg.decode_info(b"{not json")
    with pytest.raises(msg.MessageError, match="JSON object"):
        msg.decode_info(b"[1]")
    with pytest.raises(msg.MessageError, match="schema"):
        msg.decode_info(msg.encode_status(_status()))
    body = json.loads(msg.encode_info(_info())); del body["rows"]
    with pytest.raises(msg.MessageError, match="rows"):
        msg.decode_info(json.dumps(body).encode())


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(0, 40 + 57 * 3 - 1))
def test_any_truncation_is_a_message_error(cut):
    pos, nrm, unc, flags = _elements(3)
    buf = msg.encode_elements(1, 2, 3, pos, nrm, unc, flags)
    with pytest.raises(msg.MessageError):
        msg.decode(buf[:cut])


def test_decoders_accept_any_bytes_like_and_zenoh_payloads():
    import zenoh

    pos, nrm, unc, flags = _elements(3)
    buf = msg.encode_elements(8, 2, 3, pos, nrm, unc, flags)
    for wrapped in (bytearray(buf), memoryview(buf), np.frombuffer(buf, np.uint8),
                    zenoh.ZBytes(buf)):
        out = msg.decode_elements(wrapped)
        assert out.seq == 8
        np.testing.assert_array_equal(out.normals, nrm)
    info = msg.encode_info({"device": "d", "rows": 1, "cols": 1, "pitch_m": 0.01,
                            "elements": {"count": 0}, "calibration": {}, "versions": {}})
    assert msg.decode_info(zenoh.ZBytes(info))["device"] == "d"


def test_replay_compares_a_layout_1_log_by_the_fields_it_has():
    """Replaying a log written before layout 2: its elements messages lack the scatter array, and
    are the same as the replayed ones where every field they have holds the same bytes."""
    from skinmap.daemon.replay import _older_layout_alike

    pos, nrm, unc, flags = _elements(3)
    k, start = 3, msg.HEADER_SIZE + 8 + 56 * 3
    new = msg.encode_elements(5, 6, 7, pos, nrm, unc, flags, unc / 2)
    old = _layout_1(new, (start, start + 8 * k))
    assert _older_layout_alike(old, new)
    moved = pos.copy()
    moved[1, 2] += 1e-9
    assert not _older_layout_alike(_layout_1(msg.encode_elements(5, 6, 7, moved, nrm, unc, flags), (start, start + 8 * k)),
                                   new)
    assert not _older_layout_alike(new, new)  # a layout-2 log is compared byte for byte
