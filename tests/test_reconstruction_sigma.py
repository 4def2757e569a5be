"""Uncertainty read node by node (uncertainty.SigmaField): what a consumer reading a few nodes
gets equals the whole field's values there, without the whole field being computed."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import frame_errors, within_3_sigma_in_frame

from skinmap.emulator.physics import gauge_strains, make_shape
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.uncertainty import SigmaField

N = M = 5
ELEMENTS_UV = np.stack([(np.arange(64) - 31.5) * 0.6, np.zeros(64)], axis=1)  # a row on a fine-grid line
SCATTERED_UV = np.random.default_rng(7).uniform(-29.0, 29.0, (40, 2))


@pytest.fixture(scope="module")
def rec() -> Reconstructor:
    return Reconstructor(N, M)


def strains(kind: str, seed: int, **params) -> tuple[np.ndarray, np.ndarray]:
    eu, el = gauge_strains(make_shape(kind, **params), N, M, pitch=12.0)
    rng = np.random.default_rng(seed)
    return eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape)


def bilinear(surf, sigma: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """locate_sigma's interpolation, from a whole field."""
    u, v = surf._u, surf._v
    h = u[1] - u[0]
    x, y = (uv[:, 0] - u[0]) / h, (uv[:, 1] - v[0]) / h
    b = np.clip(x.astype(int), 0, len(u) - 2)
    a = np.clip(y.astype(int), 0, len(v) - 2)
    tx, ty = x - b, y - a
    return ((1 - ty) * ((1 - tx) * sigma[a, b] + tx * sigma[a, b + 1])
            + ty * ((1 - tx) * sigma[a + 1, b] + tx * sigma[a + 1, b + 1]))


def frames(rec: Reconstructor):
    """(name, a function giving a fresh surface of the same frame): warm graph frames (σ from the
    graph fit, node by node), one with a missing unit, a cold graph frame and a general-model one."""
    e0 = strains("gaussian", 1, height=4.0, fwhm=18.0, u0=-6.0, v0=-4.0)
    first = rec(*e0)
    e1 = strains("gaussian", 2, height=4.0, fwhm=18.0, u0=-5.5, v0=-4.0)
    missing = (e1[0].copy(), e1[1])
    missing[0][0, 1, 2] = np.nan
    flat_cyl = strains("cylinder", 3, radius=40.0)
    return [
        ("warm graph", lambda: rec(*e1, previous=first)),
        ("warm graph, a missing unit", lambda: rec(*missing, previous=first)),
        ("cold graph", lambda: rec(*e0)),
        ("general model", lambda: rec(*flat_cyl)),
    ]


def test_node_sigma_and_locate_sigma_read_node_by_node_equal_the_whole_field(rec):
    for name, frame in frames(rec):
        by_node, whole = frame(), frame()
        assert by_node.diagnostics.extra["model"] == whole.diagnostics.extra["model"], name
        node_sigma = by_node.node_sigma
        on_line = by_node.locate_sigma(ELEMENTS_UV)
        scattered = by_node.locate_sigma(SCATTERED_UV)
        if name.startswith("warm graph"):
            assert by_node.diagnostics.extra["graph_fit"] == "warm", name
            # read node by node: the whole field was never computed
            assert by_node._fine_sigma is None, name
        field = whole.fine_sigma
        rows, cols = whole._node_index
        np.testing.assert_allclose(node_sigma, field[rows[:, None], cols], rtol=1e-10, atol=1e-15, err_msg=name)
        np.testing.assert_allclose(on_line, bilinear(whole, field, ELEMENTS_UV), rtol=1e-10, atol=1e-15, err_msg=name)
        np.testing.assert_allclose(scattered, bilinear(whole, field, SCATTERED_UV), rtol=1e-10, atol=1e-15,
                                   err_msg=name)
        # and once the whole field is there, the same values come from it
        np.testing.assert_allclose(by_node.node_sigma, by_node.fine_sigma[rows[:, None], cols], rtol=1e-10, err_msg=name)
        assert (node_sigma > 0).sum() >= node_sigma.size - 1, name  # the centre is the frame's origin


