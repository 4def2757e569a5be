"""The sheet's full 3D position fitted to every gauge, with the membrane's tangential equilibrium
as the prior for what the gauges do not measure (docs/reconstruction.md, "Elastic films").

x(u, v) = (u + U, v + V, w): three bicubic tensor B-splines over the film.  Per frame it
minimises, by Gauss-Newton steps from a start (the height-graph or general model's surface, or
the previous frame's answer),

    Σ_gauges ρ((Θ/g)_model − Θ/g)/σ_Θ) + ρ(((L/g)_model − L/g)/σ_L)
      + w_eq² ∫∫ |t(x)|² + w_s² ∫∫ |∇³(U, V, w)|²,

where Θ/g and L/g are each gauge's exact turning and stretch along its line (Gauss-Legendre),
t = (x_u, x_v)ᵀ ∂_a(S^{ab} x_b) is the tangential part of the divergence of the membrane stress
(Saint Venant-Kirchhoff, plane stress, Poisson's ratio ν): zero for a film loaded only along its
normal (a frictionless mold, pressure), and ρ is a Huber loss (quadratic within ``huber`` noise
s.d., linear beyond) so that one biased gauge cannot pull the sheet.  Each step is the convex
problem of the linearised residuals within a trust region, solved by Clarabel (a QP with the
Huber slacks and the box |δ| ≤ Δ); ``step_solver="cholesky"`` solves the plain least-squares
step instead (no Huber), for comparison.

Each point touches 16 of the nb tensor B-splines, so the operators are kept sparse (`_PointDesign`):
the local derivatives come by one batched complex step, the Jacobians are assembled into a fixed
sparsity pattern, and JᵀJ of the equilibrium rows is a sum of 48×48 blocks.  A cold frame goes
through `ElasticFit`: half the knots first (a turned saddle converges there in ~20 steps where the
full basis crawls along the twist valley for 60+), then the full basis.

With ``film_margin`` (pitches of film beyond the outer cells) the basis covers the whole film.
`PositionFit.slide` solves the film's in-plane sliding (U, V)
from its height alone in the equilibrium's weak form (the membrane's virtual work on every
displacement tangent to the film: free edges are its natural condition), which converges on
coarser knots than the collocated rows (docs/reconstruction.md, "What an elastic film's error is
made of").

Pure: `PositionFit` holds the operators of one geometry (built once); `fit` takes the frame's
data and a start and returns a `PositionResult`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from skinmap.reconstruction.graphfit import _basis_1d, _design, _gram
from skinmap.strains import cell_axes

# Derivatives of the position the residuals use, (order along u, order along v).
_DERIVATIVES = ((1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
# ∫|∇³f|² = Σ binomial-weighted squares of the third derivatives.
_SMOOTH = {(3, 0): 1.0, (2, 1): 3.0, (1, 2): 3.0, (0, 3): 1.0}
_STEP_CS = 1e-30  # complex step: derivatives exact to rounding
_CLEARLY_LOWER = 1e-3  # a prior cost lower by less than this is rounding, not evidence


class PositionResult(NamedTuple):
    coeffs: np.ndarray        # (3, nb) coefficients of U, V, w
    chi2: float               # gauges' Σ (residual/σ)² per valid gauge datum
    steps: int
    status: str               # "converged", "max_steps", "stalled"
    prior_cost: float         # ½ w_eq² Σ|t|² at the answer: how far the film is from normal loading
    cost: float               # the whole objective at the answer
    weights: np.ndarray       # (2, 2, N, M) Huber weight of each datum (turning, stretch) at the answer
    turning_residual: np.ndarray  # (2, N, M) model − data, per material mm
    stretch_residual: np.ndarray  # (2, N, M)


def _rows(bu: np.ndarray, bv: np.ndarray) -> np.ndarray:
    """Tensor-product design rows: point k's basis values B_j(u_k) B_i(v_k), column i·nbu + j."""
    return (bv[:, :, None] * bu[:, None, :]).reshape(bu.shape[0], -1)


class _PointDesign(NamedTuple):
    """The basis at a set of points, kept sparse: at each point only the 4×4 tensor B-splines of
    its knot span are nonzero (16 of nb), so evaluation and Jacobians cost O(16) per point."""
    idx: np.ndarray   # (P, 16) coefficient index of each nonzero basis function
    vals: dict        # derivative (du, dv) -> (P, 16) values
    stack: np.ndarray  # (P, D, 16) the same, derivatives in the order of ``vals``


def _span_values(knots: np.ndarray, nb: int, x: np.ndarray, der: int, start: np.ndarray) -> np.ndarray:
    """(P, 4): the der-th derivative of the 4 cubic B-splines of each point's span."""
    dense = _design(knots, nb, x, der)
    cols = start[:, None] + np.arange(4)
    vals = np.take_along_axis(dense, cols, axis=1)
    rest = np.abs(dense).sum(axis=1) - np.abs(vals).sum(axis=1)
    if rest.max(initial=0.0) > 1e-9 * max(1.0, float(np.abs(dense).max(initial=0.0))):
        raise AssertionError("B-spline support outside the point's knot span")
    return vals


def _span_start(knots: np.ndarray, nb: int, x: np.ndarray) -> np.ndarray:
    breaks = np.unique(knots)
    return np.clip(np.searchsorted(breaks, x, side="right") - 1, 0, nb - 4)


class _Entries(NamedTuple):
    rows: np.ndarray
    cols: np.ndarray


