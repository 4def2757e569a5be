"""Reconstruction numerics: the fast per-frame kernels agree with their plain definitions."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.emulator import physics as ph
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.grid import FineGrid
from skinmap.reconstruction.linalg import cayley_t, exp_so3, exp_so3_t, matmul_t

PITCH = 12.0


def _skew(w: np.ndarray) -> np.ndarray:
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-3, 0.5, 3.0])
def test_rotation_maps_match_the_matrix_exponential(scale):
    from scipy.linalg import expm

    rng = np.random.default_rng(7)
    w = rng.normal(size=(3, 6)) * scale
    r = exp_so3_t(w)
    for k in range(w.shape[1]):
        assert np.allclose(r[:, :, k], expm(_skew(w[:, k])), atol=1e-13)
    # the array-of-vectors form is the same map
    assert np.allclose(exp_so3(w.T), r.transpose(2, 0, 1), atol=1e-15)
    c = cayley_t(w)
    assert np.allclose(matmul_t(c, c.transpose(1, 0, 2)), np.eye(3)[:, :, None], atol=1e-14)
    if scale <= 1e-3:  # Cayley = exp up to O(|w|³)
        assert np.allclose(c, r, atol=10 * scale**3 + 1e-15)


def test_components_first_products_and_divergence():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(3, 3, 17)), rng.normal(size=(3, 3, 17))
    assert np.allclose(matmul_t(a, b), np.einsum("ikn,kjn->ijn", a, b))
    assert np.allclose(matmul_t(a, b).transpose(2, 0, 1), a.transpose(2, 0, 1) @ b.transpose(2, 0, 1))
    grid = FineGrid(3, 4, PITCH, 10.0, sub=2)
    values = rng.normal(size=(3, grid.incidence.shape[0]))
    assert np.allclose(grid.divergence(values), grid.incidence.T @ values.T)
    u_part, v_part = values[:, : grid.n_uedges], values[:, grid.n_uedges :]
    assert np.allclose(grid.divergence(u_part, v_part), grid.incidence.T @ values.T)


def test_banded_solver_matches_a_dense_solve():
    grid = FineGrid(6, 6, PITCH, 10.0, sub=4)  # 25×25 nodes: banded factor
    rhs = np.random.default_rng(5).normal(size=(grid.nf * grid.mf, 3))
    dense = grid.laplacian  # Laplacian with the centre pinned
    lap = (grid.incidence.T @ grid.incidence).toarray()
    c = grid.centre[0] * grid.mf + grid.centre[1]
    lap[c, c] += 1.0
    for b in (rhs, rhs[:, 0], np.asfortranarray(rhs)):
        assert np.allclose(dense.solve(b), np.linalg.solve(lap, b), atol=1e-9)


@pytest.mark.parametrize("n, m, per_pitch", [(5, 5, 20), (5, 5, 3), (4, 7, 1), (3, 3, 7)])
def test_points_equal_located_points_on_the_same_grid(n, m, per_pitch):
    shape = ph.GaussianBumps(height=4.0, fwhm=18.0, centre=(5.0, -3.0))
    eu, el = ph.gauge_strains(shape, n, m, PITCH, 0.2, 0.2, 10.0)
    surf = Reconstructor(n, m, PITCH)(eu, el)
    cloud = surf.points(per_pitch=per_pitch)
    u0, u1, v0, v1 = surf.extent
    step = PITCH / per_pitch
    us = u0 + step * (np.arange(int(round((u1 - u0) / step))) + 0.5)
    vs = v0 + step * (np.arange(int(round((v1 - v0) / step))) + 0.5)
    uu, vv = np.meshgrid(us, vs)
    expected, _ = surf.locate(np.stack([uu.ravel(), vv.ravel()], axis=1))
    assert cloud.shape == (us.size * vs.size, 3)
    assert np.allclose(cloud, expected, atol=1e-9)
    # the cloud passes through the nodes where a sample falls on a cell centre
    if per_pitch % 2 == 1:
        centre_samples = cloud.reshape(vs.size, us.size, 3)[per_pitch // 2 :: per_pitch, per_pitch // 2 :: per_pitch]
        assert np.allclose(centre_samples, surf.nodes, atol=1e-9)


def test_points_rejects_bad_density():
    eu = np.zeros((2, 3, 3))
    surf = Reconstructor(3, 3)(eu, eu)
    for bad in (0, -2, 2.5):
        with pytest.raises(ValueError, match="per_pitch"):
            surf.points(per_pitch=bad)


def test_huber_fit_gives_the_least_squares_surface_even_with_a_glitch():
    """The field fit interpolates the units' data (2·N·M data, far more potential unknowns), so
    every residual stays far inside the Huber threshold and the Clarabel fit cannot down-weight a
    glitching gauge: both solvers give the same surface (see docs/reconstruction.md)."""
    shape = ph.GaussianBumps(height=3.0, fwhm=20.0, centre=(4.0, -3.0))
    eu, el = ph.gauge_strains(shape, 5, 5, PITCH, 0.2, 0.2, 10.0)
    eu[0, 2, 1] += 0.005  # 0.5 % glitch on one gauge
    ls = Reconstructor(5, 5, graph_fit=False)(eu, el)
    hub = Reconstructor(5, 5, convex_solver="clarabel", graph_fit=False)(eu, el)
    assert hub.diagnostics.extra["convex_status"] == "Solved"
    assert np.abs(ls.nodes - hub.nodes).max() < 1e-3