def test_graph_sigma_at_chosen_nodes_is_the_whole_propagation_there(rec):
    eu, el = strains("gaussian", 4, height=3.0, fwhm=20.0, u0=4.0, v0=2.0)
    surf = rec(eu, el)
    assert surf.diagnostics.extra["model"] == "graph"
    from skinmap.reconstruction.engine import unit_data

    graph = rec._graph
    turning, stretch, valid = unit_data(eu, el, rec.h_upper, rec.h_lower, rec.gauge_length)
    sig_t = np.sqrt(2.0) * 5.7e-5 / (rec.h_upper + rec.h_lower)
    sig_s = 5.7e-5 * np.hypot(rec.h_upper, rec.h_lower) / (rec.h_upper + rec.h_lower)
    data = graph.prepare(turning, stretch, valid, sig_t, sig_s)
    coeffs = surf.state.graph
    whole = graph.fine_height_sigma(coeffs, data, 0.7, rec.grid.centre)
    at = graph.height_sigma_at(coeffs, data, 0.7, rec.grid.centre)
    nodes = np.random.default_rng(5).choice(whole.size, 60, replace=False)
    np.testing.assert_allclose(at(nodes), whole.reshape(-1)[nodes], rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(at(np.arange(whole.size)), whole.reshape(-1), rtol=1e-10, atol=1e-15)


def test_sigma_field_reads_the_whole_field_once_and_repeats_for_free():
    calls: list[str] = []
    field = np.arange(12.0).reshape(3, 4)

    def whole() -> np.ndarray:
        calls.append("whole")
        return field

    def nodes(flat: np.ndarray) -> np.ndarray:
        calls.append(f"nodes {flat.tolist()}")
        return field.reshape(-1)[flat]

    sf = SigmaField(whole, nodes)
    assert sf.at(np.array([[5, 1], [5, 5]])).tolist() == [[5.0, 1.0], [5.0, 5.0]]
    assert calls == ["nodes [1, 5]"]  # each node once
    assert sf.at(np.array([5, 6])).tolist() == [5.0, 6.0]
    assert calls == ["nodes [1, 5]", "nodes [6]"]  # nodes read before are not computed again
    assert sf() is field and sf() is field and calls.count("whole") == 1
    assert sf.at(np.array([3])).tolist() == [3.0] and len(calls) == 3  # from the whole field now
    plain = SigmaField(whole)
    assert plain.at(np.array([7])).tolist() == [7.0]


@pytest.mark.parametrize("spec", ["gaussian:height=3,fwhm=18,u0=8,v0=-5",
                                  "gaussian:height=-4,fwhm=20,u0=-3,v0=14 + gaussian:height=2,fwhm=16,u0=15,v0=-12"])
def test_sensor_frame_errors_of_elastic_bumps_near_the_centre_within_3_sigma(spec: str) -> None:
    """A film on bumps beside the centre: the general model misplaces curvature that changes at
    the gauge scale, by more than the noise.  node_sigma says so (a share of
    uncertainty.resolution_sigma); the noise's σ alone does not.  (Without the gauges' shared
    gain, whose term the composition checked here does not hold: test_reconstruction_gain.py.)"""
    from skinmap.emulator import scenes
    from skinmap.reconstruction.engine import unit_data
    from skinmap.reconstruction.uncertainty import RESOLUTION_SHARE, resolution_sigma

    rec = Reconstructor(N, M, graph_fit=False, gain_sd=0.0)
    shape = scenes.parse_scene_spec(spec, "elastic", N, M, 12.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rng = np.random.default_rng(5)
    eu, el = eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape)
    surf = rec(eu, el)
    err = frame_errors(shape, surf, rec.grid)
    assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.node_sigma.max())
    turning, _, valid = unit_data(eu, el, 0.2, 0.2, 10.0)
    term = RESOLUTION_SHARE * resolution_sigma(rec.grid, valid, turning, np.sqrt(2.0) * 5.7e-5 / 0.4)
    noise_only = surf.node_scatter_sigma  # node_sigma without that term (nor the alignment floor)
    assert np.any(err > 3.0 * noise_only + 0.05)
    local = np.hypot(noise_only, term[np.ix_(rec.grid.node_rows, rec.grid.node_cols)])
    assert np.allclose(surf.node_sigma, np.maximum(local, local.mean()), rtol=1e-6, atol=1e-9)


