"""Candidate model: the sheet's full 3D position fitted to every gauge, with tangential membrane
equilibrium as the prior for what the gauges do not measure (docs/reconstruction.md, "Toward
the full-position model").

Run: .venv/bin/python bench/equilibrium_prior.py [--cases saddle:0,poisson_0.3:1] [--nu 0.4,true,free]
     [--evaluations 400]

Each case is an elastic scene of bench/elastic_dataset.py (5×5 cells, 12 mm pitch, seed 2024;
``class:index``), noise-free.  The model: x(u, v) = (u + U, v + V, w), three bicubic B-splines
with knots every half pitch over the film (±30 mm), fitted by least squares (scipy's trust-region
reflective solver, the Jacobian by finite differences on its sparsity pattern) to

    Σ_gauges ((Θ/g)_model − Θ/g)²/σ_Θ² + ((L/g)_model − L/g)²/σ_L²
      + w_eq² Σ_points |t(x)|² + w_s² ∫∫ |∇³(U, V, w)|²,

where Θ/g and L/g are each gauge's exact turning and stretch along its 10 mm line (8-point
Gauss-Legendre), and t = (x_u, x_v)ᵀ ∂_a(S^{ab} x_b) is the tangential part of the divergence of
the membrane stress (Saint Venant-Kirchhoff, plane stress, shear modulus 1, Poisson's ratio ν),
which is zero for a film loaded only along its normal (frictionless mold, pressure).  It starts
from the default reconstruction's surface.  ν is the scene's own ("true"), a fixed value, or a
free parameter of the fit ("free", in [0, 0.5)).  It prints, per case and ν, the default
reconstruction's mean node error after the best rigid alignment and the fit's, with the fit's
time and the gauges' χ² per gauge (noise s.d. 0.0057 % strain).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))
import elastic_dataset as ed  # noqa: E402
from reconstruction import GAUGE, H, PITCH, node_errors  # noqa: E402

from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.reconstruction import reconstruct  # noqa: E402
from skinmap.reconstruction.engine import unit_data  # noqa: E402
from skinmap.reconstruction.graphfit import _basis_1d, _design  # noqa: E402

NOISE = 0.0057e-2
DERIVATIVES = ((1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
SMOOTH = {(3, 0): 1.0, (2, 1): 3.0, (1, 2): 3.0, (0, 3): 1.0}


def _rows(bu: np.ndarray, bv: np.ndarray) -> np.ndarray:
    return (bv[:, :, None] * bu[:, None, :]).reshape(bu.shape[0], -1)


class PositionFit:
    """The candidate model's operators for an n×m sheet (built once) and its residuals."""

    def __init__(self, n: int, m: int, w_eq: float = 1e3, w_s: float = 0.1, per_pitch: int = 2):
        self.n, self.m = n, m
        hu, hv = 0.5 * m * PITCH, 0.5 * n * PITCH
        self.ku, self.nbu = _basis_1d(-hu, hu, per_pitch * m)
        self.kv, self.nbv = _basis_1d(-hv, hv, per_pitch * n)
        self.nb = self.nbu * self.nbv
        uc = (np.arange(m) - (m - 1) / 2) * PITCH
        vc = (np.arange(n) - (n - 1) / 2) * PITCH
        xg, wg = np.polynomial.legendre.leggauss(8)
        s, self.wq = 0.5 * GAUGE * xg, wg / wg.sum()
        vv, uu = np.meshgrid(vc, uc, indexing="ij")
        self.gauges = [
            self._design((uu[..., None] + s).ravel(), np.repeat(vv.ravel(), s.size), DERIVATIVES),
            self._design(np.repeat(uu.ravel(), s.size), (vv[..., None] + s).ravel(), DERIVATIVES),
        ]
        ev, eu = np.meshgrid((np.arange(3 * n) + 0.5) / (3 * n) * 2 * hv - hv,
                             (np.arange(3 * m) + 0.5) / (3 * m) * 2 * hu - hu, indexing="ij")
        self.points = self._design(eu.ravel(), ev.ravel(), DERIVATIVES)
        self.smooth = self._design(eu.ravel(), ev.ravel(), tuple(SMOOTH))
        area = np.sqrt(4 * hu * hv / eu.size)
        self.w_eq, self.w_s = w_eq * area, w_s * area
        self.centres = _rows(_design(self.ku, self.nbu, np.tile(uc, n), 0), _design(self.kv, self.nbv, np.repeat(vc, m), 0))
        self.cu, self.cv = np.tile(uc, n), np.repeat(vc, m)

    def _design(self, pu: np.ndarray, pv: np.ndarray, ders) -> dict:
        return {d: _rows(_design(self.ku, self.nbu, pu, d[0]), _design(self.kv, self.nbv, pv, d[1])) for d in ders}

    def _x(self, c: np.ndarray, mats: dict) -> dict:
        nb = self.nb
        out = {}
        for d, mat in mats.items():
            x = np.stack([mat @ c[:nb], mat @ c[nb:2 * nb], mat @ c[2 * nb:3 * nb]], axis=-1)
            if d == (1, 0):
                x[:, 0] += 1.0
            if d == (0, 1):
                x[:, 1] += 1.0
            out[d] = x
        return out

    def gauge_data(self, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Turning per material length and stretch ratio of every gauge, (2, n, m) each."""
        turning, stretch = [], []
        for a, mats in enumerate(self.gauges):
            x = self._x(c, mats)
            xa, xaa = (x[(1, 0)], x[(2, 0)]) if a == 0 else (x[(0, 1)], x[(0, 2)])
            normal = np.cross(x[(1, 0)], x[(0, 1)])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            length = np.linalg.norm(xa, axis=1)
            turning.append(((-(xaa * normal).sum(1) / length).reshape(-1, self.wq.size) @ self.wq).reshape(self.n, self.m))
            stretch.append((length.reshape(-1, self.wq.size) @ self.wq).reshape(self.n, self.m))
        return np.array(turning), np.array(stretch)

    def equilibrium(self, c: np.ndarray, nu: float) -> np.ndarray:
        """The tangential components of ∂_a(S^{ab} x_b) at the collocation points."""
        x = self._x(c, self.points)
        xu, xv, xuu, xuv, xvv = (x[d] for d in DERIVATIVES)
        lam = 2.0 * nu / (1.0 - nu)
        e_uu, e_vv, e_uv = 0.5 * ((xu * xu).sum(1) - 1), 0.5 * ((xv * xv).sum(1) - 1), 0.5 * (xu * xv).sum(1)
        s_uu, s_vv, s_uv = lam * (e_uu + e_vv) + 2 * e_uu, lam * (e_uu + e_vv) + 2 * e_vv, 2 * e_uv
        euu_u, euu_v = (xuu * xu).sum(1), (xuv * xu).sum(1)
        evv_u, evv_v = (xuv * xv).sum(1), (xvv * xv).sum(1)
        euv_u = 0.5 * ((xuu * xv).sum(1) + (xu * xuv).sum(1))
        euv_v = 0.5 * ((xuv * xv).sum(1) + (xu * xvv).sum(1))
        ds_u = lam * (euu_u + evv_u) + 2 * euu_u + 2 * euv_v
        ds_v = lam * (euu_v + evv_v) + 2 * evv_v + 2 * euv_u
        div = (ds_u[:, None] * xu + ds_v[:, None] * xv + s_uu[:, None] * xuu + 2 * s_uv[:, None] * xuv
               + s_vv[:, None] * xvv)
        return np.concatenate([(div * xu).sum(1), (div * xv).sum(1)])

    def residuals(self, p: np.ndarray, data: tuple, nu: float | None) -> np.ndarray:
        turning, stretch, sig_t, sig_s = data
        c, nu_here = (p[:-1], float(p[-1])) if nu is None else (p, nu)
        t, s = self.gauge_data(c)
        nb = self.nb
        smooth = [np.sqrt(wt) * (self.smooth[d] @ c[k * nb:(k + 1) * nb]) for d, wt in SMOOTH.items() for k in range(3)]
        return np.concatenate([((t - turning) / sig_t).ravel(), ((s - stretch) / sig_s).ravel(),
                               self.w_eq * self.equilibrium(c, nu_here), self.w_s * np.concatenate(smooth), 1e-6 * c])

    def sparsity(self, free_nu: bool) -> sp.csr_matrix:
        nb, rows = self.nb, []

        def support(mats: dict, groups) -> list[np.ndarray]:
            mask = sum(np.abs(mat) > 0 for mat in mats.values())
            return [np.concatenate([k * nb + np.nonzero(mask[g].any(axis=0))[0] for k in range(3)]) for g in groups]

        q = self.wq.size
        per_gauge = [c for mats in self.gauges for c in support(mats, [slice(i * q, (i + 1) * q) for i in range(self.n * self.m)])]
        rows += per_gauge + per_gauge
        count = next(iter(self.points.values())).shape[0]
        per_point = support(self.points, [slice(i, i + 1) for i in range(count)])
        eq_rows = (len(rows), len(rows) + 2 * count)
        rows += per_point + per_point
        for mat in self.smooth.values():
            cols = [np.nonzero(np.abs(mat[i]) > 0)[0] for i in range(mat.shape[0])]
            rows += [col + k * nb for k in range(3) for col in cols]
        rows += [np.array([k]) for k in range(3 * nb)]
        r = np.concatenate([np.full(len(c), i) for i, c in enumerate(rows)])
        pattern = sp.csr_matrix((np.ones(r.size), (r, np.concatenate(rows))), shape=(len(rows), 3 * nb + free_nu))
        if free_nu:
            pattern = pattern.tolil()
            pattern[eq_rows[0]:eq_rows[1], 3 * nb] = 1
        return pattern.tocsr()

    def start(self, surf) -> np.ndarray:
        """Coefficients of a reconstructed surface (its positions on its own fine grid)."""
        vv, uu = np.meshgrid(surf._v, surf._u, indexing="ij")
        pos = surf.locate(np.stack([uu.ravel(), vv.ravel()], axis=-1))[0]
        design = _rows(_design(self.ku, self.nbu, uu.ravel(), 0), _design(self.kv, self.nbv, vv.ravel(), 0))
        target = np.stack([pos[:, 0] - uu.ravel(), pos[:, 1] - vv.ravel(), pos[:, 2]], axis=-1)
        return np.linalg.lstsq(design, target, rcond=None)[0].T.ravel()

    def nodes(self, c: np.ndarray) -> np.ndarray:
        nb = self.nb
        return np.stack([self.cu + self.centres @ c[:nb], self.cv + self.centres @ c[nb:2 * nb],
                         self.centres @ c[2 * nb:]], axis=-1).reshape(self.n, self.m, 3)


def run_case(fit: PositionFit, key: str, index: int, nu_modes: list[str], evaluations: int) -> None:
    plan = ed.class_plans(key, 2024, index + 1, fit.n)[index]
    shape, _, _ = ed.solve_scene(plan)
    eu, el = ph.gauge_strains(shape, fit.n, fit.m, PITCH, H, H, GAUGE)
    truth = ph.ground_truth(shape, fit.n, fit.m, PITCH).nodes
    kw = {} if plan.twist_sign is None else {"twist_sign": plan.twist_sign}
    surf = reconstruct(eu, el, PITCH, H, H, **kw)
    default_error = node_errors(surf.nodes, truth).mean()
    turning, stretch, _ = unit_data(eu, el, H, H, GAUGE)
    data = (turning, stretch, np.sqrt(2.0) * NOISE / (2 * H), NOISE * np.sqrt(2 * H * H) / (2 * H))
    true_nu = float(plan.elastic.get("poisson", 0.48))
    c0 = fit.start(surf)
    for mode in nu_modes:
        free = mode == "free"
        nu = None if free else (true_nu if mode == "true" else float(mode))
        p0 = np.concatenate([c0, [0.4]]) if free else c0
        lo, hi = np.full(p0.size, -np.inf), np.full(p0.size, np.inf)
        if free:
            lo[-1], hi[-1] = 0.0, 0.499
        t0 = time.perf_counter()
        sol = least_squares(fit.residuals, p0, args=(data, nu), method="trf", x_scale="jac", max_nfev=evaluations,
                            jac_sparsity=fit.sparsity(free), bounds=(lo, hi))
        seconds = time.perf_counter() - t0
        c = sol.x[:-1] if free else sol.x
        t, s = fit.gauge_data(c)
        chi2 = float((((t - turning) / data[2]) ** 2).sum() + (((s - stretch) / data[3]) ** 2).sum()) / (2 * t.size)
        error = node_errors(fit.nodes(c), truth).mean()
        nu_used = float(sol.x[-1]) if free else nu
        print(f"{plan.spec:58s} true nu {true_nu:.2f} | default {default_error:7.4f} | nu {mode:>5s} -> {nu_used:.3f}: "
              f"{error:7.4f} mm, chi2/gauge {chi2:.2g}, {seconds:.0f} s, {sol.nfev} evaluations", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="saddle:0,poisson_0.3:1", help="class:index of bench/elastic_dataset.py, comma-separated")
    ap.add_argument("--nu", default="true,0.4,free", help="Poisson's ratio of the prior: true, a number, or free")
    ap.add_argument("--evaluations", type=int, default=400, help="solver evaluations per fit")
    args = ap.parse_args()
    fit = PositionFit(5, 5)
    for case in args.cases.split(","):
        key, index = case.split(":")
        run_case(fit, key, int(index), args.nu.split(","), args.evaluations)


if __name__ == "__main__":
    main()
