"""Validation of the elastic-sheet solver (`skinmap.emulator.mechanics`) and the elastic scenes
(`skinmap.emulator.scenes`) against closed forms.

Every test prints the figure it measured (run with ``-s`` to see them): the errors against the
closed forms, the change on halving the mesh, the differences between the elastic and kinematic
forms.  Units are mm and N; strains are dimensionless, positive in tension.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from skinmap.emulator import mechanics as mc
from skinmap.emulator import physics as ph
from skinmap.emulator import scenes

PITCH = 12.0
H = 0.2  # the gauges' layers sit ±0.2 mm from the neutral plane (physics.gauge_strains' default)


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """One disk cache for the whole run: a scene used by several tests is solved once."""
    return tmp_path_factory.mktemp("mechanics-cache")


def readings(shape, n, m, t=0.0) -> np.ndarray:
    """(2 layers: upper, lower; 2 directions: along u, along v; N; M) gauge strains."""
    return np.stack(ph.gauge_strains(shape, n, m, PITCH, H, H, t=t))


# --------------------------------------------------------------------------- 1. cylinder wrap


def cylinder_layer_strain(cos_theta: float, offset: float, radius: float) -> float:
    """A gauge at angle θ to the circumference of a cylinder the sheet is wrapped on without
    stretch: its layer at ``offset`` from the mid-surface follows a helix whose circumferential
    part is scaled by (1 + offset/R), the axial part unchanged."""
    return math.sqrt((1.0 - cos_theta**2) + cos_theta**2 * (1.0 + offset / radius) ** 2) - 1.0


def gauge_cos_to_circumference(axis_angle: float) -> np.ndarray:
    """|cos θ| between each gauge direction (along u, along v) and the circumference: the axis is
    turned ``axis_angle`` from +v toward +u, so the circumference runs along (cos a, −sin a)."""
    a = math.radians(axis_angle)
    return np.array([abs(math.cos(a)), abs(math.sin(a))])


CYL_R = 40.0


@pytest.mark.parametrize("axis_angle", [0.0, 30.0])
def test_cylinder_wrap_of_a_membrane_is_isometric_and_gauges_read_the_closed_form(cache_dir, axis_angle):
    # a pure membrane (bending ~0): the only departure from an isometric wrap is the mesh's, of
    # order h²/(24R²) (chord against arc: 5.9e-5 at h = 1.5 mm, R = 40 mm)
    shape = scenes.make_scene("cylinder", 3, 3, PITCH, radius=CYL_R, axis_angle=axis_angle, bending=1e-6,
                              cache_dir=cache_dir)
    h_mesh = shape.grid.hu
    chord = h_mesh**2 / (24.0 * CYL_R**2)
    green = np.abs(mc.membrane_green_strain(shape.grid, shape.positions)).max()
    eps = readings(shape, 3, 3)
    cos = gauge_cos_to_circumference(axis_angle)
    closed = np.array([[cylinder_layer_strain(c, s * H, CYL_R) for c in cos] for s in (+1, -1)])  # (layer, dir)
    err = np.abs(eps - closed[:, :, None, None]).max()
    stretch = np.abs(0.5 * (eps[0] + eps[1])).max()
    print(f"\ncylinder R={CYL_R:g} axis {axis_angle:g}°, D=1e-6: max |Green strain| {green:.2e} "
          f"(bound h²/24R² = {chord:.2e}); layer strains vs closed form {err:.2e} "
          f"(signal {np.abs(closed).max():.2e}); |gauge stretch| {stretch:.2e}")
    assert green < chord
    assert err < 2 * chord
    assert stretch < 2 * chord
    # and the bending part is h·κ_n with κ_n = cos²θ/R, to the same order
    bend = 0.5 * (eps[0] - eps[1])
    np.testing.assert_allclose(bend, np.broadcast_to((H * cos**2 / CYL_R)[:, None, None], bend.shape), atol=2 * chord)


@pytest.mark.parametrize("axis_angle", [0.0, 30.0])
def test_cylinder_wrap_with_the_films_bending_stiffness_stretches_less_than_3D_over_Y_R2(cache_dir, axis_angle):
    # With the film's bending stiffness the discrete bending energy D/2|x_uu|² grows like
    # (1 + ε)⁴ with the membrane strain ε along the curvature, so the film is compressed there by
    # about 2·D·κ²/Y (1.85e-4 at R = 40 mm): the wrap is isometric only to that order (a 3-D
    # Saint Venant–Kirchhoff plate of the same D would give ~D·κ²/(2Y)).  Bound: 3·D/(Y·R²).
    shape = scenes.make_scene("cylinder", 3, 3, PITCH, radius=CYL_R, axis_angle=axis_angle, cache_dir=cache_dir)
    mat = mc.SheetMaterial()
    bound = 3.0 * mat.bending_stiffness / (mat.membrane_stiffness * CYL_R**2)
    green = mc.membrane_green_strain(shape.grid, shape.positions)
    a = math.radians(axis_angle)
    across = np.array([math.cos(a), -math.sin(a)])
    circumferential = np.einsum("i,...ij,j->...", across, green, across)
    eps = readings(shape, 3, 3)
    cos = gauge_cos_to_circumference(axis_angle)
    closed = np.array([[cylinder_layer_strain(c, s * H, CYL_R) for c in cos] for s in (+1, -1)])
    err = np.abs(eps - closed[:, :, None, None]).max()
    stretch = 0.5 * (eps[0] + eps[1])
    print(f"\ncylinder R={CYL_R:g} axis {axis_angle:g}°, D=0.083: max |Green strain| {np.abs(green).max():.2e}, "
          f"median circumferential {np.median(circumferential):.2e} (2Dκ²/Y = {2 * bound / 3:.2e}); "
          f"layer strains vs closed form {err:.2e}; gauge stretch {stretch.min():.2e}..{stretch.max():.2e}")
    assert np.abs(green).max() < bound
    assert err < bound
    assert np.abs(stretch).max() < bound
    assert np.median(circumferential) < 0  # compressed, not stretched, by the coupling


# --------------------------------------------------------------------------- 2. spherical cap


def solve_disc_on_sphere(a: float, radius: float, spacing: float, poisson: float = 0.48):
    """A free disc of radius ``a`` (the element mask) laid frictionless on a sphere, a pure
    membrane; its in-plane rigid motions held.  Element centres (material), their radii, and the
    Green strain's radial, hoop and shear parts there."""
    grid = mc.SheetGrid(a + 2 * spacing, a + 2 * spacing, spacing)
    uv = grid.uv()
    centre = 0.25 * (uv[1:, 1:] + uv[:-1, :-1] + uv[1:, :-1] + uv[:-1, 1:])
    r = np.linalg.norm(centre, axis=-1)
    active = r < a
    material = mc.SheetMaterial(poisson=poisson, bending_stiffness=1e-6)
    problem = mc.SheetProblem(grid, material, mold=mc.SphereHeight(radius), active=active,
                              hold_rigid=("x", "y", "turn"))
    sol = mc.solve(problem, grid.flat())
    green = mc.membrane_green_strain(grid, sol.positions)
    e_r = np.where((r > 1e-9)[..., None], centre / np.maximum(r, 1e-9)[..., None], np.array([1.0, 0.0]))
    e_t = np.stack([-e_r[..., 1], e_r[..., 0]], axis=-1)
    err = np.einsum("...i,...ij,...j->...", e_r, green, e_r)
    ett = np.einsum("...i,...ij,...j->...", e_t, green, e_t)
    ert = np.einsum("...i,...ij,...j->...", e_r, green, e_t)
    return r, active, err, ett, ert


