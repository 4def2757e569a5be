"""The free-edge membrane's reading of the twist and of ν (skinmap.reconstruction.membrane): its
biharmonic solve against the clamped plate's closed form, its stretch against the Airy relation,
its refusals, and on films solved by the emulator's finite elements (saddles turned near the grid
lines, which the trace alone could not tell from untwisted ones)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as spl
from conftest import elastic_dataset, frame_errors

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import Reconstructor, default_subdivision
from skinmap.reconstruction import reconstructor as reconstructor_module
from skinmap.reconstruction.airy import trace_laplacian
from skinmap.reconstruction.engine import unit_data
from skinmap.reconstruction.grid import FineGrid
from skinmap.reconstruction.linalg import aligned_distances
from skinmap.reconstruction.membrane import (
    _clamped_biharmonic,
    _linspace,
    basis_curvature,
    membrane_maps,
    read_twist,
    stretch_misfit,
)

PITCH, H, G = 12.0, 0.2, 10.0
NOISE = 5.7e-5


def test_the_reading_s_grids_are_numpy_s_linspace_to_the_bit():
    """read_twist's ν and twist grids (its own steps, without np.linspace's generality)."""
    rng = np.random.default_rng(12)
    for num in (2, 21, 401):
        for _ in range(300):
            start = float(rng.normal() * 10.0 ** rng.uniform(-16, 1))
            stop = start + float(abs(rng.normal()) * 10.0 ** rng.uniform(-16, 1))
            assert np.array_equal(_linspace(start, stop, num), np.linspace(start, stop, num))
            assert np.array_equal(_linspace(-stop, stop, num), np.linspace(-stop, stop, num))
    assert np.array_equal(_linspace(0.3, 0.5, 21), np.linspace(0.3, 0.5, 21))
    assert np.array_equal(_linspace(1.0, 1.0, 5), np.linspace(1.0, 1.0, 5))


def test_the_biharmonic_solve_gives_the_clamped_square_plates_deflection_within_1_percent():
    """∇⁴φ = q with φ = ∂φ/∂n = 0 on a square of side a: φ at the centre is 0.00126·q·a⁴
    (Timoshenko and Woinowsky-Krieger, the clamped square plate under uniform load, D = 1)."""
    side = 72.0
    for nodes in (49, 65):
        matrix, interior = _clamped_biharmonic(nodes, nodes, side / (nodes - 1))
        phi = np.zeros(nodes * nodes)
        phi[interior] = spl.splu(matrix).solve(np.ones(interior.size))
        centre = phi.reshape(nodes, nodes)[nodes // 2, nodes // 2]
        assert centre / side ** 4 == pytest.approx(0.00126, rel=0.01), nodes


@pytest.mark.parametrize("nu", [0.3, 0.48])
def test_a_uniform_gaussian_curvature_gives_the_stretch_trace_airys_relation_asks(nu):
    """For any outline, ∇²(ε_uu + ε_vv) = −(1 − ν)·K: the maps' unit stretches for a constant K,
    read through the trace's 7-term fit, give that Laplacian within 5 %."""
    n = 7
    grid = FineGrid(n, n, PITCH, G, sub=default_subdivision(n, n))
    maps = membrane_maps(grid)
    k = 2e-4
    field = np.full(maps.a.shape[1], k)
    stretch = ((maps.a + nu * maps.b) @ field).reshape(2, n, n)
    fit = trace_laplacian(stretch[0] + stretch[1], PITCH)
    assert fit.laplacian == pytest.approx(-(1.0 - nu) * k, rel=0.05)


