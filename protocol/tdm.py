"""Row-column time-division multiplexing (TDM): the default channel map and sample timing.

A scan takes 2·min(N, M) TDM steps. Each step energises one drive line, i.e. one
(direction, line) pair along the shorter array dimension, and reads the max(N, M) units on
that line through 2·max(N, M) sense channels at once (upper and lower gauge of a unit are
read simultaneously through the unit's diode pair). Drive lines plus sense channels make the
2·(N + M) DAQ channels: channels 0 .. 2·min−1 are drive lines, the rest sense channels.
"""

from __future__ import annotations

import numpy as np

from .payloads import MAX_DIM, MIN_DIM
from .errors import FieldError


def _check(n: int, m: int) -> None:
    if not (MIN_DIM <= n <= MAX_DIM and MIN_DIM <= m <= MAX_DIM):
        raise FieldError(f"N={n}, M={m} outside {MIN_DIM}..{MAX_DIM}")


def default_channel_map(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Default wiring: (drive_line uint8 (2, N, M), sense_channel uint8 (2, 2, N, M)).

    If N <= M, unit (d, i, j) is on drive line d·N + i and its layer-l gauge on sense
    channel 2·N + l·M + j; otherwise (columns are the shorter side) on drive line d·M + j and
    sense channel 2·M + l·N + i. The drive line number is also the TDM step index.
    """
    _check(n, m)
    d, i, j = np.meshgrid(np.arange(2), np.arange(n), np.arange(m), indexing="ij")
    if n <= m:
        drive = d * n + i
        sense = np.stack([2 * n + layer * m + j for layer in (0, 1)])
    else:
        drive = d * m + j
        sense = np.stack([2 * m + layer * n + i for layer in (0, 1)])
    return drive.astype(np.uint8), sense.astype(np.uint8)


def tdm_steps(n: int, m: int) -> int:
    """TDM steps per scan, 2·min(N, M)."""
    _check(n, m)
    return 2 * min(n, m)


def step_period_ns(scan_rate_mhz: int, n: int, m: int) -> int:
    """TDM step period in ns for a scan rate in mHz (F_scan = 2·min(N, M)·scan rate)."""
    if scan_rate_mhz <= 0:
        raise FieldError(f"scan_rate_mhz must be > 0, got {scan_rate_mhz}")
    return round(1e12 / (scan_rate_mhz * tdm_steps(n, m)))


def unit_sample_times_us(timestamp_us: int, step_period_ns: int, drive_line: np.ndarray) -> np.ndarray:
    """Sample time (µs, float64, shaped like drive_line) of every sensing unit of one scan."""
    return timestamp_us + np.asarray(drive_line, dtype=np.float64) * (step_period_ns * 1e-3)
