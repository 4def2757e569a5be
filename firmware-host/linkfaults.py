"""Byte-level faults of the link from the device to the host (pure, seeded).

Garbage bursts inserted at random places, single-bit flips and dropped bytes, each at a rate.
Stalls, disconnects and reboots are not byte faults: the device and the transports model them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LinkFaults", "FaultyLink"]


@dataclass(frozen=True)
class LinkFaults:
    garbage_rate_hz: float = 0.0  # garbage bursts per second
    garbage_max_len: int = 32  # a burst is 1..garbage_max_len random bytes (0x00 included)
    bit_flip_rate: float = 0.0  # probability per byte that one of its bits flips
    drop_rate: float = 0.0  # probability per byte that it is lost

    def __post_init__(self):
        if not (math.isfinite(self.garbage_rate_hz) and self.garbage_rate_hz >= 0):
            raise ValueError(f"garbage rate must be >= 0 bursts/s, got {self.garbage_rate_hz!r}")
        if int(self.garbage_max_len) < 1:
            raise ValueError(f"garbage burst length must be >= 1, got {self.garbage_max_len!r}")
        for name in ("bit_flip_rate", "drop_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} is a per-byte probability in [0, 1], got {v!r}")

    @property
    def active(self) -> bool:
        return bool(self.garbage_rate_hz or self.bit_flip_rate or self.drop_rate)


class FaultyLink:
    """Applies :class:`LinkFaults` to outgoing chunks; counts what it did."""

    def __init__(self, faults: LinkFaults, rng: np.random.Generator):
        self.faults = faults
        self.rng = rng
        self._last_t: float | None = None
        self.garbage_bursts = 0
        self.garbage_bytes = 0
        self.bits_flipped = 0
        self.bytes_dropped = 0

    def apply(self, data: bytes, now_s: float) -> bytes:
        f = self.faults
        dt = 0.0 if self._last_t is None else max(0.0, now_s - self._last_t)
        self._last_t = now_s
        if not f.active:
            return data
        buf = np.frombuffer(data, dtype=np.uint8).copy()
        if f.bit_flip_rate and buf.size:
            hit = np.flatnonzero(self.rng.random(buf.size) < f.bit_flip_rate)
            buf[hit] ^= (1 << self.rng.integers(0, 8, hit.size)).astype(np.uint8)
            self.bits_flipped += hit.size
        if f.drop_rate and buf.size:
            keep = self.rng.random(buf.size) >= f.drop_rate
            self.bytes_dropped += int(buf.size - keep.sum())
            buf = buf[keep]
        out = buf.tobytes()
        bursts = self.rng.poisson(f.garbage_rate_hz * dt) if f.garbage_rate_hz else 0
        for _ in range(bursts):
            n = int(self.rng.integers(1, int(f.garbage_max_len) + 1))
            junk = self.rng.integers(0, 256, n, dtype=np.uint8).tobytes()
            at = int(self.rng.integers(0, len(out) + 1))
            out = out[:at] + junk + out[at:]
            self.garbage_bursts += 1
            self.garbage_bytes += n
        return out

    def counters(self) -> dict[str, int]:
        return {
            "garbage_bursts": self.garbage_bursts,
            "garbage_bytes": self.garbage_bytes,
            "bits_flipped": self.bits_flipped,
            "bytes_dropped": self.bytes_dropped,
        }
