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
resolved here (5 mm / FWHM 15 mm bumps: 0.19 → 0.02 mm mean error).  w is a bicubic B-spline
with knots every pitch/3 over the whole sheet (pitch/2 above :data:`COARSE_KNOTS_CELLS` cells, where
a frame's band factorisation would otherwise exceed the frame budget); the fit minimises

    ½ Σ_gauges ((Θ/g)_model − Θ/g)²/σ_Θ² + ((L/g)_model − L/g)²/σ_L² + ½ s ∫∫ |∇³w|² du dv

by Gauss-Newton with a backtracking line search.  A cold frame starts twice, from the linear
(small-slope) fit of the turning data and from the general model's surface, and keeps the
accepted fit with the lower objective (each start has basins it misses).  A warm frame starts
from the previous frame's graph, or its linear prediction for a moving shape, and takes a few
steps on one factorised matrix that also holds the stretch residuals' own curvature (damping
the steps where a slope is small).  The fit is *accepted* only when it explains the data to
within the sensor's noise (mean squared normalised residual of the turning and of the stretch
each at most :data:`ACCEPT_CHI2`) and, on a cold frame, when its surface is the general model's
within their combined uncertainty (:data:`AGREE_SIGMAS`, :func:`disagreement`: a fold hidden in
the gaps between the gauges adds slope, read as stretch, that no turning reading sees, so a film
stretched in its plane can be fitted within the noise by a graph far from it); otherwise the
sheet is not a graph (laid on isometrically, stretched in its plane, a glitching gauge, ...) and
the general model takes over.  The
uncertainty is propagated through the fit's own normal equations (:meth:`GraphFit.fine_height_sigma`).
Small problems only: the unknowns grow with the cells, (3N + 3)(3M + 3), so the fit is offered
up to :data:`MAX_CELLS` cells (the default there, see ``Reconstructor``), and above, as the rescue
of larger sheets, with (2N + 3)(2M + 3) unknowns beyond :data:`COARSE_KNOTS_CELLS` cells.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from typing import Callable, NamedTuple, cast

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.interpolate import BSpline
from scipy.linalg.blas import dgemm as _gemm
from scipy.linalg.lapack import dpbtrf as _pbtrf
from scipy.linalg.lapack import dpbtrs as _pbtrs
from scipy.linalg.lapack import dtrtrs as _trtrs

from skinmap.strains import cell_axes

from .linalg import BandCholeskyBlocks, aligned_distances
from .uncertainty import plane_slopes

__all__ = ["GraphFit", "GraphResult", "ACCEPT_CHI2", "AGREE_SIGMAS", "MAX_CELLS", "TWIST_SIGN_FLOOR", "WARM_LINEAR",
           "DAMPED_OBJECTIVE", "DAMPED_RATIO", "DAMPED_LINEAR",
           "WARM_UNSETTLED", "WARM_MORE_STEPS", "disagreement",
           "KNOTS_PER_PITCH", "COARSE_KNOTS_CELLS", "knots_per_pitch"]

