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


def load_tare(state_dir: Path, serial: str, shape: tuple[int, ...]) -> tuple[np.ndarray, str] | None:
    """The stored tare for this scanner, or None if there is none or it does not fit."""
    path = tare_path(state_dir, serial)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise ValueError(f"tare file {path} is unreadable: {exc}") from exc
    if tuple(doc.get("shape", ())) != tuple(shape):
        raise ValueError(f"tare file {path} is for an array shaped {doc.get('shape')}, the scanner is {list(shape)}")
    values = np.array([np.nan if x is None else x for x in doc["base_resistance_ohm"]], dtype=np.float64)
    return values.reshape(shape), f"tare {doc.get('created', '?')}"
