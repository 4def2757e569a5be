"""Strains → surface: the reconstruction pipeline (see docs/reconstruction.md).

1. decouple every unit into its turning per material length Θ/g and stretch L/g;
2. a bending potential z on a fine material grid, whose curvatures k_u = −z_uu, k_v = −z_vv
   have gauge averages matching the turning data (least squares + a smoothness prior); its
   mixed derivative gives the twist τ = z_uv that the gauges do not measure, consistent with
   the linearised Codazzi equations.  The stretch fields λ_u, λ_v are smoothed likewise;
3. the constant part of the twist (left free by the data) from the Gauss equation, and the
   shear angle γ between the material lines (unmeasured) from Brioschi's formula;
4. the orthonormal frame field (x̂_u, n × x̂_u, n) integrated from its rotation rates along a
   tree, then made consistent by linearised least-squares rotation corrections;
5. positions from the chords of every fine edge by least squares (a fixed graph Laplacian).

Every linear system's matrix depends only on the geometry, so its factorisation is cached and
a frame costs a few matrix-vector products and vectorised rotation algebra.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .decouple import decouple
from .grid import FineGrid
from .linalg import cayley_t, diff_u_t, diff_v_t, edge_mean, exp_so3_t, matmul_t

_EYE3 = np.eye(3)

__all__ = [
    "unit_data",
    "potential_curvatures",
    "metric_terms",
    "Metric",
    "solve_twist",
    "least_shear_noise",
    "least_shear_square",
    "stretch_variance",
    "TwistResult",
    "GraphTwist",
    "graph_slopes",
    "slope_twist_quartic",
    "solve_shear",
    "rotation_rates",
    "integrate_frames",
    "integrate_positions",
]


def unit_data(
    eps_upper: np.ndarray, eps_lower: np.ndarray, h_upper: float, h_lower: float, gauge_length: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per unit (2, N, M): mean turning per material length Θ/g, stretch ratio L/g, validity."""
    kappa, eps_s = decouple(eps_upper, eps_lower, h_upper, h_lower)
    valid = np.isfinite(kappa) & np.isfinite(eps_s)
    stretch = np.where(valid, 1.0 + eps_s, 1.0)
    turning = np.where(valid, kappa * stretch, 0.0)  # Θ/g = κ̂ L/g
    return turning, stretch, valid


