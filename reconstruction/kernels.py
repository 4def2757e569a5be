"""Compiled per-frame kernels: the steps after the field fit as loops over the fine grid.

The numpy implementations in :mod:`.engine` are the reference (same formulas, same order of
operations); these kernels do the same work in two compiled calls per frame
(:func:`metric_terms` and :func:`surface_positions`), because a 5×5 frame on its 21×21 fine
grid is hundreds of small array operations whose per-call overhead, not arithmetic, sets the
time.  Results agree with the reference to rounding (tested); the loops are sequential and use
no fast-math reordering, so a frame's result is a function of its input alone.

The entry points keep their machine code in numba's on-disk cache (``cache=True``), so a
process loads it instead of compiling: the first writable of ``NUMBA_CACHE_DIR``,
``__pycache__`` next to this file and the user's cache directory (numba's own search; see
docs/reconstruction.md, "Compiled kernels").  With none writable, or a cache that cannot be
read or written, the kernels are compiled in memory: a cache only ever saves time.
:func:`warm_up` (called when a :class:`~skinmap.reconstruction.Reconstructor` is built)
compiles or loads them before the first frame; ``python -m skinmap.reconstruction.kernels``
fills the cache ahead of use.
"""
from __future__ import annotations

import math
import os
from typing import Any, Callable, TypedDict

import numpy as np
import scipy.sparse as sp

from .linalg import cholesky_band

try:
    import numba
except ImportError:  # the numpy reference still works without it
    numba = None  # type: ignore[assignment]

__all__ = [
    "AVAILABLE", "metric_terms", "surface_positions", "as_field", "laplacian_band", "warm_up",
    "graph_residuals", "graph_normal_equations", "graph_sigma_squares", "hermite_coefficients", "node_frames",
    "gauge_strains", "basis_curvature", "stretch_residual", "quartic_grid",
]

AVAILABLE = numba is not None

# Sequential loops without fast-math keep the reference's rounding order; division by zero
# gives inf/NaN as in numpy (the caller checks the result) instead of raising; nogil lets a
# host that runs frames on several threads use its cores.
_OPTIONS: dict[str, Any] = {"error_model": "numpy", "nogil": True}


class _CacheState(TypedDict):
    cached: bool  # the entry points run with numba's on-disk cache
    cache_dir: str | None  # where it is


_state: _CacheState = {"cached": False, "cache_dir": None}
_ENTRY_POINTS: list[str] = []


def _helper(fn: Callable[..., Any]) -> Callable[..., Any]:
    """A helper of the entry points: compiled once and linked into its callers, whose cache
    entries then hold its code too (so it needs no cache entry of its own)."""
    if numba is None:
        return fn
    return numba.njit(**_OPTIONS)(fn)


