"""The emulator driven by elastic scenes: the firmware streams the solved sheet's readings, the
truth is the solved sheet's, moving scenes are sampled per TDM step, the CLI takes both forms."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap import protocol as p
from skinmap.emulator import command as cli
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.strains import gauge_strain
from skinmap.emulator.physics import gauge_strains, ground_truth, make_shape
from skinmap.emulator.scenes import KeyframedSheet, SheetShape, make_scene, parse_scene_spec


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("mechanics-cache")


def scans(dev: Device, t0: float, until: float) -> list:
    dec = p.StreamDecoder()
    frames = dec.feed(dev.on_bytes(p.encode_frame(p.Start(1), 0), t0))
    frames += dec.feed(dev.poll(until))
    return [f.msg for f in frames if f.msg_type == p.MsgType.SCAN]


@pytest.mark.slow
def test_device_streams_the_elastic_sphere_not_the_geodesic_map(cache):
    shape = make_scene("sphere", 5, 5, 12.0, radius=60.0, cache_dir=cache)
    assert isinstance(shape, SheetShape)
    dev = Device(ScannerSpec(n=5, m=5, scan_rate_hz=10.0, electrical=ElectricalConfig.ideal()), shape, now_s=100.0)
    dev.poll(100.0)
    scan = scans(dev, 100.0, 100.1)[0]
    eps = gauge_strain(scan.resistances_ohm(), dev.calibration.gauge_factor, dev.calibration.base_resistance_ohm)
    np.testing.assert_allclose(eps, np.stack(gauge_strains(shape, 5, 5)), atol=3e-7)  # the 1 µΩ quantum
    kinematic = np.stack(gauge_strains(make_shape("sphere", radius=60.0), 5, 5))
    # a film sliding on the sphere is stretched at its centre; the geodesic map only shortens circles
    stretch = 0.5 * (eps[0] + eps[1])
    kin_stretch = 0.5 * (kinematic[0] + kinematic[1])
    assert stretch[:, 2, 2].min() > 0.005 > kin_stretch[:, 2, 2].max()
    truth = dev.ground_truth(scan.sample_index)
    np.testing.assert_allclose(truth.nodes, ground_truth(shape, 5, 5, 12.0).nodes)


@pytest.mark.slow
def test_moving_elastic_scene_is_sampled_at_each_units_tdm_step(cache):
    # a coarse mesh and few key frames: this checks the sampling, not the mechanics
    shape = make_scene("membrane", 5, 5, 12.0, fingers=2, period=1.0, mesh=3.0, keyframes=8, cache_dir=cache)
    assert isinstance(shape, KeyframedSheet) and shape.time_varying
    dev = Device(ScannerSpec(n=5, m=5, scan_rate_hz=5.0, electrical=ElectricalConfig.ideal()), shape, now_s=100.0)
    dev.poll(100.0)
    scan = scans(dev, 100.0, 100.45)[0]
    eps = gauge_strain(scan.resistances_ohm(), dev.calibration.gauge_factor, dev.calibration.base_resistance_ohm)
    times = p.unit_sample_times_us(scan.timestamp_us, scan.step_period_ns, dev.drive_line) * 1e-6
    skewed = np.stack(gauge_strains(shape, 5, 5, t=times, samples=8, panels=1))  # as the device asks
    np.testing.assert_allclose(eps, skewed, atol=3e-7)
    at_step0 = np.stack(gauge_strains(shape, 5, 5, t=times.min()))
    assert np.abs(eps - at_step0).max() > 1e-4  # the fingers moved during the scan


@pytest.mark.slow
def test_keyframed_readings_are_exact_at_key_frames_and_continuous_between(cache):
    shape = make_scene("membrane", 5, 5, 12.0, fingers=1, period=1.0, mesh=3.0, keyframes=8, cache_dir=cache)
    t_k = float(shape.times[3])
    exact = np.stack(gauge_strains(shape.key_frames[3], 5, 5))
    np.testing.assert_allclose(np.stack(gauge_strains(shape, 5, 5, t=t_k)), exact, atol=1e-12)
    # a whole cycle later it is the same frame; just after, the readings move a little
    np.testing.assert_allclose(np.stack(gauge_strains(shape, 5, 5, t=t_k + shape.period)), exact, atol=1e-9)
    near = np.stack(gauge_strains(shape, 5, 5, t=t_k + 1e-4))
    assert 0 < np.abs(near - exact).max() < 1e-4


def test_cli_refuses_elastic_parameters_with_kinematic_mechanics(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--shape", "sphere:radius=60,prestretch=0.05", "--tcp", "0", "--duration", "0.1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "prestretch" in err and "elastic" in err


def test_cli_names_a_bad_elastic_parameter(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--shape", "sphere:radius=60,prestretch=-0.1", "--mechanics", "elastic",
                  "--tcp", "0", "--duration", "0.1"])
    assert exc.value.code == 2
    assert "prestretch" in capsys.readouterr().err


def test_scene_spec_mechanics_must_be_named():
    with pytest.raises(ValueError, match="mechanics"):
        parse_scene_spec("flat", "rigid", 5, 5)  # type: ignore[arg-type]


@pytest.mark.slow
def test_balloon_centre_turns_from_convex_to_concave_under_the_dome_and_back(cache):
    # the paper's balloon: a unit inside the array switches from convex (the balloon) to concave
    # (the dome's imprint) during the press and back on release
    shape = make_scene("balloon", 5, 5, 12.0, period=4.0, mesh=2.0, keyframes=8, cache_dir=cache)
    bend = {}
    for t in (0.0, 2.0, 4.0):
        eu, el = gauge_strains(shape, 5, 5, 12.0, t=t)
        bend[t] = 0.5 * (eu - el)[:, 2, 2]  # h·κ along u and v at the centre cell
    h = 0.2
    assert np.all(bend[0.0] > 0.6 * h / 80.0)  # convex, about the balloon's 1/80 mm⁻¹
    assert np.all(bend[2.0] < -0.6 * h / 50.0)  # concave, about the dome's 1/50 mm⁻¹
    np.testing.assert_allclose(bend[4.0], bend[0.0], atol=1e-9)  # released: one period later


@pytest.mark.slow
def test_palm_mold_holds_still_during_a_hold_and_moves_between_keys(cache):
    shape = make_scene("palm", 3, 3, 12.0, hold=1.0, transition=1.0, mesh=2.0, keyframes=16, cache_dir=cache)
    a = np.stack(gauge_strains(shape, 3, 3, 12.0, t=2.1))
    b = np.stack(gauge_strains(shape, 3, 3, 12.0, t=2.9))  # both inside the cylinder's hold
    np.testing.assert_allclose(a, b, atol=1e-12)
    c = np.stack(gauge_strains(shape, 3, 3, 12.0, t=3.5))  # morphing toward the bump
    assert np.abs(c - a).max() > 1e-4


def test_points_outside_the_solved_film_are_refused_not_clamped(cache):
    shape = make_scene("sphere", 3, 3, 12.0, radius=60.0, cache_dir=cache)
    shape.position(np.array([[24.0, -24.0]]))  # the film's corner
    with pytest.raises(ValueError, match="outside the solved film"):
        shape.position(np.array([[30.0, 0.0]]))
    with pytest.raises(ValueError, match="outside the solved film"):
        ground_truth(shape, 3, 3, 12.0, element_uv=[[0.0, 25.0]])


@pytest.mark.slow
def test_balloon_pressed_on_a_wall_ridge_stays_below_the_wall_and_dips_under_the_crest(cache):
    shape = make_scene("balloon", 5, 5, 12.0, indenter=1, depth=5.0, period=4.0, mesh=2.0, keyframes=4,
                       cache_dir=cache)
    rest, pressed = shape.key_frames[0], shape.key_frames[2]  # t = 0 (touching), t = 2 s (5 mm)
    centre = np.array([[0.0, 0.0]])
    # touching only: the film's own lamination tension dents the balloon a little
    assert rest.position(centre)[0, 2] > -0.5
    assert pressed.position(centre)[0, 2] < -2.0  # the crest pushed the balloon in
    # the crest runs along u: across it (along v) the film wraps the crest, concave (bend < 0),
    # and more sharply than along it
    eu, el = gauge_strains(pressed, 5, 5, 12.0)
    bend = 0.5 * (eu - el)[:, 2, 2]
    assert bend[1] < 0 and abs(bend[1]) > abs(bend[0])
