"""Position uncertainty from strain noise, by linear propagation about the flat sheet.

For small deflections the reconstruction is linear in the data: the bending potential z is a
fixed linear map of the units' turning data, and z is the height of the sheet in the sensor
frame once its value and slopes at the centre are pinned (the frame's definition).  The
one-s.d. height error of a fine node is the norm of its row of that map times the noise of a
unit's turning per length; missing units enter with the spread of the measured ones, so the
uncertainty rises around a dead gauge.  In-plane errors are a random walk of the stretch noise
along the rows and columns from the centre.
"""
from __future__ import annotations

import numpy as np

from .grid import FineGrid

__all__ = ["height_response", "fine_sigma"]


def height_response(grid: FineGrid, valid: np.ndarray) -> np.ndarray:
    """Linear map (nf·mf, 2·N·M) from the units' turning per length to fine-node heights in the
    sensor frame (centre height and slopes pinned), about the flat sheet."""
    solver, obs_t_w = grid.potential_solver(valid)
    z_ext = solver.solve(obs_t_w.toarray())
    # the reconstruction replaces the potential's mean twist by the Gauss-equation constant
    # (zero about the flat sheet): remove it here too
    mean_twist = (grid.z_uv @ z_ext).mean(axis=0)
    z = z_ext.reshape(grid.nf + 2, grid.mf + 2, -1)[1:-1, 1:-1]
    z = z - np.multiply.outer(np.outer(grid.v, grid.u), mean_twist)
    a0, b0 = grid.centre
    h = grid.spacing
    slope_u = (z[a0, b0 + 1] - z[a0, b0 - 1]) / (2 * h)
    slope_v = (z[a0 + 1, b0] - z[a0 - 1, b0]) / (2 * h)
    z = z - z[a0, b0] - grid.u[None, :, None] * slope_u - grid.v[:, None, None] * slope_v
    return z.reshape(grid.nf * grid.mf, -1)


def fine_sigma(
    grid: FineGrid,
    valid: np.ndarray,
    turning: np.ndarray,
    strain_sigma: float,
    h_upper: float,
    h_lower: float,
) -> np.ndarray:
    """One-s.d. position uncertainty (nf, mf) mm of every fine node."""
    # Per validity mask, keep only the summed squares of the response rows (the full map is
    # large for big arrays and the data enter only through one scalar below).
    cache = grid.__dict__.setdefault("_sigma_cache", {})
    key = valid.tobytes()
    sums = cache.get(key)
    if sums is None:
        v = valid.ravel()
        measured = (height_response(grid, valid)[:, v] ** 2).sum(axis=1)
        missing = np.zeros_like(measured)
        if not v.all():
            missing = (height_response(grid, np.ones_like(valid))[:, ~v] ** 2).sum(axis=1)
        if len(cache) > 16:
            cache.pop(next(iter(cache)))
        sums = cache[key] = (measured, missing)
    measured, missing = sums
    # turning per length = (ε_u − ε_l)/(h_u + h_l): two independent gauges
    sig_turn = np.sqrt(2.0) * strain_sigma / (h_upper + h_lower)
    var = measured * sig_turn**2
    if not valid.all():
        known = turning[valid]
        # a missing unit's turning is unknown with the spread of the measured ones
        # (floor: a 200 mm bend radius)
        spread2 = (np.mean(known**2) if known.size else 0.0) + (1.0 / 200.0) ** 2
        var = var + missing * spread2
    # in-plane: each pitch crossed adds one stretch reading's error times the pitch
    sig_stretch = strain_sigma * np.hypot(h_upper, h_lower) / (h_upper + h_lower)
    walk = grid.__dict__.get("_sigma_walk")
    if walk is None:  # |u| + |v| times the pitch, the same every frame
        walk = grid._sigma_walk = (np.abs(grid.u)[None, :] + np.abs(grid.v)[:, None]) * grid.pitch
    return np.sqrt(var.reshape(grid.nf, grid.mf) + walk * sig_stretch**2)
