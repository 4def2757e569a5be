"""Byte-level link faults: rates, determinism, and that the decoder resynchronises."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap import protocol as p
from skinmap.emulator.linkfaults import FaultyLink, LinkFaults


def _stream(k=200):
    return b"".join(p.encode_frame(p.Ping(i, bytes(40)), i) for i in range(k))


def test_no_faults_is_identity():
    link = FaultyLink(LinkFaults(), np.random.default_rng(0))
    data = _stream(10)
    assert link.apply(data, 0.0) == data and link.apply(data, 1.0) == data


def test_bit_flips_and_drops_happen_at_their_rates_and_are_seeded():
    data = _stream()
    faults = LinkFaults(bit_flip_rate=1e-3, drop_rate=1e-3)
    a = FaultyLink(faults, np.random.default_rng(1))
    out = a.apply(data, 0.0)
    n = len(data)
    assert abs(a.bits_flipped - n * 1e-3) < 5 * np.sqrt(n * 1e-3)
    assert abs(a.bytes_dropped - n * 1e-3) < 5 * np.sqrt(n * 1e-3)
    assert len(out) == n - a.bytes_dropped
    assert FaultyLink(faults, np.random.default_rng(1)).apply(data, 0.0) == out
    assert FaultyLink(faults, np.random.default_rng(2)).apply(data, 0.0) != out
    dec = p.StreamDecoder()
    frames = dec.feed(out)
    assert dec.crc_errors + dec.cobs_errors + dec.length_errors > 0
    assert len(frames) > 150  # each fault costs at most the frame it hits (and maybe its neighbour)


def test_garbage_bursts_follow_elapsed_time():
    link = FaultyLink(LinkFaults(garbage_rate_hz=10.0, garbage_max_len=8), np.random.default_rng(3))
    data = _stream(200)
    link.apply(data, 0.0)  # the first call starts the clock: no time elapsed, no garbage
    assert link.garbage_bursts == 0
    out = link.apply(data, 2.0)  # 2 s at 10/s: ~20 bursts
    assert 8 < link.garbage_bursts < 35
    assert len(out) == len(data) + link.garbage_bytes
    frames = p.StreamDecoder().feed(out)
    assert len(frames) >= 200 - 2 * link.garbage_bursts  # a burst costs at most two frames


@pytest.mark.parametrize("kw, words", [
    (dict(bit_flip_rate=1.5), "bit_flip_rate"),
    (dict(drop_rate=-0.1), "drop_rate"),
    (dict(garbage_rate_hz=-1.0), "garbage rate"),
    (dict(garbage_max_len=0), "burst length"),
])
def test_bad_fault_settings_are_named(kw, words):
    with pytest.raises(ValueError, match=words):
        LinkFaults(**kw)
