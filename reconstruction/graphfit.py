"""A sheet pushed out of plane, fitted as a height graph to every gauge's turning *and* stretch.

Model (docs/reconstruction.md, step 0): material point (u, v) of a clamped film pressed out of
its plane moves along the base normal, x = (u, v, w(u, v)).  Then every gauge's two numbers
are exact functionals of the height w (a = the gauge's direction, b = across it,
λ_a = √(1 + w_a²), W = √(1 + w_u² + w_v²)):

* turning per material length (normal curvature integrated over arc length):
  Θ/g = −(1/g) ∫ w_aa / (W λ_a) da;
* stretch ratio L/g = (1/g) ∫ λ_a da.

The stretch is what the curvature-field model (steps 1-5) can only smooth: its pattern carries
the sub-gauge distribution of slope, so a bump whose peak bend radius is shorter than a gauge is
resolved here (5 mm / FWHM 15 mm bumps: 0.19 → 0.015 mm mean error).  w is a bicubic B-spline
with knots every pitch/3 over the whole sheet; the fit minimises

    Σ_gauges ((Θ/g)_model − Θ/g)²/σ_Θ² + ((L/g)_model − L/g)²/σ_L² + ∫∫ |∇³w|² du dv

by Gauss-Newton with a backtracking line search, from the linear (small-slope) fit of the
turning data alone or from the previous frame's graph.  The fit is *accepted* only when it
explains the data to within the sensor's noise (mean squared normalised residual of the
turning and of the stretch each at most :data:`ACCEPT_CHI2`); otherwise the sheet is not a graph
(laid on isometrically, stretched in its plane, a glitching gauge, ...) and the general model
takes over.  Small problems only: the unknowns grow with the cells, (3N + 3)(3M + 3), so the
fit is offered up to :data:`MAX_CELLS` cells (``Reconstructor(..., graph_fit=True)``).
"""
from __future__ import annotations

import math
from collections import OrderedDict
from typing import NamedTuple

import numpy as np
import scipy.linalg
from scipy.interpolate import BSpline

__all__ = ["GraphFit", "GraphResult", "ACCEPT_CHI2", "MAX_CELLS", "TWIST_SIGN_FLOOR"]

#: Acceptance: mean squared residual of the turning and of the stretch, each in units of its
#: noise variance.  Measured (5×5, noise s.d. 0.0057 %): converged graphs 0.3-3 (noise-free
#: far below); sheets that are not graphs (isometric cylinders, geodesically laid caps and
#: bumps) 300 and above; troughs stopped short of convergence 5-15 (with errors up to 0.4 mm:
#: hence 4, not more).
ACCEPT_CHI2 = 4.0
#: Size limit (cells) of the graph fit: a 5×5 sheet has 324 unknowns, 8×8 729.
MAX_CELLS = 64
#: A graph twist (mean w_uv, 1/mm) smaller than this has no sign worth contradicting twist_sign.
TWIST_SIGN_FLOOR = 1e-4
_KNOTS_PER_PITCH = 3
_QUADRATURE = (4, 2)  # Gauss-Legendre nodes per panel, panels per gauge
_PRIOR_WEIGHTS = ((3, 0, 1.0), (2, 1, 3.0), (1, 2, 3.0), (0, 3, 1.0))  # ∫|∇³w|², isotropic
_PRIOR_SCALE = 300.0  # (mm units) far below the data where gauges are; it keeps the in-between modes stiff enough for Gauss-Newton (1: steps overshoot by 10⁶)
_RIDGE = 1e-6  # keeps the normal equations definite along modes no datum sees
_MAX_STEPS = 10  # from the linear fit
_GIVE_UP_CHI2 = 50.0 * ACCEPT_CHI2  # after _GIVE_UP_AFTER steps: not a graph, stop paying
_GIVE_UP_AFTER = 4
_WARM_STEPS = 2  # from the previous frame
_WARM_CURVATURE = (1.0, 1.0)
_COLD_CURVATURE = (0.0, 0.0)
_SCREEN_SIGMAS = 2.0  # implied mean stretch below this many noise s.d.: small slopes, no fit
_SCREEN_SHORT = 6.0  # a gauge shorter by this many noise s.d.: not a graph
_SCREEN_RATIO = (0.5, 4.0)  # measured / implied stretch outside: not a graph
_TOLERANCE = 1e-3  # stop when a step lowers the objective by less than this per gauge pair
_REUSE_RATIO = 0.3  # keep the factorised matrix while each drop is below this share of the last


