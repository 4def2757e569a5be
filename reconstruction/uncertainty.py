"""Position uncertainty from strain noise, by linear propagation about the flat sheet.

For small deflections the reconstruction is linear in the data: the bending potential z is a
fixed linear map of the units' turning data, and z is the height of the sheet in the sensor
frame once its value at the centre and its best-fit plane's slopes are pinned (the frame's
definition, to first order).  The
one-s.d. height error of a fine node is the norm of its row of that map times the noise of a
unit's turning per length; missing units enter with the spread of the measured ones, so the
uncertainty rises around a dead gauge.  In-plane errors are a random walk of the stretch noise
along the rows and columns from the centre.
"""
from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from typing import Callable, cast

import numpy as np

from skinmap.strains import SHARED_GAIN_SD

from .grid import FineGrid
from .leaveout import IllConditioned
from .linalg import FixedSolver

__all__ = ["stretch_noise_sd", "plane_slopes", "height_response", "fine_sigma", "resolution_sigma", "SigmaField", "sigma_field",
           "RESOLUTION_SHARE", "GRAPH_RESOLUTION_SHARE", "graph_resolution_share", "alignment_floor",
           "DEFAULT_STRAIN_SIGMA", "DEFAULT_GAIN_SD", "gain_sigma", "with_gain", "response_lag_sigma"]

#: Default strain-noise s.d. of one gauge: resistance noise 0.007 % of R over a gauge factor
#: of 1.24 gives 0.0057 % strain.
DEFAULT_STRAIN_SIGMA = 0.0057e-2

#: Default s.d. (relative) of a gain error the gauges share: their hysteresis and their
#: relaxation under a held strain (skinmap.strains.SHARED_GAIN_SD, 0.0247; docs/reconstruction.md,
#: "A gain the gauges share").
DEFAULT_GAIN_SD = SHARED_GAIN_SD

#: The share of :func:`resolution_sigma` that joins the general model's node_sigma where it
#: answers (the whole term stands for a deferred frame).  Measured on kinematic sheets of 1-3
#: random bumps (|h| 1.5-5 mm, FWHM 15-25 mm, anywhere) with the general model and the sensor's
#: noise, 40 sheets a size, errors in the sensor frame (the sheet's best-fit plane): the sheets
#: within 3 σ + 0.05 mm went from 5 and 15 % (noise alone) to 95 and 100 % at 5×5 and 8×8 (the
#: two 5×5 sheets beyond it are flagged ambiguous), the median error/(3σ + 0.05 mm) 0.15 and
#: 0.17 (0.3: 95 and 93 %; 0.7: the same as 0.5 with σ a third larger; docs/reconstruction.md).
RESOLUTION_SHARE = 0.5
#: The same for a graph answer (reconstruction/graphfit.py), whose prior fills in between the
#: gauges what they do not resolve.  Measured the same way on the default path (every sheet
#: answered by the graph; 60 sheets at 5×5, 40 at 8×8): within 3σ + 0.05 mm, 87 and 90 % with
#: the noise's σ alone, 98 and 100 % with 0.1 (worst 1.16 and 0.82 of the bound, median 0.15
#: and 0.32); 0.05: 97 and 95 %; 0.15: 100 and 100 % with σ half as large again.
GRAPH_RESOLUTION_SHARE = 0.1
#: Sheets of fewer cells take a larger share (:func:`graph_resolution_share`): there each node
#: lies within a cell or two of an edge, and the prior extrapolates to it from fewer gauges.
#: Measured the same way (100 sheets a size, 1-3 bumps, the default path): with a tenth, the
#: sheets beyond 3σ + 0.05 mm were 7 (3×3, worst 2.13 of the bound), 4 (3×4), 2 (3×5), 1 (3×6),
#: 3 (4×4), 2 (4×5), 2 (4×6, worst 1.01), none at 3×8, 4×8, 5×5 and 6×6 (worst 0.57-0.86); with
#: a fifth, one (3×3, 1.34).  The share 0.1·(25/cells)^1.5, at most 0.3, brings each within;
#: on 100 further sheets a size (other seeds) one 3×3 (1.01) and one 3×4 sheet (1.61, a bump
#: centred inside the corner cell) stay beyond (docs/reconstruction.md).
GRAPH_SHARE_CELLS = 25
GRAPH_SHARE_MAX = 0.3
#: The bend radius (mm) whose turning a frame with no unit read at all is uncertain by: the
#: tightest sphere the reconstruction is specified for (R 50 mm), not a flat sheet's.
NO_READING_BEND_RADIUS_MM = 50.0


