"""Twist and shear fields of a sheet pushed out of plane (a graph), beyond small slopes.

When the stretch pattern shows a graph z(u, v) over the material plane (see
``engine._graph_twist``: E = 1 + z_u², G = 1 + z_v², F = z_u z_v), the unmeasured twist and
shear follow from the graph's slopes instead of the linearised Codazzi equations and the
least-norm shear, which are exact only for small slopes:

* the gauges measure k_u = −z_uu/(W λ_u) (normal curvature along x_u times λ_u, W² = 1 + |∇z|²),
  so the height's own second derivatives are the turning data scaled by W λ_u (gauge-averaged);
  one more pass of the fixed linear fit on the scaled data gives z_uu, z_vv and the varying part
  of z_uv, and the stretch pattern again its constant part;
* the shape operator's off-diagonal in the frame (x̂_u, n × x̂_u):
  τ = (M − (F/E) L) / (√E · √(G − F²/E)), L = z_uu/W, M = z_uv/W;
* the shear F = z_u z_v supplies the part f(u) + g(v) that Brioschi's formula leaves free.

On a graph-mapped saddle turned by 30° (R 50 mm) this takes the mean node error from 0.27 to
0.026 mm; see docs/reconstruction.md, step 2b.
"""
from __future__ import annotations

import numpy as np

from .engine import GraphTwist, graph_slopes, quartic_value, slope_twist_quartic
from .grid import FineGrid

__all__ = ["graph_sheet_fields", "free_part", "RESIDUAL_LIMIT"]

# Share of the stretch pattern (Σ (E − 1)² + (G − 1)² over the cell-centre region) the refined
# graph may leave unexplained.  Measured: quadratic graphs (saddles at any angle, twisted domes,
# troughs; slopes up to 1) leave 0.0002-0.003, a Gaussian bump near the edge, whose slopes the
# gauge averages do not resolve, 0.13-0.2.
RESIDUAL_LIMIT = 0.02


def free_part(f: np.ndarray) -> np.ndarray:
    """The part a(u) + b(v) of a field (nf, mf) in least squares: the row and column means
    (what a mixed derivative ∂_uv does not see)."""
    col = f.mean(axis=0, keepdims=True)
    row = f.mean(axis=1, keepdims=True)
    return col + row - col.mean()


def graph_sheet_fields(
    grid: FineGrid,
    maps,
    turning: np.ndarray,
    stretch: np.ndarray,
    graph: GraphTwist,
    stretch_sq: tuple[np.ndarray, np.ndarray],
    passes: int = 1,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Twist field τ (nf, mf) and shear F = z_u z_v (nf, mf) of the graph, its slopes refined
    from the linear-fit slopes in ``graph`` by ``passes`` rescaled fits; None when the refined
    graph does not explain the stretch pattern (left over: ``RESIDUAL_LIMIT`` of it or more).

    ``maps``: the field maps of this frame's validity mask (``FineGrid.field_maps``);
    ``turning``, ``stretch``: the unit data (2, N, M) as ``engine.unit_data`` gives them;
    ``stretch_sq``: the fitted E − 1 and G − 1 fields (nf, mf).
    """
    v = grid.v[:, None]
    u = grid.u[None, :]
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {passes!r}")
    inner = grid.inner
    c = graph.slope_twist
    p, q = graph.p, graph.q
    for _ in range(passes):
        z_u, z_v = p + c * v, q + c * u
        w = np.sqrt(1.0 + z_u * z_u + z_v * z_v)
        lam_u, lam_v = np.sqrt(1.0 + z_u * z_u), np.sqrt(1.0 + z_v * z_v)
        # the height's second derivatives are the data scaled by W λ (gauge averages of it)
        scale = np.concatenate([grid.average[0] @ (w * lam_u).ravel(), grid.average[1] @ (w * lam_v).ravel()])
        k_uu, k_vv, tau_var = maps(turning * scale.reshape(turning.shape), stretch)[:3]
        tau_var = tau_var - tau_var.mean()
        p, q = graph_slopes(grid, k_uu, k_vv, tau_var)
        k = slope_twist_quartic(p[inner], q[inner], stretch_sq[0][inner], stretch_sq[1][inner], u[:, inner[1]], v[inner[0]])
        c = _local_minimum(k, c)
    # A constant twist is trusted in proportion to the share of the stretch misfit it removes:
    # fully from 80 %, not at all below 50 % (then the slopes' own errors, e.g. a bump the gauges
    # do not resolve, could be absorbed into a small twist that bends a large sheet's far corners)
    best, zero = quartic_value(k, c), quartic_value(k, 0.0)
    c *= min(max((zero / max(best, 1e-300) - 2.0) / 3.0, 0.0), 1.0)
    e1, g1 = stretch_sq[0][inner], stretch_sq[1][inner]
    if not quartic_value(k, c) < RESIDUAL_LIMIT * float((e1 * e1).sum() + (g1 * g1).sum()):
        return None
    z_u, z_v = p + c * v, q + c * u
    w = np.sqrt(1.0 + z_u * z_u + z_v * z_v)
    e, f, g = 1.0 + z_u * z_u, z_u * z_v, 1.0 + z_v * z_v
    ell, m = -k_uu / w, (tau_var + c) / w
    tau = (m - (f / e) * ell) / np.sqrt(e * g - f * f)
    return tau, f


def _local_minimum(k: tuple[float, ...], c: float, steps: int = 8) -> float:
    """Newton steps on the quartic's derivative from ``c`` (the slopes barely move the minimum);
    ``c`` itself when a step would leave the basin (no positive curvature), change the sign or
    raise the cost."""
    k4, k3, k2, k1, _ = k
    x = c
    for _ in range(steps):
        d1 = ((4.0 * k4 * x + 3.0 * k3) * x + 2.0 * k2) * x + k1
        d2 = (12.0 * k4 * x + 6.0 * k3) * x + 2.0 * k2
        if not d2 > 0.0:
            return c
        step = d1 / d2
        x -= step
        if abs(step) <= 1e-12 * max(abs(x), 1e-9):
            break
    # never across zero: the sign was chosen by the data's mirror test or by the caller
    return x if x * c > 0.0 and quartic_value(k, x) <= quartic_value(k, c) else c
