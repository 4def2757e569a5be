"""The blocked banded Cholesky solve (linalg.BandCholeskyBlocks) against LAPACK's ?pbtrs, and the
large graph fit's node σ through it against the same σ through ?pbtrs."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg.lapack import dpbtrf, dpbtrs

from skinmap.reconstruction.linalg import BandCholeskyBlocks


def spd_band(n: int, kd: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A random symmetric positive definite matrix of bandwidth kd: (dense, lower band storage)."""
    rng = np.random.default_rng(seed)
    a = np.tril(rng.normal(size=(n, n)))
    a[np.tri(n, k=-kd - 1, dtype=bool)] = 0.0
    h = a @ a.T + (2.0 * kd + 1.0) * np.eye(n)  # definite, moderately conditioned; bandwidth kd
    band = np.zeros((kd + 1, n))
    for d in range(min(kd, n - 1) + 1):
        band[d, : n - d] = np.diagonal(h, -d)
    return h, band


def factor(band: np.ndarray) -> np.ndarray:
    f, info = dpbtrf(band, lower=1)
    assert info == 0
    return f


@pytest.mark.parametrize("n, kd", [(1, 0), (9, 0), (2, 1), (31, 1), (40, 8), (45, 8), (6, 9), (130, 17),
                                   (301, 64), (257, 128)])
def test_band_solve_equals_lapack_band_solve(n, kd):
    h, band = spd_band(n, kd, seed=n + 1000 * kd)
    f = factor(band)
    solver = BandCholeskyBlocks(f)
    rng = np.random.default_rng(n)
    for rhs in (rng.normal(size=n), rng.normal(size=(n, 1)), np.asfortranarray(rng.normal(size=(n, 3 + 2 * kd))),
                rng.normal(size=(n, 23))):  # one and many columns, either memory order
        kept = rhs.copy()
        x = solver.solve(rhs)
        ref = dpbtrs(f, rhs, lower=1)[0]
        assert x.shape == rhs.shape
        np.testing.assert_allclose(x, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_allclose(h @ x, rhs, rtol=1e-8, atol=1e-10 * np.abs(rhs).max())
        np.testing.assert_array_equal(rhs, kept)  # the right-hand side is left alone


def test_band_solve_takes_any_memory_order_of_the_factor_and_checks_shapes():
    _, band = spd_band(50, 7, seed=3)
    f = factor(band)
    rhs = np.random.default_rng(4).normal(size=(50, 5))
    np.testing.assert_allclose(BandCholeskyBlocks(np.ascontiguousarray(f)).solve(rhs),
                               BandCholeskyBlocks(f).solve(rhs), rtol=1e-14, atol=0.0)
    with pytest.raises(ValueError):
        BandCholeskyBlocks(f).solve(rhs[:49])
    with pytest.raises(ValueError):
        BandCholeskyBlocks(f[0])
    assert BandCholeskyBlocks(f).solve(np.zeros((50, 0))).shape == (50, 0)


def test_large_graph_node_sigma_equals_the_lapack_band_solve(monkeypatch):
    """12×12 (a band of about 200 sub-diagonals over 1521 unknowns): the node σ of a graph
    answer, the nodes' columns solved in blocks, equals the same σ solved column by column."""
    from skinmap.emulator.physics import GaussianBumps, gauge_strains
    from skinmap.reconstruction import Reconstructor
    from skinmap.reconstruction import graphfit
    from skinmap.reconstruction.engine import unit_data

    n = 12
    rec = Reconstructor(n, n)
    eu, el = gauge_strains(GaussianBumps(height=5.0, fwhm=15.0, centre=(10.0, -5.0)), n, n, 12.0,
                           rec.h_upper, rec.h_lower, rec.gauge_length)
    rng = np.random.default_rng(11)
    eu, el = eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape)
    surf = rec(eu, el)
    assert surf.diagnostics.extra["model"] == "graph"
    graph = rec._graph
    assert graph is not None and graph.size > graphfit._BAND_SIGMA_SIZE  # the band branch
    turning, stretch, valid = unit_data(eu, el, rec.h_upper, rec.h_lower, rec.gauge_length)
    sig_t = np.sqrt(2.0) * 5.7e-5 / (rec.h_upper + rec.h_lower)
    sig_s = 5.7e-5 * np.hypot(rec.h_upper, rec.h_lower) / (rec.h_upper + rec.h_lower)
    data = graph.prepare(turning, stretch, valid, sig_t, sig_s)
    grid = rec.grid
    cells = (grid.node_rows[:, None] * grid.mf + grid.node_cols[None, :]).ravel()
    nodes = np.concatenate([cells, np.random.default_rng(5).choice(grid.nf * grid.mf, 30, replace=False)])
    blocked = graph.height_sigma_at(surf.state.graph, data, 0.7, rec.grid.centre)(nodes)

    class ColumnByColumn:
        def __init__(self, f: np.ndarray) -> None:
            self.f = f

        def solve(self, rhs: np.ndarray) -> np.ndarray:
            return dpbtrs(self.f, rhs, lower=1)[0]

    monkeypatch.setattr(graphfit, "BandCholeskyBlocks", ColumnByColumn)
    reference = graph.height_sigma_at(surf.state.graph, data, 0.7, rec.grid.centre)(nodes)
    assert np.all(np.isfinite(reference)) and (reference > 0).sum() >= reference.size - 1
    np.testing.assert_allclose(blocked, reference, rtol=1e-10, atol=1e-15)