def foppl_von_karman_disc(r: np.ndarray, a: float, radius: float, poisson: float):
    """Strains of a free disc forced onto a sphere (shallow membrane theory): the stress function
    solves ∇⁴φ = −Y/R², so N_rr = Y(a² − r²)/16R², N_θθ = Y(a² − 3r²)/16R² (N_rr(a) = 0 at the free
    edge); plane stress ε = (N − ν N')/Y.  The centre is in equibiaxial tension, the rim in hoop
    compression (a flat circle of radius a is longer than the sphere's geodesic circle)."""
    n_rr = (a * a - r * r) / (16.0 * radius**2)
    n_tt = (a * a - 3.0 * r * r) / (16.0 * radius**2)
    return n_rr - poisson * n_tt, n_tt - poisson * n_rr


@pytest.mark.slow
def test_free_disc_on_a_sphere_matches_the_foppl_von_karman_membrane_solution():
    a, radius, nu = 30.0, 300.0, 0.48
    centre_strain = (1.0 - nu) * a * a / (16.0 * radius**2)  # 3.25e-4
    # sign conventions of the closed form: tension at the centre, hoop compression at the rim
    err0, ett0 = foppl_von_karman_disc(np.array([0.0, a]), a, radius, nu)
    assert err0[0] == pytest.approx(centre_strain) and ett0[0] == pytest.approx(centre_strain)
    assert ett0[1] < 0 and err0[1] > 0  # rim: ε_rr = −ν N_θθ/Y > 0 although N_rr = 0
    errors = {}
    for spacing in (1.5, 1.0, 0.75):
        r, active, err, ett, ert = solve_disc_on_sphere(a, radius, spacing, nu)
        want_rr, want_tt = foppl_von_karman_disc(r, a, radius, nu)
        for zone, rmax in (("r<0.7a", 0.7 * a), ("r<0.5a", 0.5 * a)):
            inner = active & (r < rmax)
            errors[spacing, zone] = max(np.abs(err - want_rr)[inner].max(), np.abs(ett - want_tt)[inner].max(),
                                        np.abs(ert)[inner].max()) / centre_strain
        centre = r == r[active].min()
        errors[spacing, "centre"] = max(np.abs(err - want_rr)[centre].max(), np.abs(ett - want_tt)[centre].max()) / centre_strain
        # the solved disc has the closed form's signs: tension inside, hoop compression at the rim
        assert err[centre].min() > 0 and ett[centre].min() > 0
        rim = active & (r > a - 2 * spacing)
        assert np.median(ett[rim]) < -0.5 * centre_strain
    print("\nfree disc a=30 on sphere R=300, error / centre strain (3.25e-4):")
    for spacing in (1.5, 1.0, 0.75):
        print(f"  mesh {spacing:4g} mm: " + ", ".join(f"{z} {errors[spacing, z]:.2%}" for z in ("centre", "r<0.5a", "r<0.7a")))
    # Tolerances from the measured discretisation error.  The error is the staircase edge of the
    # disc (the element mask), largest at the edge and decaying inward, and an offset of the whole
    # field of about −1 % (the jagged rim carries less hoop stress); shallow-shell corrections are
    # O(a²/R²) = 1 %.  Measured at 1.5 mm: 5.4 % (r < 0.7a), 2.1 % (r < 0.5a), 0.95 % at the centre.
    tol = {"r<0.7a": 0.065, "r<0.5a": 0.03, "centre": 0.015}
    print("  tolerances: " + ", ".join(f"{z} {v:.1%}" for z, v in tol.items()))
    for spacing in (1.5, 1.0, 0.75):
        for zone, limit in tol.items():
            assert errors[spacing, zone] < limit, (spacing, zone)
    # and refining the mesh brings the solution toward the closed form
    assert errors[0.75, "r<0.7a"] < 0.8 * errors[1.5, "r<0.7a"]


