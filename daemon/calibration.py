"""Resistances → calibrated strains, and the flat-sheet tare.

The scanner reports each gauge's resistance; it also stores a factory calibration
(gauge factor GF and base resistance R0 per gauge) that it sends in HELLO. A tare of the flat,
unloaded sheet replaces R0 by the measured resting resistance, which removes the
channel-to-channel offsets and the slow drift that a factory R0 cannot know about.

    eps = (R / R0 − 1) / GF

Arrays are shaped (2 layers, 2 directions, N, M), layer 0 = upper, 1 = lower.
"""
from __future__ import annotations

import json
import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Calibration", "resistances_to_strains", "compute_tare", "save_tare", "load_tare", "tare_path"]

# A gauge whose strain reads beyond this is treated as faulty (the gauges are linear to 50 %).
MAX_PLAUSIBLE_STRAIN = 0.6


@dataclass(frozen=True)
class Calibration:
    gauge_factor: np.ndarray  # (2, 2, N, M)
    base_resistance: np.ndarray  # (2, 2, N, M) ohm
    source: str = "factory"  # "factory" or "tare <iso time>"

    def __post_init__(self) -> None:
        gf, r0 = self.gauge_factor, self.base_resistance
        if gf.shape != r0.shape or gf.ndim != 4 or gf.shape[:2] != (2, 2):
            raise ValueError(f"calibration arrays must both be (2, 2, N, M); got {gf.shape} and {r0.shape}")
        if not (np.all(np.isfinite(gf)) and np.all(gf > 0)):
            raise ValueError("calibration: every gauge factor must be finite and > 0")
        if not (np.all(np.isfinite(r0)) and np.all(r0 > 0)):
            raise ValueError("calibration: every base resistance must be finite and > 0 ohm")

    def with_tare(self, base_resistance: np.ndarray, source: str) -> "Calibration":
        tared = np.where(np.isfinite(base_resistance) & (base_resistance > 0), base_resistance, self.base_resistance)
        return Calibration(self.gauge_factor, tared, source)


def resistances_to_strains(
    resistance_ohm: np.ndarray, cal: Calibration
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Calibrated strains from resistances.

    Returns (eps_upper, eps_lower, valid): eps_* are (2, N, M) with NaN where a gauge is open,
    saturated or implausible; valid is the (2, 2, N, M) boolean mask of usable gauges.
    """
    r = np.asarray(resistance_ohm, dtype=np.float64)
    if r.shape != cal.gauge_factor.shape:
        raise ValueError(f"resistance array shape {r.shape} does not match calibration {cal.gauge_factor.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        eps = (r / cal.base_resistance - 1.0) / cal.gauge_factor
    valid = np.isfinite(eps) & (np.abs(eps) <= MAX_PLAUSIBLE_STRAIN)
    eps = np.where(valid, eps, np.nan)
    return eps[0], eps[1], valid


def compute_tare(resistance_scans: np.ndarray) -> np.ndarray:
    """Resting resistance per gauge: the median over scans (robust to glitches), NaN-aware."""
    scans = np.asarray(resistance_scans, dtype=np.float64)
    if scans.ndim != 5 or scans.shape[0] < 1:
        raise ValueError(f"tare needs scans shaped (K, 2, 2, N, M); got {scans.shape}")
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(scans, axis=0)


def tare_path(state_dir: Path, serial: str) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in serial) or "unknown"
    return Path(state_dir) / f"tare-{safe}.json"


def save_tare(state_dir: Path, serial: str, base_resistance: np.ndarray, n_scans: int) -> Path:
    """Write the tare atomically (temp file, fsync, rename) so a crash never leaves half a file."""
    path = tare_path(state_dir, serial)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "serial": serial,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "scans": int(n_scans),
        "shape": list(base_resistance.shape),
        "base_resistance_ohm": [None if not np.isfinite(x) else float(x) for x in base_resistance.ravel()],
    }
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(doc, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


#: A tare of the largest array (2 × 2 × 32 × 32 gauges) is about 80 kB; anything far larger is
#: not a tare, and reading it must not hold up the service.
MAX_TARE_BYTES = 4 * 1024 * 1024


def _read_tare_text(path: Path) -> str | None:
    """The tare file's text, or None if there is none. Never blocks: a FIFO or device at the
    path is refused (opened non-blocking, then only a regular file is read)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise ValueError(f"unreadable: {exc.strerror or exc}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"not a regular file ({_file_kind(st.st_mode)})")
        if st.st_size > MAX_TARE_BYTES:
            raise ValueError(f"{st.st_size} bytes, more than a tare can be ({MAX_TARE_BYTES})")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(MAX_TARE_BYTES + 1)
    except OSError as exc:
        raise ValueError(f"unreadable: {exc.strerror or exc}") from exc
    finally:
        os.close(fd)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"not UTF-8 text: {exc}") from exc


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def parse_tare(text: str, shape: tuple[int, ...]) -> tuple[np.ndarray, str]:
    """Base resistances shaped ``shape`` and the tare's source text, from a tare file's text;
    ValueError says what is wrong with it."""
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"not a JSON object but {_json_kind(doc)}")
    file_shape = doc.get("shape")
    if (not isinstance(file_shape, list) or not all(type(x) is int for x in file_shape)):
        raise ValueError(f"'shape' must be a list of integers, got {_json_kind(file_shape)}")
    if tuple(file_shape) != tuple(shape):
        raise ValueError(f"for an array shaped {file_shape}, the scanner is {list(shape)}")
    raw = doc.get("base_resistance_ohm")
    if not isinstance(raw, list):
        raise ValueError(f"'base_resistance_ohm' must be a list, got {_json_kind(raw)}")
    expected = int(np.prod(shape))
    if len(raw) != expected:
        raise ValueError(f"'base_resistance_ohm' has {len(raw)} values, the scanner has {expected} gauges")
    for i, x in enumerate(raw):
        # null is a gauge the tare could not measure; it keeps its factory value
        if x is not None and (type(x) not in (int, float)):
            raise ValueError(f"'base_resistance_ohm'[{i}] must be a number or null, got {_json_kind(x)}")
    values = np.array([np.nan if x is None else float(x) for x in raw], dtype=np.float64)
    created = doc.get("created", "?")
    return values.reshape(shape), f"tare {created if isinstance(created, str) else '?'}"


def _json_kind(value: object) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"the boolean {json.dumps(value)}"
    if isinstance(value, (int, float)):
        return f"the number {value!r}"
    if isinstance(value, str):
        return f"the string {value[:40]!r}"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    return "an object"


def load_tare(state_dir: Path, serial: str, shape: tuple[int, ...]) -> tuple[np.ndarray, str] | None:
    """The stored tare for this scanner, or None if there is none; ValueError (naming the file
    and what is wrong) if there is a file that is not a tare of this array."""
    path = tare_path(state_dir, serial)
    try:
        text = _read_tare_text(path)
        return None if text is None else parse_tare(text, shape)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