def test_noise_alone_and_a_pattern_the_membrane_cannot_explain_are_no_reading():
    n = 5
    grid = FineGrid(n, n, PITCH, G, sub=default_subdivision(n, n))
    maps = membrane_maps(grid)
    rng = np.random.default_rng(4)
    valid = np.ones((2, n, n), dtype=bool)
    flat = np.zeros((grid.nf, grid.mf))
    noise = 1.0 + rng.normal(0.0, NOISE, (2, n, n))
    assert read_twist(maps, noise, valid, flat, flat, flat, grid.inner, (0.3, 0.5), NOISE) is None
    # a stretch pattern with no Gaussian curvature behind it (a saddle's curvatures, turned,
    # but the stretch of a random field): the fit explains little of it
    k_u = np.full((grid.nf, grid.mf), 0.01)
    pattern = 1.0 + 3e-3 * rng.standard_normal((2, n, n))
    assert read_twist(maps, pattern, valid, k_u, -k_u, flat, grid.inner, (0.3, 0.5), NOISE) is None
    with pytest.raises(ValueError, match="film margin"):
        membrane_maps(grid, margin=-1.0)


@pytest.mark.parametrize("n", [5, 12])
@pytest.mark.parametrize("nu", [0.3, 0.48])
def test_a_twist_only_the_stretch_shows_is_read_within_2_percent(n, nu):
    """A saddle at 45° turns no gauge (k_u = k_v = 0, no twist field): its twist m shows in the
    stretch alone, through K = −m².  The twists tried must reach it: they reached 4·√|k_u k_v −
    τ₀²| only, nothing here (a 12×12 elastic saddle of R 272 mm at 48.6° went unread, 0.7 mm
    off).  The stretch is the maps' own forward model: this checks the search only; the
    emulator's finite-element films check the physics (the 12×12 test below)."""
    grid = FineGrid(n, n, PITCH, G, sub=default_subdivision(n, n))
    maps = membrane_maps(grid)
    m = 3.6e-3
    stretch = 1.0 + ((maps.a + nu * maps.b) @ np.full(maps.a.shape[1], -m * m)).reshape(2, n, n)
    flat = np.zeros((grid.nf, grid.mf))
    valid = np.ones((2, n, n), dtype=bool)
    reading = read_twist(maps, stretch, valid, flat, flat, flat, grid.inner, (0.3, 0.5), NOISE)
    assert reading is not None
    assert reading.twist == pytest.approx(m, rel=0.02) and reading.low <= m <= reading.high, reading
    assert reading.poisson == pytest.approx(nu, abs=0.02)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("mechanics-cache")


@pytest.mark.parametrize("spec, nu", [("saddle:radius=90,axis_angle=76", 0.48),
                                      ("saddle:radius=-105,axis_angle=167,poisson=0.35", 0.35)])
def test_the_emulators_saddle_surface_read_with_its_own_curvature_explains_the_stretch_and_gives_its_poisson(
        spec, nu, cache):
    """The membrane model against the emulator's finite elements: the film's own Gaussian
    curvature (from its solved positions) through the maps explains its gauges' stretch to a few
    percent of the pattern, at the film's ν (within 0.05)."""
    n = 5
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    grid = FineGrid(n, n, PITCH, G, sub=default_subdivision(n, n))
    uu, vv = np.meshgrid(grid.u, grid.v)
    positions = shape.position(np.stack([uu, vv], axis=-1))
    maps = membrane_maps(grid)
    _, stretch, valid = unit_data(eu, el, H, H, G)
    rss, poisson = stretch_misfit(maps, basis_curvature(maps, positions, grid.spacing), stretch, valid, (0.2, 0.5))
    centred = stretch - stretch.mean(axis=(1, 2), keepdims=True)
    assert np.sqrt(rss / centred.size) <= 0.06 * np.sqrt(np.mean(centred ** 2))
    assert abs(poisson - nu) <= 0.05


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["saddle:radius=90,axis_angle=76", "saddle:radius=-105,axis_angle=167,poisson=0.35",
                                  "saddle:radius=75,axis_angle=10"])
