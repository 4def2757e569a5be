"""A gain error the gauges share, in σ (``Reconstructor(gain_sd=...)``, docs/reconstruction.md,
"A gain the gauges share"): the gauges' hysteresis reads a sheet pressed from flat and held about
2 % low on every gauge, the same on every frame, which the noise's σ does not describe."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import aligned_node_errors, frame_errors

from skinmap.emulator import physics as ph
from skinmap.reconstruction import DEFAULT_GAIN_SD, Reconstructor, reconstruct
from skinmap.strains import HYSTERESIS_GAIN_SD, HYSTERESIS_LOOP, RELAXATION_SHARE, SHARED_GAIN_SD

PITCH = 12.0
NOISE = 5.7e-5


def test_the_default_is_the_hysteresis_and_the_relaxation_each_a_bounded_error_in_quadrature():
    """Half the hysteresis loop one s.d. high (2.5 %, either sign) and the relaxation's 3.5 %
    (one sign), each a rectangular distribution's s.d. about none."""
    assert HYSTERESIS_GAIN_SD == pytest.approx(0.5 * (0.0421 + 0.0070) / np.sqrt(3.0))
    assert RELAXATION_SHARE == 0.035
    assert DEFAULT_GAIN_SD == SHARED_GAIN_SD == pytest.approx(np.hypot(HYSTERESIS_GAIN_SD, 0.035 / np.sqrt(3.0)))
    for bad in (-0.01, 0.5, float("nan"), True, "0.01"):
        with pytest.raises(ValueError, match="gain_sd"):
            Reconstructor(5, 5, gain_sd=bad)


@pytest.mark.parametrize("n, spec, mechanics", [
    (5, "sphere:radius=60", "kinematic"), (5, "cylinder:radius=40,axis_angle=30", "kinematic"),
    (5, "saddle:radius=80,axis_angle=20", "kinematic"), (5, "gaussian:height=4,fwhm=20,u0=6,v0=-4", "kinematic"),
    (12, "cylinder:radius=96", "kinematic"), (12, "saddle:radius=170,axis_angle=15", "kinematic"),
    (5, "sphere:radius=70,prestretch=0.05", "elastic"),
    (5, "saddle:radius=80,axis_angle=20", "elastic"), (5, "gaussian:height=4,fwhm=20,u0=6,v0=-4", "elastic")])
def test_the_gain_term_follows_the_reconstruction_of_strains_scaled_by_a_common_gain(n: int, spec: str,
                                                                                    mechanics: str) -> None:
    """σ's gain part (node_sigma² with the gain less node_sigma² without it, over gain_sd²) against
    what a gain of 1 % does to the answer in the sensor frame, raised to its mean over the nodes
    as σ's part is (the alignment floor): within 0.8-3.5 times it where that is at least a fifth
    of its largest (the first-order model: heights linear in the curvature, the in-plane pull of
    bending quadratic, the stretch's own shift linear, the twist's part of the height scaled by
    a share between none and all; measured 0.90-2.14 on the kinematic sheets, 0.92-3.36 on the
    elastic films, the most on the saddle, least tight where the in-plane pull and the stretch's
    shift partly cancel; the 12×12 saddle, whose twist hardly scales, read 0.60 before the
    twist's part was taken apart)."""
    from skinmap.emulator import scenes

    eu, el = ph.gauge_strains(scenes.parse_scene_spec(spec, mechanics, n, n, PITCH), n, n, PITCH)
    plain = Reconstructor(n, n, twist_prior="none", gain_sd=0.0)
    with_gain = Reconstructor(n, n, twist_prior="none", gain_sd=0.02)
    base = plain(eu, el)
    moved = np.linalg.norm(plain(1.01 * eu, 1.01 * el).nodes - base.nodes, axis=-1) / 0.01
    ours = with_gain(eu, el)
    assert np.array_equal(ours.nodes, base.nodes)
    part = np.sqrt(np.maximum(ours.node_sigma ** 2 - base.node_sigma ** 2, 0.0)) / 0.02
    moved = np.maximum(moved, moved.mean())
    big = moved >= 0.2 * moved.max()
    ratio = part[big] / moved[big]
    assert ratio.min() >= 0.8 and ratio.max() <= 3.5, (ratio.min(), ratio.max())


