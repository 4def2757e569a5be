"""Resistances → calibrated strains: the one definition of the gauge law, both ways.

Each gauge's resistance follows its strain linearly (docs/architecture.md, "Electrical model"):

    R = R0 · (1 + GF · ε)          ε = (R / R0 − 1) / GF

with the per-gauge gauge factor GF and base resistance R0. The emulator's electrical model
computes readings with :func:`gauge_resistance` (plus its non-idealities); the host inverts them
with :func:`gauge_strain`. The scanner stores a factory calibration (GF, R0 per gauge) and
sends it in HELLO; a tare of the flat, unloaded sheet replaces R0 by the measured resting
resistance, which removes the channel-to-channel offsets and the slow drift that a factory R0
cannot know about.

Arrays are shaped (2 layers, 2 directions, N, M), layer 0 = upper, 1 = lower.

A mold calibration (``skinmap calibrate``, :mod:`skinmap.daemon.moldcal`) adds per-gauge gauge
factors and per-unit layer offsets, stored in a versioned calibration file next to the tare
(:mod:`skinmap.strains.calfiles`). The reconstruction takes one pair of nominal offsets, so
strains measured on a unit whose true offsets differ are mapped to the strains that unit would
read at the nominal offsets (:func:`to_nominal_offsets`): the same stretch and turning, read at
h_u and h_l.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Calibration", "gauge_resistance", "gauge_strain", "resistances_to_strains", "to_nominal_offsets",
           "GAUGE_LENGTH_MM", "cell_axes", "cell_centres", "cell_bending", "reject_implausible_units", "turning_noise_rad",
           "MAX_PLAUSIBLE_STRAIN", "MAX_UNIT_TURNING_RAD", "HYSTERESIS_LOOP", "HYSTERESIS_LOOP_SD",
           "HYSTERESIS_GAIN_SD", "RELAXATION_SHARE", "SHARED_GAIN_SD", "RESPONSE_TIME_S", "RESPONSE_LAG_S", "response_lag_s"]


def gauge_resistance(strain: np.ndarray, gauge_factor: np.ndarray, base_resistance_ohm: np.ndarray,
                     drift: np.ndarray | float = 0.0) -> np.ndarray:
    """R = R0 (1 + GF ε + drift), ohms; ``drift`` is a relative change of R that no strain
    explains (the emulator's slow drift; the host's tare takes it up)."""
    return base_resistance_ohm * (1.0 + gauge_factor * strain + drift)


def gauge_strain(resistance_ohm: np.ndarray, gauge_factor: np.ndarray, base_resistance_ohm: np.ndarray) -> np.ndarray:
    """ε = (R / R0 − 1) / GF, the inverse of :func:`gauge_resistance` without drift; NaN
    resistances (open or saturated gauges) give NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return (np.asarray(resistance_ohm, dtype=np.float64) / base_resistance_ohm - 1.0) / gauge_factor


# A gauge whose strain reads beyond this is treated as faulty (the gauges are linear to 50 %).
MAX_PLAUSIBLE_STRAIN = 0.6


@dataclass(frozen=True)
class Calibration:
    gauge_factor: np.ndarray  # (2, 2, N, M)
    base_resistance: np.ndarray  # (2, 2, N, M) ohm
    source: str = "factory"  # "factory", "tare <iso time>", "calibration <iso time>" or both
    h_upper_mm: np.ndarray | None = None  # (2, N, M) per-unit layer offsets of a mold calibration
    h_lower_mm: np.ndarray | None = None
    summary: dict[str, Any] | None = None  # what the calibration file says of itself (method, date, residuals)

    def __post_init__(self) -> None:
        if (self.h_upper_mm is None) != (self.h_lower_mm is None):
            raise ValueError("calibration: layer offsets come in pairs (h_upper_mm and h_lower_mm)")
        if self.h_upper_mm is not None:
            want = self.gauge_factor.shape[1:]
            for name in ("h_upper_mm", "h_lower_mm"):
                h = getattr(self, name)
                if h.shape != want or not (np.all(np.isfinite(h)) and np.all(h > 0)):
                    raise ValueError(f"calibration: {name} must be {list(want)} finite offsets > 0 mm")
        gf, r0 = self.gauge_factor, self.base_resistance
        if gf.shape != r0.shape or gf.ndim != 4 or gf.shape[:2] != (2, 2):
            raise ValueError(f"calibration arrays must both be (2, 2, N, M); got {gf.shape} and {r0.shape}")
        if not (np.all(np.isfinite(gf)) and np.all(gf > 0)):
            raise ValueError("calibration: every gauge factor must be finite and > 0")
        if not (np.all(np.isfinite(r0)) and np.all(r0 > 0)):
            raise ValueError("calibration: every base resistance must be finite and > 0 ohm")

    def with_tare(self, base_resistance: np.ndarray, source: str) -> "Calibration":
        tared = np.where(np.isfinite(base_resistance) & (base_resistance > 0), base_resistance, self.base_resistance)
        return Calibration(self.gauge_factor, tared, source, self.h_upper_mm, self.h_lower_mm, self.summary)

    def with_mold_fit(self, gauge_factor: np.ndarray, h_upper_mm: np.ndarray, h_lower_mm: np.ndarray,
                      source: str, summary: dict[str, Any] | None = None) -> "Calibration":
        """These gauge factors and layer offsets, the base resistances kept."""
        return Calibration(gauge_factor, self.base_resistance, source, h_upper_mm, h_lower_mm, summary)