def test_an_elastic_saddle_turned_near_the_grid_lines_5x5_is_within_0_1mm_and_3_sigma(spec, cache):
    """A film on a saddle turned 10-15° off the grid lines: the trace alone could not tell its
    twist from an untwisted saddle of larger radius, and the answer was 0.9-1.3 mm off with σ
    0.035 mm.  The membrane's reading (twist and ν together) puts it within 0.1 mm, every node
    within 3 node_sigma + 0.05 mm (with noise; for an answer said to be ambiguous, one of the
    two)."""
    n = 5
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    for draw in range(2):
        noise = np.random.default_rng(20 + draw).normal(0.0, NOISE, (2, 2, n, n))
        surf = rec(eu + noise[0], el + noise[1], strain_sigma=NOISE)
        assert surf.diagnostics.extra["stretch_reading"][0] == "membrane", surf.diagnostics.extra
        bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
        answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
        errors = [aligned_distances(s.nodes.reshape(-1, 3), truth) for s in answers]
        assert any(np.all(e <= bound) for e in errors), (spec, draw, [e.max() for e in errors], bound.min())
        assert min(e.mean() for e in errors) <= 0.1, (spec, draw, [e.mean() for e in errors])


@pytest.mark.slow
def test_a_saddle_whose_wrong_sign_fits_the_stretch_better_is_said_to_be_ambiguous_with_the_mirror_within_0_1mm(cache):
    """R 95 mm at 120°: the surface of the wrong sign explains the stretch pattern five times
    better than the right one, so the stretch does not tell the sign: the answer says so
    (Surface.mirror), and the other image is within 0.1 mm and within 3 node_sigma + 0.05 mm."""
    n = 5
    shape = parse_scene_spec("saddle:radius=95,axis_angle=120", "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    assert surf.mirror is not None and surf.diagnostics.extra["ambiguous"]
    errors = [aligned_distances(s.nodes.reshape(-1, 3), truth) for s in (surf, surf.mirror)]
    best = min(errors, key=lambda e: e.mean())
    assert best.mean() <= 0.1 and np.all(best <= 3.0 * surf.node_sigma.reshape(-1) + 0.05)


@pytest.mark.slow
def test_a_held_saddle_starts_each_frame_at_the_last_twist_and_a_sphere_after_it_goes_back_to_the_prior(cache):
    """Frame after frame of a still elastic saddle, each frame's general model starts at the last
    frame's estimate (no frame is modelled afresh once the first has moved); the next shape, a
    sphere, is not held to the saddle's twist: it is within 0.05 mm like a sphere seen cold."""
    n = 5
    rec = Reconstructor(n, n, PITCH, H, H, G)
    rng = np.random.default_rng(31)
    answers = []
    for spec, frames in (("saddle:radius=90,axis_angle=75", 4), ("sphere:radius=70", 3)):
        shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
        eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
        truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
        for _ in range(frames):
            noise = rng.normal(0.0, NOISE, (2, 2, n, n))
            previous = answers[-1][1] if answers else None
            surf = rec(eu + noise[0], el + noise[1], strain_sigma=NOISE, previous=previous)
            images = [surf] + ([surf.mirror] if surf.mirror is not None else [])
            error = min(aligned_distances(s.nodes.reshape(-1, 3), truth).mean() for s in images)
            answers.append((spec, surf, error))
    saddle = [a for a in answers if a[0].startswith("saddle")]
    assert "stretch_twist_moved" in saddle[0][1].diagnostics.extra
    assert all("stretch_twist_moved" not in s.diagnostics.extra for _, s, _ in saddle[1:])
    assert all(e <= 0.1 for _, _, e in saddle), [e for _, _, e in saddle]
    sphere = [a for a in answers if a[0].startswith("sphere")]
    assert all(e <= 0.05 for _, _, e in sphere), [e for _, _, e in sphere]


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["saddle:radius=272,axis_angle=35,poisson=0.3",
                                  "saddle:radius=150,axis_angle=45,poisson=0.3"])
