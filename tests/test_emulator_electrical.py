"""Electrical model of the emulated scanner: calibration, hysteresis, drift, noise, ADC."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.emulator.electrical import (
    GaugeConstants,
    ElectricalConfig,
    GaugeReadout,
    draw_calibration,
    hysteresis_step,
    quantise,
    strain_to_resistance,
)
from skinmap.protocol import RES_OPEN, RES_SATURATED
from skinmap.strains import gauge_strain


def test_calibration_statistics_and_determinism():
    cal = draw_calibration(np.random.default_rng(3), 32, 32)
    assert cal.shape == (2, 2, 32, 32)
    assert abs(cal.gauge_factor.mean() - 1.24) < 0.02 and abs(cal.gauge_factor.std() - 0.19) < 0.02
    assert abs(cal.base_resistance_ohm.mean() - 6.55) < 0.06
    assert abs(cal.base_resistance_ohm.std() - 0.72) < 0.06
    again = draw_calibration(np.random.default_rng(3), 32, 32)
    np.testing.assert_array_equal(cal.gauge_factor, again.gauge_factor)
    other = draw_calibration(np.random.default_rng(4), 32, 32)
    assert not np.array_equal(cal.gauge_factor, other.gauge_factor)
    gf, r0 = cal.micro_units()
    np.testing.assert_allclose(gf * 1e-6, cal.gauge_factor, atol=1e-12)
    np.testing.assert_allclose(r0 * 1e-6, cal.base_resistance_ohm, atol=1e-12)


def test_ideal_chain_inverts_exactly_to_wire_resolution():
    rng = np.random.default_rng(0)
    cal = draw_calibration(rng, 5, 5)
    strain = rng.uniform(-0.02, 0.3, size=(2, 2, 5, 5))
    ro = GaugeReadout(cal, ElectricalConfig.ideal(), rng)
    wire = ro.read(strain, 0.0)
    assert wire.dtype == np.uint32
    back = gauge_strain(wire * 1e-6, cal.gauge_factor, cal.base_resistance_ohm)
    # 1 µΩ of 6.5 Ω at GF 1.24 is ~1.2e-7 strain
    np.testing.assert_allclose(back, strain, atol=0.6e-6 / (cal.base_resistance_ohm * cal.gauge_factor).min())


def test_noise_level_matches_spec():
    rng = np.random.default_rng(1)
    cal = draw_calibration(rng, 16, 16)
    cfg = ElectricalConfig().without("hysteresis", "drift")
    ro = GaugeReadout(cal, cfg, rng)
    reads = np.array([ro.read(np.zeros((2, 2, 16, 16)), 0.01 * k) for k in range(40)]).astype(float)
    rel = (reads * 1e-6 / cal.base_resistance_ohm) - 1.0
    assert 6e-5 < rel.std() < 8e-5  # 0.007 % of R
    assert abs(rel.mean()) < 5e-6


def test_quantisation_lsb_and_saturation_and_open():
    cfg = ElectricalConfig()
    assert cfg.wire_lsb_uohm == 1
    coarse = ElectricalConfig(adc_full_scale_ohm=16.777216 * 8)  # 8 µΩ LSB
    assert coarse.wire_lsb_uohm == 8
    out = quantise(np.array([6.5000037, 200.0, 1.0, -1.0]), coarse)
    assert out[0] % 8 == 0 and abs(int(out[0]) - 6_500_004) <= 4
    assert out[1] == RES_SATURATED
    assert out[3] == 0
    assert quantise(np.array([16.8]), cfg)[0] == RES_SATURATED  # above the 16.78 Ω range
    out = quantise(np.array([6.5, 6.5, 6.5]), cfg, open_mask=[True, False, False],
                   saturated_mask=[False, True, False])
    assert list(out[:2]) == [RES_OPEN, RES_SATURATED] and out[2] == 6_500_000


def test_hysteresis_loop_height_is_four_percent_of_excursion():
    peak = 0.05
    up = np.linspace(0, peak, 101)
    down = up[::-1]
    mem = np.zeros(1)
    loading, unloading = [], []
    for e in up:
        mem = hysteresis_step(mem, np.array([e]), 0.04)
        loading.append(mem[0])
    for e in down:
        mem = hysteresis_step(mem, np.array([e]), 0.04)
        unloading.append(mem[0])
    loading, unloading = np.array(loading), np.array(unloading)[::-1]
    gap = unloading - loading
    assert np.all(gap >= -1e-15)
    # the widest point sits just after the turn: H·(1 − H/2)/(1 + H/2) ≈ 3.8 % of the peak
    np.testing.assert_allclose(gap.max() / peak, 0.04 * 0.98 / 1.02, rtol=0.02)
    assert abs(mem[0]) < 1e-12  # closes at rest
    # rate independent: the same path sampled 10x coarser gives the same outputs
    mem2 = np.zeros(1)
    for e in up[::10]:
        mem2 = hysteresis_step(mem2, np.array([e]), 0.04)
    assert abs(mem2[0] - loading[-1]) < 1e-15


def test_drift_is_small_and_seeded():
    cal = draw_calibration(np.random.default_rng(5), 4, 4)
    cfg = ElectricalConfig().without("hysteresis", "noise", "quantise")
    reads = []
    for seed in (9, 9, 10):
        ro = GaugeReadout(cal, cfg, np.random.default_rng(seed))
        reads.append(np.array([ro.read(np.zeros((2, 2, 4, 4)), t) for t in np.arange(0, 60, 1.0)]))
    np.testing.assert_array_equal(reads[0], reads[1])
    assert not np.array_equal(reads[0], reads[2])
    rel = reads[0] * 1e-6 / cal.base_resistance_ohm - 1
    assert 0 < np.abs(rel).max() < 1e-4


def test_response_lag_is_first_order_and_off_by_default():
    assert ElectricalConfig().response_tau_s == 0.0
    cal = draw_calibration(np.random.default_rng(0), 2, 2)
    cfg = ElectricalConfig.ideal()
    cfg = ElectricalConfig(**{**cfg.__dict__, "response_tau_s": 0.05})
    ro = GaugeReadout(cal, cfg, np.random.default_rng(0))
    zero, step = np.zeros((2, 2, 2, 2)), np.full((2, 2, 2, 2), 0.01)
    ro.read(zero, 0.0)
    eps = [gauge_strain(ro.read(step, 0.01 * k) * 1e-6, cal.gauge_factor, cal.base_resistance_ohm)
           for k in range(1, 31)]
    eps = np.array(eps)[:, 0, 0, 0, 0]
    expected = 0.01 * (1 - np.exp(-0.01 * np.arange(1, 31) / 0.05))
    np.testing.assert_allclose(eps, expected, atol=2e-7)
    assert eps[17] > 0.0095  # within 170 ms the response is above 95 %


def test_relaxation_loses_its_share_of_a_held_strain_at_its_rate_and_recovers_when_released():
    """A strain step from rest held 30 s: the reading falls from the strain to (1 − f) of it as
    1 − f·(1 − e^(−t/τ)) (f 3.5 %, the paper's share; τ 10 s); released, it reads −f·q and
    recovers at the same rate; off by default."""
    assert ElectricalConfig().relaxation == 0.0
    cal = draw_calibration(np.random.default_rng(0), 2, 2)
    cfg = ElectricalConfig(**{**ElectricalConfig.ideal().__dict__, "relaxation": 0.035, "relaxation_tau_s": 10.0})
    ro = GaugeReadout(cal, cfg, np.random.default_rng(0))
    zero, step = np.zeros((2, 2, 2, 2)), np.full((2, 2, 2, 2), 0.01)

    def read(strain, t):
        return gauge_strain(ro.read(strain, t) * 1e-6, cal.gauge_factor, cal.base_resistance_ohm)[0, 0, 0, 0]

    read(zero, 0.0)
    times = np.arange(1, 31) * 1.0
    held = np.array([read(step, t) for t in times])
    # the step is applied at t = 1 s (the first reading of it has been held no time)
    np.testing.assert_allclose(held, 0.01 * (1 - 0.035 * (1 - np.exp(-(times - 1.0) / 10.0))), atol=2e-7)
    q_end = 0.01 * (1 - np.exp(-30.0 / 10.0))  # held from 1 s to the first reading after release, 31 s
    released = np.array([read(zero, 30.0 + k) for k in range(1, 11)])
    np.testing.assert_allclose(released, -0.035 * q_end * np.exp(-np.arange(0, 10) / 10.0), atol=2e-7)
    assert ElectricalConfig(relaxation=0.035).without("relaxation").relaxation == 0.0


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="relaxation"):
        ElectricalConfig(relaxation=1.0)
    with pytest.raises(ValueError, match="relaxation_tau_s"):
        ElectricalConfig(relaxation_tau_s=0.0)
    with pytest.raises(ValueError, match="hysteresis"):
        ElectricalConfig(hysteresis=-0.1)
    with pytest.raises(ValueError, match="response_tau_s"):
        ElectricalConfig(response_tau_s=-1.0)
    with pytest.raises(ValueError, match="unknown effect"):
        ElectricalConfig().without("wobble")
    with pytest.raises(ValueError, match=r"\(2, 2, N, M\)"):
        GaugeConstants(np.ones((2, 3, 3)), np.ones((2, 3, 3)))
    cal = draw_calibration(np.random.default_rng(0), 3, 3)
    with pytest.raises(ValueError, match="expected"):
        GaugeReadout(cal, ElectricalConfig(), np.random.default_rng()).read(np.zeros((2, 3, 3)), 0.0)
    with pytest.raises(ValueError, match="Generator"):
        strain_to_resistance(np.zeros((2, 2, 3, 3)), cal, noise_rel_sd=1e-4)
