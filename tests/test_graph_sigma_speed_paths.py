"""The large graph fit's node σ (GraphFit.height_sigma_at above 8×8: band factor, the nodes' heights
swept from their first coefficient, the frame's forms combined after the forward sweep, J by each
gauge's own coefficients, the right-hand sides kept by node set) against a straightforward
reference: dense J from the numpy model, dense H = JᵀJ + P, σ_p = |J H⁻¹ s_p| by a dense solve."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.emulator.physics import GaussianBumps, gauge_strains
from skinmap.reconstruction import Reconstructor, graphfit
from skinmap.reconstruction.engine import unit_data

NOISE = 5.7e-5


@pytest.fixture(scope="module")
def answer():
    """A 12×12 graph answer (a sharp bump, noisy): (reconstructor, graph fit, coefficients, data, nodes)."""
    n = 12
    rec = Reconstructor(n, n)
    eu, el = gauge_strains(GaussianBumps(height=5.0, fwhm=15.0, centre=(10.0, -5.0)), n, n, 12.0,
                           rec.h_upper, rec.h_lower, rec.gauge_length)
    rng = np.random.default_rng(11)
    eu, el = eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape)
    surf = rec(eu, el)
    assert surf.diagnostics.extra["model"] == "graph"
    graph = rec._graph
    assert graph is not None and graph.size > graphfit._BAND_SIGMA_SIZE  # the band branch
    turning, stretch, valid = unit_data(eu, el, rec.h_upper, rec.h_lower, rec.gauge_length)
    sig_t = np.sqrt(2.0) * NOISE / (rec.h_upper + rec.h_lower)
    sig_s = NOISE * np.hypot(rec.h_upper, rec.h_lower) / (rec.h_upper + rec.h_lower)
    data = graph.prepare(turning, stretch, valid, sig_t, sig_s)
    grid = rec.grid
    cells = (grid.node_rows[:, None] * grid.mf + grid.node_cols[None, :]).ravel()
    nodes = np.concatenate([cells, np.random.default_rng(5).choice(grid.nf * grid.mf, 30, replace=False)])
    return rec, graph, np.array(surf.state.graph), data, nodes


def dense_reference(graph, c: np.ndarray, data: tuple, noise_ratio: float, centre, nodes: np.ndarray) -> np.ndarray:
    """σ_p = noise_ratio · |J H⁻¹ s_p|, everything dense from the numpy reference model."""
    turning, stretch, w_t, w_s = data[:4]
    g = len(turning)
    j, res = graph._numpy_jacobian(c, turning, stretch, w_t, w_s)
    h = graph._numpy_matrix(c, j, res[g:], w_s, graph.sigma_curvature)  # JᵀJ + P (+ the curvature share)
    s = graph._frame_height_rows(nodes, centre)
    r = j @ np.linalg.solve(h, s.T)
    return noise_ratio * np.sqrt((r * r).sum(axis=0))


def test_large_node_sigma_equals_the_dense_reference(answer):
    rec, graph, c, data, nodes = answer
    fast = graph.height_sigma_at(c, data, 0.7, rec.grid.centre)(nodes)
    reference = dense_reference(graph, c, data, 0.7, rec.grid.centre, nodes)
    assert np.all(np.isfinite(reference)) and (reference > 0).sum() >= reference.size - 1
    np.testing.assert_allclose(fast, reference, rtol=1e-9, atol=1e-15)


def test_large_node_sigma_by_any_node_set_and_kept_right_hand_sides(answer):
    """Any order, repeats, subsets: each node's σ as from the whole set; a node set asked again
    (its right-hand sides kept) gives the same bytes; the kept sets are bounded."""
    rec, graph, c, data, nodes = answer
    centre = rec.grid.centre
    whole = graph.height_sigma_at(c, data, 0.7, centre)(nodes)
    again = graph.height_sigma_at(c, data, 0.7, centre)(nodes)
    np.testing.assert_array_equal(again, whole)
    pick = np.random.default_rng(3).permutation(len(nodes))[:40]
    mixed = np.concatenate([nodes[pick], nodes[pick[:5]]])  # shuffled, with repeats
    part = graph.height_sigma_at(c, data, 0.7, centre)(mixed)
    np.testing.assert_allclose(part, np.concatenate([whole[pick], whole[pick[:5]]]), rtol=1e-12, atol=1e-15)
    at = graph.height_sigma_at(c, data, 1.0, centre)
    for k in range(graphfit._SIGMA_ROWS_KEPT + 3):  # more node sets than are kept
        one = nodes[k: k + 1]
        np.testing.assert_allclose(at(one), whole[k] / 0.7, rtol=1e-12)
    assert len(graph._sigma_rows) <= graphfit._SIGMA_ROWS_KEPT


def test_local_jacobian_and_sigma_squares_kernels(answer):
    """The kernel's Jacobian rows over each gauge's own coefficients are its dense Jacobian, and
    graph_sigma_squares is |J x_p|² column by column."""
    _, graph, c, data, _ = answer
    turning, stretch, w_t, w_s = data[:4]
    g = len(turning)
    dense = np.zeros((2 * g, graph.size))
    local = np.zeros((2 * g, graph.idx.shape[1]))
    for jac, jac_local in ((dense, np.zeros((0, 0))), (np.zeros((0, 0)), local)):
        graph._compiled.graph_normal_equations(c, graph.idx, graph.da, graph.db, graph.daa, graph.wq, turning, stretch,
                                               w_t, w_s, graph.prior_band.copy(), np.zeros(graph.size), True,
                                               np.asarray(graph.sigma_curvature, dtype=float), np.empty(2 * g), jac,
                                               jac_local)
    rebuilt = np.zeros_like(dense)
    rows = np.repeat(np.arange(2 * g), graph.idx.shape[1])
    np.add.at(rebuilt, (rows, np.concatenate([graph.idx, graph.idx]).ravel()), local.ravel())
    np.testing.assert_array_equal(rebuilt, dense)
    x = np.random.default_rng(2).normal(size=(graph.size, 17))
    out = np.zeros(17)
    graph._compiled.graph_sigma_squares(graph.idx, local, x, out)
    np.testing.assert_allclose(out, ((dense @ x) ** 2).sum(axis=0), rtol=1e-12)


@pytest.mark.parametrize("n, m", [(3, 3), (5, 5), (6, 4), (8, 8)])
def test_small_sheets_node_sigma_through_the_band_equals_the_dense_triangle(monkeypatch, n, m):
    """Sheets of up to 64 cells take the band path too (their H carries a share of the stretch
    residuals' curvature): node_sigma and locate_sigma as through the dense triangle."""
    def answer() -> tuple[np.ndarray, np.ndarray, str, int]:
        rec = Reconstructor(n, m)
        eu, el = gauge_strains(GaussianBumps(height=2.0, fwhm=18.0, centre=(2.0, -3.0)), n, m, 12.0,
                               rec.h_upper, rec.h_lower, rec.gauge_length)
        rng = np.random.default_rng(3)
        surf = rec(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape))
        pick = np.random.default_rng(1)
        uv = np.column_stack([pick.uniform(-5.0 * m, 5.0 * m, 20), pick.uniform(-5.0 * n, 5.0 * n, 20)])
        sigma = surf.node_sigma.copy(), surf.locate_sigma(uv)
        assert rec._graph is not None
        return *sigma, surf.diagnostics.extra["model"], len(rec._graph._sigma_rows)

    band_nodes, band_points, model, band_sets = answer()
    assert model == "graph" and band_sets > 0  # (the band path keeps its node sets' right-hand sides)
    monkeypatch.setattr(graphfit, "_BAND_SIGMA_SIZE", 10 ** 9)
    dense_nodes, dense_points, _, dense_sets = answer()
    assert dense_sets == 0
    assert band_nodes.max() > 0.0
    np.testing.assert_allclose(band_nodes, dense_nodes, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(band_points, dense_points, rtol=1e-12, atol=1e-15)