def test_sensor_frame_is_the_best_fit_plane_from_the_centre_node_with_rows_along_x() -> None:
    """to_sensor_frame: the centre node at the origin, the least-squares plane of the fine nodes
    as z = 0 (its normal towards the upper side), the rows' mean chord along +x; the same
    answer for the sheet moved rigidly anywhere, and a tilted plane's heights come out flat."""
    from skinmap.reconstruction import to_sensor_frame

    grid = Reconstructor(N, M).grid
    uu, vv = np.meshgrid(grid.u, grid.v)
    # a bump beside the centre: its tangent there is tilted, its best-fit plane less so
    z = 3.0 * np.exp(-((uu - 9.0) ** 2 + (vv + 4.0) ** 2) / (2 * 7.0 ** 2))
    pos = np.stack([uu, vv, z], axis=-1)
    out = to_sensor_frame(grid, pos)
    a0, b0 = grid.centre
    assert np.allclose(out[a0, b0], 0.0, atol=1e-12)
    cells = out
    flat = cells.reshape(-1, 3)
    spread = flat - flat.mean(axis=0)
    cov = spread.T @ spread
    assert abs(cov[0, 2]) < 1e-8 and abs(cov[1, 2]) < 1e-8 and cov[2, 2] < 0.01 * cov[1, 1]  # z: the least axis
    chord = (cells[:, -1] - cells[:, 0]).sum(axis=0)
    assert abs(chord[1]) < 1e-9 and chord[0] > 0  # in the xz-plane, along +x
    assert out[a0, b0 + 1, 2] != pytest.approx(0.0, abs=1e-3)  # not the centre's tangent plane
    # any rigid motion of the sheet: the same frame
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    moved = pos @ q.T + np.array([5.0, -7.0, 11.0])
    assert np.allclose(to_sensor_frame(grid, moved), out, atol=1e-9)
    # a plane seen tilted: flat in its own frame, upper side +z
    tilted = np.stack([uu, vv, 0.2 * uu - 0.1 * vv], axis=-1)
    plane = to_sensor_frame(grid, tilted)
    assert np.abs(plane[..., 2]).max() < 1e-9
    assert np.allclose(np.hypot(plane[..., 0], plane[..., 1]), np.linalg.norm(tilted - tilted[a0, b0], axis=-1))


def test_a_sheet_wrapped_past_a_half_tube_keeps_a_steady_frame() -> None:
    """Wrapped so far that the best-fit plane is ill defined (a closed tube), the frame turns
    to the centre's tangent plane continuously: a small change of the wrap moves no node far."""
    from skinmap.reconstruction import to_sensor_frame

    grid = Reconstructor(N, M).grid
    uu, vv = np.meshgrid(grid.u, grid.v)
    frames, shapes = [], []
    for radius in np.linspace(5.0, 30.0, 60):  # flat up to u = -9 mm, wrapped beyond: 75°-440°
        phi = np.maximum(uu + 9.0, 0.0) / radius
        pos = np.stack([radius * np.sin(phi) + np.minimum(uu + 9.0, 0.0), vv, radius * (np.cos(phi) - 1.0)], axis=-1)
        frames.append(to_sensor_frame(grid, pos))
        shapes.append(pos)
    # each step of the wrap moves the nodes in the frame by little more than it moves them in
    # the centre's tangent plane (where the plane is defined it differs: rows off the centre)
    a0, b0 = grid.centre
    for k in range(len(frames) - 1):
        own = [p - p[a0, b0] for p in (shapes[k], shapes[k + 1])]
        step = np.linalg.norm(frames[k + 1] - frames[k], axis=-1).max()
        assert step < 2.0 * np.linalg.norm(own[1] - own[0], axis=-1).max() + 0.5, (k, step)
    # a closed tube (430° about the centre): the centre's tangent plane, the rows along +x there
    phi = uu / 8.0
    tube = np.stack([8.0 * np.sin(phi), vv, 8.0 * (np.cos(phi) - 1.0)], axis=-1)
    assert np.allclose(to_sensor_frame(grid, tube), tube, atol=1e-9)


@pytest.mark.parametrize("params", [{"radius": 87.3, "axis_angle": 54.5}, {"radius": 114.4, "axis_angle": 0.2}])
def test_graph_answer_sigma_median_within_0_7_to_1_6_of_its_monte_carlo_scatter_on_saddles(params) -> None:
    """A graph answer's node_sigma (the fit's Fisher information JᵀJ + P, the sensor frame by
    to_sensor_frame's own stencil) against the scatter of 24 noisy reconstructions in the
    sensor frame: the median ratio over the nodes within [0.7, 1.6] (with the fit's damping in
    the information and central differences for the frame, 2.3-2.4; the saddle at 54.5° stays
    at 1.5-1.6, the stretch's response to the noise is not linear at its full size).  Without
    the gauges' shared gain, which repeated frames do not scatter by (test_reconstruction_gain.py)."""
    rec = Reconstructor(N, M, gain_sd=0.0)
    shape = make_shape("saddle", **params)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rng = np.random.default_rng(11)
    nodes, sigmas = [], []
    for _ in range(24):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape))
        assert surf.diagnostics.extra["model"] == "graph"
        nodes.append(surf.nodes.reshape(-1, 3))
        sigmas.append(surf.node_sigma.reshape(-1))
    pts, sig = np.array(nodes), np.mean(sigmas, axis=0)
    scatter = np.sqrt(((pts - pts.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))
    keep = sig > 0  # the centre node is the frame's origin
    ratio = float(np.median(scatter[keep] / sig[keep]))
    assert 0.7 <= ratio <= 1.6, ratio


def test_twist_the_stretch_leaves_undecided_joins_sigma_on_a_turned_poisson_0_3_saddle_within_3_sigma() -> None:
    """A ν 0.3 film on a saddle turned 6° from the grid: the stretch pattern's interval reaches
    zero twist on some noise draws, where the least-shear answer (no twist) stood 0.4 mm off
    with σ 0.035 mm (5 times the bound).  The twist refined on the answer's family still says
    one: it joins node_sigma, and the sensor-frame errors lie within 3σ + 0.05 mm."""
    from skinmap.emulator import scenes

    rec5 = Reconstructor(N, M)
    shape = scenes.parse_scene_spec("saddle:radius=109.7,axis_angle=173.9,poisson=0.3", "elastic", N, M, 12.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rng = np.random.default_rng(3)
    undecided = 0
    for _ in range(24):
        surf = rec5(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape))
        extra = surf.diagnostics.extra
        if extra.get("stretch_twist", (0.0, 1.0))[1] != 0.0 or "stretch_twist_refined" not in extra:
            continue  # the pattern needed a twist on this draw: not the case under test
        undecided += 1
        err = frame_errors(shape, surf, rec5.grid)
        assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.node_sigma.max(), extra)
    assert undecided, "no draw reached the undecided case: the test no longer tests it"