# --------------------------------------------------------------------------- 3. pre-stretch


def test_flat_sheet_prestretched_uniformly_reads_the_prestretch_on_every_gauge_and_layer(cache_dir):
    shape = scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.05, cache_dir=cache_dir)
    eps = readings(shape, 3, 3)
    print(f"\nflat, prestretch 0.05: readings {eps.min():.12f}..{eps.max():.12f}")
    np.testing.assert_allclose(eps, 0.05, atol=1e-9)
    assert np.abs(shape.positions[..., 2]).max() < 1e-12  # stays flat: no bending


def test_uniaxial_prestretch_contracts_the_free_direction_by_plane_stress_poisson(cache_dir):
    nu = 0.48
    shape = scenes.make_scene("flat", 3, 3, PITCH, prestretch_u=0.05, cache_dir=cache_dir)
    eps = readings(shape, 3, 3)
    # Saint Venant–Kirchhoff in plane stress, uniaxial: S_vv = 0 ⇒ E_vv = −ν E_uu
    e_uu = 0.5 * ((1.05) ** 2 - 1.0)
    contraction = math.sqrt(1.0 + 2.0 * (-nu * e_uu)) - 1.0  # −0.0249103
    print(f"\nflat, prestretch_u 0.05: along u {eps[:, 0].min():.10f}..{eps[:, 0].max():.10f}; "
          f"along v {eps[:, 1].min():.10f}..{eps[:, 1].max():.10f} (closed form {contraction:.10f}); "
          f"error {np.abs(eps[:, 1] - contraction).max():.1e}")
    np.testing.assert_allclose(eps[:, 0], 0.05, atol=1e-9)
    # the anchor foundation that holds the free film's mean position costs ~1e-6 of the strain
    np.testing.assert_allclose(eps[:, 1], contraction, atol=1e-7)
    # the frame holds only u: the same stretch along v is the mirror image
    other = readings(scenes.make_scene("flat", 3, 3, PITCH, prestretch_v=0.05, cache_dir=cache_dir), 3, 3)
    np.testing.assert_allclose(other[:, 1], 0.05, atol=1e-9)
    np.testing.assert_allclose(other[:, 0], contraction, atol=1e-7)


