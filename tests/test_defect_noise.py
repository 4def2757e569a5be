"""Defect correction under noise: where the noise alone leaves the general model above one χ² per
gauge (large sheets), a pass also reads the residual averaged over 3 × 3 units
(reconstruction.DEFECT_SMOOTH_UNITS) and takes it where it gains and keeps the constant twist, so
the noise is not fed back into the model twice and the answer carries no bias of the noise
(docs/reconstruction.md, *Under noise on large sheets*)."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.emulator import physics as ph
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.forward import unit_box_mean

NOISE = 0.0057e-2


def test_unit_box_mean_averages_each_gauge_kind_over_its_neighbours_and_keeps_missing_gauges_missing():
    values = np.zeros((2, 5, 6))
    values[0, 2, 3] = 9.0  # one row gauge
    values[1] = 4.0  # every column gauge alike
    values[1, 0, 0] = np.nan  # a missing column gauge
    out = unit_box_mean(values, 3)
    # the spike spreads over its 3 × 3 units, within its own kind only
    assert out[0, 1:4, 2:5] == pytest.approx(np.ones((3, 3)))
    assert out[0].sum() == pytest.approx(9.0)
    # a constant stays constant, at the edges too (the units beyond the sheet are left out)
    assert np.isnan(out[1, 0, 0])
    assert np.delete(out[1].ravel(), 0) == pytest.approx(4.0)
    # at a corner the mean is over the four units that exist
    corner = np.zeros((2, 5, 6))
    corner[0, 0, 0] = 4.0
    assert unit_box_mean(corner, 3)[0, 0, 0] == pytest.approx(1.0)
    assert unit_box_mean(values, 1)[0] == pytest.approx(values[0])
    with pytest.raises(ValueError, match="odd number of units"):
        unit_box_mean(values, 2)


@pytest.mark.slow
@pytest.mark.parametrize("radius", [-450.0, 450.0])
def test_a_noisy_32x32_sphere_is_read_without_a_bias_of_the_noise_below_0_04_mm(radius):
    # Antithetic pairs of noise draws: the mean of a pair's two answers less the noise-free
    # answer is what the noise does to the answer beyond its first-order scatter.  Before the
    # averaged pass most of these frames' raw passes failed and left the uncorrected model's own
    # error in: 0.104 mm rms over the nodes, now 0.010 (every frame takes an averaged pass).
    n = 32
    shape = ph.SphereCap(radius=radius)
    eu, el = ph.gauge_strains(shape, n, n, 12.0, 0.2, 0.2, 10.0)
    rec = Reconstructor(n, n, 12.0)
    clean = rec(eu, el, strain_sigma=NOISE).nodes
    rng = np.random.default_rng(5)
    shifts, averaged = [], 0
    for _ in range(12):
        du, dl = rng.normal(0.0, NOISE, eu.shape), rng.normal(0.0, NOISE, el.shape)
        a, b = rec(eu + du, el + dl), rec(eu - du, el - dl)
        averaged += sum("defect_smoothed" in s.diagnostics.extra for s in (a, b))
        shifts.append(0.5 * (a.nodes + b.nodes) - clean)
    bias = np.mean(shifts, axis=0)
    assert np.sqrt((bias ** 2).sum(axis=-1).mean()) < 0.04
    assert averaged >= 6  # the averaged pass did the work
