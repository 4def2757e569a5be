"""The full-position fit with the membrane-equilibrium prior (skinmap.reconstruction.positionfit):
its derivatives, its settings, and its answers on elastic films solved by the emulator's own
mechanics (an independent model: finite elements of a film sliding on a mold)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import aligned_error

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.engine import unit_data
from skinmap.reconstruction.positionfit import ElasticFit, PositionFit, PositionFitSettings, start_from_surface

PITCH, H, G = 12.0, 0.2, 10.0
N = M = 5
NOISE = 0.0057e-2
SIG_T, SIG_S = np.sqrt(2.0) * NOISE / (2 * H), NOISE * np.sqrt(2 * H * H) / (2 * H)


@pytest.mark.parametrize("knots,margin", [(1, 0.0), (2, 0.0), (2, 0.5)])
def test_jacobians_of_the_gauges_and_of_the_equilibrium_prior_match_finite_differences_to_1e_5(knots, margin):
    # (with a margin, the basis covers film beyond the outer cells)
    fit = PositionFit(3, 4, PITCH, G, PositionFitSettings(knots_per_pitch=knots, film_margin=margin))
    rng = np.random.default_rng(knots)
    c = rng.normal(0.0, 0.3, (3, fit.nb))
    t, s, jt, js = fit.gauge_model(c, jacobian=True)
    e, je = fit.equilibrium(c, jacobian=True)
    h = 1e-6
    for k in rng.choice(3 * fit.nb, 6, replace=False):
        d = np.zeros(3 * fit.nb)
        d[k] = h
        t2, s2 = fit.gauge_model(c + d.reshape(3, -1))
        e2 = fit.equilibrium(c + d.reshape(3, -1))
        for numeric, exact in (((t2 - t) / h, jt[..., k]), ((s2 - s) / h, js[..., k]), ((e2 - e) / h, je[:, k])):
            assert np.abs(numeric - exact).max() <= 1e-5 * max(1.0, np.abs(exact).max())


def test_settings_out_of_range_are_refused_by_name():
    with pytest.raises(ValueError, match="poisson"):
        PositionFit(5, 5, PITCH, G, PositionFitSettings(poisson=0.5))
    with pytest.raises(ValueError, match="step_solver"):
        PositionFit(5, 5, PITCH, G, PositionFitSettings(step_solver="newton"))
    with pytest.raises(ValueError, match="film_margin"):
        PositionFit(5, 5, PITCH, G, PositionFitSettings(film_margin=-0.5))
    with pytest.raises(ValueError, match="film_margin"):
        PositionFit(5, 5, PITCH, G, PositionFitSettings(film_margin=float("nan")))
    fit = PositionFit(3, 3, PITCH, G)
    with pytest.raises(ValueError, match=rf"coefficients of shape \(2, {fit.nb}\): this basis has \(3, {fit.nb}\)"):
        fit.slide(np.zeros((2, fit.nb)))


SLIDING = PositionFitSettings(knots_per_pitch=3, film_margin=0.5)  # the basis covers the whole film


def _film_grid(half: float, step: float = 1.5) -> np.ndarray:
    u = np.linspace(-half, half, int(round(2 * half / step)) + 1)
    uu, vv = np.meshgrid(u, u)
    return np.stack([uu.ravel(), vv.ravel()], axis=-1)


def test_a_film_wrapped_isometrically_on_a_cylinder_slides_back_to_its_wrap_from_its_height_alone_within_1um():
    """Closed form: a film wrapped on a cylinder of radius R about the v axis, without stretch,
    lies at (R sin(u/R), v, R(1 − cos(u/R))): its in-plane displacement U = R sin(u/R) − u is the
    stress-free state, so the membrane's equilibrium with free edges, given the height alone and
    started from no sliding at all, must find it."""
    radius = 60.0
    fit = PositionFit(N, M, PITCH, G, SLIDING)
    uv = _film_grid(0.5 * N * PITCH + 0.5 * PITCH)
    u, v = uv[:, 0], uv[:, 1]
    wrapped = np.stack([radius * np.sin(u / radius), v, radius * (1 - np.cos(u / radius))], axis=-1)
    truth = fit.coeffs_from_positions(u, v, wrapped)
    start = truth.copy()
    start[:2] = 0.0  # a height graph: no sliding
    slid = fit.slide(start)
    assert np.array_equal(slid[2], truth[2])  # the height is held
    off_before = np.abs(fit.nodes(start) - fit.nodes(truth)).max()
    off = np.abs(fit.nodes(slid) - fit.nodes(truth)).max()
    print(f"cylinder R {radius:g} mm: nodes {off_before:.3f} mm off without sliding, {1e3 * off:.3f} um after")
    assert off_before > 0.3
    assert off < 1e-3


def test_a_film_laminated_on_a_bump_slides_as_its_height_says_within_0p005mm_where_a_height_graph_is_0p1mm_off(cache):
    """The emulator's film (finite elements with bending, sliding on a 4.4 mm / FWHM 15 mm bump):
    its true height, with no sliding (a height graph over the material coordinates), puts the
    cell centres 0.16 mm off; the membrane's virtual work on tangential displacements, free
    edges, recovers the sliding from the height alone (measured 0.0015 mm mean at 3 knots a
    pitch; the collocated equilibrium rows reached 0.010 there)."""
    shape = parse_scene_spec("gaussian:height=4.44,fwhm=15.06,u0=-13.28,v0=1.16", "elastic", N, M, PITCH,
                             cache_dir=cache)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    fit = PositionFit(N, M, PITCH, G, SLIDING)
    uv = shape.grid.uv().reshape(-1, 2)
    c = fit.coeffs_from_positions(uv[:, 0], uv[:, 1], shape.positions.reshape(-1, 3))
    c[:2] = 0.0
    graph = aligned_error(fit.nodes(c), truth)
    slid_c = fit.slide(c)
    slid = aligned_error(fit.nodes(slid_c), truth)
    print(f"bump: height graph {graph:.4f} mm, slid by the membrane {slid:.4f} mm (mean node error, aligned)")
    assert graph > 0.1
    assert slid < 0.005
    # the answer is the weak form's root: its residual a tiny share of the unslid film's
    before, _ = fit.virtual_work(c)
    after, _ = fit.virtual_work(slid_c)
    assert np.linalg.norm(after) < 1e-3 * np.linalg.norm(before)


def test_the_virtual_work_s_jacobian_is_its_finite_difference():
    """The sliding's Gauss-Newton steps use the weak form's Jacobian by (U, V), assembled from
    complex-step derivatives at each Gauss point: checked against central differences on a
    sheet wrapped, stretched and slid at random."""
    fit = PositionFit(3, 3, PITCH, G, PositionFitSettings(knots_per_pitch=2, film_margin=0.5))
    rng = np.random.default_rng(5)
    c = np.zeros((3, fit.nb))
    c[:2] = rng.normal(0.0, 0.3, (2, fit.nb))
    c[2] = rng.normal(0.0, 2.0, fit.nb)
    r0, jac = fit.virtual_work(c)
    dense = jac.toarray()
    for col in rng.choice(2 * fit.nb, 6, replace=False):
        h = 1e-6
        plus, minus = c.copy(), c.copy()
        plus.reshape(-1)[col] += h
        minus.reshape(-1)[col] -= h
        fd = (fit.virtual_work(plus)[0] - fit.virtual_work(minus)[0]) / (2 * h)
        assert np.allclose(dense[:, col], fd, rtol=1e-5, atol=1e-8 * np.abs(r0).max())


def test_a_flat_sheet_stays_flat_and_its_coefficients_round_trip_through_positions():
    fit = PositionFit(N, M, PITCH, G)
    zero = np.zeros((2, N, M))
    res = fit.fit(zero, np.ones((2, N, M)), np.ones((2, N, M), bool), SIG_T, SIG_S, np.zeros((3, fit.nb)))
    assert res.status == "converged"
    assert np.abs(fit.nodes(res.coeffs) - ph.ground_truth(ph.Flat(), N, M, PITCH).nodes).max() < 1e-9


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("mechanics-cache")


def _fit_scene(spec: str, cache, poisson: float, solver: str = "cholesky", max_steps: int = 80):
    shape = parse_scene_spec(spec, "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    surf = Reconstructor(N, M, PITCH, H, H, G)(eu, el)
    turning, stretch, valid = unit_data(eu, el, H, H, G)
    fit = PositionFit(N, M, PITCH, G, PositionFitSettings(poisson=poisson, step_solver=solver, max_steps=max_steps))
    # from the answer and, when the gauges cannot tell, from its mirror image: the lower objective
    starts = [surf] if surf.mirror is None else [surf, surf.mirror]
    res = min((fit.fit(turning, stretch, valid, SIG_T, SIG_S, start_from_surface(fit, s)) for s in starts),
              key=lambda r: r.cost)
    return aligned_error(surf.nodes, truth), aligned_error(fit.nodes(res.coeffs), truth), res


@pytest.mark.slow
@pytest.mark.parametrize("spec,poisson", [("saddle:radius=95,axis_angle=120", 0.48),
                                          ("saddle:radius=105,axis_angle=62,poisson=0.35", 0.35)])
def test_elastic_saddle_off_the_grid_lines_is_within_0_1mm_with_the_films_poisson_ratio(spec, poisson, cache):
    default, fitted, res = _fit_scene(spec, cache, poisson)
    assert res.chi2 < 1.0  # the answer explains the gauges within the noise
    assert fitted <= 0.1, f"position fit {fitted:.3f} mm (default {default:.3f} mm)"


@pytest.mark.slow
def test_clarabel_huber_steps_give_the_least_squares_answer_when_every_residual_is_within_the_threshold(cache):
    _, cholesky, res_c = _fit_scene("sphere:radius=85", cache, 0.48, "cholesky", 12)
    _, clarabel, res_q = _fit_scene("sphere:radius=85", cache, 0.48, "clarabel", 12)
    assert (res_q.weights == 1.0).all()
    assert abs(cholesky - clarabel) < 2e-3
    assert np.abs(res_c.coeffs - res_q.coeffs).max() < 1e-3


def test_reconstructor_refuses_an_elastic_prior_that_is_not_settings_or_too_large_a_sheet():
    with pytest.raises(ValueError, match="elastic_prior must be"):
        Reconstructor(N, M, elastic_prior=0.48)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="up to 64 cells"):
        Reconstructor(9, 8, elastic_prior=PositionFitSettings())


@pytest.fixture(scope="module")
def elastic_rec():
    return Reconstructor(N, M, PITCH, H, H, G, elastic_prior=PositionFitSettings(poisson=0.48, max_steps=80))


@pytest.mark.slow
def test_reconstructor_with_the_elastic_prior_is_within_0_1mm_on_an_unseen_elastic_saddle_with_sigma_covering(
        elastic_rec, cache):
    shape = parse_scene_spec("saddle:radius=100,axis_angle=35", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    default = Reconstructor(N, M, PITCH, H, H, G)(eu, el)
    surf = elastic_rec(eu, el)
    assert surf.diagnostics.extra["elastic_prior"] == "used"
    error = aligned_error(surf.nodes, truth)
    assert error <= 0.1, f"{error:.3f} mm (default {aligned_error(default.nodes, truth):.3f} mm)"
    assert error <= 3 * float(surf.node_sigma.mean()) + 0.05
    assert surf.state.position is not None


@pytest.mark.slow
def test_reconstructor_keeps_an_isometric_cylinders_mirror_and_says_why_when_the_prior_does_not_hold(elastic_rec, cache):
    # an oblique cylinder bends without stretching: the prior cannot tell it from its mirror image
    shape = parse_scene_spec("cylinder:radius=70,axis_angle=30", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    surf = elastic_rec(eu, el)
    assert surf.mirror is not None and surf.diagnostics.extra["ambiguous"]
    # a bump whose film is not normally loaded everywhere in the prior's basis: the default stays, said aloud
    shape = parse_scene_spec("gaussian:height=4,fwhm=18,u0=5,v0=-3", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    bump = elastic_rec(eu, el)
    assert bump.diagnostics.extra["elastic_prior"].startswith("not used: prior cost")
    assert bump.diagnostics.extra["model"] != "position (equilibrium prior)"


def test_a_fit_on_half_the_knots_carries_over_to_the_full_basis_exactly():
    fine = PositionFit(4, 5, PITCH, G, PositionFitSettings(knots_per_pitch=2))
    coarse = PositionFit(4, 5, PITCH, G, PositionFitSettings(knots_per_pitch=1))
    c = np.random.default_rng(3).normal(0.0, 0.5, (3, coarse.nb))
    u, v = np.random.default_rng(4).uniform(-25, 25, (2, 200)) * np.array([[1.0], [0.8]])
    moved = c @ fine.transfer(coarse).T
    for a, b in zip(coarse.evaluate(c, u, v), fine.evaluate(moved, u, v)):
        assert np.abs(a - b).max() < 1e-9


@pytest.mark.slow
def test_the_answers_first_order_response_to_poissons_ratio_matches_a_refit_at_the_shifted_ratio(cache):
    _, _, res = _fit_scene("saddle:radius=100,axis_angle=35", cache, 0.48)
    shape = parse_scene_spec("saddle:radius=100,axis_angle=35", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    data = (*unit_data(eu, el, H, H, G), SIG_T, SIG_S)
    fit = PositionFit(N, M, PITCH, G, PositionFitSettings(poisson=0.48))
    linear = fit.nodes(res.coeffs - 0.03 * fit.poisson_response(res, *data)) - fit.nodes(res.coeffs)
    shifted = PositionFit(N, M, PITCH, G, PositionFitSettings(poisson=0.45))
    refit = shifted.nodes(shifted.fit(*data, res.coeffs, max_steps=60).coeffs) - fit.nodes(res.coeffs)
    size = np.linalg.norm(refit, axis=-1).mean()
    assert size > 0.005  # ν matters on a saddle: the check below is not of two zeros
    assert np.linalg.norm(linear - refit, axis=-1).mean() <= 0.3 * size


@pytest.mark.slow
def test_a_cold_elastic_fit_keeps_an_answer_that_was_right_where_the_film_carries_no_stress(cache):
    # an oblique isometric cylinder: no stress, no prior; only the smoothness term differs between
    # the default's answer and others that fit the gauges as well, and that is no evidence
    shape = parse_scene_spec("cylinder:radius=55,axis_angle=33", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    surf = Reconstructor(N, M, PITCH, H, H, G)(eu, el)
    if surf.mirror is not None:  # the gauges cannot tell: start from the right one of the two
        surf = min((surf, surf.mirror), key=lambda s: aligned_error(s.nodes, truth))
    elastic = ElasticFit(N, M, PITCH, G, PositionFitSettings(poisson=0.48))
    res = elastic.cold(surf, *unit_data(eu, el, H, H, G), SIG_T, SIG_S)
    assert aligned_error(elastic.fine.nodes(res.coeffs), truth) <= aligned_error(surf.nodes, truth) + 0.01