class GraphResult(NamedTuple):
    """Outcome of one graph fit."""

    accepted: bool
    coeffs: np.ndarray  # (nbv·nbu,) B-spline coefficients of w (mm)
    chi2_turning: float  # mean squared normalised residual
    chi2_stretch: float
    iterations: int
    twist: float  # mean w_uv over the cell-centre region (1/mm): the sign of a mirror pair
    turning_rms: float  # RMS turning misfit per length (1/mm)
    how: str  # "warm" (previous frame), "linear" / "general" (cold start), or why not accepted
    factor: object  # the last Gauss-Newton matrix factorised (the next frame starts with it)
    objective: float  # the minimised objective (data misfit and prior), to rank cold starts


def _rotation(g) -> np.ndarray:
    """Rotation matrix of the rotation vector g (Rodrigues)."""
    g = np.asarray(g, dtype=float)
    angle = float(np.linalg.norm(g))
    if angle < 1e-15:
        return np.eye(3)
    k = g / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def _basis_1d(lo: float, hi: float, intervals: int) -> tuple[np.ndarray, int]:
    knots = np.concatenate([[lo] * 3, np.linspace(lo, hi, intervals + 1), [hi] * 3])
    return knots, len(knots) - 4


def _design(knots: np.ndarray, nb: int, x: np.ndarray, der: int) -> np.ndarray:
    """(len(x), nb): the der-th derivative of every cubic B-spline at x (setup only)."""
    out = np.empty((len(x), nb))
    eye = np.eye(nb)
    for k in range(nb):
        out[:, k] = BSpline(knots, eye[k], 3, extrapolate=True)(x, nu=der)
    return out


def _gram(knots: np.ndarray, nb: int, der: int) -> np.ndarray:
    """∫ B_i^(der) B_j^(der) over the knot range, exact (Gauss-Legendre per interval)."""
    breaks = np.unique(knots)
    x, w = np.polynomial.legendre.leggauss(4)
    pts = ((breaks[:-1, None] + breaks[1:, None]) + (breaks[1:, None] - breaks[:-1, None]) * x) / 2
    wts = (breaks[1:, None] - breaks[:-1, None]) / 2 * w
    d = _design(knots, nb, pts.ravel(), der)
    return d.T @ (d * wts.ravel()[:, None])