def graph_resolution_share(cells: int) -> float:
    """The share of :func:`resolution_sigma` that joins a graph answer's σ on a sheet of
    ``cells`` cells: GRAPH_RESOLUTION_SHARE from GRAPH_SHARE_CELLS cells up, more below (at most
    GRAPH_SHARE_MAX)."""
    if cells >= GRAPH_SHARE_CELLS:
        return GRAPH_RESOLUTION_SHARE
    return min(GRAPH_RESOLUTION_SHARE * (GRAPH_SHARE_CELLS / max(int(cells), 1)) ** 1.5, GRAPH_SHARE_MAX)


def alignment_floor(node_sigma: np.ndarray) -> float:
    """The least σ (mm) any point of the sheet keeps: the mean of ``node_sigma`` over the
    surface's nodes (NaN left out; 0 with none).

    The sensor frame pins the centre node at the origin, so there its frame error is zero by
    definition; a reference placed by its best rigid fit over the nodes (a truth, another
    instrument, a probe's own frame) shares their centroid instead, and moves every node by the
    mean of their errors.  The errors of one frame are smooth fields, correlated across the
    sheet, so that mean is not averaged down by the node count: its bound is the mean σ itself
    (|mean e| ≤ mean |e|).  Measured on elastic scenes (docs/reconstruction.md, "Uncertainty
    after a rigid alignment"): without it a 5×5 ridge's centre node stood 4.1× beyond 3σ +
    0.05 mm once aligned while every node was within it in the frame; with it none was beyond
    0.72.  The twist's spread is added after it, not floored: its mode (about c·u·v) has no mean
    over a symmetric sheet, and an alignment leaves the centre's part of it at zero."""
    values = np.asarray(node_sigma, dtype=float).reshape(-1)
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else 0.0


def response_lag_sigma(now: np.ndarray, before: np.ndarray, dt_s: float, scatter_now: np.ndarray,
                       scatter_before: np.ndarray, lag_s: float) -> np.ndarray:
    """(K,) σ (mm) of points read by gauges that answer up to ``lag_s`` late, from the same points
    ``now`` and ``dt_s`` earlier (``before``, both (K, 3) mm in the sensor frame) and each frame's
    scatter σ there (K,).

    A gauge of first-order response τ follows a strain that changes at a steady rate τ late, so a
    sheet moving at speed v is reconstructed v·τ behind where it is.  τ is known only as a bound
    (the gauges settle within 170 ms: τ ≤ ``lag_s``), so the error is taken as bounded, between
    none and v·``lag_s``: a rectangular distribution's s.d., v·``lag_s``/√3.  v is read from the
    two frames, their noise taken out: |Δx|² less the two scatter variances (the noise's own
    expectation of it), none where the frames differ by no more than their noise."""
    d = np.asarray(now, dtype=float) - np.asarray(before, dtype=float)
    noise = np.asarray(scatter_now, dtype=float) ** 2 + np.asarray(scatter_before, dtype=float) ** 2
    excess = np.einsum("kc,kc->k", d, d) - noise
    speed = np.sqrt(np.maximum(np.nan_to_num(excess, nan=0.0), 0.0)) / float(dt_s)
    return speed * (float(lag_s) / math.sqrt(3.0))