# --------------------------------------------------------------------------- 4. mesh convergence


@pytest.mark.parametrize("kind, params", [
    ("gaussian", dict(height=4.0, fwhm=18.0, u0=4.0, v0=-3.0)),
    ("sphere", dict(radius=60.0)),
], ids=["gaussian-off-centre", "sphere-R60"])
@pytest.mark.slow
def test_halving_the_mesh_changes_every_reading_by_less_than_1_percent_of_the_largest(cache_dir, kind, params):
    coarse = readings(scenes.make_scene(kind, 3, 3, PITCH, mesh=1.5, cache_dir=cache_dir, **params), 3, 3)
    fine = readings(scenes.make_scene(kind, 3, 3, PITCH, mesh=0.75, cache_dir=cache_dir, **params), 3, 3)
    largest = np.abs(fine).max()
    change = np.abs(coarse - fine)
    big = np.abs(fine) > 0.1 * largest
    per_gauge = (change[big] / np.abs(fine[big])).max()
    stretch_change = np.abs(0.5 * (coarse[0] + coarse[1] - fine[0] - fine[1])).max()
    bend_change = np.abs(0.5 * (coarse[0] - coarse[1] - fine[0] + fine[1])).max()
    print(f"\n{kind} {params}: largest reading {largest:.3e}; mesh 1.5 → 0.75 changes readings by "
          f"{change.max():.2e} = {change.max() / largest:.2%} of it (stretch {stretch_change:.1e}, "
          f"bending {bend_change:.1e}); per gauge above 10 % of the largest: up to {per_gauge:.1%}")
    assert change.max() < 0.01 * largest
    assert per_gauge < 0.05


# --------------------------------------------------------------------------- 5. elastic vs kinematic


def test_elastic_film_on_a_sphere_slides_outward_of_the_geodesic_map(cache_dir):
    elastic = scenes.make_scene("sphere", 3, 3, PITCH, radius=60.0, cache_dir=cache_dir)
    kinematic = ph.make_shape("sphere", radius=60.0)
    xe = ph.ground_truth(elastic, 3, 3, PITCH).nodes
    xk = ph.ground_truth(kinematic, 3, 3, PITCH).nodes
    for x in (xe, xk):  # both on the sphere
        np.testing.assert_allclose(x[..., 2], np.sqrt(60.0**2 - np.sum(x[..., :2] ** 2, -1)) - 60.0, atol=1e-6)
    dxy = np.linalg.norm(xe[..., :2] - xk[..., :2], axis=-1)
    outward = np.linalg.norm(xe[..., :2], axis=-1) - np.linalg.norm(xk[..., :2], axis=-1)
    print(f"\nsphere R=60, 3×3: elastic − geodesic in-plane node offset up to {dxy.max():.3f} mm "
          f"(corners {outward[0, 0]:+.3f} mm radially), centre {dxy[1, 1]:.1e} mm")
    # the geodesic map keeps radial lines unstretched; the elastic film is in radial tension inside
    # (the free-disc solution), so its outer cells lie further out along the sphere
    assert dxy.max() > 0.05
    assert outward[[0, 0, -1, -1], [0, -1, 0, -1]].min() > 0.05
    assert dxy[1, 1] < 1e-6  # the centre is held (symmetry and the rigid-motion hold)