def _compiled(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Compile ``fn`` lazily with numba's on-disk cache (``cache=True``: ``NUMBA_CACHE_DIR``,
    else ``__pycache__`` next to this file, else the user's cache directory, the first that
    is writable), or in memory only when numba finds none of them writable (a read-only
    install run by a user without a cache directory must still run)."""
    if numba is None:
        return fn
    if not _ENTRY_POINTS or _state["cached"]:
        try:
            disp = numba.njit(cache=True, **_OPTIONS)(fn)
        except RuntimeError:  # numba found no writable location ("cannot cache function ...")
            _in_memory()  # the entry points before this one too: all or none
        else:
            _ENTRY_POINTS.append(fn.__name__)
            _state["cached"], _state["cache_dir"] = True, disp.stats.cache_path
            return disp
    _ENTRY_POINTS.append(fn.__name__)
    return numba.njit(**_OPTIONS)(fn)


def _in_memory() -> None:
    """Rebind every entry point to a dispatcher without a cache (same function, same options,
    so the same machine code): the cache numba chose could not be used."""
    for name in _ENTRY_POINTS:
        globals()[name] = numba.njit(**_OPTIONS)(globals()[name].py_func)
    _state["cached"], _state["cache_dir"] = False, None


# ------------------------------------------------------------------------------ grid helpers
@_helper
def _diff_u(f, h, out):
    """∂/∂u, central differences, one-sided at the edges (as linalg.diff_u_t)."""
    nf, mf = f.shape
    c, e = 0.5 / h, 1.0 / h
    for a in range(nf):
        for b in range(1, mf - 1):
            out[a, b] = (f[a, b + 1] - f[a, b - 1]) * c
        out[a, 0] = (f[a, 1] - f[a, 0]) * e
        out[a, mf - 1] = (f[a, mf - 1] - f[a, mf - 2]) * e


@_helper
def _diff_v(f, h, out):
    """∂/∂v, central differences, one-sided at the edges (as linalg.diff_v_t)."""
    nf, mf = f.shape
    c, e = 0.5 / h, 1.0 / h
    for a in range(1, nf - 1):
        for b in range(mf):
            out[a, b] = (f[a + 1, b] - f[a - 1, b]) * c
    for b in range(mf):
        out[0, b] = (f[1, b] - f[0, b]) * e
        out[nf - 1, b] = (f[nf - 1, b] - f[nf - 2, b]) * e


@_helper
def _mixed_antiderivative(src, h2, out):
    """Least-norm F whose mixed difference over every cell equals h2 × the cell mean of
    ``src`` (as engine._cell_mean + engine._mixed_antiderivative)."""
    nf, mf = src.shape
    col = np.zeros(mf - 1)  # running sums down each column (cumsum over rows)
    for b in range(mf):
        out[0, b] = 0.0
    for a in range(nf - 1):
        out[a + 1, 0] = 0.0
        run = 0.0
        for b in range(mf - 1):
            s0 = src[a, b] + src[a + 1, b]
            s1 = src[a, b + 1] + src[a + 1, b + 1]
            col[b] += h2 * (0.25 * (s0 + s1))
            run += col[b]
            out[a + 1, b + 1] = run
    # double centring: remove column means, row means, add back the grand mean
    col_mean = np.zeros(mf)
    for a in range(nf):
        for b in range(mf):
            col_mean[b] += out[a, b]
    inv_n = 1.0 / nf
    for b in range(mf):
        col_mean[b] *= inv_n
    row_mean = np.zeros(nf)
    grand = 0.0
    for a in range(nf):
        s = 0.0
        for b in range(mf):
            s += out[a, b]
        row_mean[a] = s * (1.0 / mf)
        grand += row_mean[a]
    grand *= 1.0 / nf
    for a in range(nf):
        for b in range(mf):
            out[a, b] = out[a, b] - col_mean[b] - (row_mean[a] - grand)


# ---------------------------------------------------------------------------- metric terms
@_compiled
def metric_terms(h, lam_u, lam_v):
    """(9, nf, mf): E, G, E_u, E_v, G_u, G_v, E_vv/2 + G_uu/2, EG and Brioschi's source at
    F = 0 without the curvature term (the fields of engine.Metric, in its order)."""
    nf, mf = lam_u.shape
    out = np.empty((9, nf, mf))
    e, g = out[0], out[1]
    for a in range(nf):
        for b in range(mf):
            e[a, b] = lam_u[a, b] * lam_u[a, b]
            g[a, b] = lam_v[a, b] * lam_v[a, b]
    e_u, e_v, g_u, g_v, base, eg, src0 = out[2], out[3], out[4], out[5], out[6], out[7], out[8]
    _diff_u(e, h, e_u)
    _diff_u(g, h, g_u)
    _diff_v(e, h, e_v)
    _diff_v(g, h, g_v)
    _diff_v(e_v, h, base)
    _diff_u(g_u, h, src0)  # scratch: G_uu
    for a in range(nf):
        for b in range(mf):
            bs = 0.5 * (base[a, b] + src0[a, b])
            base[a, b] = bs
            ee, gg = e[a, b], g[a, b]
            eu, ev, gu, gv = e_u[a, b], e_v[a, b], g_u[a, b], g_v[a, b]
            eg[a, b] = ee * gg
            q0 = -0.25 * (eu * gu * gg + ev * ee * gv + ev * ev * gg + ee * gu * gu)
            src0[a, b] = bs + q0 / eg[a, b]
    return out


# ----------------------------------------------------------------------------------- shear
@_helper
def _clip9(x):
    """x limited to [−0.9, 0.9]; NaN stays NaN (as np.minimum/np.maximum)."""
    if x > 0.9:
        return 0.9
    if x < -0.9:
        return -0.9
    return x


@_helper
def _shear(h, k_u, k_v, lam_u, lam_v, tau, metric, passes):
    """Sine of the shear angle (as engine.solve_shear with ``passes`` ≥ 1)."""
    nf, mf = k_u.shape
    e, g, e_u, e_v, g_u, g_v, base, eg, src0 = (
        metric[0], metric[1], metric[2], metric[3], metric[4], metric[5], metric[6], metric[7], metric[8],
    )
    src = np.empty((nf, mf))
    for a in range(nf):
        for b in range(mf):
            s11 = k_u[a, b] / lam_u[a, b]
            t = tau[a, b]
            src[a, b] = src0[a, b] + (s11 * k_v[a, b] / lam_v[a, b] - t * t) * eg[a, b]
    f = np.empty((nf, mf))
    h2 = h * h
    _mixed_antiderivative(src, h2, f)
    f_u = np.empty((nf, mf))
    f_v = np.empty((nf, mf))
    for _ in range(passes - 1):
        _diff_u(f, h, f_u)
        _diff_v(f, h, f_v)
        for a in range(nf):
            for b in range(mf):
                lu, lv, t, ff = lam_u[a, b], lam_v[a, b], tau[a, b], f[a, b]
                sg = _clip9(ff / (lu * lv))
                cg2 = 1.0 - sg * sg
                s11 = k_u[a, b] / lu
                s22 = (k_v[a, b] / lv - s11 * sg * sg + 2.0 * t * sg * math.sqrt(cg2)) / cg2
                k_gauss = s11 * s22 - t * t
                # Brioschi's F_uv for this K with the current F (engine._brioschi_source)
                ee, gg, eu, ev, gu, gv = e[a, b], g[a, b], e_u[a, b], e_v[a, b], g_u[a, b], g_v[a, b]
                det = eg[a, b] - ff * ff
                a12, a13 = 0.5 * eu, f_u[a, b] - 0.5 * ev
                a21, a31 = f_v[a, b] - 0.5 * gu, 0.5 * gv
                det_b = -0.5 * ev * (0.5 * ev * gg - 0.5 * ff * gu) + 0.5 * gu * (0.5 * ev * ff - 0.5 * ee * gu)
                q = a12 * (a21 * gg - ff * a31) - a13 * (a21 * ff - ee * a31) + det_b
                src[a, b] = base[a, b] + k_gauss * det + q / det
        _mixed_antiderivative(src, h2, f)
    for a in range(nf):
        for b in range(mf):
            f[a, b] = _clip9(f[a, b] / (lam_u[a, b] * lam_v[a, b]))
    return f


# ------------------------------------------------------------------------- rotation rates
@_helper
def _rotation_rates(h, k_u, k_v, lam_u, lam_v, tau, sin_gamma):
    """Rotation vectors of every u-edge (nf, mf−1, 3) and v-edge (nf−1, mf, 3), in the tail
    frame (as engine.rotation_rates)."""
    nf, mf = k_u.shape
    luv_sg = np.empty((nf, mf))
    for a in range(nf):
        for b in range(mf):
            luv_sg[a, b] = lam_u[a, b] * lam_v[a, b] * sin_gamma[a, b]
    lu_u = np.empty((nf, mf))
    lv_u = np.empty((nf, mf))
    f_u = np.empty((nf, mf))
    lu_v = np.empty((nf, mf))
    _diff_u(lam_u, h, lu_u)
    _diff_u(lam_v, h, lv_u)
    _diff_u(luv_sg, h, f_u)
    _diff_v(lam_u, h, lu_v)
    w_u = np.empty((nf, mf, 3))
    w_v = np.empty((nf, mf, 3))
    for a in range(nf):
        for b in range(mf):
            sg = sin_gamma[a, b]
            cg = math.sqrt(1.0 - sg * sg)
            lu, lv, t = lam_u[a, b], lam_v[a, b], tau[a, b]
            s11 = k_u[a, b] / lu
            s22 = (k_v[a, b] / lv - s11 * sg * sg + 2.0 * t * sg * cg) / (cg * cg)
            inv = 1.0 / (lu * cg)
            w_u[a, b, 0] = lu * t
            w_u[a, b, 1] = lu * s11
            w_u[a, b, 2] = ((f_u[a, b] - lu * lu_v[a, b]) / lv - sg * lu_u[a, b]) * inv
            w_v[a, b, 0] = lv * (t * sg - s22 * cg)
            w_v[a, b, 1] = lv * (s11 * sg - t * cg)
            w_v[a, b, 2] = (lv_u[a, b] - sg * lu_v[a, b]) * inv
    half_h = 0.5 * h
    rot_u = np.empty((nf, mf - 1, 3))
    rot_v = np.empty((nf - 1, mf, 3))
    for a in range(nf):
        for b in range(mf - 1):
            for k in range(3):
                rot_u[a, b, k] = half_h * (w_u[a, b, k] + w_u[a, b + 1, k])
    for a in range(nf - 1):
        for b in range(mf):
            for k in range(3):
                rot_v[a, b, k] = half_h * (w_v[a, b, k] + w_v[a + 1, b, k])
    return rot_u, rot_v


# ------------------------------------------------------------------------------ rotations
@_helper
def _axis_form(c, bb, aa, x, y, z, r):
    """r = c·I + bb·w wᵀ + aa·[w]× for w = (x, y, z) (as linalg._axis_form)."""
    bx, by, bz = bb * x, bb * y, bb * z
    ax, ay, az = aa * x, aa * y, aa * z
    r[0, 0] = c + bx * x
    r[1, 1] = c + by * y
    r[2, 2] = c + bz * z
    bxy, bxz, byz = bx * y, bx * z, by * z
    r[0, 1] = bxy - az
    r[1, 0] = bxy + az
    r[0, 2] = bxz + ay
    r[2, 0] = bxz - ay
    r[1, 2] = byz - ax
    r[2, 1] = byz + ax


@_helper
def _rodrigues(w, r):
    """r = exp([w]×) (as linalg.exp_so3_t)."""
    x, y, z = w[0], w[1], w[2]
    half = 0.5 * math.sqrt(x * x + y * y + z * z)
    sh = math.sin(half)
    sinc_h = sh / half if half > 0 else 1.0
    _axis_form(1.0 - 2.0 * sh * sh, 0.5 * sinc_h * sinc_h, sinc_h * math.cos(half), x, y, z, r)


@_helper
def _mul(p, q, out):
    """out = p q for 3×3 matrices (out must not alias p or q)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = p[i, 0] * q[0, j] + p[i, 1] * q[1, j] + p[i, 2] * q[2, j]


