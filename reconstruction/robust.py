"""Robust fits solved with Clarabel: the gauge screen of the default path, and the optional
Huber field fit.

**Gauge screen** (:class:`GaugeScreen`, run before every reconstruction, docs/reconstruction.md,
"Robust gauge screen").  The reconstruction's own fits interpolate the units' data, so a gauge
whose gain is off is absorbed and never shows as misfit.  The screen fits a model with
redundancy instead: per direction, a turning field T and a stretch field S over the cells,
each read by both gauges of a unit (ε_upper = S + h_u T, ε_lower = S − h_l T, as
:func:`.decouple.decouple` inverts), with a stiff prior on their third differences along the
rows and columns (quadratic fields cost nothing: cylinders, spheres, saddles).  A gain error on
one gauge then cannot be followed by the fields (it would need a spike in T and in S at one
cell) and stays in that gauge's residual, while its partner's stays small; a real feature the
fields cannot follow (a bump sharper than the cells) leaves residuals in both gauges of its
units.  The fit is a closed-form least-squares solve (a cached hat matrix or factorisation: tens
of microseconds on 5×5);
when some gauge's residual stands out of the frame's own scatter the robust problem is solved,
the same fit with a Huber loss on every gauge's residual, by Clarabel, whose residuals localise
the bad gauge (least squares spreads it over its neighbours).  The gauge it names is set
missing for every later fit (the existing missing-unit path) and reported.

Huber as a QP (s: the part of the residual inside the quadratic zone, t ≥ |r − s|):

    min ½ xᵀ P x + Σ_i (½ s_i² + δ t_i)   s.t.   −t ≤ O x − d − s ≤ t,

with P the prior and O the data operator (data and residuals in noise units).  The optional
Huber field fit (``Reconstructor(convex_solver="clarabel")``) poses the bending potential's fit
the same way.
"""
from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .grid import FineGrid

__all__ = ["huber_fit", "huber_potential", "HuberProblem", "GaugeScreen", "Suspect", "gauge_name", "SCREEN_PRIOR",
           "SCREEN_SIGMAS", "SCREEN_PARTNER", "SCREEN_GAIN_RANGE", "SCREEN_TRIGGER", "SCREEN_PARTNER_TRIGGER",
           "SCREEN_TRIGGER_GAIN", "SCREEN_WINDOW", "SCREEN_HUBER", "SCREEN_LEAVE_OUT"]

#: Weight of the screen's third-difference prior against one gauge's datum (noise units): stiff,
#: so that one gauge's error cannot be followed, while quadratic fields are free.
SCREEN_PRIOR = 100.0
#: A gauge is named when its Huber residual exceeds this many times the frame's scatter (the
#: larger of the noise and 1.4826 × the median absolute residual of all gauges) ...
SCREEN_SIGMAS = 6.0
#: ... and its partner's residual (the other layer of its unit) is below this share of its own.
SCREEN_PARTNER = 0.3
#: ... and it reads between these multiples of the strain the fit expects there: a calibration
#: gone wrong by tens of percent.  Farther off, the misfit is the shape's (measured: a bump
#: sharper than the cells, moving over a 5×5 sheet, makes one gauge read 3.8-4.5x the fields'
#: value when their stretch cannot follow it), and a gauge that far off is left to the
#: plausibility checks of skinmap.strains.
SCREEN_GAIN_RANGE = (0.5, 2.0)
#: Clarabel runs only when some least-squares residual exceeds this many times the scatter
#: (a gauge's error spreads into its neighbours under least squares, so below the naming level).
SCREEN_TRIGGER = 5.0
#: ... and its partner's least-squares residual is below this share of its own.
SCREEN_PARTNER_TRIGGER = 0.4
#: ... and reads within these multiples of the least-squares fit's value there (which has taken
#: in part of a gauge's error: a 1.3 gain reads 1.15-1.3x it).
SCREEN_TRIGGER_GAIN = (0.4, 2.5)
#: The robust fit takes a window of at most this many cells a side around the gauge that
#: called for it (Clarabel's time grows with the cells; a gauge's error stays local).
SCREEN_WINDOW = 7
#: The Huber threshold of the screen, in units of the frame's scatter.
SCREEN_HUBER = 3.0
#: A named gauge is checked against this many gauges of largest Huber residual in its window:
#: the one whose leaving out lets the others be fitted closest is named (GaugeScreen._leave_out_check).
SCREEN_LEAVE_OUT = 3
_LAYERS = ("upper", "lower")
_DIRECTIONS = ("row", "column")


