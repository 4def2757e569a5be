"""Position uncertainty from strain noise, by linear propagation about the flat sheet.

The reconstruction is linear in the data for small deflections: the turning data fix the
curvature fields, the Codazzi solve the twist, and the height follows from the three curvature
components.  The one-s.d. height error of every fine node is the norm of the row of that linear
map, scaled by the noise of a unit's turning per length; missing units enter with the spread of
the measured curvatures, so the uncertainty rises around a dead gauge.  In-plane errors are a
random walk of the stretch noise along the rows and columns from the centre.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .grid import FineGrid
from .linalg import FixedSolver

__all__ = ["height_response", "fine_sigma"]


def _height_solver(grid: FineGrid) -> tuple[FixedSolver, sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
    cached = getattr(grid, "_height_solver", None)
    if cached is None:
        nf, mf = grid.nf, grid.mf

        def d2(k):
            return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(k - 2, k))

        def d1(k):
            return sp.diags([-1.0, 1.0], [0, 1], shape=(k - 1, k))

        d_uu = sp.kron(sp.identity(nf), d2(mf)).tocsr()
        d_vv = sp.kron(d2(nf), sp.identity(mf)).tocsr()
        d_uv = sp.kron(d1(nf), d1(mf)).tocsr()
        normal = d_uu.T @ d_uu + d_vv.T @ d_vv + 2.0 * (d_uv.T @ d_uv)
        solver = FixedSolver((normal + 1e-9 * sp.identity(nf * mf)).tocsc())
        cached = (solver, d_uu, d_vv, d_uv)
        grid._height_solver = cached
    return cached


def height_response(grid: FineGrid, valid: np.ndarray) -> np.ndarray:
    """Linear map (nf·mf, 2·N·M) from unit turning-per-length data to fine-node heights in the
    sensor frame (centre height and slopes pinned to zero), about the flat sheet."""
    from .engine import codazzi_twist  # local: engine imports nothing from here

    nf, mf, h = grid.nf, grid.mf, grid.spacing
    n_units = grid.n * grid.m
    fields = []
    for d in (0, 1):
        solver, at_w = grid.field_solver(d, valid[d])
        block = np.zeros((nf * mf, 2 * n_units))
        block[:, d * n_units : (d + 1) * n_units] = solver.solve(at_w.toarray())
        fields.append(block.reshape(nf, mf, -1))
    k_u, k_v = fields
    tau = codazzi_twist(grid, k_u, k_v)
    solver, d_uu, d_vv, d_uv = _height_solver(grid)
    flat = lambda f: f.reshape(nf * mf, -1)  # noqa: E731
    # z_uu = −k_u, z_vv = −k_v, z_uv = τ (small slopes, convex positive)
    rhs = -h * h * (d_uu.T @ _rows_interior(flat(k_u), nf, mf, "u"))
    rhs += -h * h * (d_vv.T @ _rows_interior(flat(k_v), nf, mf, "v"))
    rhs += 2.0 * h * h * (d_uv.T @ _cell_means(tau, nf, mf))
    z = solver.solve(rhs).reshape(nf, mf, -1)
    a0, b0 = grid.centre
    slope_u = (z[a0, b0 + 1] - z[a0, b0 - 1]) / (2 * h)
    slope_v = (z[a0 + 1, b0] - z[a0 - 1, b0]) / (2 * h)
    z = z - z[a0, b0] - grid.u[None, :, None] * slope_u - grid.v[:, None, None] * slope_v
    return z.reshape(nf * mf, -1)


def _rows_interior(f: np.ndarray, nf: int, mf: int, axis: str) -> np.ndarray:
    g = f.reshape(nf, mf, -1)
    g = g[:, 1:-1] if axis == "u" else g[1:-1, :]
    return g.reshape(-1, f.shape[-1])


def _cell_means(f: np.ndarray, nf: int, mf: int) -> np.ndarray:
    g = 0.25 * (f[:-1, :-1] + f[1:, :-1] + f[:-1, 1:] + f[1:, 1:])
    return g.reshape((nf - 1) * (mf - 1), -1)


def fine_sigma(
    grid: FineGrid,
    valid: np.ndarray,
    turning: np.ndarray,
    strain_sigma: float,
    h_upper: float,
    h_lower: float,
) -> np.ndarray:
    """One-s.d. position uncertainty (nf, mf) mm of every fine node."""
    cache = grid.__dict__.setdefault("_response_cache", {})
    key = valid.tobytes()
    if key not in cache:
        if len(cache) > 8:
            cache.pop(next(iter(cache)))
        cache[key] = height_response(grid, valid)
    z = cache[key]
    # turning per length = (ε_u − ε_l)/(h_u + h_l): two independent gauges
    sig_turn = np.sqrt(2.0) * strain_sigma / (h_upper + h_lower)
    v = valid.ravel()
    var = (z[:, v] ** 2).sum(axis=1) * sig_turn**2
    if not v.all():
        all_valid = np.ones_like(valid)
        key0 = all_valid.tobytes()
        if key0 not in cache:
            cache[key0] = height_response(grid, all_valid)
        measured = turning.ravel()[v]
        spread2 = (np.mean(measured**2) if measured.size else 0.0) + (1.0 / 200.0) ** 2
        var += (cache[key0][:, ~v] ** 2).sum(axis=1) * spread2
    # in-plane: each pitch crossed adds one stretch reading's error times the pitch
    sig_stretch = strain_sigma * np.hypot(h_upper, h_lower) / (h_upper + h_lower)
    uu, vv = np.meshgrid(grid.u, grid.v)
    var_plane = (np.abs(uu) + np.abs(vv)) * grid.pitch * sig_stretch**2
    return np.sqrt(var.reshape(grid.nf, grid.mf) + var_plane)
