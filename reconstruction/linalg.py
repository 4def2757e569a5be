"""Small numerical helpers: grid differences, vectors, rotations, and cached solvers for fixed
sparse symmetric systems."""
from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp

__all__ = ["diff_u", "diff_v", "edge_mean", "exp_so3", "cross", "unit", "FixedSolver", "DowndatedSolver"]

# Below this size a dense pseudo-inverse is faster to apply than banded triangular solves
# (Python overhead dominates); above it the banded factor wins on memory and time.
_DENSE_LIMIT = 200


def diff_u(f: np.ndarray, h: float) -> np.ndarray:
    """∂/∂u by central differences (one-sided at the edges), like np.gradient but cheaper."""
    out = np.empty_like(f)
    out[:, 1:-1] = (f[:, 2:] - f[:, :-2]) / (2.0 * h)
    out[:, 0] = (f[:, 1] - f[:, 0]) / h
    out[:, -1] = (f[:, -1] - f[:, -2]) / h
    return out


def diff_v(f: np.ndarray, h: float) -> np.ndarray:
    """∂/∂v by central differences (one-sided at the edges)."""
    out = np.empty_like(f)
    out[1:-1] = (f[2:] - f[:-2]) / (2.0 * h)
    out[0] = (f[1] - f[0]) / h
    out[-1] = (f[-1] - f[-2]) / h
    return out


def edge_mean(f: np.ndarray, axis: int) -> np.ndarray:
    """Mean of the two end values of every grid edge along ``axis`` (0: v-edges, 1: u-edges)."""
    return 0.5 * (f[:-1] + f[1:]) if axis == 0 else 0.5 * (f[:, :-1] + f[:, 1:])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product along the last axis (np.cross's axis handling costs more than the
    arithmetic on the small arrays here)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def unit(v: np.ndarray) -> np.ndarray:
    """Vectors along the last axis scaled to unit length."""
    return v / np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th2 = np.einsum("...i,...i->...", w, w)
    th = np.sqrt(th2)
    small = th2 < 1e-12
    safe = np.where(small, 1.0, th)
    # Taylor series below 1e-6 rad keeps full precision where sin(x)/x loses it
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    out = np.empty(w.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1.0 - b * (y * y + z * z)
    out[..., 1, 1] = 1.0 - b * (x * x + z * z)
    out[..., 2, 2] = 1.0 - b * (x * x + y * y)
    out[..., 0, 1] = b * x * y - a * z
    out[..., 1, 0] = b * x * y + a * z
    out[..., 0, 2] = b * x * z + a * y
    out[..., 2, 0] = b * x * z - a * y
    out[..., 1, 2] = b * y * z - a * x
    out[..., 2, 1] = b * y * z + a * x
    return out


class FixedSolver:
    """Solves A x = b for one fixed symmetric positive semi-definite sparse A (regularised by a
    tiny multiple of a null-space penalty), many right-hand sides.

    Small systems keep the dense pseudo-inverse (eigenvalues below ``rtol``·max dropped, so the
    solution is the least-norm one, free of the regularisation); one solve is then a single
    matrix product.  Large systems are grid operators with natural (row-major) ordering, so a
    banded Cholesky factor (bandwidth ~ a few grid rows) fills in far less than a general
    sparse LU and solves in O(n·bandwidth).
    """

    def __init__(self, a: sp.spmatrix, rtol: float = 1e-9):
        a = sp.csc_matrix(a)
        if a.shape[0] != a.shape[1]:
            raise ValueError(f"matrix must be square, got {a.shape}")
        self.size = a.shape[0]
        if self.size <= _DENSE_LIMIT:
            w, v = scipy.linalg.eigh(a.toarray(), check_finite=False)
            keep = w > rtol * w[-1]
            self._pinv = (v[:, keep] / w[keep]) @ v[:, keep].T
            self._lu = None
        else:
            self._pinv = None
            coo = a.tocoo()
            upper = coo.col >= coo.row
            rows, cols, vals = coo.row[upper], coo.col[upper], coo.data[upper]
            bw = int((cols - rows).max()) if vals.size else 0
            ab = np.zeros((bw + 1, self.size))
            np.add.at(ab, (bw + rows - cols, cols), vals)
            self._band = scipy.linalg.cholesky_banded(ab, lower=False, check_finite=False)

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=float)
        if self._pinv is not None:
            return self._pinv @ b
        return scipy.linalg.cho_solve_banded((self._band, False), b, check_finite=False)


class DowndatedSolver:
    """Solves (A − Oᵀ O) x = b given a :class:`FixedSolver` for A and a few rows O (k × n):
    the normal matrix of a least-squares fit with k data rows removed (missing gauges), by the
    Woodbury identity, so a dead gauge costs k extra solves instead of a new factorisation."""

    def __init__(self, base: FixedSolver, rows: np.ndarray):
        self.base = base
        self.rows = np.atleast_2d(np.asarray(rows, dtype=float))
        self.y = base.solve(self.rows.T)  # A⁻¹ Oᵀ, (n, k)
        cap = np.eye(self.rows.shape[0]) - self.rows @ self.y
        if np.linalg.cond(cap) > 1e10:
            raise np.linalg.LinAlgError("removing these rows leaves the system singular")
        self.cap_inv = np.linalg.inv(cap)
        self.size = base.size

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = self.base.solve(b)
        return x + self.y @ (self.cap_inv @ (self.rows @ x))