def noisy_frames_within_3_sigma_in_frame(spec: str, n: int, seed: int, frames: int, keys: tuple[str, ...]) -> int:
    """Noisy frames of an elastic n×n scene, each asserted within 3σ + 0.05 mm in the sensor frame
    (its answer or, flagged ambiguous, its mirror); how many carry one of ``keys`` in their
    diagnostics."""
    from skinmap.emulator import scenes

    rec = Reconstructor(n, n)
    shape = scenes.parse_scene_spec(spec, "elastic", n, n, 12.0)
    eu, el = gauge_strains(shape, n, n, pitch=12.0)
    rng = np.random.default_rng(seed)
    count = 0
    for _ in range(frames):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape))
        err = frame_errors(shape, surf, rec.grid)
        assert within_3_sigma_in_frame(shape, surf, rec.grid), (err.max(), surf.node_sigma.max(),
                                                                 surf.diagnostics.extra)
        count += any(key in surf.diagnostics.extra for key in keys)
    return count


#: Films on domes turned off the grid, whose twist (k_uv, 1/mm) the stretch pattern does not tell
#: from none: frictionless, with partial friction, pre-stretched 5 % (principal axes at 45°), and
#: with a bump on it, whose stretch neither reading explains.
TURNED_DOMES = (
    "quadric:k_uu=0.0143,k_uv=0.002,k_vv=0.0143",
    "quadric:k_uu=0.0125,k_uv=0.002,k_vv=0.008,friction=0.001",
    "quadric:k_uu=0.0143,k_uv=0.0057,k_vv=0.0143,prestretch=0.05",
    "quadric:k_uu=0.01,k_uv=0.003,k_vv=0.006 + gaussian:height=2,fwhm=16,u0=6,v0=-5",
)


@pytest.mark.parametrize("spec", TURNED_DOMES)
def test_a_turned_dome_whose_twist_the_stretch_cannot_tell_from_none_is_within_3_sigma(spec: str) -> None:
    """A dome's twist is read only through its Gaussian curvature k_u k_v − τ², and the stretch
    reads that to a few percent: a dome of k = 0.0143 /mm with its principal axes at 45°
    (k_uv = 0.002) read 0.00147 /mm of an interval [0, 0.00353], a sphere of R 70 mm 0.00135
    of [0, 0.00377].  The answer keeps none (the least-shear prior), 0.9-1.6 mm off at a
    corner (3.8 mm pre-stretched); the twists the reading allows join node_sigma (where
    neither reading explains the stretch, a bump on the dome, those between none and the
    curvature product's own), and every noisy frame's sensor-frame errors lie within 3σ + 0.05
    mm (before, on 6 noisy frames of another seed, 0.35-1.7 mm mean off with σ 0.03-0.28: 2-10
    times the bound)."""
    opened = noisy_frames_within_3_sigma_in_frame(spec, N, seed=5, frames=6,
                                                  keys=("stretch_twist_open", "stretch_unread_twist"))
    assert opened, "no draw left the twist open: the test no longer tests it"


def test_a_dome_moved_into_the_trace_interval_keeps_either_sign_of_its_twist_within_3_sigma() -> None:
    """A 5×5 film pre-stretched 5 % on a dome turned off the rows (k_uu = 0.0125, k_vv = k_uv =
    0.005 /mm; principal axes 27° off the grid): the general model's twist lies beyond the
    trace's interval (−0.0099 against [0, 0.0069] /mm), and the answer is moved to the interval's middle with the model's sign, the wrong one,
    1.5 mm off.  The interval reaches none, so nothing tells the sign and no mirror is tried:
    the twists of either sign up to its top join node_sigma, and every noisy frame lies within
    3σ + 0.05 mm in the sensor frame (before, σ 0.55 mm: 1.56-1.58 times the bound on 5 of 6)."""
    moved = noisy_frames_within_3_sigma_in_frame("quadric:k_uu=0.0125,k_uv=0.005,k_vv=0.005,prestretch=0.05", N,
                                                 seed=11, frames=6, keys=("stretch_twist_moved",))
    assert moved, "no draw moved the twist into the trace's interval: the test no longer tests it"


