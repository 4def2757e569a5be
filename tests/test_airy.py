"""The Gaussian curvature a film's stretch pattern implies (skinmap.reconstruction.airy): the fit
against its closed form, its refusals, and on films solved by the emulator's mechanics; and the
elastic prior's use of it on noisy data (an answer in another valley is declined or its σ says so)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import aligned_error, frame_errors

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.airy import MIN_UNITS, airy_curvature_range, airy_gaussian_curvature, trace_laplacian
from skinmap.reconstruction.engine import unit_data
from skinmap.reconstruction.linalg import aligned_distances
from skinmap.reconstruction.positionfit import PositionFitSettings

PITCH, H, G = 12.0, 0.2, 10.0
N = M = 5
NOISE = 5.7e-5


def test_the_trace_laplacian_is_read_through_any_harmonic_part_and_constant():
    vc = (np.arange(6) - 2.5) * PITCH
    uc = (np.arange(7) - 3.0) * PITCH
    vv, uu = np.meshgrid(vc, uc, indexing="ij")
    b = -3e-6
    harmonic = 2e-4 * uu - 1e-4 * vv + 3e-7 * (uu ** 2 - vv ** 2) - 2e-7 * uu * vv + 1e-10 * (uu ** 4 - 6 * uu ** 2 * vv ** 2 + vv ** 4)
    trace = 0.01 + b * (uu ** 2 + vv ** 2) + harmonic
    fit = trace_laplacian(trace, PITCH)
    assert abs(fit.laplacian - 4 * b) < 1e-12 and fit.residual_rms < 1e-12
    noisy = trace + np.random.default_rng(0).normal(0.0, 1e-5, trace.shape)
    fit = trace_laplacian(noisy, PITCH)
    assert abs(fit.laplacian - 4 * b) <= 4 * fit.sd and fit.sd > 0


def test_the_fit_cached_per_mask_equals_a_fresh_least_squares_fit():
    """The 7-term fit's operator is kept per validity mask; each mask's fit is numpy's lstsq."""
    rng = np.random.default_rng(3)
    for n, m, holes in ((5, 5, 0), (5, 5, 2), (12, 12, 3), (6, 7, 1), (5, 5, 2)):
        trace = rng.normal(0.0, 1e-3, (n, m))
        trace.ravel()[rng.choice(n * m, holes, replace=False)] = np.nan
        fit = trace_laplacian(trace, PITCH)
        ok = np.isfinite(trace)
        vv, uu = np.meshgrid((np.arange(n) - (n - 1) / 2.0) * PITCH, (np.arange(m) - (m - 1) / 2.0) * PITCH, indexing="ij")
        cols = [np.ones_like(uu), uu ** 2 + vv ** 2, uu, vv, uu ** 2 - vv ** 2, uu * vv, uu ** 4 - 6 * uu ** 2 * vv ** 2 + vv ** 4]
        a = np.stack([c[ok] for c in cols], axis=1)
        coef = np.linalg.lstsq(a, trace[ok], rcond=None)[0]
        resid = trace[ok] - a @ coef
        sd = 4.0 * np.sqrt(float(resid @ resid) / (ok.sum() - 7) * np.linalg.pinv(a.T @ a)[1, 1])
        assert np.isclose(fit.laplacian, 4.0 * coef[1], rtol=1e-9, atol=0.0)
        assert np.isclose(fit.sd, sd, rtol=1e-9, atol=0.0)
        assert np.isclose(fit.residual_rms, np.sqrt(float(resid @ resid) / ok.sum()), rtol=1e-9, atol=0.0)


def test_too_few_units_or_a_wrong_shape_are_refused_by_name():
    trace = np.full((3, 3), 0.01)
    with pytest.raises(ValueError, match=f"at least {MIN_UNITS}"):
        trace_laplacian(trace, PITCH)
    with pytest.raises(ValueError, match=r"\(N, M\)"):
        trace_laplacian(np.zeros(12), PITCH)
    nan = np.full((2, 4, 4), 1.0)
    valid = np.ones((2, 4, 4), bool)
    valid[0, :, :2] = False  # half the units lack a u gauge
    with pytest.raises(ValueError, match="units with both gauges"):
        airy_gaussian_curvature(nan, valid, PITCH, 0.48)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("mechanics-cache")