def _huber_matrices(prior: sp.spmatrix, obs: sp.spmatrix) -> tuple[sp.csc_matrix, sp.csc_matrix]:
    """The Huber QP's quadratic form (upper triangle) and constraint matrix over (x, s, t)."""
    m = obs.shape[0]
    eye = sp.identity(m, format="csc")
    p = sp.block_diag([prior, eye, sp.csc_matrix((m, m))], format="csc")
    a = sp.vstack([sp.hstack([obs, -eye, -eye]), sp.hstack([-obs, eye, -eye])], format="csc")
    return sp.triu(p, format="csc"), a


def _clarabel_settings(screen: bool = False):
    import clarabel  # imported here: only the robust paths need it

    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.max_threads = 1  # a small problem on the processing thread (see Reconstructor.__call__)
    if screen:
        # the screen reads its residuals to a tenth of a noise s.d. (data in noise units): looser
        # than the defaults (1e-8), and no iterative refinement of the steps, a third less time
        # (7×7 cells: 2.3 → 1.5 ms; the same gauges named in the bench)
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-5
        settings.iterative_refinement_enable = False
    return settings


def _info(sol) -> dict:
    return {"status": str(sol.status), "iterations": int(sol.iterations), "solve_time": float(sol.solve_time)}


def huber_fit(prior: sp.spmatrix, obs: sp.spmatrix, data: np.ndarray, delta: float) -> tuple[np.ndarray, dict]:
    """x minimising ½ xᵀ prior x + Σ huber_δ(obs x − data), solved by Clarabel.  Returns x and
    a dict with Clarabel's status, iterations and solve time (s)."""
    import clarabel

    if not delta > 0:
        raise ValueError(f"Huber threshold delta must be > 0, got {delta!r}")
    n, m = prior.shape[0], obs.shape[0]
    if m == 0:
        return np.zeros(n), {"status": "no data", "iterations": 0, "solve_time": 0.0}
    p, a = _huber_matrices(prior, obs)
    q = np.concatenate([np.zeros(n + m), np.full(m, float(delta))])
    b = np.concatenate([data, -data])
    solver = clarabel.DefaultSolver(p, q, a, b, [clarabel.NonnegativeConeT(2 * m)], _clarabel_settings())
    sol = solver.solve()
    return np.asarray(sol.x[:n]), _info(sol)


class HuberProblem:
    """The gauge screen's Huber fit, its QP kept set up in Clarabel (its matrices fixed), so
    that a frame only updates the data and the threshold: the setup (matrix assembly, the KKT
    system's symbolic factorisation) is paid once."""

    def __init__(self, prior: sp.spmatrix, obs: sp.spmatrix):
        import clarabel

        self.n, self.m = prior.shape[0], obs.shape[0]
        p, a = _huber_matrices(prior, obs)
        q = np.concatenate([np.zeros(self.n + self.m), np.ones(self.m)])
        self._q = q
        self._solver = clarabel.DefaultSolver(p, q, a, np.zeros(2 * self.m), [clarabel.NonnegativeConeT(2 * self.m)],
                                              _clarabel_settings(screen=True))

    def solve(self, data: np.ndarray, delta: float) -> tuple[np.ndarray, dict]:
        if not delta > 0:
            raise ValueError(f"Huber threshold delta must be > 0, got {delta!r}")
        q = self._q.copy()
        q[self.n + self.m:] = float(delta)
        self._solver.update(q=q, b=np.concatenate([data, -data]))
        sol = self._solver.solve()
        return np.asarray(sol.x[: self.n]), _info(sol)


