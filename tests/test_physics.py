"""Forward model: shapes, gauge strains, ground truth."""
from __future__ import annotations

import math

import numpy as np
import pytest

from skinmap.emulator.physics import (
    SHAPE_KINDS,
    BalloonDome,
    Cylinder,
    Flat,
    GaussianBumps,
    GraphSum,
    PalmGesture,
    Saddle,
    SphereCap,
    cell_centres,
    decouple_pair,
    gauge_layer_strains,
    gauge_strains,
    ground_truth,
    make_shape,
    parse_shape_spec,
)
from skinmap.emulator import physics as ph

H = 0.2


def test_cell_centres_follow_grid_convention():
    c = cell_centres(3, 4, 12.0)
    assert c.shape == (3, 4, 2)
    # u follows the column index j, v the row index i, centred on the sheet
    np.testing.assert_allclose(c[0, :, 0], [-18.0, -6.0, 6.0, 18.0])
    np.testing.assert_allclose(c[:, 0, 1], [-12.0, 0.0, 12.0])
    np.testing.assert_allclose(c.mean(axis=(0, 1)), 0.0, atol=1e-12)


def test_flat_reads_zero_everywhere():
    eu, el = gauge_strains(Flat(), 5, 7)
    assert eu.shape == el.shape == (2, 5, 7)
    np.testing.assert_allclose(eu, 0.0, atol=1e-10)
    np.testing.assert_allclose(el, 0.0, atol=1e-10)


@pytest.mark.parametrize("radius", [30.0, 80.0, -45.0])
def test_cylinder_along_v_gives_exact_layer_strains(radius):
    eu, el = gauge_strains(Cylinder(radius), 5, 5, h_upper=0.2, h_lower=0.25)
    np.testing.assert_allclose(eu[0], 0.2 / radius, atol=1e-9)
    np.testing.assert_allclose(el[0], -0.25 / radius, atol=1e-9)
    np.testing.assert_allclose(eu[1], 0.0, atol=1e-9)
    np.testing.assert_allclose(el[1], 0.0, atol=1e-9)


def test_cylinder_is_isometric_and_normals_are_unit_and_orthogonal():
    shape = Cylinder(35.0, axis_angle=25.0)
    uv = np.random.default_rng(1).uniform(-30, 30, size=(50, 2))
    n = shape.normal(uv)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-12)
    d = 1e-4
    for step in ([d, 0.0], [0.0, d]):
        tangent = (shape.position(uv + step) - shape.position(uv - step)) / (2 * d)
        np.testing.assert_allclose(np.linalg.norm(tangent, axis=-1), 1.0, atol=1e-7)
        np.testing.assert_allclose(np.sum(tangent * n, axis=-1), 0.0, atol=1e-7)
    # analytic normal agrees with the generic finite-difference one
    from skinmap.emulator.physics import Shape

    np.testing.assert_allclose(Shape.normal(shape, uv), n, atol=1e-8)


@pytest.mark.parametrize("angle", [0.0, 20.0, 45.0, 70.0, 90.0, 135.0])
def test_cylinder_any_axis_angle_matches_normal_curvature(angle):
    radius = 40.0
    th = math.radians(angle)
    eu, el = gauge_strains(Cylinder(radius, axis_angle=angle), 3, 3)
    # exact: the offset surface is a cylinder of radius R+h, circumferential stretch 1+h/R
    for k, c2 in ((0, math.cos(th) ** 2), (1, math.sin(th) ** 2)):
        for h, eps in ((H, eu[k]), (-H, el[k])):
            exact = math.sqrt((1 - c2) + c2 * (1 + h / radius) ** 2) - 1
            np.testing.assert_allclose(eps, exact, atol=1e-9)
            # first order: Kirchhoff–Love strain h·κ_n with κ_n = cos²θ/R along u, sin²θ/R along v
            np.testing.assert_allclose(eps, h * c2 / radius, atol=(H / radius) ** 2)


@pytest.mark.parametrize("radius", [40.0, -60.0])
def test_paper_decoupling_recovers_radius_and_stretch(radius):
    # a pure bend: the paper's formula inverts the forward model exactly
    eu, el = gauge_strains(Cylinder(radius), 5, 5, h_upper=0.2, h_lower=0.2)
    r, s = decouple_pair(eu[0], el[0])
    np.testing.assert_allclose(r, radius, rtol=1e-7)
    np.testing.assert_allclose(s, 0.0, atol=1e-10)
    # a sphere's offset layers are scaled copies of the neutral surface: exact for every gauge
    eu, el = gauge_strains(SphereCap(radius), 5, 5, h_upper=0.2, h_lower=0.3)
    r, s = decouple_pair(eu, el, 0.2, 0.3)
    np.testing.assert_allclose(r, radius, rtol=1e-6)