@pytest.mark.slow
@pytest.mark.parametrize("radius", [75.0, -62.0])
def test_an_elastic_film_on_a_sphere_reads_its_gaussian_curvature_within_the_stated_error(radius, cache):
    shape = parse_scene_spec(f"sphere:radius={radius}", "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    _, stretch, valid = unit_data(eu, el, H, H, G)
    k, sd = airy_gaussian_curvature(stretch, valid, PITCH, 0.48)
    assert abs(k - 1.0 / radius ** 2) <= 2 * sd


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["saddle:radius=100,axis_angle=35", "sphere:radius=72,friction=0.001"])
def test_the_elastic_prior_on_noisy_data_is_within_3_sigma_plus_0_05mm(spec, cache):
    shape = parse_scene_spec(spec, "elastic", N, M, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    rec = Reconstructor(N, M, PITCH, H, H, G, elastic_prior=PositionFitSettings(poisson=0.48))
    for draw in (11, 12):
        rng = np.random.default_rng(draw)
        surf = rec(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape), strain_sigma=NOISE)
        error = aligned_error(surf.nodes, truth)
        assert error <= 3 * float(surf.node_sigma.mean()) + 0.05, (spec, draw, error, surf.diagnostics.extra)
        if spec.startswith("saddle"):
            assert error <= 0.1, (draw, error)  # the stretch pattern's curvature finds the saddle's valley


def test_the_curvature_range_spans_the_poisson_interval_and_refuses_what_is_no_reading_of_k():
    vc = (np.arange(6) - 2.5) * PITCH
    vv, uu = np.meshgrid(vc, vc, indexing="ij")
    b = -3e-6  # ∇²tr = 4b = −(1 − ν)K
    trace = 0.01 + b * (uu ** 2 + vv ** 2)
    stretch = np.stack([1.0 + trace / 2, 1.0 + trace / 2])
    valid = np.ones((2, 6, 6), bool)
    lo, hi = airy_curvature_range(stretch, valid, PITCH, 0.3, 0.5)
    # K(0.3) = 12e-6/0.7, K(0.5) = 12e-6/0.5, each ± 2 s.d.: 10 % (the closed form's own error)
    # and the floor of 1e-6 /mm² in quadrature (an exact pattern: no fit scatter); on the far
    # side the |K| that friction on a mold would have hidden, K/(1 − 0.35), ± the same
    k_lo, k_hi = 12e-6 / 0.7, 12e-6 / 0.5
    assert lo == pytest.approx(k_lo - 2 * np.hypot(0.1 * k_lo, 1e-6), rel=1e-6)
    assert hi == pytest.approx(k_hi / 0.65 + 2 * np.hypot(0.1 * k_hi, 1e-6), rel=1e-6)
    # a bump's trace is no reading of one mean K
    bump = 2e-3 * np.exp(-((uu - 10.0) ** 2 + vv ** 2) / 200.0)
    assert airy_curvature_range(np.stack([1 + bump / 2, 1 + bump / 2]), valid, PITCH, 0.3, 0.5) is None
    with pytest.raises(ValueError, match="Poisson range"):
        airy_curvature_range(stretch, valid, PITCH, 0.5, 0.3)


@pytest.mark.slow
def test_a_prestretched_oblique_cylinder_5x5_is_within_0_15mm_and_3_sigma_by_the_stretch_patterns_twist(cache):
    """A film pre-stretched 5 % on an oblique cylinder: the stretch made the model read a doubly
    curved sheet without twist (this one 1.6 mm off with σ 0.035 mm); the stretch pattern says
    K ≈ 0, which needs the twist back: the trace's move (0.10 mm), or, since the least-shear twist
    is weighed by the stretch pattern, that twist (0.035 mm); every node within 3 node_sigma +
    0.05 mm.  The cylinder's twist is sin(2·38°)/(2·70 mm) = 0.0069 /mm."""
    shape = parse_scene_spec("cylinder:radius=-70,axis_angle=-38,prestretch=0.05", "elastic", N, M, PITCH,
                             cache_dir=cache)
    eu, el = ph.gauge_strains(shape, N, M, PITCH, H, H, G)
    truth = ph.ground_truth(shape, N, M, PITCH).nodes
    rec = Reconstructor(N, M, PITCH, H, H, G)
    for draw in range(2):
        noise = np.random.default_rng(draw).normal(0.0, NOISE, (2, 2, N, M)) if draw else np.zeros((2, 2, N, M))
        surf = rec(eu + noise[0], el + noise[1], strain_sigma=NOISE, twist_sign=1)
        assert surf.diagnostics.twist_constant == pytest.approx(0.0069, rel=0.1)
        d = aligned_distances(surf.nodes.reshape(-1, 3), truth.reshape(-1, 3))
        assert d.mean() <= 0.15 and np.all(d <= 3.0 * surf.node_sigma.reshape(-1) + 0.05)


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["saddle:radius=-150,axis_angle=118", "saddle:radius=190,axis_angle=63"])
def test_an_elastic_saddle_on_12x12_is_within_3_sigma_plus_0_05mm_or_said_to_be_ambiguous(spec, cache):
    """On a large sheet the general model's twist sign for an elastic saddle came from the
    kinematic stretch of a graph, which the film does not follow (10 mm off, σ 0.1 mm): the sign
    the stretch pattern cannot give is now said aloud, and one of the two answers is within
    3 node_sigma + 0.05 mm."""
    n = 12
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes
    surf = Reconstructor(n, n, PITCH, H, H, G)(eu, el, strain_sigma=NOISE)
    bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
    answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
    within = [bool(np.all(aligned_distances(s.nodes.reshape(-1, 3), truth.reshape(-1, 3)) <= bound)) for s in answers]
    assert any(within), (spec, [aligned_error(s.nodes, truth) for s in answers], float(surf.node_sigma.mean()))