def potential_curvatures(grid: FineGrid, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """k_u = −z_uu, k_v = −z_vv, τ = z_uv on the fine grid from a bending potential z."""
    shape = (grid.nf, grid.mf)
    return -(grid.z_uu @ z).reshape(shape), -(grid.z_vv @ z).reshape(shape), (grid.z_uv @ z).reshape(shape)


def solve_twist(
    grid: FineGrid,
    k_u: np.ndarray,
    k_v: np.ndarray,
    tau0: np.ndarray,
    lam_u: np.ndarray,
    lam_v: np.ndarray,
    twist_sign: float = 1.0,
    turning_sigma: float = 0.0,
    metric: Metric | None = None,
    stretch_sigma: float = 0.0,
    sign_from_data: bool = True,
    product_noise: tuple[float, float] | None = None,
    quiet: float = 1.0,
    open_spread: float | None = None,
    stretch_dev2: float | None = None,
    shear_noise: float = 0.0,
) -> "TwistResult":
    """Twist field τ: the potential's twist (made zero-mean) plus a constant from the Gauss
    equation K = k_u k_v − τ².

    A positive product k_u k_v is attributed to a constant twist only in proportion to how
    little the stretch varies (a developable sheet, e.g. an oblique cylinder) and once it exceeds
    what the turning noise ``turning_sigma`` (per length, one unit) can produce; otherwise a
    saddle turned off the grid lines is looked for: first as a sheet pushed out of plane
    (:func:`_graph_twist`, whose stretch pattern usually fixes the sign too), else from the shear
    it needs (:func:`_saddle_twist`).  Where the sign is not observable (mirror-image twists give
    identical strains, e.g. an oblique cylinder) ``twist_sign`` chooses it; it also overrides a
    sign read from the data when ``sign_from_data`` is False.  ``stretch_sigma``: stretch noise
    s.d. of one unit.  ``product_noise``: (bias, s.d.) of the mean product k_u k_v − τ₀² that
    the turning noise alone causes (:mod:`.productnoise`; the bias is removed before the product
    is read as a twist); without it, independent noise on every node is assumed.  ``quiet``: the
    share of that noise the data themselves show, where they show clearly less (a positive
    product is read against that share; the search for a turned saddle keeps the stated noise,
    whose product has no sign to read).  ``open_spread``: the product's s.d. that the twist left
    open is judged with, where it is read otherwise than the twist taken (the fields' own,
    where the gauge pairs' reading sets what is taken: ``Reconstructor._pair_reading``).
    ``stretch_dev2``: the measured stretch's variance over the cells' region where the stretch
    fields given are not the gauges' (a defect pass's corrected input).  ``shear_noise``: three
    s.d. of the least-shear square of a turned saddle's twist that the stretch noise causes
    (:func:`least_shear_noise` times the stretch s.d. and 3); the search for a turned saddle
    reads its square against that and the product's noise together.  Returns the τ
    field and its constant without the graph refinement, the graph model
    (:class:`GraphTwist`) when the stretch pattern suggests one, and the twist the product
    allows where its noise shrank the one taken, or hides where none was taken (``open``).
    """
    tau0 = tau0 - tau0.sum() / tau0.size
    shear_open = 0.0  # the twist a least-shear square within its noise hides
    # Only the region spanned by the cell centres: one-sided differences at the border would
    # bias the estimates.
    inner = grid.inner
    ku_in, kv_in = k_u[inner], k_v[inner]
    count = ku_in.size
    # A doubly curved sheet (K ≠ 0) cannot be laid flat without stretching by about K ρ²/12
    # over a half-size ρ; a developable one needs none.  Attribute positive k_u k_v to a constant
    # twist only in proportion to how little the stretch varies.
    prod, need, dev2 = _stretch_need(grid, k_u, k_v, tau0, lam_u, lam_v)
    if stretch_dev2 is not None:
        dev2 = stretch_dev2
    if product_noise is not None:
        # the noise's own share of the product is no curvature (a flat noisy sheet is no cylinder)
        bias, spread = product_noise
        prod = prod - bias
        need = abs(prod) * _half_size2(grid) / 12.0
        noise = 3.0 * spread
    else:
        # three s.d. of the mean product when each unit's turning carries independent noise
        n_units = grid.n * grid.m
        curv_rms = math.sqrt(float((ku_in * ku_in).sum() + (kv_in * kv_in).sum()) / count)
        noise = 3.0 * (turning_sigma * curv_rms + turning_sigma**2) / math.sqrt(n_units)
    dev = math.sqrt(max(dev2 - stretch_sigma**2, 0.0))  # the noise's own share removed, as stretch_supports_curvature
    ratio = dev / need if need > 0 else math.inf
    weight = min(max(1.5 - 3.0 * ratio, 0.0), 1.0)
    # unbiased above twice the noise level, off below it, continuous in between
    read = noise * quiet
    significance = min(max(prod / read - 1.0, 0.0), 1.0) if read > 0 else float(prod > 0)
    c2 = max(prod, 0.0) * weight * significance
    graph = None
    from_shear = False
    if prod <= read or weight < 1.0:
        # not a developable sheet: a sheet pushed out of plane (a graph) may explain its twist
        # through the stretch pattern, whatever the sign of k_u k_v (a turned saddle, a twisted
        # dome, an oblique trough pressed into a clamped film); the caller refines it and
        # keeps it only if the refined graph explains the stretch (graphsheet.py)
        if metric is None:
            metric = metric_terms(grid.spacing, lam_u, lam_v)
        graph = _graph_twist(grid, k_u, k_v, tau0, inner, metric, stretch_sigma)
        if graph is not None and (not graph.decisive or not sign_from_data):
            graph = graph._replace(
                constant=math.copysign(graph.constant, twist_sign), slope_twist=math.copysign(graph.slope_twist, twist_sign)
            )
        if prod <= read:  # no positive curvature product to explain: look for a turned saddle
            if graph is not None and graph.significant:
                return TwistResult(tau0 + graph.constant, graph.constant, graph)
            c2, clipped, square = _saddle_twist(grid, k_u, k_v, lam_u, lam_v, tau0, inner,
                                                math.hypot(noise, shear_noise), metric)
            # the search's answer is the least-shear prior's alone; so is none where the prior
            # asked for a negative square beyond the noise (a film with friction on a saddle 11°
            # off the rows: -4·10⁻⁶ /mm², the twist taken none for 1.3·10⁻³ /mm)
            from_shear = c2 > 0.0 or clipped
            if c2 == 0.0 and not clipped:
                # nor is a least-shear square within its noise a proof of no twist: the twist one
                # s.d. beyond it hides (a saddle 45° off the rows has no bend along them, and
                # its twist reaches the gauges only through the stretch: on 5×5, R 2000-3000 mm,
                # 3.3-5·10⁻⁴ /mm, stood 1.2-1.7 times beyond 3σ + 0.05 mm)
                spread = math.hypot(noise, shear_noise) / 3.0
                hidden = (max(square, 0.0) + spread if square >= -spread else spread * spread / -square)
                shear_open = math.sqrt(hidden)
    c = math.copysign(math.sqrt(c2), twist_sign)
    # a product the data show (beyond 1 s.d. of its noise) but the significance test shrank:
    # the twist it would be, and one s.d. of the product beyond, is not ruled out (a cylinder 6°
    # off the grid lines, whose twist of 0.0015 /mm reads 2-4 s.d. of the product's noise; on
    # one draw in 8 the product read 2.4 s.d. low)
    # (the stretch's verdict on developability counts only where the stretch a doubly curved
    # sheet would need exceeds three of its noise s.d.: below that its variation is the noise's)
    # (judged at the noise of the product's other reading where the twist was read from the gauge
    # pairs: a sharper reading takes more twists, it rules none out that the fields' noise
    # leaves open: a 12×12 film pre-stretched 5 % on a cylinder 6.8° off the columns, whose
    # stretch varies with the pre-stretch, read its product at 6.3 s.d. by the pairs, took no
    # twist and left none open, 0.98 mm off with σ 0.056)
    if open_spread is None:
        open_noise, open_significance = noise, significance
    else:
        open_noise = 3.0 * open_spread
        open_read = open_noise * quiet
        open_significance = min(max(prod / open_read - 1.0, 0.0), 1.0) if open_read > 0 else float(prod > 0)
    allowed = max(prod, 0.0) * (weight if need > 3.0 * stretch_sigma else 1.0)
    opened = (math.sqrt(allowed + open_noise / 3.0) if open_significance < 1.0 and prod > open_noise / 3.0
              and c2 < allowed else 0.0)
    if c2 == 0.0 and graph is None and prod <= open_noise / 3.0 and (weight == 1.0 or need <= 3.0 * stretch_sigma):
        # nor is a product within one s.d. of its noise a proof of no twist, on a sheet the
        # stretch cannot call doubly curved: the twist one s.d. of the product hides (a 5 %
        # pre-stretched cylinder 4.9° off the rows: a twist of 0.0009 /mm reads 0.8 s.d.)
        opened = math.sqrt(max(prod, 0.0) + open_noise / 3.0)
    opened = max(opened, shear_open)
    # the significance ramp's gain on the product's noise: inside the ramp d(c²)/d(product) is
    # weight · (significance + product/read), 2 at its middle, where the s.d. through c = √product
    # takes 1 (the weight left out: it only lowers it)
    ramp = significance + prod / read if 0.0 < significance < 1.0 and c2 > 0.0 else 1.0
    return TwistResult(tau0 + c, c, graph, opened, from_shear, prod, ramp)


def _integrate_from(f: np.ndarray, start: int, h: float) -> np.ndarray:
    """Trapezoid integral of samples ``f`` (along axis 0, spacing ``h``) from index ``start``."""
    mid = (0.5 * h) * (f[1:] + f[:-1])
    out = np.zeros_like(f)
    out[start + 1 :] = mid[start:].cumsum(axis=0)
    out[:start] = -mid[:start][::-1].cumsum(axis=0)[::-1]
    return out


class GraphTwist(NamedTuple):
    """A sheet pushed out of plane, as its stretch pattern suggests: the frame model's constant
    twist per material length, whether the data decide its sign, and the graph's own slopes
    (z_u = p + c v, z_v = q + c u on the whole fine grid, with c = ``slope_twist``)."""

    constant: float
    decisive: bool
    significant: bool  # the twist removes most of the stretch misfit of no twist
    slope_twist: float
    p: np.ndarray
    q: np.ndarray


class TwistResult(NamedTuple):
    """The twist field and its constant part, and the graph model when the stretch suggests one."""

    tau: np.ndarray
    constant: float
    graph: GraphTwist | None
    # the twist magnitude the curvature product allows where the noise's significance shrank
    # what was taken below it (the product beyond 1 s.d. of its noise), or that one s.d. of it
    # hides where no twist was taken and the stretch cannot call the sheet doubly curved; 0
    # otherwise
    open: float = 0.0
    # the constant (none included) came from the least-shear prior of a turned saddle
    # (_saddle_twist), which no datum confirms: a film on a mold shears otherwise
    from_shear: bool = False
    # the mean curvature product k_u k_v − τ₀² read (the noise's own part removed); less the
    # constant's square, the answer's mean Gaussian curvature
    product: float = 0.0
    # how much more the constant's square moves with the product than the product itself: the
    # significance ramp's slope where the constant was shrunk by it (1 elsewhere)
    ramp: float = 1.0


def graph_slopes(grid: FineGrid, k_u, k_v, tau0) -> tuple[np.ndarray, np.ndarray]:
    """Slopes p = z_u − c v, q = z_v − c u of the height z with z_uu = −k_u, z_vv = −k_v and
    zero-mean twist ``tau0`` (integrated from the centre: along its column, then the rows)."""
    h = grid.spacing
    a0, b0 = grid.centre
    p = _integrate_from(tau0[:, b0], a0, h)[:, None] - _integrate_from(k_u.T, b0, h).T
    q = _integrate_from(tau0[a0, :], b0, h)[None, :] - _integrate_from(k_v, a0, h)
    return p, q


def slope_twist_quartic(p, q, e1, g1, u, v) -> tuple[float, float, float, float, float]:
    """Coefficients (highest first) of the quartic cost(c) = Σ (e1 − (p + c v)²)² + (g1 − (q + c u)²)²
    (``v`` a column, ``u`` a row of the grid's coordinates)."""
    # residuals r0 + r1 c + r2 c² with r0 = e1 − p², r1 = −2 p v, r2 = −v² (and q, u alike);
    # the sums written out (no stacked temporaries: this runs on every stretched frame)
    vv, uu = v * v, u * u
    r0e, r0g = e1 - p * p, g1 - q * q
    pv, qu = p * v, q * u
    k4 = p.shape[1] * float((vv * vv).sum()) + q.shape[0] * float((uu * uu).sum())
    k3 = 4.0 * float((pv * vv).sum() + (qu * uu).sum())
    k2 = 4.0 * float((pv * pv).sum() + (qu * qu).sum()) - 2.0 * float((r0e * vv).sum() + (r0g * uu).sum())
    k1 = -4.0 * float((r0e * pv).sum() + (r0g * qu).sum())
    k0 = float((r0e * r0e).sum() + (r0g * r0g).sum())
    return k4, k3, k2, k1, k0


def quartic_value(k: tuple[float, ...], c: float) -> float:
    k4, k3, k2, k1, k0 = k
    return (((k4 * c + k3) * c + k2) * c + k1) * c + k0


def _cubic_real_roots(a: float, b: float, c: float, d: float) -> list[float]:
    """Real roots of a x³ + b x² + c x + d (a ≠ 0) in closed form: the root of largest
    magnitude (Cardano, or the trigonometric form for three real roots), Newton-polished, then
    the others from the deflated quadratic in its cancellation-free form (np.roots' eigenvalue
    solve costs 60 µs here)."""
    b, c, d = b / a, c / a, d / a
    shift = -b / 3.0
    p = c - b * b / 3.0
    q = (2.0 * b * b * b - 9.0 * b * c) / 27.0 + d
    disc = 0.25 * q * q + p * p * p / 27.0
    if disc > 0.0 or p == 0.0:
        sq = math.sqrt(max(disc, 0.0))
        x = math.copysign(abs(-0.5 * q + sq) ** (1.0 / 3.0), -0.5 * q + sq)
        x += math.copysign(abs(-0.5 * q - sq) ** (1.0 / 3.0), -0.5 * q - sq)
        x += shift
    else:
        r = 2.0 * math.sqrt(-p / 3.0)
        phi = math.acos(min(max(3.0 * q / (p * r), -1.0), 1.0)) / 3.0
        x = max((r * math.cos(phi - 2.0 * math.pi * k / 3.0) + shift for k in range(3)), key=abs)

    def polish(x: float) -> float:
        for _ in range(3):
            f, df = ((x + b) * x + c) * x + d, (3.0 * x + 2.0 * b) * x + c
            if df == 0.0:
                break
            x -= f / df
        return x

    x = polish(x)
    if x == 0.0:  # d = 0: the others solve x² + b x + c = 0
        big, small = b, c
    else:
        # (x − x₁)(x² + B x + C): C from the constant term, B from the linear one (x₁ is the
        # largest root, so neither divides by a small number nor cancels)
        small = -d / x
        big = (small - c) / x
    disc2 = big * big - 4.0 * small
    if disc2 < 0.0:
        return [x]
    w = -0.5 * (big + math.copysign(math.sqrt(disc2), big))
    others = [w, small / w] if w != 0.0 else [0.0]
    return [x] + [polish(y) for y in others]


def _fit_slope_twist(p, q, e1, g1, u, v) -> tuple[float, float, float, float] | None:
    """c minimising Σ (e1 − (p + c v)²)² + (g1 − (q + c u)²)²: (c, cost(c), cost(0), cost(−c)),
    or None for a degenerate quartic."""
    k = slope_twist_quartic(p, q, e1, g1, u, v)
    if not k[0] > 0.0:
        return None
    roots = _cubic_real_roots(4.0 * k[0], 3.0 * k[1], 2.0 * k[2], k[3])
    c = min(roots, key=lambda r: quartic_value(k, r))
    return c, quartic_value(k, c), quartic_value(k, 0.0), quartic_value(k, -c)


def sign_decided(best: float, mirror: float, total: float) -> bool:
    """Whether the stretch pattern decides a graph's twist sign: the mirror twist's misfit
    ``mirror`` exceeds twice the best's ``best`` (and a thousandth of the pattern ``total``)."""
    return mirror > 2.0 * best + 1e-3 * total


def _graph_twist(grid: FineGrid, k_u, k_v, tau0, inner, metric: Metric, stretch_sigma: float) -> GraphTwist | None:
    """Signed constant twist of a sheet pushed out of plane (a graph over the centre's tangent
    plane), from its stretch pattern, or None when that model does not explain the stretch.

    For a graph, E − 1 = z_u² and G − 1 = z_v²; the slopes are those of the bending potential
    (integrated from the centre) plus the constant twist c: z_u = p + c v, z_v = q + c u.  The
    cross terms 2c·v·p, 2c·u·q make the stretch pattern depend on the sign of c, so unlike a
    developable twist (no stretch) the sign is observable wherever p, q do not vanish.  c
    minimises Σ ((E − 1) − (p + c v)²)² + ((G − 1) − (q + c u)²)² (a quartic: roots of its cubic
    derivative).  The constant the frame model needs is the twist per material length,
    z_uv/(W λ_u λ_v), averaged over the sheet (W² = 1 + |∇z|²).  Returns None unless the stretch
    stands well above its noise and the graph explains it (what is left is small); c may then be
    near zero (a saddle or dome on the grid lines), the graph's slopes still serve
    :func:`graphsheet.graph_sheet_fields`.
    """
    e1, g1 = (metric.e - 1.0)[inner], (metric.g - 1.0)[inner]
    if float(e1.mean() + g1.mean()) <= 20.0 * stretch_sigma:
        return None
    p_full, q_full = graph_slopes(grid, k_u, k_v, tau0)
    p, q = p_full[inner], q_full[inner]
    u = grid.u[inner[1]][None, :]
    v = grid.v[inner[0]][:, None]
    fit = _fit_slope_twist(p, q, e1, g1, u, v)
    if fit is None:
        return None
    c, best, zero, mirror = fit
    total = float((e1 * e1).sum() + (g1 * g1).sum())
    if not best < 0.2 * total:  # the graph leaves more than a fifth of the stretch unexplained
        return None
    decisive = sign_decided(best, mirror, total)
    slope2 = (p + c * v) ** 2 + (q + c * u) ** 2
    c_eff = c * float((1.0 / np.sqrt((1.0 + slope2) * metric.eg[inner])).mean())
    return GraphTwist(c_eff, decisive, best < 0.5 * zero, c, p_full, q_full)


def _saddle_twist(grid: FineGrid, k_u, k_v, lam_u, lam_v, tau0, inner, noise: float, metric: Metric
                  ) -> tuple[float, bool, float]:
    """Squared constant twist of a sheet whose stretch pattern needs negative Gaussian curvature
    (a saddle turned off the grid lines: small k_u k_v, strongly varying stretch).

    Without twist, Brioschi's formula asks for a shear F = F₀; a twist c adds −c²·EG to its
    source, so F = F₀ − c² F₁.  The least-shear c² (least squares over the cell-centre region)
    bounds the answer; it is right for a sheet whose material lines stay orthogonal, but a sheet
    pushed out of plane (material points moving along the normal of the base plane, as a
    membrane) shears with F² = (E − 1)(G − 1).  The c² in [0, least-shear] that best meets
    F(c²)² = (E − 1)(G − 1) covers both: with no stretch (E = G = 1) it is the least-shear
    value.  A twist is used only when the least-shear fit removes most of the shear (a uniform
    twist, as on a saddle, not the local shear around a bump) and stands above the noise.
    Also returns whether the least-shear square is negative beyond the noise while explaining
    most of the shear as well: no twist can give it, the shear is not the prior's (in-plane
    loads), and the none returned is the prior's boundary, not a reading; and the least-shear
    square itself (0 where no twist shears the sheet).
    """
    f0, f1, x = least_shear_square(grid, k_u, k_v, lam_u, lam_v, tau0, inner, metric)
    if x is None:
        return 0.0, False, 0.0
    den = float((f1 * f1).sum())
    explained = x * x * den / max(float((f0 * f0).sum()), 1e-300)
    weight = min(max((explained - 0.5) / 0.3, 0.0), 1.0)
    significance = min(max(abs(x) / noise - 1.0, 0.0), 1.0) if noise > 0 else 1.0
    if x <= 0.0:
        return 0.0, weight * significance > 0.0, x
    if weight * significance == 0.0:
        return 0.0, False, x
    # Σ ((f₀ − x f₁)² − P)² over x ∈ [0, x_ls]: a quartic; its stationary points are the roots
    # of the cubic below (g = a x² + b x + c, cost' = 2 Σ g g')
    a, b = f1 * f1, -2.0 * f0 * f1
    c = f0 * f0 - ((metric.e - 1.0) * (metric.g - 1.0))[inner]
    cubic = [2.0 * float((a * a).sum()), 3.0 * float((a * b).sum()), float((b * b + 2.0 * a * c).sum()), float((b * c).sum())]
    roots = np.roots(cubic) if cubic[0] > 0 else np.empty(0)
    cands = np.array([0.0, x, *(r.real for r in roots if abs(r.imag) <= 1e-12 * abs(r) and 0.0 < r.real < x)])
    g = a[None] * cands[:, None, None] ** 2 + b[None] * cands[:, None, None] + c[None]
    best = float(cands[np.argmin((g * g).sum(axis=(1, 2)))])
    return best * weight * significance, False, x


def least_shear_square(grid: FineGrid, k_u, k_v, lam_u, lam_v, tau0, inner, metric: Metric
                        ) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Brioschi's shear without twist F₀ and the twist's part F₁ over the cells' region, and the
    least-shear square of the constant twist, Σ F₀F₁ / Σ F₁² (None where F₁ vanishes)."""
    h = grid.spacing
    eg = metric.eg
    src0 = metric.source0 + (k_u * k_v / (lam_u * lam_v) - tau0 * tau0) * eg
    f0, f1 = _mixed_antiderivative((h * h) * _cell_mean(np.array([src0, eg])))
    f0, f1 = f0[inner], f1[inner]
    den = float((f1 * f1).sum())
    return f0, f1, (float((f0 * f1).sum()) / den if den > 0.0 else None)


#: Seeded draws of :func:`least_shear_noise` (the same every time: a log replays bit for bit).
SHEAR_NOISE_DRAWS, SHEAR_NOISE_SEED = 64, 20261207


def least_shear_noise(grid: FineGrid, maps) -> float:
    """The s.d. of the least-shear square of the twist (:func:`_saddle_twist`'s reading) that
    stretch noise of unit s.d. on every unit causes on a flat sheet, from the all-valid field
    ``maps`` (``FineGrid.field_maps``) on seeded draws, read on a small step (the square is
    linear in the stretch there: Brioschi's source takes the metric's second derivatives).  The
    turning's noise reaches it through the curvature product, whose s.d. is measured apart
    (:mod:`.productnoise`); the stretch's reaches it through the metric, and on a 5×5 sheet it is
    the larger part by far (1.1·10⁻⁷ /mm² at the sensor's noise, against the product's 1.7·10⁻⁸)."""
    rng = np.random.default_rng(SHEAR_NOISE_SEED)
    shape = (2, grid.n, grid.m)
    zeros = np.zeros(shape)
    step = 1e-4
    squares = []
    for _ in range(SHEAR_NOISE_DRAWS):
        k_u, k_v, tau0, lam_u, lam_v = maps(zeros, 1.0 + step * rng.normal(0.0, 1.0, shape))[:5]
        metric = metric_terms(grid.spacing, lam_u, lam_v)
        x = least_shear_square(grid, k_u, k_v, lam_u, lam_v, tau0 - tau0.mean(), grid.inner, metric)[2]
        squares.append(0.0 if x is None else x / step)
    return math.sqrt(float(np.mean(np.square(squares))))


def _mixed_antiderivative(cell: np.ndarray) -> np.ndarray:
    """Least-norm node fields F (..., nf, mf) whose mixed difference over every cell equals
    ``cell`` (..., nf−1, mf−1): a double cumulative sum solves it exactly; removing the row and
    column means (double centring) projects out the free part f(u) + g(v)."""
    f: np.ndarray = np.zeros(cell.shape[:-2] + (cell.shape[-2] + 1, cell.shape[-1] + 1))
    f[..., 1:, 1:] = cell.cumsum(axis=-2).cumsum(axis=-1)
    col_mean = f.sum(axis=-2, keepdims=True) * (1.0 / f.shape[-2])
    row_mean = f.sum(axis=-1, keepdims=True) * (1.0 / f.shape[-1])
    return f - col_mean - (row_mean - row_mean.sum(axis=-2, keepdims=True) * (1.0 / f.shape[-2]))


class Metric(NamedTuple):
    """First fundamental form terms that do not change with the shear F: E = λ_u², G = λ_v²,
    their first derivatives, EG, and Brioschi's F_uv source at F = 0 without the curvature
    term (E_vv/2 + G_uu/2 + Q(F = 0)/(EG))."""

    e: np.ndarray
    g: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    g_u: np.ndarray
    g_v: np.ndarray
    base: np.ndarray  # E_vv/2 + G_uu/2
    eg: np.ndarray
    source0: np.ndarray


def metric_terms(h: float, lam_u, lam_v) -> Metric:
    """The F-independent metric terms (:class:`Metric`) from the stretch fields."""
    e_g = np.array([lam_u * lam_u, lam_v * lam_v])
    (e_u, g_u), (e_v, g_v) = diff_u_t(e_g, h), diff_v_t(e_g, h)
    e, g = e_g
    base = 0.5 * (diff_v_t(e_v, h) + diff_u_t(g_u, h))
    eg = e * g
    # Q at F = 0: a12·a21·g + a13·e·a31 + det_b with a21 = −G_u/2, a13 = −E_v/2
    q0 = -0.25 * (e_u * g_u * g + e_v * e * g_v + e_v * e_v * g + e * g_u * g_u)
    return Metric(e, g, e_u, e_v, g_u, g_v, base, eg, base + q0 / eg)


def _brioschi_source(h: float, metric: Metric, f, k_gauss) -> np.ndarray:
    """F_uv that Brioschi's formula requires for Gaussian curvature ``k_gauss`` with
    E = λ_u², G = λ_v² and the current F: E_vv/2 + G_uu/2 + K (EG − F²) + Q/(EG − F²)."""
    e, g, e_u, e_v, g_u, g_v, base = metric[:7]
    f_u, f_v = diff_u_t(f, h), diff_v_t(f, h)
    det = metric.eg - f * f
    a12, a13 = 0.5 * e_u, f_u - 0.5 * e_v
    a21, a31 = f_v - 0.5 * g_u, 0.5 * g_v
    det_b = -0.5 * e_v * (0.5 * e_v * g - 0.5 * f * g_u) + 0.5 * g_u * (0.5 * e_v * f - 0.5 * e * g_u)
    q = a12 * (a21 * g - f * a31) - a13 * (a21 * f - e * a31) + det_b
    return base + k_gauss * det + q / det


def _cell_mean(f: np.ndarray) -> np.ndarray:
    """Mean of the four corners of every grid cell, over the last two axes."""
    s = f[..., :-1, :] + f[..., 1:, :]
    return 0.25 * (s[..., :-1] + s[..., 1:])


def least_shear_twists(grid: FineGrid, k_u, k_v, lam_u, lam_v, tau0, metric: Metric) -> list[tuple[float, float]]:
    """Constant twists c that locally minimise the in-plane shear the sheet needs, with their
    shear: [(c, mean F² over the cells' region)], lowest first.

    The gauges fix the stretch along the material lines (E, G) and the normal curvatures, not
    the shear F nor a constant twist c; each c gives a sheet that matches the data, with the
    shear that Gauss's equation then demands (Brioschi, one pass from F = 0: F is exactly
    F_a + c F_b + c² F_c since K carries −(τ₀ + c)²).  For fixed stretches the membrane energy
    of a film changes with c only through its shear term 2μ E_uv² = μ F²/2, whatever its Young's
    modulus and Poisson's ratio, so the least-shear twist is the least-energy sheet among those
    the data allow: the prior for the one parameter the data leave open.  ``tau0``: the
    zero-mean twist of the potential."""
    h = grid.spacing
    s11 = k_u / lam_u
    cell = lambda src: _mixed_antiderivative((h * h) * _cell_mean(src))[grid.inner]  # noqa: E731
    f_a = cell(metric.source0 + (s11 * k_v / lam_v - tau0 * tau0) * metric.eg)
    f_b = cell(-2.0 * tau0 * metric.eg)
    f_c = cell(-metric.eg)
    # mean (f_a + c f_b + c² f_c)² = q4 c⁴ + q3 c³ + q2 c² + q1 c + q0
    dot = lambda x, y: float((x * y).sum()) / x.size  # noqa: E731
    q4, q3 = dot(f_c, f_c), 2.0 * dot(f_b, f_c)
    q2, q1, q0 = dot(f_b, f_b) + 2.0 * dot(f_a, f_c), 2.0 * dot(f_a, f_b), dot(f_a, f_a)
    if q4 <= 0.0:
        return [(0.0, q0)]
    value = lambda c: (((q4 * c + q3) * c + q2) * c + q1) * c + q0  # noqa: E731
    roots = _cubic_real_roots(4.0 * q4, 3.0 * q3, 2.0 * q2, q1)
    minima = [c for c in roots if 12.0 * q4 * c * c + 6.0 * q3 * c + 2.0 * q2 > 0.0]
    return sorted(((c, value(c)) for c in minima), key=lambda t: t[1])


def _stretch_need(grid: FineGrid, k_u, k_v, tau, lam_u, lam_v) -> tuple[float, float, float]:
    """Over the cells' region: the mean Gaussian curvature k_u k_v − τ², the stretch variation
    it needs to be laid out (|K| ρ²/12, ρ² the mean squared half-size) and the measured
    stretch's variance."""
    inner = grid.inner
    ku_in, kv_in, t_in = k_u[inner], k_v[inner], tau[inner]
    count = ku_in.size
    gauss = float((ku_in * kv_in - t_in * t_in).sum()) / count
    rho2 = _half_size2(grid)
    return gauss, abs(gauss) * rho2 / 12.0, stretch_variance(grid, lam_u, lam_v)


def stretch_variance(grid: FineGrid, lam_u, lam_v) -> float:
    """The stretch fields' variance over the cells' region (the mean of the two directions')."""
    inner = grid.inner
    lu_in, lv_in = lam_u[inner], lam_v[inner]
    count = lu_in.size
    lu_dev, lv_dev = lu_in - lu_in.sum() / count, lv_in - lv_in.sum() / count
    return 0.5 * float((lu_dev * lu_dev).sum() + (lv_dev * lv_dev).sum()) / count


def _half_size2(grid: FineGrid) -> float:
    """Mean squared half-size ρ² of the cells' region."""
    return 0.25 * ((grid.u[grid.node_cols[-1]]) ** 2 + (grid.v[grid.node_rows[-1]]) ** 2)


def stretch_supports_curvature(grid: FineGrid, k_u, k_v, tau, lam_u, lam_v, stretch_sigma: float = 0.0) -> bool:
    """Whether the measured stretch varies as much as the Gaussian curvature of the sheet with
    twist field ``tau`` needs (at least half of it): a surface of curvature K over a half-size ρ
    cannot be laid out without stretch variations of about |K| ρ²/12, and a film is stretched
    no more than its shape forces (``stretch_sigma``: the noise s.d. of one unit's stretch,
    whose share of the variation is removed; variation of more than twice the need is
    attributed to loads and is no evidence either way).  A twist that trades that curvature for shear is then no
    better an answer (a sphere's gauges also fit a cylinder at 45°, with shear)."""
    _, need, dev2 = _stretch_need(grid, k_u, k_v, tau, lam_u, lam_v)
    dev = math.sqrt(max(dev2 - stretch_sigma**2, 0.0))  # the noise's own share removed
    # far more variation than the curvature needs has another cause (edge loads, a frame's
    # pre-stretch) and says nothing about the curvature
    return 0.5 * need <= dev <= 2.0 * need


def least_shear_value(grid: FineGrid, k_u, k_v, lam_u, lam_v, tau0, metric: Metric, c: float) -> float:
    """Mean F² over the cells' region of the sheet with zero-mean twist ``tau0`` plus ``c``
    (the measure :func:`least_shear_twists` minimises)."""
    h = grid.spacing
    tau = tau0 + c
    f = _mixed_antiderivative((h * h) * _cell_mean(metric.source0 + (k_u * k_v / (lam_u * lam_v) - tau * tau) * metric.eg))
    f = f[grid.inner]
    return float((f * f).sum()) / f.size


def solve_shear(
    grid: FineGrid, k_u, k_v, lam_u, lam_v, tau, iterations: int = 2, metric: Metric | None = None
) -> np.ndarray:
    """Sine of the shear angle γ (nf, mf) between x_v and the normal to x_u, from the Gauss
    equation (|sin γ| ≤ 0.9).

    The gauges measure E = λ_u² and G = λ_v² but not F = x_u·x_v.  Brioschi's formula is linear
    in F_uv:  F_uv = E_vv/2 + G_uu/2 + K (EG − F²) + Q(E, F, G, first derivatives)/(EG − F²),
    with K = det S from the curvature fields.  Fixed-point passes re-evaluate the right-hand side
    with the current F (the first from F = 0, whose source is precomputed in ``metric``); the
    least-norm solution fixes the part f(u) + g(v) that ∂_uv leaves free.
    """
    h = grid.spacing
    if metric is None:
        metric = metric_terms(h, lam_u, lam_v)
    s11 = k_u / lam_u
    lam_uv = lam_u * lam_v
    f = _mixed_antiderivative((h * h) * _cell_mean(metric.source0 + (s11 * k_v / lam_v - tau * tau) * metric.eg))
    for _ in range(max(1, iterations) - 1):
        sg = np.minimum(np.maximum(f / lam_uv, -0.9), 0.9)  # ufuncs: np.clip's wrapper costs more
        cg2 = 1.0 - sg * sg
        s22 = (k_v / lam_v - s11 * sg * sg + 2.0 * tau * sg * np.sqrt(cg2)) / cg2
        src = _brioschi_source(h, metric, f, s11 * s22 - tau * tau)
        f = _mixed_antiderivative((h * h) * _cell_mean(src))
    return np.minimum(np.maximum(f / lam_uv, -0.9), 0.9)


def rotation_rates(grid: FineGrid, k_u, k_v, lam_u, lam_v, tau, sin_gamma) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors (in the tail frame) of every u-edge and v-edge, components first:
    (3, E_u) and (3, E_v).

    The frame is e1 = x_u/|x_u|, e2 = n × e1, e3 = n; x_v = λ_v (sin γ e1 + cos γ e2).  With the
    shape operator S (convex positive) in (e1, e2): S11 = k_u/λ_u, S12 = −τ and S22 from the
    normal curvature along x_v; the in-plane rates are the Christoffel terms of the metric
    (E, F, G) = (λ_u², λ_u λ_v sin γ, λ_v²).
    """
    h = grid.spacing
    sg = sin_gamma
    cg = np.sqrt(1.0 - sg * sg)
    s11 = k_u / lam_u
    s22 = (k_v / lam_v - s11 * sg * sg + 2.0 * tau * sg * cg) / (cg * cg)
    lu_u, lv_u, f_u = diff_u_t(np.array([lam_u, lam_v, lam_u * lam_v * sg]), h)
    lu_v = diff_v_t(lam_u, h)
    inv = 1.0 / (lam_u * cg)
    w_u = np.array([lam_u * tau, lam_u * s11, ((f_u - lam_u * lu_v) / lam_v - sg * lu_u) * inv])
    w_v = np.array([lam_v * (tau * sg - s22 * cg), lam_v * (s11 * sg - tau * cg), (lv_u - sg * lu_v) * inv])
    half_h = 0.5 * h
    return (
        (half_h * (w_u[:, :, :-1] + w_u[:, :, 1:])).reshape(3, -1),
        (half_h * (w_v[:, :-1] + w_v[:, 1:])).reshape(3, -1),
    )


def _prefix_products(mats: np.ndarray) -> np.ndarray:
    """Cumulative matrix products along axis 2 of components-first matrices (3, 3, K, ...):
    P_k = M_0 M_1 … M_k, in log₂(K) batched steps."""
    out = mats.copy()
    step = 1
    while step < out.shape[2]:
        out[:, :, step:] = matmul_t(out[:, :, :-step], out[:, :, step:])
        step *= 2
    return out


def integrate_frames(grid: FineGrid, rot_u: np.ndarray, rot_v: np.ndarray, corrections: int = 1) -> np.ndarray:
    """Frames (nf, mf, 3, 3) (columns t_u, t_v, n) from edge rotations: integrate along the
    centre row then along every column, then least-squares corrections that spread the loop
    misclosures over the whole grid (linearised rotation averaging on the fixed Laplacian).

    The work is done components-first ((3, 3, nodes) arrays); the result is a view in the
    usual (nf, mf, 3, 3) layout."""
    nf, mf = grid.nf, grid.mf
    a0, b0 = grid.centre
    n_u = rot_u.shape[1]
    edge_rot = exp_so3_t(np.concatenate([rot_u, rot_v], axis=1))  # (3, 3, E)
    ru = edge_rot[:, :, :n_u].reshape(3, 3, nf, mf - 1)
    rv = edge_rot[:, :, n_u:].reshape(3, 3, nf - 1, mf)
    frames = np.empty((3, 3, nf, mf))
    frames[:, :, a0, b0] = _EYE3
    # the centre is the middle node, so both halves of a line have the same length: one
    # cumulative product for the two directions (backwards: transposed, reversed)
    row = np.stack([ru[:, :, a0, b0:], ru[:, :, a0, b0 - 1 :: -1].transpose(1, 0, 2)], axis=3)  # (3, 3, L, 2)
    cols = np.stack([rv[:, :, a0:], rv[:, :, a0 - 1 :: -1].transpose(1, 0, 2, 3)], axis=3)  # (3, 3, L', 2, mf)
    if a0 == b0:  # square fine grid: the row and all columns in one batch
        both = _prefix_products(np.concatenate([row[..., None], cols], axis=4))
        row, cols = both[..., 0], both[..., 1:]
    else:
        row, cols = _prefix_products(row), _prefix_products(cols)
    frames[:, :, a0, b0 + 1 :] = row[..., 0]
    frames[:, :, a0, :b0] = row[:, :, ::-1, 1]
    col = matmul_t(frames[:, :, a0, None, None, :], cols)
    frames[:, :, a0 + 1 :] = col[:, :, :, 0]
    frames[:, :, :a0] = col[:, :, ::-1, 1]
    flat = frames.reshape(3, 3, -1)
    for _ in range(corrections):
        # world-frame misclosure of each edge, R_tail exp(ω) = exp(m) R_head: for the small
        # misclosures left by the tree, m = ½ Σ_k head_k × predicted_k (columns), which is
        # the axial vector of the skew part of A = predicted · headsᵀ
        pred = matmul_t(np.take(flat, grid.edge_tails, axis=2), edge_rot)  # take: contiguous result
        a = np.einsum("ikn,jkn->ijn", pred, np.take(flat, grid.edge_heads, axis=2))
        mis = 0.5 * np.array([a[2, 1] - a[1, 2], a[0, 2] - a[2, 0], a[1, 0] - a[0, 1]])
        delta = grid.laplacian.solve(grid.divergence(mis))
        flat = matmul_t(cayley_t(delta.T), flat)
    return flat.reshape(3, 3, nf, mf).transpose(2, 3, 0, 1)


def _chord_ratio(bend: np.ndarray) -> np.ndarray:
    """Chord over arc length of circular arcs turning by ``bend``: sin(θ/2)/(θ/2), 1 at θ = 0
    (np.sinc's wrapper costs more than this arithmetic on the small arrays here)."""
    half = 0.5 * bend
    out = np.ones_like(half)
    np.divide(np.sin(half), half, out=out, where=half > 0)
    return out


def integrate_positions(grid: FineGrid, frames, rot_u, rot_v, lam_u, lam_v, sin_gamma) -> np.ndarray:
    """Positions (nf, mf, 3) whose edge vectors best match the chords of the arcs implied by the
    frames: length λ·spacing·sinc(bend/2) along the bisector of the end tangents (x̂_u, or x̂_v
    sheared by γ), which is the chord direction of a circular arc."""
    h = grid.spacing
    nf, mf = grid.nf, grid.mf
    frames_t = frames.transpose(2, 3, 0, 1)  # components first: (3, 3, nf, mf)
    t_u = frames_t[:, 0]
    t_v = frames_t[:, 0] * sin_gamma + frames_t[:, 1] * np.sqrt(1.0 - sin_gamma * sin_gamma)
    dir_u = t_u[:, :, :-1] + t_u[:, :, 1:]
    dir_v = t_v[:, :-1] + t_v[:, 1:]
    bend_u = np.hypot(rot_u[1], rot_u[2]).reshape(nf, mf - 1)
    bend_v = np.hypot(rot_v[0], rot_v[2]).reshape(nf - 1, mf)
    len_u = (h * edge_mean(lam_u, 1)) * _chord_ratio(bend_u)
    len_v = (h * edge_mean(lam_v, 0)) * _chord_ratio(bend_v)
    chord_u = dir_u * (len_u / np.sqrt(np.einsum("i...,i...->...", dir_u, dir_u)))
    chord_v = dir_v * (len_v / np.sqrt(np.einsum("i...,i...->...", dir_v, dir_v)))
    pos = grid.laplacian.solve(grid.divergence(chord_u.reshape(3, -1), chord_v.reshape(3, -1)))
    # the banded solver returns (nodes, 3) in column-major order: a view of (3, nf, mf)
    return np.ascontiguousarray(pos.T).reshape(3, nf, mf).transpose(1, 2, 0)
