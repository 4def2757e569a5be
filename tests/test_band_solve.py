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


def test_band_solve_sweeps_take_the_columns_begun_and_the_blocked_layout():
    """forward with ``starts`` (each column zero above its start, the sweep taking the columns
    begun) equals forward without; the blocked layout round-trips; bad arguments are refused."""
    n, kd = 301, 64
    h, band = spd_band(n, kd, seed=7)
    solver = BandCholeskyBlocks(factor(band))
    rng = np.random.default_rng(8)
    starts = np.sort(rng.integers(0, n, size=40))
    starts[:3] = 0
    rhs = rng.normal(size=(n, 40))
    rhs[np.arange(n)[:, None] < starts[None, :]] = 0.0
    y = solver.blocked(rhs)
    np.testing.assert_array_equal(solver.unblocked(y), rhs)
    assert y.shape == (solver.blocks, 40, kd)
    begun = solver.forward(solver.blocked(rhs), starts)
    every = solver.forward(solver.blocked(rhs))
    np.testing.assert_allclose(solver.unblocked(begun), solver.unblocked(every), rtol=1e-13, atol=1e-14)
    x = solver.unblocked(solver.backward(begun))
    np.testing.assert_allclose(h @ x, rhs, rtol=1e-8, atol=1e-10 * np.abs(rhs).max())
    with pytest.raises(ValueError):
        solver.forward(solver.blocked(rhs), starts[::-1])
    with pytest.raises(ValueError):
        solver.forward(np.zeros((solver.blocks, 3, kd + 1)))


def test_large_graph_node_sigma_equals_the_lapack_band_solve():
    """12×12 (a band of about 200 sub-diagonals over 1521 unknowns): the node σ of a graph
    answer, the nodes' columns solved in blocks, equals the same σ solved column by column
    with LAPACK's ?pbtrs on the same factor."""
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
    c = surf.state.graph
    blocked = graph.height_sigma_at(c, data, 0.7, rec.grid.centre)(nodes)

    # the same matrix and the dense Jacobian from the kernel, ?pbtrs column by column
    g = len(data[0])
    band = graph.prior_band.copy()
    j = np.zeros((2 * g, graph.size))
    graph._compiled.graph_normal_equations(c, graph.idx, graph.da, graph.db, graph.daa, graph.wq, *data[:4], band,
                                           np.zeros(graph.size), True, np.asarray(graph.sigma_curvature, dtype=float),
                                           np.empty(2 * g), j, np.zeros((0, 0)))
    f = factor(band)
    r = j @ dpbtrs(f, graph._frame_height_rows(nodes, rec.grid.centre).T, lower=1)[0]
    reference = 0.7 * np.sqrt(np.einsum("kp,kp->p", r, r))
    assert np.all(np.isfinite(reference)) and (reference > 0).sum() >= reference.size - 1
    np.testing.assert_allclose(blocked, reference, rtol=1e-10, atol=1e-15)