def test_sphere_cap_radial_lines_unstretched_and_circumference_shortened():
    radius = 50.0
    shape = SphereCap(radius)
    eu, el = gauge_strains(shape, 5, 5, h_upper=H, h_lower=H)
    r, s = decouple_pair(eu, el)
    # the centre row's u gauges and centre column's v gauges lie on radial geodesics
    np.testing.assert_allclose(s[0, 2, :], 0.0, atol=1e-9)
    np.testing.assert_allclose(s[1, :, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(eu[0, 2, 2], H / radius, atol=1e-9)
    # off the axes the circumferential part is compressed
    assert np.all(s[0, [0, 1, 3, 4], :] < 0)
    # geodesic distance from the apex equals the material radius
    uv = np.array([[20.0, 0.0], [0.0, -30.0], [12.0, 9.0]])
    x = shape.position(uv)
    centre = np.array([0.0, 0.0, -radius])
    np.testing.assert_allclose(np.linalg.norm(x - centre, axis=-1), radius, atol=1e-12)
    angle = np.arccos(np.clip(((x - centre) @ [0, 0, 1]) / radius, -1, 1))
    np.testing.assert_allclose(angle * radius, np.linalg.norm(uv, axis=-1), atol=1e-9)
    # concave sphere mirrors the convex one
    eu2, el2 = gauge_strains(SphereCap(-radius), 5, 5)
    r2, _ = decouple_pair(eu2, el2)
    np.testing.assert_allclose(r2, -radius, rtol=1e-6)


def test_symmetries():
    # a centred bump: 180° rotation and mirror symmetry; u/v swap exchanges the directions
    eu, el = gauge_strains(GaussianBumps(height=4.0, fwhm=18.0), 5, 5)
    np.testing.assert_allclose(eu, eu[:, ::-1, ::-1], atol=1e-10)
    np.testing.assert_allclose(eu[0], eu[1].T, atol=1e-10)
    np.testing.assert_allclose(el[0], el[1].T, atol=1e-10)
    # the saddle with R is the saddle with -R with u and v exchanged
    a_u, a_l = gauge_strains(Saddle(60.0), 4, 4)
    b_u, b_l = gauge_strains(Saddle(-60.0), 4, 4)
    np.testing.assert_allclose(a_u[0], b_u[1].T, atol=1e-10)
    np.testing.assert_allclose(a_l[0], b_l[1].T, atol=1e-10)
    # upper/lower of a convex shape are the lower/upper of its concave mirror image
    c_u, c_l = gauge_strains(Cylinder(50.0), 3, 4)
    d_u, d_l = gauge_strains(Cylinder(-50.0), 3, 4)
    np.testing.assert_allclose(c_u, d_l, atol=1e-10)
    np.testing.assert_allclose(c_l, d_u, atol=1e-10)


def test_saddle_signs_and_bump_is_convex_on_top():
    eu, el = gauge_strains(Saddle(60.0), 5, 5)
    r, _ = decouple_pair(eu, el)
    assert r[0, 2, 2] < 0 < r[1, 2, 2]  # curves toward the upper side along u
    np.testing.assert_allclose(abs(r[:, 2, 2]), 60.0, rtol=0.02)
    eu, el = gauge_strains(GaussianBumps(height=4.0, fwhm=18.0), 5, 5)
    r, s = decouple_pair(eu, el)
    assert r[0, 2, 2] > 0 and s[0, 2, 2] > 0  # graph mapping stretches the neutral plane


def test_graph_normal_matches_finite_difference_normal():
    from skinmap.emulator.physics import Shape

    shape = GaussianBumps(bumps=[dict(height=5, fwhm=15, u0=4, v0=-3), dict(height=-2, fwhm=10)])
    uv = np.random.default_rng(2).uniform(-25, 25, size=(40, 2))
    np.testing.assert_allclose(shape.normal(uv), Shape.normal(shape, uv), atol=1e-7)
    for t in (0.0, 0.37):
        mem = make_shape("membrane", fingers=2)
        np.testing.assert_allclose(mem.normal(uv, t), Shape.normal(mem, uv, t), atol=1e-7)


def test_quadrature_is_converged():
    for shape in (GaussianBumps(4, 12, 3, -2), BalloonDome(period=0), make_shape("membrane")):
        a = gauge_strains(shape, 5, 5, t=0.6)
        b = gauge_strains(shape, 5, 5, t=0.6, samples=16, panels=16)
        np.testing.assert_allclose(a, b, atol=1e-7)


def test_balloon_contact_follows_dome():
    # concave under the dome; the smoothing of the contact rim slightly flattens the patch
    eu, el = gauge_strains(BalloonDome(depth=7.0, period=0, smoothing=0.5), 5, 5)
    r, _ = decouple_pair(eu, el)
    np.testing.assert_allclose(r[:, 2, 2], -50.0, rtol=0.02)
    eu, el = gauge_strains(BalloonDome(depth=7.0, period=0), 5, 5)
    r, _ = decouple_pair(eu, el)
    np.testing.assert_allclose(r[:, 2, 2], -50.0, rtol=0.1)
    eu, el = gauge_strains(BalloonDome(depth=0.0, period=0), 5, 5)
    r, _ = decouple_pair(eu, el)
    np.testing.assert_allclose(r, 80.0, rtol=1e-6)  # untouched balloon


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["membrane:fingers=2", "palm", "balloon", "membrane"])
def test_time_varying_shapes_are_continuous_in_time(spec):
    # continuous (indeed Lipschitz) in t: halving the time step halves the largest change
    shape = parse_shape_spec(spec)
    assert shape.time_varying
    uv = cell_centres(5, 5, 12.0)

    def largest_changes(dt):
        ts = np.arange(0.0, 9.0, dt)
        x = shape.position(np.broadcast_to(uv, (len(ts),) + uv.shape), ts[:, None, None])
        # all instants in one call: the gauges of a 3x3 grid, repeated once per instant
        c = cell_centres(3, 3, 12.0).reshape(-1, 2)
        centres = np.tile(np.concatenate([c, c]), (len(ts), 1))
        dirs = np.tile(np.repeat([[1.0, 0.0], [0.0, 1.0]], len(c), axis=0), (len(ts), 1))
        times = np.repeat(ts, 2 * len(c))
        eps = gauge_layer_strains(shape, centres, dirs, [H, -H], 10.0, times, 8, 2)
        eps = eps.reshape(2, len(ts), -1).swapaxes(0, 1)
        return np.abs(np.diff(x, axis=0)).max(), np.abs(np.diff(eps, axis=0)).max(), np.ptp(x[..., 2])

    dx1, de1, travel = largest_changes(0.05)
    dx2, de2, _ = largest_changes(0.025)
    assert travel > 1.0  # it actually moves
    assert dx1 / dx2 > 1.7 and de1 / de2 > 1.7, (dx1, dx2, de1, de2)


def test_per_gauge_times_match_scalar_times():
    shape = make_shape("membrane", fingers=2)
    t = np.full((2, 4, 4), 0.3)
    t[1] = 0.8
    eu, el = gauge_strains(shape, 4, 4, t=t)
    eu3, _ = gauge_strains(shape, 4, 4, t=0.3)
    eu8, _ = gauge_strains(shape, 4, 4, t=0.8)
    np.testing.assert_allclose(eu[0], eu3[0], atol=1e-12)
    np.testing.assert_allclose(eu[1], eu8[1], atol=1e-12)


@pytest.mark.parametrize("t", [1.3, 1.5, 1.8, 3.2, 3.4])
def test_palm_morphs_to_and_from_the_cylinder_without_stretch(t):
    palm = PalmGesture(hold=1.0, transition=1.0, radius=40.0)
    eu, el = gauge_strains(palm, 5, 5, t=t)
    r, stretch = decouple_pair(eu, el)
    np.testing.assert_allclose(stretch, 0.0, atol=1e-9)  # isometric all the way
    assert np.all(np.isinf(r[1]) | (np.abs(r[1]) > 1e6))  # still a cylinder along v
    assert np.all(r[0] >= 40.0 - 1e-6)  # bending grows or relaxes toward R = 40


def test_palm_per_gauge_times_equal_scalar_times():
    palm = PalmGesture()
    t = np.where(np.arange(2)[:, None, None] == 0, 1.4, 4.6) * np.ones((2, 4, 4))
    eu, el = gauge_strains(palm, 4, 4, t=t)
    np.testing.assert_allclose(eu[0], gauge_strains(palm, 4, 4, t=1.4)[0][0], atol=1e-12)
    np.testing.assert_allclose(el[1], gauge_strains(palm, 4, 4, t=4.6)[1][1], atol=1e-12)


def test_palm_gesture_holds_its_key_shapes():
    palm = PalmGesture(hold=1.0, transition=1.0, radius=40.0)
    eu, el = gauge_strains(palm, 5, 5, t=2.5)  # holding the cylinder
    ref = gauge_strains(Cylinder(40.0), 5, 5)
    np.testing.assert_allclose(eu, ref[0], atol=1e-9)
    eu, _ = gauge_strains(palm, 5, 5, t=0.5 + palm.cycle)  # flat again after one cycle
    np.testing.assert_allclose(eu, 0.0, atol=1e-9)


def test_ground_truth_nodes_and_elements():
    shape = make_shape("gaussian", height=4.0, fwhm=18.0, centre=(3.0, -2.0))
    gt = ground_truth(shape, 5, 5, 12.0, t=0.0, element_uv=[[3.0, -2.0], [0.0, 0.0]])
    assert gt.nodes.shape == (5, 5, 3) and gt.normals.shape == (5, 5, 3)
    np.testing.assert_allclose(gt.element_positions[0], [3.0, -2.0, 4.0], atol=1e-12)
    np.testing.assert_allclose(gt.element_normals[0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(gt.nodes[..., :2], cell_centres(5, 5, 12.0), atol=1e-12)
    assert ground_truth(shape, 5, 5).element_positions is None


def test_spec_parsing_and_factory():
    s = parse_shape_spec("gaussian:height=4,fwhm=18,u0=3,v0=-2")
    assert isinstance(s, GaussianBumps) and s.bumps == [(4.0, 18.0, (3.0, -2.0))]
    s = parse_shape_spec("gaussian:height=4,centre=3/-2")
    assert s.bumps[0][2] == (3.0, -2.0)
    s = parse_shape_spec("saddle:radius=80 + gaussian:height=-3,u0=-15")
    assert isinstance(s, GraphSum) and len(s.parts) == 2
    assert isinstance(parse_shape_spec("cylinder:radius=-30,axis_angle=45"), Cylinder)
    for kind in SHAPE_KINDS:
        shape = make_shape(kind)
        x = shape.position(cell_centres(2, 2, 12.0), 0.5)
        assert x.shape == (2, 2, 3) and np.all(np.isfinite(x))


@pytest.mark.parametrize(
    "spec, words",
    [
        ("blob", "unknown shape kind 'blob'"),
        ("cylinder:radius=0", "radius"),
        ("cylinder:rad=3", "unknown parameter"),
        ("gaussian:fwhm=-1", "fwhm"),
        ("gaussian:height=abc", "not a number"),
        ("cylinder:radius", "key=value"),
        ("cylinder + gaussian", "graph shapes"),
        ("membrane:fingers=3", "fingers"),
        ("cylinder:radius=3/4", "bad parameter value"),
        ("", "empty"),
    ],
)
def test_bad_specs_are_named(spec, words):
    with pytest.raises(ValueError, match=words):
        parse_shape_spec(spec)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="rows"):
        gauge_strains(Flat(), 0, 3)
    with pytest.raises(ValueError, match="pitch"):
        cell_centres(3, 3, -1.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        Flat().position(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="unit"):
        gauge_layer_strains(Flat(), [[0, 0]], [[2.0, 0.0]], [0.2])
    with pytest.raises(ValueError, match="per-gauge times"):
        gauge_strains(Flat(), 3, 3, t=np.zeros((3, 3)))


from hypothesis import example, given, settings, strategies as st  # noqa: E402


@settings(max_examples=60, deadline=None)
@example(radius=40.0, angle=0.0, h_u=0.2, h_l=0.3)
@example(radius=-25.0, angle=180.0, h_u=0.1, h_l=0.4)
@given(
    radius=st.floats(15.0, 500.0) | st.floats(-500.0, -15.0),
    angle=st.floats(-180.0, 180.0),
    h_u=st.floats(0.05, 0.5),
    h_l=st.floats(0.05, 0.5),
)
def test_cylinder_property_exact_strains_and_decoupling(radius, angle, h_u, h_l):
    eu, el = gauge_strains(Cylinder(radius, axis_angle=angle), 2, 3, h_upper=h_u, h_lower=h_l)
    c2 = math.cos(math.radians(angle)) ** 2
    for k, c in ((0, c2), (1, 1.0 - c2)):
        np.testing.assert_allclose(eu[k], math.sqrt(1 - c + c * (1 + h_u / radius) ** 2) - 1, atol=1e-9)
        np.testing.assert_allclose(el[k], math.sqrt(1 - c + c * (1 - h_l / radius) ** 2) - 1, atol=1e-9)
    if c2 > 0.999999:  # a pure bend along u: the paper's formula recovers the radius
        r, s = decouple_pair(eu[0], el[0], h_u, h_l)
        np.testing.assert_allclose(r, radius, rtol=1e-5)


def test_turned_saddle_is_the_saddle_in_rotated_axes():
    rng = np.random.default_rng(3)
    uv = rng.uniform(-30.0, 30.0, (50, 2))
    for phi in (15.0, -30.0, 45.0):
        th = math.radians(phi)
        p = uv[:, 0] * math.cos(th) + uv[:, 1] * math.sin(th)
        q = -uv[:, 0] * math.sin(th) + uv[:, 1] * math.cos(th)
        pos = Saddle(70.0, axis_angle=phi).position(uv)
        np.testing.assert_allclose(pos[:, :2], uv, atol=1e-12)  # graph mapping
        np.testing.assert_allclose(pos[:, 2], (p * p - q * q) / 140.0, atol=1e-12)
    # default and 0° are the old saddle; 90° swaps the axes (the saddle of −R)
    np.testing.assert_allclose(Saddle(70.0).position(uv), Saddle(70.0, axis_angle=0.0).position(uv))
    np.testing.assert_allclose(Saddle(70.0, axis_angle=90.0).position(uv), Saddle(-70.0).position(uv), atol=1e-12)
    with pytest.raises(ValueError, match="axis_angle"):
        Saddle(70.0, axis_angle=float("nan"))


def test_turned_saddle_strains_twist_and_mirror():
    # at 45° the gauges along u and v see no mean bend at the centre, only the twist
    eu, el = gauge_strains(Saddle(60.0, axis_angle=45.0), 5, 5)
    kappa = (eu - el) / (2 * H)
    assert np.abs(kappa[:, 2, 2]).max() < 1e-6
    # at 30°: bend 1/R·cos 60° along u and its opposite along v at the centre
    eu, el = gauge_strains(Saddle(60.0, axis_angle=30.0), 5, 5)
    r, _ = decouple_pair(eu, el)
    np.testing.assert_allclose(1.0 / r[:, 2, 2], [-0.5 / 60.0, 0.5 / 60.0], rtol=0.02)
    # mirroring u → −u turns +φ into −φ: the strains are those of the mirrored grid
    a_u, _ = gauge_strains(Saddle(60.0, axis_angle=30.0), 4, 5)
    b_u, _ = gauge_strains(Saddle(60.0, axis_angle=-30.0), 4, 5)
    np.testing.assert_allclose(a_u, b_u[:, :, ::-1], atol=1e-10)
    assert np.abs(a_u - b_u).max() > 1e-3  # and differ from each other (the stretch pattern)
    # the spec parser and amplitude scaling keep the angle
    s = parse_shape_spec("saddle:radius=80,axis_angle=30")
    assert isinstance(s, Saddle) and s.axis_angle == 30.0


def test_quadric_matches_turned_saddle_and_checks_its_parameters():
    from skinmap.emulator.physics import Quadric, parse_shape_spec

    radius, angle = 70.0, 25.0
    phi = math.radians(angle)
    c2, s2 = math.cos(2 * phi), math.sin(2 * phi)
    quad = Quadric(c2 / radius, s2 / radius, -c2 / radius)
    saddle = Saddle(radius, axis_angle=angle)
    uv = np.random.default_rng(2).uniform(-30, 30, (50, 2))
    np.testing.assert_allclose(quad.position(uv), saddle.position(uv), atol=1e-12)
    np.testing.assert_allclose(quad.normal(uv), saddle.normal(uv), atol=1e-12)
    for a, b in zip(gauge_strains(quad, 4, 4), gauge_strains(saddle, 4, 4)):
        np.testing.assert_allclose(a, b, atol=1e-12)
    spec = parse_shape_spec("quadric:k_uu=0.01,k_uv=-0.004")
    assert (spec.k_uu, spec.k_uv, spec.k_vv) == (0.01, -0.004, 0.0)
    with pytest.raises(ValueError, match="k_uv"):
        Quadric(0.0, float("nan"), 0.0)


@pytest.mark.parametrize("bump, message", [
    ((2.0, 18.0, (0.0, 0.0)), "a mapping of height, fwhm and centre"),
    ({"height": 2.0, "width": 18.0}, "unknown parameter(s) ['width']"),
    ({"height": 2.0, 3: 1.0}, "unknown parameter(s) ['3']"),
])
def test_a_malformed_bump_is_named_not_a_type_error(bump, message):
    with pytest.raises(ValueError) as err:
        GaussianBumps(bumps=[{"height": 1.0}, bump])
    assert "bump 1" in str(err.value) and message in str(err.value)


class _Crease(ph.Shape):
    """z = k·|u − u0|: a V whose slope jumps from −k to +k along the line u = u0."""

    def __init__(self, k: float, u0: float):
        self.k, self.u0 = k, u0

    def position(self, uv, t=0.0):
        uv = ph._as_uv(uv)
        return np.concatenate([uv, self.k * np.abs(uv[..., :1] - self.u0)], axis=-1)

    def position_and_normal(self, uv, t=0.0):
        uv = ph._as_uv(uv)
        g = self.k * np.sign(uv[..., 0] - self.u0)
        normal = np.stack([-g, np.zeros_like(g), np.ones_like(g)], axis=-1) / np.sqrt(1.0 + g * g)[..., None]
        return self.position(uv), normal


@pytest.mark.parametrize("u0", [0.0, 1.2345, -3.3])
def test_creased_layer_strains_read_a_crease_as_its_turning_within_2e_4(u0):
    """Across a crease of turning angle Δθ = 2 atan k the layers at ±h lengthen by ∓h Δθ (first
    order; the concave side's cut corner and the convex side's arc differ from it at second
    order, 1e-4 here), on top of the neutral line's √(1 + k²); the quadrature's point
    derivatives miss a crease between their points (or spike on one inside their stencil)."""
    k, h, g = 0.2, 0.2, 10.0
    shape = _Crease(k, u0)
    centre, direction, offsets = np.array([[0.0, 0.0]]), np.array([[1.0, 0.0]]), np.array([h, -h])
    creased = ph.creased_layer_strains(shape, centre, direction, offsets, g, np.asarray(0.0)).ravel()
    neutral, turn = math.sqrt(1.0 + k * k) - 1.0, h * 2.0 * math.atan(k) / g
    assert creased == pytest.approx([neutral - turn, neutral + turn], abs=2e-4)
    quadrature = ph.quadrature_layer_strains(shape, centre, direction, offsets, g, np.asarray(0.0), 8, 4).ravel()
    assert abs(quadrature[1] - quadrature[0]) < 0.5 * turn  # what the crease-safe route is for


@pytest.mark.parametrize("spec", ["sphere:radius=40", "gaussian:height=5,fwhm=15,u0=7,v0=-5", "saddle:radius=30",
                                  "cylinder:radius=25,axis_angle=30"])
def test_creased_layer_strains_equal_the_quadrature_within_1e_6_on_smooth_surfaces(spec):
    shape = ph.parse_shape_spec(spec)
    centres, directions = ph._gauge_layout(5, 5, 12.0)
    offsets = np.array([0.2, -0.2])
    quadrature = ph.quadrature_layer_strains(shape, centres, directions, offsets, 10.0, np.asarray(0.0), 8, 4)
    creased = ph.creased_layer_strains(shape, centres, directions, offsets, 10.0, np.asarray(0.0))
    assert np.abs(creased - quadrature).max() < 1e-6


def test_the_emulator_reconstruction_and_gateway_share_one_cell_layout():
    """The emulator's cells, the reconstruction's nodes and the gateway's cell coordinates are one
    layout (skinmap.strains.cell_centres): a rectangular sheet's nodes sit where its cells are."""
    from skinmap.daemon.pipeline import ArrayGeometry
    from skinmap.reconstruction import reconstruct
    from skinmap.strains import cell_axes

    u, v = cell_axes(3, 4, 12.0)
    np.testing.assert_allclose(u, [-18.0, -6.0, 6.0, 18.0])
    np.testing.assert_allclose(v, [-12.0, 0.0, 12.0])
    eu, el = gauge_strains(Flat(), 3, 4, 12.0)
    surf = reconstruct(eu, el, 12.0, 0.2, 0.2)
    np.testing.assert_allclose(surf.nodes[..., :2], cell_centres(3, 4, 12.0), atol=1e-9)
    np.testing.assert_allclose(ArrayGeometry(3, 4, 12.0, 0.2, 0.2).cell_uv(), cell_centres(3, 4, 12.0))
