"""Elastic scenes (films laminated on molds, skinmap.emulator.scenes) through the reconstruction,
and when the height-graph fit may answer (docs/reconstruction.md, step 0, "Acceptance"): only
where it explains the data within the noise *and* its surface is the general model's within
their combined uncertainty.  A film pre-stretched in its frame and laminated on a sphere or a
cylinder is not a height graph over its material coordinates, yet a graph with folds hidden
between the gauges explains its strains; the general model must answer it."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import aligned_error, bench_frame, elastic_dataset, frame_errors, worst_of_answers

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import GRAPH_AGREE_SIGMAS, Reconstructor, nodes_in_sensor_frame
from skinmap.reconstruction.engine import unit_data
from skinmap.reconstruction.graphfit import disagreement
from skinmap.reconstruction.linalg import aligned_distances
from skinmap.reconstruction.uncertainty import resolution_sigma

PITCH, H, G = 12.0, 0.2, 10.0
N = M = 5
NOISE = 0.0057e-2
CENTRES = ph.cell_centres(N, M, PITCH)
SIG_TURN = np.sqrt(2.0) * NOISE / (2 * H)  # one unit's turning per length, one s.d.
NOT_THE_GENERAL_MODEL = "not the general model's surface"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("mechanics-cache")


@pytest.fixture(scope="module")
def recs():
    """The default reconstruction (graph fit first on 5×5) and the general model alone."""
    return Reconstructor(N, M, PITCH, H, H, G), Reconstructor(N, M, PITCH, H, H, G, graph_fit=False)


def elastic(spec: str, cache, noise_seed: int | None = None):
    shape = parse_scene_spec(spec, "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
        eu, el = eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)
    return eu, el, ph.ground_truth(shape, N, M, PITCH).nodes


def noisy(shape, seed: int):
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    rng = np.random.default_rng(seed)
    return (eu, el), (eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape))


# 5 % pre-stretch on a convex sphere (the reported case: the graph fit gave 0.709 mm, node_sigma
# 0.011 mm) and a concave one, and 1 % on a flatter sphere (a weaker in-plane strain)
PRESTRETCHED_SPHERES = ["sphere:radius=61.2,prestretch=0.05", "sphere:radius=-70,prestretch=0.05",
                        "sphere:radius=120,prestretch=0.01"]


@pytest.mark.slow
@pytest.mark.parametrize("noise_seed", [None, 3], ids=["clean", "noisy"])
@pytest.mark.parametrize("spec", PRESTRETCHED_SPHERES)
def test_prestretched_elastic_sphere_5x5_is_within_0_05mm_mean_after_rigid_alignment_and_not_answered_by_the_graph_fit(
        recs, cache, spec, noise_seed):
    rec, general = recs
    eu, el, truth = elastic(spec, cache, noise_seed)
    surf = rec(eu, el)
    assert surf.diagnostics.extra["model"] == "general"
    # a graph explained the strains within the noise; the comparison with the general model refused it
    assert NOT_THE_GENERAL_MODEL in surf.diagnostics.extra["graph_fit"]
    assert surf.diagnostics.extra["graph_agreement"] > GRAPH_AGREE_SIGMAS
    assert np.array_equal(surf.nodes, general(eu, el).nodes)
    assert aligned_error(surf.nodes, truth) < 0.05


@pytest.mark.slow
def test_prestretched_elastic_cylinder_5x5_is_not_answered_by_the_graph_fit_and_is_the_general_models_surface(
        recs, cache):
    # the reported oblique case (the graph fit gave 1.30 mm); the general model's own accuracy on
    # it is a separate matter, this asserts only who answers
    rec, general = recs
    for seed in (None, 4):
        eu, el, _ = elastic("cylinder:radius=-54.4,axis_angle=78.9,prestretch=0.05", cache, seed)
        surf = rec(eu, el)
        assert surf.diagnostics.extra["model"] == "general"
        assert NOT_THE_GENERAL_MODEL in surf.diagnostics.extra["graph_fit"]
        assert np.array_equal(surf.nodes, general(eu, el).nodes)


@pytest.mark.slow
def test_prestretched_elastic_sphere_with_a_dead_gauge_or_after_a_graph_frame_is_within_0_05mm_and_not_graph_fitted(
        recs, cache):
    rec, _ = recs
    eu, el, truth = elastic("sphere:radius=61.2,prestretch=0.05", cache)
    dead = eu.copy()
    dead[1, 3, 3] = np.nan  # the missing unit's share of the comparison is no licence for a fold
    surf = rec(dead, el)
    assert surf.diagnostics.extra["model"] == "general" and aligned_error(surf.nodes, truth) < 0.05
    # a previous frame answered by a graph (a bump): this frame is checked again
    bump = ph.GaussianBumps(height=4.5, fwhm=16.0, centre=(-6.0, 11.0))
    prev = rec(*ph.gauge_strains(bump, N, M, PITCH, H, H, G))
    assert prev.diagnostics.extra["model"] == "graph"
    surf = rec(eu, el, previous=prev)
    assert surf.diagnostics.extra["model"] == "general" and aligned_error(surf.nodes, truth) < 0.05
    # noise-free use (strain_sigma=0) compares at the sensor's noise level, not at zero
    surf = rec(eu, el, strain_sigma=0.0)
    assert surf.diagnostics.extra["model"] == "general" and aligned_error(surf.nodes, truth) < 0.05


# sharp bumps (the spec corner, |h| 5 mm / FWHM 15 mm) and gentler ones, at places of their own
BUMPS = [(5.0, 15.0, (17.0, -9.0)), (-5.0, 15.0, (-8.0, -6.0)), (-5.0, 15.0, (-15.0, 18.0)),
         (2.5, 22.0, (4.0, -13.0)), (-1.5, 28.0, (-15.0, 3.0))]


@pytest.mark.parametrize("height, fwhm, centre", BUMPS)
def test_kinematic_bumps_are_still_answered_by_the_graph_fit_at_under_half_the_general_error_and_0_08mm_noisy(
        recs, height, fwhm, centre):
    rec, general = recs
    shape = ph.GaussianBumps(height=height, fwhm=fwhm, centre=centre)
    truth = shape.position(CENTRES)
    (eu, el), (nu, nl) = noisy(shape, int(10 * abs(height) + fwhm))
    surf = rec(eu, el)
    assert surf.diagnostics.extra["model"] == "graph"
    assert surf.diagnostics.extra["graph_agreement"] <= GRAPH_AGREE_SIGMAS
    assert aligned_error(surf.nodes, truth) < 0.5 * aligned_error(general(eu, el).nodes, truth)
    surf = rec(nu, nl)
    assert surf.diagnostics.extra["model"] == "graph"
    assert aligned_error(surf.nodes, truth) < 0.08
    # noise-free use still takes the graph (the comparison is made at the sensor's noise level)
    assert rec(eu, el, strain_sigma=0.0).diagnostics.extra["model"] == "graph"


def _trough(radius: float, angle: float) -> ph.Quadric:
    d = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
    return ph.Quadric(d[0] * d[0] / radius, d[0] * d[1] / radius, d[1] * d[1] / radius)


@pytest.mark.parametrize("shape", [ph.Saddle(60.0, axis_angle=30.0), ph.Saddle(-45.0), ph.Quadric(0.022, -0.018, 0.012),
                                   _trough(-70.0, 35.0)], ids=["turned saddle", "saddle", "twisted quadric", "trough"])
def test_kinematic_graphs_of_smooth_curvature_are_still_answered_by_the_graph_fit_within_0_001mm_clean_0_02mm_noisy(
        recs, shape):
    # smooth turning patterns leave the general model no resolution allowance: the graph agrees
    # with it within the noise (median about 0.1-0.4 s.d.) and is the more accurate of the two
    rec, _ = recs
    truth = shape.position(CENTRES)
    for i, (eu, el) in enumerate(noisy(shape, 7)):
        surf = rec(eu, el)
        assert surf.diagnostics.extra["model"] == "graph"
        assert surf.diagnostics.extra["graph_agreement"] <= GRAPH_AGREE_SIGMAS
        assert aligned_error(surf.nodes, truth) < (0.001 if i == 0 else 0.02)


def test_resolution_sigma_is_zero_for_an_affine_turning_pattern_and_bounds_the_general_models_error_on_a_bump(recs):
    rec, general = recs
    grid = rec.grid
    valid = np.ones((2, N, M), dtype=bool)
    uc = (np.arange(M) - (M - 1) / 2) * PITCH
    vc = (np.arange(N) - (N - 1) / 2) * PITCH
    affine = np.stack([0.012 + 1e-4 * uc[None, :] - 2e-4 * vc[:, None], -0.004 + 3e-4 * vc[:, None] + 0 * uc[None, :]])
    assert np.abs(resolution_sigma(grid, valid, affine, SIG_TURN)).max() < 1e-9
    rng = np.random.default_rng(1)  # noise alone: departures within the noise add (almost) nothing
    jitter = resolution_sigma(grid, valid, affine + rng.normal(0, SIG_TURN, affine.shape), SIG_TURN)
    assert np.median(jitter) < 0.03
    # a spec-corner bump: the general model's error after the best rigid alignment is well inside
    # the bound over most of the sheet (the bound is generous: about the bump's own height)
    shape = ph.GaussianBumps(height=5.0, fwhm=15.0, centre=(-8.0, -6.0))
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    turning, _, _ = unit_data(eu, el, H, H, G)
    bound = resolution_sigma(grid, valid, turning, SIG_TURN)
    uv = np.stack(np.broadcast_arrays(grid.u[None, :], grid.v[:, None]), axis=-1).reshape(-1, 2)
    truth = shape.position(uv).reshape(grid.nf, grid.mf, 3)
    fine = general(eu, el)._coeffs[:, :, 0, :]  # the general model's fine-grid positions
    assert disagreement(fine, truth, bound) < 0.5 and bound.max() < 3 * 5.0
    # a missing unit's departure is unknown with the measured units' spread: the bound stays finite
    gap = valid.copy()
    gap[0, 2, 2] = False
    assert np.isfinite(resolution_sigma(grid, gap, np.where(gap, turning, 0.0), SIG_TURN)).all()


def test_disagreement_is_the_median_distance_in_sigma_after_the_best_rigid_motion():
    rng = np.random.default_rng(2)
    uu, vv = np.meshgrid(np.linspace(-30, 30, 21), np.linspace(-30, 30, 21))
    surf = np.stack([uu, vv, 3.0 * np.exp(-(uu**2 + vv**2) / 200.0)], axis=-1)
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    moved = surf @ rot.T + np.array([1.0, -2.0, 5.0])
    tol = np.full(uu.shape, 0.01)
    assert disagreement(moved, surf, tol) < 1e-6  # a rigid motion is no disagreement
    shaken = surf + rng.normal(0, 0.01, surf.shape)  # 0.01 mm per coordinate: |d| / 0.01 ~ chi(3)
    assert 1.2 < disagreement(shaken, surf, tol) < 1.9
    tol[10, 10] = 0.0  # a node of zero tolerance (the sensor frame's origin) is left out
    assert np.isfinite(disagreement(shaken, surf, tol))


# A ridge of three bumps along a diagonal: the least-shear prior's twist (−0.0066 /mm) put the
# corners 3.7 mm off (1.40 mm mean); the model's own twist explains the film's stretch with a
# third of the misfit through each one's own Gaussian curvature (membrane.stretch_misfit)
DIAGONAL_RIDGE = ("gaussian:height=4.63,fwhm=20.9,u0=5.1,v0=-0.72 + gaussian:height=4.63,fwhm=20.9,u0=-3.48,v0=6.4"
                  " + gaussian:height=4.63,fwhm=20.9,u0=-12.05,v0=13.53")


@pytest.mark.parametrize("noise_seed", [None, 4], ids=["clean", "noisy"])
def test_least_shear_twist_the_stretch_contradicts_gives_way_on_a_diagonal_ridge_within_0_2mm(recs, cache, noise_seed):
    eu, el, truth = elastic(DIAGONAL_RIDGE, cache, noise_seed)
    surf = recs[1](eu, el)
    assert "least_shear_shift" not in surf.diagnostics.extra, surf.diagnostics.extra
    assert aligned_error(surf.nodes, truth) <= 0.2


def test_elastic_saddle_turned_to_129_deg_is_read_by_the_membrane_within_0_05mm(recs, cache):
    """Its stretch pattern is explained but for 8.6-9.7 % through the model's fields (the linear
    membrane with the true K leaves 3-9 %): read, 0.01 mm; refused at a bar of 8 %, the
    trace's interval left it 0.12 mm off."""
    eu, el, truth = elastic("saddle:radius=-109.7,axis_angle=129.1", cache)
    surf = recs[1](eu, el, twist_sign=None)
    assert surf.diagnostics.extra["stretch_reading"][0] == "membrane", surf.diagnostics.extra
    best = min(aligned_error(a.nodes, truth) for a in [surf] + ([surf.mirror] if surf.mirror is not None else []))
    assert best <= 0.05, best