#: Acceptance: mean squared residual of the turning and of the stretch, each in units of its
#: noise variance.  Measured (5×5, noise s.d. 0.0057 %): converged graphs 0.3-3 (noise-free
#: far below); sheets that are not graphs (isometric cylinders, geodesically laid caps and
#: bumps) 300 and above; troughs stopped short of convergence 5-15 (with errors up to 0.4 mm:
#: hence 4, not more).
ACCEPT_CHI2 = 4.0
#: Agreement with the general model (cold frames): the median over the fine nodes of the distance
#: between the two surfaces (after the best rigid alignment) in units of their combined s.d.
#: (noise of both, and the general model's resolution, see uncertainty.resolution_sigma) at
#: most this: 3 s.d.  Measured (5×5, noise-free and noisy, 300 frames): graphs up to 1.1; films
#: pre-stretched in their plane, which a graph mimics with folds hidden between the gauges,
#: 9.4 (1 % on a sphere of R 120 mm, noisy) to 34.
AGREE_SIGMAS = 3.0
#: Size limit (cells) of the graph fit: a 5×5 sheet has 324 unknowns, 8×8 729.
MAX_CELLS = 64
#: A graph twist (mean w_uv, 1/mm) smaller than this has no sign worth contradicting twist_sign.
TWIST_SIGN_FLOOR = 1e-4
#: Knots a pitch of the graph's B-splines: every pitch/3 holds a bump of FWHM 15 mm (on 5×5,
#: pitch/2 misfits it beyond ACCEPT_CHI2 and the spec corner falls back to the general model).
KNOTS_PER_PITCH = 3
#: Above this many cells (the rescue of larger sheets, 145 to 256 cells) knots every pitch/2: a
#: warm frame's cost is one band factorisation, n·b² for n = (kN + 3)(kM + 3) unknowns and a band
#: b of about 5(kM + 3), and pitch/3 made a 16×16 frame of a sharp moving bump 13–17 ms (7 ms of
#: it the factorisation, 2601 unknowns).  At pitch/2 (1225 unknowns) it is 6.3 ms and its node σ
#: 33 ms (85), and the bump is read to 0.048 mm (0.039; the general model alone 0.235): the
#: bench's 16×16 kinematic bumps noise-free 0.0055 → 0.0092 mm, the spec corner 0.014 → 0.019,
#: noisy the same (docs/reconstruction.md, *Larger sheets*).
COARSE_KNOTS_CELLS = 144
_QUADRATURE = (4, 2)  # Gauss-Legendre nodes per panel, panels per gauge
_PRIOR_WEIGHTS = ((3, 0, 1.0), (2, 1, 3.0), (1, 2, 3.0), (0, 3, 1.0))  # ∫|∇³w|², isotropic
_PRIOR_SCALE = 1000.0  # (mm units) far below the data where gauges are; stiff enough between
# them for Gauss-Newton (at 1, steps overshoot by 10⁶) and for a modest scatter at the corners
_RIDGE = 1e-6  # keeps the normal equations definite along modes no datum sees
_MAX_STEPS = 10  # from a cold start
_GIVE_UP_CHI2 = 50.0 * ACCEPT_CHI2  # after _GIVE_UP_AFTER steps: not a graph, stop paying
_GIVE_UP_AFTER = 4
_WARM_STEPS = 4  # from the previous frame (or its prediction), on one factorised matrix
# The stretch residuals' own curvature in the matrix, for r > 0 and r < 0 (see
# kernels.graph_normal_equations): damps the steps where a slope is small, at the price of
# slower progress from far away, so the warm steps (near the optimum) and the uncertainty take
# it and the cold fits do not.
_WARM_CURVATURE = (1.0, 1.0)
# The uncertainty takes a quarter of that curvature on sheets of up to _SIGMA_CURVATURE_CELLS
# cells.  At full weight it is damping, no information (the graph's σ was 0.6 of the Monte-Carlo
# scatter on turned saddles), and at 0.5-1 the bumps' scatter stood at 1.3-1.9 of σ; without it,
# where the sheet is flat, JᵀJ loses the stretch (quadratic in the slope) that the fit itself
# meets, and the 5×5 and 8×8 bumps' scatter was 0.57-0.65 of σ; a quarter brings them to
# 0.94-1.01.  On larger sheets, flat over more of their extent, the same quarter left σ short
# (16×16 bumps and ridges 1.32-1.39 of it on unseen scenes, and two frames beyond 3σ + 0.05 mm),
# so they keep JᵀJ + P (docs/reconstruction.md, "A graph answer's own answer to noise").  At a
# noise-free answer the residuals, hence the term, vanish.
_SIGMA_CURVATURE = (0.25, 0.25)
_SIGMA_CURVATURE_CELLS = 64
_COLD_CURVATURE = (0.0, 0.0)
# Near the optimum (objective within this many times the noise's own, about one per unit) a
# cold fit's Gauss-Newton steps overshoot: the stretch residuals' own curvature, which JᵀJ
# leaves out, is then as large as what it keeps, and nearly every step was halved or quartered
# (5×5 noisy bumps: 9 factorisations and 21 evaluations a fit, 54 of 104 fits stopped by the
# step limit).  From there the matrix takes that curvature where it adds to JᵀJ (residuals
# r > 0; where r < 0 it would take away, and the matrix could lose definiteness): 6
# factorisations and 9 evaluations a fit, and a lower objective on most fits (docs/reconstruction.md).
_CURVATURE_NEAR = 4.0
_NEAR_CURVATURE = (1.0, 0.0)
_WARM_REUSE = 1.0  # warm: reuse the factorised matrix until a step with it fails
_REUSE_RATIO = 0.3  # cold: keep the factorised matrix while each drop is below this share of the last
_SCREEN_SIGMAS = 2.0  # implied mean stretch below this many noise s.d.: small slopes, no fit
_SCREEN_SHORT = 6.0  # a gauge shorter by this many noise s.d.: not a graph
# measured / implied stretch outside: not a graph.  The upper end is 8, not 4: a 5 mm / FWHM 15
# mm bump between the cells of a 5×5 sheet reads 4.1-4.5 times the stretch of either smooth
# start, and from either the fit reaches it (0.33 → 0.010 mm)
_SCREEN_RATIO = (0.5, 8.0)
_MORE_STRETCH = "stretch above:"  # screen reasons that another start (with twist) may answer
_TOLERANCE = 1e-3  # stop when a step lowers the objective by less than this per gauge pair
# above this many coefficients node σ from the band factor, J by gauge (every size: on 5×5 and 8×8
# too it is 1.9x and 2.3x faster than the dense triangle's ?trtrs, the same σ to 1e-14; tests set it
# high to reach the dense path as a reference)
_BAND_SIGMA_SIZE = 0
_SIGMA_ROWS_KEPT = 8  # node sets whose σ right-hand sides a large fit keeps (GraphFit._sigma_rows_of)
#: A warm fit whose Gauss-Newton step still to take is longer than this, squared, in its own
#: posterior s.d. (the Newton decrement on the last matrix factorised, :meth:`GraphFit._descend`;
#: 3: the 3σ of the error bound) has not followed the shape, and the basin its chain holds may not
#: be the one a fresh start finds: the linear start is then descended as well, as a cold fit
#: descends it, and the lower objective answers (how: :data:`WARM_LINEAR`; the chain keeps its
#: basin test's yardstick).  Fingertips releasing a 5×5 membrane (``membrane:fingers=2``), each
#: scan warm from the one before: the warm graphs lagged into another basin (turning χ² 0.2-0.9
#: against a cold fit's 0.003-0.03, objectives 37-230 above the linear start's), frames beyond
#: 3σ + 0.05 mm up to 1.31 times; with the linear start beside the warm one where the step left
#: is longer than 3 s.d., over 6 noise seeds: every scan 56 of 2400 frames → 8 (worst 1.34 →
#: 1.14), at 10 Hz 8 of 480 → 0 (1.10 → 0.60).  The linear start's descent costs about four warm
#: fits (5×5: 2.7 ms, 8×8: 6.4); on sheets above :data:`MAX_CELLS`, where the graph answers only
#: as a rescue, it would cost 19 ms (12×12) and changed nothing measured, so they keep the warm
#: answer (and its basin test).
WARM_UNSETTLED = 9.0
WARM_LINEAR = "warm: linear start"
#: Steps more for a warm fit whose first :data:`_WARM_STEPS` leave the gauges misread (not
#: accepted) and whose frame's linear start, descended as a cold fit descends it, is not
#: accepted either, on sheets up to :data:`MAX_CELLS` cells: with them as many as a cold fit
#: takes (:meth:`GraphFit.fit_warm`).  skinmapd at
#: 10 Hz (a warm start five scans old), 5×5, over the emulated device's noise seeds: frames
#: answered while their cold fit was deferred (DEGRADED, σ widened by the gauges' resolution)
#: on the palm gesture 77 → 20 of 480, on two fingertips releasing a membrane 145 → 25 (mean node
#: error 0.089 → 0.047 mm), none beyond 3σ + 0.05 mm before or after (docs/reconstruction.md).
WARM_MORE_STEPS = _MAX_STEPS - _WARM_STEPS
#: A cold fit whose best accepted objective is above this many per unit descends the linear
#: start once more, first :data:`_DAMPED_STEPS` steps with the stretch residuals' own
#: curvature in the matrix (damped, as the warm steps), then as a cold fit; the lower objective
#: answers.  Two bumps at a 5×5 sheet's corner: of 12 noise draws, 6 had both starts end in
#: another basin (objective 2.9-3.2 a unit, a fold of the corner beyond the last gauges) where
#: the others found 1.8-1.9; the damped descent reaches 1.8-2.4 on all 12 (docs/reconstruction.md,
#: *Two bumps at the corner*).  Where no graph is accepted it is not tried: there the general
#: model answers, and on the bench's kinematic classes it was 28 % of the cold fits (sheets that
#: are not graphs) with none of its answers taken.
DAMPED_OBJECTIVE = 2.4
#: ... and answers only where its objective is below this share of the best accepted one: on the
#: sharpest bumps (5 mm, FWHM 15 mm, whose misfit puts them above DAMPED_OBJECTIVE) it reaches
#: objectives within 1 % of the two starts' in a nearby configuration that was up to 0.14 mm off
#: noise-free where theirs was 0.08 (the two bumps' other basin is 20-40 % above).
DAMPED_RATIO = 0.9
DAMPED_LINEAR = "damped linear"
_DAMPED_STEPS = 10


class _SigmaRows(NamedTuple):
    """The right-hand sides of a large fit's node σ for one set of nodes and centre node
    (:meth:`GraphFit._band_sigma_squares`): the frame's three forms (the centre node's height
    and the best-fit plane's two slopes), then the nodes' heights in the order of their first
    coefficient, as the non-zero entries of the band solver's blocked layout."""

    order: np.ndarray  # (P,) the nodes (positions in the set asked for) in that order
    starts: np.ndarray  # (3 + P,) each right-hand side's first non-zero coefficient (the forms': 0)
    at: np.ndarray  # flat positions of their non-zero entries in the blocked layout
    values: np.ndarray  # their values
    weights: np.ndarray  # (P, 3) Fortran: s_p = e_p − weights[p] · forms, weights[p] = (1, u_p, v_p)


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
    objective: float  # the minimised objective (data misfit and prior), to rank cold starts
    agreement: float = math.nan  # median distance to the general model in combined s.d. (cold frames)


def disagreement(graph_pos: np.ndarray, general_pos: np.ndarray, tolerance: np.ndarray) -> float:
    """The median over the fine nodes of the distance between two surfaces (fine-grid positions
    (nf, mf, 3) each), the first moved by the best rigid motion onto the second, in units of
    ``tolerance`` (nf, mf), the combined one-s.d. uncertainty; nodes of zero tolerance (the
    sensor frame's origin, where both are pinned) are left out.  The median: the general model
    may be off around a feature it cannot resolve, and the noise-propagated s.d. of either
    surface is a sensor-frame estimate that is loose near the centre, so agreement is asked of
    the sheet as a whole (half of its nodes), not of every node."""
    p = np.asarray(graph_pos, dtype=float).reshape(-1, 3)
    q = np.asarray(general_pos, dtype=float).reshape(-1, 3)
    tol = np.asarray(tolerance, dtype=float).reshape(-1)
    dist = aligned_distances(p, q)
    keep = tol > 0.0
    if not keep.any() or not np.isfinite(dist).all():
        return math.inf
    return float(np.median(dist[keep] / tol[keep]))


