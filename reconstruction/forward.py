"""The gauges' own forward model applied to a reconstructed surface: what each gauge would read
on it, and how far that is from what it did read.

This is the check every answer passes through (docs/reconstruction.md, "Posterior check"): the
surface is taken as it will be published (its bicubic interpolant), each gauge's two layer
curves x ± h n are traced along its material line, and their lengths are compared with the
measured strains.  It assumes nothing the model assumed (no decoupling into turning and
stretch, no small slopes, no circular arcs), so a misfit here is a misfit of the answer.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from skinmap.strains import cell_axes

from .surface import hermite_weights

__all__ = ["GaugeLayout", "Patches", "surface_strains", "misfit", "misfit_and_strains", "unit_box_mean"]

# Chords per gauge of the coarse polyline; the fine one has twice as many and Richardson's rule
# removes their common O(segment²) shortfall (a 25 mm bend: 1e-7 strain).  The coarse polyline's
# points are every other point of the fine one, so only the fine one's are evaluated.
_SEGMENTS = 6


@dataclass(frozen=True)
class GaugeLayout:
    """Where the gauges are: the sample points of every gauge's material line, built once per
    geometry.  Unit (d, i, j): direction d (0 along the rows, u; 1 along the columns, v), cell
    (i, j) centred at u_j = (j − (M−1)/2)·a, v_i = (i − (N−1)/2)·a."""

    n: int
    m: int
    gauge_length: float
    h_upper: float
    h_lower: float
    uv: np.ndarray  # (2 dirs · N · M · (2S + 1), 2) sample points of the fine polylines
    # the Hermite weights of those points per fine grid (nf, mf, origin, spacing), built on first
    # use: fixed points cost one sparse product per frame
    _weights: dict = field(default_factory=dict, compare=False, repr=False)
    # the compiled kernels (reconstruction.kernels) when the reconstruction uses them: the whole
    # forward model is then one compiled call on the patches' data (the same numbers)
    compiled: Any = field(default=None, compare=False, repr=False)

    @classmethod
    def build(cls, n: int, m: int, pitch: float, gauge_length: float, h_upper: float, h_lower: float,
              compiled: Any = None) -> "GaugeLayout":
        u_c, v_c = cell_axes(n, m, pitch)
        t = np.linspace(-0.5, 0.5, 2 * _SEGMENTS + 1) * gauge_length
        vv, uu, tt = np.meshgrid(v_c, u_c, t, indexing="ij")  # (N, M, points)
        along_u = np.stack([uu + tt, vv], axis=-1)
        along_v = np.stack([uu, vv + tt], axis=-1)
        uv = np.stack([along_u, along_v]).reshape(-1, 2)
        return cls(n, m, float(gauge_length), float(h_upper), float(h_lower), uv, compiled=compiled)

    def dense_weights(self, nf: int, mf: int, origin: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """The Hermite weights of the sample points as the compiled forward model takes them:
        (each point's patch corner as a flat node index, (points, 3, 16) weights), cached."""
        key = ("dense", nf, mf, float(origin[0]), float(origin[1]), spacing)
        hit = self._weights.get(key)
        if hit is None:
            rows = hermite_weights(nf, mf, origin, spacing, self.uv)
            cols = rows[0].indices.reshape(-1, 16)
            weights = np.ascontiguousarray(np.stack([w.data.reshape(-1, 16) for w in rows], axis=1))
            hit = self._weights[key] = ((cols[:, 0] // 4).astype(np.intp), weights)
        return hit


class Patches:
    """A candidate surface's bicubic patch data alone (what the forward model reads), from fine
    positions (nf, mf, 3) by the compiled kernels: the numbers :class:`~.surface.Surface` would
    hold, without building one for a candidate that is only weighed against the gauges."""

    def __init__(self, positions: np.ndarray, fine_u: np.ndarray, fine_v: np.ndarray, compiled: Any):
        self._spacing = float(fine_u[1] - fine_u[0])
        pos_t = np.ascontiguousarray(np.asarray(positions, dtype=float).transpose(2, 0, 1))
        nf, mf = pos_t.shape[1:]
        self._coeffs = np.empty((nf, mf, 4, 3))
        slopes = np.empty((2, 3, nf, mf))
        compiled.hermite_coefficients(pos_t, self._spacing, self._coeffs, slopes[0], slopes[1])
        self._origin = np.array([fine_u[0], fine_v[0]])

    def _uv_origin(self) -> np.ndarray:
        return self._origin


def surface_strains(surface, layout: GaugeLayout) -> tuple[np.ndarray, np.ndarray]:
    """Upper- and lower-layer strains (2, N, M) each that the gauges would read on ``surface``
    (anything with ``locate(uv) → (positions, normals)``)."""
    coeffs = getattr(surface, "_coeffs", None)
    if layout.compiled is not None and coeffs is not None:
        nf, mf = coeffs.shape[:2]
        base, weights = layout.dense_weights(nf, mf, surface._uv_origin(), surface._spacing)
        shape = (2, layout.n, layout.m)
        fu, fl = np.empty(shape), np.empty(shape)
        layout.compiled.gauge_strains(coeffs.reshape(nf * mf, 4, 3), base, mf, weights, 2 * _SEGMENTS + 1,
                                      layout.h_upper, layout.h_lower, layout.gauge_length, fu.reshape(-1),
                                      fl.reshape(-1))
        return fu, fl
    pos, nrm = _locate(surface, layout)
    per = pos.shape[0] // (2 * layout.n * layout.m)
    pos = pos.reshape(2, layout.n, layout.m, per, 3)
    nrm = nrm.reshape(2, layout.n, layout.m, per, 3)
    out = []
    for h in (layout.h_upper, -layout.h_lower):
        layer = pos + h * nrm
        d = np.diff(layer, axis=3)  # (2, N, M, per − 1, 3)
        fine = np.sqrt((d * d).sum(axis=4)).sum(axis=3)
        d2 = d[..., 0::2, :] + d[..., 1::2, :]  # chords over every other point: the coarse line
        coarse = np.sqrt((d2 * d2).sum(axis=4)).sum(axis=3)
        length = (4.0 * fine - coarse) / 3.0
        out.append(length / layout.gauge_length - 1.0)
    return out[0], out[1]


def _locate(surface, layout: GaugeLayout) -> tuple[np.ndarray, np.ndarray]:
    """Positions and unit normals of the layout's points on ``surface``: by the cached sparse
    Hermite weights for a :class:`~.surface.Surface`, else through its ``locate``."""
    coeffs = getattr(surface, "_coeffs", None)
    if coeffs is None:
        return surface.locate(layout.uv)
    nf, mf = coeffs.shape[:2]
    origin = surface._uv_origin()
    key = (nf, mf, float(origin[0]), float(origin[1]), surface._spacing)
    weights = layout._weights.get(key)
    if weights is None:
        weights = layout._weights[key] = hermite_weights(nf, mf, origin, surface._spacing, layout.uv)
    flat = coeffs.reshape(nf * mf * 4, 3)
    pos, d_u, d_v = (w @ flat for w in weights)
    normal = np.cross(d_u, d_v)
    normal /= np.sqrt((normal * normal).sum(axis=1))[:, None]
    return pos, normal


def misfit(surface, layout: GaugeLayout, eps_upper: np.ndarray, eps_lower: np.ndarray, strain_sigma: float) -> tuple[float, int, np.ndarray]:
    """χ² of the measured strains against those the surface predicts, with independent noise of
    s.d. ``strain_sigma`` on every gauge; NaN gauges are left out.  Returns (χ², gauges counted,
    per-gauge normalised residuals (2 layers, 2, N, M), NaN where left out)."""
    fu, fl = surface_strains(surface, layout)
    return _chi2(fu, fl, eps_upper, eps_lower, strain_sigma)


def misfit_and_strains(surface, layout: GaugeLayout, eps_upper: np.ndarray, eps_lower: np.ndarray,
                       strain_sigma: float) -> tuple[float, int, np.ndarray, np.ndarray]:
    """As :func:`misfit`, returning (χ², gauges counted, upper strains, lower strains) read on
    the surface (for a caller that uses them again)."""
    fu, fl = surface_strains(surface, layout)
    chi2, count, _ = _chi2(fu, fl, eps_upper, eps_lower, strain_sigma)
    return chi2, count, fu, fl


def _chi2(fu, fl, eps_upper, eps_lower, strain_sigma: float) -> tuple[float, int, np.ndarray]:
    # (written in place, and every gauge's term summed in the same order as the mask would
    # take them where none is missing: a frame reads three or four answers)
    r = np.empty((2,) + np.shape(fu))
    np.subtract(fu, eps_upper, out=r[0])
    np.subtract(fl, eps_lower, out=r[1])
    r /= strain_sigma
    counted = np.isfinite(r)
    if counted.all():
        return float(np.square(r.reshape(-1)).sum()), r.size, r
    return float(np.square(r[counted]).sum()), int(counted.sum()), r


def unit_box_mean(values: np.ndarray, width: int) -> np.ndarray:
    """Each gauge's value (directions first: (2, N, M)) averaged with those of its kind (the
    same direction) over the ``width`` × ``width`` units about it, those beyond the sheet's edge
    or not finite (a missing gauge) left out; a missing gauge stays NaN."""
    values = np.asarray(values, dtype=float)
    if width < 1 or width % 2 == 0:
        raise ValueError(f"width must be an odd number of units >= 1, got {width!r}")
    finite = np.isfinite(values)
    out = np.full(values.shape, np.nan)
    for k in range(values.shape[0]):
        weight = uniform_filter(finite[k].astype(float), size=width, mode="constant", cval=0.0)
        total = uniform_filter(np.where(finite[k], values[k], 0.0), size=width, mode="constant", cval=0.0)
        out[k] = np.where(finite[k], total / np.where(finite[k], weight, 1.0), np.nan)
    return out