@pytest.mark.parametrize("noise_seed", [None, 2], ids=["clean", "noisy"])
def test_friction_saddle_whose_sign_only_the_kinematic_misfit_prefers_is_flagged_with_a_mirror_within_0_2mm(
        recs, cache, noise_seed):
    """A film with friction on a saddle, R 85 mm at 54°: both signs read the gauges as well as
    the noise alone would (0.10 and 0.43 per gauge clean), and the one the kinematic forward
    model prefers is 4.4 mm off.  The other is not rejected: the answer is flagged ambiguous, and
    one of its two answers is within 0.2 mm."""
    eu, el, truth = elastic("saddle:radius=-85.4,axis_angle=53.9,friction=0.001", cache, noise_seed)
    surf = recs[1](eu, el)
    assert surf.mirror is not None and surf.diagnostics.extra["ambiguous"]
    best = min(aligned_error(a.nodes, truth) for a in (surf, surf.mirror))
    assert best <= 0.2, best


def test_each_twist_sign_weighed_at_its_own_best_magnitude_picks_a_turned_saddles_sign_on_every_noise_draw_within_0_05mm(
        recs, cache):
    """A saddle R 74 mm turned 32°: each sign prefers its own twist magnitude (0.0114 /mm the
    right one, 0.0120 the wrong one).  Weighed at the magnitude read on the first answer's
    family, the wrong sign won whenever that answer had it (here the 21st of these draws, 1 in 3
    of the bench's: 4.9 mm off, its flagged mirror right but 0.16 mm off); each at its own, the
    right sign wins on every draw."""
    shape = parse_scene_spec("saddle:radius=-74.0,axis_angle=31.6", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    rng = np.random.default_rng(21)
    errors = []
    for _ in range(24):
        surf = recs[1](eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape))
        errors.append(aligned_error(surf.nodes, truth))
    assert max(errors) <= 0.05, np.round(errors, 3)


