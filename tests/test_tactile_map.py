"""`skinmap map` end to end: the emulated balloon pressed on the letter wall, logged by a running
gateway, replayed and stitched with the poses from a CSV."""
from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import running_gateway

from skinmap.daemon.cli import main as skinmap_main
from skinmap.emulator.device import DeviceConfig
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.physics import SphereCap
from skinmap.emulator.transport import TcpTransport
from skinmap.emulator.walls import LetterRelief, PressSequence

pytestmark = pytest.mark.slow

PRESSES = [(-30.0, 30.0, 10.0, 2.0), (30.0, 30.0, -15.0, 2.0), (-30.0, -30.0, 5.0, 2.0)]


@pytest.fixture(scope="module")
def press_log(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("map")
    emu = Emulator(DeviceConfig(n=8, m=8, scan_rate_hz=20.0, seed=3, electrical=ElectricalConfig().without("drift")),
                   SphereCap(80.0), TcpTransport(0))
    emu.start()
    cfg_text = f"""
[device]
port = "{emu.transport.url}"
name = "map"
scan_rate_hz = 20
[output]
rate_hz = 10
[zenoh]
enabled = false
[log]
directory = "logs"
[state]
directory = "state"
"""
    (tmp / "skinmapd.toml").write_text(cfg_text)
    from skinmap.daemon.config import load_config

    cfg = load_config(tmp / "skinmapd.toml")
    try:
        with running_gateway(cfg) as gw:
            deadline = time.monotonic() + 60
            while gw.stats.results < 12 and time.monotonic() < deadline:  # the baseline: the free balloon
                time.sleep(0.05)
            scene = PressSequence(LetterRelief(), PRESSES, rest_s=0.5, hold_s=1.0, gap_s=0.6,
                                  start_s=emu.device.shape_time(time.monotonic()))
            emu.set_shape(scene)
            while time.monotonic() < deadline and emu.device.shape_time(time.monotonic()) < scene.duration_s + 0.5:
                time.sleep(0.1)
            assert gw.stats.results > 30
    finally:
        emu.stop()
    poses = tmp / "poses.csv"
    poses.write_text("x_mm,y_mm,angle_deg,depth_mm\n" + "".join(f"{x},{y},{a},{d}\n" for x, y, a, d in PRESSES))
    return tmp, next((tmp / "logs").glob("*.mcap")), poses


def test_map_finds_every_press_and_writes_png_and_ply(press_log, capsys):
    tmp, log, poses = press_log
    png, ply = tmp / "relief.png", tmp / "relief.ply"
    assert skinmap_main(["map", str(log), "--poses", str(poses), "--png", str(png), "--ply", str(ply)]) == 0
    out = capsys.readouterr().out
    assert "3 contact events" in out and "coverage" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = ply.read_text().splitlines()
    count = int(next(line for line in text if line.startswith("element vertex")).split()[-1])
    assert count > 500 and len(text) == text.index("end_header") + 1 + count
    xyz = np.loadtxt(text[text.index("end_header") + 1:])
    # every mapped point lies under the sheet at one of the presses (half its diagonal: 59.4 mm)
    reach = np.min([np.hypot(xyz[:, 0] - x, xyz[:, 1] - y) for x, y, _, _ in PRESSES], axis=0)
    assert np.all(reach < 42.0 * np.sqrt(2) + 1.0)


def test_map_refuses_a_pose_file_that_does_not_match_the_presses(press_log, capsys, tmp_path):
    _tmp, log, _ = press_log
    short = tmp_path / "short.csv"
    short.write_text("x_mm,y_mm,angle_deg,depth_mm\n0,0,0,2\n")
    assert skinmap_main(["map", str(log), "--poses", str(short)]) == 1
    assert "3 contact events, but" in capsys.readouterr().err