@pytest.mark.slow
def test_a_dome_with_friction_whose_stretch_nothing_reads_is_within_3_sigma() -> None:
    """A 12×12 film with partial friction (10⁻³ N/mm³) on a dome turned off the grid (k_uu =
    0.0052, k_uv = 0.0008, k_vv = 0.0033 /mm): friction leaves the membrane's reading and the
    trace's both declined, the least-shear prior keeps none, 0.97 mm off.  The sheet is a dome
    all over, so the twists between none and the curvature product's own join node_sigma, and
    every noisy frame lies within 3σ + 0.05 mm in the sensor frame (before, σ 0.06 mm: 9.5-10
    times the bound)."""
    unread = noisy_frames_within_3_sigma_in_frame("quadric:k_uu=0.0052,k_uv=0.0008,k_vv=0.0033,friction=0.001", 12,
                                                  seed=7, frames=4, keys=("stretch_unread_twist",))
    assert unread, "no draw left the stretch unread: the test no longer tests it"


def test_twist_prior_none_keeps_the_answer_and_leaves_the_open_twist_out_of_sigma() -> None:
    """``twist_prior="none"`` (a sheet known to carry no twist where the stretch allows none: a
    balloon, a sphere) gives the same answer, and a σ without the open twist: on a film on a
    sphere of R 70 mm the corners' σ falls back to the noise's (both without the gauges' shared
    gain, test_reconstruction_gain.py)."""
    from skinmap.emulator import scenes

    shape = scenes.parse_scene_spec("sphere:radius=70", "elastic", N, M, 12.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rng = np.random.default_rng(6)
    eu, el = eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape)
    open_, none = Reconstructor(N, M, gain_sd=0.0)(eu, el), Reconstructor(N, M, twist_prior="none", gain_sd=0.0)(eu, el)
    assert np.array_equal(open_.nodes, none.nodes)
    assert "stretch_twist_open" in open_.diagnostics.extra and "stretch_twist_open" not in none.diagnostics.extra
    corners = (slice(None, None, N - 1), slice(None, None, M - 1))
    assert np.all(open_.node_sigma[corners] > 5.0 * none.node_sigma[corners])
    assert np.all(none.node_sigma[corners] < 0.1)
    assert np.all(frame_errors(shape, none, Reconstructor(N, M).grid) <= 3.0 * none.node_sigma + 0.05)
    with pytest.raises(ValueError, match="twist_prior"):
        Reconstructor(N, M, twist_prior="sometimes")


def test_a_twist_the_noise_hides_widens_sigma_on_a_cylinder_6_deg_off_the_grid_within_3_sigma() -> None:
    """A cylinder R 71 mm turned 84° (6° from the columns): its twist, 0.0015 /mm, reads 2-4 s.d.
    of the curvature product's noise.  Where the twist is taken, its sign is within the noise, no
    mirror is tried and the default sign stands: 0.65 mm off with σ 0.054 mm where it is wrong;
    where the noise's significance shrinks it to none, 0.31 mm off with σ 0.035.  Half the
    distance to the mirror image, or to the twist the product allows, joins σ, or the mirror
    stands beside the answer (a less-sheared twist the product agrees with, whose sign nothing
    reads): on every draw the sensor-frame errors of the answer or its mirror lie within
    3σ + 0.05 mm."""
    rec5 = Reconstructor(N, M)
    shape = make_shape("cylinder", radius=-71.2, axis_angle=84.1)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rng = np.random.default_rng(8)
    wrong = untwisted = 0
    for _ in range(10):
        surf = rec5(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape))
        err = frame_errors(shape, surf, rec5.grid)
        assert within_3_sigma_in_frame(shape, surf, rec5.grid), (err.max(), surf.node_sigma.max(),
                                                                 surf.diagnostics.twist_constant)
        wrong += err.mean() > 0.5  # the other sign's answer
        untwisted += surf.diagnostics.twist_constant == 0.0
    assert wrong and untwisted, "the draws no longer reach both cases: the test no longer tests them"