@pytest.mark.slow
def test_a_twist_only_the_least_shear_prior_gives_carries_its_spread_so_every_node_is_within_3_sigma(cache):
    """A film with friction on a 12×12 saddle, R 286 mm at 49°: neither stretch reading explains
    its pattern, and the twist comes from the least-shear prior of a turned saddle alone, 12 %
    off (0.73 mm mean node error).  It was reported with node_sigma 0.048 mm; the prior's share
    of the twist now joins the spread, and every node of the answer is within 3σ + 0.05 mm."""
    n = 12
    shape = parse_scene_spec("saddle:radius=286.2,axis_angle=49.1,friction=0.001", "elastic", n, n, PITCH,
                             cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    assert "shear_prior_twist" in surf.diagnostics.extra
    err = aligned_distances(surf.nodes.reshape(-1, 3), truth)
    assert np.all(err <= 3.0 * surf.node_sigma.reshape(-1) + 0.05), float(np.max(err / (3.0 * surf.node_sigma.reshape(-1) + 0.05)))


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["saddle:radius=284.3,axis_angle=169.0,friction=0.001",
                                  "saddle:radius=233.8,axis_angle=107.8,friction=0.001"])
def test_a_twist_the_least_shear_prior_cannot_give_is_left_open_so_every_node_is_within_3_sigma(cache, spec):
    """Films with friction on 12×12 saddles near the grid lines.  (1) R 284 mm 11° off the rows:
    the least-shear prior asked for a negative square of the twist, which no twist gives; the
    answer took none for 1.3·10⁻³ /mm and was 1.7 mm mean off with node_sigma 0.05 mm (17.8
    times the bound).  (2) R 234 mm 18° off the columns: the prior's small twist, of the default
    sign and unflagged, for −2.5·10⁻³ /mm.  The twists whose squares lie within half the
    answer's Gaussian curvature, of either sign, now join node_sigma."""
    n = 12
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    assert "shear_prior_twist" in surf.diagnostics.extra and "stretch_reading" not in surf.diagnostics.extra
    worst = worst_of_answers(surf, truth)
    assert min(worst) <= 1.0, worst


