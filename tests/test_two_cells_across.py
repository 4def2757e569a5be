"""A sheet two cells across (2×M or N×2) cannot read its constant twist: the gauges lie along
rows and columns, which a twist leaves straight, and the stretch gives the Gaussian curvature
only through second differences along both directions, which two cells do not have.  Where
nothing reads it, σ must reach every twist the sheet may take (reconstructor.UNREAD_TWIST_TURN),
or the answer is confidently wrong: a 2×2 film on a sphere mold read as the cylinder at 45°,
0.5-0.6 mm off with σ 0.03; a saddle turned 45° read flat, 1.4 mm off with σ 0.008."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import aligned_error, worst_of_answers

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.reconstructor import UNREAD_TWIST_TURN

PITCH, H, G = 12.0, 0.2, 10.0
NOISE = 0.0057e-2


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("mechanics-cache")


def noisy_frames(shape, n: int, m: int, seed: int, count: int = 3):
    eu, el = ph.gauge_strains(shape, n, m, PITCH, H, H, G)
    rng = np.random.default_rng(seed)
    return [(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)) for _ in range(count)]


# the films' own mechanics (the emulator's elastic solver: films slid onto molds), and kinematic
# shapes the gauges are blind to the twist of
CASES = [
    ("elastic", "sphere:radius=65", 2, 2),
    ("elastic", "sphere:radius=-70,friction=0.001", 2, 2),
    ("elastic", "saddle:radius=65,axis_angle=25", 2, 2),
    ("elastic", "sphere:radius=-59.5,friction=0.001", 2, 4),
    ("kinematic", "saddle:radius=30,axis_angle=45", 2, 2),
    ("kinematic", "quadric:k_uu=0.001,k_uv=-0.023,k_vv=0.007", 3, 2),
]


@pytest.mark.parametrize("kind, spec, n, m", CASES)
def test_a_sheet_two_cells_across_is_within_3_sigma_of_a_twist_it_cannot_read(kind, spec, n, m, cache):
    shape = parse_scene_spec(spec, kind, n, m, PITCH, **({"cache_dir": cache} if kind == "elastic" else {}))
    truth = ph.ground_truth(shape, n, m, PITCH).nodes
    open_rec, none_rec = Reconstructor(n, m, PITCH, H, H, G), Reconstructor(n, m, PITCH, H, H, G, twist_prior="none")
    limit = UNREAD_TWIST_TURN / (max(n, m) * PITCH)
    for eu, el in noisy_frames(shape, n, m, seed=7):
        surf, told_none = open_rec(eu, el), none_rec(eu, el)
        assert min(worst_of_answers(surf, truth)) <= 1.0
        assert surf.diagnostics.extra["twist_unread_limit"] == pytest.approx(limit, rel=1e-4)
        # the answers are the same either way: only σ says what the data leave open
        np.testing.assert_array_equal(surf.nodes, told_none.nodes)
        assert "twist_unread_limit" not in told_none.diagnostics.extra
    # (the shapes are ones where that matters: told there is no twist, σ misses it)
    assert aligned_error(told_none.nodes, truth) > 0.1
    assert min(worst_of_answers(told_none, truth)) > 1.0


def test_a_sheet_three_cells_across_reads_its_twist_and_takes_no_such_term():
    for n, m in ((3, 3), (3, 8)):
        frames = noisy_frames(ph.make_shape("saddle", radius=60.0, axis_angle=30.0), n, m, seed=3, count=1)
        surf = Reconstructor(n, m, PITCH, H, H, G)(*frames[0])
        assert "twist_unread_limit" not in surf.diagnostics.extra


def test_the_unread_twist_reaches_from_none_to_the_limit_of_a_sign_told():
    """The spread is half the reach from the answer's twist to the farthest twist allowed: ±the
    limit, or from none to the limit of the sign told; it is the sheet's response u·v."""
    rec = Reconstructor(2, 2, PITCH, H, H, G)
    limit = rec._unread_twist_limit
    u, v = rec.grid.u[None, :], rec.grid.v[:, None]
    np.testing.assert_allclose(rec._unread_twist_spread(0.0, None), 0.5 * limit * np.abs(u * v))
    np.testing.assert_allclose(rec._unread_twist_spread(0.01, None), 0.5 * (limit + 0.01) * np.abs(u * v))
    np.testing.assert_allclose(rec._unread_twist_spread(0.01, 1.0), 0.5 * max(limit - 0.01, 0.01) * np.abs(u * v))
    np.testing.assert_allclose(rec._unread_twist_spread(0.01, -1.0), 0.5 * (limit + 0.01) * np.abs(u * v))