def test_a_twist_the_shrunk_product_allows_joins_sigma_on_a_cylinder_turned_6_deg() -> None:
    """A cylinder of R 80 mm turned 6° (twist 0.0013 /mm, 1-3 s.d. of the curvature product's
    noise): the significance test shrinks the twist taken; the twist the product allows, and
    one s.d. of it beyond (on one draw in 8 the product read 2.4 s.d. low, the twist taken was
    none and a corner 0.19 mm off, 1.2 times 3σ + 0.05 mm), joins σ: every node of 8 noisy draws
    within 3σ + 0.05 mm in the sensor frame."""
    from skinmap.emulator import physics as ph

    shape = ph.Cylinder(radius=80.0, axis_angle=6.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rec = Reconstructor(N, M)
    rng = np.random.default_rng(4)
    for _ in range(8):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape), twist_sign=1.0)
        err = frame_errors(shape, surf, rec.grid)
        assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.node_sigma.max())


def test_a_twist_the_curvature_product_hides_joins_sigma_on_a_cylinder_turned_2_deg() -> None:
    """A cylinder of R 80 mm turned 2° off the rows has a twist of 0.00044 /mm, below one s.d. of
    what the turning noise makes of the curvature product: the model takes none (the
    least-shear prior), 0.26 mm off at a corner.  The twist that s.d. hides joins node_sigma
    (engine.solve_twist's open twist): every node within 3σ + 0.05 mm in the sensor frame, on
    every noise draw (without it 2.5 times that)."""
    from skinmap.emulator import physics as ph

    shape = ph.Cylinder(radius=80.0, axis_angle=2.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rec = Reconstructor(N, M)
    rng = np.random.default_rng(4)
    grid = rec.grid
    for _ in range(6):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape), twist_sign=1.0)
        err = frame_errors(shape, surf, grid)
        assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.node_sigma.max())


@pytest.mark.slow
def test_a_prestretched_cylinder_near_the_rows_is_within_3_sigma_in_the_sensor_frame() -> None:
    """A film pre-stretched 5 % on a cylinder of R 93 mm turned 4.9° off the rows (twist
    0.0009 /mm, 0.8 s.d. of the curvature product's noise): 0.2 mm off with σ 0.03 mm before
    the hidden twist joined σ; now every node within 3σ + 0.05 mm (of the answer, or of its
    mirror where a less-sheared twist of no known sign was taken and flagged)."""
    from skinmap.emulator import scenes

    shape = scenes.parse_scene_spec("cylinder:radius=93,axis_angle=4.9,prestretch=0.05", "elastic", N, M, 12.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rec = Reconstructor(N, M)
    rng = np.random.default_rng(6)
    for _ in range(4):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape))
        err = frame_errors(shape, surf, rec.grid)
        assert within_3_sigma_in_frame(shape, surf, rec.grid), (err.max(), surf.node_sigma.max())


def test_the_stretch_noise_does_not_shrink_a_turned_cylinders_twist() -> None:
    """A cylinder of R 58 mm turned 9° off the columns (twist 0.0027 /mm, sign told): the
    stretch's own noise read as variation made the sheet look less developable, and the twist
    taken was 5 % short on average (one draw in 20: 18 %, 0.44 mm off at a corner, 1.6 times
    3σ + 0.05 mm).  With the noise's share removed from the variation (as
    engine.stretch_supports_curvature does) the twist is unbiased within 2 % and every node of
    20 noisy draws lies within 3σ + 0.05 mm in the sensor frame."""
    from skinmap.emulator import physics as ph

    shape = ph.Cylinder(radius=58.1, axis_angle=-80.8)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rec = Reconstructor(N, M)
    true = np.sin(2 * np.radians(-80.8)) / (2 * 58.1)
    rng = np.random.default_rng(1)
    ratios = []
    for _ in range(20):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape), twist_sign=-1.0)
        err = frame_errors(shape, surf, rec.grid)
        assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.node_sigma.max())
        ratios.append(surf.diagnostics.twist_constant / true)
    assert abs(np.mean(ratios) - 1.0) < 0.02, np.mean(ratios)


def test_a_less_sheared_twist_taken_keeps_the_products_own_within_sigma() -> None:
    """An oblique cylinder (R 95.2 mm at -61.6°, sign told) on one noise draw: the least-shear
    prior took a twist 5.6 % below the curvature product's (the data could not tell them
    apart), 0.19 mm off at a corner with σ 0.023 mm.  The product's own twist, which the data
    could not rule out either, now joins σ: every node within 3σ + 0.05 mm in the sensor frame."""
    import zlib

    from skinmap.emulator import physics as ph

    shape = ph.Cylinder(radius=95.2, axis_angle=-61.6)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    # the elastic bench's draw 0 of this scene (bench/elastic_dataset.py: class poisson_0.3, scene 3)
    rng = np.random.default_rng([2024, zlib.crc32(b"poisson_0.3"), N, M, 3, 2])
    du, dl = rng.normal(0.0, 5.7e-5, eu.shape), rng.normal(0.0, 5.7e-5, el.shape)
    rec = Reconstructor(N, M)
    surf = rec(eu + du, el + dl, twist_sign=-1.0)
    shift = surf.diagnostics.extra.get("least_shear_shift")
    assert shift is not None and surf.diagnostics.extra["undecided_twist"] == -shift
    err = frame_errors(shape, surf, rec.grid)
    assert np.all(err <= 3.0 * surf.node_sigma + 0.05), (err.max(), surf.node_sigma.max())