def _noisy_frames(spec: str, n: int, cache, draws):
    """(draw, the default Reconstructor's surface, the truth's nodes (K, 3)) of an elastic scene
    on an n×n sheet, draw 0 noise-free, the others with the sensor's noise seeded by the draw."""
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    for draw in draws:
        noise = np.random.default_rng(draw).normal(0.0, NOISE, (2, 2, n, n)) if draw else np.zeros((2, 2, n, n))
        yield draw, rec(eu + noise[0], el + noise[1], strain_sigma=NOISE), truth


@pytest.mark.slow
def test_an_elastic_saddle_near_the_grid_lines_on_12x12_takes_its_refined_twist_within_0_15mm_or_as_its_mirror(cache):
    """A 12×12 saddle 8° off the grid lines (twist 1.06·10⁻³/mm): where the membrane's interval
    for the twist reaches down to none, the least-shear answer kept none and was 1.35 mm off (σ
    covering it, the 0.15 mm target missed).  The twist refined on the answer's own family is
    well above the reading's noise there, so the answer moves to it, both signs weighed: one of
    the two answers is within 0.15 mm and 3 node_sigma + 0.05 mm, the other is the mirror."""
    moved_open = 0
    for draw, surf, truth in _noisy_frames("saddle:radius=260,axis_angle=8", 12, cache, range(5)):
        refined = surf.diagnostics.extra.get("stretch_twist_refined")
        moved_open += refined is not None and refined[1] == 0.0
        bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
        answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
        errors = [aligned_distances(s.nodes.reshape(-1, 3), truth) for s in answers]
        assert any(e.mean() <= 0.15 and np.all(e <= bound) for e in errors), (draw, [e.mean() for e in errors])
    assert moved_open  # the case this test is about: a refined interval down to none


@pytest.mark.slow
def test_a_16x16_saddle_whose_refined_twist_says_none_against_its_reading_has_sigma_covering_the_twist(cache):
    """A 16×16 saddle 1.5° off the grid lines (twist 1.7·10⁻⁴/mm, 0.4 mm at the corners): the
    membrane read a twist, its refinement on the answer's family none.  Taken as none, σ was
    0.06-0.08 mm against errors of 0.4 mm; the readings disagreeing, the twists up to the
    reading's stay in node_sigma.  Every frame whose twist was refined is within
    3 node_sigma + 0.05 mm (a frame whose reading is below half its interval's top is not
    refined: docs/reconstruction.md, *Large sheets*)."""
    refined_none = 0
    for draw, surf, truth in _noisy_frames("saddle:radius=-300,axis_angle=1.5", 16, cache, range(1, 6)):
        refined = surf.diagnostics.extra.get("stretch_twist_refined")
        if refined is None:
            continue
        refined_none += refined[0] == 0.0
        d = aligned_distances(surf.nodes.reshape(-1, 3), truth)
        assert np.all(d <= 3.0 * surf.node_sigma.reshape(-1) + 0.05), (draw, d.mean(), float(surf.node_sigma.mean()))
    assert refined_none >= 2