@_helper
def _mul_t(p, q, out):
    """out = p qᵀ for 3×3 matrices."""
    for i in range(3):
        for j in range(3):
            out[i, j] = p[i, 0] * q[j, 0] + p[i, 1] * q[j, 1] + p[i, 2] * q[j, 2]


# ------------------------------------------------------------------ graph Laplacian solves
@_helper
def _divergence(u_vals, v_vals, out):
    """incidenceᵀ @ edge values: every node gets its incoming minus its outgoing edges' values;
    u_vals (nf, mf−1, 3), v_vals (nf−1, mf, 3) → out (3, nf·mf), components first (as
    FineGrid.divergence)."""
    nf, mf1 = u_vals.shape[0], u_vals.shape[1]
    mf = mf1 + 1
    for k in range(3):
        for p in range(nf * mf):
            out[k, p] = 0.0
    for a in range(nf):
        for b in range(mf1):
            p = a * mf + b
            for k in range(3):
                out[k, p + 1] += u_vals[a, b, k]
                out[k, p] -= u_vals[a, b, k]
    for a in range(nf - 1):
        for b in range(mf):
            p = a * mf + b
            for k in range(3):
                out[k, p + mf] += v_vals[a, b, k]
                out[k, p] -= v_vals[a, b, k]


@_helper
def _band_solve(band, x):
    """Solve A x = b in place for A = UᵀU, U upper banded with bandwidth bw, three right-hand
    sides stored components first (3, n).  ``band`` (2, n, bw + 1) holds U by rows,
    band[0, i, k] = U[i, i + k], and by columns, band[1, j, bw − k] = U[j − k, j], so that
    both triangular solves read contiguous memory; each unknown is one dot product per
    component (three independent sums in flight), as LAPACK's ?pbtrs forms it."""
    n, w = band.shape[1], band.shape[2]
    bw = w - 1
    for j in range(n):  # Uᵀ y = b
        s0, s1, s2 = x[0, j], x[1, j], x[2, j]
        for i in range(max(0, j - bw), j):
            u = band[1, j, bw + i - j]
            s0 -= u * x[0, i]
            s1 -= u * x[1, i]
            s2 -= u * x[2, i]
        d = band[1, j, bw]
        x[0, j], x[1, j], x[2, j] = s0 / d, s1 / d, s2 / d
    for i in range(n - 1, -1, -1):  # U x = y
        s0, s1, s2 = x[0, i], x[1, i], x[2, i]
        for k in range(min(bw, n - 1 - i), 0, -1):
            u = band[0, i, k]
            s0 -= u * x[0, i + k]
            s1 -= u * x[1, i + k]
            s2 -= u * x[2, i + k]
        d = band[0, i, 0]
        x[0, i], x[1, i], x[2, i] = s0 / d, s1 / d, s2 / d


# ------------------------------------------------------------------------- frames, positions
@_helper
def _integrate_frames(rot_u, rot_v, a0, b0, corrections, band):
    """Frames (nf, mf, 3, 3) (columns t_u, t_v, n): the tree from the centre (along the centre
    row, then every column), then ``corrections`` least-squares rotation-averaging passes
    (as engine.integrate_frames)."""
    nf, mf = rot_v.shape[0] + 1, rot_v.shape[1]
    ru = np.empty((nf, mf - 1, 3, 3))
    rv = np.empty((nf - 1, mf, 3, 3))
    for a in range(nf):
        for b in range(mf - 1):
            _rodrigues(rot_u[a, b], ru[a, b])
    for a in range(nf - 1):
        for b in range(mf):
            _rodrigues(rot_v[a, b], rv[a, b])
    fr = np.empty((nf, mf, 3, 3))
    for i in range(3):
        for j in range(3):
            fr[a0, b0, i, j] = 1.0 if i == j else 0.0
    # head = tail · R along an edge, tail = head · Rᵀ against it
    for b in range(b0 + 1, mf):
        _mul(fr[a0, b - 1], ru[a0, b - 1], fr[a0, b])
    for b in range(b0 - 1, -1, -1):
        _mul_t(fr[a0, b + 1], ru[a0, b], fr[a0, b])
    for b in range(mf):
        for a in range(a0 + 1, nf):
            _mul(fr[a - 1, b], rv[a - 1, b], fr[a, b])
        for a in range(a0 - 1, -1, -1):
            _mul_t(fr[a + 1, b], rv[a, b], fr[a, b])
    if corrections > 0:
        mis_u = np.empty((nf, mf - 1, 3))
        mis_v = np.empty((nf - 1, mf, 3))
        delta = np.empty((3, nf * mf))
        pred = np.empty((3, 3))
        am = np.empty((3, 3))
        cay = np.empty((3, 3))
        tmp = np.empty((3, 3))
        for _ in range(corrections):
            # world-frame misclosure of each edge: the axial vector of the skew part of
            # (R_tail exp(ω)) R_headᵀ
            for a in range(nf):
                for b in range(mf - 1):
                    _mul(fr[a, b], ru[a, b], pred)
                    _mul_t(pred, fr[a, b + 1], am)
                    mis_u[a, b, 0] = 0.5 * (am[2, 1] - am[1, 2])
                    mis_u[a, b, 1] = 0.5 * (am[0, 2] - am[2, 0])
                    mis_u[a, b, 2] = 0.5 * (am[1, 0] - am[0, 1])
            for a in range(nf - 1):
                for b in range(mf):
                    _mul(fr[a, b], rv[a, b], pred)
                    _mul_t(pred, fr[a + 1, b], am)
                    mis_v[a, b, 0] = 0.5 * (am[2, 1] - am[1, 2])
                    mis_v[a, b, 1] = 0.5 * (am[0, 2] - am[2, 0])
                    mis_v[a, b, 2] = 0.5 * (am[1, 0] - am[0, 1])
            _divergence(mis_u, mis_v, delta)
            _band_solve(band, delta)
            for a in range(nf):
                for b in range(mf):
                    p = a * mf + b
                    x, y, z = 0.5 * delta[0, p], 0.5 * delta[1, p], 0.5 * delta[2, p]
                    q2 = x * x + y * y + z * z
                    c = 2.0 / (1.0 + q2)
                    _axis_form(1.0 - c * q2, c, c, x, y, z, cay)  # Cayley map
                    _mul(cay, fr[a, b], tmp)
                    for i in range(3):
                        for j in range(3):
                            fr[a, b, i, j] = tmp[i, j]
    return fr