def huber_potential(
    grid: FineGrid, turning: np.ndarray, valid: np.ndarray, delta: float
) -> tuple[np.ndarray, dict]:
    """Bending potential z (extended grid, flattened) minimising prior + Huber data loss.

    Returns z and a dict with Clarabel's status, iterations and solve time (s).
    """
    if not delta > 0:
        raise ValueError(f"Huber threshold delta must be > 0, got {delta!r}")
    mask = np.asarray(valid, dtype=bool).ravel()
    obs = grid.potential_observation()[mask]
    d = np.asarray(turning, dtype=float).ravel()[mask]
    return huber_fit(grid.potential_prior(), obs, d, delta)


def gauge_name(layer: int, direction: int, row: int, col: int) -> str:
    """A gauge as the strains and the status name it: layer, direction, cell (row, column)."""
    return f"{_LAYERS[layer]} {_DIRECTIONS[direction]}-direction gauge of cell (row {row}, column {col})"


@dataclass(frozen=True)
class Suspect:
    """A gauge the screen found inconsistent with the rest of the frame."""

    layer: int  # 0 upper, 1 lower
    direction: int  # 0 row (u), 1 column (v)
    row: int
    col: int
    residual_sigmas: float  # its Huber residual in units of the frame's scatter
    gain: float  # measured over the strain the fit expects there (1.3: reads 30 % high)

    @property
    def name(self) -> str:
        return gauge_name(self.layer, self.direction, self.row, self.col)

    def describe(self) -> str:
        return f"{self.name}: reads {self.gain:.2f}x the strain its neighbours imply ({self.residual_sigmas:.0f} s.d.)"


def _third_differences(k: int) -> sp.csr_matrix:
    """(k − 3, k) third differences (zero for quadratics); none on lines shorter than 4."""
    if k < 4:
        return sp.csr_matrix((0, k))
    return sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(k - 3, k), format="csr")


