"""The Gaussian curvature a film's stretch pattern implies (Airy), for a film loaded only along its
normal (a frictionless mold, pressure): one source for the reconstruction's elastic prior and for
calibration's Poisson ratio.

In plane stress with no in-plane load the membrane stress has an Airy function φ with
∇⁴φ = −E·t·K (the compatibility of Föppl-von Kármán), and tr ε = (1 − ν)·∇²φ/(E·t), so

    ∇²(ε_uu + ε_vv) = −(1 − ν)·K

whatever the sheet's outline or its edge loads.  Over the units the trace of the stretch is then
c + (∇²tr/4)·r² plus a harmonic function, fitted here with the harmonics up to fourth order
(square symmetry): 7 terms from the units' stretch, each gauge's mean along its line adding only
constants to them.  The fit reads the mean Laplacian over the sheet, which is insensitive to
noise (it is the curvature of a fit over the whole sheet, not of neighbouring units).  Against the
film's own mean K over the units' hull (`bench/equilibrium_prior.py --airy`, films solved by the
emulator's finite elements): spheres 0.97-0.99, saddles 0.98-1.00, ν = 0.3 0.999; a sphere with
friction 0.82 and a 5 % pre-stretched one 1.23-1.28 (outside the closed form's assumptions), hence
the 10 % model s.d.  Where K changes across the sheet (a bump) the mean Laplacian of a 7-term fit
is no reading of K: the elastic prior's own cost declines those shapes.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from skinmap.strains import cell_axes

__all__ = ["TraceLaplacian", "trace_laplacian", "stretch_trace", "airy_gaussian_curvature", "airy_curvature_range",
           "MIN_UNITS"]

_TERMS = 7
MIN_UNITS = _TERMS + 3  # fewer leave the fit's scatter unknown
AIRY_MODEL_SD = 0.10     # the closed form's error on elastic molds, relative (module text)
AIRY_FLOOR = 1e-6        # 1/mm²: a curvature of 1/(1 m)², beneath what a 12 mm grid's twist shows
# Friction on the mold holds the film where it would slide, and the trace then reads |K| low,
# never high: spheres (R 70-320 mm) with friction 3e-4 to 3e-3 read 0.72-0.92 of their K at 5×5
# and 8×8, 0.70-0.76 at 12×12 (frictionless: 0.96-1.00).  The interval reaches that far
# beyond the reading's magnitude (a sphere with friction read as a sphere plus a twist of the
# missing K was 2.2 mm off on 8×8).
AIRY_FRICTION_LOSS = 0.35
# The trace is a reading of one mean K only where the 7-term pattern describes it: spheres,
# saddles and cylinders on molds leave 1-7 % of the trace's spread (18 % pre-stretched on a
# large sheet); bumps, ridges and a mold with friction 60-100 %.
AIRY_MAX_RESIDUAL = 0.25


class TraceLaplacian(NamedTuple):
    laplacian: float     # ∇²(ε_uu + ε_vv), 1/mm²
    sd: float            # its s.d. from the fit's residuals
    residual_rms: float  # strain: the trace's misfit to the model
    units: int


def trace_laplacian(trace: np.ndarray, pitch_mm: float) -> TraceLaplacian:
    """The mean Laplacian of the stretch trace ε_uu + ε_vv (N, M) per unit (NaN: missing) on a grid
    of pitch ``pitch_mm``.  ValueError if fewer than ``MIN_UNITS`` units have both gauges."""
    trace = np.asarray(trace, float)
    if trace.ndim != 2:
        raise ValueError(f"the stretch trace must be (N, M) per unit, got shape {trace.shape}")
    n, m = trace.shape
    ok = np.isfinite(trace)
    count = int(ok.sum())
    if count < MIN_UNITS:
        raise ValueError(f"{count} units with both gauges: the stretch pattern's curvature needs at least {MIN_UNITS} "
                         "(a sheet of 3×4 units or more)")
    a, solve, cov11 = _design(n, m, float(pitch_mm), ok.tobytes())
    y = trace[ok]
    coef = solve @ y
    resid = y - a @ coef
    var = float(resid @ resid) / (count - _TERMS)
    return TraceLaplacian(4.0 * float(coef[1]), 4.0 * math.sqrt(max(var * cov11, 0.0)),
                          math.sqrt(float(resid @ resid) / count), count)


@lru_cache(maxsize=16)
def _design(n: int, m: int, pitch_mm: float, mask: bytes) -> tuple[np.ndarray, np.ndarray, float]:
    """The 7-term fit for the units of ``mask`` (the (N, M) bool array's bytes) on a grid of pitch
    ``pitch_mm``: its design matrix (units, 7), the least-squares solution operator (7, units)
    (the minimum-norm solution of numpy's lstsq, column by column) and the (1, 1) entry of
    pinv(AᵀA), the coefficient's variance per unit residual variance.  Cached: the mask changes
    rarely, the data every frame."""
    ok = np.frombuffer(mask, dtype=bool).reshape(n, m)
    uc, vc = cell_axes(n, m, pitch_mm)
    vv, uu = np.meshgrid(vc, uc, indexing="ij")
    columns = [np.ones_like(uu), uu ** 2 + vv ** 2, uu, vv, uu ** 2 - vv ** 2, uu * vv,
               uu ** 4 - 6 * uu ** 2 * vv ** 2 + vv ** 4]
    a = np.stack([c[ok] for c in columns], axis=1)
    solve = np.linalg.lstsq(a, np.eye(a.shape[0]), rcond=None)[0]
    for x in (a, solve):
        x.flags.writeable = False
    return a, solve, float(np.linalg.pinv(a.T @ a)[1, 1])


def stretch_trace(stretch: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Every unit's stretch trace, ε_uu + ε_vv (N, M), from its stretch ratios (2, N, M); NaN
    where either gauge is not measured (``valid``)."""
    stretch = np.asarray(stretch, float)
    both = np.asarray(valid, bool).all(axis=0)
    return np.where(both, stretch[0] + stretch[1] - 2.0, np.nan)


def airy_gaussian_curvature(stretch: np.ndarray, valid: np.ndarray, pitch_mm: float, poisson: float,
                            poisson_sd: float = 0.0) -> tuple[float, float]:
    """Mean Gaussian curvature over the units (1/mm²) and its s.d. (the fit's, ν's and the closed
    form's own error) from the units' stretch ratios (2, N, M) (``valid``: which are measured)."""
    trace = stretch_trace(stretch, valid)
    fit = trace_laplacian(trace, pitch_mm)
    k = -fit.laplacian / (1.0 - poisson)
    sd = math.sqrt((fit.sd / (1.0 - poisson)) ** 2 + (k * poisson_sd / (1.0 - poisson)) ** 2 + (AIRY_MODEL_SD * k) ** 2
                   + AIRY_FLOOR ** 2)
    return k, sd


def airy_curvature_range(stretch: np.ndarray, valid: np.ndarray, pitch_mm: float, poisson_lo: float,
                         poisson_hi: float, sds: float = 2.0, noise_sd: float = 0.0) -> tuple[float, float] | None:
    """The interval of mean Gaussian curvature (1/mm²) the units' stretch ratios (2, N, M) allow
    for a film loaded along its normal whose Poisson ratio lies in [``poisson_lo``,
    ``poisson_hi``]: the closed form at both ends, widened by ``sds`` s.d. of the fit and of the
    closed form's own error, and on its far side by what friction on the mold hides of |K|
    (``AIRY_FRICTION_LOSS``).  None where the stretch pattern is no reading of one mean K (too few
    units, or a trace the 7-term pattern leaves more than ``AIRY_MAX_RESIDUAL`` of unexplained:
    a bump, a ridge, friction; or a trace whose spread is within 3 ``noise_sd``, the s.d. of one
    unit's trace from noise alone: no pattern to read)."""
    if not 0.0 <= poisson_lo <= poisson_hi < 1.0:
        raise ValueError(f"the Poisson range must satisfy 0 <= lo <= hi < 1, got [{poisson_lo!r}, {poisson_hi!r}]")
    trace = stretch_trace(stretch, valid)
    if int(np.isfinite(trace).sum()) < MIN_UNITS:
        return None
    spread = float(np.nanstd(trace))
    if not spread > 3.0 * noise_sd:
        return None
    fit = trace_laplacian(trace, pitch_mm)
    if not spread > 0.0 or fit.residual_rms > AIRY_MAX_RESIDUAL * spread:
        return None
    ends = []
    for nu in (poisson_lo, poisson_hi):
        k = -fit.laplacian / (1.0 - nu)
        sd = math.sqrt((fit.sd / (1.0 - nu)) ** 2 + (AIRY_MODEL_SD * k) ** 2 + AIRY_FLOOR ** 2)
        far = k / (1.0 - AIRY_FRICTION_LOSS)  # friction reads |K| low: the truth may be this far
        ends += [k - sds * sd, k + sds * sd, far - sds * sd, far + sds * sd]
    return min(ends), max(ends)