@_helper
def _chord_ratio(bend):
    half = 0.5 * bend
    return math.sin(half) / half if half > 0 else 1.0


@_helper
def _positions(h, fr, rot_u, rot_v, lam_u, lam_v, sin_gamma, band):
    """Positions (3, nf·mf) from the chords of every edge (as engine.integrate_positions)."""
    nf, mf = lam_u.shape
    t_v = np.empty((nf, mf, 3))
    for a in range(nf):
        for b in range(mf):
            sg = sin_gamma[a, b]
            cg = math.sqrt(1.0 - sg * sg)
            for k in range(3):
                t_v[a, b, k] = fr[a, b, k, 0] * sg + fr[a, b, k, 1] * cg
    chord_u = np.empty((nf, mf - 1, 3))
    chord_v = np.empty((nf - 1, mf, 3))
    for a in range(nf):
        for b in range(mf - 1):
            d0 = fr[a, b, 0, 0] + fr[a, b + 1, 0, 0]
            d1 = fr[a, b, 1, 0] + fr[a, b + 1, 1, 0]
            d2 = fr[a, b, 2, 0] + fr[a, b + 1, 2, 0]
            bend = math.hypot(rot_u[a, b, 1], rot_u[a, b, 2])
            length = (h * (0.5 * (lam_u[a, b] + lam_u[a, b + 1]))) * _chord_ratio(bend)
            s = length / math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            chord_u[a, b, 0], chord_u[a, b, 1], chord_u[a, b, 2] = d0 * s, d1 * s, d2 * s
    for a in range(nf - 1):
        for b in range(mf):
            d0 = t_v[a, b, 0] + t_v[a + 1, b, 0]
            d1 = t_v[a, b, 1] + t_v[a + 1, b, 1]
            d2 = t_v[a, b, 2] + t_v[a + 1, b, 2]
            bend = math.hypot(rot_v[a, b, 0], rot_v[a, b, 2])
            length = (h * (0.5 * (lam_v[a, b] + lam_v[a + 1, b]))) * _chord_ratio(bend)
            s = length / math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            chord_v[a, b, 0], chord_v[a, b, 1], chord_v[a, b, 2] = d0 * s, d1 * s, d2 * s
    pos = np.empty((3, nf * mf))
    _divergence(chord_u, chord_v, pos)
    _band_solve(band, pos)
    return pos


@_helper
def _sensor_frame(pos, nf, mf, a0, b0, plane_open, plane_blend):
    """Positions (3, nf·mf) → components-first (3, nf, mf) in the sensor frame, as
    reconstruction.to_sensor_frame (every fine node's best-fit plane; the centre's tangent plane
    where that is ill defined, blended): the same steps in the same order."""
    n = nf * mf
    mean = np.zeros(3)
    for k in range(3):
        acc = 0.0
        for p in range(n):
            acc += pos[k, p]
        mean[k] = acc / n
    cov = np.zeros((3, 3))
    for i in range(3):
        for j in range(i + 1):
            acc = 0.0
            for p in range(n):
                acc += pos[i, p] * pos[j, p]
            cov[i, j] = acc - n * mean[i] * mean[j]
            cov[j, i] = cov[i, j]
    var, axes = np.linalg.eigh(cov)
    nz = axes[:, 0].copy()
    c = a0 * mf + b0
    w = mf + mf
    t_u = np.empty(3)
    t_v = np.empty(3)
    for k in range(3):
        t_u[k] = 8.0 * (pos[k, c + 1] - pos[k, c - 1]) - (pos[k, c + 2] - pos[k, c - 2])
        t_v[k] = 8.0 * (pos[k, c + mf] - pos[k, c - mf]) - (pos[k, c + w] - pos[k, c - w])
    n_c = np.array([t_u[1] * t_v[2] - t_u[2] * t_v[1], t_u[2] * t_v[0] - t_u[0] * t_v[2],
                    t_u[0] * t_v[1] - t_u[1] * t_v[0]])
    n_c /= math.sqrt(n_c[0] * n_c[0] + n_c[1] * n_c[1] + n_c[2] * n_c[2])
    chord = np.zeros(3)
    for k in range(3):
        for a in range(nf):
            chord[k] += pos[k, a * mf + mf - 1] - pos[k, a * mf]
    ratio = var[0] / var[1] if var[1] > 0.0 else 1.0
    dot = nz[0] * n_c[0] + nz[1] * n_c[1] + nz[2] * n_c[2]
    if ratio > plane_open:
        t = min((ratio - plane_open) / plane_blend, 1.0)
        sgn = 1.0 if dot >= 0.0 else -1.0
        nz = (1.0 - t) * sgn * nz + t * n_c
        nz /= math.sqrt(nz[0] * nz[0] + nz[1] * nz[1] + nz[2] * nz[2])
        cn = math.sqrt(chord[0] * chord[0] + chord[1] * chord[1] + chord[2] * chord[2])
        un = math.sqrt(t_u[0] * t_u[0] + t_u[1] * t_u[1] + t_u[2] * t_u[2])
        chord = (1.0 - t) * chord / cn + t * t_u / un
    elif dot < 0.0:
        nz = -nz
    d = nz[0] * chord[0] + nz[1] * chord[1] + nz[2] * chord[2]
    x0, x1, x2 = chord[0] - nz[0] * d, chord[1] - nz[1] * d, chord[2] - nz[2] * d
    s = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0, x1, x2 = x0 / s, x1 / s, x2 / s
    n0, n1, n2 = nz[0], nz[1], nz[2]
    y0, y1, y2 = n1 * x2 - n2 * x1, n2 * x0 - n0 * x2, n0 * x1 - n1 * x0
    out = np.empty((3, nf, mf))
    o0, o1, o2 = pos[0, c], pos[1, c], pos[2, c]
    for a in range(nf):
        for b in range(mf):
            p = a * mf + b
            d0, d1, d2 = pos[0, p] - o0, pos[1, p] - o1, pos[2, p] - o2
            out[0, a, b] = x0 * d0 + x1 * d1 + x2 * d2
            out[1, a, b] = y0 * d0 + y1 * d1 + y2 * d2
            out[2, a, b] = n0 * d0 + n1 * d1 + n2 * d2
    return out


