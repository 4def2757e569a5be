"""The small-array kernels of the per-frame path against plain reference formulas."""
import numpy as np
import pytest

from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.linalg import diff_u_t, diff_v_t
from skinmap.reconstruction.surface import hermite_patch_eval


def test_grid_differences_match_numpy_gradient():
    f = np.random.default_rng(3).normal(size=(3, 9, 7))
    assert np.allclose(diff_u_t(f, 0.7), np.gradient(f, 0.7, axis=-1, edge_order=1), rtol=0, atol=1e-13)
    assert np.allclose(diff_v_t(f, 0.7), np.gradient(f, 0.7, axis=-2, edge_order=1), rtol=0, atol=1e-13)


def test_hermite_patches_reproduce_a_bicubic_exactly():
    # a bicubic is its own Hermite interpolant when the node data are its exact derivatives
    h, u0, v0 = 1.5, -6.0, -4.5
    u = u0 + h * np.arange(9)
    v = v0 + h * np.arange(7)
    cu, cv = np.array([0.3, -0.2, 0.05, 0.01]), np.array([1.0, 0.4, -0.03, 0.02])

    def poly(c, x, d=0):
        return np.polyval(np.polyder(c[::-1], d), x) if d else np.polyval(c[::-1], x)

    coeffs = np.zeros((v.size, u.size, 4, 3))
    for q, (du, dv, scale) in enumerate(((0, 0, 1.0), (1, 0, h), (0, 1, h), (1, 1, h * h))):
        val = np.outer(poly(cv, v, dv), poly(cu, u, du)) * scale
        coeffs[:, :, q, 0] = val
        coeffs[:, :, q, 1] = 2.0 * val
    coeffs[:, :, 0, 2] = 1.0  # a constant third coordinate
    uv = np.random.default_rng(5).uniform([u[0], v[0]], [u[-1], v[-1]], size=(50, 2))
    uv[:2] = [[u[0], v[0]], [u[-1], v[-1]]]  # the sheet's corners (the last patch's far edge)
    p, pu, pv = hermite_patch_eval(coeffs, u0, v0, h, uv)
    x, y = uv[:, 0], uv[:, 1]
    want = poly(cu, x) * poly(cv, y)
    assert np.allclose(p[:, 0], want, atol=1e-12) and np.allclose(p[:, 1], 2 * want, atol=1e-12)
    assert np.allclose(p[:, 2], 1.0, atol=1e-14)
    assert np.allclose(pu[:, 0], poly(cu, x, 1) * poly(cv, y), atol=1e-12)
    assert np.allclose(pv[:, 0], poly(cu, x) * poly(cv, y, 1), atol=1e-12)
    assert np.allclose(pu[:, 2], 0.0, atol=1e-14) and np.allclose(pv[:, 2], 0.0, atol=1e-14)


@pytest.fixture(scope="module")
def surfaces():
    rec = Reconstructor(3, 3, 12.0)
    rng = np.random.default_rng(11)
    eu = 1e-3 * rng.normal(size=(2, 3, 3))
    el = -eu
    return rec(eu, el), rec(eu * 0.5, el * 0.5), rec(eu, el, strain_sigma=2e-4)


def test_locate_sigma_is_bilinear_in_the_fine_sigma(surfaces):
    surf = surfaces[0]
    sig = surf.fine_sigma
    u0, u1, v0, v1 = surf.extent
    h = surf._spacing
    uv = np.random.default_rng(2).uniform([u0, v0], [u1, v1], size=(40, 2))
    uv[0] = [u1, v1]
    got = surf.locate_sigma(uv)
    for (x, y), g in zip(uv, got):
        b = min(int(np.floor((x - u0) / h)), sig.shape[1] - 2)
        a = min(int(np.floor((y - v0) / h)), sig.shape[0] - 2)
        s, t = (x - u0) / h - b, (y - v0) / h - a
        want = (1 - s) * (1 - t) * sig[a, b] + s * (1 - t) * sig[a, b + 1] + (1 - s) * t * sig[a + 1, b] + s * t * sig[a + 1, b + 1]
        assert g == pytest.approx(want, rel=1e-12)


def test_all_valid_uncertainty_is_shared_per_noise_level(surfaces):
    from skinmap.emulator import physics as ph

    # strains of a real sheet, which the model explains within the noise (nothing to add for
    # misfit): the noise map alone, computed once per mask and noise level
    # (told it carries no twist: a 3×3 sheet has too few units for the stretch to be read, and a
    # dome's twist would be left open, a term the same at every noise level)
    rec = Reconstructor(3, 3, 12.0, twist_prior="none", gain_sd=0.0)
    eu, el = ph.gauge_strains(ph.SphereCap(150.0), 3, 3, 12.0, 0.2, 0.2, 10.0)  # no twist the noise leaves open
    a, b = rec(eu, el), rec(0.5 * eu, 0.5 * el)
    assert a.diagnostics.extra["chi2_per_gauge"] < 1.0 and b.diagnostics.extra["chi2_per_gauge"] < 1.0
    other = rec(eu, el, strain_sigma=2e-4)
    assert a.fine_sigma is b.fine_sigma  # same mask and noise: computed once
    assert not a.fine_sigma.flags.writeable  # shared, so nobody may change it
    ns = a.node_sigma
    ns[0, 0] = -1.0  # node_sigma is the caller's own copy
    assert b.node_sigma[0, 0] > 0
    # the centre is the frame's origin (no scatter there: zero by definition) and keeps the
    # alignment floor, the mean over the nodes
    assert b.node_scatter_sigma[1, 1] == 0.0 and b.node_sigma[1, 1] == pytest.approx(b.node_scatter_sigma.mean())
    assert np.all(other.node_sigma > b.node_sigma)  # not served from the cache


def test_locate_rejects_bad_points_by_name(surfaces):
    surf = surfaces[0]
    with pytest.raises(ValueError, match="shape"):
        surf.locate(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        surf.locate([[np.nan, 0.0]])
    with pytest.raises(ValueError, match="off the sheet"):
        surf.locate_sigma([[1e3, 0.0]])
    p, n = surf.locate([0.0, 0.0])  # a single point as a (2,) pair
    assert p.shape == (1, 3) and np.allclose(np.linalg.norm(n, axis=1), 1.0)