@pytest.mark.parametrize("axis_angle", [0.0, 30.0])
def test_elastic_film_on_a_cylinder_agrees_with_the_isometric_wrap(cache_dir, axis_angle):
    elastic = scenes.make_scene("cylinder", 3, 3, PITCH, radius=CYL_R, axis_angle=axis_angle, cache_dir=cache_dir)
    kinematic = ph.make_shape("cylinder", radius=CYL_R, axis_angle=axis_angle)
    ge = ph.ground_truth(elastic, 3, 3, PITCH)
    gk = ph.ground_truth(kinematic, 3, 3, PITCH)
    dx = np.linalg.norm(ge.nodes - gk.nodes, axis=-1).max()
    dn = np.linalg.norm(ge.normals - gk.normals, axis=-1).max()
    print(f"\ncylinder R={CYL_R:g} axis {axis_angle:g}°: elastic − isometric wrap node offset {dx:.2e} mm, "
          f"normals {dn:.1e}")
    # the bending coupling's compression (≤ 3D/(YR²) ≈ 2.8e-4) over the 17 mm to the outer cells
    assert dx < 5e-3
    assert dn < 2e-4


# --------------------------------------------------------------------------- 6. cache


def test_scene_cache_stores_one_file_per_parameter_set_and_reloads_it_without_solving(tmp_path, monkeypatch):
    first = scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.02, cache_dir=tmp_path)
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 1

    def no_solve(*args, **kwargs):
        raise AssertionError("solved again although the scene is cached")

    monkeypatch.setattr(mc, "solve", no_solve)
    again = scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.02, cache_dir=tmp_path)
    assert np.array_equal(again.positions, first.positions)
    monkeypatch.undo()

    other = scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.03, cache_dir=tmp_path)
    files2 = sorted(tmp_path.glob("*.npz"))
    assert len(files2) == 2 and files[0] in files2
    assert not np.array_equal(other.positions, first.positions)
    np.testing.assert_allclose(readings(other, 3, 3), 0.03, atol=1e-9)


def test_scene_cache_resolves_a_damaged_file_and_cache_false_writes_nothing(tmp_path):
    first = scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.02, cache_dir=tmp_path)
    (path,) = tmp_path.glob("*.npz")
    path.write_bytes(b"not an npz file")
    again = scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.02, cache_dir=tmp_path)
    assert np.array_equal(again.positions, first.positions)
    uncached = tmp_path / "uncached"
    scenes.make_scene("flat", 3, 3, PITCH, prestretch=0.02, cache=False, cache_dir=uncached)
    assert not uncached.exists() or not any(uncached.iterdir())


# --------------------------------------------------------------------------- 7. bad input


def test_negative_prestretch_is_refused_naming_the_prestretch(tmp_path):
    with pytest.raises(ValueError, match=r"prestretch.*between 0 and 0\.5.*-0\.05"):
        scenes.make_scene("flat", 3, 3, PITCH, prestretch=-0.05, cache_dir=tmp_path)
    with pytest.raises(ValueError, match=r"prestretch_v.*0\.6"):
        scenes.make_scene("flat", 3, 3, PITCH, prestretch_v=0.6, cache_dir=tmp_path)
    assert not list(tmp_path.glob("*.npz"))


def test_unknown_scene_parameter_is_refused_naming_it(tmp_path):
    with pytest.raises(ValueError, match=r"unknown parameter.*bogus"):
        scenes.make_scene("sphere", 3, 3, PITCH, radius=60.0, bogus=1.0, cache_dir=tmp_path)
    with pytest.raises(ValueError, match=r"unknown parameter.*bogus"):
        scenes.parse_scene_spec("sphere:radius=60,bogus=1", "elastic", 3, 3, PITCH, cache_dir=tmp_path)
    with pytest.raises(ValueError, match=r"unknown shape kind 'blob'"):
        scenes.make_scene("blob", 3, 3, PITCH, cache_dir=tmp_path)