class _SparseRows:
    """A sparse matrix of fixed pattern assembled from per-entry values (duplicates summed): the
    pattern is sorted once, each step only adds values into their slots."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]):
        key = rows.ravel().astype(np.int64) * shape[1] + cols.ravel()
        unique, self._slot = np.unique(key, return_inverse=True)
        self._indices = (unique % shape[1]).astype(np.int32)
        self._indptr = np.searchsorted(unique // shape[1], np.arange(shape[0] + 1)).astype(np.int32)
        self.shape = shape

    def matrix(self, values: np.ndarray) -> sp.csr_matrix:
        data = np.bincount(self._slot, weights=values.ravel(), minlength=self._indices.size)
        return sp.csr_matrix((data, self._indices, self._indptr), shape=self.shape)


def _turning(xu: np.ndarray, xv: np.ndarray, xaa: np.ndarray, xa: np.ndarray) -> np.ndarray:
    """Turning rate −x_aa·n/|x_a| (works on complex input for the complex step)."""
    nrm = np.cross(xu, xv)
    nrm = nrm / np.sqrt((nrm * nrm).sum(-1, keepdims=True))
    return -(xaa * nrm).sum(-1) / np.sqrt((xa * xa).sum(-1))


def _tangential_divergence(xu, xv, xuu, xuv, xvv, nu: complex, full: bool = False) -> np.ndarray:
    """(2, P): x_u· and x_v· ∂_a(S^{ab} x_b), St Venant-Kirchhoff plane stress, shear modulus 1."""
    lam = 2.0 * nu / (1.0 - nu)
    e_uu, e_vv, e_uv = 0.5 * ((xu * xu).sum(-1) - 1), 0.5 * ((xv * xv).sum(-1) - 1), 0.5 * (xu * xv).sum(-1)
    tr = e_uu + e_vv
    s_uu, s_vv, s_uv = lam * tr + 2 * e_uu, lam * tr + 2 * e_vv, 2 * e_uv
    euu_u, euu_v = (xuu * xu).sum(-1), (xuv * xu).sum(-1)
    evv_u, evv_v = (xuv * xv).sum(-1), (xvv * xv).sum(-1)
    euv_u = 0.5 * ((xuu * xv).sum(-1) + (xu * xuv).sum(-1))
    euv_v = 0.5 * ((xuv * xv).sum(-1) + (xu * xvv).sum(-1))
    ds_u = lam * (euu_u + evv_u) + 2 * euu_u + 2 * euv_v
    ds_v = lam * (euu_v + evv_v) + 2 * evv_v + 2 * euv_u
    div = (ds_u[..., None] * xu + ds_v[..., None] * xv + s_uu[..., None] * xuu
           + 2 * s_uv[..., None] * xuv + s_vv[..., None] * xvv)
    if full:
        return div
    return np.stack([(div * xu).sum(-1), (div * xv).sum(-1)], axis=-2)


def _virtual_work_terms(xu, xv, xuu, xuv, xvv, nu: complex) -> np.ndarray:
    """(6, P): for c = u, v the integrand's parts of the membrane's virtual work on a tangential
    virtual displacement α x_c, ∫ S^{ab} x_b · ∂_a(α x_c) = ∫ (T^u·x_c) α_u + (T^v·x_c) α_v +
    (T^a·x_ca) α, with T^a = S^{ab} x_b (St Venant-Kirchhoff, plane stress, shear modulus 1):
    rows (T^u·x_u, T^v·x_u, T^a·x_ua, T^u·x_v, T^v·x_v, T^a·x_va)."""
    lam = 2.0 * nu / (1.0 - nu)
    e_uu, e_vv, e_uv = 0.5 * ((xu * xu).sum(-1) - 1), 0.5 * ((xv * xv).sum(-1) - 1), 0.5 * (xu * xv).sum(-1)
    tr = e_uu + e_vv
    s_uu, s_vv, s_uv = lam * tr + 2 * e_uu, lam * tr + 2 * e_vv, 2 * e_uv
    t_u = s_uu[..., None] * xu + s_uv[..., None] * xv
    t_v = s_uv[..., None] * xu + s_vv[..., None] * xv
    rows = []
    for xc, xcu, xcv in ((xu, xuu, xuv), (xv, xuv, xvv)):
        rows += [(t_u * xc).sum(-1), (t_v * xc).sum(-1), (t_u * xcu).sum(-1) + (t_v * xcv).sum(-1)]
    return np.stack(rows, axis=-2)


class _Galerkin(NamedTuple):
    """The sliding's weak form on one basis: Gauss points (4 a knot span each way), their
    weights, the test functions' (α_u, α_v, α) there, and the Jacobian's fixed pattern."""
    design: _PointDesign
    weights: np.ndarray  # (P,)
    test: np.ndarray  # (P, 3, 16)
    rows: np.ndarray  # (P, 32): the residual index of each point's (component, test function)
    jacobian: "_SparseRows"


def _local_jacobian(fun, args: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """fun(*args) (R, P) and its derivative by each component of each (P, 3) argument:
    a list over arguments of (R, P, 3), by the complex step (exact to rounding).  All 3·len(args)
    directions go through ``fun`` at once, stacked on a leading axis (fun broadcasts over it)."""
    n_dir = 3 * len(args)
    stacked = []
    for a, x in enumerate(args):
        z = np.broadcast_to(x, (n_dir,) + x.shape).astype(complex)
        z[3 * a + np.arange(3), :, np.arange(3)] += 1j * _STEP_CS
        stacked.append(z)
    out = fun(*stacked)  # (n_dir, R..., P)
    value = np.real(out[0])
    deriv = np.imag(out) / _STEP_CS
    return value, [np.moveaxis(deriv[3 * a:3 * a + 3], 0, -1) for a in range(len(args))]


@dataclass(frozen=True)
class PositionFitSettings:
    poisson: float = 0.48          # the film's Poisson ratio (calibration; docs/calibration.md)
    knots_per_pitch: int = 2
    equilibrium_per_pitch: int = 3  # collocation points of the equilibrium prior per pitch
    equilibrium_weight: float = 1e3
    smooth_weight: float = 0.1
    huber: float = 3.0              # noise s.d. where the gauge loss turns linear
    max_steps: int = 8              # steps of a fit from the previous frame's answer (measured: 40 gain nothing)
    coarse_steps: int = 20          # cold: steps on half the knots first (its valley is far less
    refine_steps: int = 10          # curved), then on the full basis
    tolerance_mm: float = 1e-4      # converged when no coefficient (so no position) moves more
    step_solver: str = "cholesky"   # or "clarabel": Huber steps, each a QP
    # when Reconstructor(elastic_prior=...) uses the answer (measured: bench/equilibrium_prior.py)
    max_prior_cost: float = 3.0     # ½ w_eq² ∫|t|² beyond this: the prior does not hold
    max_chi2: float = 4.0           # gauges' χ² per datum beyond this: the answer misfits
    poisson_sd: float = 0.02        # how well ν is known; its effect is added to σ
    mirror_cost_ratio: float = 1.5  # the mirror image stays an answer within this ratio of costs
    # The film beyond the outer cells, in pitches, covered by the basis (the emulator's films:
    # half a pitch).  Off by default: the film's in-plane sliding (PositionFit.slide) takes the
    # basis's edges for the film's; the elastic prior (Reconstructor(elastic_prior=...)) leaves
    # it off (docs/reconstruction.md, "Elastic films").
    film_margin: float = 0.0


class PositionFit:
    """Operators of the position fit for one n×m geometry (built once)."""

    def __init__(self, n: int, m: int, pitch: float, gauge_length: float,
                 settings: PositionFitSettings = PositionFitSettings(), quadrature: int = 8):
        if not 0.0 <= settings.poisson < 0.5:
            raise ValueError(f"poisson ratio must be in [0, 0.5), got {settings.poisson}")
        if not (math.isfinite(settings.film_margin) and settings.film_margin >= 0):
            raise ValueError(f"film_margin must be a finite number >= 0, got {settings.film_margin!r}")
        if settings.step_solver not in ("clarabel", "cholesky"):
            raise ValueError(f"step_solver must be 'clarabel' or 'cholesky', got {settings.step_solver!r}")
        self.n, self.m, self.pitch, self.settings = n, m, pitch, settings
        margin = settings.film_margin * pitch
        hu, hv = 0.5 * m * pitch + margin, 0.5 * n * pitch + margin
        spans_u = int(round(settings.knots_per_pitch * (m + 2 * settings.film_margin)))
        spans_v = int(round(settings.knots_per_pitch * (n + 2 * settings.film_margin)))
        self.ku, self.nbu = _basis_1d(-hu, hu, spans_u)
        self.kv, self.nbv = _basis_1d(-hv, hv, spans_v)
        self.nb = nb = self.nbu * self.nbv
        self.uc, self.vc = cell_axes(n, m, pitch)
        xg, wg = np.polynomial.legendre.leggauss(quadrature)
        s = 0.5 * gauge_length * xg
        self.q = quadrature
        self.wq = wg / wg.sum()
        vv, uu = np.meshgrid(self.vc, self.uc, indexing="ij")
        # Gauge quadrature points: u gauges along u, v gauges along v; (n·m·q) points each.
        self._gauge = [
            self._design((uu[..., None] + s).ravel(), np.repeat(vv.ravel(), s.size), _DERIVATIVES),
            self._design(np.repeat(uu.ravel(), s.size), (vv[..., None] + s).ravel(), _DERIVATIVES),
        ]
        ne = int(round(settings.equilibrium_per_pitch * 2 * hv / pitch))
        me = int(round(settings.equilibrium_per_pitch * 2 * hu / pitch))
        ev_grid, eu_grid = np.meshgrid((np.arange(ne) + 0.5) / ne * 2 * hv - hv,
                                       (np.arange(me) + 0.5) / me * 2 * hu - hu, indexing="ij")
        eu, ev = eu_grid.ravel(), ev_grid.ravel()
        self._eq_scale = np.full(eu.size, settings.equilibrium_weight * np.sqrt(4 * hu * hv / eu.size))
        self._points = self._design(eu, ev, _DERIVATIVES)
        # ∫|∇³f|² as an exact quadratic form (per component).
        gram_u = [_gram(self.ku, self.nbu, d) for d in range(4)]
        gram_v = [_gram(self.kv, self.nbv, d) for d in range(4)]
        smooth = sum(wt * np.kron(gram_v[dv], gram_u[du]) for (du, dv), wt in _SMOOTH.items())
        self._smooth = settings.smooth_weight ** 2 * smooth
        # The sensor frame fixes the rigid motion every other term leaves free: the material
        # centre at the origin, its normal +z, the tangent of +u along +x (U = V = w = 0,
        # V_u = w_u = w_v = 0 at (0, 0)), as heavily weighted linear rows.
        at0 = {d: _rows(_design(self.ku, self.nbu, np.zeros(1), d[0]), _design(self.kv, self.nbv, np.zeros(1), d[1]))
               for d in ((0, 0), (1, 0), (0, 1))}
        zero = np.zeros((1, nb))
        frame = np.vstack([
            np.hstack([at0[(0, 0)], zero, zero]), np.hstack([zero, at0[(0, 0)], zero]),
            np.hstack([zero, zero, at0[(0, 0)]]), np.hstack([zero, at0[(1, 0)], zero]),
            np.hstack([zero, zero, at0[(1, 0)]]), np.hstack([zero, zero, at0[(0, 1)]]),
        ])
        self._frame = 1e6 * frame.T @ frame
        self._prior_matrix = sla.block_diag(self._smooth, self._smooth, self._smooth) + self._frame
        # the units' hull, where the stretch pattern reads the Gaussian curvature (.airy)
        hv_, hu_ = np.meshgrid(np.linspace(self.vc[0], self.vc[-1], 9), np.linspace(self.uc[0], self.uc[-1], 9),
                               indexing="ij")
        self._hull = self._design(hu_.ravel(), hv_.ravel(), _DERIVATIVES)
        self._centres = _rows(_design(self.ku, self.nbu, np.tile(self.uc, n), 0),
                              _design(self.kv, self.nbv, np.repeat(self.vc, m), 0))
        # Jacobian patterns: the gauges' rows (turning u, v gauges, then stretch u, v; each the
        # mean over its q points) and the equilibrium's (component, point).
        nm, q = n * m, quadrature
        gauge_of = np.repeat(np.arange(nm), q)[None, :]
        self._gauge_pattern = [self._pattern(self._gauge[a], gauge_of + (kind * 2 + a) * nm)
                               for kind in (0, 1) for a in (0, 1)]
        self._gauge_rows = _SparseRows(
            np.concatenate([pt.rows for pt in self._gauge_pattern]),
            np.concatenate([pt.cols for pt in self._gauge_pattern]), (4 * nm, 3 * nb))
        p_eq = eu.size
        self._eq_rows_pattern = self._pattern(self._points, np.arange(2 * p_eq).reshape(2, p_eq))
        self._eq_rows = _SparseRows(self._eq_rows_pattern.rows, self._eq_rows_pattern.cols, (2 * p_eq, 3 * nb))
        local_cols = (np.arange(3)[None, :, None] * nb + self._points.idx[:, None, :]).reshape(p_eq, 48)
        self._eq_pairs = (local_cols[:, :, None] * (3 * nb) + local_cols[:, None, :]).ravel()
        self._galerkin: _Galerkin | None = None  # the sliding's weak form (slide), built on first use

    def _design(self, pu: np.ndarray, pv: np.ndarray, ders) -> _PointDesign:
        pu, pv = np.asarray(pu, float), np.asarray(pv, float)
        su, sv = _span_start(self.ku, self.nbu, pu), _span_start(self.kv, self.nbv, pv)
        idx = ((sv[:, None] + np.arange(4))[:, :, None] * self.nbu + (su[:, None] + np.arange(4))[:, None, :])
        vals = {}
        for d in ders:
            bu = _span_values(self.ku, self.nbu, pu, d[0], su)
            bv = _span_values(self.kv, self.nbv, pv, d[1], sv)
            vals[d] = (bv[:, :, None] * bu[:, None, :]).reshape(pu.size, 16)
        return _PointDesign(idx.reshape(pu.size, 16), vals, np.stack(list(vals.values()), axis=1))

    @staticmethod
    def _x(c: np.ndarray, design: _PointDesign) -> dict:
        """Derivatives of the position at the design's points, (P, 3) each; c is (3, nb)."""
        local = np.asarray(c).T[design.idx]  # (P, 16, 3)
        every = np.matmul(design.stack, local)  # (P, D, 3)
        out = {}
        for i, d in enumerate(design.vals):
            x = every[:, i]
            if d == (1, 0):
                x[:, 0] += 1.0
            elif d == (0, 1):
                x[:, 1] += 1.0
            out[d] = x
        return out

    def _pattern(self, design: _PointDesign, rows: np.ndarray) -> "_Entries":
        """The Jacobian entries of residual rows ``rows`` (R, P) over the design's points:
        (R, P, 3 components, 16), column k·nb + idx."""
        cols = np.arange(3)[None, :, None] * self.nb + design.idx[:, None, :]  # (P, 3, 16)
        cols = np.broadcast_to(cols[None], rows.shape + (3, 16))
        return _Entries(np.broadcast_to(rows[:, :, None, None], cols.shape).ravel(), cols.ravel())

    def gauge_model(self, c: np.ndarray, jacobian: bool = False):
        """Turning and stretch of every gauge (2, n·m) each; with ``jacobian`` also their
        derivatives by the coefficients, (2, n·m, 3·nb) each (dense: for inspection)."""
        if not jacobian:
            return self._gauges(c, False)[:2]
        t, s, jac = self._gauges(c, True)
        dense = jac.toarray().reshape(2, 2, self.n * self.m, -1)
        return t, s, dense[0], dense[1]

    def _gauges(self, c: np.ndarray, jacobian: bool):
        """Turning, stretch (2, n·m) and, with ``jacobian``, their sparse Jacobian (4·n·m, 3·nb):
        rows turning of the u then v gauges, then stretch of the u then v gauges."""
        turning, stretch, t_vals, s_vals = [], [], [], []
        nm, q = self.n * self.m, self.q
        wq = np.tile(self.wq, nm)[:, None, None]
        for a, design in enumerate(self._gauge):
            x = self._x(c, design)
            da = (1, 0) if a == 0 else (0, 1)
            daa = (2, 0) if a == 0 else (0, 2)
            xu, xv, xa, xaa = x[(1, 0)], x[(0, 1)], x[da], x[daa]
            length = np.linalg.norm(xa, axis=1)
            stretch.append((length.reshape(nm, q) @ self.wq))
            if not jacobian:
                turning.append(_turning(xu, xv, xaa, xa).reshape(nm, q) @ self.wq)
                continue
            # turning depends on x_u, x_v, x_aa (x_a is x_u or x_v)
            val, (g_u, g_v, g_aa) = _local_jacobian(lambda p, r, t: _turning(p, r, t, p if a == 0 else r),
                                                    [xu, xv, xaa])
            turning.append(val.reshape(nm, q) @ self.wq)
            vals = design.vals
            t_vals.append(wq * (g_u[:, :, None] * vals[(1, 0)][:, None, :] + g_v[:, :, None] * vals[(0, 1)][:, None, :]
                                + g_aa[:, :, None] * vals[daa][:, None, :]))
            s_vals.append(wq * ((xa / length[:, None])[:, :, None] * vals[da][:, None, :]))
        if not jacobian:
            return np.array(turning), np.array(stretch), None
        jac = self._gauge_rows.matrix(np.concatenate([t_vals[0].ravel(), t_vals[1].ravel(),
                                                      s_vals[0].ravel(), s_vals[1].ravel()]))
        return np.array(turning), np.array(stretch), jac

    def equilibrium(self, c: np.ndarray, jacobian: bool = False):
        """Weighted tangential equilibrium residuals (2·P,), and with ``jacobian`` (2·P, 3·nb)
        (dense: for inspection)."""
        if not jacobian:
            return self._equilibrium(c, False)[0]
        r, lin = self._equilibrium(c, True)
        return r, lin.matrix.toarray()

    def _equilibrium(self, c: np.ndarray, jacobian: bool, poisson: float | None = None):
        x = self._x(c, self._points)
        args = [x[d] for d in _DERIVATIVES]
        nu = self.settings.poisson if poisson is None else poisson
        if not jacobian:
            xu, xv, xuu, xuv, xvv = args
            return (self._eq_scale * _tangential_divergence(xu, xv, xuu, xuv, xvv, nu)).ravel(), None
        val, grads = _local_jacobian(
            lambda xu, xv, xuu, xuv, xvv: _tangential_divergence(xu, xv, xuu, xuv, xvv, nu), args)
        # entries (2, P, 3, 16) = Σ_d ∂r/∂x_d · B_d: one batched product over the derivatives
        by_der = np.stack(grads, axis=-1)  # (2, P, 3, D)
        entries = self._eq_scale[:, None, None] * np.matmul(by_der, self._points.stack[None])
        return (self._eq_scale * val).ravel(), _Linear(self._eq_rows.matrix(entries), entries)

    def _equilibrium_normal(self, entries: np.ndarray) -> np.ndarray:
        """J_eᵀJ_e (3·nb)² dense, from the (2, P, 3, 16) entries: each point's rows touch only its
        48 columns, so the product is a sum of 48×48 blocks scattered into place."""
        p = entries.shape[1]
        local = entries.transpose(1, 0, 2, 3).reshape(p, 2, 48)
        blocks = np.matmul(local.transpose(0, 2, 1), local)
        size = 3 * self.nb
        return np.bincount(self._eq_pairs, weights=blocks.ravel(), minlength=size * size).reshape(size, size)

    def poisson_sensitivity(self, c: np.ndarray) -> np.ndarray:
        """∂(weighted equilibrium residuals)/∂ν at c, (2·P,) (complex step in ν)."""
        x = self._x(c, self._points)
        args = [x[d] for d in _DERIVATIVES]
        nu = complex(self.settings.poisson, _STEP_CS)
        xu, xv, xuu, xuv, xvv = args
        return (self._eq_scale * np.imag(_tangential_divergence(xu, xv, xuu, xuv, xvv, nu))).ravel() / _STEP_CS

    def tangential_fraction(self, c: np.ndarray) -> float:
        """How far the answer is from a normally loaded film: ∫|t|² / ∫|∂_a(S^{ab} x_b)|², the share
        of the stress divergence that lies in the sheet's plane (0 on a frictionless mold or under
        pressure; friction or a load with in-plane parts raise it)."""
        x = self._x(np.asarray(c).reshape(3, -1), self._points)
        args = [x[d] for d in _DERIVATIVES]
        xu, xv, xuu, xuv, xvv = args
        t = _tangential_divergence(xu, xv, xuu, xuv, xvv, self.settings.poisson)
        div = _tangential_divergence(xu, xv, xuu, xuv, xvv, self.settings.poisson, full=True)
        total = float((div * div).sum())
        return float((t * t).sum()) / total if total > 0 else 0.0

    def mean_gaussian_curvature(self, c: np.ndarray) -> float:
        """Mean Gaussian curvature (1/mm²) over the units' hull, (LN − M²)/(EG − F²)."""
        x = self._x(np.asarray(c).reshape(3, -1), self._hull)
        xu, xv, xuu, xuv, xvv = (x[d] for d in _DERIVATIVES)
        nrm = np.cross(xu, xv)
        area2 = (nrm * nrm).sum(-1)
        nrm = nrm / np.sqrt(area2)[:, None]
        ell, mm, en = ((xuu * nrm).sum(-1), (xuv * nrm).sum(-1), (xvv * nrm).sum(-1))
        return float(((ell * en - mm * mm) / area2).mean())

    def nodes(self, c: np.ndarray) -> np.ndarray:
        """Cell-centre positions (n, m, 3)."""
        uu, vv = np.tile(self.uc, self.n), np.repeat(self.vc, self.m)
        pos = self._centres @ c.T
        pos[:, 0] += uu
        pos[:, 1] += vv
        return pos.reshape(self.n, self.m, 3)

    def evaluate(self, c: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions and first derivatives x_u, x_v at material points (u, v), (P, 3) each."""
        return self.evaluator(u, v)(c)

    def evaluator(self, u: np.ndarray, v: np.ndarray):
        """``evaluate`` at fixed points, the basis built once: c ↦ (x, x_u, x_v)."""
        u, v = np.asarray(u, float), np.asarray(v, float)
        design = self._design(u, v, ((0, 0), (1, 0), (0, 1)))

        def at(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            x = self._x(c, design)
            x[(0, 0)][:, 0] += u
            x[(0, 0)][:, 1] += v
            return x[(0, 0)], x[(1, 0)], x[(0, 1)]

        return at

    def transfer(self, coarser: "PositionFit") -> np.ndarray:
        """(nb, nb_coarser): the coefficients of ``coarser``'s splines in this basis. Exact when its
        knots are a subset of these (a fit on half the knots, refined here)."""
        u = np.linspace(self.ku[0], self.ku[-1], 4 * self.nbu + 1)
        v = np.linspace(self.kv[0], self.kv[-1], 4 * self.nbv + 1)
        uu, vv = (a.ravel() for a in np.meshgrid(u, v))
        mine = _rows(_design(self.ku, self.nbu, uu, 0), _design(self.kv, self.nbv, vv, 0))
        theirs = _rows(_design(coarser.ku, coarser.nbu, uu, 0), _design(coarser.kv, coarser.nbv, vv, 0))
        return sla.lstsq(mine, theirs)[0]

    def coeffs_from_positions(self, u: np.ndarray, v: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Least-squares coefficients (3, nb) of positions (P, 3) at material points (P,)."""
        design = _rows(_design(self.ku, self.nbu, u, 0), _design(self.kv, self.nbv, v, 0))
        target = np.stack([pos[:, 0] - u, pos[:, 1] - v, pos[:, 2]], axis=-1)
        gram = design.T @ design + 1e-9 * np.eye(self.nb)
        if self.settings.film_margin > 0:
            # the film beyond the points: continued smoothly (its third derivatives least)
            raw = self._smooth / max(self.settings.smooth_weight ** 2, 1e-300)
            gram = gram + 1e-3 * np.trace(gram) / np.trace(raw) * raw
        return sla.solve(gram, design.T @ target, assume_a="pos").T

    def slide(self, c: np.ndarray, max_steps: int = 20, tolerance_mm: float = 1e-7) -> np.ndarray:
        """The in-plane displacement (U, V) of a film whose height w (c[2]) is held: the one whose
        membrane stress does no virtual work on any displacement tangent to the film, the film
        being the basis's whole domain (``film_margin``: the film beyond the outer cells) with its
        edges free; returns the coefficients (3, nb) with w unchanged.  A film laminated on a
        frictionless mold slides so (the mold's reaction is normal: it does no such work).  The
        weak form (:meth:`virtual_work`) converges on coarser knots than the collocated
        equilibrium rows (measured, docs/reconstruction.md "What an elastic film's error is made
        of"): given its true height it recovers the film's true in-plane displacement, which a
        height graph (U = V = 0) leaves out.  Gauss-Newton from c's own (U, V), each step halved
        until the residual's norm does not grow; the sensor frame's rows fix the rigid motion."""
        c = self._coefficients(c)
        nb = self.nb
        frame = self._frame[:2 * nb, :2 * nb] / 1e6  # the frame's rows, unweighted
        r, jac = self.virtual_work(c)
        norm = float(r @ r)
        for _ in range(max_steps):
            j = jac.tocsc()[:, :2 * nb]
            jtj = (j.T @ j).tocsc()
            # the frame's rows weighted well above the film's stiffness (its mean diagonal)
            weight = 1e3 * float(jtj.diagonal().mean())
            normal = (jtj + weight * sp.csc_matrix(frame)).tocsc()
            step = -spl.splu(normal).solve(j.T @ r + weight * (frame @ c[:2].ravel())).reshape(2, nb)
            t = 1.0
            for _ in range(12):
                trial = c.copy()
                trial[:2] += t * step
                r_new, jac_new = self.virtual_work(trial)
                if np.all(np.isfinite(r_new)) and float(r_new @ r_new) <= norm * (1.0 + 1e-12):
                    break
                t *= 0.5
            else:
                break  # no step lowers the residual: as far as it goes
            c, r, jac, norm = trial, r_new, jac_new, float(r_new @ r_new)
            if t * float(np.abs(step).max()) <= tolerance_mm:
                break
        return c

    def virtual_work(self, c: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        """The membrane's virtual work on each tangential test displacement α x_c (α a basis
        function, c = u, v), (2·nb,), and its Jacobian by the in-plane coefficients (U, V),
        (2·nb, 2·nb); zero at the film's sliding equilibrium (:meth:`slide`)."""
        g = self._galerkin_operators()
        x = self._x(self._coefficients(c), g.design)
        args = [x[d] for d in _DERIVATIVES]
        nu = self.settings.poisson
        val, grads = _local_jacobian(
            lambda xu, xv, xuu, xuv, xvv: _virtual_work_terms(xu, xv, xuu, xuv, xvv, nu), args)
        # residual (c, i): Σ_points w (parts_c · (α_u, α_v, α)_i)
        parts = val.reshape(2, 3, -1)
        local = np.einsum("ctp,pti->pci", parts, g.test) * g.weights[:, None, None]
        residual = np.bincount(g.rows.ravel(), weights=local.ravel(), minlength=2 * self.nb)
        # d parts / d (U, V coefficient j): through each derivative of x at the point
        by_coeff = sum(np.einsum("kpd,pj->kpdj", grad[:, :, :2], g.design.vals[d])
                       for grad, d in zip(grads, _DERIVATIVES))
        by_coeff = by_coeff.reshape(2, 3, *by_coeff.shape[1:])
        entries = np.einsum("pti,ctpdj->pcidj", g.test, by_coeff) * g.weights[:, None, None, None, None]
        return residual, g.jacobian.matrix(entries)

    def _coefficients(self, c: np.ndarray) -> np.ndarray:
        """A copy of coefficients ``c`` as (3, nb) floats, or a ValueError naming the shape."""
        c = np.array(c, dtype=float)
        if c.size != 3 * self.nb:
            raise ValueError(f"coefficients of shape {c.shape}: this basis has (3, {self.nb})")
        return c.reshape(3, self.nb)

    def _galerkin_operators(self) -> _Galerkin:
        """The weak form's points and patterns, built on first use (:meth:`slide`)."""
        if self._galerkin is None:
            gauss, gw = np.polynomial.legendre.leggauss(4)

            def points(knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                lo, hi = np.unique(knots)[:-1, None], np.unique(knots)[1:, None]
                return (0.5 * (lo + hi) + 0.5 * (hi - lo) * gauss).ravel(), (0.5 * (hi - lo) * gw).ravel()

            pu, wu = points(self.ku)
            pv, wv = points(self.kv)
            uu, vv = np.meshgrid(pu, pv)
            design = self._design(uu.ravel(), vv.ravel(), ((0, 0),) + _DERIVATIVES)
            test = np.stack([design.vals[(1, 0)], design.vals[(0, 1)], design.vals[(0, 0)]], axis=1)
            p, nb = uu.size, self.nb
            rows = np.arange(2)[None, :, None] * nb + design.idx[:, None, :]  # (P, 2, 16)
            pattern = _SparseRows(np.broadcast_to(rows[:, :, :, None, None], (p, 2, 16, 2, 16)).ravel(),
                                  np.broadcast_to(rows[:, None, None, :, :], (p, 2, 16, 2, 16)).ravel(),
                                  (2 * nb, 2 * nb))
            self._galerkin = _Galerkin(design, np.outer(wv, wu).ravel(), test, rows.reshape(p, 32), pattern)
        return self._galerkin

    def fit(self, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_t: float, sigma_s: float,
            start: np.ndarray, max_steps: int | None = None) -> PositionResult:
        """Gauss-Newton from ``start`` (3, nb). turning, stretch, valid: (2, n, m) unit data."""
        st = self.settings
        steps_allowed = st.max_steps if max_steps is None else max_steps
        problem = _Problem(np.concatenate([turning.reshape(-1), stretch.reshape(-1)]),
                           np.concatenate([np.full(turning.size, sigma_t), np.full(stretch.size, sigma_s)]),
                           np.concatenate([valid.reshape(2, -1).ravel()] * 2))
        smooth = self._prior_matrix
        c = np.asarray(start, float).reshape(-1).copy()
        damping = 1e-4  # Levenberg-Marquardt: relative to the diagonal; adapted per step
        status = "max_steps"
        steps = 0
        cost = None
        for steps in range(1, steps_allowed + 1):
            r_g, j_g, r_e, j_e = self._linearised(c, problem)
            if cost is None:
                cost = self._cost(r_g, r_e, c, smooth)
            # The Gauss-Newton matrix, formed once per step: gauges inside the Huber threshold
            # weigh fully, those beyond it not at all (the loss's curvature there).
            w_g = (np.abs(r_g) <= st.huber).astype(float) if st.step_solver == "clarabel" else np.ones(r_g.size)
            prior_h = self._equilibrium_normal(j_e.entries) + smooth
            j_e = j_e.matrix
            prior_g = j_e.T @ r_e + smooth @ c
            normal = prior_h + (j_g.T @ (j_g if st.step_solver == "cholesky" else sp.diags(w_g) @ j_g)).toarray()
            diag = np.diag(normal).copy()
            gradient = prior_g + j_g.T @ (w_g * r_g)
            if float(np.abs(gradient).max()) <= 1e-9 * max(1.0, cost):
                status = "converged"  # at a stationary point already
                break
            for _ in range(8):
                factor = sla.cho_factor(normal + damping * np.diag(diag))
                if st.step_solver == "cholesky":
                    delta = -sla.cho_solve(factor, prior_g + j_g.T @ r_g)
                else:
                    delta = _clarabel_step(prior_h + damping * np.diag(diag), prior_g, r_g, j_g.toarray(), st.huber,
                                           None)
                trial = c + delta
                if self._accelerate:
                    trial = trial + self._acceleration(c, delta, r_g, j_g, r_e, j_e, w_g, problem, factor)
                new_cost = self._total_cost(trial, problem, smooth)
                if new_cost <= cost:
                    break
                damping *= 8.0
            else:
                status = "stalled"
                break
            moved = float(np.abs(trial - c).max())
            c, improvement, cost = trial, cost - new_cost, new_cost
            damping = max(damping / 4.0, 1e-9)
            # positions are convex combinations of the coefficients: none moved more than this
            if improvement <= 1e-10 * max(cost, 1.0) or moved <= st.tolerance_mm:
                status = "converged"
                break
        t, s = self.gauge_model(c.reshape(3, -1))
        rt, rs = t.reshape(turning.shape) - turning, s.reshape(stretch.shape) - stretch
        z = np.abs(np.stack([rt / sigma_t, rs / sigma_s]))
        weights = np.where(z <= st.huber, 1.0, st.huber / np.maximum(z, 1e-300))
        vmask = np.stack([valid, valid])
        chi2 = float((z[vmask] ** 2).sum() / max(vmask.sum(), 1))
        r_e = self.equilibrium(c.reshape(3, -1))
        return PositionResult(c.reshape(3, -1), chi2, steps, status, 0.5 * float(r_e @ r_e), float(cost or 0.0),
                              weights, rt, rs)

    def poisson_response(self, result: PositionResult, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray,
                         sigma_t: float, sigma_s: float, damping: float = 1e-8) -> np.ndarray:
        """dc/dν (3, nb): how the answer moves per unit of Poisson's ratio, by the implicit function
        theorem at the fit's optimum (one solve with its Gauss-Newton matrix), in place of refits."""
        problem = _Problem(np.concatenate([turning.reshape(-1), stretch.reshape(-1)]),
                           np.concatenate([np.full(turning.size, sigma_t), np.full(stretch.size, sigma_s)]),
                           np.concatenate([valid.reshape(2, -1).ravel()] * 2))
        c = result.coeffs.reshape(-1)
        _, j_g, _, j_e = self._linearised(c, problem)
        normal = self._equilibrium_normal(j_e.entries) + (j_g.T @ j_g).toarray() + self._prior_matrix
        j_e = j_e.matrix
        rhs = j_e.T @ self.poisson_sensitivity(c.reshape(3, -1))
        # damped as the fit's own steps are: along a direction the data and the prior leave
        # (nearly) free, the linear response is unbounded while the true one is not
        normal += damping * np.diag(np.diag(normal))
        return -sla.solve(normal, rhs, assume_a="pos").reshape(3, -1)

    _accelerate = True

    def _linearised(self, c: np.ndarray, problem: "_Problem"):
        """Gauge residuals/σ and equilibrium residuals at c, with their sparse Jacobians."""
        t, s, jt = self._gauges(c.reshape(3, -1), True)
        keep = problem.valid_rows
        r_g = ((np.concatenate([t.ravel(), s.ravel()]) - problem.data) / problem.scale)[keep]
        jt.data /= np.repeat(problem.scale, np.diff(jt.indptr))
        j_g = jt if keep.all() else jt[keep]
        r_e, j_e = self._equilibrium(c.reshape(3, -1), True)
        return r_g, j_g, r_e, j_e

    def _residuals(self, c, problem: "_Problem") -> tuple[np.ndarray, np.ndarray]:
        t, s, _ = self._gauges(c.reshape(3, -1), False)
        r_g = ((np.concatenate([t.ravel(), s.ravel()]) - problem.data) / problem.scale)[problem.valid_rows]
        return r_g, self._equilibrium(c.reshape(3, -1), False)[0]

    def _acceleration(self, c, delta, r_g, j_g, r_e, j_e, w_g, problem: "_Problem", factor) -> np.ndarray:
        """Geodesic acceleration (Transtrum & Sethna): the second-order correction along δ, from one
        more residual evaluation and the step's own factorisation; it lets a step follow a curved
        valley (the twist family)."""
        h = 0.1
        g2, e2 = self._residuals(c + h * delta, problem)
        rvv_g = (2.0 / h) * ((g2 - r_g) / h - j_g @ delta)
        rvv_e = (2.0 / h) * ((e2 - r_e) / h - j_e @ delta)
        acc = -sla.cho_solve(factor, j_g.T @ (w_g * rvv_g) + j_e.T @ rvv_e)
        if np.linalg.norm(acc) > 0.75 * np.linalg.norm(delta):
            return np.zeros_like(delta)
        return 0.5 * acc

    def _huber(self, r: np.ndarray) -> float:
        k = self.settings.huber
        a = np.abs(r)
        return float(np.where(a <= k, 0.5 * r * r, k * a - 0.5 * k * k).sum())

    def _cost(self, r_g, r_e, c, smooth) -> float:
        gauge = self._huber(r_g) if self.settings.step_solver == "clarabel" else 0.5 * float(r_g @ r_g)
        return gauge + 0.5 * float(r_e @ r_e) + 0.5 * float(c @ smooth @ c)

    def _total_cost(self, c, problem: "_Problem", smooth) -> float:
        r_g, r_e = self._residuals(c, problem)
        return self._cost(r_g, r_e, c, smooth)


class _Linear(NamedTuple):
    matrix: sp.csr_matrix   # the Jacobian
    entries: np.ndarray     # its per-point entries (2, P, 3, 16), for the normal matrix


class _Problem(NamedTuple):
    data: np.ndarray        # turning then stretch, per gauge (4·n·m,)
    scale: np.ndarray       # their noise s.d.
    valid_rows: np.ndarray  # which rows have data


class ElasticFit:
    """The position fit on two levels for one geometry: a cold frame is fitted on half the knots
    first, then refined on the full basis, and also refined directly from the start it is given;
    the lower objective wins (the coarse level finds a turned saddle in a few steps where the full
    basis crawls along its valley; the direct refinement keeps an answer that was right already).
    A warm frame (the previous answer's coefficients) is refined directly."""

    def __init__(self, n: int, m: int, pitch: float, gauge_length: float,
                 settings: PositionFitSettings = PositionFitSettings()):
        self.settings = settings
        self.fine = PositionFit(n, m, pitch, gauge_length, settings)
        self.coarse = (None if settings.knots_per_pitch < 2 else
                       PositionFit(n, m, pitch, gauge_length,
                                   dataclasses.replace(settings, knots_per_pitch=settings.knots_per_pitch // 2)))
        self._transfer = None if self.coarse is None else self.fine.transfer(self.coarse)

    def cold(self, surf, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_t: float,
             sigma_s: float) -> PositionResult:
        """From a reconstructed surface (the default answer, or its mirror image)."""
        st = self.settings
        data = (turning, stretch, valid, sigma_t, sigma_s)
        direct = self.fine.fit(*data, start_from_surface(self.fine, surf), max_steps=st.refine_steps)
        if self.coarse is None or self._transfer is None:
            return direct
        rough = self.coarse.fit(*data, start_from_surface(self.coarse, surf), max_steps=st.coarse_steps)
        refined = self.fine.fit(*data, rough.coeffs @ self._transfer.T, max_steps=st.refine_steps)
        # The start stays unless the other is better overall and clearly better by the prior: where
        # the film carries no stress (an isometric cylinder) there is no prior, the two differ by
        # the smoothness term alone, and that is no evidence against the start.
        clearly = (refined.cost < direct.cost and refined.prior_cost < direct.prior_cost / st.mirror_cost_ratio
                   and direct.prior_cost - refined.prior_cost > _CLEARLY_LOWER)
        return refined if clearly else direct

    def warm(self, coeffs: np.ndarray, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray,
             sigma_t: float, sigma_s: float) -> PositionResult:
        return self.fine.fit(turning, stretch, valid, sigma_t, sigma_s, coeffs)


def start_from_surface(fit: PositionFit, surf) -> np.ndarray:
    """Coefficients (3, nb) of a reconstructed :class:`~skinmap.reconstruction.surface.Surface`,
    fitted to its positions on its own fine grid (the start of a fit)."""
    u0, u1, v0, v1 = surf.extent
    uu, vv = np.meshgrid(np.linspace(u0, u1, 4 * fit.m + 1), np.linspace(v0, v1, 4 * fit.n + 1))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=-1)
    return fit.coeffs_from_positions(uv[:, 0], uv[:, 1], surf.locate(uv)[0])


def _clarabel_step(hess: np.ndarray, grad: np.ndarray, r_g: np.ndarray, j_g: np.ndarray, huber: float,
                   radius: float | None) -> np.ndarray:
    """min ½δᵀHδ + gᵀδ + Σ huber(r + Jδ), |δ|∞ ≤ radius, as a QP for Clarabel:
    huber(y) = min_{s,t} ½s² + κ t  s.t. −t ≤ y − s ≤ t."""
    import clarabel

    n, k = hess.shape[0], r_g.size
    # variables [δ (n), s (k), t (k)]
    p = sp.block_diag([sp.csc_matrix(hess), sp.identity(k), sp.csc_matrix((k, k))], format="csc")
    q = np.concatenate([grad, np.zeros(k), np.full(k, huber)])
    jg = sp.csc_matrix(j_g)
    eye = sp.identity(k, format="csc")
    # y − s − t ≤ 0 and −(y − s) − t ≤ 0 with y = r + Jδ
    a = [sp.hstack([jg, -eye, -eye]), sp.hstack([-jg, eye, -eye])]
    b = [-r_g, r_g]
    if radius is not None:
        box = sp.hstack([sp.identity(n), sp.csc_matrix((n, 2 * k))])
        a += [box, -box]
        b += [np.full(n, radius), np.full(n, radius)]
    a_mat = sp.vstack(a, format="csc")
    b_vec = np.concatenate(b)
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(sp.triu(p, format="csc"), q, a_mat, b_vec,
                                    [clarabel.NonnegativeConeT(b_vec.size)], settings)
    sol = solver.solve()
    status = str(sol.status)
    if "Solved" not in status:
        raise RuntimeError(f"Clarabel step: {status}")
    return np.asarray(sol.x)[:n]
