"""Twist and shear fields of a sheet pushed out of plane (a graph), beyond small slopes.

When the stretch pattern shows a graph z(u, v) over the material plane (see
``engine._graph_twist``: E = 1 + z_u², G = 1 + z_v², F = z_u z_v), the unmeasured twist and
shear follow from the graph's slopes instead of the linearised Codazzi equations and the
least-norm shear, which are exact only for small slopes:

* the gauges measure k_u = −z_uu/(W λ_u) (normal curvature along x_u times λ_u, W² = 1 + |∇z|²),
  so the height's own second derivatives are the turning data scaled by W λ_u (gauge-averaged);
  one more pass of the fixed linear fit on the scaled data gives z_uu, z_vv and the varying part
  of z_uv, and the stretch pattern again its constant part;
* the shape operator's off-diagonal in the frame (x̂_u, n × x̂_u):
  τ = (M − (F/E) L) / (√E · √(G − F²/E)), L = z_uu/W, M = z_uv/W;
* the shear F = z_u z_v supplies the part f(u) + g(v) that Brioschi's formula leaves free.

On a graph-mapped saddle turned by 30° (R 50 mm) this takes the mean node error from 0.27 to
0.026 mm; see docs/reconstruction.md, step 2b.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .engine import GraphTwist, graph_slopes, quartic_value, sign_decided, slope_twist_quartic
from .grid import FineGrid

__all__ = ["graph_sheet_fields", "free_part", "RESIDUAL_LIMIT", "SlopeNoise", "slope_noise"]

# Share of the stretch pattern (Σ (E − 1)² + (G − 1)² over the cell-centre region) the refined
# graph may leave unexplained.  Measured: quadratic graphs (saddles at any angle, twisted domes,
# troughs; slopes up to 1) leave 0.0002-0.003, a Gaussian bump near the edge, whose slopes the
# gauge averages do not resolve, 0.13-0.2.
RESIDUAL_LIMIT = 0.02
# Seeded noise draws that measure how unit noise reaches the stretch misfit of the graph's
# slopes (:func:`slope_noise`): 64 give its mean and spread to about a tenth.
NOISE_DRAWS, NOISE_SEED = 64, 20261205
# Of the stretch misfit the best twist leaves, the noise's share is taken as up to its mean and
# NOISE_FLOOR_SDS s.d. (measured: the misfit's own spread over noise draws is up to about twice
# what the linear draws give, its tail heavy: the slopes' noise is a random walk from the centre)
NOISE_FLOOR_SDS = 2.0
# A twist must remove more misfit than fitting one parameter to the noise alone does, by this
# factor of that mean reduction (3 s.d. of a χ² with one degree of freedom)
CHANCE_FACTOR = 9.0


class SlopeNoise(NamedTuple):
    """Unit-noise draws (``NOISE_DRAWS``, the inner region's cells flattened) of the graph's
    slopes p, q (per unit turning s.d.) and of E − 1, G − 1 (per unit stretch s.d.), through one
    geometry's all-valid field maps, with the products the misfit's expansion needs: what
    :func:`graph_sheet_fields` weighs the stretch misfit against."""

    p: np.ndarray
    q: np.ndarray
    e1: np.ndarray
    g1: np.ndarray
    e1_p: np.ndarray  # e1·p, cell by cell
    g1_q: np.ndarray
    p2: np.ndarray    # p²
    q2: np.ndarray
    e1_sq: np.ndarray  # Σ e1² over the cells, per draw
    g1_sq: np.ndarray

    def residual_draws(self, z_u: np.ndarray, z_v: np.ndarray, turning_sd: float,
                       stretch_sd: float) -> tuple[np.ndarray, np.ndarray]:
        """The noise's part of the residuals e1 − z_u², g1 − z_v² (draws, cells) at slopes
        ``z_u``, ``z_v`` (the inner region) for unit noise of these s.d., to first order in the
        noise."""
        zu, zv = np.ravel(z_u), np.ravel(z_v)
        return (stretch_sd * self.e1 - (2.0 * turning_sd) * zu * self.p,
                stretch_sd * self.g1 - (2.0 * turning_sd) * zv * self.q)

    def misfit_noise(self, z_u: np.ndarray, z_v: np.ndarray, u: np.ndarray, v: np.ndarray, turning_sd: float,
                     stretch_sd: float) -> tuple[float, float, float, float]:
        """(floor, chance, twist s.d., mean) of the stretch misfit Σ (e1 − z_u²)² + (g1 − z_v²)²
        over the inner region (the sums of :meth:`residual_draws`' squares, expanded into
        products with the slopes): the share of the misfit the noise leaves (its mean and
        NOISE_FLOOR_SDS s.d. over the draws), the reduction fitting the constant twist to the
        noise alone achieves (CHANCE_FACTOR times its mean), the s.d. of the twist so fitted
        (1/mm, to first order), and the misfit's mean over the draws."""
        zu, zv, uu, vv = np.ravel(z_u), np.ravel(z_v), np.ravel(u), np.ravel(v)
        a, b = stretch_sd, 2.0 * turning_sd
        misfit = (a * a * (self.e1_sq + self.g1_sq) - 2.0 * a * b * (self.e1_p @ zu + self.g1_q @ zv)
                  + b * b * (self.p2 @ (zu * zu) + self.q2 @ (zv * zv)))
        floor = float(misfit.mean() + NOISE_FLOOR_SDS * misfit.std())
        j_e, j_g = zu * vv, zv * uu  # the residuals' derivatives in the twist, over −2
        norm = float(j_e @ j_e + j_g @ j_g)
        if not norm > 0.0:
            return floor, math.inf, math.inf, float(misfit.mean())
        along = a * (self.e1 @ j_e + self.g1 @ j_g) - b * (self.p @ (zu * j_e) + self.q @ (zv * j_g))
        power = float((along * along).mean())
        # (the twist's step for residuals r: Σ J r / (2 Σ J²), the derivatives being −2 J)
        return floor, CHANCE_FACTOR * power / norm, math.sqrt(power) / (2.0 * norm), float(misfit.mean())


def slope_noise(grid: FineGrid, maps) -> SlopeNoise:
    """The :class:`SlopeNoise` of a geometry, from its all-valid field ``maps``
    (``FineGrid.field_maps``), on seeded draws (the same every time: a log replays bit for bit)."""
    rng = np.random.default_rng(NOISE_SEED)
    shape = (2, grid.n, grid.m)
    inner = grid.inner
    ones, zeros = np.ones(shape), np.zeros(shape)
    step = 1e-3  # the stretch fields' response, read on a small step (λ² − 1 is nearly linear)
    ps, qs, es, gs = [], [], [], []
    for _ in range(NOISE_DRAWS):
        k_uu, k_vv, tau_var = maps(rng.normal(0.0, 1.0, shape), ones)[:3]
        p, q = graph_slopes(grid, k_uu, k_vv, tau_var - tau_var.mean())
        ps.append(p[inner].ravel())
        qs.append(q[inner].ravel())
        lam_u, lam_v = maps(zeros, 1.0 + step * rng.normal(0.0, 1.0, shape))[3:5]
        es.append(((lam_u * lam_u - 1.0) / step)[inner].ravel())
        gs.append(((lam_v * lam_v - 1.0) / step)[inner].ravel())
    p_d, q_d, e_d, g_d = (np.array(x) for x in (ps, qs, es, gs))
    return SlopeNoise(p_d, q_d, e_d, g_d, e_d * p_d, g_d * q_d, p_d * p_d, q_d * q_d,
                      (e_d * e_d).sum(axis=1), (g_d * g_d).sum(axis=1))


def free_part(f: np.ndarray) -> np.ndarray:
    """The part a(u) + b(v) of a field (nf, mf) in least squares: the row and column means
    (what a mixed derivative ∂_uv does not see)."""
    col = f.mean(axis=0, keepdims=True)
    row = f.mean(axis=1, keepdims=True)
    return col + row - col.mean()


def graph_sheet_fields(
    grid: FineGrid,
    maps,
    turning: np.ndarray,
    stretch: np.ndarray,
    graph: GraphTwist,
    stretch_sq: tuple[np.ndarray, np.ndarray],
    passes: int = 1,
    noise: SlopeNoise | None = None,
    noise_sd: tuple[float, float] = (0.0, 0.0),
    want_twist_sd: bool = True,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Twist field τ (nf, mf) and shear F = z_u z_v (nf, mf) of the graph, its slopes refined
    from the linear-fit slopes in ``graph`` by ``passes`` rescaled fits; None when the refined
    graph does not explain the stretch pattern (left over: ``RESIDUAL_LIMIT`` of it or more).

    ``maps``: the field maps of this frame's validity mask (``FineGrid.field_maps``);
    ``turning``, ``stretch``: the unit data (2, N, M) as ``engine.unit_data`` gives them;
    ``stretch_sq``: the fitted E − 1 and G − 1 fields (nf, mf); ``noise``, ``noise_sd``: the
    geometry's :class:`SlopeNoise` and the data's turning and stretch noise s.d. per unit, which
    the twist's trust weighs the stretch misfit against (None: noise-free data); with them, the
    third item is the constant twist's s.d. from that noise where the twist is trusted whole and
    the refined slopes decide its sign (1/mm of the slopes' twist), else NaN; with
    ``want_twist_sd`` False it is not computed (NaN), nor the noise's share where the fixed
    share already trusts the twist whole.
    """
    v = grid.v[:, None]
    u = grid.u[None, :]
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {passes!r}")
    inner = grid.inner
    e1, g1 = stretch_sq[0][inner], stretch_sq[1][inner]
    total = float((e1 * e1).sum() + (g1 * g1).sum())
    c = graph.slope_twist
    p, q = graph.p, graph.q
    for _ in range(passes):
        z_u, z_v = p + c * v, q + c * u
        w = np.sqrt(1.0 + z_u * z_u + z_v * z_v)
        lam_u, lam_v = np.sqrt(1.0 + z_u * z_u), np.sqrt(1.0 + z_v * z_v)
        # the height's second derivatives are the data scaled by W λ (gauge averages of it)
        scale = np.concatenate([grid.average[0] @ (w * lam_u).ravel(), grid.average[1] @ (w * lam_v).ravel()])
        k_uu, k_vv, tau_var = maps(turning * scale.reshape(turning.shape), stretch)[:3]
        tau_var = tau_var - tau_var.mean()
        p, q = graph_slopes(grid, k_uu, k_vv, tau_var)
        k = slope_twist_quartic(p[inner], q[inner], e1, g1, u[:, inner[1]], v[inner[0]])
        c = _local_minimum(k, c)
    # A constant twist is trusted in proportion to the share of the stretch misfit it removes:
    # fully from 80 %, not at all below 50 % (then the slopes' own errors, e.g. a bump the gauges
    # do not resolve, could be absorbed into a small twist that bends a large sheet's far corners).
    # The misfit the noise leaves is no error a twist could absorb: the share is of the misfit
    # beyond it, where the twist removes more than fitting it to the noise alone would (a noisy
    # 16×16 saddle of R 293 mm 1° off the rows, twist 1.2·10⁻⁴ /mm: its best twist left 0.003-0.01
    # of a misfit of 0.012-0.019 with none, the noise's share 0.004 ± 0.0013: trusted 0-0.7 of
    # it, the sheet 0.18-0.27 mm off; noise-free 1·10⁻⁴, trusted fully, 0.012 mm)
    best, zero = quartic_value(k, c), quartic_value(k, 0.0)
    trust = min(max((zero / max(best, 1e-300) - 2.0) / 3.0, 0.0), 1.0)
    twist_sd = math.nan
    if noise is not None and (noise_sd[0] > 0.0 or noise_sd[1] > 0.0) and (trust < 1.0 or want_twist_sd):
        cols, rows = u[:, inner[1]], v[inner[0]]
        floor, chance, sd, mean = noise.misfit_noise((p + c * v)[inner], (q + c * u)[inner],
                                                     np.broadcast_to(cols, (rows.shape[0], cols.shape[1])),
                                                     np.broadcast_to(rows, (rows.shape[0], cols.shape[1])), *noise_sd)
        removed, beyond = zero - best, best - floor
        if removed > chance:
            trust = 1.0 if beyond <= 0.0 else max(trust, min(max((removed / beyond - 1.0) / 3.0, 0.0), 1.0))
        # (its sign decided by the refined slopes, as engine._graph_twist decides it on the
        # linear fit's: a 16×16 saddle 0.7° off the rows left 0.065 and 0.105 on the linear
        # slopes, 0.0056 and 0.044 refined)
        if want_twist_sd and trust == 1.0 and mean > 0.0 and sign_decided(best, quartic_value(k, -c), total):
            # a twist trusted whole, its sign the data's: its own noise (one shrunk is not the
            # data's alone), scaled by the misfit it leaves over the noise's (a graph that
            # misfits beyond the noise reads its twist worse than the noise alone would say)
            twist_sd = sd * math.sqrt(max(best / mean, 1.0))
    c *= trust
    if not quartic_value(k, c) < RESIDUAL_LIMIT * total:
        return None
    z_u, z_v = p + c * v, q + c * u
    w = np.sqrt(1.0 + z_u * z_u + z_v * z_v)
    e, f, g = 1.0 + z_u * z_u, z_u * z_v, 1.0 + z_v * z_v
    ell, m = -k_uu / w, (tau_var + c) / w
    tau = (m - (f / e) * ell) / np.sqrt(e * g - f * f)
    return tau, f, twist_sd


def _local_minimum(k: tuple[float, ...], c: float, steps: int = 8) -> float:
    """Newton steps on the quartic's derivative from ``c`` (the slopes barely move the minimum);
    ``c`` itself when a step would leave the basin (no positive curvature), change the sign or
    raise the cost."""
    k4, k3, k2, k1, _ = k
    x = c
    for _ in range(steps):
        d1 = ((4.0 * k4 * x + 3.0 * k3) * x + 2.0 * k2) * x + k1
        d2 = (12.0 * k4 * x + 6.0 * k3) * x + 2.0 * k2
        if not d2 > 0.0:
            return c
        step = d1 / d2
        x -= step
        if abs(step) <= 1e-12 * max(abs(x), 1e-9):
            break
    # never across zero: the sign was chosen by the data's mirror test or by the caller
    return x if x * c > 0.0 and quartic_value(k, x) <= quartic_value(k, c) else c
