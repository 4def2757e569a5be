"""Mold calibration: hidden device truths, the per-gauge fit, the procedure, the calibration file
and its use, the port lock and the tare's refusals."""
from __future__ import annotations

import json

import numpy as np
import pytest

from skinmap.daemon import cli
from skinmap.daemon.calibrate import (CalibrationAborted, EmulatedPlacer, LinkFeed, run_calibration, take_static,
                                      tare_problem)
from skinmap.strains import (Calibration, calibration_path, load_calibration_file, parse_calibration, save_calibration,
                                        resistances_to_strains, to_nominal_offsets)
from skinmap.daemon.config import DeviceConfig as LinkConfig
from skinmap.daemon.moldcal import Pose, check_pose, fit_mold_calibration, standard_poses
from skinmap.daemon.portlock import PortBusy, PortLock
from skinmap.emulator import physics as ph
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.molds import mold_scene
from skinmap.emulator.transport import TcpTransport
from skinmap.reconstruction import reconstruct
from skinmap.reconstruction.linalg import aligned_distances

SPREADS = dict(gf_spread=0.15, offset_spread=0.10)


def _readings(dev: Device, poses: list[Pose], mechanics: str = "kinematic", seed: int = 1, scans: int = 30):
    """Mean strains of every pose as the host reads them (factory GF, tared R0), each pose placed
    with its axis off by up to 3° and off-centre by up to 5 mm, the sheet at rest in between."""
    rng = np.random.default_rng(seed)
    gf0 = dev.calibration.gauge_factor
    out, tare, t = [], None, 0.0
    for pose in poses:
        dev.set_shape(mold_scene(pose.kind, dev.config.n, dev.config.m, 12.0, radius=pose.radius_mm,
                                 direction=pose.direction or "rows", stretch=pose.stretch,
                                 axis_error_deg=rng.uniform(-3, 3), offset_mm=rng.uniform(-5, 5), mechanics=mechanics))
        st = dev.strains(0.0)
        dev.readout.read(np.zeros_like(st), t)
        r = []
        for _ in range(scans):
            t += 0.02
            r.append(dev.readout.read(st, t).astype(float) * 1e-6)
        r = np.array(r)
        if tare is None:
            tare = np.median(r, axis=0)
        out.append((r.mean(axis=0) / tare - 1.0) / gf0)
        t += 0.02
    return out, tare


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def test_hidden_truths_are_seeded_spread_and_not_in_hello():
    dev = Device(ScannerSpec(seed=4, **SPREADS), ph.Flat())
    truth = dev.hidden_truth()
    rel = truth["gauge_factor"] / dev.calibration.gauge_factor - 1.0
    assert 0.10 < _rms(rel) < 0.20
    assert 0.06 < _rms(truth["h_upper_mm"] / 0.2 - 1.0) < 0.14
    hello = dev.hello()
    assert np.allclose(hello.gauge_factor(), dev.calibration.gauge_factor)  # HELLO: factory values only
    assert not np.allclose(hello.gauge_factor(), truth["gauge_factor"])
    again = Device(ScannerSpec(seed=4, **SPREADS), ph.Flat()).hidden_truth()
    assert np.array_equal(again["h_lower_mm"], truth["h_lower_mm"])
    plain = Device(ScannerSpec(seed=4), ph.Flat()).hidden_truth()
    assert np.array_equal(plain["gauge_factor"], dev.calibration.gauge_factor)


def test_per_unit_offsets_give_each_layer_its_own_bending_strain():
    dev = Device(ScannerSpec(seed=5, electrical=ScannerSpec().electrical, **SPREADS), ph.Cylinder(40.0))
    truth = dev.hidden_truth()
    st = dev.strains(0.0)
    assert np.allclose(st[0, 0], truth["h_upper_mm"][0] / 40.0, rtol=1e-4)
    assert np.allclose(st[1, 0], -truth["h_lower_mm"][0] / 40.0, rtol=1e-4)


