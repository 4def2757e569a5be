"""Missing units: an unseen validity mask leaves them out of the all-valid fits (Woodbury),
exactly as a new factorisation would, and raises the uncertainty where data are missing."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import aligned_error

from skinmap.emulator import physics as ph
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.engine import unit_data
from skinmap.reconstruction.grid import FineGrid
from skinmap.reconstruction.leaveout import IllConditioned, LeaveOut, woodbury_weights
from skinmap.reconstruction.uncertainty import fine_sigma, height_response

PITCH, H, G = 12.0, 0.2, 10.0


class _SparseGrid(FineGrid):
    """A small grid forced onto the large-grid path (per-unit solves instead of dense maps)."""

    @property
    def dense_maps(self) -> bool:
        return False


def _strains(n, m, shape=None):
    shape = shape or ph.GaussianBumps(height=3.0, fwhm=20.0, centre=(4.0, -3.0))
    return ph.gauge_strains(shape, n, m, PITCH, H, H, G)


@pytest.mark.slow
@pytest.mark.parametrize("grid_cls", [FineGrid, _SparseGrid])
def test_left_out_fields_and_sigma_equal_a_new_factorisation(grid_cls):
    n, m = 4, 5
    grid = grid_cls(n, m, PITCH, G, sub=2)
    eu, el = _strains(n, m)
    rng = np.random.default_rng(7)
    for k in (1, 3, 9):
        eu_k = eu.copy()
        eu_k.reshape(-1)[rng.choice(eu.size, k, replace=False)] = np.nan
        turning, stretch, valid = unit_data(eu_k, el, H, H, G)
        left_out = grid.field_maps(valid)(turning, stretch)
        refactorised = grid._build_maps(valid)(turning, stretch)
        for a, b in zip(left_out[:5], refactorised[:5]):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7 * np.abs(b).max())
        # uncertainty: the response of the left-out fit, by its own factorisation
        v = valid.ravel()
        sig = fine_sigma(grid, valid, turning, 1e-4, H, H)
        measured = (height_response(grid, valid)[:, v] ** 2).sum(axis=1)
        missing = (height_response(grid, np.ones_like(valid))[:, ~v] ** 2).sum(axis=1)
        sig_turn = np.sqrt(2.0) * 1e-4 / (2 * H)
        spread2 = np.mean(turning[valid] ** 2) + (1.0 / 200.0) ** 2
        walk = (np.abs(grid.u)[None, :] + np.abs(grid.v)[:, None]) * PITCH * (1e-4 * np.hypot(H, H) / (2 * H)) ** 2
        expected = np.sqrt((measured * sig_turn**2 + missing * spread2).reshape(grid.nf, grid.mf) + walk)
        np.testing.assert_allclose(sig, expected, rtol=1e-7)


@pytest.mark.slow
def test_random_dead_gauge_sequence_gives_finite_surfaces_with_raised_uncertainty():
    n = m = 5
    shape = ph.GaussianBumps(height=3.0, fwhm=20.0, centre=(4.0, -3.0))
    eu, el = _strains(n, m, shape)
    truth = shape.position(ph.cell_centres(n, m, PITCH))
    # the general model: its noise map (linear propagation) never falls with a unit missing; its
    # resolution term (uncertainty.resolution_sigma, the departures from the measured units'
    # affine turning pattern) moves with the units that pattern is fitted to, by a percent
    rec = Reconstructor(n, m, PITCH, H, H, G, graph_fit=False)
    clean = rec(eu, el)
    base_sigma = clean.node_sigma
    rng = np.random.default_rng(11)
    prev = clean
    raised = 0
    for _ in range(25):
        eu_k, el_k = eu.copy(), el.copy()
        dead = rng.choice(2 * n * m, rng.integers(1, 5), replace=False)
        (eu_k if rng.random() < 0.5 else el_k).reshape(-1)[dead] = np.nan
        surf = rec(eu_k, el_k, previous=prev)
        assert np.isfinite(surf.nodes).all() and np.isfinite(surf.normals).all()
        sig = surf.node_sigma
        assert np.isfinite(sig).all() and (sig >= base_sigma * 0.98).all()
        # the cell of every dead unit (both of its gauges are read as one unit) gets less certain
        cells = np.unravel_index(dead % (n * m), (n, m))
        raised += int((sig[cells] > 1.5 * base_sigma[cells]).sum())
        assert "missing" in surf.diagnostics.status
        err = np.linalg.norm(surf.nodes - clean.nodes, axis=-1)
        assert err.max() < 2.0  # a few dead gauges on a 3 mm bump: filled, not lost
        prev = surf
    assert raised > 0
    # a single dead gauge barely changes the shape
    eu_1 = eu.copy()
    eu_1[0, 2, 3] = np.nan
    one = rec(eu_1, el)
    assert np.abs(one.nodes - clean.nodes).max() < 0.3
    assert aligned_error(one.nodes, truth) < 2.0 * aligned_error(clean.nodes, truth) + 0.05


@pytest.mark.slow
def test_replay_of_the_same_sequence_is_bit_identical():
    n = m = 5
    eu, el = _strains(n, m)
    rng = np.random.default_rng(5)
    frames = []
    for _ in range(8):
        a, b = eu + rng.normal(0, 5e-5, eu.shape), el + rng.normal(0, 5e-5, el.shape)
        a.reshape(-1)[rng.choice(a.size, 2, replace=False)] = np.nan
        frames.append((a, b))
    frames += frames[:3]  # masks seen before, now from the cache

    def run():
        rec, prev, out = Reconstructor(n, m, PITCH, H, H, G), None, []
        for a, b in frames:
            prev = rec(a, b, previous=prev)
            out.append((prev.nodes, prev.node_sigma))
        return out

    for (n1, s1), (n2, s2) in zip(run(), run()):
        assert np.array_equal(n1, n2) and np.array_equal(s1, s2)


def test_a_whole_direction_missing_falls_back_to_its_own_factorisation():
    n = m = 4
    eu, el = _strains(n, m)
    eu[0] = np.nan  # no row-direction data at all: the prior alone cannot fix k_u
    surf = Reconstructor(n, m, PITCH, H, H, G)(eu, el)
    assert np.isfinite(surf.nodes).all() and np.isfinite(surf.node_sigma).all()
    with pytest.raises(IllConditioned, match="undetermined"):
        woodbury_weights(np.eye(3))


def test_leave_out_rejects_bad_construction():
    with pytest.raises(ValueError, match="either"):
        LeaveOut()
    with pytest.raises(ValueError, match="data operator"):
        LeaveOut(solver=object())


@pytest.mark.parametrize(
    "radius, angle, kwargs, bound",
    [
        (50.0, 15.0, {}, 0.5),
        (-60.0, -30.0, {}, 0.4),
        (120.0, 30.0, {}, 0.15),
        (80.0, -15.0, {}, 0.3),
        # at 45° the saddle and its mirror image give identical strains: the sign is told
        (50.0, 45.0, {"twist_sign": 1.0}, 0.2),
        (50.0, -45.0, {"twist_sign": -1.0}, 0.2),
    ],
)
@pytest.mark.slow
def test_turned_saddles_from_the_physics_model(radius, angle, kwargs, bound):
    n = m = 5
    shape = ph.Saddle(radius, axis_angle=angle)
    eu, el = ph.gauge_strains(shape, n, m, PITCH, H, H, G)
    surf = Reconstructor(n, m, PITCH, H, H, G)(eu, el, **kwargs)
    assert aligned_error(surf.nodes, shape.position(ph.cell_centres(n, m, PITCH))) < bound


@pytest.mark.slow
@pytest.mark.parametrize("grid_cls", [FineGrid, _SparseGrid])
def test_cache_state_changes_no_digit(grid_cls):
    n, m = 4, 5
    eu, el = _strains(n, m)
    eu[0, 1, 2] = eu[1, 3, 0] = el[0, 2, 4] = np.nan
    turning, stretch, valid = unit_data(eu, el, H, H, G)
    fresh = grid_cls(n, m, PITCH, G, sub=2)
    want = fresh.field_maps(valid)(turning, stretch), fine_sigma(fresh, valid, turning, 1e-4, H, H)
    warm = grid_cls(n, m, PITCH, G, sub=2)
    for other in ([(0, 1, 2)], [(1, 3, 0), (0, 0, 0)], [(0, 2, 4), (0, 1, 2), (1, 1, 1)]):
        v = np.ones_like(valid)
        for idx in other:
            v[idx] = False
        t = np.where(v, turning, 0.0)
        s = np.where(v, stretch, 1.0)
        warm.field_maps(v)(t, s)
        fine_sigma(warm, v, t, 1e-4, H, H)
    got = warm.field_maps(valid)(turning, stretch), fine_sigma(warm, valid, turning, 1e-4, H, H)
    for a, b in zip(want[0], got[0]):
        assert np.array_equal(a, b)
    assert np.array_equal(want[1], got[1])


def test_no_valid_unit_gives_the_flat_sheet_with_raised_uncertainty():
    n = m = 4
    eu, el = _strains(n, m)
    rec = Reconstructor(n, m, PITCH, H, H, G)
    clean = rec(eu, el)
    nan = np.full((2, n, m), np.nan)
    surf = rec(nan, nan)
    assert np.abs(surf.nodes[..., 2]).max() == 0.0 and "no valid gauge" in surf.diagnostics.status
    assert np.isfinite(surf.node_sigma).all() and (surf.node_sigma > clean.node_sigma).all()
    some = eu.copy()
    some[0, :2] = np.nan  # half the row-direction gauges
    partial = rec(some, el)
    assert np.isfinite(partial.nodes).all() and (partial.node_sigma >= clean.node_sigma - 1e-12).all()


def test_probe_estimate_of_a_refactorised_mask_is_close_to_the_exact_response():
    from skinmap.reconstruction.uncertainty import _left_out_sums, _probe_sums

    n, m = 5, 6
    grid = _SparseGrid(n, m, PITCH, G, sub=2)
    valid = np.ones((2, n, m), dtype=bool)
    valid.reshape(-1)[np.random.default_rng(2).choice(valid.size, 12, replace=False)] = False
    exact = _left_out_sums(grid, valid)
    probe = _probe_sums(grid, valid)
    assert np.array_equal(probe[0], _probe_sums(grid, valid)[0])  # seeded by the mask
    sig_turn2, spread2 = 1e-8, 1e-4
    var_exact = exact[0] * sig_turn2 + exact[1] * spread2
    var_probe = probe[0] * sig_turn2 + probe[1] * spread2
    inside = var_exact > 1e-3 * var_exact.max()  # the pinned centre has no variance at all
    ratio = np.sqrt(var_probe[inside] / var_exact[inside])
    assert 0.5 < ratio.min() and ratio.max() < 1.6 and abs(np.median(ratio) - 1.0) < 0.15


@pytest.mark.parametrize("shape", [ph.Saddle(-102.3, axis_angle=-45.0), ph.GaussianBumps(height=3.0, fwhm=20.0),
                                   ph.Cylinder(60.0, axis_angle=30.0)])
def test_a_unit_with_one_gauge_reading_is_that_unit_missing_to_the_bit(shape):
    """No fit uses a lone gauge (a unit needs both layers to tell bending from stretch), and
    no check against the gauges counts it either: the answer and its σ are those of the whole
    unit missing (8×8, three lone gauges, one at the edge where the saddle stretches the film
    10 %; counted, the saddle's σ was widened by their misfit)."""
    n = 8
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rng = np.random.default_rng(0)
    eu, el = eu + rng.normal(0, 5.7e-5, eu.shape), el + rng.normal(0, 5.7e-5, el.shape)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    lone_u, lone_l = eu.copy(), el.copy()
    lone_u[0, 1, 4] = lone_u[0, n - 1, 2] = np.nan
    lone_l[1, 4, 3] = np.nan
    both_u, both_l = lone_u.copy(), lone_l.copy()
    both_l[0, 1, 4] = both_l[0, n - 1, 2] = np.nan
    both_u[1, 4, 3] = np.nan
    a, b = rec(lone_u, lone_l), rec(both_u, both_l)
    np.testing.assert_array_equal(a.nodes, b.nodes)
    np.testing.assert_array_equal(a.node_sigma, b.node_sigma)
    assert a.diagnostics.status == b.diagnostics.status == "solved with 3 missing unit(s)"


def test_lone_gauges_do_not_decide_the_sign_of_a_saddle_at_45_degrees_that_the_live_units_read_alike():
    """A saddle at 45° reads the same with either twist sign.  Three units with one gauge dead
    (noisy 8×8): what each sign's answer predicts at their live gauges is its prior's fill, up to
    700 in χ² at a sheet's edge where the saddle stretches the film 10 %; counted, it chose the
    wrong sign, 11 mm off with σ 0.45, unflagged.  Every draw: the answer or its mirror within
    3σ + 0.05 mm."""
    from conftest import worst_of_answers

    n = 8
    shape = ph.Saddle(-102.3, axis_angle=-45.0)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = shape.position(ph.cell_centres(n, n, PITCH))
    rec = Reconstructor(n, n, PITCH, H, H, G)
    rng = np.random.default_rng(1)
    for _ in range(6):
        a, b = eu + rng.normal(0, 5.7e-5, eu.shape), el + rng.normal(0, 5.7e-5, el.shape)
        a.reshape(-1)[rng.choice(a.size, 3, replace=False)] = np.nan
        assert min(worst_of_answers(rec(a, b), truth)) <= 1.0
