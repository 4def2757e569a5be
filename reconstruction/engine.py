"""Strains → surface: the reconstruction pipeline (see docs/reconstruction.md).

1. decouple every unit into the normal turning angle Θ over its gauge and the stretch ε̂_s;
2. estimate smooth fields on a fine material grid whose gauge averages match the data:
   k_u, k_v (normal curvature per unit material length) and λ_u, λ_v (stretch ratios);
3. the twist τ that the gauges do not measure, from the Codazzi equations (∂_u τ = −∂_v k_u,
   ∂_v τ = −∂_u k_v) plus, for its constant part, the Gauss equation;
4. the orthonormal frame field (t_u, t_v, n) integrated from the rotation rates
   ω_u = (τ, k_u, g_u), ω_v = (−k_v, −τ, g_v) along a tree, then made consistent by a linearised
   least-squares correction on the whole grid;
5. positions from the chords of every fine edge by least squares (a fixed graph Laplacian).

Steps 2, 3 and 5 are linear least-squares problems whose matrices depend only on the geometry:
their factorisations are cached, so a frame costs a few triangular solves and vectorised
rotation algebra.
"""
from __future__ import annotations

import numpy as np

from .decouple import decouple
from .grid import FineGrid
from .linalg import exp_so3, log_so3

__all__ = [
    "unit_data",
    "solve_fields",
    "codazzi_twist",
    "solve_twist",
    "rotation_rates",
    "integrate_frames",
    "integrate_positions",
    "refine_positions",
]