@pytest.mark.parametrize("mechanics", ["kinematic", "elastic"])
def test_fit_gauge_factor_error_below_3pct_and_offset_error_below_3pct(mechanics):
    dev = Device(ScannerSpec(n=4 if mechanics == "elastic" else 5, m=4 if mechanics == "elastic" else 5, seed=6,
                              **SPREADS), ph.Flat())
    poses = standard_poses()
    readings, _ = _readings(dev, poses, mechanics)
    fit = fit_mold_calibration(poses, readings, dev.calibration.gauge_factor, 0.2, 0.2, noise_sd=1e-5)
    truth = dev.hidden_truth()
    assert _rms(dev.calibration.gauge_factor / truth["gauge_factor"] - 1) > 0.10  # it had something to find
    assert _rms(fit.gauge_factor / truth["gauge_factor"] - 1) <= 0.03
    assert _rms(fit.h_upper_mm / truth["h_upper_mm"] - 1) <= 0.03
    assert _rms(fit.h_lower_mm / truth["h_lower_mm"] - 1) <= 0.03
    assert fit.offsets_determined and np.all(np.isfinite(fit.residual_rms))
    assert np.all(fit.gauge_factor_sd > 0) and np.all(fit.h_upper_sd_mm > 0)
    cyl = [e for p, e in zip(poses, fit.axis_error_deg) if p.kind == "cylinder"]
    assert max(cyl) < 6.0  # placements were off by up to 3°


def test_fit_without_stretch_keeps_nominal_offsets_and_says_so():
    dev = Device(ScannerSpec(seed=7, **SPREADS), ph.Flat())
    poses = standard_poses(stretch=0.0)
    readings, _ = _readings(dev, poses)
    fit = fit_mold_calibration(poses, readings, dev.calibration.gauge_factor, 0.2, 0.2)
    assert not fit.offsets_determined and np.all(fit.h_upper_mm == 0.2)
    assert any("offsets not determined" in n for n in fit.notes)


def test_fit_refuses_too_few_poses():
    with pytest.raises(ValueError, match="two cylinder poses along the columns"):
        fit_mold_calibration([Pose("flat"), Pose("cylinder", 40, "rows"), Pose("cylinder", -40, "rows")],
                             [np.zeros((2, 2, 3, 3))] * 3, np.ones((2, 2, 3, 3)), 0.2, 0.2)


def test_reconstruction_error_calibrated_within_1p5x_of_perfect():
    cfg = ScannerSpec(seed=8, **SPREADS)
    dev = Device(cfg, ph.Flat())
    poses = standard_poses()
    readings, tare = _readings(dev, poses)
    fit = fit_mold_calibration(poses, readings, dev.calibration.gauge_factor, 0.2, 0.2, noise_sd=1e-5)
    truth = dev.hidden_truth()
    cals = {"factory": Calibration(dev.calibration.gauge_factor, tare),
            "calibrated": Calibration(fit.gauge_factor, tare, "c", fit.h_upper_mm, fit.h_lower_mm),
            "perfect": Calibration(truth["gauge_factor"], tare, "t", truth["h_upper_mm"], truth["h_lower_mm"])}
    shapes = [ph.Cylinder(-50.0), ph.SphereCap(80.0), ph.GaussianBumps(height=4.0, fwhm=20.0, centre=(5.0, -3.0))]
    err = {k: [] for k in cals}
    t = 10.0
    for shape in shapes:
        dev.set_shape(shape)
        st = dev.strains(0.0)
        for k, cal in cals.items():
            dev.readout.read(np.zeros_like(st), t)
            t += 0.1
            wire = dev.readout.read(st, t)
            eu, el, _ = resistances_to_strains(wire.astype(float) * 1e-6, cal)
            if cal.h_upper_mm is not None:
                eu, el = to_nominal_offsets(eu, el, cal.h_upper_mm, cal.h_lower_mm, 0.2, 0.2)
            nodes = reconstruct(eu, el, 12.0, 0.2, 0.2).nodes
            gt = ph.ground_truth(shape, 5, 5, 12.0).nodes
            err[k].append(float(np.mean(aligned_distances(nodes.reshape(-1, 3), gt.reshape(-1, 3)))))
    mean = {k: float(np.mean(v)) for k, v in err.items()}
    assert mean["factory"] > 2.0 * mean["perfect"]  # uncalibrated is measurably worse
    assert mean["calibrated"] <= 1.5 * mean["perfect"]


def test_to_nominal_offsets_keeps_stretch_and_turning():
    rng = np.random.default_rng(0)
    hu, hl = rng.uniform(0.15, 0.25, (2, 3, 3)), rng.uniform(0.15, 0.25, (2, 3, 3))
    s, k = rng.normal(0, 1e-3, (2, 3, 3)), rng.normal(0, 1e-2, (2, 3, 3))
    eu, el = to_nominal_offsets(s + hu * k, s - hl * k, hu, hl, 0.2, 0.2)
    assert np.allclose(eu, s + 0.2 * k) and np.allclose(el, s - 0.2 * k)