class SigmaField:
    """A fine-node σ map (nf, mf) computed on demand: whole (calling it; computed once and then
    shared) or at some nodes only (:meth:`at`, flat indices into the (nf, mf) grid).  A consumer
    that reads a few nodes (skinmapd: the cell centres and the patches its elements sit on, a few
    dozen of 441 at 5×5) then pays for those alone where ``at_nodes`` is given; without it
    :meth:`at` reads the whole field."""

    def __init__(self, field: Callable[[], np.ndarray],
                 at_nodes: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        self._field = field
        self._at_nodes = at_nodes
        self._whole: np.ndarray | None = None
        # nodes read so far, each computed once: their values and which are known, by flat
        # index (grown to the largest index asked for; arrays, so a frame's few reads cost
        # microseconds, not a Python loop over nodes)
        self._values = np.empty(0)
        self._known = np.zeros(0, dtype=bool)

    def __call__(self) -> np.ndarray:
        if self._whole is None:
            self._whole = self._field()
        return self._whole

    def at(self, flat: np.ndarray) -> np.ndarray:
        """σ (mm) at the fine nodes of flat indices ``flat`` (any shape; repeats, and nodes read
        before, cost nothing)."""
        flat = np.asarray(flat, dtype=np.intp)
        if self._whole is not None or self._at_nodes is None:
            return self().reshape(-1)[flat]
        if flat.size and int(flat.max()) >= self._known.size:
            size = int(flat.max()) + 1
            self._values = np.concatenate([self._values, np.empty(size - self._values.size)])
            self._known = np.concatenate([self._known, np.zeros(size - self._known.size, dtype=bool)])
        need = ~self._known[flat]
        if need.any():
            new = np.unique(flat[need])
            self._values[new] = np.asarray(self._at_nodes(new), dtype=float).reshape(-1)
            self._known[new] = True
        return self._values[flat]

    def wrapped(self, around: Callable[[Callable], Callable]) -> "SigmaField":
        """The same map with both ways of reading it run inside ``around`` (e.g. a thread limit)."""
        return SigmaField(around(self.__call__), around(self.at) if self._at_nodes is not None else None)


def gain_sigma(positions: np.ndarray, u: np.ndarray, v: np.ndarray, stretch: np.ndarray, pitch: float,
               gain_sd: float, twist: float = 0.0) -> np.ndarray:
    """(nf, mf) σ (mm) of the fine nodes from a gain error of s.d. ``gain_sd`` (relative) common
    to every gauge: it scales each unit's turning and stretch alike.  ``positions`` (nf, mf, 3)
    in the sensor frame over material coordinates ``u`` (mf,), ``v`` (nf,); ``stretch`` (2, N,
    M) the units' stretch ratios L/g (row gauges, column gauges; 1 where missing); ``twist`` the
    answer's constant twist (1/mm), whose part of the height is taken apart (below).

    To first order in the gain g a node moves by g·((2 d_x − s_u, 2 d_y − s_v), d_z), with d the
    node's deflection from its flat place (u, v, 0): the height is linear in the curvature, the
    in-plane pull of bending (d_xy − s) quadratic, and s, the stretch's own in-plane shift (its
    integral along the row and the column from the sheet's centre), linear in the stretch.
    Measured against reconstructions of strains scaled by 1.01 (docs/reconstruction.md, each
    raised to its mean over the nodes as the reconstructor raises this one): 0.90-2.14 times
    their change in the sensor frame on kinematic spheres, cylinders, saddles and bumps at 5×5 to
    16×16, 0.92-3.36 on elastic films, where that change is at least a fifth of its largest;
    0.95-1.07 on spheres and cylinders, the most on saddles."""
    pos = np.asarray(positions, dtype=float)
    ext = np.asarray(stretch, dtype=float) - 1.0
    n, m = ext.shape[1:]
    # each fine node takes the stretch of the cell it lies in (the outer half pitch: the outer cell's)
    cols = np.clip(np.rint(u / pitch + 0.5 * (m - 1)).astype(int), 0, m - 1)
    rows = np.clip(np.rint(v / pitch + 0.5 * (n - 1)).astype(int), 0, n - 1)
    e_u, e_v = ext[0][np.ix_(rows, cols)], ext[1][np.ix_(rows, cols)]
    # (the trapezoid rule along the rows and the columns)
    s_u = np.zeros(e_u.shape)
    s_u[:, 1:] = np.cumsum(0.5 * (e_u[:, 1:] + e_u[:, :-1]) * np.diff(u), axis=1)
    s_v = np.zeros(e_v.shape)
    s_v[1:] = np.cumsum(0.5 * (e_v[1:] + e_v[:-1]) * np.diff(v)[:, None], axis=0)
    # from the sheet's material centre (u = v = 0, the frame's origin), linear between the nodes about it
    s_u -= _at_zero(u, s_u, axis=1)[:, None]
    s_v -= _at_zero(v, s_v, axis=0)[None, :]
    dx = 2.0 * (pos[..., 0] - u[None, :]) - s_u
    dy = 2.0 * (pos[..., 1] - v[:, None]) - s_v
    # the twist's part of the height, τ·u·v, scales with the gain by a share between none and
    # all of it: where the twist is read from the Gauss equation the curvature product scales
    # twice and the stretch's K once (measured, strains scaled by 1.01: a saddle's twist by 0.05 %
    # on 12×12 and 16×16, by 0.5 % on 5×5), so the height moves by g·|z − (1 − f)τuv| for some f
    # in [0, 1], at most g·max(|z|, |z − τuv|) (|z| alone reads nothing on a saddle's nodal
    # lines, where the two parts cancel and the twist, not scaled, stays)
    twist_part = float(twist) * u[None, :] * v[:, None]
    dz = np.maximum(np.abs(pos[..., 2]), np.abs(pos[..., 2] - twist_part))
    return gain_sd * np.sqrt(dx * dx + dy * dy + dz * dz)


def _at_zero(x: np.ndarray, f: np.ndarray, axis: int) -> np.ndarray:
    """``f`` interpolated linearly along ``axis`` at x = 0 (``x`` increasing, spanning 0)."""
    k = int(np.clip(np.searchsorted(x, 0.0) - 1, 0, len(x) - 2))
    w = (0.0 - x[k]) / (x[k + 1] - x[k])
    lo, hi = np.take(f, k, axis=axis), np.take(f, k + 1, axis=axis)
    return lo + w * (hi - lo)


def with_gain(field: Callable[[], np.ndarray], gain: Callable[[], np.ndarray]) -> SigmaField:
    """σ ``field`` with a gain error's σ ``gain`` (a whole-field callable, computed once on
    first use) in quadrature, read whole or node by node as ``field`` is."""
    base = sigma_field(field)
    known: list[np.ndarray] = []

    def gain_map() -> np.ndarray:
        if not known:
            known.append(gain())
        return known[0]

    def whole() -> np.ndarray:
        out = np.hypot(base(), gain_map())
        out.flags.writeable = False
        return out

    def at(flat: np.ndarray) -> np.ndarray:
        return np.hypot(base.at(flat), gain_map().reshape(-1)[flat])

    return SigmaField(whole, at)


def stretch_noise_sd(strain_sigma: float, h_upper: float, h_lower: float) -> float:
    """The noise s.d. of one unit's stretch reading (the layers' mean, weighted by their
    offsets) for strain noise ``strain_sigma`` on each layer: σ·√(h_u² + h_l²)/(h_u + h_l)."""
    return float(strain_sigma * math.hypot(h_upper, h_lower) / (h_upper + h_lower))


def sigma_field(fn: Callable[[], np.ndarray]) -> SigmaField:
    """``fn`` (a whole-field σ callable) as a :class:`SigmaField` (itself if it is one)."""
    return fn if isinstance(fn, SigmaField) else SigmaField(fn)


def _heights(grid: FineGrid, z_ext: np.ndarray) -> np.ndarray:
    """Fine-node heights in the sensor frame (centre height and best-fit plane pinned, mean twist
    removed) of potential columns z_ext (n_potential, K) → (nf·mf, K); linear."""
    # the reconstruction replaces the potential's mean twist by the Gauss-equation constant
    # (zero about the flat sheet): remove it here too
    mean_twist = (grid.z_uv @ z_ext).mean(axis=0)
    z = z_ext.reshape(grid.nf + 2, grid.mf + 2, -1)[1:-1, 1:-1]
    z = z - np.multiply.outer(np.outer(grid.v, grid.u), mean_twist)
    a0, b0 = grid.centre
    slope_u, slope_v = plane_slopes(grid.u, grid.v, z)
    z = z - z[a0, b0] - grid.u[None, :, None] * slope_u - grid.v[:, None, None] * slope_v
    return z.reshape(grid.nf * grid.mf, -1)


def plane_slopes(u: np.ndarray, v: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The slopes along u and v of the least-squares plane through heights ``z`` (n, m, ...)
    over a grid symmetric about its centre (``u`` (m,), ``v`` (n,), each summing to zero; the
    fine grid's):
    the sensor frame's tilt (reconstruction.to_sensor_frame) to first order about a flat
    sheet.  On such a grid 1, u and v are orthogonal, so each slope is one projection."""
    z = np.asarray(z)
    slope_u = np.tensordot(u, z.sum(axis=0), axes=(0, 0)) / (len(v) * float(u @ u))
    slope_v = np.tensordot(v, z.sum(axis=1), axes=(0, 0)) / (len(u) * float(v @ v))
    return slope_u, slope_v


def height_response(grid: FineGrid, valid: np.ndarray) -> np.ndarray:
    """Linear map (nf·mf, 2·N·M) from the units' turning per length to fine-node heights in the
    sensor frame (centre height and best-fit plane pinned), about the flat sheet."""
    solver, obs_t_w = grid.potential_solver(valid)
    return _heights(grid, solver.solve(obs_t_w.toarray()))


def _all_valid_response(grid: FineGrid) -> dict:
    """Row sums of squares of the all-valid height response R, and R itself on small grids."""
    base = grid.__dict__.get("_sigma_base")
    if base is None:
        r = height_response(grid, np.ones((2, grid.n, grid.m), dtype=bool))
        base = grid.__dict__["_sigma_base"] = {"rowsq": (r * r).sum(axis=1), "r": r if grid.dense_maps else None, "columns": OrderedDict()}
    return base


def _unit_columns(grid: FineGrid, base: dict, missing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R_J = R[:, J] (the all-valid height response to the missing units) and G_J = (R H)[:, J]
    (its product with the hat matrix), (nf·mf, k) each: slices on small grids, per unit and
    cached on large ones (each unit alone, so its digits do not depend on the others)."""
    lo = grid.leave_out("potential")
    if base["r"] is not None:  # small grid: R and R H whole (R H once, then slices)
        if "rh_t" not in base:  # transposed: the missing units' columns are contiguous rows
            base["r_t"] = np.ascontiguousarray(base["r"].T)
            base["rh_t"] = lo.hat @ base["r_t"]
        return base["r_t"][missing].T, base["rh_t"][missing].T
    cols = base["columns"]
    for j in dict.fromkeys(missing.tolist()):
        if j in cols:
            continue
        # one unit at a time, so that its digits do not depend on the other missing units
        jj = np.array([j])
        h_j = lo.hat_columns(jj)[:, 0]
        # R H e_j = T A⁻¹ Oᵀ (O Y_j): one more solve with the all-valid factor
        r_j = _heights(grid, lo.solution_columns(jj))[:, 0]
        g_j = _heights(grid, cast(FixedSolver, lo.solver).solve(grid.transposed("potential") @ h_j)[:, None])[:, 0]
        cols[j] = (r_j, g_j)
    for j in missing.tolist():
        cols.move_to_end(j)
    while len(cols) > max(256, missing.size):
        cols.popitem(last=False)
    return (np.stack([cols[j][0] for j in missing.tolist()], axis=1),
            np.stack([cols[j][1] for j in missing.tolist()], axis=1))


def _left_out_sums(grid: FineGrid, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(measured, missing) row sums for a mask with missing units, from the all-valid response
    by the Woodbury identity (see :mod:`.leaveout`); None when that is ill-conditioned.

    With B = R_J M the response over the valid columns V is R_V + B H[J, V], so its row sums of
    squares are |R_V|² + 2 Σ B ∘ (R_V H[V, J]) + Σ (B Q_V) ∘ B, Q_V = H[J, V] H[V, J]; each
    restricted product is the all-column one minus the J columns' part (no large cancellation:
    B enters only multiplied)."""
    missing_units = np.flatnonzero(~valid.ravel())
    lo = grid.leave_out("potential")
    try:
        m = lo.weights(missing_units)
    except IllConditioned:
        return None
    if np.abs(m).max() > 1e6:  # nearly undetermined: the product form would lose all digits
        return None
    base = _all_valid_response(grid)
    r_j, g_j = _unit_columns(grid, base, missing_units)
    h_cols = lo.hat_columns(missing_units)
    h_jj = h_cols[missing_units]
    b = r_j @ m
    g_v = g_j - r_j @ h_jj
    q_v = h_cols.T @ h_cols - h_jj @ h_jj
    missing = (r_j * r_j).sum(axis=1)
    measured = base["rowsq"] - missing + 2.0 * (b * g_v).sum(axis=1) + ((b @ q_v) * b).sum(axis=1)
    return np.maximum(measured, 0.0), missing


def _probe_sums(grid: FineGrid, valid: np.ndarray, probes: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """(measured, missing) row sums estimated with random ±1 probes (E[(Rξ)²] = Σ R²), for
    large grids when a mask had to be refactorised: 2·``probes`` solves instead of one per unit
    (relative s.d. of each node's variance about √(2/probes), 25 % for 32).  The probes are
    seeded by the mask, so the estimate is a fixed function of the inputs."""
    v = valid.ravel()
    rng = np.random.default_rng(int.from_bytes(hashlib.blake2b(valid.tobytes(), digest_size=8).digest(), "little"))
    xi = rng.choice([-1.0, 1.0], size=(v.size, probes))
    obs_t = grid.transposed("potential")
    solver, _ = grid.potential_solver(valid)  # this mask's own factor (the fields built it)
    measured = _heights(grid, solver.solve(obs_t @ np.where(v[:, None], xi, 0.0)))
    missing = _heights(grid, cast(FixedSolver, grid.leave_out("potential").solver).solve(obs_t @ np.where(v[:, None], 0.0, xi)))
    return (measured * measured).mean(axis=1), (missing * missing).mean(axis=1)


def _affine_fit(grid: FineGrid, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The least-squares affine fit over the ``valid`` unit centres (one direction, flat): its
    design D (k, 3) and pseudo-inverse D⁺ (3, k), kept per mask (a frame fits two directions);
    None for too few units to fit one."""
    cache = grid.__dict__.setdefault("_affine_fit", {})
    key = valid.tobytes()
    if key not in cache:
        uc = (np.arange(grid.m) - 0.5 * (grid.m - 1)) * grid.pitch
        vc = (np.arange(grid.n) - 0.5 * (grid.n - 1)) * grid.pitch
        design = np.stack(np.broadcast_arrays(1.0, uc[None, :], vc[:, None]), axis=-1).reshape(-1, 3)[valid]
        if len(design) <= design.shape[1]:
            cache[key] = None
        else:
            cache[key] = (design, np.linalg.pinv(design))
        if len(cache) > 16:
            cache.pop(next(iter(cache)))
    return cache[key]


def resolution_sigma(grid: FineGrid, valid: np.ndarray, turning: np.ndarray, turning_sigma: float) -> np.ndarray:
    """How far (one s.d., (nf, mf) mm) the general model's heights may be off because the sheet
    has structure at the gauge scale, which its fields cannot resolve.

    The fields reproduce a turning pattern that is affine across the sheet exactly (a gauge
    average of a linear field is its value at the gauge's centre); of any departure from that
    pattern the gauges give only averages, and how it is distributed within and between them
    the fields must guess.  So each measured unit's departure from the affine fit of its
    direction's turning, beyond the noise (``turning_sigma``, per length), is taken as an
    uncertainty of that unit's turning and propagated like the noise, through the height
    response about the flat sheet: zero on spheres, cylinders and saddles of constant
    curvature, about the feature's own height around a bump (a generous bound: the general
    model's actual error there is a tenth or less of it).  A missing unit's departure is unknown,
    as large as the largest of the measured ones (a missing unit is not taken as calm).  Dense-map grids only (the response is held
    whole, from the cached all-valid one)."""
    base = _all_valid_response(grid)
    rsq = base.get("r_sq")
    if rsq is None:
        r = base["r"] if base["r"] is not None else height_response(grid, np.ones((2, grid.n, grid.m), dtype=bool))
        rsq = base["r_sq"] = r * r
    valid = np.asarray(valid, dtype=bool).reshape(2, grid.n, grid.m)
    turning = np.asarray(turning, dtype=float).reshape(2, grid.n, grid.m)
    excess = np.zeros((2, grid.n * grid.m))
    fitted = np.zeros((2, grid.n * grid.m), dtype=bool)
    for k in range(2):
        v = valid[k].ravel()
        fit = _affine_fit(grid, v)
        if fit is None:
            continue  # too few units for a pattern: their departures stay unknown (below)
        t = turning[k].ravel()[v]
        dev = t - fit[0] @ (fit[1] @ t)
        excess[k, v] = np.maximum(dev * dev - turning_sigma**2, 0.0)
        fitted[k] = v
    if not fitted.all():
        excess[~fitted] = excess[fitted].max() if fitted.any() else 0.0
    return np.sqrt(rsq @ excess.ravel()).reshape(grid.nf, grid.mf)


def fine_sigma(
    grid: FineGrid,
    valid: np.ndarray,
    turning: np.ndarray,
    strain_sigma: float,
    h_upper: float,
    h_lower: float,
    left_out: bool = True,
    missing_spread: float | None = None,
) -> np.ndarray:
    """One-s.d. position uncertainty (nf, mf) mm of every fine node.  ``left_out``: the fields
    of this frame left the missing units out of the all-valid fit (else they refactorised the
    mask, and a large grid estimates the response with random probes instead of one solve per
    missing unit).  ``missing_spread``: the s.d. of a missing unit's turning per length (default
    the spread of the measured ones, at least a 200 mm bend radius)."""
    all_valid = valid.all()
    if all_valid:  # the usual frame: the result depends on the noise level alone
        done = grid.__dict__.setdefault("_sigma_all_valid", {})
        sigma = done.get((strain_sigma, h_upper, h_lower))
        if sigma is not None:
            return sigma
    # Per validity mask, keep only the summed squares of the response rows (the full map is
    # large for big arrays and the data enter only through one scalar below).
    cache = grid.__dict__.setdefault("_sigma_cache", {})
    key = valid.tobytes() + bytes([bool(left_out)])
    sums = cache.get(key)
    if sums is None:
        if valid.all():
            sums = (_all_valid_response(grid)["rowsq"], np.zeros(grid.nf * grid.mf))
        elif not valid.any():  # nothing measured: every unit is unknown with the spread
            sums = (np.zeros(grid.nf * grid.mf), _all_valid_response(grid)["rowsq"])
        else:
            sums = _left_out_sums(grid, valid) if left_out else None
        if sums is None and not grid.dense_maps:
            sums = _probe_sums(grid, valid)
        elif sums is None:  # the remaining data leave the fit open: a response of its own
            v = valid.ravel()
            measured = (height_response(grid, valid)[:, v] ** 2).sum(axis=1)
            r_all = _all_valid_response(grid)["r"]
            sums = (measured, (r_all[:, ~v] ** 2).sum(axis=1))
        if len(cache) > 16:
            cache.pop(next(iter(cache)))
        cache[key] = sums
    measured, missing = sums
    # turning per length = (ε_u − ε_l)/(h_u + h_l): two independent gauges
    sig_turn = np.sqrt(2.0) * strain_sigma / (h_upper + h_lower)
    var = measured * sig_turn**2
    if not all_valid:
        known = turning[valid]
        # a missing unit's turning is unknown with the spread of the measured ones (floor: a
        # 200 mm bend radius); with none measured, that of the tightest bend the sheet is
        # specified for (NO_READING_BEND_RADIUS_MM), not the flat sheet it is shown as
        spread2 = ((np.mean(known**2) if known.size else (1.0 / NO_READING_BEND_RADIUS_MM) ** 2)
                   + (1.0 / 200.0) ** 2)
        if missing_spread is not None:
            spread2 = float(missing_spread) ** 2
        var = var + missing * spread2
    # in-plane: each pitch crossed adds one stretch reading's error times the pitch
    sig_stretch = stretch_noise_sd(strain_sigma, h_upper, h_lower)
    walk = grid.__dict__.get("_sigma_walk")
    if walk is None:  # |u| + |v| times the pitch, the same every frame
        walk = grid.__dict__["_sigma_walk"] = (np.abs(grid.u)[None, :] + np.abs(grid.v)[:, None]) * grid.pitch
    sigma = np.sqrt(var.reshape(grid.nf, grid.mf) + walk * sig_stretch**2)
    if all_valid:
        sigma.flags.writeable = False  # shared by every all-valid frame at this noise level
        if len(done) > 16:
            done.pop(next(iter(done)))
        done[(strain_sigma, h_upper, h_lower)] = sigma
    return sigma
