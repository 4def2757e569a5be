"""The reconstructed surface: nodes, normals, dense points and fast location of any material point."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp

from .linalg import cross_t

__all__ = ["Surface", "Diagnostics", "hermite_patch_eval", "hermite_grid_eval", "hermite_weights"]

# Points per block in locate(): the Hermite evaluation holds ~50 floats per point.
_LOCATE_CHUNK = 16384
# cyclic component shifts for a cross product: (a × b)_i = a_{i+1} b_{i+2} − a_{i+2} b_{i+1}
_SHIFT1 = np.array([1, 2, 0])
_SHIFT2 = np.array([2, 0, 1])


@dataclass
class Diagnostics:
    """How the solve went."""

    iterations: int  # fixed-point passes of the shear estimate + rotation corrections
    residual: float  # RMS misfit of the fitted fields to the decoupled gauge data (rad per gauge)
    solve_time: float  # seconds, strains in to surface out
    status: str  # "solved", or a note such as "no valid gauge"
    twist_constant: float = 0.0  # constant twist chosen from the Gauss equation (1/mm)
    valid_units: int = 0
    extra: dict = field(default_factory=dict)
    # gauges the robust screen found contradicted by the rest of the frame and left out of the
    # fit, named with their apparent gain ("" if none; reconstruction/robust.py)
    suspect_gauges: str = ""


def slopes(f: np.ndarray, h: float, axis: int) -> np.ndarray:
    """Fourth-order finite-difference derivative of node fields along ``axis`` (−1: u, −2: v),
    one-sided fourth-order stencils on the two nodes nearest each edge.  The Hermite patches
    take their slopes from here: with central differences of second order, and first order at
    the edges, the normals of a 40 mm bend came out tens of mrad off in the outer patches,
    where the outer gauges lie (fields need at least five nodes per line)."""
    g = np.moveaxis(f, axis, -1)
    out = np.empty_like(g)
    out[..., 2:-2] = (g[..., :-4] - g[..., 4:]) + 8.0 * (g[..., 3:-1] - g[..., 1:-3])
    out[..., 0] = -25.0 * g[..., 0] + 48.0 * g[..., 1] - 36.0 * g[..., 2] + 16.0 * g[..., 3] - 3.0 * g[..., 4]
    out[..., 1] = -3.0 * g[..., 0] - 10.0 * g[..., 1] + 18.0 * g[..., 2] - 6.0 * g[..., 3] + g[..., 4]
    out[..., -1] = 25.0 * g[..., -1] - 48.0 * g[..., -2] + 36.0 * g[..., -3] - 16.0 * g[..., -4] + 3.0 * g[..., -5]
    out[..., -2] = 3.0 * g[..., -1] + 10.0 * g[..., -2] - 18.0 * g[..., -3] + 6.0 * g[..., -4] - g[..., -5]
    out *= 1.0 / (12.0 * h)
    return np.moveaxis(out, -1, axis)


def _hermite_basis(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic Hermite basis (h00, h10, h01, h11) and derivatives, each (K, 4)."""
    t2 = t * t
    t3 = t2 * t
    h = np.empty(t.shape + (4,))
    dh = np.empty(t.shape + (4,))
    h[..., 2] = 3.0 * t2 - 2.0 * t3
    h[..., 0] = 1.0 - h[..., 2]
    h[..., 1] = t3 - 2.0 * t2 + t
    h[..., 3] = t3 - t2
    dh[..., 2] = 6.0 * (t - t2)
    dh[..., 0] = -dh[..., 2]
    dh[..., 1] = 3.0 * t2 - 4.0 * t + 1.0
    dh[..., 3] = 3.0 * t2 - 2.0 * t
    return h, dh


