"""Per-geometry precomputation: the fine material grid, its linear operators and factorisations.

Everything here depends only on (N, M, pitch, gauge length, subdivision, regularisation weights,
valid-gauge mask), never on the measured strains, so it is built once and reused every frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import numpy as np
import scipy.sparse as sp

from .leaveout import IllConditioned, LeaveOut
from .linalg import FixedSolver

__all__ = ["FineGrid", "hat_average_weights"]


def _hat_cdf(x: np.ndarray) -> np.ndarray:
    """Integral from -inf to x of the unit hat function max(0, 1 - |t|)."""
    x = np.clip(x, -1.0, 1.0)
    return np.where(x <= 0.0, 0.5 * (1.0 + x) ** 2, 1.0 - 0.5 * (1.0 - x) ** 2)


def hat_average_weights(offsets: np.ndarray, spacing: float, length: float) -> np.ndarray:
    """Weights w_k such that Σ w_k f_k is the mean over [-length/2, length/2] of the
    piecewise-linear interpolant of samples f_k taken at ``offsets`` (uniform ``spacing``)."""
    lo = (-0.5 * length - offsets) / spacing
    hi = (0.5 * length - offsets) / spacing
    return (_hat_cdf(hi) - _hat_cdf(lo)) * spacing / length


def _second_differences(nf: int, mf: int) -> sp.csr_matrix:
    """Stacked second-difference operators (uu, vv, and √2·uv) on an nf × mf node grid."""
    def d2(k: int) -> sp.csr_matrix:
        return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(k - 2, k))

    def d1(k: int) -> sp.csr_matrix:
        return sp.diags([-1.0, 1.0], [0, 1], shape=(k - 1, k))

    iu, iv = sp.identity(mf), sp.identity(nf)
    blocks = []
    if mf >= 3:
        blocks.append(sp.kron(iv, d2(mf)))
    if nf >= 3:
        blocks.append(sp.kron(d2(nf), iu))
    if nf >= 2 and mf >= 2:
        blocks.append(np.sqrt(2.0) * sp.kron(d1(nf), d1(mf)))
    return sp.vstack(blocks).tocsr()


def _banded_cheaper(p_solver: FixedSolver, s_solvers: list[FixedSolver], fields: int, data: int) -> bool:
    """Whether a frame's fields cost fewer operations through the fits' banded factors (a solve
    reads its band twice) than through the dense data → field maps (``fields`` curvature
    rows and the stretch rows, each over ``data`` turning or half as many stretch data, and
    the data × data misfit map).  The dense products read every entry of matrices of tens of
    megabytes (16×16: 20 MB) from memory; the bands are a few hundred kB.  The two give the
    same fields to rounding (about 1e-11 of their size)."""
    banded = 0
    for solver in [p_solver, *s_solvers]:
        band = solver.band
        if band is None:  # a small system kept as its dense pseudo-inverse
            return False
        banded += 2 * band.size
    dense = fields * data + (fields // 3) * data + data * data
    return banded < dense


@dataclass
class FineGrid:
    """Fine material grid with ``sub`` intervals per pitch, covering the sheet to half a pitch
    beyond the outer cell centres; cell centre (i, j) is fine node (sub·i + sub/2, sub·j + sub/2).

    Nodes are numbered p = a·mf + b (a along v, b along u).
    """

    n: int
    m: int
    pitch: float
    gauge_length: float
    sub: int = 2
    field_smoothing: float = 1e-3
    curvature_smoothing: float = 1e-2
    # filled in __post_init__
    nf: int = field(init=False)
    mf: int = field(init=False)
    spacing: float = field(init=False)
    u: np.ndarray = field(init=False)
    v: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        if self.sub < 2 or self.sub % 2:
            raise ValueError(f"grid subdivision must be an even integer >= 2, got {self.sub!r}")
        if not 0 < self.gauge_length <= self.pitch:
            raise ValueError(
                f"gauge_length must be in (0, pitch] = (0, {self.pitch}], got {self.gauge_length!r}"
            )
        s = self.sub
        self.nf, self.mf = s * self.n + 1, s * self.m + 1
        self.spacing = self.pitch / s
        self.u = (np.arange(self.mf) - (self.mf - 1) / 2.0) * self.spacing
        self.v = (np.arange(self.nf) - (self.nf - 1) / 2.0) * self.spacing
        self.node_rows = s * np.arange(self.n) + s // 2
        self.node_cols = s * np.arange(self.m) + s // 2
        self.centre = (self.nf // 2, self.mf // 2)
        self._build_operators()
        self._field_solvers: dict[tuple[bytes, int], tuple[FixedSolver, sp.csr_matrix]] = {}
        self._potential_solvers: dict[bytes, tuple[FixedSolver, sp.csr_matrix]] = {}
        self._field_maps: dict[bytes, object] = {}
        self._build_potential_operators()

    # ----------------------------------------------------------------------------- operators
    def _build_operators(self) -> None:
        nf, mf, s, h = self.nf, self.mf, self.sub, self.spacing
        n_nodes = nf * mf
        idx = np.arange(n_nodes).reshape(nf, mf)
        # Gauge averaging: each gauge is a mean over its length of a piecewise-linear field.
        reach = int(np.ceil(0.5 * self.gauge_length / h))
        offs = np.arange(-reach, reach + 1)
        w = hat_average_weights(offs * h, h, self.gauge_length)
        keep = w > 0
        offs, w = offs[keep], w[keep]
        ii, jj = np.meshgrid(np.arange(self.n), np.arange(self.m), indexing="ij")
        unit = (ii * self.m + jj).ravel()
        a0 = (s * ii + s // 2).ravel()
        b0 = (s * jj + s // 2).ravel()
        n_units = self.n * self.m
        rows = np.repeat(unit, offs.size)
        vals = np.tile(w, n_units)
        cols_u = idx[np.repeat(a0, offs.size), (b0[:, None] + offs[None, :]).ravel()]
        cols_v = idx[(a0[:, None] + offs[None, :]).ravel(), np.repeat(b0, offs.size)]
        self.average = (
            sp.csr_matrix((vals, (rows, cols_u)), shape=(n_units, n_nodes)),
            sp.csr_matrix((vals, (rows, cols_v)), shape=(n_units, n_nodes)),
        )
        self.smooth = _second_differences(nf, mf)
        # Edges of the fine grid: u-edges (a, b)->(a, b+1), v-edges (a, b)->(a+1, b).
        eu_a, eu_b = idx[:, :-1].ravel(), idx[:, 1:].ravel()
        ev_a, ev_b = idx[:-1, :].ravel(), idx[1:, :].ravel()
        self.n_uedges = eu_a.size
        tails = np.concatenate([eu_a, ev_a])
        heads = np.concatenate([eu_b, ev_b])
        ne = tails.size
        er = np.arange(ne)
        self.incidence = sp.csr_matrix(
            (np.r_[-np.ones(ne), np.ones(ne)], (np.r_[er, er], np.r_[tails, heads])), shape=(ne, n_nodes)
        )
        self.edge_tails, self.edge_heads = tails, heads
        lap = (self.incidence.T @ self.incidence).tocsc()
        # The Laplacian's null space is the constant: pin the centre node (any offset is
        # removed later when the surface is put in the sensor frame).
        c = idx[self.centre]
        self.laplacian = FixedSolver(lap + sp.csc_matrix(([1.0], ([c], [c])), shape=lap.shape))
        du = self.incidence[: self.n_uedges]
        dv = self.incidence[self.n_uedges :]
        self.du, self.dv = du, dv

    def divergence(self, edge_values: np.ndarray, v_edge_values: np.ndarray | None = None) -> np.ndarray:
        """incidenceᵀ @ values for components-first edge values (3, E) (u-edges first, as the
        edge numbering), or the u- and v-edge parts given separately: each node gets the sum
        over its incoming edges minus the sum over its outgoing ones.  Returns (nodes, 3), a
        view of a components-first array (what the banded solver takes without a copy)."""
        nf, mf = self.nf, self.mf
        if v_edge_values is None:
            u_vals, v_vals = edge_values[:, : self.n_uedges], edge_values[:, self.n_uedges :]
        else:
            u_vals, v_vals = edge_values, v_edge_values
        u_vals = u_vals.reshape(-1, nf, mf - 1)
        v_vals = v_vals.reshape(-1, nf - 1, mf)
        out = np.zeros((u_vals.shape[0], nf, mf))
        out[:, :, 1:] += u_vals
        out[:, :, :-1] -= u_vals
        out[:, 1:] += v_vals
        out[:, :-1] -= v_vals
        return out.reshape(-1, nf * mf).T

    def _build_potential_operators(self) -> None:
        """Operators on the bending potential z, defined on the fine grid plus one ring.

        k_u = −z_uu, k_v = −z_vv, τ = z_uv at every fine node (central differences), and the
        third differences of z over the extended grid for the smoothness prior.
        """
        nf, mf, h = self.nf, self.mf, self.spacing
        ne_, me_ = nf + 2, mf + 2
        ext = np.arange(ne_ * me_).reshape(ne_, me_)
        a, b = np.meshgrid(np.arange(1, nf + 1), np.arange(1, mf + 1), indexing="ij")
        rows = np.arange(nf * mf)

        def op(stencil: list[tuple[int, int, float]]) -> sp.csr_matrix:
            r = np.concatenate([rows] * len(stencil))
            c = np.concatenate([ext[a + da, b + db].ravel() for da, db, _ in stencil])
            v = np.concatenate([np.full(nf * mf, w) for _, _, w in stencil])
            return sp.csr_matrix((v, (r, c)), shape=(nf * mf, ne_ * me_))

        self.z_uu = op([(0, -1, 1.0), (0, 0, -2.0), (0, 1, 1.0)]) / (h * h)
        self.z_vv = op([(-1, 0, 1.0), (0, 0, -2.0), (1, 0, 1.0)]) / (h * h)
        self.z_uv = op([(1, 1, 0.25), (1, -1, -0.25), (-1, 1, -0.25), (-1, -1, 0.25)]) / (h * h)

        def d(k: int, order: int) -> sp.csr_matrix:
            coeffs = {1: [-1.0, 1.0], 2: [1.0, -2.0, 1.0], 3: [-1.0, 3.0, -3.0, 1.0]}[order]
            return sp.diags(coeffs, list(range(order + 1)), shape=(k - order, k))

        def d0(k: int, order: int) -> sp.csr_matrix:
            return sp.identity(k) if order == 0 else d(k, order)

        # ‖∇k‖²: all third derivatives of z with their binomial weights
        blocks = []
        for ov, ou, w in ((0, 3, 1.0), (1, 2, 3.0), (2, 1, 3.0), (3, 0, 1.0)):
            blocks.append(np.sqrt(w) * sp.kron(d0(ne_, ov), d0(me_, ou)))
        self.z_third = (sp.vstack(blocks) / h**3).tocsr()
        self.n_potential = ne_ * me_

    def potential_observation(self) -> sp.csr_matrix:
        """Data operator of the bending potential: rows are the units' mean turning per length,
        (2·N·M, n_potential)."""
        if not hasattr(self, "_potential_obs"):
            self._potential_obs = sp.vstack([-(self.average[0] @ self.z_uu), -(self.average[1] @ self.z_vv)]).tocsr()
        return self._potential_obs

    def potential_prior(self) -> sp.csc_matrix:
        """Quadratic form of the potential's prior: smoothness α‖∇k‖² plus pins of z at the four
        nodes of the centre cell (z = a + bu + cv + d·uv changes neither data nor smoothness; the
        twist's constant is set later from the Gauss equation)."""
        if not hasattr(self, "_potential_prior"):
            obs = self.potential_observation()
            area = self.spacing**2 / self.pitch**2  # prior per fine node, data per unit
            smooth = self.curvature_smoothing * area * (self.z_third.T @ self.z_third)
            a0, b0 = self.centre
            me_ = self.mf + 2
            pins = [(a0 + 1 + da) * me_ + (b0 + 1 + db) for da in (0, 1) for db in (0, 1)]
            rho = float((obs.T @ obs + smooth).diagonal().max())
            self._potential_prior = (smooth + sp.csr_matrix((np.full(4, rho), (pins, pins)), shape=smooth.shape)).tocsc()
        return self._potential_prior

    def potential_solver(self, valid: np.ndarray) -> tuple[FixedSolver, sp.csr_matrix]:
        """Solver for the bending potential whose curvatures' gauge averages fit the turning
        data of the valid units (least squares + prior); returns (solver, masked data
        operator transposed, with 2·N·M columns)."""
        valid = np.asarray(valid, dtype=bool).reshape(2, -1)
        key = valid.tobytes()
        hit = self._potential_solvers.get(key)
        if hit is None:
            obs = self.potential_observation()
            obs_t_w = (obs.T @ sp.diags(valid.ravel().astype(float))).tocsr()
            hit = (self._masked_solver(("potential",), lambda m: obs.T @ sp.diags(m) @ obs + self.potential_prior(), obs, valid.ravel()), obs_t_w)
            if len(self._potential_solvers) > 16:
                self._potential_solvers.pop(next(iter(self._potential_solvers)))
            self._potential_solvers[key] = hit
        return hit

    def _masked_solver(self, name: tuple, normal_for, obs: sp.csr_matrix, valid: np.ndarray):
        """Solver of a fit's normal matrix with the invalid data rows removed: the all-valid
        factorisation (built once), or one of its own for a mask.  Masks normally never get
        here (their units are left out of the all-valid fit, :mod:`.leaveout`); this serves
        the masks that leaving out cannot handle, where a downdate would fail too."""
        full = self.__dict__.setdefault("_full_solvers", {})
        base = full.get(name)
        if base is None:
            base = full[name] = FixedSolver(normal_for(np.ones(valid.size)).tocsc())
        if valid.all():
            return base
        return FixedSolver(normal_for(valid.astype(float)).tocsc())

    @property
    def inner(self) -> tuple[slice, slice]:
        """Index of the region spanned by the cell centres (where differences are central)."""
        return (slice(self.node_rows[0], self.node_rows[-1] + 1), slice(self.node_cols[0], self.node_cols[-1] + 1))

    @property
    def dense_maps(self) -> bool:
        """Small grids keep dense data → field maps (the uncertainty and leaving units out read
        them; a frame takes one product per field block where that costs less than the banded
        solves, :func:`_banded_cheaper`); large ones solve through the sparse factorisations."""
        return self.nf * self.mf * 4 * self.n * self.m <= 4_000_000

    def field_maps(self, valid: np.ndarray):
        """Linear maps from unit data to the fine fields for this validity mask, cached.

        Returns a function (turning (2, N, M), stretch (2, N, M)) → (k_u, k_v, τ, λ_u, λ_v, fit):
        five (nf, mf) fields and the misfit of the curvature fields' gauge averages to the
        turning data, (2·N·M,) (invalid units included; mask them).  The data of invalid units
        must be zero turning and unit stretch (as :func:`engine.unit_data` gives them).  The
        all-valid maps are built once; a mask with missing units leaves them out of the
        all-valid fits (:mod:`.leaveout`), at the cost of a k × k inverse, and refactorises only
        when the remaining data no longer determine the fit or, on large grids, when more units
        than the leave-out budget are missing for the first time; ``fn.left_out`` tells which.
        """
        valid = np.asarray(valid, dtype=bool).reshape(2, self.n, self.m)
        key = valid.tobytes()
        fn = self._field_maps.get(key)
        if fn is not None:
            return fn
        if valid.all():
            fn = self._all_valid_maps()
        else:
            try:
                fn = self._left_out_maps(valid)
                fn.left_out = True
            except IllConditioned:
                fn = self._build_maps(valid)
                fn.left_out = False
        if len(self._field_maps) > 16:
            self._field_maps.pop(next(iter(self._field_maps)))
        self._field_maps[key] = fn
        return fn

    def _all_valid_maps(self):
        if not hasattr(self, "_all_maps_fn"):
            self._all_maps_fn = self._build_maps(np.ones((2, self.n, self.m), dtype=bool), keep=True)
        return self._all_maps_fn

    def transposed(self, fit: str, direction: int = 0) -> sp.csr_matrix:
        """Oᵀ of a fit's all-valid data operator (CSR, cached)."""
        key = "_obs_t_" + (fit if fit == "potential" else f"{fit}{direction}")
        if key not in self.__dict__:
            obs = self.potential_observation() if fit == "potential" else self.average[direction]
            self.__dict__[key] = obs.T.tocsr()
        return self.__dict__[key]

    def leave_out(self, fit: str, direction: int = 0) -> LeaveOut:
        """The all-valid fit ``fit`` ("potential" or "stretch" along ``direction``) prepared for
        leaving units out."""
        self._all_valid_maps()
        return self._leave_outs[fit if fit == "potential" else (fit, direction)]

    @property
    def curvature_operator(self) -> sp.csr_matrix:
        """z → (k_u, k_v, τ) stacked, (3 n_fine, n_potential)."""
        if not hasattr(self, "_curv_ops"):
            self._curv_ops = sp.vstack([-self.z_uu, -self.z_vv, self.z_uv]).tocsr()
        return self._curv_ops

    @property
    def unit_average(self) -> sp.csr_matrix:
        """(k_u, k_v) → their gauge averages per unit, (2NM, 2 n_fine)."""
        if not hasattr(self, "_unit_average"):
            self._unit_average = sp.block_diag(self.average).tocsr()
        return self._unit_average

    def _build_maps(self, valid: np.ndarray, keep: bool = False):
        """Data → field maps through the factorisations for this mask; ``keep`` stores the
        dense maps and the leave-out preparations (all-valid mask)."""
        shape = (self.nf, self.mf)
        n_fine = self.nf * self.mf
        n_units = self.n * self.m
        curv_ops = self.curvature_operator
        average = self.unit_average  # (2NM, 2 n_fine): k_u, k_v → unit means
        p_solver, obs_t_w = self.potential_solver(valid)
        s_solvers = [self.field_solver(d, valid[d]) for d in (0, 1)]
        if self.dense_maps:
            curv = curv_ops @ p_solver.solve(obs_t_w.toarray())  # (3 n_fine, 2NM)
            stretch_maps = [sol.solve(at_w.toarray()) for sol, at_w in s_solvers]  # (n_fine, NM)
            misfit = average @ curv[: 2 * n_fine] - np.eye(2 * n_units)  # (2NM, 2NM)
            if keep:
                self._dense = {"curv": curv, "stretch": stretch_maps, "misfit": misfit}
                self._leave_outs: dict[str | tuple[str, int], LeaveOut] = {"potential": LeaveOut(hat=misfit + np.eye(2 * n_units))}
                for d in (0, 1):
                    self._leave_outs[("stretch", d)] = LeaveOut(hat=self.average[d] @ stretch_maps[d])

            # one dense product per block (the maps are dense; stacking them block-diagonally
            # would multiply zeros)
            def dense_fn(turning, stretch):
                d = turning.ravel()
                k = curv @ d
                lam_u = stretch_maps[0] @ (stretch[0].ravel() - 1.0)
                lam_v = stretch_maps[1] @ (stretch[1].ravel() - 1.0)
                lam_u += 1.0
                lam_v += 1.0
                return (*k.reshape(3, *shape), lam_u.reshape(shape), lam_v.reshape(shape), misfit @ d)

            if not _banded_cheaper(p_solver, [sol for sol, _ in s_solvers], curv_ops.shape[0], 2 * n_units):
                return dense_fn
        elif keep:
            self._leave_outs = {"potential": LeaveOut(solver=p_solver, obs=self.potential_observation())}
            for d in (0, 1):
                self._leave_outs[("stretch", d)] = LeaveOut(solver=s_solvers[d][0], obs=self.average[d])

        # through the factorisations (large grids; and where the bands cost less than the dense maps)
        def fn(turning, stretch):
            d = turning.ravel()
            k = curv_ops @ p_solver.solve(obs_t_w @ d)
            lam = [1.0 + sol.solve(at_w @ (stretch[i].ravel() - 1.0)) for i, (sol, at_w) in enumerate(s_solvers)]
            fit = average @ k[: 2 * n_fine] - d
            return (*k.reshape(3, *shape), *(x.reshape(shape) for x in lam), fit)

        return fn

    def _dense_transposed(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """The dense curvature and stretch maps transposed (units × fields), built once."""
        if "_dense_t" not in self.__dict__:
            d = self._dense
            self._dense_t = (np.ascontiguousarray(d["curv"].T), [np.ascontiguousarray(x.T) for x in d["stretch"]])
        return self._dense_t

    def _left_out_maps(self, valid: np.ndarray):
        """Maps for a mask with missing units: the all-valid maps, then the Woodbury correction
        of each fit for its missing units (see :mod:`.leaveout`).  Invalid units' data are zero
        (turning 0, stretch − 1 = 0), so the all-valid maps see no data there."""
        self._all_valid_maps()
        shape = (self.nf, self.mf)
        n_fine = self.nf * self.mf
        miss_p = np.flatnonzero(~valid.ravel())
        miss_s = [np.flatnonzero(~valid[d].ravel()) for d in (0, 1)]
        lo_p = self._leave_outs["potential"]
        lo_s = [self._leave_outs[("stretch", d)] for d in (0, 1)]
        if not (lo_p.affordable(miss_p) and all(lo_s[d].affordable(miss_s[d]) for d in (0, 1))):
            raise IllConditioned("too many new units missing at once: refactorise")
        m_p = lo_p.weights(miss_p)
        m_s = [lo_s[d].weights(miss_s[d]) if miss_s[d].size else None for d in (0, 1)]
        h_p = lo_p.hat_columns(miss_p)  # (2NM, k)
        avg_miss = [self.average[d][miss_s[d]] for d in (0, 1)]  # fitted stretch at missing units
        if self.dense_maps:
            curv, stretch_maps, misfit = self._dense["curv"], self._dense["stretch"], self._dense["misfit"]
            # row gathers of the transposed maps are contiguous (column gathers are strided)
            curv_t, stretch_t = self._dense_transposed()
            curv_miss = curv_t[miss_p].T
            stretch_miss = [stretch_t[d][miss_s[d]].T for d in (0, 1)]

            def fn(turning, stretch):
                d = turning.ravel()
                fit = misfit @ d
                w = m_p @ fit[miss_p]  # d = 0 there: the fit's own value at the missing units
                k = curv @ d + curv_miss @ w
                fit += h_p @ w
                lam = []
                for i in (0, 1):
                    x = stretch_maps[i] @ (stretch[i].ravel() - 1.0)
                    if m_s[i] is not None:
                        x += stretch_miss[i] @ (m_s[i] @ (avg_miss[i] @ x))
                    x += 1.0
                    lam.append(x.reshape(shape))
                return (*k.reshape(3, *shape), *lam, fit)

        else:
            curv_ops, average = self.curvature_operator, self.unit_average
            obs = self.potential_observation()
            obs_miss = obs[miss_p]
            p_solver, obs_t = cast(FixedSolver, lo_p.solver), self.transposed("potential")
            y_p = lo_p.solution_columns(miss_p)
            y_s = [lo_s[d].solution_columns(miss_s[d]) for d in (0, 1)]
            s_solvers = [(cast(FixedSolver, lo_s[d].solver), self.transposed("stretch", d)) for d in (0, 1)]

            def fn(turning, stretch):
                d = turning.ravel()
                z = p_solver.solve(obs_t @ d)
                z += y_p @ (m_p @ (obs_miss @ z))
                k = curv_ops @ z
                lam = []
                for i, (sol, at) in enumerate(s_solvers):
                    x = sol.solve(at @ (stretch[i].ravel() - 1.0))
                    if m_s[i] is not None:
                        x += y_s[i] @ (m_s[i] @ (avg_miss[i] @ x))
                    x += 1.0
                    lam.append(x.reshape(shape))
                fit = average @ k[: 2 * n_fine] - d
                return (*k.reshape(3, *shape), *lam, fit)

        return fn

    # --------------------------------------------------------------------------- field solve
    def field_solver(self, direction: int, valid: np.ndarray) -> tuple[FixedSolver, sp.csr_matrix]:
        """Solver for the smoothed field whose gauge averages match the valid data.

        Minimises Σ_valid (A f − d)² + α‖D² f‖² (thin-plate smoothing on the fine grid, scaled
        per unit area); returns (solver of the normal matrix, masked Aᵀ).
        """
        valid = np.asarray(valid, dtype=bool).ravel()
        key = (valid.tobytes(), direction)
        hit = self._field_solvers.get(key)
        if hit is None:
            a = self.average[direction]
            at_w = (a.T @ sp.diags(valid.astype(float))).tocsr()
            # α is per fine node; the data term has one row per unit (sub² fine nodes per unit)
            alpha = self.field_smoothing * (self.n * self.m) / (self.nf * self.mf)
            prior = alpha * (self.smooth.T @ self.smooth) + 1e-12 * sp.identity(a.shape[1])
            hit = (self._masked_solver(("stretch", direction), lambda m: a.T @ sp.diags(m) @ a + prior, a, valid), at_w)
            if len(self._field_solvers) > 16:  # masks change rarely; keep the cache bounded
                self._field_solvers.pop(next(iter(self._field_solvers)))
            self._field_solvers[key] = hit
        return hit
