"""Sheets pushed out of plane (graph mappings): twist and shear from the graph's slopes.

Turned saddles, twisted domes and oblique troughs pressed into a clamped film stretch in a
pattern that fixes their twist; with large slopes the twist field and the shear's free part
must come from the graph itself (reconstruction/graphsheet.py), not from the small-slope
Codazzi relations.  Shapes here are not the benchmark's (other angles, a general quadratic).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import skinmap.reconstruction.reconstructor as recon
from skinmap.emulator import physics as ph
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.linalg import aligned_distances

N = M = 5
PITCH, H, GAUGE = 12.0, 0.2, 10.0
NOISE = 5.7e-5


def trough(radius: float, angle_deg: float) -> ph.Quadric:
    """A parabolic trough of bend radius ``radius`` across the direction ``angle_deg``."""
    th = math.radians(angle_deg)
    d = np.array([math.cos(th), math.sin(th)])
    h = np.outer(d, d) / radius
    return ph.Quadric(h[0, 0], h[0, 1], h[1, 1])


@pytest.fixture(scope="module")
def rec() -> Reconstructor:
    return Reconstructor(N, M, PITCH, H, H, GAUGE)


def mean_error(surf, shape) -> float:
    """Mean node error (mm) after the best rigid alignment (Kabsch)."""
    n, m = surf.nodes.shape[:2]
    truth = shape.position(ph.cell_centres(n, m, PITCH).reshape(-1, 2))
    return float(aligned_distances(surf.nodes.reshape(-1, 3), truth.reshape(-1, 3)).mean())


def strains(shape):
    return ph.gauge_strains(shape, N, M, PITCH, H, H, GAUGE)


@pytest.mark.parametrize("radius, angle", [(55.0, 20.0), (-80.0, 35.0), (70.0, -60.0), (100.0, 110.0), (45.0, 5.0)])
def test_turned_saddles_at_unseen_angles(rec, radius, angle):
    shape = ph.Saddle(radius, axis_angle=angle)
    err = mean_error(rec(*strains(shape)), shape)
    assert err < 0.06, f"saddle R={radius} at {angle} deg: {err:.3f} mm"


@pytest.mark.parametrize(
    "shape",
    [
        ph.Quadric(10e-3, 5e-3, 10e-3),  # a twisted dome
        ph.Quadric(-18e-3, 9e-3, -8e-3),  # a twisted bowl
        ph.Quadric(9.8e-3, -10.4e-3, -24.9e-3),  # a saddle with unequal curvatures
        trough(60.0, 30.0),  # an oblique trough pressed into the film
        trough(-45.0, 120.0),
    ],
    ids=["dome", "bowl", "skew-saddle", "trough30", "trough120"],
)
def test_twisted_graph_shapes(rec, shape):
    err = mean_error(rec(*strains(shape)), shape)
    assert err < 0.08, f"{shape}: {err:.3f} mm"


@pytest.mark.slow
def test_twisted_graph_with_noise_and_a_dead_gauge(rec):
    shape = ph.Saddle(65.0, axis_angle=25.0)
    eu, el = strains(shape)
    rng = np.random.default_rng(4)
    errs = [mean_error(rec(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)), shape) for _ in range(4)]
    assert max(errs) < 0.1, errs
    eu_dead = eu.copy()
    eu_dead[0, 1, 3] = np.nan
    surf = rec(eu_dead, el)
    assert np.isfinite(surf.nodes).all() and np.isfinite(surf.normals).all()
    assert mean_error(surf, shape) < 0.15


def test_mirror_saddle_at_45_degrees_follows_twist_sign(rec):
    """At 45° the two mirror images give the same strains; the told sign picks the right one."""
    for radius in (60.0, -60.0):
        shape = ph.Saddle(radius, axis_angle=45.0)
        sign = math.copysign(1.0, radius)  # sign of z_uv = sin 2φ / R
        right = mean_error(rec(*strains(shape), twist_sign=sign), shape)
        wrong = mean_error(rec(*strains(shape), twist_sign=-sign), shape)
        assert right < 0.06 and wrong > 1.0, (radius, right, wrong)


def test_graph_fields_used_only_when_the_stretch_shows_a_graph(rec, monkeypatch):
    calls = []
    real = recon.graph_sheet_fields

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(recon, "graph_sheet_fields", counting)
    # bent without stretch, or stretched in a pattern no graph explains: not used
    for shape in (ph.Cylinder(50.0, axis_angle=30.0), ph.SphereCap(60.0), ph.Flat(), ph.Cylinder(40.0)):
        rec(*strains(shape))
    assert calls == []
    rec(*strains(ph.Saddle(60.0, axis_angle=30.0)))
    assert calls  # (and again for its mirror image, which the posterior check weighs)


def test_a_bump_on_a_large_sheet_gets_no_spurious_constant_twist():
    """A bump's slopes are only partly resolved; a small constant twist fitted to absorb that
    would bend the far corners of a 16×16 sheet by millimetres."""
    n = 16
    shape = ph.GaussianBumps(height=-4.985, fwhm=39.34, centre=(-36.29, -33.48))
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
    err = mean_error(Reconstructor(n, n, PITCH, H, H, GAUGE)(eu, el), shape)
    assert err < 0.06, err


def test_closed_form_cubic_roots_match_numpy():
    """The twist fit's cubic: closed-form real roots equal numpy's eigenvalue roots, also for
    coefficients spread over twelve decades (largest root found first, the others deflated)."""
    from skinmap.reconstruction.engine import _cubic_real_roots

    rng = np.random.default_rng(11)
    for _ in range(3000):
        coeffs = rng.normal(size=4) * 10.0 ** rng.uniform(-6, 6, 4)
        expected = [r.real for r in np.roots(coeffs) if abs(r.imag) <= 1e-9 * max(abs(r), 1e-12)]
        got = _cubic_real_roots(*coeffs)
        for r in expected:
            assert min(abs(r - g) for g in got) <= 1e-7 * max(abs(r), 1e-12), (coeffs, expected, got)
    assert sorted(_cubic_real_roots(1.0, -6.0, 11.0, -6.0)) == pytest.approx([1.0, 2.0, 3.0])
    assert _cubic_real_roots(2.0, 0.0, 0.0, -16.0) == pytest.approx([2.0])