def unit_data(
    eps_upper: np.ndarray, eps_lower: np.ndarray, h_upper: float, h_lower: float, gauge_length: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per unit (2, N, M): mean turning per material length Θ/g, stretch ratio L/g, validity."""
    kappa, eps_s = decouple(eps_upper, eps_lower, h_upper, h_lower)
    valid = np.isfinite(kappa) & np.isfinite(eps_s)
    stretch = np.where(valid, 1.0 + eps_s, 1.0)
    turning = np.where(valid, kappa * stretch, 0.0)  # Θ/g = κ̂ L/g
    return turning, stretch, valid


def solve_fields(grid: FineGrid, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray):
    """Smooth fine-grid fields k_u, k_v, λ_u, λ_v whose gauge averages fit the data."""
    out = []
    for d in (0, 1):
        solver, at_w = grid.field_solver(d, valid[d])
        rhs = at_w @ np.stack([turning[d].ravel(), stretch[d].ravel() - 1.0], axis=1)
        f = solver.solve(rhs)
        out.append((f[:, 0].reshape(grid.nf, grid.mf), 1.0 + f[:, 1].reshape(grid.nf, grid.mf)))
    (k_u, lam_u), (k_v, lam_v) = out
    return k_u, k_v, lam_u, lam_v


def _edge_mean(f: np.ndarray, axis: int) -> np.ndarray:
    return 0.5 * (f[:-1] + f[1:]) if axis == 0 else 0.5 * (f[:, :-1] + f[:, 1:])


def geodesic_rates(grid: FineGrid, lam_u: np.ndarray, lam_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic curvature per material length of the u- and v-lines of an orthogonal net
    (Liouville): g_u = −∂_v λ_u / λ_v, g_v = ∂_u λ_v / λ_u."""
    h = grid.spacing
    g_u = -np.gradient(lam_u, h, axis=0) / lam_v if grid.nf > 1 else np.zeros_like(lam_u)
    g_v = np.gradient(lam_v, h, axis=1) / lam_u if grid.mf > 1 else np.zeros_like(lam_v)
    return g_u, g_v


def gaussian_curvature_of_metric(grid: FineGrid, lam_u: np.ndarray, lam_v: np.ndarray) -> np.ndarray:
    """K of the orthogonal metric diag(λ_u², λ_v²) (Brioschi, to first order in λ − 1)."""
    h = grid.spacing
    return -(np.gradient(np.gradient(lam_v, h, axis=1), h, axis=1) + np.gradient(np.gradient(lam_u, h, axis=0), h, axis=0))


def codazzi_twist(grid: FineGrid, k_u: np.ndarray, k_v: np.ndarray) -> np.ndarray:
    """Zero-mean twist field τ (per material length) from the Codazzi equations
    ∂_u τ = −∂_v k_u and ∂_v τ = −∂_u k_v, least squares on the fine edges.  Fields are
    (nf, mf) or (nf, mf, B) for B right-hand sides at once."""
    h = grid.spacing
    dkudv = np.gradient(k_u, h, axis=0) if grid.nf > 1 else np.zeros_like(k_u)
    dkvdu = np.gradient(k_v, h, axis=1) if grid.mf > 1 else np.zeros_like(k_v)
    batch = k_u.shape[2:]
    # targets for (τ_head − τ_tail) on u-edges and v-edges
    t_u = -h * _edge_mean(dkudv, 1).reshape((-1,) + batch)
    t_v = -h * _edge_mean(dkvdu, 0).reshape((-1,) + batch)
    rhs = grid.du.T @ t_u + grid.dv.T @ t_v
    tau = grid.twist_solver.solve(rhs).reshape(k_u.shape)
    return tau - tau.mean(axis=(0, 1))


def solve_twist(
    grid: FineGrid,
    k_u: np.ndarray,
    k_v: np.ndarray,
    lam_u: np.ndarray,
    lam_v: np.ndarray,
    twist_sign: float = 1.0,
) -> tuple[np.ndarray, float]:
    """Twist field τ: the Codazzi solution plus a constant from the Gauss equation
    K = k_u k_v − τ².

    The constant is set only where the product of the normal curvatures is mostly unexplained by
    the metric (an oblique cylinder, a twisted sheet); its sign is not observable (mirror-image
    twists give identical strains), so ``twist_sign`` chooses it.
    """
    tau0 = codazzi_twist(grid, k_u, k_v)
    # Only the region spanned by the cell centres: one-sided differences at the border would
    # bias the metric's curvature.
    inner = (slice(grid.node_rows[0], grid.node_rows[-1] + 1), slice(grid.node_cols[0], grid.node_cols[-1] + 1))
    prod = (k_u * k_v)[inner]
    c2 = np.mean(prod - gaussian_curvature_of_metric(grid, lam_u, lam_v)[inner] - (tau0 * tau0)[inner])
    scale = np.mean(np.abs(prod))
    c2 = max(0.0, 2.0 * c2 - scale)  # 0 unless more than half of k_u k_v is unexplained
    c = float(np.copysign(np.sqrt(c2), twist_sign))
    return tau0 + c, c


def rotation_rates(grid: FineGrid, k_u, k_v, lam_u, lam_v, tau) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors (in the tail frame) of every u-edge and v-edge, (E, 3) each."""
    h = grid.spacing
    g_u, g_v = geodesic_rates(grid, lam_u, lam_v)
    w_u = np.stack([tau, k_u, g_u], axis=-1)
    w_v = np.stack([-k_v, -tau, g_v], axis=-1)
    return h * _edge_mean(w_u, 1).reshape(-1, 3), h * _edge_mean(w_v, 0).reshape(-1, 3)


def integrate_frames(grid: FineGrid, rot_u: np.ndarray, rot_v: np.ndarray, corrections: int = 2) -> np.ndarray:
    """Frames (nf, mf, 3, 3) (columns t_u, t_v, n) from edge rotations: integrate along the
    centre row then along every column, then least-squares corrections that spread the loop
    misclosures over the whole grid (linearised rotation averaging on the fixed Laplacian)."""
    nf, mf = grid.nf, grid.mf
    a0, b0 = grid.centre
    ru = exp_so3(rot_u).reshape(nf, mf - 1, 3, 3)
    rv = exp_so3(rot_v).reshape(nf - 1, mf, 3, 3)
    frames = np.empty((nf, mf, 3, 3))
    frames[a0, b0] = np.eye(3)
    for b in range(b0, mf - 1):
        frames[a0, b + 1] = frames[a0, b] @ ru[a0, b]
    for b in range(b0, 0, -1):
        frames[a0, b - 1] = frames[a0, b] @ ru[a0, b - 1].T
    for a in range(a0, nf - 1):
        frames[a + 1] = frames[a] @ rv[a]
    for a in range(a0, 0, -1):
        frames[a - 1] = frames[a] @ np.swapaxes(rv[a - 1], -1, -2)
    flat = frames.reshape(-1, 3, 3)
    edge_rot = np.concatenate([ru.reshape(-1, 3, 3), rv.reshape(-1, 3, 3)])
    for _ in range(corrections):
        tails, heads = flat[grid.edge_tails], flat[grid.edge_heads]
        mis = log_so3(tails @ edge_rot @ np.swapaxes(heads, -1, -2))  # world-frame misclosure
        delta = grid.laplacian.solve(grid.incidence.T @ mis)
        flat = exp_so3(delta) @ flat
    return flat.reshape(nf, mf, 3, 3)


def integrate_positions(grid: FineGrid, frames, rot_u, rot_v, lam_u, lam_v) -> np.ndarray:
    """Positions (nf, mf, 3) whose edge vectors best match the chords of the arcs implied by the
    frames: length λ·spacing·sinc(bend/2) along the mid-edge tangent."""
    h = grid.spacing
    nf, mf = grid.nf, grid.mf
    flat = frames.reshape(-1, 3, 3)
    chords = []
    for rot, lam, axis, col in ((rot_u, lam_u, 1, 0), (rot_v, lam_v, 0, 1)):
        tails = flat[grid.edge_tails[: grid.n_uedges]] if col == 0 else flat[grid.edge_tails[grid.n_uedges :]]
        mid = tails @ exp_so3(0.5 * rot)
        bend = np.hypot(rot[:, 1 - col], rot[:, 2]) if col == 0 else np.hypot(rot[:, 0], rot[:, 2])
        length = h * _edge_mean(lam, axis).ravel() * np.sinc(bend / (2.0 * np.pi))
        chords.append(mid[:, :, col] * length[:, None])
    chords = np.concatenate(chords)
    pos = grid.laplacian.solve(grid.incidence.T @ chords)
    return pos.reshape(nf, mf, 3)


def refine_positions(
    grid: FineGrid,
    pos: np.ndarray,
    frames: np.ndarray,
    rot_u: np.ndarray,
    rot_v: np.ndarray,
    lam_u: np.ndarray,
    lam_v: np.ndarray,
    iterations: int = 3,
    shear_prior: float = 0.01,
    cg_tol: float = 1e-7,
    cg_maxiter: int = 60,
) -> tuple[np.ndarray, int]:
    """Gauss–Newton passes that let the material lines shear (F ≠ 0) as compatibility demands.

    Each fine edge must lie in the tangent plane (⊥ the mid-edge normal from the frames) and
    have the measured chord length; its in-plane direction is pulled only weakly
    (``shear_prior``) towards the orthogonal net of the frames.  On a curved, non-developable
    sheet the lengths and normals then fix the shear that the gauges do not measure.  Each pass
    is a linear least-squares problem solved by conjugate gradients preconditioned with the
    fixed graph Laplacian.
    """
    if iterations <= 0:
        return pos, 0
    h = grid.spacing
    nf, mf = grid.nf, grid.mf
    flat = frames.reshape(-1, 3, 3)
    tails, heads = grid.edge_tails, grid.edge_heads
    nu = grid.n_uedges
    nrm = flat[tails, :, 2] + flat[heads, :, 2]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    # orthogonal-net direction of each edge (t_u for u-edges, t_v for v-edges) → its in-plane normal
    t_net = np.concatenate([flat[tails[:nu], :, 0] + flat[heads[:nu], :, 0], flat[tails[nu:], :, 1] + flat[heads[nu:], :, 1]])
    b_net = np.cross(nrm, t_net)
    b_net /= np.linalg.norm(b_net, axis=1, keepdims=True)
    bend = np.concatenate([np.hypot(rot_u[:, 1], rot_u[:, 2]), np.hypot(rot_v[:, 0], rot_v[:, 2])])
    length = h * np.concatenate([_edge_mean(lam_u, 1).ravel(), _edge_mean(lam_v, 0).ravel()]) * np.sinc(bend / (2.0 * np.pi))
    inc, inc_t = grid.incidence, grid.incidence.T
    x = pos.reshape(-1, 3).copy()
    beta = shear_prior

    def apply(p: np.ndarray, t_dir: np.ndarray) -> np.ndarray:
        d = inc @ p
        w = (
            nrm * np.einsum("ij,ij->i", nrm, d)[:, None]
            + t_dir * np.einsum("ij,ij->i", t_dir, d)[:, None]
            + beta * b_net * np.einsum("ij,ij->i", b_net, d)[:, None]
        )
        return inc_t @ w

    done = 0
    for _ in range(iterations):
        d = inc @ x
        d -= nrm * np.einsum("ij,ij->i", nrm, d)[:, None]
        t_dir = d / np.linalg.norm(d, axis=1, keepdims=True)
        rhs = inc_t @ (t_dir * length[:, None])
        # preconditioned conjugate gradients, all three coordinates as one vector
        r = rhs - apply(x, t_dir)
        z = grid.laplacian.solve(r)
        p = z.copy()
        rz = np.vdot(r, z)
        r0 = np.sqrt(np.vdot(rhs, rhs)) + 1e-300
        for _k in range(cg_maxiter):
            ap = apply(p, t_dir)
            alpha = rz / np.vdot(p, ap)
            x += alpha * p
            r -= alpha * ap
            if np.sqrt(np.vdot(r, r)) < cg_tol * r0:
                break
            z = grid.laplacian.solve(r)
            rz_new = np.vdot(r, z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        done += 1
    return x.reshape(nf, mf, 3), done