def knots_per_pitch(n: int, m: int) -> int:
    """The graph's knots a pitch on an N×M sheet (:data:`KNOTS_PER_PITCH`, 2 above
    :data:`COARSE_KNOTS_CELLS`)."""
    return KNOTS_PER_PITCH if n * m <= COARSE_KNOTS_CELLS else 2


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


def _projection(design: np.ndarray, gram3: np.ndarray) -> np.ndarray:
    """The least-squares projection of values at the fine nodes onto the 1D basis (``design``:
    (nodes, B-splines)).  Where the nodes are fewer than the B-splines (above 8×8 the fine grid
    is coarser than the knots: 25 nodes for 39 B-splines a side on 12×12) the pseudo-inverse
    leaves the B-splines between the nodes free, and a smooth sheet came out rippled between
    them (a twisted quadric's own heights implied three times the stretch its gauges read, and
    the general model's answer as a start was screened out); there a small penalty on the third
    derivative (``gram3``) fills them smoothly."""
    if design.shape[0] >= design.shape[1]:
        return np.linalg.pinv(design)
    normal = design.T @ design
    return np.linalg.solve(normal + 1e-6 * np.trace(normal) / np.trace(gram3) * gram3, design.T)


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
        #: the share of the stretch residuals' curvature the uncertainty takes (_SIGMA_CURVATURE)
        self.sigma_curvature = _SIGMA_CURVATURE if n * m <= _SIGMA_CURVATURE_CELLS else (0.0, 0.0)
        per = knots_per_pitch(n, m)
        ku, self.nbu = _basis_1d(-0.5 * m * pitch, 0.5 * m * pitch, per * m)
        kv, self.nbv = _basis_1d(-0.5 * n * pitch, 0.5 * n * pitch, per * n)
        nbu, nbv = self.nbu, self.nbv
        self.size = nc = nbu * nbv
        uc, vc = cell_axes(n, m, pitch)
        # a twist τ stretches a row gauge by τ²v²/2 and a column gauge by τ²u²/2: their mean over
        # the units is τ²/2 times this (the mean of v² and u² over the cells' centres)
        self._mean_cross2 = 0.5 * (float(np.mean(vc * vc)) + float(np.mean(uc * uc)))
        xq, wq = np.polynomial.legendre.leggauss(_QUADRATURE[0])
        panels = _QUADRATURE[1]
        s = np.concatenate([((p + (xq + 1.0) / 2.0) / panels - 0.5) * gauge_length for p in range(panels)])
        self.wq = np.concatenate([wq / (2.0 * panels)] * panels)  # weights of a mean over the gauge
        q = len(s)
        # Quadrature points of every gauge, (2, n, m, q): u gauges along u, v gauges along v.
        pu: np.ndarray = np.empty((2, n, m, q))
        pv: np.ndarray = np.empty((2, n, m, q))
        pu[0] = uc[None, :, None] + s
        pv[0] = vc[:, None, None]
        pu[1] = uc[None, :, None]
        pv[1] = vc[:, None, None] + s
        pu, pv = pu.reshape(-1), pv.reshape(-1)
        bu = [_design(ku, nbu, pu, d) for d in range(3)]
        bv = [_design(kv, nbv, pv, d) for d in range(3)]

        g = 2 * n * m
        half = g // 2
        # Each gauge touches a few dozen coefficients: keep them as a local dense block, built
        # gauge by gauge (a dense (points, coefficients) design is 170 MB on 16×16).
        # along (a), across (b), second derivative along (aa): u gauges then v gauges
        touched = []
        blocks = []
        for k in range(g):
            sl = slice(k * q, (k + 1) * q)
            cu = np.flatnonzero(np.abs(bu[0][sl]).sum(0) + np.abs(bu[1][sl]).sum(0) + np.abs(bu[2][sl]).sum(0))
            cv = np.flatnonzero(np.abs(bv[0][sl]).sum(0) + np.abs(bv[1][sl]).sum(0) + np.abs(bv[2][sl]).sum(0))

            def local(a: int, b: int) -> np.ndarray:  # ∂u^a ∂v^b w at the gauge's points, (q, |cv|·|cu|)
                return (bv[b][sl][:, cv, None] * bu[a][sl][:, None, cu]).reshape(q, -1)

            cols = (cv[:, None] * nbu + cu[None, :]).ravel()
            if k < half:
                da, db, daa = local(1, 0), local(0, 1), local(2, 0)
            else:
                da, db, daa = local(0, 1), local(1, 0), local(0, 2)
            nz = np.flatnonzero(np.abs(np.concatenate([da, db, daa])).sum(0))
            order = np.argsort(cols[nz], kind="stable")
            keep = nz[order]
            touched.append(cols[keep])
            blocks.append((da[:, keep], db[:, keep], daa[:, keep]))
        width = max(len(t) for t in touched)
        self.idx = np.zeros((g, width), dtype=np.int64)
        self.da, self.db, self.daa = (np.zeros((g, q, width)) for _ in range(3))
        for k, t in enumerate(touched):
            self.idx[k, : len(t)] = t
            self.idx[k, len(t):] = t[0]  # padding: weight 0 on a real index
            self.da[k, :, : len(t)], self.db[k, :, : len(t)], self.daa[k, :, : len(t)] = blocks[k]
        self.bandwidth = int(max((t.max() - t.min()) for t in touched))
        # Prior ∫∫|∇³w|² as Kronecker products of 1D Gram matrices, plus a ridge and a pin of
        # the centre coefficient (the height offset is seen by no datum).
        gu = [_gram(ku, nbu, d) for d in range(4)]
        gv = [_gram(kv, nbv, d) for d in range(4)]
        prior = _PRIOR_SCALE * sum((wt * scipy.sparse.kron(gv[b], gu[a]) for a, b, wt in _PRIOR_WEIGHTS),
                                   scipy.sparse.csr_array((nc, nc)))
        self.pin = (nbv // 2) * nbu + nbu // 2
        ridge = np.full(nc, _RIDGE)
        ridge[self.pin] += 1.0
        # sparse: a dense prior is 54 MB on 16×16 (2601 unknowns), and its product with the
        # coefficients cost 5 ms a call there, more than the rest of an evaluation
        self._prior_sparse = scipy.sparse.csr_array(prior + scipy.sparse.diags_array(ridge))
        coo = self._prior_sparse.tocoo()
        self.bandwidth = int(max(self.bandwidth, np.max(np.abs(coo.row - coo.col))))
        bw = self.bandwidth
        self.prior_band = np.zeros((bw + 1, nc))
        lower = coo.row >= coo.col
        self.prior_band[coo.row[lower] - coo.col[lower], coo.col[lower]] = coo.data[lower]
        off, col = np.nonzero(np.ones((bw + 1, nc), dtype=bool))
        self._band_index = (off[col + off < nc], col[col + off < nc])  # the band's entries, for _dense
        # the same entries as flat indices into the band and into a dense (nc, nc) Fortran array's
        # lower triangle: a band factor expands into a dense one in one gather
        band_d, band_j = self._band_index
        self._band_flat = band_d * nc + band_j
        self._lower_flat = band_j * nc + (band_j + band_d)
        self._lower_buffer: np.ndarray | None = None
        # the sensor frame's linear forms by centre node (_frame_height_rows)
        self._frame_forms: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        # the large fits' node σ right-hand sides by (nodes, centre node, band) (_sigma_rows_of): they
        # depend on the geometry and the nodes alone, and skinmapd asks for the same nodes every frame
        self._sigma_rows: OrderedDict[tuple[bytes, tuple[int, int], int], _SigmaRows] = OrderedDict()
        # Linear start: the turning data alone in the small-slope model, Θ/g ≈ −mean(w_aa).
        self._j0 = -np.einsum("q,gql->gl", self.wq, self.daa)
        self._no_band = np.zeros((1, 1))
        self._no_jacobian = np.zeros((0, 0))
        self._starts: OrderedDict[bytes, np.ndarray] = OrderedDict()
        # Fine-grid evaluation w, w_u, w_v (separable) and the mean twist over the inner region.
        self._fine_u, self._fine_v = np.asarray(fine_u, float), np.asarray(fine_v, float)
        self._fu = [_design(ku, nbu, np.asarray(fine_u, float), d) for d in range(2)]
        self._fv = [_design(kv, nbv, np.asarray(fine_v, float), d) for d in range(2)]
        self._twist = np.kron(self._fv[1][inner[0]].mean(0), self._fu[1][inner[1]].mean(0))
        # Least-squares projection of fine-grid heights onto the basis (separable).
        self._project_u = _projection(self._fu[0], gu[3])
        self._project_v = _projection(self._fv[0], gv[3])
        self._fine_uv = np.stack(np.broadcast_arrays(self._fine_u[None, :], self._fine_v[:, None]), axis=-1).reshape(-1, 2)

    # ---------------------------------------------------------------- per frame
    def _start(self, turning: np.ndarray, valid: np.ndarray, sigma_t: float) -> np.ndarray:
        """The linear start: min Σ ((J₀c)_k − Θ_k)²/σ_Θ² + cᵀPc over the valid gauges, J₀ the
        small-slope turning rows (banded normal equations, factorised once per mask)."""
        key = valid.tobytes()
        factor = self._starts.get(key)
        w = valid.astype(float) / sigma_t
        if factor is None:
            rows = self._j0 * w[:, None]
            i = np.broadcast_to(self.idx[:, :, None], rows.shape + (rows.shape[1],))
            j = np.broadcast_to(self.idx[:, None, :], i.shape)
            lower = i >= j
            band = self.prior_band.copy()
            np.add.at(band, ((i - j)[lower], j[lower]), (rows[:, :, None] * rows[:, None, :])[lower])
            f, info = _pbtrf(band, lower=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"the graph fit's linear start is not definite (LAPACK info {info})")
            factor = f
            self._starts[key] = factor
            if len(self._starts) > 16:
                self._starts.popitem(last=False)
        rhs = np.bincount(self.idx.ravel(), weights=(self._j0 * (w * w * np.where(valid, turning, 0.0))[:, None]).ravel(),
                          minlength=self.size)
        return _pbtrs(factor, rhs, lower=1)[0]

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
        return 0.5 * float(rt @ rt + rs @ rs + c @ (self._prior_sparse @ c)), rt, rs

    def _evaluate(self, c, turning, stretch, w_t, w_s, with_matrix: bool, curvature=(0.0, 0.0)):
        """At c: the objective, its gradient Jᵀr + Pc, the normalised residuals (turning then
        stretch) and, ``with_matrix``, the factorised Gauss-Newton matrix JᵀJ + P (plus the
        stretch curvature, see kernels.graph_normal_equations; None when not positive definite)."""
        pc = self._prior_sparse @ c
        rhs = pc.copy()
        factor = None
        g = len(turning)
        if self._compiled is not None:
            band = self.prior_band.copy() if with_matrix else self._no_band
            res = np.empty(2 * g)
            self._compiled.graph_normal_equations(c, self.idx, self.da, self.db, self.daa, self.wq, turning,
                                                  stretch, w_t, w_s, band, rhs, with_matrix,
                                                  np.asarray(curvature, dtype=float), res, self._no_jacobian,
                                                  self._no_jacobian)
            if with_matrix:
                f, info = _pbtrf(band, lower=1)
                factor = ("band", f) if info == 0 else None
            return 0.5 * float(res @ res + c @ pc), rhs, res, factor
        j, res = self._numpy_jacobian(c, turning, stretch, w_t, w_s)
        rhs += j.T @ res
        if with_matrix:
            try:
                factor = ("dense", scipy.linalg.cho_factor(self._numpy_matrix(c, j, res[g:], w_s, curvature),
                                                           lower=True, check_finite=False))
            except (np.linalg.LinAlgError, ValueError):
                factor = None
        return 0.5 * float(res @ res + c @ pc), rhs, res, factor

    def _numpy_jacobian(self, c, turning, stretch, w_t, w_s) -> tuple[np.ndarray, np.ndarray]:
        """Numpy reference: the normalised Jacobian (2G, coefficients), dense, and residuals."""
        tm, sm, jt, js = self._model(c, True)
        g = len(turning)
        j = np.zeros((2 * g, self.size))
        rows = np.repeat(np.arange(g), self.idx.shape[1])
        np.add.at(j, (rows, self.idx.ravel()), (jt * w_t[:, None]).ravel())
        np.add.at(j, (rows + g, self.idx.ravel()), (js * w_s[:, None]).ravel())
        return j, np.concatenate([(tm - turning) * w_t, (sm - stretch) * w_s])

    def _numpy_matrix(self, c, j, rs, w_s, curvature) -> np.ndarray:
        """Numpy reference: JᵀJ + P plus the stretch residuals' own curvature (see
        kernels.graph_normal_equations), dense."""
        h = j.T @ j + self._prior_sparse.toarray()
        a = np.einsum("gql,gl->gq", self.da, c[self.idx])
        cr = np.where(rs > 0.0, curvature[0] * rs, -curvature[1] * rs)
        cw = (cr * w_s)[:, None] * self.wq / (1.0 + a * a) ** 1.5
        np.add.at(h, (self.idx[:, :, None], self.idx[:, None, :]), np.einsum("gq,gqk,gql->gkl", cw, self.da, self.da))
        return h

    def _dense(self, band: np.ndarray) -> np.ndarray:
        """The symmetric matrix of lower band storage ``band`` (band[d, j] = A[j + d, j])."""
        d, j = self._band_index
        a = np.zeros((self.size, self.size))
        a[j + d, j] = band[d, j]
        a[j, j + d] = band[d, j]
        return a

    def _dense_lower(self, band: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Lower band storage ``band`` as the lower triangle of a dense Fortran-ordered matrix
        (one kept buffer: the entries off the band stay zero; valid until the next call), or
        in ``out`` (zero off the band)."""
        if out is None:
            if self._lower_buffer is None:
                self._lower_buffer = np.zeros((self.size, self.size), order="F")
            out = self._lower_buffer
        out.reshape(-1, order="F")[self._lower_flat] = band.reshape(-1)[self._band_flat]
        return out

    @staticmethod
    def _solve(factor, rhs: np.ndarray) -> np.ndarray:
        kind, f = factor
        if kind == "band":
            return _pbtrs(f, rhs, lower=1)[0]
        return scipy.linalg.cho_solve(f, rhs, check_finite=False)

    def _descend(self, c, turning, stretch, w_t, w_s, n_valid: int, max_steps: int, curvature=(0.0, 0.0),
                 reuse: float = _REUSE_RATIO, curvature_near: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float, float]:
        """Gauss-Newton with a backtracking line search.  The factorised matrix is reused for the
        next step while the steps keep shrinking (by at least the factor ``reuse``: it changes
        little near the optimum) and refreshed otherwise or when a step with it fails.  Given
        ``curvature_near``, once the objective is below that many times ``n_valid`` the matrix also takes the
        stretch residuals' own curvature where it adds to JᵀJ (:data:`_NEAR_CURVATURE`).  Returns
        (c, rt, rs, steps, the objective, the step still to take): the last as gᵀH⁻¹g, the
        gradient at c on the last matrix factorised (the Newton decrement: the step's squared
        length in the fit's posterior s.d.; inf if the matrix was not definite)."""
        g = len(turning)
        f0, grad, res, factor = self._evaluate(c, turning, stretch, w_t, w_s, True, curvature)
        fresh, last = True, math.inf
        steps = 0
        tol = _TOLERANCE * n_valid
        curved = curvature_near is None  # (None: never switch)
        while steps < max_steps and factor is not None:
            dc = self._solve(factor, grad)
            t = 1.0
            f1, grad1, res1, _ = self._evaluate(c - dc, turning, stretch, w_t, w_s, False)
            if not f1 < f0:
                if not fresh:  # the reused matrix failed: linearise here again
                    f0, grad, res, factor = self._evaluate(c, turning, stretch, w_t, w_s, True, curvature)
                    fresh = True
                    continue
                while not f1 < f0 and t > 1e-3:
                    t *= 0.5
                    f1, grad1, res1, _ = self._evaluate(c - t * dc, turning, stretch, w_t, w_s, False)
                if not f1 < f0:
                    break
            c = c - t * dc
            grad, res = grad1, res1
            steps += 1
            drop, f0 = f0 - f1, f1
            if drop <= tol:
                break
            if steps >= _GIVE_UP_AFTER and float(res[g:] @ res[g:]) / n_valid > _GIVE_UP_CHI2:
                break
            if not curved and steps < max_steps and f0 < cast(float, curvature_near) * n_valid:
                curved = True
                f0, grad, res, factor = self._evaluate(c, turning, stretch, w_t, w_s, True, _NEAR_CURVATURE)
                if factor is None:  # (a positive term added: only rounding fails it) Gauss-Newton's stays
                    f0, grad, res, factor = self._evaluate(c, turning, stretch, w_t, w_s, True, curvature)
                else:
                    curvature = _NEAR_CURVATURE
                fresh = True
            elif steps < max_steps and (t < 1.0 or drop > reuse * last):
                f0, grad, res, factor = self._evaluate(c, turning, stretch, w_t, w_s, True, curvature)
                fresh = True
            else:
                fresh = False
            last = drop
        left = math.inf if factor is None else float(grad @ self._solve(factor, grad))
        return c, res[:g], res[g:], steps, f0, left

    def prepare(self, turning: np.ndarray, stretch: np.ndarray, valid: np.ndarray, sigma_t: float,
                sigma_s: float) -> tuple:
        """The unit data (2, N, M) (``engine.unit_data``) as the fits take them, with noise s.d.
        ``sigma_t`` (turning per length, 1/mm) and ``sigma_s`` (stretch)."""
        turning = np.ascontiguousarray(turning, dtype=float).ravel()
        stretch = np.ascontiguousarray(stretch, dtype=float).ravel()
        valid = np.asarray(valid, dtype=bool).ravel()
        return (np.where(valid, turning, 0.0), np.where(valid, stretch, 1.0), valid / sigma_t, valid / sigma_s,
                valid, max(int(valid.sum()), 1), float(sigma_t), float(sigma_s))

    def fit_warm(self, data: tuple, start: tuple, twist_sign: float | None = None,
                 linear: Callable[[], tuple[list, list[str]]] | None = None,
                 climbed_over: float = math.inf, refused_over: float = math.inf) -> GraphResult:
        """A few Gauss-Newton steps from the previous frame's accepted graph: ``start`` =
        (its coefficients, those of the graph before it or None).  For a shape in motion the
        linear prediction from the two is tried first.  Where the steps stop with more than
        :data:`WARM_UNSETTLED` still to take, the linear start is descended too (sheets of up to
        :data:`MAX_CELLS` cells) and the lower objective answers; where they stop with the gauges
        misread (not accepted), the linear start descended so answers if it is accepted, else
        :data:`WARM_MORE_STEPS` steps more from where the warm steps stopped.  The linear start is
        also descended where the warm objective lies in (``climbed_over``, ``refused_over``]: it
        has climbed far above its chain's lowest while its basin test would still pass it
        (reconstructor.WARM_CLIMB_RATIO).  ``linear``: gives :meth:`cold_starts` of ``data`` (a
        caller that needs it too computes it once)."""
        turning, stretch, w_t, w_s, _, n_valid, sigma_t, _ = data
        if np.shape(start[0]) != (self.size,):
            raise ValueError(f"a warm start needs {self.size} coefficients, got shape {np.shape(start[0])}")
        c = np.array(start[0], dtype=float)
        if start[1] is not None:
            # a shape in motion: the linear prediction from the last two graphs, if it fits better
            predicted = 2.0 * c - start[1]
            if (self._objective(predicted, turning, stretch, w_t, w_s)[0]
                    < self._objective(c, turning, stretch, w_t, w_s)[0]):
                c = predicted
        out = self._descend(c, turning, stretch, w_t, w_s, n_valid, _WARM_STEPS, _WARM_CURVATURE, _WARM_REUSE)
        warm = self._judge(self._result(*out[:5], n_valid, sigma_t, "warm"), twist_sign)
        cells_ok = self.n * self.m <= MAX_CELLS
        if not warm.accepted and cells_ok and math.isfinite(out[4]):
            refit = self._misread_refit(data, out, twist_sign, linear)
            return warm if refit is None else refit
        climbed = climbed_over < warm.objective <= refused_over
        if not warm.accepted or not cells_ok or (out[5] <= WARM_UNSETTLED and not climbed):
            return warm
        # the warm steps stopped far from their optimum: the shape has moved faster than they
        # follow, and the chain may hold a basin a fresh start would leave (the linear start,
        # as a cold fit descends from it; the lower objective answers)
        fresh = self._linear_descent(data, twist_sign, linear)
        if fresh is None:
            return warm
        return fresh if fresh.accepted and fresh.objective < warm.objective else warm

    def _misread_refit(self, data: tuple, out: tuple, twist_sign: float | None,
                        linear: Callable[[], tuple[list, list[str]]] | None) -> GraphResult | None:
        """A graph for a frame whose warm steps (``out``: :meth:`_descend`'s) stopped with the
        gauges misread, or None: the shape moved further than they follow (skinmapd at 10 Hz
        starts from a graph five scans old).  A chain that lags so far may hold another basin:
        the frame's linear start is descended as a cold fit descends it, and where that is not
        accepted the warm descent goes on from where it stopped, as far as a cold fit's would
        (:data:`WARM_MORE_STEPS`)."""
        fresh = self._linear_descent(data, twist_sign, linear)
        if fresh is not None and fresh.accepted:
            return fresh
        turning, stretch, w_t, w_s, _, n_valid, sigma_t, _ = data
        more = self._descend(out[0], turning, stretch, w_t, w_s, n_valid, WARM_MORE_STEPS, _WARM_CURVATURE,
                             _WARM_REUSE)
        longer = self._judge(self._result(*more[:5], n_valid, sigma_t, "warm"), twist_sign)
        return longer._replace(iterations=out[3] + more[3]) if longer.accepted else None

    def _linear_descent(self, data: tuple, twist_sign: float | None,
                        linear: Callable[[], tuple[list, list[str]]] | None) -> GraphResult | None:
        """The frame's linear start descended as a cold fit descends it (how: :data:`WARM_LINEAR`);
        None where its screen rules it out."""
        turning, stretch, w_t, w_s, _, n_valid, sigma_t, _ = data
        starts, reasons = self.cold_starts(data) if linear is None else linear()
        if reasons[0]:
            return None
        return self._judge(self._result(*self._descend(starts[0][1], turning, stretch, w_t, w_s, n_valid, _MAX_STEPS,
                                                       curvature=_COLD_CURVATURE, curvature_near=_CURVATURE_NEAR)[:5],
                                        n_valid, sigma_t, WARM_LINEAR), twist_sign)

    def warm_screen(self, c: np.ndarray, data: tuple, linear: tuple[list, list[str]] | None = None
                    ) -> tuple[str, tuple[list, list[str]]]:
        """Why the warm graph ``c`` cannot stand ('' where it may), and the cold fit's linear start
        (:meth:`cold_starts` without the general model's surface: a refused frame's cold fit
        takes it).  Where the screen of the turning's linear start finds the gauges stretched with
        slopes too small to stretch them (``stretch above: small slopes``), only a twist, which
        the turning does not see, could make the sheet a graph; a warm graph whose own twist
        stretches it by less than the screen's floor explains that stretch with structure
        between the gauges instead.  On a membrane pulled flat by its frame as two fingertips
        released it (8×8, each frame warm from the one before) the warm graphs read the gauges
        within the noise, twist 1-4·10⁻⁵ /mm, while their nodes went 0.05 → 0.25 mm off with
        σ 0.06 (6.9 times 3σ + 0.05 mm); a cold fit of the same frames is screened out.
        ``linear``: :meth:`cold_starts` of ``data``, if already known."""
        if linear is None:
            linear = self.cold_starts(data)
        reason = linear[1][0]
        if reason != f"{_MORE_STRETCH} small slopes":
            return "", linear
        sigma_s = float(data[7])
        tau = float(self._twist @ c)
        twist_stretch = 0.5 * tau * tau * self._mean_cross2
        if twist_stretch >= _SCREEN_SIGMAS * sigma_s:
            return "", linear
        return (f"{reason}, and the graph's own twist stretches it by {twist_stretch / sigma_s:.2g} noise s.d.",
                linear)

    def cold_starts(self, data: tuple, general: np.ndarray | None = None,
                    linear: tuple[list, list[str]] | None = None) -> tuple[list, list[str]]:
        """The cold fit's starts, [(name, coefficients)], and why each cannot be a graph ('' where
        it may be; :meth:`_screen`): cheap, so that a caller can tell before paying for the fit
        whether there is one to do (all reasons given: none).  ``linear``: this method's answer
        without ``general`` (the linear start alone), if already known."""
        turning, stretch, _, _, valid, _, sigma_t, sigma_s = data
        if linear is None:
            starts = [("linear", self._start(turning, valid, sigma_t))]
            reasons = [self._screen(starts[0][1], stretch, valid, sigma_s)]
        else:
            starts, reasons = list(linear[0][:1]), list(linear[1][:1])
        if general is not None and _twist_may_answer(reasons[0]):
            c = self.coeffs_from_positions(general)
            if np.isfinite(c).all():
                starts.append(("general", c))
                reasons.append(self._screen(c, stretch, valid, sigma_s))
        return starts, reasons

    @staticmethod
    def ruled_out(linear: tuple[list, list[str]]) -> GraphResult | None:
        """The cold fit's answer where its screen rules out every graph from the linear start
        alone (:meth:`cold_starts` without the general model's surface), as :meth:`fit_cold`
        gives it; None where a fit may be a graph.  The general model's surface, the second
        start, is then not needed for the fit."""
        starts, reasons = linear
        return None if _twist_may_answer(reasons[0]) else _rejected(starts, reasons[0])

    def fit_cold(self, data: tuple, general: np.ndarray | None = None, twist_sign: float | None = None,
                 agree=None, prepared: tuple[list, list[str]] | None = None) -> GraphResult:
        """Fit from the linear fit of the turning data and, given ``general`` (the general
        model's fine-grid positions (nf, mf, 3), any rigid frame), from that surface as well;
        the accepted fit with the lower objective wins.  The two starts fail differently: the
        linear one has no twist (steep twisted quadrics can end in a wrong basin), the general
        model's smooths sub-gauge features (sharp bumps can end in a wrong basin).  ``agree``
        (coefficients → the median distance to the general model in combined s.d., see
        :data:`AGREE_SIGMAS`): an accepted fit must also pass it, in the order of the
        objective.  ``prepared``: :meth:`cold_starts` of these arguments, if already known."""
        turning, stretch, w_t, w_s, valid, n_valid, sigma_t, sigma_s = data
        starts, reasons = self.cold_starts(data, general) if prepared is None else prepared
        if all(reasons):
            return _rejected(starts, reasons[-1])
        results = [self._judge(self._result(*self._descend(c, turning, stretch, w_t, w_s, n_valid, _MAX_STEPS,
                                                           curvature=_COLD_CURVATURE, curvature_near=_CURVATURE_NEAR)[:5],
                                            n_valid, sigma_t, how), twist_sign)
                   for (how, c), why in zip(starts, reasons) if not why]
        best = min((r.objective for r in results if r.accepted), default=math.inf)
        if not reasons[0] and DAMPED_OBJECTIVE * n_valid < best < math.inf and self.n * self.m <= MAX_CELLS:
            damped = self._damped_descent(data, starts[0][1], twist_sign)
            if damped.objective < DAMPED_RATIO * best:  # (another basin, not the same one's noise)
                results.append(damped)
        if agree is not None:
            checked = []
            for r in sorted(results, key=lambda r: r.objective):
                if r.accepted:
                    ratio = float(agree(r.coeffs))
                    r = r._replace(agreement=ratio)
                    if not ratio <= AGREE_SIGMAS:
                        r = r._replace(accepted=False, how=f"{r.how}: not the general model's surface (median "
                                                           f"{ratio:.3g} s.d. away)")
                    else:
                        return r
                checked.append(r)
            results = checked
        accepted = [r for r in results if r.accepted]
        if accepted:
            return min(accepted, key=lambda r: r.objective)
        closest = min(results, key=lambda r: r.chi2_stretch)
        screened = [f"{how}: {why}" for (how, _), why in zip(starts, reasons) if why]
        return closest._replace(how="; ".join([r.how for r in results] + screened))

    def _damped_descent(self, data: tuple, c: np.ndarray, twist_sign: float | None) -> GraphResult:
        """The start ``c`` descended :data:`_DAMPED_STEPS` steps with the stretch residuals' own
        curvature in the matrix, then as a cold fit (how: :data:`DAMPED_LINEAR`)."""
        turning, stretch, w_t, w_s, _, n_valid, sigma_t, _ = data
        first = self._descend(c, turning, stretch, w_t, w_s, n_valid, _DAMPED_STEPS, _WARM_CURVATURE, _WARM_REUSE)
        out = self._descend(first[0], turning, stretch, w_t, w_s, n_valid, _MAX_STEPS, curvature=_COLD_CURVATURE,
                            curvature_near=_CURVATURE_NEAR)
        return self._judge(self._result(out[0], out[1], out[2], first[3] + out[3], out[4], n_valid, sigma_t,
                                        DAMPED_LINEAR), twist_sign)

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
            if measured.size and measured.mean() >= _SCREEN_SIGMAS * sigma_s:
                return f"{_MORE_STRETCH} small slopes"  # stretch without slopes: twist, perhaps
            return "small slopes"
        if measured.min() < -_SCREEN_SHORT * sigma_s:
            return "a gauge shortens"
        ratio = measured.sum() / implied.sum()
        if ratio < _SCREEN_RATIO[0]:
            return f"stretch {ratio:.2f} x the graph's"
        if ratio > _SCREEN_RATIO[1]:
            return f"{_MORE_STRETCH} {ratio:.2f} x the graph's"
        return ""

    def _result(self, c, rt, rs, steps: int, objective: float, n_valid: int, sigma_t: float,
                how: str) -> GraphResult:
        if rt is None:
            return GraphResult(False, c, math.inf, math.inf, 0, 0.0, math.inf, how, math.inf)
        chi_t, chi_s = float(rt @ rt) / n_valid, float(rs @ rs) / n_valid
        accepted = bool(chi_t <= ACCEPT_CHI2 and chi_s <= ACCEPT_CHI2 and np.isfinite(c).all())
        return GraphResult(accepted, c, chi_t, chi_s, steps, float(self._twist @ c), math.sqrt(chi_t) * sigma_t,
                           how if accepted else f"{how}: misfit chi2 {chi_t:.3g} (turning), {chi_s:.3g} (stretch)",
                           float(objective))

    def fine_height_sigma(self, c: np.ndarray, data: tuple, noise_ratio: float, centre: tuple[int, int]) -> np.ndarray:
        """One-s.d. height error (nf, mf) mm of every fine node in the sensor frame (the height
        over the best-fit plane from the centre node ``centre``, to_sensor_frame to first
        order), by linear propagation through the Gauss-Newton
        normal equations at the solution c: δc = −H⁻¹Jᵀδr with H = JᵀJ + P, the residuals δr
        normalised by the fit's noise and scattering with s.d. ``noise_ratio`` (the actual noise
        over the fit's).  The prior's pull is part of H, so where the data say little (between
        gauges, beyond the outer ones) the fit follows the prior and the scatter stays small."""
        turning, stretch, w_t, w_s = data[:4]
        g = len(turning)
        resp = None
        if self._compiled is not None:  # H in band form and J dense from one kernel call
            band = self.prior_band.copy()
            j = np.zeros((2 * g, self.size))
            self._compiled.graph_normal_equations(c, self.idx, self.da, self.db, self.daa, self.wq, turning, stretch,
                                                  w_t, w_s, band, np.zeros(self.size), True,
                                                  np.asarray(self.sigma_curvature, dtype=float), np.empty(2 * g), j,
                                                  self._no_jacobian)
            # H = L·Lᵀ factorised in band form (cheap), then the many right-hand sides through
            # the dense triangle as level-3 BLAS (a band solve runs them one at a time, 2x slower)
            f, info = _pbtrf(band, lower=1)
            if info == 0:
                lower = self._dense_lower(f)
                y, info = _trtrs(lower, j.T, lower=1)  # j.T is Fortran-ordered: no copy
                if info == 0:
                    resp, info = _trtrs(lower, y, lower=1, trans=1, overwrite_b=1)
                resp = resp if info == 0 else None
            if resp is None:
                h = self._dense(band)
        else:
            j, res = self._numpy_jacobian(c, turning, stretch, w_t, w_s)
            h = self._numpy_matrix(c, j, res[g:], w_s, self.sigma_curvature)
        if resp is None:
            try:
                resp = scipy.linalg.cho_solve(scipy.linalg.cho_factor(h, lower=True, check_finite=False), j.T,
                                              check_finite=False)
            except np.linalg.LinAlgError:
                resp = np.linalg.lstsq(h, j.T, rcond=None)[0]
        nf, mf = len(self._fine_v), len(self._fine_u)
        k = resp.shape[1]
        # fine heights per datum: Fv · A_k · Fuᵀ, all data at once, as (nf, k, mf) from two
        # products (the data's coefficients A_k are the rows of respᵀ)
        a_t = np.ascontiguousarray(resp.T).reshape(k * self.nbv, self.nbu)
        t = (a_t @ self._fu[0].T).reshape(k, self.nbv, mf).transpose(1, 0, 2).reshape(self.nbv, k * mf)
        w = (self._fv[0] @ t).reshape(nf, k, mf)
        a0, b0 = centre
        # the sensor frame: height over the best-fit plane, from the centre node
        slope_u, slope_v = plane_slopes(self._fine_u, self._fine_v, w.transpose(0, 2, 1))
        w -= w[a0, :, b0].copy()[None, :, None]
        w -= self._fine_u[None, None, :] * slope_u[None, :, None]
        w -= self._fine_v[:, None, None] * slope_v[None, :, None]
        return noise_ratio * np.sqrt(np.einsum("ikj,ikj->ij", w, w))

    def height_sigma_at(self, c: np.ndarray, data: tuple, noise_ratio: float,
                        centre: tuple[int, int]) -> Callable[[np.ndarray], np.ndarray]:
        """:meth:`fine_height_sigma` at chosen fine nodes only: a function of flat node indices
        (into the (nf, mf) grid) giving their s.d. (mm).  The same propagation read the other way
        round: σ_p = |J H⁻¹ s_p| with s_p the node's height in the sensor frame as a
        row over the coefficients, so each node costs one band solve instead of every datum's
        response over the whole grid (5×5: the 25 cell centres and an element row's patches are
        about 50 of 441 nodes).  The matrix is factorised on the first call and kept."""
        system: list[Callable[[np.ndarray], np.ndarray]] = []

        def squares() -> Callable[[np.ndarray], np.ndarray]:
            """flat nodes → |J H⁻¹ s_p|² (the matrix factorised on the first call)."""
            if system:
                return system[0]
            turning, stretch, w_t, w_s = data[:4]
            g = len(turning)
            h = None
            if self._compiled is not None and self.size > _BAND_SIGMA_SIZE:
                # the band factor, the nodes' columns solved together in blocks of the band (?pbtrs
                # takes them one at a time, 2.5-3x slower), and J by each gauge's own coefficients
                # (the dense Jacobian and the dense triangle cost a 16×16 frame's node σ 125-280 ms;
                # :meth:`_band_sigma_squares`)
                band = self.prior_band.copy()
                jac_local = np.zeros((2 * g, self.idx.shape[1]))
                self._compiled.graph_normal_equations(c, self.idx, self.da, self.db, self.daa, self.wq, turning,
                                                      stretch, w_t, w_s, band, np.zeros(self.size), True,
                                                      np.asarray(self.sigma_curvature, dtype=float), np.empty(2 * g),
                                                      self._no_jacobian, jac_local)
                f, info = _pbtrf(band, lower=1)
                if info == 0:
                    blocks = BandCholeskyBlocks(f)

                    def band_squares(flat: np.ndarray) -> np.ndarray:
                        return self._band_sigma_squares(blocks, jac_local, flat, centre)

                    system.append(band_squares)
                    return band_squares
            if self._compiled is not None:
                band = self.prior_band.copy()
                j = np.zeros((2 * g, self.size))
                self._compiled.graph_normal_equations(c, self.idx, self.da, self.db, self.daa, self.wq, turning,
                                                      stretch, w_t, w_s, band, np.zeros(self.size), True,
                                                      np.asarray(self.sigma_curvature, dtype=float), np.empty(2 * g), j,
                                                      self._no_jacobian)
                f, info = _pbtrf(band, lower=1)
                if info != 0:
                    h = self._dense(band)
            else:
                j, res = self._numpy_jacobian(c, turning, stretch, w_t, w_s)
                h = self._numpy_matrix(c, j, res[g:], w_s, self.sigma_curvature)
            if h is None:
                # the factor through the dense triangle (a band solve takes the right-hand
                # sides one at a time, 2x slower), as fine_height_sigma
                lower = self._dense_lower(f, np.zeros((self.size, self.size), order="F"))  # kept past other fits

                def solve(rhs: np.ndarray) -> np.ndarray:
                    y, info = _trtrs(lower, rhs, lower=1)
                    if info == 0:
                        y, info = _trtrs(lower, y, lower=1, trans=1, overwrite_b=1)
                    if info != 0:
                        raise np.linalg.LinAlgError(f"graph fit's factor is singular (info {info})")
                    return y
            else:  # as fine_height_sigma: a dense factorisation, least squares if not definite
                try:
                    dense = scipy.linalg.cho_factor(h, lower=True, check_finite=False)

                    def solve(rhs: np.ndarray) -> np.ndarray:
                        return scipy.linalg.cho_solve(dense, rhs, check_finite=False)
                except np.linalg.LinAlgError:
                    def solve(rhs: np.ndarray) -> np.ndarray:
                        return np.linalg.lstsq(h, rhs, rcond=None)[0]

            def dense_squares(flat: np.ndarray) -> np.ndarray:
                r = j @ solve(np.asfortranarray(self._frame_height_rows(flat, centre).T))
                return np.einsum("kp,kp->p", r, r)

            system.append(dense_squares)
            return dense_squares

        def at(flat: np.ndarray) -> np.ndarray:
            return noise_ratio * np.sqrt(squares()(np.asarray(flat, dtype=np.intp).reshape(-1)))

        return at

    def _band_sigma_squares(self, blocks: BandCholeskyBlocks, jac_local: np.ndarray, flat: np.ndarray,
                            centre: tuple[int, int]) -> np.ndarray:
        """|J H⁻¹ s_p|² of fine nodes ``flat`` from H's band factor ``blocks`` and J by each
        gauge's own coefficients (``jac_local``, kernels.graph_normal_equations).  s_p = e_p −
        (ref + u_p·slope_u + v_p·slope_v): a node's height e_p touches 16 coefficients, the frame's
        three forms (:meth:`_frame_forms_at`) all of them.  So L⁻¹ (the forward sweep) is taken of
        the three forms and of the nodes' heights, each from its first coefficient on (a node's
        height far down the system costs little: about half the sweep's work), and combined:
        L⁻¹s_p, then L⁻ᵀ of it is H⁻¹s_p, the same as solving for s_p up to rounding."""
        rows = self._sigma_rows_of(flat, centre, blocks)
        nodes = len(rows.order)
        y = blocks.columns(3 + nodes)  # the three forms, then the nodes' heights
        y.reshape(-1)[rows.at] = rows.values
        blocks.forward(y, rows.starts)
        for block in y:  # L⁻¹s_p = L⁻¹e_p − w_p·(L⁻¹ forms), block by block (Fortran (kd, columns) each)
            _gemm(-1.0, block[:3].T, rows.weights, beta=1.0, c=block[3:].T, trans_b=1, overwrite_c=1)
        x = blocks.backward(y[:, 3:])
        out = np.zeros(nodes)
        self._compiled.graph_sigma_squares(self.idx, jac_local, np.ascontiguousarray(blocks.unblocked(x)), out)
        squares = np.empty(nodes)
        squares[rows.order] = out
        return squares

    def _sigma_rows_of(self, flat: np.ndarray, centre: tuple[int, int], blocks: BandCholeskyBlocks) -> _SigmaRows:
        """The right-hand sides of :meth:`_band_sigma_squares` for nodes ``flat`` in the blocked
        layout of ``blocks``, kept for the last :data:`_SIGMA_ROWS_KEPT` node sets made (skinmapd
        reads the same nodes every frame)."""
        key = (flat.tobytes(), centre, blocks.bandwidth)
        rows = self._sigma_rows.get(key)
        if rows is not None:
            return rows
        fv, fu = self._fv[0], self._fu[0]
        a, b = np.divmod(flat, len(self._fine_u))
        nodes = len(flat)
        height = (fv[a][:, :, None] * fu[b][:, None, :]).reshape(nodes, self.size)
        nonzero = height != 0.0
        first = np.where(nonzero.any(axis=1), nonzero.argmax(axis=1), self.size)
        order = np.argsort(first, kind="stable")
        rhs = np.concatenate([np.array(self._frame_forms_at(centre)), height[order]])
        col, coef = np.nonzero(rhs)
        kd, columns = blocks.bandwidth, 3 + nodes
        rows = _SigmaRows(order=order, starts=np.concatenate([np.zeros(3, dtype=np.intp), first[order]]),
                          at=(coef // kd) * (columns * kd) + col * kd + coef % kd, values=rhs[col, coef],
                          weights=np.asfortranarray(np.stack([np.ones(nodes), self._fine_u[b[order]],
                                                              self._fine_v[a[order]]], axis=1)))
        self._sigma_rows[key] = rows
        if len(self._sigma_rows) > _SIGMA_ROWS_KEPT:
            self._sigma_rows.popitem(last=False)
        return rows

    def _frame_height_rows(self, flat: np.ndarray, centre: tuple[int, int]) -> np.ndarray:
        """(P, coefficients): the height of fine nodes ``flat`` in the sensor frame (over the
        best-fit plane, from the centre node ``centre``), as fine_height_sigma builds it, as
        linear forms in the coefficients."""
        fv, fu = self._fv[0], self._fu[0]
        a, b = np.divmod(flat, len(self._fine_u))
        u, v = self._fine_u, self._fine_v
        ref, slope_u, slope_v = self._frame_forms_at(centre)
        height = (fv[a][:, :, None] * fu[b][:, None, :]).reshape(len(a), self.size)
        return height - ref - u[b][:, None] * slope_u[None, :] - v[a][:, None] * slope_v[None, :]

    def _frame_forms_at(self, centre: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sensor frame's own linear forms in the coefficients: the height of the centre node
        ``centre`` and the best-fit plane's two slopes (they depend on the geometry and the
        centre alone, kept)."""
        frame = self._frame_forms.get(centre)
        if frame is None:
            fv, fu = self._fv[0], self._fu[0]
            u, v = self._fine_u, self._fine_v
            a0, b0 = centre
            ref = (fv[a0][:, None] * fu[b0][None, :]).reshape(-1)
            # uncertainty.plane_slopes as linear forms: over a separable grid each slope's sum is
            # one outer product (the whole (nf, mf, coefficients) array would cost megabytes a frame)
            slope_u = np.outer(fv.sum(axis=0), u @ fu).reshape(-1) / (len(v) * float(u @ u))
            slope_v = np.outer(v @ fv, fu.sum(axis=0)).reshape(-1) / (len(u) * float(v @ v))
            frame = self._frame_forms[centre] = (ref, slope_u, slope_v)
        return frame

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

    def fine_derivatives(self, c: np.ndarray) -> np.ndarray:
        """∂u x, ∂v x and ∂u∂v x of x = (u, v, w) at every fine-grid node, (3 derivatives,
        nf, mf, 3), base frame: the graph's own, for the surface's patches (finite differences
        of the nodes miss what the graph holds between them where the fine grid is coarser
        than its knots, above 8×8)."""
        cm = c.reshape(self.nbv, self.nbu)
        nf, mf = len(self._fine_v), len(self._fine_u)
        out = np.zeros((3, nf, mf, 3))
        out[0, ..., 0] = 1.0
        out[1, ..., 1] = 1.0
        out[0, ..., 2] = self._fv[0] @ cm @ self._fu[1].T
        out[1, ..., 2] = self._fv[1] @ cm @ self._fu[0].T
        out[2, ..., 2] = self._fv[1] @ cm @ self._fu[1].T
        return out


def _twist_may_answer(linear_reason: str) -> bool:
    """Whether a start with twist (the general model's surface) may still be a graph where the
    linear start's screen gave ``linear_reason``: a gauge that shortens, slopes within the noise
    or too little stretch for the slopes the turning implies rule out every graph; more stretch
    than that may be twist, which the linear start lacks."""
    return not linear_reason or linear_reason.startswith(_MORE_STRETCH)


def _rejected(starts: list, reason: str) -> GraphResult:
    """The cold fit's answer where its screen rules out every start (none was fitted)."""
    return GraphResult(False, starts[0][1], math.inf, math.inf, 0, 0.0, math.inf, reason, math.inf)
