"""Per-geometry precomputation: the fine material grid, its linear operators and factorisations.

Everything here depends only on (N, M, pitch, gauge length, subdivision, regularisation weights,
valid-gauge mask), never on the measured strains, so it is built once and reused every frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

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
    twist_tikhonov: float = 1e-4
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
        # The tiny diagonal fixes the free translation/rotation offset; right-hand sides are
        # divergences (sum zero), so it only selects the zero-mean solution.
        self.laplacian = FixedSolver(lap + 1e-9 * sp.identity(n_nodes))
        du = self.incidence[: self.n_uedges]
        dv = self.incidence[self.n_uedges :]
        self.twist_solver = FixedSolver((lap + self.twist_tikhonov * sp.identity(n_nodes)).tocsc())
        self.du, self.dv = du, dv

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
            normal = (at_w @ a + alpha * (self.smooth.T @ self.smooth)).tocsc()
            hit = (FixedSolver(normal + 1e-12 * sp.identity(normal.shape[0])), at_w)
            if len(self._field_solvers) > 16:  # masks change rarely; keep the cache bounded
                self._field_solvers.pop(next(iter(self._field_solvers)))
            self._field_solvers[key] = hit
        return hit