def test_check_pose_names_wrong_side_wrong_mold_and_bent_flat():
    eps = np.zeros((2, 2, 4, 4))
    eps[0, 0], eps[1, 0] = 0.2 / 40, -0.2 / 40
    assert check_pose(Pose("cylinder", 40.0, "rows"), eps, 0.2, 0.2) == ""
    assert "wrong way" in check_pose(Pose("cylinder", -40.0, "rows"), eps, 0.2, 0.2)
    assert "radius of 40 mm" in check_pose(Pose("cylinder", 80.0, "rows"), eps, 0.2, 0.2)
    assert "turn it by 90" in check_pose(Pose("cylinder", 40.0, "columns"), eps, 0.2, 0.2)
    assert "bent" in check_pose(Pose("flat"), eps, 0.2, 0.2)


def test_tare_problem_refuses_moving_palm_and_bent_sheet_accepts_flat():
    dev = Device(ScannerSpec(seed=9, scan_rate_hz=50.0), ph.make_shape("palm"))
    gf, r0 = dev.calibration.gauge_factor, dev.calibration.base_resistance_ohm

    def scans(t0: float, count: int = 40) -> np.ndarray:
        out = []
        for k in range(count):
            t = t0 + 0.02 * k
            times = np.full((2, 5, 5), dev.shape_time(t))
            out.append(dev.readout.read(dev.strains(times), t).astype(float) * 1e-6)
        return np.array(out)

    problems = [tare_problem(scans(t0), gf, r0, 0.2, 0.2) for t0 in np.arange(0.0, 8.0, 0.8)]
    assert any("moving" in p for p in problems)
    assert any("bent" in p for p in problems) or any("stretched" in p for p in problems)
    dev.set_shape(ph.Flat())
    assert tare_problem(scans(100.0), gf, r0, 0.2, 0.2) == ""


def test_port_lock_refuses_a_second_holder_and_names_the_first(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    with PortLock("socket://127.0.0.1:7999", "skinmapd"):
        with pytest.raises(PortBusy, match=r"in use by skinmapd \(pid \d+\)"):
            PortLock("socket://127.0.0.1:7999", "skinmap tare").acquire()
    PortLock("socket://127.0.0.1:7999", "skinmap tare").acquire().release()  # free again



def test_a_lock_file_another_user_left_still_locks_the_port(tmp_path, monkeypatch):
    """A lock file left by another user (a tool run as root, the service's former dynamic user)
    cannot be opened for writing: the daemon could not start ('Permission denied').  Opened for
    reading, it locks as well; the other user's record is left as it was."""
    import os

    from skinmap.daemon import portlock

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    port = "socket://127.0.0.1:7997"
    path = portlock.lock_path(port)
    path.write_text("skinmap tare (pid 1)\n")
    real_open = os.open

    def open_as_another_user(file, flags, *args):
        if str(file) == str(path) and flags & (os.O_RDWR | os.O_WRONLY):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, flags, *args)

    monkeypatch.setattr(portlock.os, "open", open_as_another_user)
    held = PortLock(port, "skinmapd").acquire()
    monkeypatch.setattr(portlock.os, "open", real_open)
    with pytest.raises(PortBusy):
        PortLock(port, "skinmap calibrate").acquire()
    held.release()
    assert path.read_text() == "skinmap tare (pid 1)\n"
    PortLock(port, "skinmap calibrate").acquire().release()  # free again

