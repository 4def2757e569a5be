"""The tare and the mold calibration file: their formats, writing them atomically, and reading
them back with an error that names the file and what is wrong with it.

The tare (``tare-SERIAL.json``) holds each gauge's resting resistance of the flat, unloaded
sheet; the calibration file (``calibration-SERIAL.json``, :data:`CALIBRATION_FORMAT`) holds the
gauge factors and layer offsets a mold calibration found (docs/calibration.md). Both live in
the state directory.
"""
from __future__ import annotations

import json
import os
import stat
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["compute_tare", "save_tare", "parse_tare", "load_tare", "tare_path", "calibration_path",
           "save_calibration", "parse_calibration", "load_calibration_file", "CALIBRATION_FORMAT", "MAX_TARE_BYTES"]


def compute_tare(resistance_scans: np.ndarray) -> np.ndarray:
    """Resting resistance per gauge: the median over scans (robust to glitches), NaN-aware."""
    scans = np.asarray(resistance_scans, dtype=np.float64)
    if scans.ndim != 5 or scans.shape[0] < 1:
        raise ValueError(f"tare needs scans shaped (K, 2, 2, N, M); got {scans.shape}")
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(scans, axis=0)


def tare_path(state_dir: Path, serial: str) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in serial) or "unknown"
    return Path(state_dir) / f"tare-{safe}.json"


def _write_atomically(path: Path, doc: dict) -> Path:
    """Temp file, fsync, rename: a crash never leaves half a file."""
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(doc, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


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
    return _write_atomically(path, doc)


#: A tare of the largest array (2 × 2 × 32 × 32 gauges) is about 80 kB; anything far larger is
#: not a tare, and reading it must not hold up the service.
MAX_TARE_BYTES = 4 * 1024 * 1024


def _read_tare_text(path: Path) -> str | None:
    """The tare (or calibration) file's text, or None if there is none. Never blocks: a FIFO or
    device at the path is refused (opened non-blocking, then only a regular file is read)."""
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


def _json_object(text: str) -> dict:
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"not a JSON object but {_json_kind(doc)}")
    return doc


def parse_tare(text: str, shape: tuple[int, ...]) -> tuple[np.ndarray, str]:
    """Base resistances shaped ``shape`` and the tare's source text, from a tare file's text;
    ValueError says what is wrong with it."""
    doc = _json_object(text)
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


# ------------------------------------------------------------------------------------------
# the mold calibration file

#: Name and version of the calibration file's layout; a reader refuses any other.
CALIBRATION_FORMAT = ("skinmap.calibration", 1)


def calibration_path(state_dir: Path, serial: str) -> Path:
    return tare_path(state_dir, serial).with_name(tare_path(state_dir, serial).name.replace("tare-", "calibration-", 1))


def _finite_list(a: np.ndarray) -> list:
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).ravel()]


def save_calibration(state_dir: Path, serial: str, *, gauge_factor: np.ndarray, gauge_factor_sd: np.ndarray,
                     h_upper_mm: np.ndarray, h_upper_sd_mm: np.ndarray, h_lower_mm: np.ndarray,
                     h_lower_sd_mm: np.ndarray, residual_rms: np.ndarray, method: str,
                     offsets_determined: bool, poses: list[dict], duration_s: float, notes: list[str],
                     poisson: tuple[float, float] | None = None) -> Path:
    """Write the calibration file atomically (temp file, fsync, rename)."""
    path = calibration_path(state_dir, serial)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "format": CALIBRATION_FORMAT[0], "version": CALIBRATION_FORMAT[1],
        "serial": serial,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "method": method,
        "duration_s": round(float(duration_s), 3),
        "shape": list(np.shape(gauge_factor)),
        "gauge_factor": _finite_list(gauge_factor),
        "gauge_factor_sd": _finite_list(gauge_factor_sd),
        "residual_strain_rms": _finite_list(residual_rms),
        "offsets_determined": bool(offsets_determined),
        "h_upper_mm": _finite_list(h_upper_mm),
        "h_upper_sd_mm": _finite_list(h_upper_sd_mm),
        "h_lower_mm": _finite_list(h_lower_mm),
        "h_lower_sd_mm": _finite_list(h_lower_sd_mm),
        "poses": poses,
        "notes": list(notes),
    }
    if poisson is not None:  # measured on a dome (optional in version 1: older files have none)
        doc["poisson_ratio"], doc["poisson_ratio_sd"] = round(float(poisson[0]), 5), round(float(poisson[1]), 5)
    return _write_atomically(path, doc)