@pytest.mark.slow
def test_a_held_12x12_elastic_saddle_keeps_its_twist_and_sign_from_frame_to_frame_within_0_1mm(cache):
    """Streamed with ``previous``, a 12×12 saddle 8° off the grid lines: its twist carried from
    frame to frame where the reading's interval reaches none but the reading and its refinement
    still say it, and its sign kept unless the stretch clearly prefers the other.  Before, the
    second noisy frame read the sign afresh, wrongly, and every frame after kept it (2.6 mm off,
    flagged); a 12×12 saddle at 83° went between its twist and none, 0.05 and 1.0 mm off.  Now no
    frame changes the sign.  Nor is the carried twist modelled afresh where this frame's estimate
    differs from it by no more than the estimate's own noise (StretchPatternTwist._move_threshold):
    before, 5 of these 12 held frames moved on a 5-10 % difference, and their errors reached
    0.17 mm; now none moves after the first, and every frame's answer or its flagged mirror is
    within 0.1 mm (0.04-0.06)."""
    n = 12
    shape = parse_scene_spec("saddle:radius=260,axis_angle=8", "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    surf, signs, moved = None, [], []
    for draw in range(12):
        noise = np.random.default_rng(draw).normal(0.0, NOISE, (2, 2, n, n))
        surf = rec(eu + noise[0], el + noise[1], strain_sigma=NOISE, previous=surf)
        signs.append(np.sign(surf.diagnostics.twist_constant))
        moved.append("stretch_twist_moved" in surf.diagnostics.extra)
        answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
        errors = [aligned_distances(s.nodes.reshape(-1, 3), truth).mean() for s in answers]
        assert min(errors) <= 0.1, (draw, errors)
    assert len(set(signs)) == 1 and signs[0] != 0, signs
    assert not any(moved[1:]), moved


@pytest.mark.parametrize("n, spec", [(5, "sphere:radius=-75,friction=0.003"), (8, "sphere:radius=140,friction=0.0005"),
                                     (8, "sphere:radius=-180,friction=0.002")])
def test_friction_on_a_mold_reads_the_spheres_k_low_and_the_range_still_holds_it(n, spec):
    """Friction holds the film where it would slide: the trace reads |K| low (0.70-0.92 of a
    sphere's 1/R², measured), never high.  The curvature range reaches that far on its far side,
    so the mold's own K lies within it (the 10 % closed-form error alone left it out at 8×8)."""
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    _, stretch, valid = unit_data(eu, el, H, H, G)
    k_true = 1.0 / float(spec.split("radius=")[1].split(",")[0]) ** 2
    k_read, _ = airy_gaussian_curvature(stretch, valid, PITCH, 0.48)
    assert k_read < k_true  # friction hides curvature
    lo, hi = airy_curvature_range(stretch, valid, PITCH, 0.3, 0.5)
    assert lo <= k_true <= hi, (lo / k_true, hi / k_true)


@pytest.mark.parametrize("spec", ["sphere:radius=-160,friction=0.002", "sphere:radius=120,friction=0.001"])
def test_an_8x8_sphere_with_friction_is_not_given_the_twist_of_the_curvature_friction_hid(spec):
    """The trace of an 8×8 film on a sphere with friction read K low; the twist that the missing
    K would need (k_u k_v − τ² = K) moved the answer 1.9-2.6 mm off, beyond 3σ + 0.05 mm.  With
    friction's reach in the range no twist is needed: within 0.1 mm and 3σ + 0.05 mm."""
    n = 8
    shape = parse_scene_spec(spec, "elastic", n, n, PITCH)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rec = Reconstructor(n, n)
    rng = np.random.default_rng(4)
    for _ in range(4):
        surf = rec(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape))
        err = frame_errors(shape, surf, rec.grid)
        assert err.mean() <= 0.1, (err.mean(), surf.diagnostics.extra)
        assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.diagnostics.extra)



@pytest.mark.slow
def test_a_held_12x12_saddle_whose_twist_is_left_open_stays_within_3_sigma_on_every_frame(cache):
    """40 held frames of a 12×12 saddle of R 286 mm at 83° (twist 0.0008 /mm): on frames whose
    reading's interval reaches none the answer keeps none, and the twists the stretch leaves open
    join node_sigma.  On one frame the twist refined on the untwisted answer's family read 0.00046
    /mm, and σ reaching to that alone left the answer 1.05 mm off at 1.21 times 3σ + 0.05 mm; the
    open twists now reach past the estimate by 2 s.d. of its own noise, and every frame's answer
    or its flagged mirror is within the bound in the sensor frame."""
    n = 12
    shape = parse_scene_spec("saddle:radius=285.7,axis_angle=83.3", "elastic", n, n, PITCH, cache_dir=cache)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rec = Reconstructor(n, n, PITCH, H, H, G)
    rng = np.random.default_rng(5)
    surf = None
    for frame in range(40):
        surf = rec(eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape), previous=surf)
        images = [surf] + ([surf.mirror] if surf.mirror is not None else [])
        ratio = min(float(np.max(frame_errors(shape, s, rec.grid) / (3.0 * surf.node_sigma + 0.05))) for s in images)
        assert ratio <= 1.0, (frame, ratio, surf.diagnostics.extra.get("stretch_twist_refined"))