class GaugeScreen:
    """The gauge screen for one geometry (N×M cells, layer offsets): its operators, and per
    direction and validity mask the least-squares fit's hat matrix (or factorisation) and the
    Huber problem set up in Clarabel (cached: not thread-safe, like the :class:`Reconstructor`
    that holds it).

    Unknowns per direction: T and S on the cells (2·N·M); data: that direction's upper and
    lower gauges (2·N·M).  The two directions share no unknown, so they are fitted apart."""

    def __init__(self, n: int, m: int, h_upper: float, h_lower: float, prior: float = SCREEN_PRIOR):
        self.n, self.m = int(n), int(m)
        self.h_upper, self.h_lower = float(h_upper), float(h_lower)
        cells = self.n * self.m
        d_rows = sp.kron(sp.identity(self.n), _third_differences(self.m))  # along a row (u)
        d_cols = sp.kron(_third_differences(self.n), sp.identity(self.m))  # along a column (v)
        one = (d_rows.T @ d_rows + d_cols.T @ d_cols) * float(prior)
        self.prior = sp.block_diag([one, one], format="csc")  # T, S
        eye = sp.identity(cells, format="csr")
        # rows: upper gauges, then lower ones (cells in C order); columns: T, then S
        self.obs = sp.bmat([[eye * self.h_upper, eye], [eye * -self.h_lower, eye]], format="csr")
        self._fits: OrderedDict[bytes, tuple[np.ndarray | None, object]] = OrderedDict()
        self._robust: OrderedDict[bytes, HuberProblem] = OrderedDict()
        self._full_hat: np.ndarray | None = None
        self._obs_t: sp.csr_matrix | None = None
        self._prior_weight = float(prior)
        self._windows: dict[tuple[int, int], GaugeScreen] = {}
        # Clarabel's all-valid problem set up now, not in the first frame that needs it
        window = self._window(0)[0]
        every = np.ones(window.obs.shape[0], dtype=bool)
        window._cached(window._robust, every.tobytes(), lambda: HuberProblem(window.prior, window.obs))
        if 4 * cells <= 800:
            # the all-valid hat of both directions in the strains' own order (layer, direction, cell)
            hat = self._least_squares_hat(np.ones(2 * cells, dtype=bool))
            full = np.zeros((2, 2, cells, 2, 2, cells))
            for d in (0, 1):
                full[:, d, :, :, d, :] = hat.reshape(2, cells, 2, cells)
            self._full_hat = full.reshape(4 * cells, 4 * cells)

    @staticmethod
    def _cached(cache: OrderedDict, key: bytes, build):
        hit = cache.get(key)
        if hit is None:
            hit = cache[key] = build()
            if len(cache) > 16:
                cache.popitem(last=False)
        else:
            cache.move_to_end(key)
        return hit

    def _normal(self, valid: np.ndarray) -> sp.csc_matrix:
        w = sp.diags(valid.astype(float))
        normal = (self.obs.T @ w @ self.obs + self.prior).tocsc()
        return normal + sp.identity(normal.shape[0], format="csc") * 1e-9  # cells with no valid gauge

    def _least_squares_hat(self, valid: np.ndarray) -> np.ndarray:
        """Data → fitted strains of one direction, dense (invalid data columns zero)."""
        w = sp.diags(valid.astype(float))
        return self.obs @ np.linalg.solve(self._normal(valid).toarray(), (self.obs.T @ w).toarray())

    def _least_squares(self, data: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Fitted strains (noise units) of one direction's gauges by least squares over the valid ones."""
        def build():
            if self.obs.shape[0] <= 400:  # small sheets: the dense hat matrix, one product per frame
                return self._least_squares_hat(valid), None
            return None, spla.factorized(self._normal(valid))

        hat, solve = self._cached(self._fits, valid.tobytes(), build)
        d = np.where(valid, data, 0.0)
        if hat is not None:
            return hat @ d
        if self._obs_t is None:  # (the same products as obs.T, without its conversion every frame)
            self._obs_t = self.obs.T.tocsr()
        return self.obs @ solve(self._obs_t @ d)

    def screen(self, eps_upper: np.ndarray, eps_lower: np.ndarray, strain_sigma: float) -> tuple[list[Suspect], dict]:
        """The gauges of one frame that its other gauges contradict (at most one per
        direction), and what the screen did: {"screen": "clean", "robust fit: ...", and
        "screen_clarabel": Clarabel's status and iterations when it ran}.  ``strain_sigma``:
        one gauge's noise s.d. (> 0)."""
        sigma = float(strain_sigma)
        if not (sigma > 0.0 and math.isfinite(sigma)):
            raise ValueError(f"strain_sigma must be a finite number > 0 for the gauge screen, got {strain_sigma!r}")
        strains = np.stack([np.asarray(eps_upper, dtype=float), np.asarray(eps_lower, dtype=float)])
        if strains.shape != (2, 2, self.n, self.m):
            raise ValueError(f"strains must have shape (2, {self.n}, {self.m}) per layer, got {strains.shape[1:]}")
        info: dict = {"screen": "clean"}
        suspects: list[Suspect] = []
        runs = []
        data_all = strains.reshape(-1) / sigma
        if self._full_hat is not None and np.isfinite(data_all).all():
            # every gauge valid (the usual frame): both directions' fits in one product
            resid_all = (data_all - self._full_hat @ data_all).reshape(2, 2, -1)
            data_dirs = data_all.reshape(2, 2, -1)
            if all(self._candidate(resid_all[:, d].reshape(-1), data_dirs[:, d].reshape(-1), None) < 0 for d in (0, 1)):
                return suspects, info
        for d in (0, 1):
            part = strains[:, d].reshape(-1)  # upper cells, then lower cells
            valid = np.isfinite(part)
            if valid.sum() < 8:
                continue
            data = np.where(valid, part, 0.0) / sigma
            resid = np.where(valid, data - self._least_squares(data, valid), 0.0)
            candidate = self._candidate(resid, data, valid)
            if candidate < 0:
                continue
            # the robust problem: the same fit with a Huber loss on every gauge of a window of
            # cells around the candidate (the whole sheet up to SCREEN_WINDOW cells a side: a
            # gauge's error reaches about two cells through the stiff prior), by Clarabel
            window, (i0, j0) = self._window(candidate % (self.n * self.m))
            part_w = strains[:, d, i0:i0 + window.n, j0:j0 + window.m].reshape(-1)
            valid_w = np.isfinite(part_w)
            data_w = np.where(valid_w, part_w, 0.0) / sigma
            if window is not self:
                # the candidate must stand out of its window's own scatter too (a feature the
                # fields cannot follow raises it there, however quiet the rest of the sheet)
                resid_w = resid.reshape(2, self.n, self.m)[:, i0:i0 + window.n, j0:j0 + window.m].reshape(-1)
                if window._candidate(resid_w, data_w, valid_w) < 0:
                    continue
            problem = window._cached(window._robust, valid_w.tobytes(),
                                     lambda: HuberProblem(window.prior, window.obs[valid_w]))
            x, cl = problem.solve(data_w[valid_w], SCREEN_HUBER * self._scale(resid, valid))
            runs.append(f"{_DIRECTIONS[d]}: {cl['status']}, {cl['iterations']} iterations")
            huber = np.where(valid_w, data_w - window.obs @ x, 0.0)
            found = window._suspect(huber, valid_w, data_w, d)
            if found is not None:
                found = window._leave_out_check(found, huber, valid_w, data_w, d)
            if found is not None:
                suspects.append(dataclasses.replace(found, row=found.row + i0, col=found.col + j0))
        if runs:
            info["screen_clarabel"] = "; ".join(runs)
            info["screen"] = f"robust fit: {len(suspects)} suspect gauge(s)"
        return suspects, info

    def _window(self, cell: int) -> tuple["GaugeScreen", tuple[int, int]]:
        """The screen of the window of cells the robust fit takes around ``cell`` (flat index),
        and the window's first row and column: the sheet itself up to SCREEN_WINDOW cells a
        side, else a SCREEN_WINDOW-wide window centred on the cell and shifted inside the sheet."""
        wn, wm = min(self.n, SCREEN_WINDOW), min(self.m, SCREEN_WINDOW)
        if (wn, wm) == (self.n, self.m):
            return self, (0, 0)
        i, j = divmod(cell, self.m)
        i0 = min(max(i - wn // 2, 0), self.n - wn)
        j0 = min(max(j - wm // 2, 0), self.m - wm)
        sub = self._windows.get((wn, wm))
        if sub is None:
            sub = self._windows[(wn, wm)] = GaugeScreen(wn, wm, self.h_upper, self.h_lower, self._prior_weight)
        return sub, (i0, j0)

    def _candidate(self, resid: np.ndarray, data: np.ndarray, valid: np.ndarray | None) -> int:
        """The gauge (flat index into one direction's upper-then-lower data) whose
        least-squares residual calls for the robust fit, or −1: the largest of those above
        SCREEN_TRIGGER of the scatter whose partner misfits less than SCREEN_PARTNER_TRIGGER
        of them and whose reading is within SCREEN_TRIGGER_GAIN of the fit's (least squares
        spreads part of a gauge's error into its partner and neighbours, so these bounds are
        looser than the naming's)."""
        a = np.abs(resid)
        if not a.max() > SCREEN_TRIGGER:  # the scatter is at least the noise: nothing stands out
            return -1
        scale = _median_scale(a if valid is None else a[valid])
        big = a > SCREEN_TRIGGER * scale
        if not big.any():  # (none above the trigger: no gauge to weigh further)
            return -1
        cells = self.n * self.m
        partner = np.concatenate([a[cells:], a[:cells]])
        expected = data - resid
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = np.where(expected != 0.0, data / expected, np.inf)
        lo, hi = SCREEN_TRIGGER_GAIN
        marked = np.where(big & (partner < SCREEN_PARTNER_TRIGGER * a) & (gain >= lo)
                          & (gain <= hi), a, -1.0)
        best = int(np.argmax(marked))
        return best if marked[best] >= 0.0 else -1

    def _suspect(self, resid: np.ndarray, valid: np.ndarray, data: np.ndarray, d: int) -> Suspect | None:
        """The gauge that stands out of one direction's robust residuals alone, if any: above
        SCREEN_SIGMAS of the frame's scatter, with its partner (the unit's other layer) below
        SCREEN_PARTNER of it (a feature the fields cannot follow misfits both layers), reading
        within SCREEN_GAIN_RANGE of what the fit expects."""
        scale = self._scale(resid, valid)
        r = resid.reshape(2, self.n, self.m)
        layer, i, j = (int(k) for k in np.unravel_index(int(np.argmax(np.abs(resid))), r.shape))
        own, partner = abs(r[layer, i, j]), abs(r[1 - layer, i, j])
        if not (own > SCREEN_SIGMAS * scale and partner < SCREEN_PARTNER * own):
            return None
        measured = data.reshape(r.shape)[layer, i, j]
        expected = measured - r[layer, i, j]
        gain = measured / expected if expected != 0.0 else math.inf
        if not SCREEN_GAIN_RANGE[0] <= gain <= SCREEN_GAIN_RANGE[1]:
            return None
        return Suspect(layer, d, i, j, float(own / scale), float(gain))

    def _leave_out_check(self, found: Suspect, huber: np.ndarray, valid: np.ndarray, data: np.ndarray,
                         d: int) -> Suspect | None:
        """The suspect, or the gauge that explains the frame better: of the SCREEN_LEAVE_OUT
        gauges of largest Huber residual, the one whose leaving out lets least squares fit the
        others closest (the largest residual left).  A gauge whose neighbours the fields follow
        least (a corner's, an edge's) hands most of its error to a neighbour, whose Huber
        residual can then stand highest: measured on a twisted quadric, a corner's column gauge
        1.3× high named its row neighbour, the frame 2.3-3.9 mm off.  The gauge so chosen is named
        by :meth:`_suspect`'s three tests, its residual and gain now against the fit without it
        (its partner's still the Huber fit's), or none is."""
        cells = self.n * self.m
        own = found.layer * cells + found.row * self.m + found.col
        order = [int(k) for k in np.argsort(-np.abs(huber)) if valid[k]][:SCREEN_LEAVE_OUT]
        if own not in order:
            order = [own] + order[:-1]
        best, best_left, best_resid = own, math.inf, 0.0
        for k in order:
            keep = valid.copy()
            keep[k] = False
            fitted = self._least_squares(data, keep)  # (the left-out gauge's too: its prediction)
            left = float(np.max(np.abs(np.where(keep, data - fitted, 0.0))))
            if left < best_left:
                best, best_left, best_resid = k, left, data[k] - fitted[k]
        if best == own:
            return found
        scale = self._scale(np.where(valid, huber, 0.0), valid)
        layer, rest = divmod(best, cells)
        i, j = divmod(rest, self.m)
        measured = data[best]
        expected = measured - float(best_resid)
        partner = best + (cells if layer == 0 else -cells)
        gain = measured / expected if expected != 0.0 else math.inf
        own_resid = abs(float(best_resid))
        if not (own_resid > SCREEN_SIGMAS * scale and SCREEN_GAIN_RANGE[0] <= gain <= SCREEN_GAIN_RANGE[1]
                and abs(huber[partner]) < SCREEN_PARTNER * own_resid):
            return None
        return Suspect(layer, d, i, j, own_resid / scale, float(gain))

    @staticmethod
    def _scale(resid: np.ndarray, valid: np.ndarray) -> float:
        """The residual scatter in noise units: at least the noise, else the robust (median
        absolute) spread of the valid gauges' residuals, so that a shape the fields cannot
        follow everywhere raises the bar instead of naming its gauges."""
        return _median_scale(np.abs(resid[valid]))


def _median_scale(a: np.ndarray) -> float:
    """max(1, 1.4826 × the median of ``a``) (the upper median: np.median's sort-and-average
    costs more than the rest of the screen on small sheets)."""
    k = a.size // 2
    return max(1.0, 1.4826 * float(np.partition(a, k)[k]))