def to_nominal_offsets(eps_upper: np.ndarray, eps_lower: np.ndarray, h_upper: np.ndarray, h_lower: np.ndarray,
                       h_upper_nominal: float, h_lower_nominal: float) -> tuple[np.ndarray, np.ndarray]:
    """Strains of units with layer offsets (h_upper, h_lower) as units at the nominal offsets
    would read them: the stretch (ε_u h_l + ε_l h_u)/(h_u + h_l) and the turning
    (ε_u − ε_l)/(h_u + h_l) are kept (Kirchhoff–Love, to first order in h)."""
    total = h_upper + h_lower
    stretch = (eps_upper * h_lower + eps_lower * h_upper) / total
    turning = (eps_upper - eps_lower) / total
    return stretch + h_upper_nominal * turning, stretch - h_lower_nominal * turning


#: The gauges' length (mm) where a device's is not given: the paper's 10 mm.
GAUGE_LENGTH_MM = 10.0

#: The gauges' hysteresis: the loop's height as a share of the strain excursion, 4.21 ± 0.70 %
#: over 100 channels (the sensor's paper).  The loop closes at rest, so a gauge reads up to half
#: of it off its strain: low while the strain grows from rest, high while it returns.
HYSTERESIS_LOOP = 0.0421
HYSTERESIS_LOOP_SD = 0.0070
#: The s.d. of the gain error the gauges share through it (relative): gauges that move together
#: (a sheet pressed onto a shape and held) read off the same way, by up to half a loop one s.d.
#: high (2.5 %), a bounded error of unknown sign: a rectangular distribution's s.d. (÷ √3).
HYSTERESIS_GAIN_SD = 0.5 * (HYSTERESIS_LOOP + HYSTERESIS_LOOP_SD) / math.sqrt(3.0)
#: The gauges' reading relaxes under a held strain: 3.5 % of it at 20 % strain (the sensor's
#: paper; a linear material loses the same share at any strain).  A sheet held reads up to that
#: much low, from none as it is formed: a bounded error of one sign, its root mean square about
#: none that share over √3.
RELAXATION_SHARE = 0.035
#: The s.d. of the gain error the gauges share (relative), the hysteresis's and the relaxation's
#: together (independent, in quadrature: 0.0247; 3 s.d. reach 7.4 %, past a held sheet's 2.5 % +
#: 3.5 % low): what σ carries by default (docs/reconstruction.md, "A gain the gauges share").
SHARED_GAIN_SD = math.hypot(HYSTERESIS_GAIN_SD, RELAXATION_SHARE / math.sqrt(3.0))

#: The gauges' response and recovery times: below 170 ms for a 0.5 % strain step (the sensor's
#: paper).  Read as a first-order response reaching 95 % of a step within it, a gauge follows a
#: moving strain RESPONSE_LAG_S (τ = 170/3 ≈ 57 ms) late at most, so a sheet that moves is
#: reconstructed where it was up to that long before (docs/reconstruction.md, "A sheet that moves").
RESPONSE_TIME_S = 0.170


def response_lag_s(response_time_s: float) -> float:
    """The time constant (s) of a first-order response that reaches 95 % of a step within
    ``response_time_s``: a third of it (e⁻³ ≈ 5 %)."""
    return float(response_time_s) / 3.0


RESPONSE_LAG_S = response_lag_s(RESPONSE_TIME_S)