def test_tare_refuses_while_the_daemon_holds_the_port(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    conf = tmp_path / "c.toml"
    conf.write_text('[device]\nport = "socket://127.0.0.1:7998"\n[zenoh]\nenabled = false\n[log]\nenabled = false\n')
    with PortLock("socket://127.0.0.1:7998", "skinmapd"):
        assert cli.main(["tare", "--config", str(conf)]) == 1
    err = capsys.readouterr().err
    assert "in use by skinmapd" in err and "nothing written" in err
    assert not list(tmp_path.glob("state/*"))


def _calibrate_emulated(tmp_path, n=3, seed=11):
    cfg = ScannerSpec(n=n, m=n, scan_rate_hz=50.0, seed=seed, **SPREADS)
    emu = Emulator(cfg, ph.Flat(), TcpTransport(0))
    placer = EmulatedPlacer(emu, "kinematic", seed, rest_s=0.1)
    poses = standard_poses()
    placer.prepare(poses)
    emu.start()
    feed = LinkFeed(LinkConfig(port=emu.transport.url, scan_rate_hz=50.0))
    said: list[str] = []
    try:
        hello = feed.start()
        run = run_calibration(feed, placer, poses, hello, state_dir=tmp_path, h_upper_mm=0.2, h_lower_mm=0.2,
                              window=15, say=said.append)
    finally:
        feed.stop()
        emu.stop()
    return run, hello, emu.hidden_truth(), said


def test_procedure_writes_a_calibration_file_that_skinmapd_and_replay_use(tmp_path):
    from skinmap.daemon.config import DaemonConfig, StateConfig
    from skinmap.daemon.replay import _calibration_from_doc
    from skinmap.daemon.device_setup import calibration_doc, load_calibration

    run, hello, truth, said = _calibrate_emulated(tmp_path)
    assert any(line.startswith("[10/10]") for line in said)
    doc = json.loads(run.calibration_file.read_text())
    assert (doc["format"], doc["version"]) == ("skinmap.calibration", 1)
    assert doc["serial"] == hello.serial_number and len(doc["poses"]) == 10
    assert len(doc["residual_strain_rms"]) == len(doc["gauge_factor"]) == 36
    assert _rms(np.array(doc["gauge_factor"]).reshape(2, 2, 3, 3) / truth["gauge_factor"] - 1) <= 0.03
    cfg = DaemonConfig(state=StateConfig(directory=str(tmp_path)))
    cal, problem = load_calibration(hello, cfg)
    assert problem == "" and cal.source.startswith("calibration ") and "tare" in cal.source
    assert np.allclose(cal.h_upper_mm, run.fit.h_upper_mm) and np.allclose(cal.gauge_factor, run.fit.gauge_factor)
    logged = calibration_doc(cal)
    back = _calibration_from_doc(json.loads(json.dumps(logged)))
    assert np.array_equal(back.h_lower_mm, cal.h_lower_mm) and np.array_equal(back.gauge_factor, cal.gauge_factor)
    assert logged["fit"]["method"].startswith("mold fit")


def test_a_damaged_calibration_file_is_named_and_the_factory_values_kept(tmp_path):
    from skinmap.daemon.config import DaemonConfig, StateConfig
    from skinmap.daemon.device_setup import load_calibration

    dev = Device(ScannerSpec(n=3, m=3, seed=12), ph.Flat())
    hello = dev.hello()
    path = calibration_path(tmp_path, hello.serial_number)
    path.write_text(json.dumps({"format": "skinmap.calibration", "version": 1, "shape": [2, 2, 3, 3],
                                "gauge_factor": [1.0] * 35, "h_upper_mm": [0.2] * 18, "h_lower_mm": [0.2] * 18}))
    cal, problem = load_calibration(hello, DaemonConfig(state=StateConfig(directory=str(tmp_path))))
    assert "ignoring calibration" in problem and "36" in problem and str(path) in problem
    assert cal.source == "factory" and cal.h_upper_mm is None
    with pytest.raises(ValueError, match="version 2"):
        parse_calibration(json.dumps({"format": "skinmap.calibration", "version": 2}), (2, 2, 3, 3))
    assert load_calibration_file(tmp_path / "none", "x", (2, 2, 3, 3)) is None


def test_take_static_gives_up_on_a_sheet_that_keeps_moving():
    class Moving:
        def __init__(self):
            self.t = 0

        def scans(self, count, timeout_s):
            out = []
            for _ in range(count):
                self.t += 1
                out.append(np.full((2, 2, 2, 2), 6.5 * (1 + 1e-4 * self.t)))
            return out

    with pytest.raises(CalibrationAborted, match="did not come to rest"):
        take_static(Moving(), np.ones((2, 2, 2, 2)), np.full((2, 2, 2, 2), 6.5), 9, 0.05, say=lambda s: None)


def test_calibrate_command_against_the_emulator_writes_both_files(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    rc = cli.main(["calibrate", "--emulate", "3x3", "--state-dir", str(tmp_path / "state"), "--seed", "13",
                   "--window", "15"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "[10/10]" in out and "against the emulator's hidden truth" in out
    assert len(list((tmp_path / "state").glob("calibration-EMU-*.json"))) == 1
    assert len(list((tmp_path / "state").glob("tare-EMU-*.json"))) == 1
    assert cli.main(["calibrate"]) == 2  # neither a config nor --emulate
    assert "give --config" in capsys.readouterr().err


# -- the film's Poisson ratio from a dome ---------------------------------------------------------

def _dome_strains(spec: str, cache, n: int = 5):
    from skinmap.emulator.scenes import parse_scene_spec

    shape = parse_scene_spec(spec, "elastic", n, n, 12.0, cache_dir=cache)
    return ph.gauge_strains(shape, n, n, 12.0, 0.2, 0.2, 10.0)


@pytest.mark.slow
@pytest.mark.parametrize("spec,radius,nu", [("sphere:radius=65", 65.0, 0.48), ("sphere:radius=-75,poisson=0.3", -75.0, 0.3),
                                            ("sphere:radius=90,poisson=0.4", 90.0, 0.4)])
def test_poisson_ratio_from_a_lubricated_dome_is_within_0_02_and_its_sd_covers_the_error(spec, radius, nu, tmp_path):
    from skinmap.daemon.moldcal import fit_poisson_ratio

    eu, el = _dome_strains(spec, tmp_path)
    rng = np.random.default_rng(4)
    eu, el = eu + rng.normal(0, 0.0057e-2 / np.sqrt(30), eu.shape), el + rng.normal(0, 0.0057e-2 / np.sqrt(30), el.shape)
    fit = fit_poisson_ratio(eu, el, 0.2, 0.2, 12.0, radius)
    assert abs(fit.poisson - nu) <= 0.02
    assert abs(fit.poisson - nu) <= 3 * fit.sd


@pytest.mark.slow
def test_poisson_ratio_refuses_a_film_that_stuck_to_the_dome_and_a_sheet_too_small(tmp_path):
    from skinmap.daemon.moldcal import fit_poisson_ratio

    eu, el = _dome_strains("sphere:radius=80,friction=0.001", tmp_path)
    with pytest.raises(ValueError, match="did not slide"):
        fit_poisson_ratio(eu, el, 0.2, 0.2, 12.0, 80.0)
    small = np.zeros((2, 2, 2))
    with pytest.raises(ValueError, match="at least 10"):
        fit_poisson_ratio(small, small, 0.2, 0.2, 12.0, 80.0)


def test_dome_pose_is_checked_like_a_mold_and_refused_below_20mm():
    with pytest.raises(ValueError, match="dome pose needs a radius"):
        Pose("dome", radius_mm=10.0)
    dome = Pose("dome", radius_mm=60.0)
    assert standard_poses((40.0, 80.0), 0.05, 60.0)[-1] == dome
    h = 0.2
    on_it = np.stack([np.full((2, 5, 5), h / 60.0), np.full((2, 5, 5), -h / 60.0)])
    assert check_pose(dome, on_it, h, h) == ""
    assert "this side up" in check_pose(dome, -on_it, h, h)
    cylinder_like = on_it.copy()
    cylinder_like[:, 1] = 0.0
    assert "a cylinder, not the dome" in check_pose(dome, cylinder_like, h, h)
    assert "not 60 mm" in check_pose(dome, 2.0 * on_it, h, h)


def test_calibration_file_carries_the_poisson_ratio_and_refuses_an_impossible_one(tmp_path):
    shape = (2, 2, 3, 3)
    kw = dict(gauge_factor=np.full(shape, 1.24), gauge_factor_sd=np.full(shape, 0.01), h_upper_mm=np.full(shape[1:], 0.2),
              h_upper_sd_mm=np.full(shape[1:], 0.001), h_lower_mm=np.full(shape[1:], 0.2),
              h_lower_sd_mm=np.full(shape[1:], 0.001), residual_rms=np.full(shape, 1e-5), method="mold fit",
              offsets_determined=True, poses=[], duration_s=1.0, notes=[])
    path = save_calibration(tmp_path, "SN1", **kw, poisson=(0.47, 0.01))
    *_, summary = parse_calibration(path.read_text(), shape)
    assert summary["poisson_ratio"] == 0.47 and summary["poisson_ratio_sd"] == 0.01
    doc = json.loads(path.read_text())
    doc["poisson_ratio"] = 0.7
    with pytest.raises(ValueError, match="poisson_ratio"):
        parse_calibration(json.dumps(doc), shape)
    *_, summary = parse_calibration(save_calibration(tmp_path, "SN2", **kw).read_text(), shape)
    assert summary["poisson_ratio"] is None