@_helper
def _shear_free_part(sin_gamma, lam_u, lam_v, target):
    """Replace the shear's part a(u) + b(v) by that of ``target`` (F of a graph; as
    Reconstructor._positions with graphsheet.free_part)."""
    nf, mf = sin_gamma.shape
    f = np.empty((nf, mf))
    col = np.zeros(mf)
    row = np.zeros(nf)
    for a in range(nf):
        for b in range(mf):
            f[a, b] = sin_gamma[a, b] * (lam_u[a, b] * lam_v[a, b])
            d = target[a, b] - f[a, b]
            col[b] += d
            row[a] += d
    col /= nf
    row /= mf
    mean = col.mean()
    for a in range(nf):
        for b in range(mf):
            sin_gamma[a, b] = _clip9((f[a, b] + col[b] + row[a] - mean) / (lam_u[a, b] * lam_v[a, b]))


@_compiled
def surface_positions(h, k_u, k_v, lam_u, lam_v, tau, metric, shear_passes, corrections, band, a0, b0, shear_target, use_target,
                      plane_open, plane_blend):
    """Fine-grid positions in the sensor frame, components first (3, nf, mf), from the fitted
    fields, the twist τ and the metric terms: shear, rotation rates, frames, chords and their
    least-squares positions in one call (engine.solve_shear, rotation_rates, integrate_frames,
    integrate_positions and to_sensor_frame, whose plane thresholds are ``plane_open`` and
    ``plane_blend``).  With ``use_target`` the shear's free
    part a(u) + b(v) comes from ``shear_target`` (a graph's F, reconstruction/graphsheet.py)."""
    nf, mf = k_u.shape
    if shear_passes > 0:
        sin_gamma = _shear(h, k_u, k_v, lam_u, lam_v, tau, metric, shear_passes)
    else:
        sin_gamma = np.zeros((nf, mf))
    if use_target:
        _shear_free_part(sin_gamma, lam_u, lam_v, shear_target)
    rot_u, rot_v = _rotation_rates(h, k_u, k_v, lam_u, lam_v, tau, sin_gamma)
    fr = _integrate_frames(rot_u, rot_v, a0, b0, corrections, band)
    pos = _positions(h, fr, rot_u, rot_v, lam_u, lam_v, sin_gamma, band)
    return _sensor_frame(pos, nf, mf, a0, b0, plane_open, plane_blend)


# ------------------------------------------------------------------- patches, forward model
@_helper
def _slopes_line(g, n, inv, out):
    """surface.slopes along one line of ``n`` values (fourth-order differences, one-sided
    fourth-order stencils at the ends), in its order of operations, times ``inv`` = 1/(12h)."""
    for i in range(2, n - 2):
        out[i] = ((g[i - 2] - g[i + 2]) + 8.0 * (g[i + 1] - g[i - 1])) * inv
    out[0] = ((((-25.0 * g[0] + 48.0 * g[1]) - 36.0 * g[2]) + 16.0 * g[3]) - 3.0 * g[4]) * inv
    out[1] = ((((-3.0 * g[0] - 10.0 * g[1]) + 18.0 * g[2]) - 6.0 * g[3]) + g[4]) * inv
    out[n - 1] = ((((25.0 * g[n - 1] - 48.0 * g[n - 2]) + 36.0 * g[n - 3]) - 16.0 * g[n - 4]) + 3.0 * g[n - 5]) * inv
    out[n - 2] = ((((3.0 * g[n - 1] + 10.0 * g[n - 2]) - 18.0 * g[n - 3]) + 6.0 * g[n - 4]) - g[n - 5]) * inv


@_compiled
def hermite_coefficients(pos, h, coeffs, d_u, d_v):
    """The bicubic Hermite data of :class:`~.surface.Surface` from fine positions ``pos``
    (3, nf, mf): ``coeffs`` (nf, mf, 4, 3) = value, h·∂u, h·∂v, h²·∂uv per node and the
    unscaled slopes ``d_u``, ``d_v`` (3, nf, mf), as surface.slopes computes them."""
    nf, mf = pos.shape[1], pos.shape[2]
    inv = 1.0 / (12.0 * h)
    hh = h * h
    line_u = np.empty(mf)
    line_v = np.empty(nf)
    col = np.empty(nf)
    duv = np.empty(nf)
    for c in range(3):
        for a in range(nf):
            _slopes_line(pos[c, a], mf, inv, line_u)
            for b in range(mf):
                d_u[c, a, b] = line_u[b]
        for b in range(mf):
            for a in range(nf):
                col[a] = pos[c, a, b]
            _slopes_line(col, nf, inv, line_v)
            for a in range(nf):
                d_v[c, a, b] = line_v[a]
                col[a] = d_u[c, a, b]
            _slopes_line(col, nf, inv, duv)
            for a in range(nf):
                coeffs[a, b, 0, c] = pos[c, a, b]
                coeffs[a, b, 1, c] = d_u[c, a, b] * h
                coeffs[a, b, 2, c] = line_v[a] * h
                coeffs[a, b, 3, c] = duv[a] * hh


@_compiled
def node_frames(pos, d_u, d_v, rows, cols, nodes, normals):
    """A :class:`~.surface.Surface`'s nodes and unit normals, each (N, M, 3), at the fine nodes
    ``rows`` × ``cols`` of its positions ``pos`` and slopes ``d_u``, ``d_v`` (3, nf, mf, as
    :func:`hermite_coefficients` gives them): the cross product d_u × d_v over its norm, in
    linalg.cross_t's and the Surface's own order of operations."""
    for i in range(rows.size):
        a = rows[i]
        for j in range(cols.size):
            b = cols[j]
            u0, u1, u2 = d_u[0, a, b], d_u[1, a, b], d_u[2, a, b]
            v0, v1, v2 = d_v[0, a, b], d_v[1, a, b], d_v[2, a, b]
            n0 = u1 * v2 - u2 * v1
            n1 = u2 * v0 - u0 * v2
            n2 = u0 * v1 - u1 * v0
            norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            normals[i, j, 0], normals[i, j, 1], normals[i, j, 2] = n0 / norm, n1 / norm, n2 / norm
            nodes[i, j, 0], nodes[i, j, 1], nodes[i, j, 2] = pos[0, a, b], pos[1, a, b], pos[2, a, b]


@_helper
def _sum_like_numpy(a):
    """Sum of a short contiguous row in numpy's order (its pairwise summation: eight partial
    sums from 8 terms on, combined pairwise, then the rest one by one)."""
    n = a.shape[0]
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - (n % 8):
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res