@pytest.mark.parametrize("draw", [0, 1, 2])
def test_a_saddle_whose_stretch_only_bounds_the_twist_leaves_the_least_shear_prior_open_so_every_node_is_within_3_sigma(cache, draw):
    """A film with friction on a 5×5 saddle of R 93 mm 13.7° off the rows (twist 4.9·10⁻³ /mm).
    The stretch pattern's trace read the twist only as [0, 0.0082] /mm; the least-shear prior
    took none, and that none, which nothing confirmed, counted as read: 1.0 mm mean off with
    node_sigma 0.03 mm (18 times the bound).  A reading that only bounds the twist confirms
    nothing either: the prior's own reach now joins node_sigma."""
    n = 5
    shape = parse_scene_spec("saddle:radius=-93.1,axis_angle=13.7,friction=0.001", "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rng = np.random.default_rng(draw)
    eu, el = eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el, strain_sigma=NOISE)
    extra = surf.diagnostics.extra
    assert "shear_prior_twist" in extra and extra["stretch_reading"][0] == "trace"
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    assert min(worst_of_answers(surf, truth)) <= 1.0
    assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)


def _dataset_frame(key: str, index: int, n: int, spec: str, draw: int, cache, seed: int = 2024):
    """The elastic bench's scene ``index`` of class ``key`` at n×n, the film itself
    (conftest.bench_frame), and its true nodes: (plan, shape, upper strains, lower strains, true
    nodes (K, 3))."""
    plan, shape, eu, el = bench_frame(key, seed, index, n, spec, draw, elastic_cache=cache)
    return plan, shape, eu, el, ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)


