"""skinmap.strains: one gauge law both ways, shared by the emulator's electrical model and the
host's conversion."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.emulator.electrical import ElectricalConfig, GaugeReadout, draw_calibration, strain_to_resistance
from skinmap.strains import (MAX_PLAUSIBLE_STRAIN, Calibration, gauge_resistance, gauge_strain,
                             reject_implausible_units, resistances_to_strains, turning_noise_rad)


def test_gauge_law_inverts_both_ways():
    rng = np.random.default_rng(0)
    gf = rng.uniform(1.0, 1.5, (2, 2, 3, 4))
    r0 = rng.uniform(5.0, 8.0, (2, 2, 3, 4))
    eps = rng.uniform(-0.05, 0.4, (2, 2, 3, 4))
    np.testing.assert_allclose(gauge_strain(gauge_resistance(eps, gf, r0), gf, r0), eps, rtol=0, atol=1e-13)
    np.testing.assert_allclose(gauge_resistance(0.01, 2.0, 10.0), 10.2)
    assert np.isnan(gauge_strain(np.array([np.nan]), 1.2, 6.5)).all()  # open or saturated stays unknown


def test_the_emulators_electrical_model_uses_the_same_law():
    cal = draw_calibration(np.random.default_rng(1), 3, 3)
    eps = np.random.default_rng(2).uniform(-0.02, 0.2, (2, 2, 3, 3))
    drift = np.full(eps.shape, 1e-5)
    emulated = strain_to_resistance(eps, cal, drift)
    np.testing.assert_array_equal(emulated, gauge_resistance(eps, cal.gauge_factor, cal.base_resistance_ohm, drift))


def test_host_conversion_recovers_the_emulators_strains_to_wire_resolution():
    rng = np.random.default_rng(3)
    cal = draw_calibration(rng, 4, 4)
    eps = rng.uniform(-0.02, 0.3, (2, 2, 4, 4))
    wire = GaugeReadout(cal, ElectricalConfig.ideal(), rng).read(eps, 0.0)
    eps_u, eps_l, valid = resistances_to_strains(wire * 1e-6, Calibration(cal.gauge_factor, cal.base_resistance_ohm))
    assert valid.all()
    np.testing.assert_allclose(np.stack([eps_u, eps_l]), eps, atol=1e-6 / (cal.base_resistance_ohm * cal.gauge_factor).min())


def test_implausible_or_unknown_gauges_are_not_valid():
    cal = Calibration(np.full((2, 2, 1, 2), 1.0), np.full((2, 2, 1, 2), 10.0))
    r = np.full((2, 2, 1, 2), 10.0)
    r[0, 0, 0, 0] = np.nan
    r[1, 1, 0, 1] = 10.0 * (1 + MAX_PLAUSIBLE_STRAIN * 1.5)
    eps_u, eps_l, valid = resistances_to_strains(r, cal)
    assert valid.sum() == 6 and not valid[0, 0, 0, 0] and not valid[1, 1, 0, 1]
    assert np.isnan(eps_u[0, 0, 0]) and np.isnan(eps_l[1, 0, 1])
    with pytest.raises(ValueError, match="does not match calibration"):
        resistances_to_strains(np.ones((2, 2, 2, 2)), cal)


def test_a_unit_bent_past_half_a_circle_is_rejected_whole():
    eu, el = np.zeros((2, 2, 2)), np.zeros((2, 2, 2))
    eu[1, 0, 1], el[1, 0, 1] = 0.1, -0.1  # 0.2 strain across 0.4 mm over 10 mm: 5 rad
    valid = np.ones((2, 2, 2, 2), bool)
    eu2, el2, valid2, count = reject_implausible_units(eu, el, valid, 10.0, 0.2, 0.2)
    assert count == 1 and valid.all() and not valid2[:, 1, 0, 1].any() and valid2.sum() == 14
    assert np.isnan(eu2[1, 0, 1]) and np.isnan(el2[1, 0, 1])
    assert turning_noise_rad(1e-4, 10.0, 0.2, 0.2) == pytest.approx(np.sqrt(2) * 1e-4 * 10 / 0.4)
