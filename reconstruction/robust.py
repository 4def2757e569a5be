"""The convex field fit solved with Clarabel, with a Huber loss on the turning data.

The default path solves the field fit in closed form (its matrix is fixed, so the cached
factorisation gives the least-squares optimum in a few microseconds).  This module poses the
same convex problem to Clarabel with the squared loss replaced by Huber's (quadratic within
``delta`` of the data, linear beyond).  A residual beyond ``delta`` would pull with bounded
force; in practice the fit interpolates the units' data (far more potential unknowns than
data), residuals stay well inside ``delta`` even with a glitching gauge, and both paths give the
same surface (docs/reconstruction.md, "Solvers").

Huber as a QP (s: the part of the residual inside the quadratic zone, t ≥ |r − s|):

    min ½ zᵀ P_z z + Σ_i (½ s_i² + δ t_i)   s.t.   −t ≤ O z − d − s ≤ t,

with P_z the smoothness prior and centre pins of the bending potential and O the data operator.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .grid import FineGrid

__all__ = ["huber_potential"]


def huber_potential(
    grid: FineGrid, turning: np.ndarray, valid: np.ndarray, delta: float
) -> tuple[np.ndarray, dict]:
    """Bending potential z (extended grid, flattened) minimising prior + Huber data loss.

    Returns z and a dict with Clarabel's status, iterations and solve time (s).
    """
    import clarabel  # imported here: only this optional path needs it

    if not delta > 0:
        raise ValueError(f"Huber threshold delta must be > 0, got {delta!r}")
    prior = grid.potential_prior()
    obs = grid.potential_observation()[np.asarray(valid, dtype=bool).ravel()]
    d = np.asarray(turning, dtype=float).ravel()[np.asarray(valid, dtype=bool).ravel()]
    n, m = prior.shape[0], obs.shape[0]
    if m == 0:
        return np.zeros(n), {"status": "no data", "iterations": 0, "solve_time": 0.0}
    eye = sp.identity(m, format="csc")
    p = sp.block_diag([prior, eye, sp.csc_matrix((m, m))], format="csc")
    q = np.concatenate([np.zeros(n + m), np.full(m, float(delta))])
    a = sp.vstack([sp.hstack([obs, -eye, -eye]), sp.hstack([-obs, eye, -eye])], format="csc")
    b = np.concatenate([d, -d])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(sp.triu(p, format="csc"), q, a, b, [clarabel.NonnegativeConeT(2 * m)], settings)
    sol = solver.solve()
    info = {"status": str(sol.status), "iterations": int(sol.iterations), "solve_time": float(sol.solve_time)}
    return np.asarray(sol.x[:n]), info