@pytest.mark.parametrize("poisson", [0.6, -0.1])
def test_poisson_ratio_outside_0_to_half_is_refused_naming_poisson(poisson):
    with pytest.raises(ValueError, match=r"poisson must be in \[0, 0\.5\]"):
        mc.SheetMaterial(poisson=poisson)
    with pytest.raises(ValueError, match=r"poisson"):
        scenes.make_scene("flat", 3, 3, PITCH, poisson=poisson, cache=False)


def test_solve_refuses_a_start_or_mask_of_the_wrong_shape_naming_the_expected_shape():
    grid = mc.SheetGrid(6.0, 4.5, 1.5)  # 9 × 7 nodes
    problem = mc.SheetProblem(grid)
    with pytest.raises(ValueError, match=r"start positions must be \(7, 9, 3\), got \(9, 7, 3\)"):
        mc.solve(problem, np.zeros((9, 7, 3)))
    with pytest.raises(ValueError, match=r"start positions must be \(7, 9, 3\), got \(7, 9, 2\)"):
        mc.solve(problem, grid.flat()[..., :2])
    with pytest.raises(ValueError, match=r"NaN"):
        mc.solve(problem, np.full((7, 9, 3), np.nan))
    with pytest.raises(ValueError, match=r"fixed mask must be \(7, 9, 3\)"):
        mc.solve(mc.SheetProblem(grid, fixed=np.zeros((7, 9), bool)), grid.flat())
    with pytest.raises(ValueError, match=r"active element mask must be \(6, 8\)"):
        mc.solve(mc.SheetProblem(grid, active=np.ones((7, 9), bool)), grid.flat())
    with pytest.raises(ValueError, match=r"hold_rigid.*'z'"):
        mc.solve(mc.SheetProblem(grid, mold=mc.FlatHeight(), hold_rigid=("x", "z")), grid.flat())


# --------------------------------------------------------------------------- 8. a moving scene


MEMBRANE = dict(fingers=1, keyframes=8)


@pytest.fixture(scope="module")
def membrane(cache_dir):
    return scenes.make_scene("membrane", 5, 5, PITCH, cache_dir=cache_dir, **MEMBRANE)


@pytest.mark.slow
def test_membrane_readings_are_the_key_frames_exact_quadrature_zero_unpressed_and_stretched_at_depth(membrane):
    shape = membrane
    assert isinstance(shape, scenes.KeyframedSheet)
    kin = ph.FingertipMembrane(fingers=1)
    # the key frames cover one cycle of 2·period: the press repeats every period, the slide every two
    assert shape.period == pytest.approx(2 * kin.period)
    np.testing.assert_allclose(shape.times, np.arange(8) * shape.period / 8)
    for k, t in enumerate(shape.times):
        exact = readings(scenes.SheetShape(shape.grid, shape.positions[k]), 5, 5)
        np.testing.assert_allclose(readings(shape, 5, 5, t=float(t)), exact, atol=1e-12)
    rest = readings(shape, 5, 5, t=0.0)
    deepest = float(kin.period / 2)  # depth·(1 − cos 2πt/period)/2 is largest at half a period
    pressed = readings(shape, 5, 5, t=deepest)
    stretch = 0.5 * (pressed[0] + pressed[1])
    print(f"\nmembrane: |readings| at rest {np.abs(rest).max():.1e}; at the deepest press (t={deepest:g} s) "
          f"centre stretch along u {stretch[0, 2, 2]:.4f}, along v {stretch[1, 2, 2]:.4f}, "
          f"largest reading {np.abs(pressed).max():.4f}")
    # unpressed, the fingertip only touches: its unilateral penalty starts 10 µm out (a smooth
    # onset), so the film sits a few µm below it and reads well under ten microstrain
    assert np.abs(rest).max() < 1e-5
    assert shape.positions[0][..., 2].min() > -1.5e-2
    # the fingertip (at (0, travel) then) stretches the membrane under and around it
    assert stretch[:, 2, 2].min() > 1e-3
    assert stretch[:, 1:4, 1:4].mean() > stretch[:, [0, -1], :].mean()


