"""The graph sheet's constant twist is trusted by the share of the stretch misfit it removes
beyond what the noise leaves (reconstruction/graphsheet.py, SlopeNoise): the noise draws describe
the field maps' own noise, and a noisy 16×16 saddle whose twist the fixed share shrank keeps it.
Such a twist, its sign decided, carries its own s.d. in σ where the noise alone leaves the model
within one per gauge (up to 16×16), the curvature product's beyond."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.emulator import physics as ph
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.engine import graph_slopes, unit_data

PITCH = 12.0
NOISE = 5.7e-5


def test_the_slope_noise_draws_give_the_stretch_misfit_that_noisy_gauges_leave_on_a_bent_sheet():
    """Independent of the draws' own construction: strain noise on both layers of every gauge of
    a bent 8×8 sheet (a cylinder, slopes up to 0.4), through unit_data and the field maps, leaves
    a misfit Σ (e1 − z_u²)² + (g1 − z_v²)² beyond the noise-free fields' whose mean over 200
    draws is what the draws give, within 30 % (measured 0.0023 against 0.0025; the slopes' noise
    is nearly all of it, the stretch's alone 1·10⁻⁵), and below the floor."""
    n = 8
    rec = Reconstructor(n, n, PITCH)
    grid = rec.grid
    maps = grid.field_maps(np.ones((2, n, n), dtype=bool))
    shape = ph.Cylinder(60.0, axis_angle=30.0)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)
    inner = grid.inner

    def fields(a, b):
        turning, stretch, _ = unit_data(a, b, 0.2, 0.2, 10.0)
        k_uu, k_vv, tau_var, lam_u, lam_v, _ = maps(turning, stretch)
        p, q = graph_slopes(grid, k_uu, k_vv, tau_var - tau_var.mean())
        return p[inner], q[inner], (lam_u * lam_u - 1.0)[inner], (lam_v * lam_v - 1.0)[inner]

    p0, q0, e0, g0 = fields(eu, el)
    rng = np.random.default_rng(5)
    misfits = []
    for _ in range(200):
        p, q, e1, g1 = fields(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape))
        # the residuals' change from the noise-free ones (the misfit the noise adds)
        r_e = (e1 - e0) - (p * p - p0 * p0)
        r_g = (g1 - g0) - (q * q - q0 * q0)
        misfits.append(float((r_e * r_e).sum() + (r_g * r_g).sum()))
    u = np.broadcast_to(grid.u[None, inner[1]], p0.shape)
    v = np.broadcast_to(grid.v[inner[0], None], p0.shape)
    draws = rec._slope_noise()
    st, ss = rec._turning_sd(NOISE), rec._stretch_sd(NOISE)
    r_e, r_g = draws.residual_draws(p0, q0, st, ss)
    expected = float(((r_e * r_e).sum(axis=1) + (r_g * r_g).sum(axis=1)).mean())
    floor, chance, _, mean = draws.misfit_noise(p0, q0, u, v, st, ss)
    measured = float(np.mean(misfits))
    assert 0.7 * expected <= measured <= 1.3 * expected, (measured, expected)
    assert mean == pytest.approx(expected) and expected < floor and 0.0 < chance < floor


@pytest.mark.slow
def test_a_noisy_16x16_saddle_near_the_rows_keeps_its_graph_twist_and_is_within_0_1mm():
    """A saddle R 293 mm 1° off the rows on 16×16 (the elastic bench's seed-2024 scene, its
    kinematic form), twist 1.2·10⁻⁴ /mm: its graph twist removed 0.009-0.012 of a stretch misfit
    of 0.012-0.019, and the share left, 0.003-0.01, is mostly the noise's (0.004 ± 0.0013); judged
    against the whole of it the twist was trusted 0-0.7 and the sheet was 0.18-0.27 mm off on every
    noisy draw.  Judged beyond the noise: within 0.1 mm mean on each of four draws."""
    from conftest import bench_frame
    from skinmap.reconstruction.linalg import aligned_distances

    n = 16
    rec = Reconstructor(n, n, PITCH)
    errors = []
    for draw in range(4):
        _, shape, eu, el = bench_frame("saddle", 2024, 0, n, "saddle:radius=292.7,axis_angle=1.0", draw)
        truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
        errors.append(float(aligned_distances(rec(eu, el).nodes.reshape(-1, 3), truth).mean()))
    assert max(errors) <= 0.1, errors