def grid_size(n: int, m: int) -> tuple[int, int]:
    """The sheet's rows and columns as ints, each refused by name unless a positive integer."""
    for name, val in (("rows n", n), ("cols m", m)):
        if int(val) != val or int(val) < 1:
            raise ValueError(f"{name} must be a positive integer, got {val!r}")
    return int(n), int(m)


def cell_axes(n: int, m: int, pitch_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The cells' material coordinates along each axis, (u (M,), v (N,)) mm: cell (i, j) is
    centred at u_j = (j − (M−1)/2)·pitch, v_i = (i − (N−1)/2)·pitch, the sheet's material centre
    at the origin (the sensor frame, docs/reconstruction.md).  The one definition of the layout
    that the emulator, the reconstruction and the gateway share."""
    n, m = grid_size(n, m)
    pitch = float(pitch_mm)
    if not (math.isfinite(pitch) and pitch > 0):
        raise ValueError(f"pitch must be a finite positive number, got {pitch_mm!r}")
    return (np.arange(m) - (m - 1) / 2.0) * pitch, (np.arange(n) - (n - 1) / 2.0) * pitch


def cell_centres(n: int, m: int, pitch_mm: float) -> np.ndarray:
    """Material coordinates of the cell centres, (N, M, 2) as (u_j, v_i) (:func:`cell_axes`)."""
    u, v = cell_axes(n, m, pitch_mm)
    uu, vv = np.meshgrid(u, v)  # (N, M): rows follow v, columns follow u
    return np.stack([uu, vv], axis=-1)


def cell_bending(eps_upper: np.ndarray, eps_lower: np.ndarray, h_upper_mm: float, h_lower_mm: float) -> np.ndarray:
    """(N, M) 1/mm: each cell's bending κ_u + κ_v, twice its mean curvature (positive where the
    upper layer lies on the convex side), from its two gauge pairs' layer strains (2, N, M):
    κ = (ε_upper − ε_lower)/(h_upper + h_lower).  NaN where a gauge is unusable."""
    eu, el = np.asarray(eps_upper, dtype=float), np.asarray(eps_lower, dtype=float)
    if eu.shape != el.shape or eu.ndim != 3 or eu.shape[0] != 2:
        raise ValueError(f"layer strains must both be (2, N, M), got {eu.shape} and {el.shape}")
    if not (h_upper_mm + h_lower_mm > 0):
        raise ValueError(f"the layers' offsets must add up to > 0 mm, got {h_upper_mm!r} + {h_lower_mm!r}")
    return ((eu - el) / (h_upper_mm + h_lower_mm)).sum(axis=0)


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
    eps = gauge_strain(r, cal.gauge_factor, cal.base_resistance)
    valid = np.isfinite(eps) & (np.abs(eps) <= MAX_PLAUSIBLE_STRAIN)
    eps = np.where(valid, eps, np.nan)
    return eps[0], eps[1], valid


# A sensing unit whose upper and lower strains imply that its gauge turns by more than half a
# circle (bend radius < L/π ≈ 3 mm for a 10 mm gauge) is not a film we can bend: both gauges
# are rejected as implausible (which of the pair is wrong cannot be told).
MAX_UNIT_TURNING_RAD = float(np.pi)


def turning_noise_rad(strain_sigma: float, gauge_length_mm: float, h_upper_mm: float, h_lower_mm: float) -> float:
    """1-s.d. turning angle of one gauge due to strain noise: √2·σε·L / (h_u + h_l)."""
    return float(np.sqrt(2.0) * strain_sigma * gauge_length_mm / (h_upper_mm + h_lower_mm))


def reject_implausible_units(
    eps_upper: np.ndarray, eps_lower: np.ndarray, valid: np.ndarray, gauge_length_mm: float, h_upper_mm: float,
    h_lower_mm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Mark both gauges of a unit unusable when together they imply an impossible bend.

    eps_* (2, N, M) with NaN for unusable gauges, valid (2, 2, N, M). Returns new arrays (the
    inputs are not modified) and the number of units rejected here.
    """
    turning = (eps_upper - eps_lower) * gauge_length_mm / (h_upper_mm + h_lower_mm)
    with np.errstate(invalid="ignore"):
        bad = valid[0] & valid[1] & ~(np.abs(turning) <= MAX_UNIT_TURNING_RAD)
    if not bad.any():
        return eps_upper, eps_lower, valid, 0
    valid = valid & ~bad[None]
    return np.where(bad, np.nan, eps_upper), np.where(bad, np.nan, eps_lower), valid, int(bad.sum())
