"""What a Reconstructor keeps from frame to frame (per geometry, validity mask and noise level)
and within a frame (reconstruction/reconstructor.py): a Reconstructor that has answered other
frames answers as a fresh one does, bit for bit, and the steps a frame shares are the ones it
would compute again."""
from __future__ import annotations

import numpy as np

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.productnoise import ProductNoise
from skinmap.reconstruction.stretchtwist import _REFINE_SQUARES, _quadratic_fit

PITCH, H, G = 12.0, 0.2, 10.0
NOISE = 5.7e-5


def _same(a, b) -> None:
    assert np.array_equal(a.nodes, b.nodes) and np.array_equal(a.normals, b.normals)
    assert np.array_equal(a.node_sigma, b.node_sigma)
    assert np.array_equal(a.node_scatter_sigma, b.node_scatter_sigma)
    assert a.diagnostics.twist_constant == b.diagnostics.twist_constant
    assert repr(a.diagnostics.extra) == repr(b.diagnostics.extra)
    assert (a.mirror is None) == (b.mirror is None)
    if a.mirror is not None:
        assert np.array_equal(a.mirror.nodes, b.mirror.nodes)


def test_a_used_reconstructor_answers_a_warm_chain_as_a_fresh_one_does():
    """Elastic films held still (the stretch pattern's twist, its mirror), a unit going missing
    and coming back, another shape: each frame from a Reconstructor that answered the ones
    before equals a fresh Reconstructor's given the same previous frame (a cache that served
    another mask's, another frame's or another field's value would show here)."""
    rng = np.random.default_rng(3)
    shared = Reconstructor(5, 5, PITCH, H, H, G)
    prev = None
    for spec in ("saddle:radius=90,axis_angle=75", "sphere:radius=70"):
        eu, el = ph.gauge_strains(parse_scene_spec(spec, "elastic", 5, 5, PITCH), 5, 5, PITCH, H, H, G)
        for k in range(4):  # (the last from the frame before's defect correction: held still)
            e_u = eu + rng.normal(0, NOISE, eu.shape)
            if k == 1:
                e_u[0, 1, 2] = np.nan
            e_l = el + rng.normal(0, NOISE, el.shape)
            answer = shared(e_u, e_l, previous=prev)
            _same(answer, Reconstructor(5, 5, PITCH, H, H, G)(e_u, e_l, previous=prev))
            prev = answer
        assert prev.diagnostics.extra.get("defect_warm") and prev.diagnostics.extra["stretch_reading"][0] == "membrane"


def test_the_product_statistics_are_each_field_s_own_and_kept_one_frame():
    """Reconstructor._product_stats keeps a field triple's cross term for the frame: another
    triple of the same shape (a defect pass's, the measured data's) gets its own, every one
    equals ProductNoise.stats, and the next frame starts afresh."""
    rec = Reconstructor(5, 5, PITCH, H, H, G)
    rec.prepare()
    noise = rec._product_noise
    assert isinstance(noise, ProductNoise)
    rng = np.random.default_rng(5)
    shape = (rec.grid.nf, rec.grid.mf)
    fields = [tuple(rng.normal(0.0, 1e-3, shape) for _ in range(3)) for _ in range(3)]
    sigma_t = rec._turning_sd(NOISE)
    for k_u, k_v, tau0 in fields + fields[::-1]:
        tau_c = tau0 - tau0.sum() / tau0.size
        for s in (sigma_t, 2.0 * sigma_t):
            assert rec._product_stats(k_u, k_v, tau0, s) == noise.stats(k_u, k_v, tau_c, rec.grid.inner, s)
    assert [sum(entry[0][0] is f[0] for entry in rec._product_cross) for f in fields] == [1, 1, 1]
    eu, el = ph.gauge_strains(ph.SphereCap(70.0), 5, 5, PITCH, H, H, G)
    rec(eu, el)
    assert all(entry[0][0] is not f[0] for entry in rec._product_cross for f in fields)


def test_the_twist_refinement_s_fit_is_numpy_s_polyfit_to_the_bit():
    rng = np.random.default_rng(8)
    for _ in range(200):
        values = rng.normal(size=4) * 10.0 ** rng.uniform(-14, 0)
        assert np.array_equal(_quadratic_fit(values), np.polyfit(_REFINE_SQUARES, values, 2))
