"""The reconstructed surface: nodes, normals, dense points and fast location of any material point."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable

import numpy as np
import scipy.sparse as sp

from .linalg import cross, cross_t, diff_u_t, diff_v_t, unit

__all__ = ["Surface", "Diagnostics", "hermite_patch_eval", "hermite_grid_eval"]

# Points per block in locate(): the Hermite evaluation holds ~50 floats per point.
_LOCATE_CHUNK = 16384


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


def hermite_patch_eval(
    coeffs: np.ndarray, u0: float, v0: float, spacing: float, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bicubic Hermite interpolation on a uniform grid.

    ``coeffs`` (nf, mf, 4, 3): value and the u, v, uv derivatives (scaled by the spacing) at each
    node.  Returns positions, ∂/∂u and ∂/∂v at ``uv`` (K, 2).
    """
    nf, mf = coeffs.shape[:2]
    x = (uv[:, 0] - u0) * (1.0 / spacing)
    y = (uv[:, 1] - v0) * (1.0 / spacing)
    b = np.minimum(np.maximum(x.astype(int), 0), mf - 2)  # x >= 0 on the sheet: truncation is floor
    a = np.minimum(np.maximum(y.astype(int), 0), nf - 2)
    hs, dhs = _hermite_basis(x - b)
    ht, dht = _hermite_basis(y - a)
    p = a * mf + b
    corners = np.stack([p, p + 1, p + mf, p + mf + 1], axis=1)  # (K, 4)
    c = np.take(coeffs.reshape(nf * mf, 12), corners, axis=0).reshape(-1, 16, 3)
    wu, dwu = np.take(hs, _IU, axis=1), np.take(dhs, _IU, axis=1)  # (K, 16)
    wv, dwv = np.take(ht, _IV, axis=1), np.take(dht, _IV, axis=1)
    w = np.stack([wu * wv, dwu * wv * (1.0 / spacing), wu * dwv * (1.0 / spacing)], axis=1)  # (K, 3, 16)
    out = w @ c  # (K, 3, 3): position, ∂u, ∂v
    return out[:, 0], out[:, 1], out[:, 2]


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


class Surface:
    """A reconstructed sheet in the sensor frame (centre of the sheet at the origin, its normal
    +z, the row direction +u along +x; mm).

    Attributes
    ----------
    nodes : (N, M, 3) cell-centre positions.
    normals : (N, M, 3) unit normals towards the upper side.
    node_sigma : (N, M) one-s.d. position uncertainty (mm) from the strain noise level, raised
        where gauges are missing.
    diagnostics : :class:`Diagnostics`.
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
    ):
        self.pitch = float(pitch)
        self._u, self._v = fine_u, fine_v
        self._spacing = float(fine_u[1] - fine_u[0])
        h = self._spacing
        # components first ((3, nf, mf), free when the positions come from the engine): every
        # difference below is then one operation on contiguous rows
        pos_t = np.ascontiguousarray(np.asarray(fine_positions, dtype=float).transpose(2, 0, 1))
        d_u = diff_u_t(pos_t, h)
        d_v = diff_v_t(pos_t, h)
        coeffs = np.stack([pos_t, h * d_u, h * d_v, (h * h) * diff_v_t(d_u, h)])  # (4, 3, nf, mf)
        self._coeffs = np.ascontiguousarray(coeffs.transpose(2, 3, 0, 1))  # (nf, mf, 4, 3)
        rows, cols = node_index
        self.shape = (rows.size, cols.size)
        at_nodes = (slice(None), rows[:, None], cols[None, :])
        self.nodes = pos_t[at_nodes].transpose(1, 2, 0).copy()
        normal_t = cross_t(d_u[at_nodes], d_v[at_nodes])
        normal_t /= np.sqrt((normal_t * normal_t).sum(axis=0))
        self.normals = normal_t.transpose(1, 2, 0).copy()
        self._node_index = node_index
        self._fine_sigma_fn = fine_sigma
        self._fine_sigma: np.ndarray | None = None
        self.diagnostics = diagnostics

    # ------------------------------------------------------------------ uncertainty (lazy)
    @property
    def fine_sigma(self) -> np.ndarray:
        if self._fine_sigma is None:
            self._fine_sigma = self._fine_sigma_fn()
        return self._fine_sigma

    @property
    def node_sigma(self) -> np.ndarray:
        """(N, M) one-s.d. position uncertainty of the nodes (mm)."""
        rows, cols = self._node_index
        return self.fine_sigma[np.ix_(rows, cols)].copy()

    # ----------------------------------------------------------------------------- queries
    @property
    def extent(self) -> tuple[float, float, float, float]:
        """Material coordinate bounds (u_min, u_max, v_min, v_max) that :meth:`locate` accepts."""
        return float(self._u[0]), float(self._u[-1]), float(self._v[0]), float(self._v[-1])

    def _check_uv(self, uv) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        if uv.ndim == 1 and uv.shape == (2,):
            uv = uv[None]
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uv must be material coordinates of shape (K, 2), got {uv.shape}")
        u0, u1, v0, v1 = self.extent
        tol = 1e-9 * max(1.0, self.pitch)
        lo, hi = np.array([u0 - tol, v0 - tol]), np.array([u1 + tol, v1 + tol])
        inside = (uv >= lo) & (uv <= hi)  # false for NaN too
        if not inside.all():
            if not np.isfinite(uv).all():
                raise ValueError("uv contains NaN or infinite coordinates")
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
        p, pu, pv = hermite_patch_eval(self._coeffs, self._u[0], self._v[0], self._spacing, uv)
        return p, unit(cross(pu, pv))

    def locate_sigma(self, uv) -> np.ndarray:
        """One-s.d. position uncertainty (K,) mm of material points ``uv`` (bilinear in the fine grid)."""
        uv = self._check_uv(uv)
        sig = self.fine_sigma
        x = (uv[:, 0] - self._u[0]) / self._spacing
        y = (uv[:, 1] - self._v[0]) / self._spacing
        b = np.clip(np.floor(x).astype(int), 0, sig.shape[1] - 2)
        a = np.clip(np.floor(y).astype(int), 0, sig.shape[0] - 2)
        s, t = x - b, y - a
        return (
            (1 - s) * (1 - t) * sig[a, b] + s * (1 - t) * sig[a, b + 1] + (1 - s) * t * sig[a + 1, b] + s * t * sig[a + 1, b + 1]
        )

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