@pytest.mark.parametrize("n, spec", [(5, "cylinder:radius=40"), (12, "saddle:radius=144"),
                                     (12, "saddle:radius=120,axis_angle=20")])
def test_a_sheet_read_half_a_hysteresis_loop_off_on_every_gauge_is_within_3_sigma(n: int, spec: str) -> None:
    """Every gauge read (1 ∓ H/2) of its strain, H the paper's loop (4.21 %: a sheet pressed
    from flat and held reads the loading branch, one released onto it the other), with the
    sensor's noise: within 3σ + 0.05 mm in the sensor frame and after the best rigid alignment.
    Without the gain in σ (gain_sd=0) these were 1.26, 1.30 and 1.25 times the bound."""
    shape = ph.parse_shape_spec(spec)
    eu, el = ph.gauge_strains(shape, n, n, PITCH)
    truth = ph.ground_truth(shape, n, n, PITCH).nodes
    rec = Reconstructor(n, n)
    for gain in (1.0 - 0.5 * HYSTERESIS_LOOP, 1.0 + 0.5 * HYSTERESIS_LOOP):
        rng = np.random.default_rng(4)
        surf = rec(gain * eu + rng.normal(0.0, NOISE, eu.shape), gain * el + rng.normal(0.0, NOISE, el.shape))
        bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
        answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
        worst = min(max(float(np.max(aligned_node_errors(a.nodes, truth) / bound)),
                        float(np.max(frame_errors(shape, a, rec.grid).reshape(-1) / bound))) for a in answers)
        assert worst <= 1.0, (gain, worst)


def test_gain_sd_leaves_the_answer_and_the_scatter_part_and_only_widens_sigma() -> None:
    eu, el = ph.gauge_strains(ph.parse_shape_spec("cylinder:radius=50,axis_angle=10"), 5, 5, PITCH)
    rng = np.random.default_rng(2)
    eu, el = eu + rng.normal(0.0, NOISE, eu.shape), el + rng.normal(0.0, NOISE, el.shape)
    none, default = reconstruct(eu, el, gain_sd=0.0), reconstruct(eu, el)
    assert np.array_equal(none.nodes, default.nodes) and np.array_equal(none.normals, default.normals)
    assert np.array_equal(none.node_scatter_sigma, default.node_scatter_sigma)
    assert np.all(default.node_sigma >= none.node_sigma) and default.node_sigma.max() > none.node_sigma.max()
    uv = np.array([[0.0, 0.0], [20.0, -15.0], [-29.0, 29.0]])
    assert np.all(default.locate_sigma(uv) >= none.locate_sigma(uv))
    assert np.array_equal(default.locate_sigma(uv, scatter=True), none.locate_sigma(uv, scatter=True))


def test_a_saddle_held_long_read_half_a_loop_and_its_whole_relaxation_low_is_within_3_sigma() -> None:
    """Every gauge of a 12×12 saddle turned 15° read 5.6 % low (half the hysteresis loop and the
    paper's 3.5 % relaxation: a sheet pressed and held long), three noise draws: within 3σ +
    0.05 mm after the best rigid alignment.  Its twist, read from the Gauss equation, hardly
    moves with a common gain while its curvatures scale; before the twist's part of the height
    was taken apart in σ's gain term (its nodal lines read no change) these were 1.07-1.25 times
    the bound."""
    shape = ph.parse_shape_spec("saddle:radius=170,axis_angle=15")
    eu, el = ph.gauge_strains(shape, 12, 12, PITCH)
    truth = ph.ground_truth(shape, 12, 12, PITCH).nodes
    rec = Reconstructor(12, 12)
    gain = 1.0 - 0.5 * HYSTERESIS_LOOP - RELAXATION_SHARE
    for seed in (4, 5, 6):
        rng = np.random.default_rng(seed)
        surf = rec(gain * eu + rng.normal(0.0, NOISE, eu.shape), gain * el + rng.normal(0.0, NOISE, el.shape))
        worst = float(np.max(aligned_node_errors(surf.nodes, truth) / (3.0 * surf.node_sigma.reshape(-1) + 0.05)))
        assert worst <= 1.0, (seed, worst)