@pytest.mark.slow
@pytest.mark.parametrize("draw", [1, 2, 5])
def test_a_noisy_12x12_cylinder_10_degrees_off_the_rows_takes_the_twist_two_readings_agree_on_within_0_15_mm(cache, draw):
    """A film on a 12×12 cylinder of R 225 mm 9.7° off the rows, its twist's sign told: the
    curvature product read its twist 3.3-3.9 s.d. above the noise, and the significance ramp
    shrank it to 0.29-0.56 of itself (0.44-0.67 mm mean off).  The least-shear prior, read
    independently, lands where the product's own reading does: that twist is now weighed as a
    choice, and taken.  (Since the product is read from the gauge pairs, 6–7 s.d. beyond its
    noise, its own twist is taken and the prior is not needed: 0.020–0.090 mm.)"""
    n = 12
    plan, _, eu, el, truth = _dataset_frame("cylinder", 1, n, "cylinder:radius=-224.9,axis_angle=9.7", draw, cache)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE, twist_sign=plan.twist_sign)
    extra = surf.diagnostics.extra
    assert "least_shear_shift" in extra or "pair_product" in extra
    assert aligned_error(surf.nodes, truth) <= 0.15


@pytest.mark.slow
@pytest.mark.parametrize("draw", [40, 142])
def test_a_12x12_cylinder_whose_least_shear_twist_overshoots_is_within_3_sigma_in_the_frame(cache, draw):
    """The same 12×12 cylinder, R 225 mm 9.7° off the rows (twist 7.4·10⁻⁴ /mm), its sign
    told: on these two of the bench's noisy frames (of 150, `--calibration-draws 150`) the
    least-shear twist taken was 9.0-9.1·10⁻⁴, 0.86-0.91 mm off at a corner, with σ reaching only
    back to the product's shrunk twist (1.37 and 1.14 times the bound).  The least-shear twist's
    own noise, which the same turning data give it through the curvature product, joins σ.
    (Since the product is read from the gauge pairs, these frames take its own twist, 0.07 mm
    off, 0.26-0.34 of the bound.)"""
    n = 12
    plan, shape, eu, el, _ = _dataset_frame("cylinder", 1, n, "cylinder:radius=-224.9,axis_angle=9.7", draw, cache)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el, strain_sigma=NOISE, twist_sign=plan.twist_sign)
    extra = surf.diagnostics.extra
    assert "least_shear_shift" in extra or "pair_product" in extra
    assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)