# Corner c = 2·da + db of a patch, quantity q = value, ∂u, ∂v, ∂uv (q = qu + 2·qv): the u-basis
# index is 2·db + qu, the v-basis index 2·da + qv.
_IU = np.array([[0, 1, 0, 1], [2, 3, 2, 3], [0, 1, 0, 1], [2, 3, 2, 3]]).ravel()
_IV = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 3, 3], [2, 2, 3, 3]]).ravel()
# Rows position, ∂/∂u, ∂/∂v of the patch weights, as columns of the basis row [h (4), dh (4)]
# of u (first) and of v (second): ∂/∂u takes dh of u, ∂/∂v dh of v.
_W_U = np.stack([_IU, _IU + 4, _IU])
_W_V = np.stack([_IV, _IV, _IV + 4])
_POWERS = np.arange(4.0)
# [1, t, t², t³] @ _HERMITE = [h00, h10, h01, h11, and their derivatives]
_HERMITE = np.array([
    [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0, -6.0, -4.0, 6.0, -2.0],
    [-3.0, -2.0, 3.0, -1.0, 6.0, 3.0, -6.0, 3.0],
    [2.0, 1.0, -2.0, 1.0, 0.0, 0.0, 0.0, 0.0],
])


def _patch_cells(uv: np.ndarray, origin: np.ndarray, inv_spacing: float, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Patch (column b, row a) of every point (K, 2) and its local coordinates in [0, 1] (K, 2);
    ``last`` = (mf − 2, nf − 2) clamps the points on the far edges into the last patch."""
    xy = (uv - origin) * inv_spacing
    cell = xy.astype(np.intp)  # xy >= 0 on the sheet (up to rounding): truncation is floor
    np.minimum(np.maximum(cell, 0, out=cell), last, out=cell)
    return cell, xy - cell


def hermite_patch_eval(
    coeffs: np.ndarray, u0: float, v0: float, spacing: float, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bicubic Hermite interpolation on a uniform grid.

    ``coeffs`` (nf, mf, 4, 3): value and the u, v, uv derivatives (scaled by the spacing) at each
    node.  Returns positions, ∂/∂u and ∂/∂v at ``uv`` (K, 2).
    """
    out = _hermite_eval(coeffs, np.array([u0, v0]), spacing, uv)
    return out[:, 0], out[:, 1], out[:, 2]


def hermite_weights(nf: int, mf: int, origin: np.ndarray, spacing: float, uv: np.ndarray) -> list[sp.csr_matrix]:
    """The bicubic Hermite evaluation at fixed points ``uv`` (K, 2) as three sparse (K, nf·mf·4)
    matrices (position, ∂/∂u, ∂/∂v), to multiply with the node coefficients reshaped to
    (nf·mf·4, 3): points that never move (the gauges') then cost one sparse product per frame
    (the same numbers as :func:`_hermite_eval`, 16 entries a row)."""
    cell, t = _patch_cells(uv, origin, 1.0 / spacing, np.array([mf - 2, nf - 2]))
    basis = (t[:, :, None] ** _POWERS) @ _HERMITE
    basis[:, :, 4:] *= 1.0 / spacing
    w = basis[:, 0][:, _W_U] * basis[:, 1][:, _W_V]  # (K, 3, 16)
    p = cell[:, 1] * mf + cell[:, 0]
    corners = p[:, None] + np.array([0, 1, mf, mf + 1])
    cols = (corners[:, :, None] * 4 + np.arange(4)).reshape(-1, 16)
    rows = np.repeat(np.arange(uv.shape[0]), 16)
    shape = (uv.shape[0], nf * mf * 4)
    return [sp.csr_matrix((w[:, k].ravel(), (rows, cols.ravel())), shape=shape) for k in range(3)]


def _hermite_eval(coeffs: np.ndarray, origin: np.ndarray, spacing: float, uv: np.ndarray) -> np.ndarray:
    """(K, 3, 3): position, ∂/∂u, ∂/∂v of every point; a handful of array operations whatever
    K is (the per-call overhead dominates for the few points of a frame)."""
    nf, mf = coeffs.shape[:2]
    cell, t = _patch_cells(uv, origin, 1.0 / spacing, np.array([mf - 2, nf - 2]))
    basis = (t[:, :, None] ** _POWERS) @ _HERMITE  # (K, 2, 8): h and dh of u, then of v
    basis[:, :, 4:] *= 1.0 / spacing
    w = basis[:, 0][:, _W_U] * basis[:, 1][:, _W_V]  # (K, 3, 16)
    p = cell[:, 1] * mf + cell[:, 0]
    corners = p[:, None] + np.array([0, 1, mf, mf + 1])
    c = coeffs.reshape(nf * mf, 12)[corners].reshape(-1, 16, 3)
    return w @ c


@lru_cache(maxsize=32)
def _regular_basis(n_nodes: int, start: float, step: float, count: int) -> sp.csr_matrix:
    """Sparse (count, 2·n_nodes) Hermite basis of ``count`` regular samples ``step`` apart from
    ``start`` (in grid-spacing units) along one axis: column 2·node + q, q = value, derivative."""
    x = start + step * np.arange(count)
    k = np.clip(x.astype(int), 0, n_nodes - 2)
    h, _ = _hermite_basis(x - k)
    cols = np.stack([2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3], axis=1)
    rows = np.repeat(np.arange(count), 4)
    return sp.csr_matrix((h.ravel(), (rows, cols.ravel())), shape=(count, 2 * n_nodes))


def hermite_grid_eval(coeffs: np.ndarray, basis_u: sp.csr_matrix, basis_v: sp.csr_matrix) -> np.ndarray:
    """Positions (Kv·Ku, 3) on a regular sample grid (v-major), from the separable bicubic
    Hermite form P = B_v D B_uᵀ per coordinate: two sparse products, four terms per sample and
    axis, instead of a per-point patch evaluation."""
    nf, mf = coeffs.shape[:2]
    # D[2a + qv, 2b + qu] = coeffs[a, b, qu + 2 qv]
    d = coeffs.reshape(nf, mf, 2, 2, 3).transpose(1, 3, 0, 2, 4).reshape(2 * mf, 2 * nf * 3)
    y = basis_u @ d  # (Ku, 2nf·3)
    ku = y.shape[0]
    y = y.reshape(ku, 2 * nf, 3).transpose(1, 0, 2).reshape(2 * nf, ku * 3)
    return (basis_v @ y).reshape(-1, 3)


@dataclass(frozen=True)
class FrameState:
    """What a frame leaves for the next one to start from (pass its :class:`Surface` as
    ``previous``): the accepted height-graph coefficients and those of the frame before, from
    which a moving shape is predicted, and the general model's defect correction, from which
    the next frame's starts.  None of it changes the answer of a frame that starts cold
    (``graph_warm=False``), so a log replays bit for bit from such a frame."""

    graph: np.ndarray | None = None
    graph_before: np.ndarray | None = None
    # the graph chain's yardstick: its last cold fit's objective, or the lowest since
    # (reconstructor.WARM_BASIN_YARDSTICKS); a warm fit far above it has followed another basin
    # (reconstructor.WARM_BASIN_RATIO)
    graph_reference: float = math.inf
    graph_objective: float = math.inf  # this frame's graph fit's objective (data misfit and prior)
    # the lowest objective the graph chain has reached since its last cold fit or linear start
    # (whatever its yardstick): a warm fit that has climbed far above it descends the frame's
    # linear start too (reconstructor.WARM_CLIMB_RATIO)
    graph_lowest: float = math.inf
    position: np.ndarray | None = None  # the position fit's coefficients (elastic prior on)
    # the general model's defect correction, (2, 2, N, M): what its answer's input added to the
    # measured strains (upper, lower layer), that answer's χ² against the gauges, and the
    # measured strains themselves (whether the next frame's sheet held still)
    defect: np.ndarray | None = None
    defect_chi2: float = math.inf
    strains: np.ndarray | None = None


class Surface:
    """A reconstructed sheet in the sensor frame (:func:`~skinmap.reconstruction.to_sensor_frame`:
    the centre node at the origin, the sheet's best-fit plane z = 0 with +z towards its upper
    side, the rows' mean direction along +x; mm).

    Attributes
    ----------
    nodes : (N, M, 3) cell-centre positions.
    normals : (N, M, 3) unit normals towards the upper side.
    node_sigma : (N, M) one-s.d. position uncertainty (mm): the strain noise carried through the
        fit, raised where gauges are missing, where the answer misfits the gauges, where the twist
        is read only within an interval, and by the model's gauge-scale resolution (a bound on a
        bias no repeated frame shows).  It describes the error in the sensor frame and after a
        reference's best rigid fit over the nodes alike: no node, the frame's pinned centre
        included, is given less than the mean over the nodes of its parts but the twist's
        spread (``reconstruction.uncertainty.alignment_floor``).
    node_scatter_sigma : (N, M) the part of ``node_sigma`` that repeated frames of a still sheet
        scatter by in the sensor frame: ``node_sigma`` without the resolution term and the
        alignment floor (zero at the centre node, the frame's origin).
    diagnostics : :class:`Diagnostics`.
    mirror : the other answer (a :class:`Surface`) when the gauges cannot tell two mirror-image
        shapes apart (an oblique cylinder, a saddle at 45°: opposite constant twists), else None;
        ``diagnostics.extra["ambiguous"]`` says the same.
    state : :class:`FrameState`, what the next frame starts from (when this surface is passed
        as its ``previous``).
    pitch, shape : grid pitch (mm) and (N, M).

    Methods: :meth:`locate` (positions and normals of material points), :meth:`locate_sigma`,
    :meth:`points` (dense cloud), :attr:`extent` (accepted material range).
    """

    def __init__(
        self,
        *,
        pitch: float,
        fine_u: np.ndarray,
        fine_v: np.ndarray,
        fine_positions: np.ndarray,
        node_index: tuple[np.ndarray, np.ndarray],
        fine_sigma: Callable[[], np.ndarray],
        diagnostics: Diagnostics,
        compiled: Any = None,
        fine_derivatives: np.ndarray | None = None,
    ):
        self.pitch = float(pitch)
        self._u, self._v = fine_u, fine_v
        self._spacing = float(fine_u[1] - fine_u[0])
        h = self._spacing
        # components first ((3, nf, mf), free when the positions come from the engine): every
        # difference below is then one operation on contiguous rows
        pos_t = np.ascontiguousarray(np.asarray(fine_positions, dtype=float).transpose(2, 0, 1))
        nf, mf = pos_t.shape[1:]
        self._coeffs = np.empty((nf, mf, 4, 3))
        rows, cols = node_index
        self.shape = (rows.size, cols.size)
        if fine_derivatives is None and compiled is not None:
            # reconstruction.kernels: the same numbers as the differences below in one compiled
            # call, and the nodes and normals as the steps after the branch take them
            d_u, d_v = np.empty((3, nf, mf)), np.empty((3, nf, mf))
            compiled.hermite_coefficients(pos_t, h, self._coeffs, d_u, d_v)
            self.nodes, self.normals = np.empty(self.shape + (3,)), np.empty(self.shape + (3,))
            compiled.node_frames(pos_t, d_u, d_v, rows, cols, self.nodes, self.normals)
        else:
            if fine_derivatives is not None:
                # the model's own ∂u, ∂v, ∂u∂v at the nodes (a graph's: what it holds between them)
                d_u, d_v, d_uv = np.asarray(fine_derivatives, dtype=float).transpose(0, 3, 1, 2)  # each (3, nf, mf)
            else:
                d_u = slopes(pos_t, h, -1)
                d_v = slopes(pos_t, h, -2)
                d_uv = slopes(d_u, h, -2)
            coeffs = self._coeffs.transpose(2, 3, 0, 1)  # (4, 3, nf, mf) view: written in place
            coeffs[0] = pos_t
            np.multiply(d_u, h, out=coeffs[1])
            np.multiply(d_v, h, out=coeffs[2])
            np.multiply(d_uv, h * h, out=coeffs[3])
            at_nodes = (slice(None), rows[:, None], cols[None, :])
            self.nodes = pos_t[at_nodes].transpose(1, 2, 0).copy()
            normal_t = cross_t(d_u[at_nodes], d_v[at_nodes])
            normal_t /= np.sqrt((normal_t * normal_t).sum(axis=0))
            self.normals = normal_t.transpose(1, 2, 0).copy()
        self._node_index = node_index
        self._fine_sigma_fn = fine_sigma
        self._fine_sigma: np.ndarray | None = None
        # the part of σ that repeated frames scatter by, where σ holds more (None: all of σ)
        self._scatter_sigma_fn: Callable[[], np.ndarray] | None = None
        self._scatter_sigma: np.ndarray | None = None
        self._uv_bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._origin: np.ndarray | None = None
        self.diagnostics = diagnostics
        # the mirror-image answer when the data cannot tell the two apart, else None
        self.mirror: Surface | None = None
        self.state = FrameState()

    # ------------------------------------------------------------------ uncertainty (lazy)
    @property
    def fine_sigma(self) -> np.ndarray:
        if self._fine_sigma is None:
            self._fine_sigma = self._fine_sigma_fn()
        return self._fine_sigma

    @property
    def node_sigma(self) -> np.ndarray:
        """(N, M) one-s.d. position uncertainty of the nodes (mm)."""
        return self._at_nodes(self._sigma_at)

    @property
    def scatter_sigma(self) -> np.ndarray:
        """(nf, mf) fine-node map of the part of σ that repeated frames scatter by."""
        if self._scatter_sigma_fn is None:
            return self.fine_sigma
        if self._scatter_sigma is None:
            self._scatter_sigma = self._scatter_sigma_fn()
        return self._scatter_sigma

    @property
    def node_scatter_sigma(self) -> np.ndarray:
        """(N, M) the part of :attr:`node_sigma` (mm) that repeated frames of a still sheet
        scatter by in the sensor frame: the noise carried through the fit and the twist's
        reading, without the model's gauge-scale resolution term (a bound on a bias, the same
        every frame) and without the alignment floor (the frame's centre does not scatter)."""
        return self._at_nodes(self._scatter_at)

    def _at_nodes(self, read: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        rows, cols = self._node_index
        return np.array(read(rows[:, None] * len(self._u) + cols[None, :]))  # a fresh array

    def _sigma_at(self, flat: np.ndarray) -> np.ndarray:
        """σ at fine nodes of flat indices ``flat``: from the whole field once it is computed, else
        from those nodes alone where the uncertainty can (reconstruction.uncertainty.SigmaField)."""
        at = getattr(self._fine_sigma_fn, "at", None)
        if self._fine_sigma is None and at is not None:
            return at(flat)
        return self.fine_sigma.reshape(-1)[flat]

    def _scatter_at(self, flat: np.ndarray) -> np.ndarray:
        """The scatter's part of σ at fine nodes ``flat``, as :meth:`_sigma_at` reads σ."""
        if self._scatter_sigma_fn is None:
            return self._sigma_at(flat)
        at = getattr(self._scatter_sigma_fn, "at", None)
        if self._scatter_sigma is None and at is not None:
            return at(flat)
        return self.scatter_sigma.reshape(-1)[flat]

    # ----------------------------------------------------------------------------- queries
    @property
    def extent(self) -> tuple[float, float, float, float]:
        """Material coordinate bounds (u_min, u_max, v_min, v_max) that :meth:`locate` accepts."""
        return float(self._u[0]), float(self._u[-1]), float(self._v[0]), float(self._v[-1])

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Accepted (u, v) range with a rounding tolerance, as two (2,) arrays (built once)."""
        if self._uv_bounds is None:
            u0, u1, v0, v1 = self.extent
            tol = 1e-9 * max(1.0, self.pitch)
            self._uv_bounds = (np.array([u0 - tol, v0 - tol]), np.array([u1 + tol, v1 + tol]))
        return self._uv_bounds

    def _check_uv(self, uv) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        if uv.ndim != 2 or uv.shape[1] != 2:
            if uv.shape != (2,):
                raise ValueError(f"uv must be material coordinates of shape (K, 2), got {uv.shape}")
            uv = uv[None]
        lo, hi = self._bounds()
        inside = (uv >= lo) & (uv <= hi)  # false for NaN too
        if not inside.all():
            if not np.isfinite(uv).all():
                raise ValueError("uv contains NaN or infinite coordinates")
            u0, u1, v0, v1 = self.extent
            k = int(np.flatnonzero(~inside.all(axis=1))[0])
            raise ValueError(
                f"uv[{k}] = {uv[k].tolist()} is off the sheet: material coordinates must lie in "
                f"u ∈ [{u0:g}, {u1:g}], v ∈ [{v0:g}, {v1:g}] mm (half a pitch beyond the outer cells)"
            )
        return uv

    def locate(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """Positions (K, 3) and unit normals (K, 3) of material points ``uv`` (K, 2) mm.

        Bicubic Hermite patches over the fine grid (positions and their derivatives), so
        positions are C¹ and normals continuous across patches.
        """
        uv = self._check_uv(uv)
        if uv.shape[0] > _LOCATE_CHUNK:  # bound the temporaries of a dense cloud
            parts = [self.locate(uv[k : k + _LOCATE_CHUNK]) for k in range(0, uv.shape[0], _LOCATE_CHUNK)]
            return np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts])
        out = _hermite_eval(self._coeffs, self._uv_origin(), self._spacing, uv)
        # normal = ∂u × ∂v: both cyclic shifts of the two tangents in two gathers
        s1, s2 = out[:, 1:, _SHIFT1], out[:, 1:, _SHIFT2]
        normal = s1[:, 0] * s2[:, 1] - s2[:, 0] * s1[:, 1]
        normal /= np.sqrt((normal * normal).sum(axis=1))[:, None]
        return out[:, 0], normal

    def _uv_origin(self) -> np.ndarray:
        """Material coordinates (u, v) of fine node (0, 0), as a (2,) array (built once)."""
        if self._origin is None:
            self._origin = np.array([self._u[0], self._v[0]])
        return self._origin

    def locate_sigma(self, uv, scatter: bool = False) -> np.ndarray:
        """One-s.d. position uncertainty (K,) mm of material points ``uv`` (bilinear in the fine
        grid); ``scatter``: only its part that repeated frames scatter by (:attr:`node_scatter_sigma`)."""
        uv = self._check_uv(uv)
        nf, mf = len(self._v), len(self._u)
        cell, t = _patch_cells(uv, self._uv_origin(), 1.0 / self._spacing, np.array([mf - 2, nf - 2]))
        lin = np.empty(t.shape + (2,))  # (K, 2 axes, 2 ends): 1 − t, t
        lin[:, :, 1] = t
        np.subtract(1.0, t, out=lin[:, :, 0])
        w = (lin[:, 1, :, None] * lin[:, 0, None, :]).reshape(-1, 4)  # corners (da, db) v-major
        p = cell[:, 1] * mf + cell[:, 0]
        corners = p[:, None] + np.array([0, 1, mf, mf + 1])
        # corners of zero weight (points on a fine-grid line: every element row at v = 0) are
        # not read, so that a map computed node by node is asked for no more than it must
        need = w != 0.0
        sig = np.zeros(w.shape)
        sig[need] = (self._scatter_at if scatter else self._sigma_at)(corners[need])
        return (w * sig).sum(axis=1)

    def points(self, per_pitch: int = 20) -> np.ndarray:
        """Dense point cloud over the whole sheet, ``per_pitch`` points per pitch in each
        direction (400 per pitch² by default), as (K, 3)."""
        if int(per_pitch) != per_pitch or per_pitch < 1:
            raise ValueError(f"per_pitch must be a positive integer, got {per_pitch!r}")
        u0, u1, v0, v1 = self.extent
        step = self.pitch / int(per_pitch)
        count_u, count_v = int(round((u1 - u0) / step)), int(round((v1 - v0) / step))
        # samples at u0 + step·(i + ½), in grid-spacing units
        rel = step / self._spacing
        nf, mf = self._coeffs.shape[:2]
        basis_u = _regular_basis(mf, 0.5 * rel, rel, count_u)
        basis_v = _regular_basis(nf, 0.5 * rel, rel, count_v)
        return hermite_grid_eval(self._coeffs, basis_u, basis_v)

    def __repr__(self) -> str:
        d = self.diagnostics
        return f"Surface({self.shape[0]}x{self.shape[1]}, pitch={self.pitch:g} mm, status={d.status!r}, {1e3 * d.solve_time:.2f} ms)"
