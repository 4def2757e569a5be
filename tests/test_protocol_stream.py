"""StreamDecoder robustness: garbage, truncation, bit flips, chunking (property tests)."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skinmap import protocol as p
from cobs import cobs

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _frames(count: int, seed: int) -> list[bytes]:
    """`count` distinct device frames (scans of random sizes, statuses, acks)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        n, m = (int(x) for x in rng.integers(2, 6, 2))
        kind = k % 3
        if kind == 0:
            msg = p.Scan(k, 1000 * k, 5000, rng.integers(6_000_000, 7_000_000, (2, 2, n, m), dtype=np.uint32))
        elif kind == 1:
            g = rng.random((2, 2, n, m)) < 0.1
            msg = p.Status(1000 * k, 0, k, 0, 0, 3300, 2500, 1, g, ~g)
        else:
            msg = p.Ack(k, int(p.MsgType.PING), rng.bytes(int(rng.integers(0, 20))))
        out.append(p.encode_frame(msg, k))
    return out


def _feed_in_chunks(decoder: p.StreamDecoder, data: bytes, sizes: list[int]) -> list[p.Frame]:
    frames, pos, i = [], 0, 0
    while pos < len(data):
        size = sizes[i % len(sizes)] if sizes else len(data)
        frames += decoder.feed(data[pos : pos + size])
        pos += size
        i += 1
    return frames


def _crc_ok(raw: bytes) -> bool:
    decoded = cobs.decode(raw[:-1])
    return p.crc32(decoded[:-4]) == int.from_bytes(decoded[-4:], "little")


chunk_sizes = st.lists(st.integers(1, 600), min_size=0, max_size=5)


@SETTINGS
@given(garbage=st.binary(max_size=1500), count=st.integers(1, 6), seed=st.integers(0, 2**16),
       sizes=chunk_sizes)
def test_garbage_prefix_then_every_frame_recovered(garbage: bytes, count: int, seed: int, sizes: list[int]) -> None:
    sent = _frames(count, seed)
    decoder = p.StreamDecoder()
    got = _feed_in_chunks(decoder, garbage + b"".join(sent), sizes)
    # with or without a delimiter at the end of the garbage, every frame after it is recovered
    assert [f.raw for f in got] == sent
    assert decoder.frames_ok == count
    assert decoder.bytes_in == len(garbage) + sum(map(len, sent))
    assert decoder.garbage_bytes <= len(garbage)


@SETTINGS
@given(count=st.integers(2, 8), seed=st.integers(0, 2**16),
       flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 7)), min_size=1, max_size=6),
       sizes=chunk_sizes)
def test_bit_flips_never_yield_bad_frames_and_spare_intact_ones(count: int, seed: int, flips: list, sizes: list[int]) -> None:
    sent = _frames(count, seed)
    data = bytearray(b"".join(sent))
    spans, pos = [], 0
    for f in sent:
        spans.append((pos, pos + len(f)))  # the frame with its own delimiter
        pos += len(f)
    hit = set()
    for where, bit in flips:
        k = int(where * len(data))
        data[k] ^= 1 << bit
        hit.add(k)
    intact = [f for f, (a, b) in zip(sent, spans) if not any(a <= k < b for k in hit)]
    decoder = p.StreamDecoder()
    got = _feed_in_chunks(decoder, bytes(data), sizes)  # must not raise
    raws = [f.raw for f in got]
    assert all(_crc_ok(r) for r in raws)
    assert all(r in sent for r in raws)  # a corrupted frame is never passed on
    assert [r for r in raws if r in intact] == intact  # every untouched frame, in order


@SETTINGS
@given(count=st.integers(2, 6), seed=st.integers(0, 2**16), cut=st.floats(0.05, 0.95),
       which=st.integers(0, 5), resync_delimiter=st.booleans())
def test_truncated_frame_costs_only_itself(count: int, seed: int, cut: float, which: int, resync_delimiter: bool) -> None:
    sent = _frames(count, seed)
    which %= count - 1  # never the last one
    truncated = sent[which][: max(1, int(cut * (len(sent[which]) - 1)))]
    # a device that resets mid-frame; after reboot it may or may not send a leading 0x00
    rest = (b"\x00" if resync_delimiter else b"") + b"".join(sent[which + 1 :])
    data = b"".join(sent[:which]) + truncated + rest
    decoder = p.StreamDecoder()
    got = [f.raw for f in decoder.feed(data)]
    assert got == sent[:which] + sent[which + 1 :]


@SETTINGS
@given(data=st.binary(max_size=3000), sizes=chunk_sizes)
def test_random_bytes_never_raise_and_chunking_does_not_matter(data: bytes, sizes: list[int]) -> None:
    whole = p.StreamDecoder()
    a = whole.feed(data)
    split = p.StreamDecoder()
    b = _feed_in_chunks(split, data, sizes)
    assert [f.raw for f in a] == [f.raw for f in b]
    assert whole.counters() == split.counters()
    assert all(_crc_ok(f.raw) for f in a)


def test_oversize_body_is_dropped_without_buffering_it() -> None:
    frame = _frames(1, 1)[0]
    decoder = p.StreamDecoder()
    junk = b"\x01" * (3 * p.MAX_ENCODED_BODY)
    for i in range(0, len(junk), 4096):
        assert decoder.feed(junk[i : i + 4096]) == []
        assert decoder.buffered_bytes <= p.MAX_ENCODED_BODY
    got = decoder.feed(b"\x00" + frame)
    assert [f.raw for f in got] == [frame]
    assert decoder.oversize_frames == 1
    assert decoder.garbage_bytes == len(junk)


def test_counters_and_sequence_gaps() -> None:
    sent = _frames(5, 7)
    decoder = p.StreamDecoder()
    decoder.feed(sent[0] + sent[1] + sent[4])  # frames with seq 2 and 3 never arrive
    assert decoder.seq_gaps == 1 and decoder.seq_lost == 2
    assert decoder.feed(b"\x00\x00\x00") == []  # idle delimiters are not errors
    assert decoder.counters()["length_errors"] == 0
    decoder.feed(b"\x02\x01\x00")
    assert decoder.length_errors == 1 and "shorter" in decoder.last_error
    assert decoder.frames_ok == 3


def test_a_rebooted_sender_is_not_counted_as_sequence_loss():
    from skinmap.protocol import Hello, Status, StreamDecoder, encode_frame
    from skinmap.protocol.specgen import example_messages

    msgs = {type(m): m for _name, _seq, m in example_messages()}
    dec = StreamDecoder()
    stream = b"".join(encode_frame(msgs[Status], s) for s in (100, 101, 103))  # one frame lost
    stream += encode_frame(msgs[Hello], 0) + encode_frame(msgs[Status], 1)  # reboot: counter restarts
    frames = dec.feed(stream)
    assert len(frames) == 5
    assert dec.seq_gaps == 1 and dec.seq_lost == 1


def test_every_counter_is_declared_on_the_decoder_and_reported():
    from skinmap.protocol.stream import COUNTERS

    declared = [name for name, kind in p.StreamDecoder.__annotations__.items() if kind == "int"]
    assert declared == list(COUNTERS)
    assert list(p.StreamDecoder().counters()) == list(COUNTERS)
