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

Pure: `PositionFit` holds the operators of one geometry (built once); `fit` takes the frame's
data and a start and returns a `PositionResult`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from skinmap.reconstruction.graphfit import _basis_1d, _design, _gram

# Derivatives of the position the residuals use, (order along u, order along v).
_DERIVATIVES = ((1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
# ∫|∇³f|² = Σ binomial-weighted squares of the third derivatives.
_SMOOTH = {(3, 0): 1.0, (2, 1): 3.0, (1, 2): 3.0, (0, 3): 1.0}
_STEP_CS = 1e-30  # complex step: derivatives exact to rounding


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


def _turning(xu: np.ndarray, xv: np.ndarray, xaa: np.ndarray, xa: np.ndarray) -> np.ndarray:
    """Turning rate −x_aa·n/|x_a| (works on complex input for the complex step)."""
    nrm = np.cross(xu, xv)
    nrm = nrm / np.sqrt((nrm * nrm).sum(-1, keepdims=True))
    return -(xaa * nrm).sum(-1) / np.sqrt((xa * xa).sum(-1))


def _tangential_divergence(xu, xv, xuu, xuv, xvv, nu: float, full: bool = False) -> np.ndarray:
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
    return np.stack([(div * xu).sum(-1), (div * xv).sum(-1)])


def _local_jacobian(fun, args: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """fun(*args) (R, P) and its derivative by each component of each (P, 3) argument:
    a list over arguments of (R, P, 3), by the complex step (exact, vectorised over points)."""
    value = np.real(fun(*args))
    out = []
    for a in range(len(args)):
        d = np.empty(value.shape + (3,))
        for k in range(3):
            shifted = [x.astype(complex) if i == a else x for i, x in enumerate(args)]
            shifted[a][..., k] += 1j * _STEP_CS
            d[..., k] = np.imag(fun(*shifted)) / _STEP_CS
        out.append(d)
    return value, out


@dataclass(frozen=True)
class PositionFitSettings:
    poisson: float = 0.48          # the film's Poisson ratio (calibration; docs/calibration.md)
    knots_per_pitch: int = 2
    equilibrium_per_pitch: int = 3  # collocation points of the equilibrium prior per pitch
    equilibrium_weight: float = 1e3
    smooth_weight: float = 0.1
    huber: float = 3.0              # noise s.d. where the gauge loss turns linear
    max_steps: int = 40
    step_solver: str = "cholesky"   # or "clarabel": Huber steps, each a QP
    # when Reconstructor(elastic_prior=...) uses the answer (measured: bench/equilibrium_prior.py)
    max_prior_cost: float = 3.0     # ½ w_eq² ∫|t|² beyond this: the prior does not hold
    max_chi2: float = 4.0           # gauges' χ² per datum beyond this: the answer misfits
    poisson_sd: float = 0.02        # how well ν is known; its effect is added to σ
    sd_steps: int = 8               # steps of the fits at ν ± poisson_sd (from the answer)
    mirror_cost_ratio: float = 1.5  # the mirror image stays an answer within this ratio of costs


class PositionFit:
    """Operators of the position fit for one n×m geometry (built once)."""

    def __init__(self, n: int, m: int, pitch: float, gauge_length: float,
                 settings: PositionFitSettings = PositionFitSettings(), quadrature: int = 8):
        if not 0.0 <= settings.poisson < 0.5:
            raise ValueError(f"poisson ratio must be in [0, 0.5), got {settings.poisson}")
        if settings.step_solver not in ("clarabel", "cholesky"):
            raise ValueError(f"step_solver must be 'clarabel' or 'cholesky', got {settings.step_solver!r}")
        self.n, self.m, self.pitch, self.settings = n, m, pitch, settings
        hu, hv = 0.5 * m * pitch, 0.5 * n * pitch
        self.ku, self.nbu = _basis_1d(-hu, hu, settings.knots_per_pitch * m)
        self.kv, self.nbv = _basis_1d(-hv, hv, settings.knots_per_pitch * n)
        self.nb = nb = self.nbu * self.nbv
        self.uc = (np.arange(m) - (m - 1) / 2) * pitch
        self.vc = (np.arange(n) - (n - 1) / 2) * pitch
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
        ne, me = settings.equilibrium_per_pitch * n, settings.equilibrium_per_pitch * m
        ev, eu = np.meshgrid((np.arange(ne) + 0.5) / ne * 2 * hv - hv, (np.arange(me) + 0.5) / me * 2 * hu - hu,
                             indexing="ij")
        self._points = self._design(eu.ravel(), ev.ravel(), _DERIVATIVES)
        self._eq_scale = settings.equilibrium_weight * np.sqrt(4 * hu * hv / eu.size)
        # ∫|∇³f|² as an exact quadratic form (per component).
        gram_u = [_gram(self.ku, self.nbu, d) for d in range(4)]
        gram_v = [_gram(self.kv, self.nbv, d) for d in range(4)]
        smooth = sum(wt * np.kron(gram_v[dv], gram_u[du]) for (du, dv), wt in _SMOOTH.items())
        self._smooth = settings.smooth_weight ** 2 * smooth
        # The sensor frame fixes the rigid motion every other term leaves free: the material
        # centre at the origin, its normal +z, the tangent of +u along +x (U = V = w = 0,
        # V_u = w_u = w_v = 0 at (0, 0)), as heavily weighted linear rows.
        at0 = self._design(np.zeros(1), np.zeros(1), ((0, 0), (1, 0), (0, 1)))
        zero = np.zeros((1, nb))
        frame = np.vstack([
            np.hstack([at0[(0, 0)], zero, zero]), np.hstack([zero, at0[(0, 0)], zero]),
            np.hstack([zero, zero, at0[(0, 0)]]), np.hstack([zero, at0[(1, 0)], zero]),
            np.hstack([zero, zero, at0[(1, 0)]]), np.hstack([zero, zero, at0[(0, 1)]]),
        ])
        self._frame = 1e6 * frame.T @ frame
        self._centres = _rows(_design(self.ku, self.nbu, np.tile(self.uc, n), 0),
                              _design(self.kv, self.nbv, np.repeat(self.vc, m), 0))

    def _design(self, pu: np.ndarray, pv: np.ndarray, ders) -> dict:
        return {d: _rows(_design(self.ku, self.nbu, pu, d[0]), _design(self.kv, self.nbv, pv, d[1])) for d in ders}

    @staticmethod
    def _x(c: np.ndarray, mats: dict) -> dict:
        """Derivatives of the position at the points of ``mats``, (P, 3) each; c is (3, nb)."""
        out = {}
        for d, mat in mats.items():
            x = mat @ c.T
            if d == (1, 0):
                x[:, 0] += 1.0
            elif d == (0, 1):
                x[:, 1] += 1.0
            out[d] = x
        return out

    def gauge_model(self, c: np.ndarray, jacobian: bool = False):
        """Turning and stretch of every gauge (2, n·m) each; with ``jacobian`` also their
        derivatives by the coefficients, (2, n·m, 3·nb) each."""
        turning, stretch, jt, js = [], [], [], []
        nm, q = self.n * self.m, self.q
        for a, mats in enumerate(self._gauge):
            x = self._x(c, mats)
            da = (1, 0) if a == 0 else (0, 1)
            daa = (2, 0) if a == 0 else (0, 2)
            xu, xv, xa, xaa = x[(1, 0)], x[(0, 1)], x[da], x[daa]
            length = np.linalg.norm(xa, axis=1)
            stretch.append((length.reshape(nm, q) @ self.wq))
            if not jacobian:
                turning.append(_turning(xu, xv, xaa, xa).reshape(nm, q) @ self.wq)
                continue
            # turning depends on x_u, x_v, x_aa (x_a is x_u or x_v)
            args = [xu, xv, xaa]
            val, (g_u, g_v, g_aa) = _local_jacobian(lambda p, r, t: _turning(p, r, t, p if a == 0 else r), args)
            turning.append(val.reshape(nm, q) @ self.wq)
            rows_t = np.zeros((nm * q, 3 * self.nb))
            rows_s = np.zeros((nm * q, 3 * self.nb))
            ds = xa / length[:, None]
            for k in range(3):
                cols = slice(k * self.nb, (k + 1) * self.nb)
                rows_t[:, cols] = (g_u[:, k:k + 1] * mats[(1, 0)] + g_v[:, k:k + 1] * mats[(0, 1)]
                                   + g_aa[:, k:k + 1] * mats[daa])
                rows_s[:, cols] = ds[:, k:k + 1] * mats[da]
            jt.append(np.einsum("gqc,q->gc", rows_t.reshape(nm, q, -1), self.wq))
            js.append(np.einsum("gqc,q->gc", rows_s.reshape(nm, q, -1), self.wq))
        if jacobian:
            return np.array(turning), np.array(stretch), np.array(jt), np.array(js)
        return np.array(turning), np.array(stretch)

    def equilibrium(self, c: np.ndarray, jacobian: bool = False):
        """Weighted tangential equilibrium residuals (2·P,), and with ``jacobian`` (2·P, 3·nb)."""
        x = self._x(c, self._points)
        args = [x[d] for d in _DERIVATIVES]
        nu = self.settings.poisson
        if not jacobian:
            return self._eq_scale * _tangential_divergence(args[0], args[1], args[2], args[3], args[4], nu).ravel()
        val, grads = _local_jacobian(lambda xu, xv, xuu, xuv, xvv: _tangential_divergence(xu, xv, xuu, xuv, xvv, nu), args)
        p = args[0].shape[0]
        jac = np.zeros((2, p, 3 * self.nb))
        for d, g in zip(_DERIVATIVES, grads):
            mat = self._points[d]
            for k in range(3):
                jac[:, :, k * self.nb:(k + 1) * self.nb] += g[:, :, k, None] * mat[None]
        return self._eq_scale * val.ravel(), self._eq_scale * jac.reshape(2 * p, -1)

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

    def nodes(self, c: np.ndarray) -> np.ndarray:
        """Cell-centre positions (n, m, 3)."""
        uu, vv = np.tile(self.uc, self.n), np.repeat(self.vc, self.m)
        pos = self._centres @ c.T
        pos[:, 0] += uu
        pos[:, 1] += vv
        return pos.reshape(self.n, self.m, 3)

    def evaluate(self, c: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions and first derivatives x_u, x_v at material points (u, v), (P, 3) each."""
        mats = self._design(np.asarray(u, float), np.asarray(v, float), ((0, 0), (1, 0), (0, 1)))
        x = self._x(c, mats)
        x[(0, 0)][:, 0] += u
        x[(0, 0)][:, 1] += v
        return x[(0, 0)], x[(1, 0)], x[(0, 1)]

    def coeffs_from_positions(self, u: np.ndarray, v: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Least-squares coefficients (3, nb) of positions (P, 3) at material points (P,)."""
        design = _rows(_design(self.ku, self.nbu, u, 0), _design(self.kv, self.nbv, v, 0))
        target = np.stack([pos[:, 0] - u, pos[:, 1] - v, pos[:, 2]], axis=-1)
        gram = design.T @ design + 1e-9 * np.eye(self.nb)
        return sla.solve(gram, design.T @ target, assume_a="pos").T

    def fit(self, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_t: float, sigma_s: float,
            start: np.ndarray, max_steps: int | None = None) -> PositionResult:
        """Gauss-Newton from ``start`` (3, nb). turning, stretch, valid: (2, n, m) unit data."""
        st = self.settings
        steps_allowed = st.max_steps if max_steps is None else max_steps
        nb3 = 3 * self.nb
        valid_rows = np.concatenate([valid.reshape(2, -1).ravel()] * 2)
        data = np.concatenate([turning.reshape(-1), stretch.reshape(-1)])
        scale = np.concatenate([np.full(turning.size, sigma_t), np.full(stretch.size, sigma_s)])
        smooth = sla.block_diag(self._smooth, self._smooth, self._smooth) + self._frame
        c = np.asarray(start, float).reshape(-1).copy()
        damping = 1e-4  # Levenberg-Marquardt: relative to the diagonal; adapted per step
        status = "max_steps"
        steps = 0
        cost = None
        for steps in range(1, steps_allowed + 1):
            t, s, jt, js = self.gauge_model(c.reshape(3, -1), jacobian=True)
            r_g = (np.concatenate([t.ravel(), s.ravel()]) - data) / scale
            j_g = np.concatenate([jt.reshape(-1, nb3), js.reshape(-1, nb3)]) / scale[:, None]
            r_g, j_g = r_g[valid_rows], j_g[valid_rows]
            r_e, j_e = self.equilibrium(c.reshape(3, -1), jacobian=True)
            if cost is None:
                cost = self._cost(r_g, r_e, c, smooth)
            # The Gauss-Newton matrix, formed once per step: gauges inside the Huber threshold
            # weigh fully, those beyond it not at all (the loss's curvature there).
            w_g = (np.abs(r_g) <= st.huber).astype(float) if st.step_solver == "clarabel" else np.ones(r_g.size)
            prior_h = j_e.T @ j_e + smooth
            prior_g = j_e.T @ r_e + smooth @ c
            normal = prior_h + (j_g * w_g[:, None]).T @ j_g
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
                    delta = _clarabel_step(prior_h + damping * np.diag(diag), prior_g, r_g, j_g, st.huber, None)
                trial = c + delta
                if self._accelerate:
                    trial = trial + self._acceleration(c, delta, r_g, j_g, r_e, j_e, w_g, data, scale, valid_rows,
                                                       factor)
                new_cost = self._total_cost(trial, data, scale, valid_rows, smooth)
                if new_cost <= cost:
                    break
                damping *= 8.0
            else:
                status = "stalled"
                break
            c, improvement, cost = trial, cost - new_cost, new_cost
            damping = max(damping / 4.0, 1e-9)
            if improvement <= 1e-10 * max(cost, 1.0):
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

    _accelerate = True

    def _residuals(self, c, data, scale, valid_rows) -> tuple[np.ndarray, np.ndarray]:
        t, s = self.gauge_model(c.reshape(3, -1))
        r_g = ((np.concatenate([t.ravel(), s.ravel()]) - data) / scale)[valid_rows]
        return r_g, self.equilibrium(c.reshape(3, -1))

    def _acceleration(self, c, delta, r_g, j_g, r_e, j_e, w_g, data, scale, valid_rows, factor) -> np.ndarray:
        """Geodesic acceleration (Transtrum & Sethna): the second-order correction along δ, from one
        more residual evaluation and the step's own factorisation; it lets a step follow a curved
        valley (the twist family)."""
        h = 0.1
        g2, e2 = self._residuals(c + h * delta, data, scale, valid_rows)
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

    def _total_cost(self, c, data, scale, valid_rows, smooth) -> float:
        t, s = self.gauge_model(c.reshape(3, -1))
        r_g = ((np.concatenate([t.ravel(), s.ravel()]) - data) / scale)[valid_rows]
        r_e = self.equilibrium(c.reshape(3, -1))
        return self._cost(r_g, r_e, c, smooth)


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