@_compiled
def gauge_strains(coeffs, base, mf, weights, per, h_upper, h_lower, gauge_length, out_u, out_l):
    """forward.surface_strains on the bicubic patches ``coeffs`` (nf·mf, 4, 3): every gauge's
    ``per`` sample points (``base``: the flat index of each point's patch corner, ``weights``
    (points, 3, 16): position, ∂u, ∂v of the 16 corner data), their unit normals, both layer
    polylines and Richardson's length, written into ``out_u``, ``out_l`` (gauges,)."""
    gauges = out_u.shape[0]
    pts = np.empty((per, 3))
    nrm = np.empty((per, 3))
    val = np.empty(3)
    offset = np.array([0, 1, mf, mf + 1])
    fine = np.empty(per - 1)
    for g in range(gauges):
        for s in range(per):
            k = g * per + s
            du0 = du1 = du2 = dv0 = dv1 = dv2 = 0.0
            p0 = p1 = p2 = 0.0
            for r in range(3):
                val[0] = val[1] = val[2] = 0.0
                for c in range(4):
                    node = base[k] + offset[c]
                    for q in range(4):
                        w = weights[k, r, 4 * c + q]
                        if w == 0.0:  # (most: a gauge runs along a fine-grid line) adds nothing
                            continue
                        val[0] += w * coeffs[node, q, 0]
                        val[1] += w * coeffs[node, q, 1]
                        val[2] += w * coeffs[node, q, 2]
                if r == 0:
                    p0, p1, p2 = val[0], val[1], val[2]
                elif r == 1:
                    du0, du1, du2 = val[0], val[1], val[2]
                else:
                    dv0, dv1, dv2 = val[0], val[1], val[2]
            n0 = du1 * dv2 - du2 * dv1
            n1 = du2 * dv0 - du0 * dv2
            n2 = du0 * dv1 - du1 * dv0
            norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            pts[s, 0], pts[s, 1], pts[s, 2] = p0, p1, p2
            nrm[s, 0], nrm[s, 1], nrm[s, 2] = n0 / norm, n1 / norm, n2 / norm
        for layer in range(2):
            hl = h_upper if layer == 0 else -h_lower
            coarse = 0.0
            e0 = e1 = e2 = 0.0
            x0 = pts[0, 0] + hl * nrm[0, 0]
            x1 = pts[0, 1] + hl * nrm[0, 1]
            x2 = pts[0, 2] + hl * nrm[0, 2]
            for s in range(per - 1):
                y0 = pts[s + 1, 0] + hl * nrm[s + 1, 0]
                y1 = pts[s + 1, 1] + hl * nrm[s + 1, 1]
                y2 = pts[s + 1, 2] + hl * nrm[s + 1, 2]
                d0, d1, d2 = y0 - x0, y1 - x1, y2 - x2
                fine[s] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if s % 2 == 0:
                    e0, e1, e2 = d0, d1, d2
                else:
                    e0, e1, e2 = e0 + d0, e1 + d1, e2 + d2
                    coarse += math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                x0, x1, x2 = y0, y1, y2
            total = _sum_like_numpy(fine)
            length = (4.0 * total - coarse) / 3.0
            if layer == 0:
                out_u[g] = length / gauge_length - 1.0
            else:
                out_l[g] = length / gauge_length - 1.0




# ------------------------------------------------------------------- the membrane's curvature
@_compiled
def basis_curvature(pos, rows, cols, h, out):
    """membrane.basis_curvature: the Gaussian curvature (LN − M²)/(EG − F²) of fine positions
    ``pos`` (nf, mf, 3) at the basis nodes ``rows`` × ``cols`` (central differences, a node on
    the outer edge taking its inner neighbour's) into ``out`` (rows·cols), in its order of
    operations.  A frame reads it for each member of a twist family it weighs."""
    nf, mf = pos.shape[0], pos.shape[1]
    h2 = h * h
    xu, xv, xuu, xvv, xuv = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    k = 0
    for r in rows:
        a = min(max(r, 1), nf - 2)
        for c in cols:
            b = min(max(c, 1), mf - 2)
            for d in range(3):
                p0 = pos[a, b, d]
                xu[d] = (pos[a, b + 1, d] - pos[a, b - 1, d]) / (2.0 * h)
                xv[d] = (pos[a + 1, b, d] - pos[a - 1, b, d]) / (2.0 * h)
                xuu[d] = (pos[a, b + 1, d] - 2.0 * p0 + pos[a, b - 1, d]) / h2
                xvv[d] = (pos[a + 1, b, d] - 2.0 * p0 + pos[a - 1, b, d]) / h2
                xuv[d] = (pos[a + 1, b + 1, d] - pos[a - 1, b + 1, d] - pos[a + 1, b - 1, d]
                          + pos[a - 1, b - 1, d]) / (4.0 * h2)
            n0 = xu[1] * xv[2] - xu[2] * xv[1]
            n1 = xu[2] * xv[0] - xu[0] * xv[2]
            n2 = xu[0] * xv[1] - xu[1] * xv[0]
            norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
            l_ = xuu[0] * n0 + xuu[1] * n1 + xuu[2] * n2
            m_ = xuv[0] * n0 + xuv[1] * n1 + xuv[2] * n2
            n_ = xvv[0] * n0 + xvv[1] * n1 + xvv[2] * n2
            e = xu[0] * xu[0] + xu[1] * xu[1] + xu[2] * xu[2]
            f = xu[0] * xv[0] + xu[1] * xv[1] + xu[2] * xv[2]
            g = xv[0] * xv[0] + xv[1] * xv[1] + xv[2] * xv[2]
            out[k] = (l_ * n_ - m_ * m_) / (e * g - f * f)
            k += 1


@_compiled
def stretch_residual(ab, k_basis, stretch, ok, nu_low, nu_high, out):
    """membrane.stretch_residual: the residuals of s = e_dir + (A + νB)K over the measured
    units ``ok`` (flat, row gauges then column gauges) into ``out`` (one per measured unit),
    each direction's mean taken out, ν fitted and held to [``nu_low``, ``nu_high``]; returns ν."""
    units = ok.size
    half = units // 2
    predicted = np.zeros(2 * units)
    for i in range(2 * units):
        acc = 0.0
        for j in range(k_basis.size):
            acc += ab[i, j] * k_basis[j]
        predicted[i] = acc
    # each direction's means of the stretch and of the two parts over its measured units
    sums = np.zeros((2, 3))
    counts = np.zeros(2)
    for i in range(units):
        if ok[i]:
            g = 0 if i < half else 1
            sums[g, 0] += stretch[i] - 1.0
            sums[g, 1] += predicted[i]
            sums[g, 2] += predicted[units + i]
            counts[g] += 1.0
    for g in range(2):
        c = max(counts[g], 1.0)
        for col in range(3):
            sums[g, col] /= c
    along = np.empty(out.size)
    k = 0
    for i in range(units):
        if ok[i]:
            g = 0 if i < half else 1
            out[k] = (stretch[i] - 1.0 - sums[g, 0]) - (predicted[i] - sums[g, 1])
            along[k] = predicted[units + i] - sums[g, 2]
            k += 1
    num, den = 0.0, 0.0
    for k in range(out.size):
        num += out[k] * along[k]
        den += along[k] * along[k]
    nu = min(max(num / max(den, 1e-300), nu_low), nu_high)
    for k in range(out.size):
        out[k] -= nu * along[k]
    return nu