@pytest.mark.slow
def test_membrane_half_a_slide_later_is_the_mirror_image_and_the_film_stays_under_the_fingertip(membrane):
    shape = membrane
    kin = ph.FingertipMembrane(fingers=1)
    # at t = period/2 the finger presses fully at v = +travel, at 3·period/2 at v = −travel
    t1, t3 = 0.5 * kin.period, 1.5 * kin.period
    first, second = readings(shape, 5, 5, t=t1), readings(shape, 5, 5, t=t3)
    mirror = np.abs(second[:, :, ::-1, :] - first).max()
    print(f"\nmembrane: readings at t={t3:g} s against the mirror image of t={t1:g} s: {mirror:.1e}")
    np.testing.assert_allclose(second[:, :, ::-1, :], first, atol=1e-6)
    radius = 8.0 + 0.5  # finger_radius + half the film
    for t, x in zip(shape.times, shape.positions):
        for d, c in kin._fingers(np.asarray(t)):
            centre = np.array([c[0], c[1], radius - float(d)])
            gap = np.linalg.norm(x - centre, axis=-1) - radius
            assert gap.min() > -1e-2  # penalty overlap only
        # pressed from above, the clamped film is pushed down, never wrapped over the finger
        assert x[..., 2].max() < 1e-3, f"the film went over the fingertip at t={t:g} s"


@pytest.mark.slow
def test_membrane_per_gauge_times_read_each_gauge_at_its_own_instant(membrane):
    shape = membrane
    t = np.zeros((2, 5, 5))
    t[0] = 1.0
    t[1, 2, :] = 0.5
    t[1, 0, 0] = 0.3  # between key frames
    mixed = readings(shape, 5, 5, t=t)
    want = np.empty_like(mixed)
    for value in np.unique(t):
        at = readings(shape, 5, 5, t=float(value))
        want[:, t == value] = at[:, t == value]
    np.testing.assert_allclose(mixed, want, atol=1e-12)
    assert np.abs(mixed[:, 0] - readings(shape, 5, 5, t=0.0)[:, 0]).max() > 1e-3  # the times mattered


def test_sparse_key_frames_keep_the_film_under_the_fingertip(cache_dir):
    # four key frames, t = 0 (no press), 1 (finger at v = +6), 2 (released), 3 (at v = −6);
    # a small coarse membrane keeps it cheap; an extrapolated warm start once lifted the film over
    # the next fingertip here
    shape = scenes.make_scene("membrane", 1, 1, PITCH, fingers=1, keyframes=4, half_u=18.0, half_v=18.0,
                              mesh=3.0, cache_dir=cache_dir)
    top = [float(x[..., 2].max()) for x in shape.positions]
    print(f"\nmembrane, 4 key frames: highest film point per frame {top}")
    assert max(top) < 1e-3
    np.testing.assert_allclose(shape.positions[3][::-1, :, 2], shape.positions[1][..., 2], atol=1e-6)


def test_elastic_parameters_that_do_not_apply_to_a_scene_are_refused_by_name(cache_dir):
    with pytest.raises(ValueError, match="finger_radius"):
        scenes.make_scene("flat", 3, 3, PITCH, finger_radius=8.0, cache_dir=cache_dir)
    with pytest.raises(ValueError, match="tension"):
        scenes.make_scene("membrane", 3, 3, PITCH, tension=0.1, cache_dir=cache_dir)
    with pytest.raises(ValueError, match="prestretch must"):
        scenes.make_scene("flat", 3, 3, PITCH, prestretch=-0.05, cache_dir=cache_dir)
    with pytest.raises(ValueError, match="keyframes"):
        scenes.make_scene("balloon", 3, 3, PITCH, keyframes=1.5, cache_dir=cache_dir)
    with pytest.raises(ValueError, match="unknown parameter"):
        scenes.make_scene("membrane", 3, 3, PITCH, fingers=1, wobble=2.0, cache_dir=cache_dir)