def test_a_sign_the_stretch_prefers_by_less_than_its_noise_leaves_the_answer_within_0_05mm(spec, cache):
    """ν 0.3 saddles near 45° on 5×5: the surface of the wrong sign explains the stretch pattern
    three times better, by a third of the s.d. the stated noise gives that difference.  Taken,
    the answer was 1.4-2.7 mm off (flagged); a sign told by less than the noise is not taken
    (SIGN_SIGMAS), and the answer, still flagged (the other sign is its mirror), is within
    0.05 mm."""
    n = 5
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    assert surf.diagnostics.extra["stretch_reading"][0] == "membrane", surf.diagnostics.extra
    assert surf.mirror is not None
    error = aligned_distances(surf.nodes.reshape(-1, 3), truth).mean()
    assert error <= 0.05, (error, surf.diagnostics.extra)


@pytest.mark.slow
def test_a_12x12_saddle_near_45_degrees_is_read_from_its_stretch_within_0_05mm(cache):
    """R 272 mm at 48.6°, ν 0.3: the gauges hardly turn (k_u k_v is 1.6 % of the twist's
    square), so the twist is the stretch pattern's.  Unread (the twists tried did not reach it),
    the least-shear prior left it 0.70 mm off; read, 0.003 mm."""
    n = 12
    shape = parse_scene_spec("saddle:radius=272.2,axis_angle=48.6,poisson=0.3", "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    assert surf.diagnostics.extra["stretch_reading"][0] == "membrane", surf.diagnostics.extra
    assert aligned_distances(surf.nodes.reshape(-1, 3), truth).mean() <= 0.05, surf.diagnostics.extra


@pytest.mark.slow
def test_a_saddle_1_degree_off_the_grid_lines_reads_as_the_same_saddle_on_them_and_is_within_3_sigma(cache):
    """An 8×8 film on a saddle of R 150 mm turned by 1° (twist sin 2φ / R = 2.3·10⁻⁴ /mm): its
    membrane stress depends on the Gaussian curvature, which the turn does not change, and its
    gauges turn by cos 2φ / R, which the turn changes by 6·10⁻⁴ of the curvature: every gauge of
    the 1° film and of the same saddle on the grid lines read alike (χ² below 1 over all 256
    against the sensor's noise).  The data cannot decide that twist; the answer keeps none and
    is 0.13 mm off (0.4 at the corners), which its σ says (every node within 3 node_sigma +
    0.05 mm), and its error is that twist alone (the answer moved along the twist mode by the
    true twist lands within 0.03 mm)."""
    n, radius = 8, 150.0
    readings = {}
    for angle in (0.0, 1.0):
        shape = parse_scene_spec(f"saddle:radius={radius},axis_angle={angle}", "elastic", n, n, PITCH,
                                 cache_dir=cache)
        readings[angle] = (shape, *ph.gauge_strains(shape, n, n, PITCH, H, H, G))
    shape, eu, el = readings[1.0]
    apart = np.concatenate([(eu - readings[0.0][1]).ravel(), (el - readings[0.0][2]).ravel()])
    assert np.sum(apart ** 2) / NOISE ** 2 < 1.0
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    nodes = surf.nodes.reshape(-1, 3)
    errors = aligned_distances(nodes, truth)
    assert np.all(errors <= 3.0 * surf.node_sigma.reshape(-1) + 0.05), (errors.max(), surf.node_sigma.min())
    twist = np.sin(np.radians(2.0)) / radius
    moved = nodes + np.outer(nodes[:, 0] * nodes[:, 1], [0.0, 0.0, 1.0])
    shifted = [aligned_distances(nodes + c * (moved - nodes), truth).mean() for c in np.linspace(0.0, 2.0 * twist, 41)]
    assert errors.mean() > 0.05 and min(shifted) <= 0.03, (errors.mean(), min(shifted))


@pytest.mark.parametrize("n, m", [(5, 5e-3), (8, 2.5e-3), (8, 5e-3)])
def test_the_readings_noise_sd_is_the_scatter_of_its_twist_over_noisy_stretch(n, m):
    """TwistReading.noise_sd (the profile over ν within 2 noise s.d. of its best) against the
    scatter of the reading over 60 draws of the stretch noise, on a saddle at 45° (the twist in
    the stretch alone, ν 0.45): the ratio within [0.8, 1.3]."""
    grid = FineGrid(n, n, PITCH, G, sub=default_subdivision(n, n))
    maps = membrane_maps(grid)
    stretch = 1.0 + ((maps.a + 0.45 * maps.b) @ np.full(maps.a.shape[1], -m * m)).reshape(2, n, n)
    flat = np.zeros((grid.nf, grid.mf))
    valid = np.ones((2, n, n), dtype=bool)
    sd = NOISE / np.sqrt(2.0)  # one stretch reading: the mean of two layers' strains
    rng = np.random.default_rng(21)
    twists, said = [], []
    for _ in range(60):
        reading = read_twist(maps, stretch + rng.normal(0.0, sd, stretch.shape), valid, flat, flat, flat, grid.inner,
                             (0.3, 0.5), sd)
        assert reading is not None
        twists.append(reading.twist)
        said.append(reading.noise_sd)
    ratio = float(np.std(twists) / np.mean(said))
    assert 0.8 <= ratio <= 1.3, ratio


@pytest.mark.slow
def test_a_saddle_that_grows_slowly_keeps_its_sign_frame_after_frame(cache):
    """A 5×5 elastic saddle at 60° whose radius grows 0.5 % a frame (90 to 110 mm over 40 frames),
    streamed with ``previous``: the carried twist lags the sheet within MOVE_SHARE, and at that
    lagging twist the mirror on the answer's own family explained the stretch with half the
    misfit.  Taken as the sign, 10 of the 40 frames changed sign (3.6 mm off, flagged, each
    turned back on the next).  The carried sign is now weighed against the other with both
    modelled afresh: no frame changes sign, and every frame is within 3σ + 0.05 mm in the
    sensor frame."""
    n = 5
    rec = Reconstructor(n, n, PITCH, H, H, G)
    rng = np.random.default_rng(5)
    surf, signs = None, []
    for i in range(40):
        shape = parse_scene_spec(f"saddle:radius={90 + 0.5 * i:.1f},axis_angle=60", "elastic", n, n, PITCH,
                                 cache_dir=cache)
        eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
        surf = rec(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape), previous=surf)
        signs.append(float(np.sign(surf.diagnostics.twist_constant)))
        images = [surf] + ([surf.mirror] if surf.mirror is not None else [])
        ratio = min(float(np.max(frame_errors(shape, s, rec.grid) / (3.0 * s.node_sigma + 0.05)))
                    for s in images)
        assert ratio <= 1.0, (i, ratio)
    assert len(set(signs)) == 1 and signs[0] != 0.0, signs