@pytest.mark.slow
def test_a_prestretched_12x12_cylinder_whose_stretch_looks_doubly_curved_leaves_the_products_twist_open(cache):
    """A film pre-stretched 5 % on a 12×12 cylinder of R 179 mm 6.8° off the columns (twist
    6.6·10⁻⁴ /mm), its sign told.  On this noisy frame of the bench's (draw 22 of 150) its
    stretch, which varies with the pre-stretch as a doubly curved sheet's would, ruled the twist
    out; the membrane's reading was declined and the trace's interval, [0, 0.0018] /mm, allowed
    none: no twist taken and none left open, 0.98 mm off with σ 0.063 (9.5 times 3σ + 0.05 mm).
    The twist the curvature product alone would be (4.4 s.d. beyond its noise) lies in that
    interval: the data have not decided, and it joins σ."""
    n = 12
    spec = "cylinder:radius=179.2,axis_angle=6.8,prestretch=0.05"
    plan, shape, eu, el, _ = _dataset_frame("cylinder_prestretch", 1, n, spec, 22, cache)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el, strain_sigma=NOISE, twist_sign=plan.twist_sign)
    assert surf.diagnostics.extra["stretch_reading"][0] == "trace"
    assert "trace_open_twist" in surf.diagnostics.extra
    assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)


@pytest.mark.slow
@pytest.mark.parametrize("index, spec, draw, passes", [(1, "cylinder:radius=300.1,axis_angle=-70.4", 78, False),
                                                       (0, "cylinder:radius=-228.0,axis_angle=-6.6", 46, True)])
def test_a_16x16_cylinder_whose_defect_correction_loses_the_twist_keeps_it_open_within_3_sigma(cache, index, spec,
                                                                                                draw, passes):
    """Films on 16×16 cylinders, their sign told, on noisy frames of the bench's (of 150): the
    general model read the twist (R 300 mm 70° off the rows: its product 10.8 s.d. beyond the
    noise) or left the product's open (R 228 mm 6.6° off them), and the defect correction's
    passes, which the gauges preferred, took it to none with nothing left open: 2.5 and 1.2 mm
    off with σ 0.07, 21.6 and 10.5 times 3σ + 0.05 mm.  The gauges' forward model cannot tell a
    twist from shear, so the twist the uncorrected model read stays open.  (Since the twist is
    read from the gauge pairs' product, the R 300 mm frame keeps its twist and takes no defect
    pass, 0.12 mm off; the R 228 mm frame still goes through one, ``passes``.)"""
    n = 16
    plan, shape, eu, el, truth = _dataset_frame("cylinder", index, n, spec, draw, cache)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el, strain_sigma=NOISE, twist_sign=plan.twist_sign)
    assert not passes or surf.diagnostics.extra.get("defect_steps", 0) >= 1
    assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)
    assert np.all(aligned_distances(surf.nodes.reshape(-1, 3), truth) <= 3.0 * surf.node_sigma.reshape(-1) + 0.05)


@pytest.mark.slow
@pytest.mark.parametrize("draw", [0, 1, 2, 3, 4])
def test_a_cylinder_whose_less_sheared_twist_has_no_sign_told_has_an_answer_within_3_sigma(cache, draw):
    """A noisy 5×5 cylinder of R 72 mm 5.6° off the columns, no sign told: on draw 1 the
    least-shear twist the product agreed with was taken with the default sign, 1.5 mm off at a
    corner, with σ reaching back only to the product's shrunk twist (1.2 times the bound).  Its
    magnitude is read twice and its sign not at all: the mirror is tried, and stands beside it.
    (With the product's exact noise statistics draw 1 reads its twist within three s.d. and takes
    none, 0.51 of the bound; with the product read from the gauge pairs, draw 4 is the one whose
    least-shear twist is contested, and draw 3's, which was, is taken by a margin the noise could
    undo, 0.60 of the bound.)"""
    _, _, eu, el, truth = _dataset_frame("cylinder", 0, N, "cylinder:radius=-72.2,axis_angle=-84.4", draw, cache)
    surf = Reconstructor(N, M, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    extra = surf.diagnostics.extra
    agreed = bool(extra.get("least_shear_contested")) and "least_shear_shift" in extra
    if agreed:
        assert surf.mirror is not None
    assert draw != 4 or agreed
    worst = worst_of_answers(surf, truth)
    assert min(worst) <= 1.0, worst


@pytest.mark.slow
@pytest.mark.parametrize("draw", [2, 19])
def test_a_saddle_near_the_rows_whose_reading_is_low_is_refined_and_every_node_is_within_3_sigma_in_the_frame(cache, draw):
    """A film on a 16×16 saddle, R 293 mm 1° off the rows (twist 1.2e-4 /mm, 1.1 mm at the far
    corners): on two noise draws of the bench's 20 the stretch reading fell below half its
    interval's top, the refinement was skipped, as for a sphere, and the answer (no twist) came
    with σ 0.065 mm, 2.3 times the bound.  A sheet whose curvature product is negative has only
    the stretch to tell its twist: it is refined, and the twists up to the larger reading join σ."""
    from skinmap.reconstruction import nodes_in_sensor_frame

    n = 16
    _, shape, eu, el, _ = _dataset_frame("saddle", 0, n, "saddle:radius=292.7,axis_angle=1.0", draw, cache)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el)
    assert "stretch_twist_refined" in surf.diagnostics.extra
    grid = rec.grid
    truth = nodes_in_sensor_frame(grid, shape.position)
    bound = 3.0 * surf.node_sigma + 0.05
    answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
    assert any(bool(np.all(np.linalg.norm(a.nodes - truth, axis=-1) <= bound)) for a in answers)


