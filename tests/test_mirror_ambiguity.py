"""Mirror images said aloud: where the gauges cannot tell a shape from its mirror image, the
surface carries the other answer, skinmapd flags every element AMBIGUOUS, and a user who
knows the mounting fixes the sign in the config."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.strains import Calibration
from skinmap.daemon.config import ConfigError, parse_config
from skinmap.wire.messages import ElementFlag
from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline
from skinmap.emulator import physics as ph

N = M = 5
PITCH = 12.0
GEOMETRY = ArrayGeometry(N, M, PITCH, 0.2, 0.2)
ELEMENT_UV = np.array([[u, v] for v in (-12.0, 0.0, 12.0) for u in (-18.0, 0.0, 18.0)])
GF = np.full((2, 2, N, M), 1.24)
R0 = np.full((2, 2, N, M), 6.55)


def resistances(shape) -> np.ndarray:
    eu, el = ph.gauge_strains(shape, N, M, pitch=PITCH)
    return R0 * (1.0 + GF * np.stack([eu, el]))


def pipeline(**kw) -> FramePipeline:
    return FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)), **kw)


@pytest.mark.slow
def test_an_oblique_cylinder_flags_every_element_ambiguous():
    result = pipeline().process(resistances(ph.Cylinder(50.0, axis_angle=30.0)), 0, 0, 0)
    assert ((result.element_flags & int(ElementFlag.AMBIGUOUS)) != 0).all()
    assert ((result.element_flags & int(ElementFlag.VALID)) != 0).all()


@pytest.mark.slow
@pytest.mark.parametrize("sign", [1, -1])
def test_twist_sign_from_the_config_settles_it(sign):
    truth = ph.Cylinder(50.0, axis_angle=30.0)
    result = pipeline(twist_sign=sign).process(resistances(truth), 0, 0, 0)
    assert not ((result.element_flags & int(ElementFlag.AMBIGUOUS)) != 0).any()


def test_a_shape_without_a_mirror_twin_is_not_flagged():
    result = pipeline().process(resistances(ph.GaussianBumps(height=3.0, fwhm=20.0, centre=(4.0, -3.0))), 0, 0, 0)
    assert not ((result.element_flags & int(ElementFlag.AMBIGUOUS)) != 0).any()


def test_config_twist_sign_is_checked_by_name():
    assert parse_config({"reconstruction": {"twist_sign": "negative"}}).reconstruction.twist_sign == "negative"
    assert parse_config({}).reconstruction.twist_sign == "auto"
    with pytest.raises(ConfigError, match="twist_sign"):
        parse_config({"reconstruction": {"twist_sign": "up"}})
    with pytest.raises(ValueError, match="twist_sign"):
        pipeline(twist_sign=2)


@pytest.mark.slow
@pytest.mark.parametrize("radius, angle", [(276.0, 168.5), (276.0, 11.5)])
def test_a_mirror_that_reads_the_gauges_within_the_noise_is_kept_not_taken_and_one_answer_is_within_3_sigma(
        radius, angle):
    """A large saddle just off the grid lines (12×12, R 276 mm): both twist signs read the
    noise-free gauges within what noise alone would leave, the mirror image even better than the
    true sign.  The data cannot tell them apart, so the answer stays and the mirror is kept
    (AMBIGUOUS); one of the two is within 3 node_sigma + 0.05 mm at every node."""
    from skinmap.reconstruction import Reconstructor
    from skinmap.reconstruction.linalg import aligned_distances

    n = 12
    shape = ph.Saddle(radius, axis_angle=angle)
    eu, el = ph.gauge_strains(shape, n, n, pitch=PITCH)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes.reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH)(eu, el, strain_sigma=5.7e-5)
    assert surf.mirror is not None and surf.diagnostics.extra["ambiguous"]
    bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
    assert any(bool(np.all(aligned_distances(s.nodes.reshape(-1, 3), truth) <= bound)) for s in (surf, surf.mirror))


@pytest.mark.parametrize("radius", [-236.6, 234.9])
def test_a_45_deg_saddle_on_12x12_is_flagged_with_its_mirror_modelled_afresh_and_one_answer_within_0_05mm(radius):
    """A saddle at 45° on a 12×12 sheet: both twist signs, each modelled on its own, read the
    gauges exactly as well (0.17 per gauge); the answer's own family reflected misread them by
    35 per gauge and was rejected, so the default sign stood unflagged, 11 mm off where it was
    the wrong one.  The mirror is modelled afresh before it is rejected."""
    from skinmap.reconstruction import Reconstructor
    from skinmap.reconstruction.linalg import aligned_distances

    n = 12
    shape = ph.Saddle(radius, axis_angle=45.0)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)
    truth = shape.position(ph.cell_centres(n, n, PITCH)).reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH)(eu, el)
    assert surf.mirror is not None and surf.diagnostics.extra["ambiguous"]
    errors = [float(aligned_distances(a.nodes.reshape(-1, 3), truth).mean()) for a in (surf, surf.mirror)]
    assert min(errors) <= 0.05, errors
    assert max(errors) > 1.0, errors  # the two answers really differ: the sign matters here


@pytest.mark.parametrize("flag_chi2", [None, 4.0])
def test_a_45_deg_saddle_whose_mirror_reads_the_gauges_worse_by_less_than_3_sd_is_flagged(flag_chi2, monkeypatch):
    """A saddle R −147.4 mm at 45° on 8×8 (both signs give the same strains), noise seed 37: the
    two graph fits read the gauges 0.029 and 0.048 per gauge, the wrong sign the better.  Told
    apart at 2 s.d. (a χ² difference of 4, ``flag_chi2=4``) the wrong sign stood unflagged, 7.8 mm
    off; a mirror is now said aloud unless the gauges read it worse by 3 s.d.
    (reconstructor.MIRROR_FLAG_CHI2), and the answer or its mirror is within 0.05 mm."""
    from skinmap.reconstruction import Reconstructor, reconstructor
    from skinmap.reconstruction.linalg import aligned_distances

    if flag_chi2 is not None:
        monkeypatch.setattr(reconstructor, "MIRROR_FLAG_CHI2", flag_chi2)
    n = 8
    shape = ph.Saddle(-147.4, axis_angle=45.0)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)
    rng = np.random.default_rng(37)
    noisy = eu + rng.normal(0, 5.7e-5, eu.shape), el + rng.normal(0, 5.7e-5, el.shape)
    truth = shape.position(ph.cell_centres(n, n, PITCH)).reshape(-1, 3)
    surf = Reconstructor(n, n, PITCH)(*noisy)
    answers = (surf,) if surf.mirror is None else (surf, surf.mirror)
    errors = [float(aligned_distances(a.nodes.reshape(-1, 3), truth).mean()) for a in answers]
    if flag_chi2 is not None:  # what the 3 s.d. catch
        assert surf.mirror is None and errors[0] > 1.0, errors
        return
    assert surf.mirror is not None and surf.diagnostics.extra["ambiguous"]
    assert min(errors) <= 0.05, errors


def test_a_mirror_modelled_afresh_is_flagged_never_taken_on_a_16x16_saddle_at_49_deg():
    """A saddle R 272 mm at 48.6° on 16×16, the bench's 17th noise draw: the answer (the right
    sign) misreads the gauges at 2.2 per gauge, its mirror modelled afresh at 0.74.  Taking the
    mirror put the answer 16.8 mm off, unflagged; the mirror is flagged, and the answer or its
    mirror lies within 3σ + 0.05 mm of the truth in the sensor frame."""
    from conftest import elastic_dataset

    from skinmap.reconstruction import Reconstructor, nodes_in_sensor_frame

    ed = elastic_dataset()

    n = 16
    plan = ed.class_plans("poisson_0.3", 2024, 1, n)[0]
    shape = ed.kinematic_shape(plan)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)
    du, dl = ed.noise_draw(plan, 16, 0.0057e-2, eu.shape)
    rec = Reconstructor(n, n, PITCH)
    surf = rec(eu + du, el + dl)
    assert surf.mirror is not None and not surf.diagnostics.extra.get("mirror_swapped")
    grid = rec.grid
    truth = nodes_in_sensor_frame(grid, shape.position)
    bound = 3.0 * surf.node_sigma + 0.05
    within = [bool(np.all(np.linalg.norm(a.nodes - truth, axis=-1) <= bound)) for a in (surf, surf.mirror)]
    assert any(within), within


def test_a_mirror_taken_over_an_answer_that_misreads_the_gauges_keeps_the_answer_beside_it():
    """A saddle R 342 mm at 71.8° on 16×16 (an unseen seed's scene in its kinematic form, noise
    draw 16): its answer, the right sign, whose defect pass was not kept (it overshot, 1.9 → 4.4
    per gauge), read the gauges at 1.9 per gauge, beyond what the noise leaves; its mirror on the
    family read 0.87 and was taken, 8.0 mm off with σ 0.12 mm, unflagged (34 times 3σ + 0.05 mm).
    The mirror is still taken, but an answer that misread the gauges stays beside it: flagged,
    and one of the two within 3σ + 0.05 mm of the truth in the sensor frame."""
    from conftest import bench_frame

    from skinmap.reconstruction import Reconstructor, nodes_in_sensor_frame

    _, shape, eu, el = bench_frame("saddle", 777, 1, 16, "saddle:radius=341.8,axis_angle=71.8", 16)
    rec = Reconstructor(16, 16, PITCH)
    surf = rec(eu, el)
    assert surf.diagnostics.extra.get("mirror_swapped")
    assert surf.mirror is not None
    truth = nodes_in_sensor_frame(rec.grid, shape.position)
    bound = 3.0 * surf.node_sigma + 0.05
    within = [bool(np.all(np.linalg.norm(a.nodes - truth, axis=-1) <= bound)) for a in (surf, surf.mirror)]
    assert any(within), within


@pytest.mark.slow
def test_on_32x32_a_family_mirror_that_reads_the_gauges_better_is_flagged_not_taken_and_one_answer_is_within_0_3mm():
    """On 32×32 the noise alone leaves the general model 2.6 per gauge, and an answer its
    defect correction did not improve misreads the gauges well beyond that while its family's
    mirror reads them better: a saddle R 520 mm at 15° without defect correction, noisy, had its
    mirror taken on 5 draws of 6, 17.9 mm off, unflagged.  The mirror is flagged instead, and the
    answer or its mirror is within 0.3 mm mean of the truth (the 32×32 target)."""
    from skinmap.reconstruction import Reconstructor
    from skinmap.reconstruction.linalg import aligned_distances

    n = 32
    shape = ph.Saddle(520.0, axis_angle=15.0)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)
    truth = shape.position(ph.cell_centres(n, n, PITCH)).reshape(-1, 3)
    rec = Reconstructor(n, n, PITCH, defect_steps=0)
    for draw in range(3):
        rng = np.random.default_rng(1000 + draw)
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape))
        assert not surf.diagnostics.extra.get("mirror_swapped"), draw
        errors = [aligned_distances(a.nodes.reshape(-1, 3), truth).mean()
                  for a in [surf] + ([surf.mirror] if surf.mirror is not None else [])]
        assert min(errors) <= 0.3, (draw, errors)
        assert errors[0] <= 0.3 or surf.mirror is not None, (draw, errors)  # a wrong answer is flagged