@pytest.mark.slow
def test_a_prestretched_32x32_film_on_an_oblique_cylinder_is_not_taken_for_a_doubly_curved_sheet(cache):
    """A film pre-stretched 5 % on a cylinder of R 407 mm at −43° (a 384 mm sheet) relaxes at its
    edges by about as much stretch as the untwisted, doubly curved sheet would need, and that
    sheet was kept: 12.5 mm mean off, 47 mm at a corner, with σ 0.12 mm.  The stretch pattern
    itself (through each candidate's own Gaussian curvature) prefers the cylinder's twist by a
    factor of three: the answer takes it, within 3σ + 0.05 mm in the sensor frame, and its mean
    node error is within 1.5 mm."""
    n = 32
    shape = parse_scene_spec("cylinder:radius=-406.7,axis_angle=-43.3,prestretch=0.05", "elastic", n, n, PITCH,
                             cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf = rec(eu, el, strain_sigma=NOISE, twist_sign=1.0)
    assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)
    assert aligned_distances(surf.nodes.reshape(-1, 3), truth).mean() <= 1.5


@pytest.mark.slow
def test_a_32x32_cylinder_whose_twist_is_within_the_products_noise_is_within_3_sigma(cache, monkeypatch):
    """A film (ν 0.3) on a cylinder of R 374 mm 8° off the columns, 32×32: its twist, 3.8·10⁻⁴
    /mm, lies within the curvature product's noise, and the answer keeps none (3.5 mm mean off,
    13 mm at a corner).  The twist the product read and the answer did not take joins σ, reached
    past by 2 s.d. of the product's noise (in the square): every node within 3σ + 0.05 mm in the
    sensor frame (it was 1.14 × that at a corner on this draw, the benchmark's).  The defect
    correction's averaged pass (``DEFECT_SMOOTH_UNITS``) now takes the twist on this frame (0.38 mm
    mean off); with the average over one unit (the raw residual again) the twist is left open as
    before."""
    n = 32
    shape = parse_scene_spec("cylinder:radius=-374.4,axis_angle=-81.7,poisson=0.3", "elastic", n, n, PITCH,
                             cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rng = np.random.default_rng([2024, 1722036517, 32, 32, 0, 2])  # the benchmark's first noisy draw
    du, dl = rng.normal(0.0, NOISE, eu.shape), rng.normal(0.0, NOISE, el.shape)
    for units in (1, reconstructor_module.DEFECT_SMOOTH_UNITS):
        monkeypatch.setattr(reconstructor_module, "DEFECT_SMOOTH_UNITS", units)
        rec = Reconstructor(n, n, PITCH, H, H, G)
        surf = rec(eu + du, el + dl, twist_sign=1.0)
        if units == 1:
            assert "undecided_twist" in surf.diagnostics.extra  # the case: a twist left within the noise
        assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)


