"""Electrical model of the gauges: strain -> resistance -> ADC code on the wire.

R = R0 · (1 + GF · ε_h + drift) + noise, then a 24-bit ADC over [0, full scale). The gauge law
itself is the host's (:func:`skinmap.strains.gauge_resistance`; the host inverts it with
:func:`skinmap.strains.gauge_strain`): the emulator adds only what a real gauge and ADC do on top.

- per-gauge gauge factor GF (1.24 ± 0.19) and base resistance R0 (6.55 ± 0.72 Ω) are the
  device's factory calibration, drawn once from a seed and reported in HELLO;
- ε_h is the strain after a rate-independent hysteresis: a play (backlash) operator whose
  half-width is proportional to the distance from the rest state, w = (H/2)·|ε|. Loading then
  reads (1 − H/2)·ε, unloading (1 + H/2)·ε, so the loop height is H (≈ 4 %) of the strain
  excursion at its peak and closes at rest; there is no creep;
- optionally a first-order response lag of the gauge (time constant ``response_tau_s``; the
  gauges respond within 170 ms, i.e. τ ≲ 57 ms for 95 %), off by default;
- optionally the reading's relaxation under a held strain (``relaxation``: the share of a held
  strain's reading lost, 3.5 % at 20 % strain in the sensor's paper; ``relaxation_tau_s``: how
  fast, which the paper does not give), off by default: the reading is ε_h − f·q with q
  following ε_h at that time constant, so a strain held reads (1 − f)·ε_h in the end and one
  released reads −f·q, recovering at the same rate (a standard linear solid);
- drift is an Ornstein–Uhlenbeck process on the relative resistance (tiny, slow);
- white noise of s.d. 0.007 % of R;
- the ADC quantises to one LSB (full scale / 2^24; the default full scale 16.777216 Ω makes the
  LSB exactly the wire's 1 µΩ); readings at or above full scale are saturated, an open gauge
  reads the open sentinel.

Every effect can be switched off (``ElectricalConfig.ideal()``).  All randomness comes from an
explicit ``numpy.random.Generator``; the functions are pure except :class:`GaugeReadout`, which
only bundles the explicit state (hysteresis memory, drift) with them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from skinmap.protocol import RES_MAX_VALID, RES_OPEN, RES_SATURATED
from skinmap.strains import gauge_resistance

__all__ = [
    "GaugeConstants",
    "ElectricalConfig",
    "GaugeReadout",
    "draw_calibration",
    "draw_true_constants",
    "hysteresis_step",
    "drift_step",
    "lag_step",
    "strain_to_resistance",
    "quantise",
]

GF_MEAN, GF_SD = 1.24, 0.19
R0_MEAN_OHM, R0_SD_OHM = 6.55, 0.72


@dataclass(frozen=True)
class GaugeConstants:
    """Gauge factor and base resistance per gauge, each (2, 2, N, M): a device's factory
    calibration (reported in HELLO) or, with a hidden spread, its true constants."""

    gauge_factor: np.ndarray
    base_resistance_ohm: np.ndarray

    def __post_init__(self) -> None:
        gf, r0 = np.asarray(self.gauge_factor), np.asarray(self.base_resistance_ohm)
        if gf.ndim != 4 or gf.shape[:2] != (2, 2) or r0.shape != gf.shape:
            raise ValueError(
                f"calibration arrays must both be (2, 2, N, M), got {gf.shape} and {r0.shape}"
            )
        if np.any(gf <= 0) or np.any(r0 <= 0):
            raise ValueError("gauge factors and base resistances must be positive")

    @property
    def shape(self) -> tuple[int, int, int, int]:
        n_layers, n_dirs, n, m = np.shape(self.gauge_factor)
        return n_layers, n_dirs, n, m

    def micro_units(self) -> tuple[np.ndarray, np.ndarray]:
        """(GF × 1e6, R0 in µΩ) as uint32, the HELLO representation."""
        gf = np.rint(np.asarray(self.gauge_factor) * 1e6).astype(np.uint32)
        r0 = np.rint(np.asarray(self.base_resistance_ohm) * 1e6).astype(np.uint32)
        return gf, r0


def _truncated_normal(rng: np.random.Generator, mean: float, sd: float, lo: float, size) -> np.ndarray:
    x = rng.normal(mean, sd, size)
    bad = x < lo
    while np.any(bad):  # redraw the rare values a real device would have rejected at test
        x[bad] = rng.normal(mean, sd, int(bad.sum()))
        bad = x < lo
    return x


def draw_calibration(
    rng: np.random.Generator,
    n: int,
    m: int,
    gf_mean: float = GF_MEAN,
    gf_sd: float = GF_SD,
    r0_mean_ohm: float = R0_MEAN_OHM,
    r0_sd_ohm: float = R0_SD_OHM,
) -> GaugeConstants:
    """Draw a device's factory calibration.  Values are rounded to the HELLO resolution
    (1e-6 GF, 1 µΩ) so the device and a host that reads HELLO use identical numbers."""
    if int(n) != n or int(m) != m or n < 1 or m < 1:
        raise ValueError(f"array size must be positive integers, got {n}x{m}")
    size = (2, 2, int(n), int(m))
    gf = _truncated_normal(rng, gf_mean, gf_sd, 0.3, size)
    r0 = _truncated_normal(rng, r0_mean_ohm, r0_sd_ohm, 1.0, size)
    return GaugeConstants(np.rint(gf * 1e6) / 1e6, np.rint(r0 * 1e6) / 1e6)


def draw_true_constants(rng: np.random.Generator, factory: GaugeConstants, gf_spread: float) -> GaugeConstants:
    """The gauges' true constants: each gauge factor departs from its factory value by a
    relative N(0, gf_spread) (clipped to ±3 s.d.), the base resistances are the factory's.  A
    host that trusts HELLO is then wrong by that spread, as with gauges whose factory values
    were measured on a different batch."""
    if not (math.isfinite(gf_spread) and 0 <= gf_spread < 0.3):
        raise ValueError(f"gauge-factor spread must be in [0, 0.3), got {gf_spread!r}")
    gf = np.asarray(factory.gauge_factor, dtype=float)
    rel = np.clip(rng.standard_normal(gf.shape), -3.0, 3.0) * gf_spread
    return GaugeConstants(gf * (1.0 + rel), np.asarray(factory.base_resistance_ohm, dtype=float))


@dataclass(frozen=True)
class ElectricalConfig:
    """Switches and magnitudes of the non-idealities (set a magnitude to 0 to switch it off)."""

    hysteresis: float = 0.04  # loop height as a fraction of the strain excursion
    noise_rel_sd: float = 7e-5  # white noise s.d. as a fraction of R (0.007 %)
    drift_rel_sd: float = 1e-5  # stationary s.d. of the relative drift
    drift_tau_s: float = 600.0  # drift correlation time
    response_tau_s: float = 0.0  # first-order lag of the gauge response (0: instantaneous)
    relaxation: float = 0.0  # share of a held strain's reading lost as it relaxes (the paper: 0.035)
    relaxation_tau_s: float = 10.0  # its time constant (assumed: the paper gives the share only)
    quantise: bool = True  # ADC quantisation (else the value is only rounded to 1 µΩ on the wire)
    adc_bits: int = 24
    adc_full_scale_ohm: float = 16.777216  # 2^24 µΩ: one ADC LSB = 1 µΩ

    def __post_init__(self):
        for name in ("hysteresis", "noise_rel_sd", "drift_rel_sd"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"ElectricalConfig.{name} must be finite and >= 0, got {v!r}")
        if not 0 <= self.hysteresis < 1:
            raise ValueError(f"ElectricalConfig.hysteresis must be in [0, 1), got {self.hysteresis!r}")
        if not (math.isfinite(self.response_tau_s) and self.response_tau_s >= 0):
            raise ValueError(f"ElectricalConfig.response_tau_s must be >= 0 s, got {self.response_tau_s!r}")
        if not (math.isfinite(self.relaxation) and 0 <= self.relaxation < 1):
            raise ValueError(f"ElectricalConfig.relaxation must be in [0, 1), got {self.relaxation!r}")
        if not (math.isfinite(self.relaxation_tau_s) and self.relaxation_tau_s > 0):
            raise ValueError(f"ElectricalConfig.relaxation_tau_s must be > 0 s, got {self.relaxation_tau_s!r}")
        if not self.drift_tau_s > 0:
            raise ValueError(f"ElectricalConfig.drift_tau_s must be > 0, got {self.drift_tau_s!r}")
        if not 8 <= int(self.adc_bits) <= 32:
            raise ValueError(f"ElectricalConfig.adc_bits must be 8..32, got {self.adc_bits!r}")
        if not 0 < self.adc_full_scale_ohm < RES_MAX_VALID * 1e-6:
            raise ValueError(
                f"ElectricalConfig.adc_full_scale_ohm must be in (0, {RES_MAX_VALID * 1e-6:.3f}) Ω, "
                f"got {self.adc_full_scale_ohm!r}"
            )

    @classmethod
    def ideal(cls) -> "ElectricalConfig":
        """No lag, hysteresis, relaxation, drift, noise or quantisation (only the 1 µΩ wire rounding remains)."""
        return cls(hysteresis=0.0, noise_rel_sd=0.0, drift_rel_sd=0.0, quantise=False, response_tau_s=0.0,
                   relaxation=0.0)

    def without(self, *effects: str) -> "ElectricalConfig":
        """A copy with the named effects off: 'hysteresis', 'noise', 'drift', 'quantise', 'lag', 'relaxation'."""
        known = ("hysteresis", "noise", "drift", "quantise", "lag", "relaxation")
        for e in effects:
            if e not in known:
                raise ValueError(f"unknown effect {e!r}; known: {', '.join(known)}")
        off = set(effects)
        return replace(
            self,
            hysteresis=0.0 if "hysteresis" in off else self.hysteresis,
            noise_rel_sd=0.0 if "noise" in off else self.noise_rel_sd,
            drift_rel_sd=0.0 if "drift" in off else self.drift_rel_sd,
            quantise=False if "quantise" in off else self.quantise,
            response_tau_s=0.0 if "lag" in off else self.response_tau_s,
            relaxation=0.0 if "relaxation" in off else self.relaxation,
        )

    @property
    def lsb_ohm(self) -> float:
        return self.adc_full_scale_ohm / 2 ** int(self.adc_bits)

    @property
    def wire_lsb_uohm(self) -> int:
        """The measurement quantum reported in HELLO (µΩ, at least 1)."""
        return max(1, round(self.lsb_ohm * 1e6)) if self.quantise else 1


def hysteresis_step(memory: np.ndarray, strain: np.ndarray, fraction: float) -> np.ndarray:
    """Proportional play operator: the output stays put until the strain leaves the band
    [ε − w, ε + w], w = (fraction/2)·|ε|.  Returns the new output (= new memory)."""
    w = 0.5 * fraction * np.abs(strain)
    return np.clip(memory, strain - w, strain + w)


def lag_step(state: np.ndarray, strain: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """Exact first-order response to a strain held over the last ``dt_s``."""
    if tau_s <= 0 or dt_s <= 0:
        return strain if tau_s <= 0 else state
    a = math.exp(-dt_s / tau_s)
    return state * a + strain * (1.0 - a)


def drift_step(
    drift: np.ndarray, dt_s: float, rel_sd: float, tau_s: float, rng: np.random.Generator
) -> np.ndarray:
    """Exact Ornstein–Uhlenbeck update over dt with stationary s.d. ``rel_sd``."""
    if rel_sd == 0 or dt_s <= 0:
        return drift
    a = math.exp(-dt_s / tau_s)
    return drift * a + rel_sd * math.sqrt(1.0 - a * a) * rng.standard_normal(np.shape(drift))


def strain_to_resistance(
    strain: np.ndarray,
    calibration: GaugeConstants,
    drift: np.ndarray | float = 0.0,
    noise_rel_sd: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """R = R0 (1 + GF ε + drift) plus white noise of s.d. noise_rel_sd · R (ohms)."""
    r = gauge_resistance(strain, calibration.gauge_factor, calibration.base_resistance_ohm, drift)
    if noise_rel_sd:
        if rng is None:
            raise ValueError("noise needs a numpy Generator (rng)")
        r = r * (1.0 + noise_rel_sd * rng.standard_normal(r.shape))
    return r


def quantise(
    resistance_ohm: np.ndarray,
    config: ElectricalConfig,
    open_mask: np.ndarray | None = None,
    saturated_mask: np.ndarray | None = None,
) -> np.ndarray:
    """ADC + wire encoding: uint32 µΩ with the open/saturated sentinels."""
    r = np.maximum(np.asarray(resistance_ohm, dtype=float), 0.0)
    if config.quantise:
        lsb = config.lsb_ohm
        codes = np.floor(r / lsb + 0.5)
        saturated = codes >= 2 ** int(config.adc_bits) - 1
        uohm = np.rint(codes * (lsb * 1e6))
    else:
        saturated = r >= config.adc_full_scale_ohm
        uohm = np.rint(r * 1e6)
    out = np.minimum(uohm, RES_MAX_VALID).astype(np.uint32)
    out[saturated] = RES_SATURATED
    if saturated_mask is not None:
        out[np.asarray(saturated_mask, dtype=bool)] = RES_SATURATED
    if open_mask is not None:
        out[np.asarray(open_mask, dtype=bool)] = RES_OPEN
    return out


@dataclass
class GaugeReadout:
    """Readout chain of all gauges of one device with its explicit state.

    ``read(strain, t_s)`` takes the true strains (2 layers, 2 directions, N, M) at device time
    ``t_s`` and returns the wire values (uint32 µΩ with sentinels).
    """

    calibration: GaugeConstants
    config: ElectricalConfig
    rng: np.random.Generator
    open_mask: np.ndarray | None = None
    saturated_mask: np.ndarray | None = None
    _memory: np.ndarray | None = field(default=None, repr=False)
    _lagged: np.ndarray | None = field(default=None, repr=False)
    _relaxed: np.ndarray | None = field(default=None, repr=False)
    _held: np.ndarray | None = field(default=None, repr=False)
    _drift: np.ndarray | None = field(default=None, repr=False)
    _last_t: float | None = field(default=None, repr=False)

    def reset_state(self) -> None:
        """Power cycle: hysteresis memory and drift start afresh (calibration is kept)."""
        self._memory = self._drift = self._last_t = self._lagged = self._relaxed = self._held = None

    def read(self, strain: np.ndarray, t_s: float) -> np.ndarray:
        strain = np.asarray(strain, dtype=float)
        if strain.shape != self.calibration.shape:
            raise ValueError(f"strain has shape {strain.shape}, expected {self.calibration.shape}")
        cfg = self.config
        dt = 0.0 if self._last_t is None else t_s - self._last_t
        if cfg.response_tau_s:
            self._lagged = strain.copy() if self._lagged is None else lag_step(
                self._lagged, strain, dt, cfg.response_tau_s)
            strain = self._lagged
        if cfg.hysteresis:
            self._memory = strain.copy() if self._memory is None else self._memory
            self._memory = hysteresis_step(self._memory, strain, cfg.hysteresis)
            strain = self._memory
        if cfg.relaxation:
            # the state q follows what was held up to now as a first-order response does (a sheet
            # already held at power-up has relaxed); the strain read now has been held no time yet
            self._relaxed = strain.copy() if self._relaxed is None or self._held is None else lag_step(
                self._relaxed, self._held, dt, cfg.relaxation_tau_s)
            self._held = strain.copy()
            strain = strain - cfg.relaxation * self._relaxed
        drift: np.ndarray | float = 0.0
        if cfg.drift_rel_sd:
            if self._drift is None:
                self._drift = cfg.drift_rel_sd * self.rng.standard_normal(strain.shape)
            else:
                self._drift = drift_step(self._drift, dt, cfg.drift_rel_sd, cfg.drift_tau_s, self.rng)
            drift = self._drift
        self._last_t = t_s
        r = strain_to_resistance(strain, self.calibration, drift, cfg.noise_rel_sd, self.rng)
        return quantise(r, cfg, self.open_mask, self.saturated_mask)
