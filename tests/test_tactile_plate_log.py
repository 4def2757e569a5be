"""`skinmap map --fit-probe-length` end to end: the emulated balloon pressed on a flat plate at
known depths, each press the solved film (its rim pushed in, as a real balloon's is), logged by a
running gateway, replayed, and the probe's stiffness length fitted from the log.

Run twice: with the sensor's gauges (hysteresis about 4 % of the strain excursion, docs/calibration.md)
and with that hysteresis off.  The gauges' hysteresis is a play (dead band) about the rest
state, so the small change of bending round a press reads low and the fit reads a longer ℓ
than the film's own (measured: 16.6-17.1 mm against 14.6; without the hysteresis 15.2-15.5): the fitted ℓ
takes that in, and it is what places the presses on the plate."""
from __future__ import annotations

import math
import re
import time

import pytest
from conftest import free_port, running_gateway, tactile_gateway_config

from skinmap.daemon.cli import main as skinmap_main
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.physics import SphereCap
from skinmap.emulator.transport import TcpTransport
from skinmap.emulator.walls import FlatPlate, Membrane, PressSequence

pytestmark = pytest.mark.slow

# (x, y, angle, depth): two presses at each of 1, 2 and 3 mm, moved and turned between them
PRESSES = [(-8.0, 5.0, 10.0, 1.0), (6.0, -4.0, -20.0, 1.0), (3.0, 7.0, 25.0, 2.0), (-5.0, -6.0, -5.0, 2.0),
           (0.0, 0.0, 15.0, 3.0), (7.0, 3.0, -30.0, 3.0)]
N = 5
PITCH = 12.0


def _model_length(membrane: Membrane, balloon_radius: float) -> float:
    """The film's own stiffness length √(T/k), k = E·t/R² (walls.Membrane's foundation)."""
    return math.sqrt(membrane.tension / (membrane.stretch / balloon_radius ** 2))


@pytest.fixture(scope="module", params=["sensor", "no hysteresis"])
def plate_log(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plate")
    off = ("drift",) if request.param == "sensor" else ("drift", "hysteresis")
    membrane = Membrane(half=max(50.0, 0.5 * N * PITCH * math.sqrt(2.0) + 5.0))
    # solved once, before the run (a second or two a press)
    scene = PressSequence(FlatPlate(), PRESSES, rest_s=0.5, hold_s=1.5, gap_s=1.0, membrane=membrane)
    emu = Emulator(ScannerSpec(n=N, m=N, scan_rate_hz=20.0, seed=5, electrical=ElectricalConfig().without(*off)),
                   SphereCap(80.0), TcpTransport(0))
    emu.start()
    cfg = tactile_gateway_config(tmp, emu.transport.url, "plate", free_port())
    try:
        with running_gateway(cfg) as gw:
            deadline = time.monotonic() + 90
            while gw.stats.results < 12 and time.monotonic() < deadline:  # the baseline: the free balloon
                time.sleep(0.05)
            scene.start_s = emu.device.shape_time(time.monotonic())
            emu.set_shape(scene)
            while time.monotonic() < deadline and emu.device.shape_time(time.monotonic()) < scene.duration_s + 0.5:
                time.sleep(0.05)
            assert gw.stats.results > 12  # scans processed after the baseline's (a count, not a rate)
    finally:
        emu.stop()
    poses = tmp / "plate.csv"
    poses.write_text("x_mm,y_mm,angle_deg,depth_mm\n" + "".join(f"{x},{y},{a},{d}\n" for x, y, a, d in PRESSES))
    return next((tmp / "logs").glob("*.mcap")), poses, _model_length(membrane, 80.0), request.param


def test_probe_length_fitted_from_a_logged_plate_run_within_10_percent_of_the_films_or_25_through_hysteresis(
        plate_log, capsys):
    log, poses, true_length, gauges = plate_log
    assert skinmap_main(["map", str(log), "--poses", str(poses), "--fit-probe-length"]) == 0
    out = capsys.readouterr().out
    fitted = re.search(r"probe stiffness length fitted on (\d+) plate presses indenting ([0-9.]+)-([0-9.]+) mm: "
                       r"([0-9.]+) mm \(residual ([0-9.]+) mm rms", out)
    assert fitted is not None, out
    contacts, length, residual = int(fitted.group(1)), float(fitted.group(4)), float(fitted.group(5))
    # the indentation range it holds for: the plate's presses (1-3 mm deep) indent less than the plate's depth
    assert 0.0 < float(fitted.group(2)) < float(fitted.group(3)) <= max(d for *_, d in PRESSES), out
    print(f"{gauges}: fitted {length:.2f} mm on {contacts} presses (the film's {true_length:.2f} mm), "
          f"residual {residual:.3f} mm")
    assert contacts >= len(PRESSES) - 1
    assert abs(length - true_length) <= (0.25 if gauges == "sensor" else 0.10) * true_length, out
    assert residual < 0.3, out
    assert f"set [tactile] probe_length_mm = {length:.2f}; a map whose presses indent much deeper than" in out


def test_a_wrong_stiffness_length_places_the_plate_presses_off_the_plate(plate_log):
    """The fitted length places every press on the plate (its contact cells at the plate's height
    0) better than a length far off does: the fit reads the presses, not a default."""
    import numpy as np

    from skinmap.daemon.tactilemap import map_log

    log, poses, _, gauges = plate_log
    fitted = map_log(log, poses, fit_length=True)
    assert fitted.length_fit is not None
    wrong = map_log(log, poses, probe_length_mm=0.4 * fitted.length_fit.length_mm)

    def plate_error(report) -> float:
        h = report.relief.height()
        return float(np.nanmean(np.abs(h)))

    good, bad = plate_error(fitted), plate_error(wrong)
    print(f"{gauges}: mean |height| over the touched plate: fitted length {fitted.length_fit.length_mm:.2f} mm "
          f"{good:.3f} mm, 0.4x {bad:.3f} mm")
    assert good < 0.3
    assert bad > good + 0.2