def _scatter_over_scatter_sigma(key: str, index: int, n: int, spec: str, draws: int, cache,
                                twist_sign: float | None = None) -> tuple[float, set[bool]]:
    """The median over the nodes (the frame's origin left out) of the scatter of ``draws`` noisy
    frames of a bench scene (each frame's better answer where it is flagged ambiguous, as the
    bench's calibration table takes it), over their mean node_scatter_sigma; and whether the
    frames moved to the stretch pattern's twist (with ``twist_sign``: whether they took a
    twist), as a set."""
    plan, shape, _, _, _ = _dataset_frame(key, index, n, spec, 0, cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    ed = elastic_dataset()
    nodes, scatter_sigma, moved = [], [], set()
    in_frame = nodes_in_sensor_frame(rec.grid, shape.position)
    for draw in range(draws):
        du, dl = ed.noise_draw(plan, draw, NOISE, eu.shape)
        surf = rec(eu + du, el + dl, strain_sigma=NOISE, twist_sign=twist_sign)
        better = ed.better_answer(surf, lambda p: np.linalg.norm(p - in_frame, axis=-1))
        nodes.append(better.nodes.reshape(-1, 3))
        scatter_sigma.append(surf.node_scatter_sigma.reshape(-1))
        moved.add("stretch_twist_moved" in surf.diagnostics.extra if twist_sign is None
                  else surf.diagnostics.twist_constant != 0.0)
    return ed.scatter_over_sigma(nodes, scatter_sigma), moved


def test_a_saddle_whose_twist_decision_the_noise_flips_has_a_scatter_sigma_that_describes_its_frames(cache):
    """A film (ν 0.3) on a 5×5 saddle of R 110 mm 6° off the rows.  Its stretch reading's
    interval clears none on most noisy frames, and the answer moves to the refined twist; on the
    others it reaches none, and the answer keeps none, 0.4 mm apart.  The part of σ said to
    scatter (node_scatter_sigma) did not carry that way: the frames scattered by 4.5 times it.
    Now the way between the two answers joins it (StretchTwist.contested)."""
    ratio, moved = _scatter_over_scatter_sigma("poisson_0.3", 1, 5, "saddle:radius=109.7,axis_angle=173.9,poisson=0.3",
                                               20, cache)
    assert moved == {True, False}  # the noise does flip the decision
    assert 0.7 <= ratio <= 1.5, ratio


@pytest.mark.slow
def test_a_12x12_saddle_whose_twist_decision_the_noise_flips_has_a_scatter_sigma_that_describes_its_frames(cache):
    """A film on a 12×12 saddle of R 286 mm 6.7° off the columns: 11 noisy frames of 20 moved to
    the refined twist, 9 kept none, 1.0 mm apart; the frames scattered by 4.7 times
    node_scatter_sigma."""
    ratio, moved = _scatter_over_scatter_sigma("saddle", 0, 12, "saddle:radius=285.7,axis_angle=83.3", 20, cache)
    assert moved == {True, False}
    assert 0.7 <= ratio <= 1.5, ratio


@pytest.mark.slow
def test_the_5x5_oblique_cylinders_scatter_by_0_7_to_1_5_times_their_scatter_sigma(cache):
    """The bench's two 5×5 films on oblique cylinders, their sign told (the σ calibration's
    class): the median over the two of each one's median node scatter / node_scatter_sigma over
    20 noisy frames.  The first, R 72 mm 5.6° off the columns, reads its curvature product 2.3-5.7
    s.d. above the noise, across the significance bar: some frames take a twist (the least-shear
    prior's, or the product's up its ramp), others none, 0.3 mm apart; it scattered by 2.0 times
    node_scatter_sigma and the class by 1.51.  The ramp's slope and a decision taken by less than
    the noise undoes now join the scatter part."""
    first, took = _scatter_over_scatter_sigma("cylinder", 0, 5, "cylinder:radius=-72.2,axis_angle=-84.4", 20, cache,
                                              twist_sign=1.0)
    second, _ = _scatter_over_scatter_sigma("cylinder", 1, 5, "cylinder:radius=53.7,axis_angle=34.0", 20, cache,
                                            twist_sign=1.0)
    assert took == {True, False}  # the noise does flip the first one's decision
    assert 0.7 <= float(np.median([first, second])) <= 1.5, (first, second)


@pytest.mark.parametrize("draw", [1, 3])
def test_each_sign_of_a_saddle_is_weighed_at_its_own_twist_and_the_right_one_is_within_0_05_mm(cache, draw):
    """A film (ν 0.3) on an 8×8 saddle of R 122 mm at 143°, whose general model started with the
    wrong sign on these noisy frames.  Both signs are modelled afresh, each at the twist its own
    family explains the stretch pattern best; the right sign's refined twist lay 4.7 % under the
    wrong one's (0.00728 against 0.00764 /mm), within the share that spared it a model of its
    own, so it was weighed at the other's twist: it explained the stretch 4.6 times worse than
    the wrong sign, which was taken, and the right image (the mirror) was 0.20-0.22 mm off.  At
    its own twist it explains the stretch 4.3 times better than the wrong sign."""
    n = 8
    _, _, eu, el, truth = _dataset_frame("poisson_0.3", 0, n, "saddle:radius=122.3,axis_angle=143.2,poisson=0.3",
                                         draw, cache)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    assert aligned_error(surf.nodes, truth) <= 0.05
    assert worst_of_answers(surf, truth)[0] <= 1.0


@pytest.mark.parametrize("draw", [0, 1, 2])
def test_a_ridge_beside_the_centre_is_within_3_sigma_after_the_best_rigid_alignment_too(cache, draw):
    """A film on a 5×5 ridge of three bumps beside the centre (the bench's first ridge scene).
    In the sensor frame every node was within 3 node_sigma + 0.05 mm, but the frame pins the
    centre node, whose σ was zero: after a reference's best rigid fit, which shares the nodes'
    centroid, the centre stood 1.5-2.3 times beyond the bound (0.1 mm off).  The alignment floor
    (uncertainty.alignment_floor) covers it."""
    n = 5
    spec = ("gaussian:height=-2.84,fwhm=16.99,u0=10.02,v0=3.67 + gaussian:height=-2.84,fwhm=16.99,u0=10.4,v0=11.49 + "
            "gaussian:height=-2.84,fwhm=16.99,u0=10.78,v0=19.31")
    plan, shape, eu, el, truth = _dataset_frame("ridge", 0, n, spec, draw, cache)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el, strain_sigma=NOISE)
    assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)
    assert min(worst_of_answers(surf, truth)) <= 1.0


@pytest.mark.slow
def test_a_twist_the_stretch_reads_is_not_vetoed_where_both_answers_read_the_gauges_within_the_noise(cache):
    """A film on a 12×12 saddle of R 221 mm 39° off the rows (the bench's seed-777 scene), one
    noisy frame: two defect passes left the least-shear answer at 0.58 per gauge, and the stretch
    pattern's twist, modelled afresh, read 0.99; the gauges' veto kept the first, 0.83 mm mean
    off.  Both read the gauges within the noise the data carry, so the difference rejects
    neither: the answer moves to the pattern's twist, as on the other 19 frames."""
    n = 12
    plan, _, eu, el, truth = _dataset_frame("saddle", 0, n, "saddle:radius=220.9,axis_angle=39.4", 15, cache, seed=777)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    extra = surf.diagnostics.extra
    assert "stretch_twist_rejected" not in extra and "stretch_twist_moved" in extra
    assert min(aligned_error(a.nodes, truth) for a in [surf] + ([surf.mirror] if surf.mirror is not None else [])) <= 0.15