@pytest.mark.slow
def test_a_noisy_32x32_saddle_takes_the_sign_its_stretch_pattern_reads_within_0_3_mm(cache, monkeypatch):
    """A film on a saddle of R 431 mm at 150° (a 384 mm sheet), with the sensor's noise.  The
    stretch pattern reads the twist's other sign seven times better than the least-shear
    answer's, but the gauges' χ² vetoed the move (5.5 per gauge at the right sign's twist against
    2.1 at the wrong one's): the answer was 31 mm mean off, flagged ambiguous with a mirror 2.3 mm
    off.  On a sheet this large the noise alone reaches 5-13 per gauge at a held twist, so the
    difference proves nothing: the answer takes the pattern's sign, within 0.3 mm mean (the
    target) and within 3σ + 0.05 mm in the sensor frame.  The defect correction's averaged pass
    (``DEFECT_SMOOTH_UNITS``) now answers this frame before the veto is asked (0.19 mm); with
    the average over one unit (the raw residual again) the veto is weighed as before (0.25 mm)."""
    n = 32
    ed = elastic_dataset()
    plan = ed.class_plans("saddle", 2024, 1, n)[0]
    assert plan.spec == "saddle:radius=430.6,axis_angle=150.4"
    shape = parse_scene_spec(plan.spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    du, dl = ed.noise_draw(plan, 0, NOISE, eu.shape)  # the benchmark's first noisy draw
    for units in (1, reconstructor_module.DEFECT_SMOOTH_UNITS):
        monkeypatch.setattr(reconstructor_module, "DEFECT_SMOOTH_UNITS", units)
        rec = Reconstructor(n, n, PITCH, H, H, G)
        surf = rec(eu + du, el + dl, strain_sigma=NOISE)
        if units == 1:
            assert "noise_reach_chi2_per_gauge" in surf.diagnostics.extra  # the case: the gauges' veto weighed
        assert surf.diagnostics.twist_constant < 0.0  # the saddle's own sign (sin 300.8° < 0)
        assert aligned_distances(surf.nodes.reshape(-1, 3), truth).mean() <= 0.3
        assert np.all(frame_errors(shape, surf, rec.grid) <= 3.0 * surf.node_sigma + 0.05)