@_compiled
def quartic_grid(c4, c3, c2, c1, c0, ms, out):
    """membrane.read_twist's misfit over its grid: ``out[i, j]`` = the quartic of coefficients
    ``c4[i]`` … ``c0[i]`` (one per ν tried) at ``ms[j]``, by Horner's rule in numpy's order of
    operations (the grid is thousands of values: numpy's passes over it cost most of a reading)."""
    for i in range(out.shape[0]):
        a4, a3, a2, a1, a0 = c4[i], c3[i], c2[i], c1[i], c0[i]
        for j in range(out.shape[1]):
            m = ms[j]
            out[i, j] = (((a4 * m + a3) * m + a2) * m + a1) * m + a0


# ------------------------------------------------------------------------ geometry, warm-up
def as_field(x: np.ndarray) -> np.ndarray:
    """``x`` as the kernels take it: float64, C-contiguous, writeable (another layout would be
    a different signature, compiled in the middle of a frame).  No copy when it already is."""
    if x.dtype == np.float64 and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.float64, order="C")



def laplacian_band(incidence: sp.spmatrix, pinned: int, factor: np.ndarray | None = None) -> np.ndarray:
    """The edge graph's Laplacian with node ``pinned`` held (its null space is the constant), as
    the Cholesky band that :func:`surface_positions` takes (see ``_band_solve``): (2, nodes,
    bw + 1).  ``factor``: that factor in LAPACK's upper band storage if already computed (the
    grid's own Laplacian solver keeps one).  Natural (row-major) node order keeps the
    bandwidth at one grid row."""
    if factor is None:
        lap = (incidence.T @ incidence).tocsc()
        n = lap.shape[0]
        factor = cholesky_band(lap + sp.csc_matrix(([1.0], ([pinned], [pinned])), shape=(n, n)))
    bw, n = factor.shape[0] - 1, factor.shape[1]
    band = np.zeros((2, n, bw + 1))
    band[1] = factor.T  # band[1, j, bw − k] = U[j − k, j] = ab[bw − k, j]
    for k in range(bw + 1):  # band[0, i, k] = U[i, i + k] = ab[bw − k, i + k]
        band[0, : n - k, k] = factor[bw - k, k:]
    return band


# ------------------------------------------------------------------------- graph fit
@_helper
def _gauge_point(da, db, daa, vals, g, q):
    """Slope along (a) and across (b) the gauge and the second derivative along it at point q."""
    a = 0.0
    b = 0.0
    aa = 0.0
    for k in range(vals.shape[0]):
        a += da[g, q, k] * vals[k]
        b += db[g, q, k] * vals[k]
        aa += daa[g, q, k] * vals[k]
    return a, b, aa


@_compiled
def graph_residuals(c, idx, da, db, daa, wq, turning, stretch, w_t, w_s, res):
    """Normalised residuals of the graph model (see :mod:`.graphfit`): res[:G] turning,
    res[G:] stretch, G gauges."""
    ng, nq, nl = da.shape
    vals = np.empty(nl)
    for g in range(ng):
        for k in range(nl):
            vals[k] = c[idx[g, k]]
        t_m = 0.0
        s_m = 0.0
        for q in range(nq):
            a, b, aa = _gauge_point(da, db, daa, vals, g, q)
            lam2 = 1.0 + a * a
            lam = math.sqrt(lam2)
            t_m += wq[q] * (-aa / (math.sqrt(lam2 + b * b) * lam))
            s_m += wq[q] * lam
        res[g] = (t_m - turning[g]) * w_t[g]
        res[ng + g] = (s_m - stretch[g]) * w_s[g]


@_compiled
def graph_normal_equations(c, idx, da, db, daa, wq, turning, stretch, w_t, w_s, band, rhs, with_matrix, curvature, res,
                           jac, jac_local):
    """Adds JᵀJ (lower band storage, band[d, j] = A[j + d, j]) and Jᵀr of the graph model's
    normalised residuals to ``band`` and ``rhs`` (which hold the prior's part); only Jᵀr when
    not ``with_matrix``; the normalised residuals to ``res`` (turning, then stretch) and, when
    ``jac`` has rows, the normalised Jacobian to ``jac`` (2G, coefficients); when ``jac_local``
    has rows, its rows over each gauge's own coefficients ``idx`` to ``jac_local`` (2G, idx
    columns: turning rows, then stretch rows; 0 at the padding).
    ``curvature`` = (p, n): the matrix also takes p·r ∂²r of every stretch residual r > 0 and
    n·|r| ∂²r of every r < 0 (∂²r ≥ 0): plain Gauss-Newton sees no stretch where a slope is
    small, and overshoots there (see :mod:`.graphfit`)."""
    ng, nq, nl = da.shape
    vals = np.empty(nl)
    jt = np.empty(nl)
    js = np.empty(nl)
    lam_q = np.empty(nq)
    block = np.empty((nl, nl))
    for g in range(ng):
        for k in range(nl):
            vals[k] = c[idx[g, k]]
            jt[k] = 0.0
            js[k] = 0.0
        t_m = 0.0
        s_m = 0.0
        for q in range(nq):
            a, b, aa = _gauge_point(da, db, daa, vals, g, q)
            lam2 = 1.0 + a * a
            w2 = lam2 + b * b
            lam = math.sqrt(lam2)
            lam_q[q] = lam
            inv = 1.0 / (math.sqrt(w2) * lam)
            t_m += wq[q] * (-aa * inv)
            s_m += wq[q] * lam
            d_aa = wq[q] * -inv
            d_a = wq[q] * (aa * inv) * (a / w2 + a / lam2)
            d_b = wq[q] * (aa * inv) * (b / w2)
            d_s = wq[q] * (a / lam)
            for k in range(nl):
                jt[k] += d_aa * daa[g, q, k] + d_a * da[g, q, k] + d_b * db[g, q, k]
                js[k] += d_s * da[g, q, k]
        rt = (t_m - turning[g]) * w_t[g]
        rs = (s_m - stretch[g]) * w_s[g]
        res[g] = rt
        res[ng + g] = rs
        for k in range(nl):
            jt[k] *= w_t[g]
            js[k] *= w_s[g]
            rhs[idx[g, k]] += jt[k] * rt + js[k] * rs
        if jac.shape[0] == 2 * ng:  # the normalised Jacobian itself, dense (the uncertainty needs it)
            for k in range(nl):
                jac[g, idx[g, k]] += jt[k]
                jac[ng + g, idx[g, k]] += js[k]
        if jac_local.shape[0] == 2 * ng:  # ... or over the gauge's own coefficients (large sheets)
            for k in range(nl):
                jac_local[g, k] = jt[k]
                jac_local[ng + g, k] = js[k]
        if not with_matrix:
            continue
        # this gauge's block (lower triangle), then added to the band at its indices
        for k in range(nl):
            for l in range(k + 1):
                block[k, l] = jt[k] * jt[l] + js[k] * js[l]
        cr = curvature[0] * rs if rs > 0.0 else -curvature[1] * rs
        if cr > 0.0:
            for q in range(nq):
                lam = lam_q[q]
                cw = cr * w_s[g] * wq[q] / (lam * lam * lam)
                for k in range(nl):
                    dk = cw * da[g, q, k]
                    for l in range(k + 1):
                        block[k, l] += dk * da[g, q, l]
        for k in range(nl):
            i = idx[g, k]
            for l in range(k + 1):
                j = idx[g, l]
                if i > j:
                    band[i - j, j] += block[k, l]
                elif j > i:
                    band[j - i, i] += block[k, l]
                elif k == l:
                    band[0, i] += block[k, l]
                else:  # padding repeats a real index: the pair counts on both sides
                    band[0, i] += 2.0 * block[k, l]