def _scatter_and_sigmas(rec: Reconstructor, shape, draws: int, seed: int, **kw):
    """Node scatter (sensor frame) over noisy frames of ``shape``, and the frames' mean
    node_sigma and node_scatter_sigma; all flattened, the centre node (the frame's origin) left out."""
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    rng = np.random.default_rng(seed)
    nodes, sigma, scatter_sigma = [], [], []
    for _ in range(draws):
        surf = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape), **kw)
        assert surf.mirror is None, surf.diagnostics.extra  # one answer: its scatter is the answer's
        nodes.append(surf.nodes.reshape(-1, 3))
        sigma.append(surf.node_sigma.reshape(-1))
        scatter_sigma.append(surf.node_scatter_sigma.reshape(-1))
        assert np.all(surf.node_scatter_sigma <= surf.node_sigma + 1e-12)
    pts = np.array(nodes)
    scatter = np.sqrt(((pts - pts.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))
    keep = np.mean(scatter_sigma, axis=0) > 0
    return scatter[keep], np.mean(sigma, axis=0)[keep], np.mean(scatter_sigma, axis=0)[keep]


@pytest.mark.parametrize("spec, kw", [("gaussian:height=3.5,fwhm=17,u0=-9,v0=6", {}),
                                      ("saddle:radius=95,axis_angle=38", {"twist_sign": 1})])
def test_scatter_sigma_median_within_0_7_to_1_5_of_the_monte_carlo_scatter_on_elastic_films(spec: str, kw) -> None:
    """On a film laminated on a bump, node_sigma is mostly the general model's resolution term
    (a bound on a bias that no repeated frame shows), and on a turned saddle mostly the stretch
    pattern's twist interval (ν unknown, the model's error in K): both are the same every frame.
    node_scatter_sigma leaves them out: the noise through the fit and the twist's reading, which
    is what 24 noisy frames scatter by (median ratio over the nodes within [0.7, 1.5]), while
    node_sigma is at least twice that scatter.  (The saddle's sign is told: at 38° the data
    leave it open, and an answer flagged ambiguous is either image from frame to frame.)"""
    from skinmap.emulator import scenes

    rec5 = Reconstructor(N, M)
    shape = scenes.parse_scene_spec(spec, "elastic", N, M, 12.0)
    scatter, sigma, scatter_sigma = _scatter_and_sigmas(rec5, shape, 24, 17, **kw)
    ratio = float(np.median(scatter / scatter_sigma))
    assert 0.7 <= ratio <= 1.5, ratio
    assert float(np.median(scatter / sigma)) <= 0.5, np.median(scatter / sigma)


def test_locate_sigma_of_the_scatter_is_bilinear_in_its_fine_map_read_node_by_node() -> None:
    """locate_sigma(uv, scatter=True) reads node_scatter_sigma's fine map as locate_sigma reads
    σ's (node by node where it can: equal to the whole map's bilinear values)."""
    from skinmap.emulator import scenes

    rec5 = Reconstructor(N, M)
    shape = scenes.parse_scene_spec("gaussian:height=3,fwhm=18,u0=8,v0=-5", "elastic", N, M, 12.0)
    eu, el = gauge_strains(shape, N, M, pitch=12.0)
    by_node = rec5(eu, el).locate_sigma(SCATTERED_UV, scatter=True)
    whole = rec5(eu, el)
    assert np.allclose(by_node, bilinear(whole, whole.scatter_sigma, SCATTERED_UV), rtol=1e-9, atol=1e-12)
    assert np.all(by_node < whole.locate_sigma(SCATTERED_UV))  # the resolution term is left out


def test_frames_limit_blas_to_one_thread_and_skip_the_limit_where_it_already_holds():
    """A frame's BLAS work runs on one thread (small problems; several threads made a busy
    machine's frames 5× slower).  skinmapd limits the whole process, and there entering and
    leaving the limit on every σ read (about 20 µs each) is skipped."""
    import contextlib

    from threadpoolctl import threadpool_limits

    rec = Reconstructor(3, 3)
    libraries = rec._blas_libraries
    if not libraries:
        pytest.skip("no BLAS library that threadpoolctl can see")
    with threadpool_limits(limits=1):
        assert isinstance(rec._one_blas_thread_context(), contextlib.nullcontext)
    with threadpool_limits(limits=2):
        if all(lib.num_threads == 1 for lib in libraries):
            pytest.skip("this BLAS runs on one thread only")
        with rec._one_blas_thread_context():
            assert all(lib.num_threads == 1 for lib in libraries)
        assert any(lib.num_threads == 2 for lib in libraries)


@pytest.mark.parametrize("n", [24, 32])
def test_scatter_sigma_of_a_turned_cylinder_on_a_large_sheet_within_0_7_to_1_5_of_its_scatter(n: int) -> None:
    """On 24×24 and larger sheets the constant twist of an oblique cylinder is read from the
    cells' gauge pairs (Reconstructor._pair_reading), whose product scatters less than the
    fields' (32×32: 1.5·10⁻⁸ against 4.5·10⁻⁸ /mm²): node_scatter_sigma carries the twist at the
    pairs' s.d., and describes what 16 noisy frames scatter by (median ratio over the nodes
    within [0.7, 1.5]; 0.57 and 0.62 with the fields' s.d.).  node_sigma, which bounds the error,
    keeps the fields'.  The cylinder is kinematic: what this checks is the noise's path through
    the model, which the mechanics of the mold do not change."""
    shape = make_shape("cylinder", radius=-470.0, axis_angle=67.7)
    eu, el = gauge_strains(shape, n, n, pitch=12.0)
    rec_n = Reconstructor(n, n)
    rng = np.random.default_rng(29)
    nodes, sigma, scatter_sigma = [], [], []
    for _ in range(16):
        surf = rec_n(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape), twist_sign=-1.0)
        assert "pair_product" in surf.diagnostics.extra  # the pairs read the twist
        nodes.append(surf.nodes.reshape(-1, 3))
        sigma.append(surf.node_sigma.reshape(-1))
        scatter_sigma.append(surf.node_scatter_sigma.reshape(-1))
    pts = np.array(nodes)
    scatter = np.sqrt(((pts - pts.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))
    keep = np.mean(scatter_sigma, axis=0) > 0
    ratio = float(np.median(scatter[keep] / np.mean(scatter_sigma, axis=0)[keep]))
    assert 0.7 <= ratio <= 1.5, ratio
    assert np.all(np.mean(scatter_sigma, axis=0) <= np.mean(sigma, axis=0) + 1e-12)


def test_graph_resolution_share_grows_below_25_cells_to_at_most_0_3() -> None:
    from skinmap.reconstruction.uncertainty import GRAPH_RESOLUTION_SHARE, graph_resolution_share

    assert graph_resolution_share(25) == graph_resolution_share(1024) == GRAPH_RESOLUTION_SHARE == 0.1
    shares = [graph_resolution_share(c) for c in (24, 20, 16, 15, 12, 9, 4, 1)]
    assert all(a < b for a, b in zip(shares[:4], shares[1:5])) and shares[4:] == [0.3] * 4
    assert shares[2] == pytest.approx(0.1 * (25 / 16) ** 1.5)


@pytest.mark.parametrize("seed", [None, 1, 2])
def test_a_3x3_graph_answer_with_bumps_at_its_edge_is_within_3_sigma_with_the_small_sheet_share(
        seed, monkeypatch) -> None:
    """Three bumps (2.9-3.8 mm, FWHM 23-25 mm) whose flanks cross a 3×3 sheet's corner and edge
    (found among 100 random sheets of 1-3 bumps): the graph answers 0.14 mm mean off, a corner
    node 0.38 mm.  With a tenth of the resolution term, as larger sheets take, 1.71-1.72 times
    3σ + 0.05 mm there; with the small sheet's share (uncertainty.graph_resolution_share, 0.3 on
    9 cells) 0.91-0.92.  Noise-free and two noise draws."""
    from conftest import aligned_node_errors

    from skinmap.emulator import physics as ph
    from skinmap.reconstruction import uncertainty

    bumps = [dict(height=2.9, fwhm=24.9, centre=(5.4, 9.7)), dict(height=3.0, fwhm=23.2, centre=(14.7, 17.3)),
             dict(height=3.8, fwhm=24.0, centre=(10.7, -1.3))]
    shape = ph.GaussianBumps(bumps=bumps)
    eu, el = gauge_strains(shape, 3, 3, pitch=12.0)
    if seed is not None:
        rng = np.random.default_rng(seed)
        eu, el = eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape)
    truth = ph.ground_truth(shape, 3, 3, 12.0).nodes

    def ratio() -> float:
        surf = Reconstructor(3, 3)(eu, el)
        assert surf.diagnostics.extra["model"] == "graph"
        err = aligned_node_errors(surf.nodes, truth)
        return float(np.max(err / (3.0 * surf.node_sigma.ravel() + 0.05)))

    assert ratio() <= 1.0
    monkeypatch.setattr(uncertainty, "GRAPH_SHARE_CELLS", 1)  # a tenth on every sheet
    assert ratio() > 1.3
