"""Decode rate of the scanner protocol: scans/s through StreamDecoder.feed in 4 KiB reads.

Run: .venv/bin/python bench/decode_rate.py [--seconds S] [--chunk BYTES]
Prints, for 5×5 and 32×32 arrays, bytes per scan on the wire, the decode rate, the encode
rate, and what the rate means against 1,000 scans/s on one core.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from skinmap.protocol import Scan, StreamDecoder, encode_frame


def make_stream(n: int, m: int, scans: int, seed: int = 0) -> tuple[bytes, int]:
    """`scans` SCAN frames of realistic resistances (≈6.55 Ω, 1 µΩ LSB) back to back."""
    rng = np.random.default_rng(seed)
    base = rng.normal(6_550_000, 720_000, (2, 2, n, m))
    frames = []
    for k in range(scans):
        res = (base * (1 + rng.normal(0, 0.003, base.shape))).astype(np.uint32)
        frames.append(encode_frame(Scan(k, 100_000 * k, 5_000_000 // min(n, m), res), k & 0xFFFF))
    return b"".join(frames), len(frames[0])


def decode_rate(data: bytes, scans: int, chunk: int, seconds: float) -> float:
    """Scans per second decoded through StreamDecoder.feed, best of repeated passes."""
    best = 0.0
    deadline = time.perf_counter() + seconds
    while True:
        decoder = StreamDecoder()
        t0 = time.perf_counter()
        got = 0
        for i in range(0, len(data), chunk):
            got += len(decoder.feed(data[i : i + chunk]))
        dt = time.perf_counter() - t0
        if got != scans or decoder.frames_ok != scans:
            raise RuntimeError(f"decoded {got} of {scans} scans: {decoder.counters()}")
        best = max(best, scans / dt)
        if time.perf_counter() > deadline:
            return best


def encode_rate(n: int, m: int, seconds: float) -> float:
    res = np.full((2, 2, n, m), 6_550_000, np.uint32)
    count, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(100):
            encode_frame(Scan(count, count, 1000, res), count & 0xFFFF)
            count += 1
    return count / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.0, help="measuring time per case (s)")
    ap.add_argument("--chunk", type=int, default=4096, help="bytes per feed() call")
    args = ap.parse_args()
    print(f"StreamDecoder.feed in {args.chunk}-byte reads, one core, best pass of ~{args.seconds:g} s")
    print(f"{'array':>7} {'bytes/scan':>10} {'decode scans/s':>15} {'MB/s':>7} {'x 1000/s':>9} {'encode scans/s':>15}")
    for n, m, scans in ((5, 5, 4000), (32, 32, 1000)):
        data, frame_len = make_stream(n, m, scans)
        rate = decode_rate(data, scans, args.chunk, args.seconds)
        enc = encode_rate(n, m, args.seconds / 2)
        print(f"{n:>3}x{m:<3} {frame_len:>10} {rate:>15,.0f} {rate * frame_len / 1e6:>7.1f} "
              f"{rate / 1000:>9.1f} {enc:>15,.0f}")


if __name__ == "__main__":
    main()