def _numbers(doc: dict, key: str, count: int, positive: bool) -> np.ndarray:
    raw = doc.get(key)
    if not isinstance(raw, list) or len(raw) != count:
        raise ValueError(f"'{key}' must be a list of {count} numbers, got {_json_kind(raw)}")
    for i, x in enumerate(raw):
        if type(x) not in (int, float) or not np.isfinite(x) or (positive and x <= 0):
            raise ValueError(f"'{key}'[{i}] must be a finite number{' > 0' if positive else ''}, got {_json_kind(x)}")
    return np.asarray(raw, dtype=np.float64)


def parse_calibration(text: str, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(gauge factors (2, 2, N, M), h_upper_mm (2, N, M), h_lower_mm, summary) from a calibration
    file's text; ValueError says what is wrong with it."""
    doc = _json_object(text)
    if (doc.get("format"), doc.get("version")) != CALIBRATION_FORMAT:
        raise ValueError(f"format {doc.get('format')!r} version {doc.get('version')!r}, this reader knows "
                         f"{CALIBRATION_FORMAT[0]!r} version {CALIBRATION_FORMAT[1]}")
    if doc.get("shape") != list(shape):
        raise ValueError(f"for an array shaped {doc.get('shape')}, the scanner is {list(shape)}")
    gauges = int(np.prod(shape))
    gf = _numbers(doc, "gauge_factor", gauges, True).reshape(shape)
    hu = _numbers(doc, "h_upper_mm", gauges // 2, True).reshape(shape[1:])
    hl = _numbers(doc, "h_lower_mm", gauges // 2, True).reshape(shape[1:])
    res = np.asarray([np.nan if x is None else x for x in doc.get("residual_strain_rms") or []], dtype=float)
    sd = np.asarray([np.nan if x is None else x for x in doc.get("gauge_factor_sd") or []], dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_sd = sd / gf.ravel() if sd.size == gf.size else np.array([np.nan])
    poisson = doc.get("poisson_ratio")
    if poisson is not None and (type(poisson) not in (int, float) or not 0.0 <= poisson < 0.5):
        raise ValueError(f"'poisson_ratio' must be a number in [0, 0.5), got {_json_kind(poisson)}")
    summary = {
        "created": doc.get("created", "?"), "method": doc.get("method", "?"),
        "poisson_ratio": poisson, "poisson_ratio_sd": doc.get("poisson_ratio_sd"),
        "offsets_determined": bool(doc.get("offsets_determined", False)),
        "duration_s": doc.get("duration_s"),
        "residual_strain_rms_median": float(np.nanmedian(res)) if res.size and np.isfinite(res).any() else None,
        "gauge_factor_rel_sd_median": float(np.nanmedian(rel_sd)) if np.isfinite(rel_sd).any() else None,
    }
    return gf, hu, hl, summary


def load_calibration_file(state_dir: Path, serial: str, shape: tuple[int, ...]
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict] | None:
    """The stored mold calibration of this scanner, or None if there is none; ValueError (naming
    the file and what is wrong) if there is a file that is not a calibration of this array."""
    path = calibration_path(state_dir, serial)
    try:
        text = _read_tare_text(path)
        return None if text is None else parse_calibration(text, shape)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