@_compiled
def graph_sigma_squares(idx, jac_local, x, out):
    """Adds |J x_p|² of every column p of ``x`` (coefficients, P), C-ordered, to ``out`` (P,):
    J the normalised Jacobian as ``jac_local`` (2G, idx columns, turning rows then stretch; see
    :func:`graph_normal_equations`), each gauge's rows over its own coefficients ``idx``
    (G, idx columns).  The node σ of a large graph fit without a sparse matrix: the rows of x
    a gauge touches are contiguous over the columns, so each datum is a few dozen
    vectorised multiply-adds over all of them at once."""
    ng = idx.shape[0]
    nl = idx.shape[1]
    acc_t = np.empty(x.shape[1])
    acc_s = np.empty(x.shape[1])
    for g in range(ng):  # a gauge's turning and stretch rows together: its rows of x read once
        acc_t[:] = 0.0
        acc_s[:] = 0.0
        for k in range(nl):
            a_t = jac_local[g, k]
            a_s = jac_local[ng + g, k]
            if a_t != 0.0 or a_s != 0.0:  # (the padding)
                row = x[idx[g, k]]
                for p in range(acc_t.shape[0]):
                    acc_t[p] += a_t * row[p]
                    acc_s[p] += a_s * row[p]
        for p in range(acc_t.shape[0]):
            out[p] += acc_t[p] * acc_t[p] + acc_s[p] * acc_s[p]


def warm_up(h: float, a0: int, b0: int, band: np.ndarray, shear_passes: int, corrections: int) -> bool:
    """Compile (or load from the cache) every kernel with the argument types of a frame, on a
    flat sheet of this grid, so that the first frame does not pay for it.  Returns whether the
    kernels came from or went to an on-disk cache.  A cache entry that cannot be read (corrupt,
    its directory gone) or written only costs the compile: the kernels are then compiled in
    memory."""
    if numba is not None and _state["cached"]:
        try:
            _warm(h, a0, b0, band, shear_passes, corrections)
        except Exception:  # noqa: BLE001 - whatever the cache holds or lacks, compiling is the answer
            _in_memory()  # and a fault of the kernels themselves shows again below
        else:
            return True
    _warm(h, a0, b0, band, shear_passes, corrections)
    return _state["cached"]


def _warm(h: float, a0: int, b0: int, band: np.ndarray, shear_passes: int, corrections: int) -> None:
    nf, mf = band.shape[1] // (2 * b0 + 1), 2 * b0 + 1
    zero, one = np.zeros((nf, mf)), np.ones((nf, mf))
    metric = metric_terms(float(h), one, one)
    pos = surface_positions(
        float(h), zero, zero, one, one, zero, metric, int(shear_passes), int(corrections), band, int(a0), int(b0),
        zero, False, 0.3, 0.2,
    )
    if not np.isfinite(pos).all():
        raise RuntimeError("compiled reconstruction kernels gave a non-finite flat sheet")
    # the patches and the gauges' forward model, on that sheet (one gauge of three points)
    coeffs = np.empty((nf, mf, 4, 3))
    slopes = np.empty((2, 3, nf, mf))
    hermite_coefficients(np.ascontiguousarray(pos), float(h), coeffs, slopes[0], slopes[1])
    # read-only arrays are another signature to numba: a twist family's members are shared
    # read-only, and their first use was compiled, or loaded from the cache, in the middle of a
    # frame (a held elastic saddle's first frame: 1.2 s with an empty cache, 5-10 ms from a
    # filled one)
    frozen = np.array(pos)
    frozen.flags.writeable = False
    hermite_coefficients(frozen, float(h), coeffs, slopes[0], slopes[1])
    at = np.zeros(1, dtype=np.intp)
    node_frames(np.ascontiguousarray(pos), slopes[0], slopes[1], at, at, np.empty((1, 1, 3)), np.empty((1, 1, 3)))
    node_frames(frozen, slopes[0], slopes[1], at, at, np.empty((1, 1, 3)), np.empty((1, 1, 3)))
    strain = np.empty(1)
    gauge_strains(coeffs.reshape(nf * mf, 4, 3), np.zeros(3, dtype=np.intp), mf, np.zeros((3, 3, 16)), 3, 0.2, 0.2,
                  1.0, strain, strain)
    # the graph fit's kernels, on one gauge touching four coefficients
    idx = np.zeros((1, 4), dtype=np.int64)
    pts = np.zeros((1, 2, 4))
    one_g, res = np.ones(1), np.empty(2)
    graph_residuals(np.zeros(4), idx, pts, pts, pts, np.full(2, 0.5), one_g, one_g, one_g, one_g, res)
    jac_local = np.zeros((2, 4))
    graph_normal_equations(np.zeros(4), idx, pts, pts, pts, np.full(2, 0.5), one_g, one_g, one_g, one_g,
                           np.zeros((4, 4)), np.zeros(4), True, np.ones(2), res, np.zeros((2, 4)), jac_local)
    graph_sigma_squares(idx, jac_local, np.zeros((4, 3)), np.zeros(3))
    # the membrane's curvature on that sheet, at one node (a flat sheet's is 0)
    corner = np.zeros(1, dtype=np.intp)
    k_flat = np.empty(1)
    basis_curvature(pos.transpose(1, 2, 0), corner, corner, float(h), k_flat)
    basis_curvature(frozen.transpose(1, 2, 0), corner, corner, float(h), k_flat)
    ab = np.zeros((4, 1))
    stretch_residual(ab, k_flat, np.ones(2), np.ones(2, dtype=np.bool_), 0.3, 0.5, np.empty(2))
    ab.flags.writeable = False  # the membrane maps' are shared read-only
    stretch_residual(ab, k_flat, np.ones(2), np.ones(2, dtype=np.bool_), 0.3, 0.5, np.empty(2))
    # the membrane's reading of the twist, on a grid of one
    quartic_grid(k_flat, k_flat, k_flat, k_flat, k_flat, k_flat, np.empty((1, 1)))


if __name__ == "__main__":  # python -m skinmap.reconstruction.kernels: fill the cache ahead of use
    from skinmap.reconstruction import Reconstructor
    from skinmap.reconstruction import kernels as _installed

    Reconstructor(5, 5)  # its warm-up compiles the kernels, or loads them when already cached
    where = _installed._state["cache_dir"]
    print(f"reconstruction kernels {f'cached ({where})' if _installed._state['cached'] else 'compiled, no cache'}")