class GraphFit:
    """Per-geometry operators of the graph fit (built once) and the per-frame fit."""

    def __init__(self, n: int, m: int, pitch: float, gauge_length: float, fine_u: np.ndarray, fine_v: np.ndarray,
                 inner: tuple[slice, slice], compiled=None):
        self.n, self.m = n, m
        self._compiled = compiled
        ku, self.nbu = _basis_1d(-0.5 * m * pitch, 0.5 * m * pitch, _KNOTS_PER_PITCH * m)
        kv, self.nbv = _basis_1d(-0.5 * n * pitch, 0.5 * n * pitch, _KNOTS_PER_PITCH * n)
        nbu, nbv = self.nbu, self.nbv
        self.size = nc = nbu * nbv
        uc = (np.arange(m) - (m - 1) / 2.0) * pitch
        vc = (np.arange(n) - (n - 1) / 2.0) * pitch
        xq, wq = np.polynomial.legendre.leggauss(_QUADRATURE[0])
        panels = _QUADRATURE[1]
        s = np.concatenate([((p + (xq + 1.0) / 2.0) / panels - 0.5) * gauge_length for p in range(panels)])
        self.wq = np.concatenate([wq / (2.0 * panels)] * panels)  # weights of a mean over the gauge
        q = len(s)
        # Quadrature points of every gauge, (2, n, m, q): u gauges along u, v gauges along v.
        pu = np.empty((2, n, m, q))
        pv = np.empty((2, n, m, q))
        pu[0] = uc[None, :, None] + s
        pv[0] = vc[:, None, None]
        pu[1] = uc[None, :, None]
        pv[1] = vc[:, None, None] + s
        pu, pv = pu.reshape(-1), pv.reshape(-1)
        bu = [_design(ku, nbu, pu, d) for d in range(3)]
        bv = [_design(kv, nbv, pv, d) for d in range(3)]

        def rows(a: int, b: int) -> np.ndarray:  # ∂u^a ∂v^b w at every point, (P, nc)
            return (bv[b][:, :, None] * bu[a][:, None, :]).reshape(len(pu), nc)

        g = 2 * n * m
        half = g // 2
        # along (a), across (b), second derivative along (aa): u gauges then v gauges
        d_a = np.concatenate([rows(1, 0)[: half * q], rows(0, 1)[half * q:]])
        d_b = np.concatenate([rows(0, 1)[: half * q], rows(1, 0)[half * q:]])
        d_aa = np.concatenate([rows(2, 0)[: half * q], rows(0, 2)[half * q:]])
        # Each gauge touches a few dozen coefficients: keep them as a local dense block.
        touched = [np.flatnonzero(np.abs(np.concatenate([d_a[k * q:(k + 1) * q], d_b[k * q:(k + 1) * q],
                                                         d_aa[k * q:(k + 1) * q]])).sum(0)) for k in range(g)]
        width = max(len(t) for t in touched)
        self.idx = np.zeros((g, width), dtype=np.int64)
        self.da, self.db, self.daa = (np.zeros((g, q, width)) for _ in range(3))
        for k, t in enumerate(touched):
            self.idx[k, : len(t)] = t
            self.idx[k, len(t):] = t[0]  # padding: weight 0 on a real index
            sl = slice(k * q, (k + 1) * q)
            self.da[k, :, : len(t)] = d_a[sl][:, t]
            self.db[k, :, : len(t)] = d_b[sl][:, t]
            self.daa[k, :, : len(t)] = d_aa[sl][:, t]
        self.bandwidth = int(max((t.max() - t.min()) for t in touched))
        # Prior ∫∫|∇³w|² as Kronecker products of 1D Gram matrices, plus a ridge and a pin of
        # the centre coefficient (the height offset is seen by no datum).
        gu = [_gram(ku, nbu, d) for d in range(4)]
        gv = [_gram(kv, nbv, d) for d in range(4)]
        prior = _PRIOR_SCALE * sum(wt * np.kron(gv[b], gu[a]) for a, b, wt in _PRIOR_WEIGHTS)
        prior[np.diag_indices(nc)] += _RIDGE
        self.pin = (nbv // 2) * nbu + nbu // 2
        prior[self.pin, self.pin] += 1.0
        self.prior = prior
        nz_i, nz_j = np.nonzero(np.abs(prior) > 0)
        self.bandwidth = int(max(self.bandwidth, np.max(np.abs(nz_i - nz_j))))
        bw = self.bandwidth
        self.prior_band = np.zeros((bw + 1, nc))
        for d in range(bw + 1):
            self.prior_band[d, : nc - d] = np.diagonal(prior, -d)
        # Linear start: the turning data alone in the small-slope model, Θ/g ≈ −mean(w_aa).
        self._j0 = -np.einsum("q,gql->gl", self.wq, self.daa)
        self._no_band = np.zeros((1, 1))
        self._starts: OrderedDict[bytes, np.ndarray] = OrderedDict()
        # Fine-grid evaluation w, w_u, w_v (separable) and the mean twist over the inner region.
        self._fine_u, self._fine_v = np.asarray(fine_u, float), np.asarray(fine_v, float)
        self._fu = [_design(ku, nbu, np.asarray(fine_u, float), d) for d in range(2)]
        self._fv = [_design(kv, nbv, np.asarray(fine_v, float), d) for d in range(2)]
        self._twist = np.kron(self._fv[1][inner[0]].mean(0), self._fu[1][inner[1]].mean(0))
        # Least-squares projection of fine-grid heights onto the basis (separable).
        self._project_u = np.linalg.pinv(self._fu[0])
        self._project_v = np.linalg.pinv(self._fv[0])
        self._fine_uv = np.stack(np.broadcast_arrays(self._fine_u[None, :], self._fine_v[:, None]), axis=-1).reshape(-1, 2)

    # ---------------------------------------------------------------- per frame
    def _start(self, turning: np.ndarray, valid: np.ndarray, sigma_t: float) -> np.ndarray:
        key = valid.tobytes()
        op = self._starts.get(key)
        if op is None:
            w = valid.astype(float) / sigma_t
            j = np.zeros((len(w), self.size))
            np.add.at(j, (np.repeat(np.arange(len(w)), self.idx.shape[1]), self.idx.ravel()),
                      (self._j0 * w[:, None]).ravel())
            a = j.T @ j + self.prior
            op = scipy.linalg.cho_solve(scipy.linalg.cho_factor(a, check_finite=False), j.T * w, check_finite=False)
            self._starts[key] = op
            if len(self._starts) > 16:
                self._starts.popitem(last=False)
        return op @ np.where(valid, turning, 0.0)

    def _model(self, c: np.ndarray, want_jacobian: bool):
        """Numpy reference: model turning and stretch per gauge, and their local Jacobian rows."""
        vals = c[self.idx]
        a = np.einsum("gql,gl->gq", self.da, vals)
        b = np.einsum("gql,gl->gq", self.db, vals)
        aa = np.einsum("gql,gl->gq", self.daa, vals)
        lam2 = 1.0 + a * a
        w2 = lam2 + b * b
        lam = np.sqrt(lam2)
        inv = 1.0 / (np.sqrt(w2) * lam)
        turning = (-aa * inv) @ self.wq
        stretch = lam @ self.wq
        if not want_jacobian:
            return turning, stretch
        wq = self.wq
        d_a = (aa * inv) * (a / w2 + a / lam2)
        d_b = (aa * inv) * (b / w2)
        jt = (np.einsum("gq,gql->gl", wq * -inv, self.daa) + np.einsum("gq,gql->gl", wq * d_a, self.da)
              + np.einsum("gq,gql->gl", wq * d_b, self.db))
        js = np.einsum("gq,gql->gl", wq * (a / lam), self.da)
        return turning, stretch, jt, js

    def _objective(self, c, turning, stretch, w_t, w_s) -> tuple[float, np.ndarray, np.ndarray]:
        if self._compiled is not None:
            g = len(turning)
            res = np.empty(2 * g)
            self._compiled.graph_residuals(c, self.idx, self.da, self.db, self.daa, self.wq, turning, stretch,
                                           w_t, w_s, res)
            rt, rs = res[:g], res[g:]
        else:
            tm, sm = self._model(c, False)
            rt, rs = (tm - turning) * w_t, (sm - stretch) * w_s
        return 0.5 * float(rt @ rt + rs @ rs + c @ (self.prior @ c)), rt, rs

    def _linearise(self, c, turning, stretch, w_t, w_s, with_matrix: bool, curvature=(0.0, 0.0)):
        """Gradient Jᵀr + Pc of the objective at c and, ``with_matrix``, the Cholesky factor of
        the Gauss-Newton matrix JᵀJ + P (None when it is not positive definite)."""
        rhs = self.prior @ c
        factor = None
        if self._compiled is not None:
            band = self.prior_band.copy() if with_matrix else self._no_band
            self._compiled.graph_normal_equations(c, self.idx, self.da, self.db, self.daa, self.wq, turning,
                                                  stretch, w_t, w_s, band, rhs, with_matrix,
                                                  np.asarray(curvature, dtype=float))
            if with_matrix:
                try:
                    factor = ("band", scipy.linalg.cholesky_banded(band, lower=True, check_finite=False))
                except (np.linalg.LinAlgError, ValueError):
                    factor = None
            return rhs, factor
        tm, sm, jt, js = self._model(c, True)
        rt, rs = (tm - turning) * w_t, (sm - stretch) * w_s
        g = len(turning)
        j = np.zeros((2 * g, self.size))
        rows = np.repeat(np.arange(g), self.idx.shape[1])
        np.add.at(j, (rows, self.idx.ravel()), (jt * w_t[:, None]).ravel())
        np.add.at(j, (rows + g, self.idx.ravel()), (js * w_s[:, None]).ravel())
        rhs += j.T @ np.concatenate([rt, rs])
        if with_matrix:
            # r ∂²r of the stretch residuals r > 0 (see kernels.graph_normal_equations)
            a = np.einsum("gql,gl->gq", self.da, c[self.idx])
            cr = np.where(rs > 0.0, curvature[0] * rs, -curvature[1] * rs)
            cw = (cr * w_s)[:, None] * self.wq / (1.0 + a * a) ** 1.5
            blocks = np.einsum("gq,gqk,gql->gkl", cw, self.da, self.da)
            curv = np.zeros((self.size, self.size))
            np.add.at(curv, (self.idx[:, :, None], self.idx[:, None, :]), blocks)
            try:
                factor = ("dense", scipy.linalg.cho_factor(j.T @ j + curv + self.prior, lower=True, check_finite=False))
            except (np.linalg.LinAlgError, ValueError):
                factor = None
        return rhs, factor

    @staticmethod
    def _solve(factor, rhs: np.ndarray) -> np.ndarray:
        kind, f = factor
        if kind == "band":
            return scipy.linalg.cho_solve_banded((f, True), rhs, check_finite=False)
        return scipy.linalg.cho_solve(f, rhs, check_finite=False)

    def _descend(self, c, turning, stretch, w_t, w_s, n_valid: int, max_steps: int, factor=None,
                 curvature=(0.0, 0.0)):
        """Gauss-Newton with a backtracking line search; the factorised matrix is reused while
        the steps keep shrinking fast (it changes little near the optimum) and refreshed
        otherwise; ``factor``: one to start with (the previous frame's).  Returns (c, rt, rs,
        steps, the last factor computed)."""
        f0, rt, rs = self._objective(c, turning, stretch, w_t, w_s)
        fresh, last = False, math.inf
        steps = 0
        tol = _TOLERANCE * n_valid
        while steps < max_steps:
            if factor is None:
                rhs, factor = self._linearise(c, turning, stretch, w_t, w_s, True, curvature)
                if factor is None:
                    break
                fresh = True
            else:
                rhs, _ = self._linearise(c, turning, stretch, w_t, w_s, False)
                fresh = False
            dc = self._solve(factor, rhs)
            t = 1.0
            f1, rt1, rs1 = self._objective(c - dc, turning, stretch, w_t, w_s)
            if not f1 < f0:
                if not fresh:
                    factor = None  # stale matrix: linearise again before damping
                    continue
                while not f1 < f0 and t > 1e-3:
                    t *= 0.5
                    f1, rt1, rs1 = self._objective(c - t * dc, turning, stretch, w_t, w_s)
                if not f1 < f0:
                    break
            c = c - t * dc
            rt, rs = rt1, rs1
            steps += 1
            drop, f0 = f0 - f1, f1
            if drop <= tol:
                break
            if steps >= _GIVE_UP_AFTER and float(rs @ rs) / n_valid > _GIVE_UP_CHI2:
                break
            if t < 1.0 or drop > _REUSE_RATIO * last:
                factor = None
            last = drop
        return c, rt, rs, steps, factor, f0

    def prepare(self, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_t: float,
                sigma_s: float) -> tuple:
        """The unit data (2, N, M) (``engine.unit_data``) as the fits take them, with noise s.d.
        ``sigma_t`` (turning per length, 1/mm) and ``sigma_s`` (stretch)."""
        turning = np.ascontiguousarray(turning, dtype=float).ravel()
        stretch = np.ascontiguousarray(stretch, dtype=float).ravel()
        valid = np.asarray(valid, dtype=bool).ravel()
        return (np.where(valid, turning, 0.0), np.where(valid, stretch, 1.0), valid / sigma_t, valid / sigma_s,
                valid, max(int(valid.sum()), 1), float(sigma_t), float(sigma_s))

    def fit_warm(self, data: tuple, start: tuple, twist_sign: float | None = None) -> GraphResult:
        """A few Gauss-Newton steps from the previous frame's accepted graph, ``start`` =
        (coeffs, factor) (``GraphResult.coeffs`` and ``.factor``)."""
        turning, stretch, w_t, w_s, valid, n_valid, sigma_t, _ = data
        if np.shape(start[0]) != (self.size,):
            raise ValueError(f"a warm start needs {self.size} coefficients, got shape {np.shape(start[0])}")
        out = self._descend(np.array(start[0], dtype=float), turning, stretch, w_t, w_s, n_valid, _WARM_STEPS, start[1],
                            _WARM_CURVATURE)
        return self._judge(self._result(*out, n_valid, sigma_t, "warm"), twist_sign)

    def fit_cold(self, data: tuple, general: np.ndarray | None = None, twist_sign: float | None = None) -> GraphResult:
        """Fit from the linear fit of the turning data and, given ``general`` (the general
        model's fine-grid positions (nf, mf, 3), any rigid frame), from that surface as well;
        the accepted fit with the lower objective wins.  The two starts fail differently: the
        linear one has no twist (steep twisted quadrics can end in a wrong basin), the general
        model's smooths sub-gauge features (sharp bumps can end in a wrong basin)."""
        turning, stretch, w_t, w_s, valid, n_valid, sigma_t, sigma_s = data
        starts = [("linear", self._start(turning, valid, sigma_t))]
        if general is not None:
            c = self.coeffs_from_positions(general)
            if np.isfinite(c).all():
                starts.append(("general", c))
        reasons = [self._screen(c, stretch, valid, sigma_s) for _, c in starts]
        if all(reasons):
            return GraphResult(False, starts[0][1], math.inf, math.inf, 0, 0.0, math.inf, reasons[-1], None, math.inf)
        results = [self._judge(self._result(*self._descend(c, turning, stretch, w_t, w_s, n_valid, _MAX_STEPS,
                                                           curvature=_COLD_CURVATURE),
                                            n_valid, sigma_t, how), twist_sign)
                   for (how, c), why in zip(starts, reasons) if not why]
        accepted = [r for r in results if r.accepted]
        if accepted:
            return min(accepted, key=lambda r: r.objective)
        closest = min(results, key=lambda r: r.chi2_stretch)
        screened = [f"{how}: {why}" for (how, _), why in zip(starts, reasons) if why]
        return closest._replace(how="; ".join([r.how for r in results] + screened))

    def fit(self, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_t: float, sigma_s: float,
            start: tuple | None = None, general: np.ndarray | None = None,
            twist_sign: float | None = None) -> GraphResult:
        """Fit w to the unit data (2, N, M) (``engine.unit_data``): from ``start`` (the previous
        frame's (coeffs, factor)) first, then cold (:meth:`fit_cold`)."""
        data = self.prepare(turning, stretch, valid, sigma_t, sigma_s)
        if start is not None:
            warm = self.fit_warm(data, start, twist_sign)
            if warm.accepted:
                return warm
        return self.fit_cold(data, general, twist_sign)

    def coeffs_from_positions(self, pos: np.ndarray, passes: int = 4) -> np.ndarray:
        """Coefficients of the graph closest to a surface given by its fine-grid positions (nf,
        mf, 3) in any rigid frame.  The base frame is the one that puts every node over its own
        material point (u, v): alternating the rigid fit (Kabsch) of the nodes to (u, v, ẑ) and
        ẑ ← the nodes' heights in that frame (the heights are free, so each pass lowers the
        in-plane misfit alone); then the heights projected onto the basis."""
        p = np.asarray(pos, dtype=float).reshape(-1, 3)
        p = p - p.mean(axis=0)
        target = np.empty_like(p)
        target[:, :2] = self._fine_uv - self._fine_uv.mean(axis=0)
        target[:, 2] = 0.0  # first pass: the best plane
        moved = p
        for _ in range(passes):
            target[:, 2] -= target[:, 2].mean()
            u, _, vt = np.linalg.svd(p.T @ target)
            d = np.sign(np.linalg.det(u @ vt))
            rot = (u * np.array([1.0, 1.0, d])) @ vt  # p @ rot ≈ target
            moved = p @ rot
            target[:, 2] = moved[:, 2]
        z = moved[:, 2].reshape(len(self._fine_v), len(self._fine_u))
        c = (self._project_v @ z @ self._project_u.T).ravel()
        return c - c[self.pin]

    @staticmethod
    def _judge(res: GraphResult, twist_sign: float | None) -> GraphResult:
        if res.accepted and twist_sign is not None and res.twist * float(twist_sign) < -TWIST_SIGN_FLOOR:
            return res._replace(accepted=False, how=f"{res.how}: the graph's twist has the other sign than twist_sign")
        return res

    def _screen(self, c: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_s: float) -> str:
        """Why the sheet cannot be a graph ('' when it may be): in a graph no gauge shortens
        (λ_a ≥ 1), and the stretch the linear fit's slopes imply is what is measured, within a
        factor (measured: graphs 0.8-3, isometric sheets 0, sheets laid on a dome below 0).
        Sheets whose implied stretch is within the noise need no graph fit (small slopes)."""
        if self._compiled is not None:
            res = np.empty(2 * len(stretch))
            one = np.ones(len(stretch))
            self._compiled.graph_residuals(c, self.idx, self.da, self.db, self.daa, self.wq, np.zeros(len(stretch)),
                                           one, np.zeros(len(stretch)), one, res)
            implied = res[len(stretch):][valid]
        else:
            implied = self._model(c, False)[1][valid] - 1.0
        measured = stretch[valid] - 1.0
        if not implied.size or implied.mean() < _SCREEN_SIGMAS * sigma_s:
            return "small slopes"
        if measured.min() < -_SCREEN_SHORT * sigma_s:
            return "a gauge shortens"
        ratio = measured.sum() / implied.sum()
        if not _SCREEN_RATIO[0] <= ratio <= _SCREEN_RATIO[1]:
            return f"stretch {ratio:.2f} x the graph's"
        return ""

    def _result(self, c, rt, rs, steps: int, factor, objective: float, n_valid: int, sigma_t: float,
                how: str) -> GraphResult:
        if rt is None:
            return GraphResult(False, c, math.inf, math.inf, 0, 0.0, math.inf, how, None, math.inf)
        chi_t, chi_s = float(rt @ rt) / n_valid, float(rs @ rs) / n_valid
        accepted = bool(chi_t <= ACCEPT_CHI2 and chi_s <= ACCEPT_CHI2 and np.isfinite(c).all())
        return GraphResult(accepted, c, chi_t, chi_s, steps, float(self._twist @ c), math.sqrt(chi_t) * sigma_t,
                           how if accepted else f"{how}: misfit chi2 {chi_t:.3g} (turning), {chi_s:.3g} (stretch)",
                           factor, float(objective))

    def fine_positions(self, c: np.ndarray) -> np.ndarray:
        """x = (u, v, w) at every fine-grid node, (nf, mf, 3), base frame."""
        cm = c.reshape(self.nbv, self.nbu)
        w = self._fv[0] @ cm @ self._fu[0].T
        nf, mf = w.shape
        out = np.empty((nf, mf, 3))
        out[..., 0] = self._fine_u[None, :]
        out[..., 1] = self._fine_v[:, None]
        out[..., 2] = w
        return out