@pytest.mark.slow
@pytest.mark.parametrize("index, spec", [(0, "saddle:radius=292.7,axis_angle=1.0"),
                                         (1, "saddle:radius=-255.0,axis_angle=179.3")])
def test_a_graph_sheets_twist_carries_its_own_noise_which_describes_its_scatter_and_no_node_exceeds_3_sigma(index, spec):
    """That saddle's twist and its sign are read from the graph's stretch pattern: its s.d. is
    that reading's (graph_twist_sd), not the curvature product's, which left the sign open and
    put σ at 0.8 mm for errors of 0.04-0.07 (now 0.08, 0.8 where the twist is not trusted whole,
    one draw in eight).  The bench's other 16×16 saddle, 0.7° off the rows, whose sign the linear
    fit's slopes did not decide (its mirror left 0.105 of the stretch misfit, the answer 0.065),
    is decided by the refined ones (0.044 against 0.0056).  Over eight noisy draws the twist's
    scatter is within a factor of two of the s.d. said, and every node lies within 3σ + 0.05 mm
    of the truth after the best rigid alignment."""
    from conftest import bench_frame
    from skinmap.reconstruction.linalg import aligned_distances

    n = 16
    rec = Reconstructor(n, n, PITCH)
    twists, sds = [], []
    for draw in range(8):
        _, shape, eu, el = bench_frame("saddle", 2024, index, n, spec, draw)
        surf = rec(eu, el)
        sds.append(surf.diagnostics.extra.get("graph_twist_sd"))
        twists.append(surf.diagnostics.twist_constant)
        truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
        errors = aligned_distances(surf.nodes.reshape(-1, 3), truth)
        assert np.all(errors <= 3.0 * surf.node_sigma.reshape(-1) + 0.05), (draw, float(errors.max()))
    # (a frame whose twist is not trusted whole keeps the product's s.d.: one of the eight)
    assert sum(sd is not None for sd in sds) >= 6, sds
    said = float(np.mean([sd for sd in sds if sd is not None]))
    assert 0.5 * said <= float(np.std(twists, ddof=1)) <= 2.0 * said, (np.std(twists, ddof=1), said)


@pytest.mark.slow
def test_on_32x32_a_graph_sheets_twist_keeps_the_products_sd_and_a_twisted_quadric_stays_within_3_sigma_in_frame():
    """Where the noise alone leaves the model above one per gauge (32×32: 2.6) its answers are not
    the linear noise's: a twisted quadric (the kinematic bench's unseen seed-99 shape) whose σ
    came from the graph's own twist s.d. was 1.04 times 3σ + 0.05 mm off in the sensor frame on
    one of these four draws.  There the curvature product's s.d. stays: every node within
    3σ + 0.05 mm of the truth in the sensor frame."""
    from skinmap.reconstruction import nodes_in_sensor_frame

    n = 32
    shape = ph.Quadric(-0.00241876897083924, -0.0009267903681090468, 0.0032246955620116413)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)
    rec = Reconstructor(n, n, PITCH)
    truth = nodes_in_sensor_frame(rec.grid, shape.position)
    rng = np.random.default_rng(100)
    for draw in range(4):
        surf = rec(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape))
        ratio = np.linalg.norm(surf.nodes - truth, axis=-1) / (3.0 * surf.node_sigma + 0.05)
        assert ratio.max() <= 1.0, (draw, float(ratio.max()))
