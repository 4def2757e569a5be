"""What the turning noise makes of the sheet's mean Gaussian curvature product.

The constant twist c comes from the Gauss equation, c² = mean(k_u k_v − τ₀²) over the cells'
region (developable sheets), and several tests ask whether such a product stands above the
noise.  The fields k_u, k_v, τ₀ are the field fit's linear maps of the units' turning data, and
they carry the noise of many units at once: their noise at a fine node is several times a unit's
own, correlated from node to node, and k_u and k_v are correlated with each other (a noise
ripple of the bending potential curves both directions alike).  So the noise alone gives the
mean product a positive *bias*, which does not average away over the sheet: on a flat 16×16
sheet with the sensor's noise, mean(k_u k_v − τ₀²) ≈ 7e-7 /mm², a constant twist of 8e-4 /mm
and millimetres of spurious deflection, while the estimate "(σ_t κ_rms + σ_t²)/√units" that
assumes independent nodes puts its s.d. at 5e-8.

:class:`ProductNoise` measures both parts once per geometry from the model itself: the field
maps' response to every unit's turning alone (sheets of up to :data:`EXACT_MAX_UNITS` units) gives
the noise-only product's mean (the bias, also node by node: the Gaussian curvature the shear is
solved for is debiased with it) and s.d. exactly, as a quadratic form of the noise, and, per
frame, the s.d. of the cross term between the measured fields and the noise (linear in the
noise).  On larger sheets seeded draws of unit-variance noise estimate the same (each s.d. to
about ±9 % with 64 draws: an 8×8 oblique cylinder's product s.d. came out 15 % low that way, and
its corners beyond 3σ on one noisy frame in 40).  The noise parts scale with σ_t².  The bias is
removed at the noise the data actually carry (:func:`turning_noise_estimate`, no more than twice
the stated one): removing the bias of noise that is not there would bend a clean sheet as much
as the noise would have.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ProductNoise", "measure_product_noise", "turning_noise_estimate", "pair_product", "EXACT_MAX_UNITS"]

#: Noise draws per geometry above EXACT_MAX_UNITS: the bias is known to ~1/√draws of its s.d.
#: (12 %), enough for a 3 s.d. test; the fields kept cost draws · 3 · (inner nodes) doubles
#: (6 MB at 32×32).
DRAWS = 64
#: Up to this many valid units (12×12) the statistics are exact: one response per unit, 3.7 MB of
#: fields at 12×12.  Not yet at 16×16: there the exact s.d. is lower than the sampled one on the
#: bench's cylinders and saddles (scatter / σ 1.23 → 1.30), and what it exposes, the noise's
#: nonlinear path on large curved sheets (a saddle's edge scatters 1.2–1.7 times its σ), has no
#: term of σ yet (docs/reconstruction.md, "Exact product statistics").
EXACT_MAX_UNITS = 288
_SEED = 20240917  # fixed: the same geometry gives the same statistics (replay is bit for bit)


@dataclass(frozen=True)
class ProductNoise:
    """Noise statistics of K̄ = mean over the cells' region of k_u k_v − τ₀² (τ₀ zero-mean over
    the fine grid), per unit turning noise s.d. σ_t = 1 (one unit, per length, 1/mm)."""

    bias: float  # E[K̄] from the noise alone
    spread: float  # s.d. of K̄ from the noise alone
    # (draws, 3 · inner nodes): k_u, k_v, τ₀ of each draw, read-only; their second moments are
    # the noise's (the exact path's unit responses scaled by √units)
    fields: np.ndarray
    bias_field: np.ndarray  # (nf, mf): E[k_u k_v − τ₀²] at every fine node from the noise alone
    twist_bias: float = 0.0  # E[mean τ₀²] from the noise alone (the part of ``bias`` the twist field gives, negated)
    twist_spread: float = 0.0  # s.d. of mean τ₀² from the noise alone

    def stats(self, k_u: np.ndarray, k_v: np.ndarray, tau0: np.ndarray, inner, sigma_t: float) -> tuple[float, float]:
        """(bias, s.d.) of K̄ at turning noise ``sigma_t`` for the measured fields (fine grid;
        ``tau0`` zero-mean): the noise-only part plus the cross term 2·mean(signal · noise)."""
        if not sigma_t > 0.0:
            return 0.0, 0.0
        return self.stats_at(self.cross_sd(k_u, k_v, tau0, inner), sigma_t)

    def cross_sd(self, k_u: np.ndarray, k_v: np.ndarray, tau0: np.ndarray, inner) -> float:
        """The s.d. of the cross term 2·mean(signal · noise) of K̄ per unit turning noise for the
        measured fields (``tau0`` zero-mean): the part of :meth:`stats` the fields set."""
        ku, kv, tt = (np.ascontiguousarray(f[inner]).ravel() for f in (k_u, k_v, tau0))
        count = ku.size
        # cross term of draw d: mean(ku·kv_d + kv·ku_d − 2 τ·τ_d) (zero-mean, linear in the noise)
        cross = self.fields @ np.concatenate([kv, ku, -2.0 * tt]) / count
        return math.sqrt(float(cross @ cross) / cross.size)

    def stats_at(self, cross_sd: float, sigma_t: float) -> tuple[float, float]:
        """:meth:`stats` from the fields' :meth:`cross_sd`, at turning noise ``sigma_t`` > 0."""
        s2 = sigma_t * sigma_t
        return self.bias * s2, math.hypot(self.spread * s2, cross_sd * sigma_t)

    def twist_stats(self, tau0: np.ndarray, inner, sigma_t: float) -> tuple[float, float]:
        """(bias, s.d.) of mean(τ₀²) over the cells' region at turning noise ``sigma_t`` for the
        measured twist field (``tau0`` zero-mean): the noise-only part plus the cross term
        2·mean(τ₀ · noise)."""
        if not sigma_t > 0.0:
            return 0.0, 0.0
        tt = np.ascontiguousarray(tau0[inner]).ravel()
        draws = self.fields.reshape(self.fields.shape[0], 3, -1)[:, 2]
        cross = draws @ (2.0 * tt) / tt.size
        cross_sd = math.sqrt(float(cross @ cross) / cross.size)
        s2 = sigma_t * sigma_t
        return self.twist_bias * s2, math.hypot(self.twist_spread * s2, cross_sd * sigma_t)


def measure_product_noise(maps, valid: np.ndarray, inner, draws: int = DRAWS) -> ProductNoise:
    """:class:`ProductNoise` of the field maps ``maps`` (``grid.field_maps(valid)``: turning,
    stretch → k_u, k_v, τ₀, λ_u, λ_v, fit): exact from each valid unit's response where there are
    at most :data:`EXACT_MAX_UNITS`, else from ``draws`` seeded draws of unit-variance noise on
    the valid units' turning."""
    valid = np.asarray(valid, dtype=bool)
    units = np.flatnonzero(valid)
    exact = 0 < units.size <= EXACT_MAX_UNITS
    stretch = np.ones(valid.shape)
    rng = np.random.default_rng(_SEED)
    count = units.size if exact else draws
    kept = np.empty((count, 3, 0))
    total: np.ndarray | None = None
    products = np.empty(count)
    twists = np.empty(count)
    for d in range(count):
        if exact:
            turning = np.zeros(valid.shape)
            turning.flat[units[d]] = 1.0
        else:
            turning = np.where(valid, rng.standard_normal(valid.shape), 0.0)
        k_u, k_v, tau0 = (np.asarray(f, dtype=float) for f in maps(turning, stretch)[:3])
        tau0 = tau0 - tau0.sum() / tau0.size
        here = k_u * k_v - tau0 * tau0
        total = here if total is None else total + here
        ku, kv, tt = (np.ascontiguousarray(f[inner]).ravel() for f in (k_u, k_v, tau0))
        products[d] = float(ku @ kv - tt @ tt) / ku.size
        twists[d] = float(tt @ tt) / tt.size
        if kept.shape[2] == 0:
            kept = np.empty((count, 3, ku.size))
        kept[d] = (ku, kv, tt)
    assert total is not None
    if exact:
        # K̄(z) = zᵀQz for unit noise z: E = tr Q (the responses' own products summed),
        # Var = 2 ||Q||²_F; the cross term's second moment Σ_u (wᵀ f_u)² is the mean over the
        # responses scaled by √units
        nodes = kept.shape[2]
        q = (kept[:, 0] @ kept[:, 1].T) / nodes
        q = 0.5 * (q + q.T) - (kept[:, 2] @ kept[:, 2].T) / nodes
        bias, spread = float(products.sum()), math.sqrt(2.0 * float((q * q).sum()))
        qt = (kept[:, 2] @ kept[:, 2].T) / nodes
        twist_bias, twist_spread = float(twists.sum()), math.sqrt(2.0 * float((qt * qt).sum()))
        bias_field = total
        kept *= math.sqrt(count)
    else:
        bias, spread = float(products.mean()), float(products.std(ddof=1))
        twist_bias, twist_spread = float(twists.mean()), float(twists.std(ddof=1))
        bias_field = total / count
    fields = np.ascontiguousarray(kept.reshape(count, -1))
    fields.flags.writeable = False
    bias_field.flags.writeable = False
    return ProductNoise(bias, spread, fields, bias_field, twist_bias, twist_spread)


def turning_noise_estimate(turning: np.ndarray, valid: np.ndarray) -> float:
    """Robust estimate of the turning noise s.d. of one unit (per length) from the data
    themselves: the median absolute second difference of the units' turning along the rows and
    the columns (6 σ² for independent noise; a smooth sheet's own second differences are small,
    and a sharp feature touches a minority of units).  NaN when too few units are valid."""
    t = np.where(valid, turning, np.nan)
    # (slices and a partition: the same numbers as np.take and np.median, at a fraction of their
    # cost; a frame asks twice)
    d = np.concatenate([((t[:, :-2] - 2.0 * t[:, 1:-1]) + t[:, 2:]).ravel(),
                        ((t[:, :, :-2] - 2.0 * t[:, :, 1:-1]) + t[:, :, 2:]).ravel()])
    d = np.abs(d[np.isfinite(d)])
    if d.size < 8:
        return float("nan")
    half = d.size // 2
    if d.size % 2:
        median = float(np.partition(d, half)[half])
    else:  # the mean of the two middle values, as np.median takes it
        part = np.partition(d, (half - 1, half))
        median = float((part[half - 1] + part[half]) / 2.0)
    return median / (0.6745 * math.sqrt(6.0))


def pair_product(turning: np.ndarray, valid: np.ndarray, sigma_t: float) -> tuple[float, float, int]:
    """The mean over the cells of the product of each cell's two gauge pairs' turning, its row
    pair's by its column pair's (``turning`` (2, N, M), per length), with its s.d. at turning
    noise ``sigma_t`` (one unit), and the cells counted (both pairs valid).

    Why: the two pairs of a cell are separate gauges with independent noise, so the product of
    their readings carries no noise bias and only the cross term signal × noise (the noise's own
    product averages to zero), whereas the field fit's k_u and k_v share every unit's noise (a
    noise ripple of the bending potential curves both directions alike): on a 32×32 sheet at the
    sensor's noise the fields' mean product has a noise bias of 3.8·10⁻⁷ /mm² and an s.d. of
    4.2·10⁻⁸ against the pairs' 1.8·10⁻⁸ (16×16: 9.6·10⁻⁸ against 5.2·10⁻⁸; 5×5 about equal).
    It is the mean of the cells' gauge-averaged curvatures, not of the fine fields': the two
    agree on uniformly curved sheets and part on sharp features (a ridge on 5×5 by 30 s.d.),
    which the caller tests before using it."""
    both = np.asarray(valid[0], bool) & np.asarray(valid[1], bool)
    count = int(both.sum())
    if count == 0:
        return 0.0, math.inf, 0
    tu, tv = np.asarray(turning[0], float)[both], np.asarray(turning[1], float)[both]
    s2 = float(sigma_t) ** 2
    # Var(mean) = Σ (t_v² + t_u²) σ² + σ⁴ over the cells, / count² (each reading's own noise
    # included in t², a slight overstatement)
    var = (float(tv @ tv + tu @ tu) * s2 + count * s2 * s2) / (count * count)
    return float(tu @ tv) / count, math.sqrt(var), count
