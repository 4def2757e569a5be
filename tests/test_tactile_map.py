"""`skinmap map` end to end: the emulated balloon pressed on the letter wall, logged by a running
gateway, replayed and stitched with the poses from a CSV."""
from __future__ import annotations

import contextlib
import math
import time

import numpy as np
import pytest
from conftest import free_port, running_gateway, tactile_gateway_config

from skinmap.daemon.cli import main as skinmap_main
from skinmap.emulator.device import ScannerSpec
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
    emu = Emulator(ScannerSpec(n=8, m=8, scan_rate_hz=20.0, seed=3, electrical=ElectricalConfig().without("drift")),
                   SphereCap(80.0), TcpTransport(0))
    emu.start()
    zport = free_port()
    _write_calibration(tmp / "state", emu)
    cfg = tactile_gateway_config(tmp, emu.transport.url, "map", zport)
    try:
        with running_gateway(cfg) as gw:
            deadline = time.monotonic() + 60
            while gw.stats.results < 12 and time.monotonic() < deadline:  # the baseline: the free balloon
                time.sleep(0.05)
            scene = PressSequence(LetterRelief(), PRESSES, rest_s=0.5, hold_s=1.5, gap_s=1.0,
                                  start_s=emu.device.shape_time(time.monotonic()))
            with _pose_sender(zport) as put_pose:
                put_pose(b'{"schema":"skinmap.pose/1","x_mm":"left"}')  # refused, with a warning
                put_pose(PRESSES[0])
                emu.set_shape(scene)
                sent = 1
                while time.monotonic() < deadline and emu.device.shape_time(time.monotonic()) < scene.duration_s + 0.5:
                    # each later pose in the gap before its press (the probe is moved, then pressed)
                    if sent < len(PRESSES) and emu.device.shape_time(time.monotonic()) > \
                            scene.start_s + scene.rest_s + (sent - 1) * 2.5 + 1.5 + 0.5:
                        put_pose(PRESSES[sent])
                        sent += 1
                    time.sleep(0.05)
            assert gw.stats.results > 30
            latest = _latest_contact(zport)
    finally:
        emu.stop()
    poses = tmp / "poses.csv"
    poses.write_text("x_mm,y_mm,angle_deg,depth_mm\n" + "".join(f"{x},{y},{a},{d}\n" for x, y, a, d in PRESSES))
    return tmp, next((tmp / "logs").glob("*.mcap")), poses, latest


@contextlib.contextmanager
def _pose_sender(zport: int):
    """put(pose tuple or raw bytes) on the gateway's pose key, over loopback Zenoh."""
    from skinmap.daemon.zenoh_io import make_session_config, open_session
    from skinmap.wire.keys import pose_key
    from skinmap.wire.messages import encode_pose

    with open_session(make_session_config([], [f"tcp/127.0.0.1:{zport}"])) as session:
        time.sleep(0.5)  # the route to the gateway's subscriber

        def put(pose) -> None:
            payload = pose if isinstance(pose, bytes) else encode_pose(dict(zip(("x_mm", "y_mm", "angle_deg", "depth_mm"), pose)))
            session.put(pose_key("skinmap", "map"), payload)

        yield put


def _write_calibration(state, emu) -> None:
    """A mold calibration in force for the run (gauge factors 2 % above HELLO's, offsets off
    nominal), so that the log carries it and replay must use it."""
    from skinmap.strains import save_calibration

    gf = emu.device.calibration.gauge_factor * 1.02
    hu, hl = np.full((2, 8, 8), 0.21), np.full((2, 8, 8), 0.19)
    save_calibration(state, emu.device.serial_number, gauge_factor=gf, gauge_factor_sd=gf * 1e-3, h_upper_mm=hu,
                     h_upper_sd_mm=hu * 1e-3, h_lower_mm=hl, h_lower_sd_mm=hl * 1e-3, residual_rms=gf * 0 + 1e-5,
                     method="test", offsets_determined=True, poses=[], duration_s=1.0, notes=[])


def test_a_calibrated_run_logs_its_calibration_and_replays_identically(press_log, capsys):
    import json

    from skinmap.daemon.mcapread import iter_messages_file_order

    _tmp, log, _poses, _ = press_log
    config = next(json.loads(m.data) for m in iter_messages_file_order(str(log)) if m.topic == "/config")
    cal = config["calibration"]
    assert cal["source"].startswith("calibration ") and cal["h_upper_mm"][0] == 0.21
    assert skinmap_main(["replay", str(log), "--quiet"]) == 0
    assert "IDENTICAL" in capsys.readouterr().out


def _latest_contact(zport: int) -> dict:
    """The newest `contact` message, asked of the running gateway over loopback Zenoh."""
    import json

    from skinmap.daemon.zenoh_io import make_session_config, open_session

    with open_session(make_session_config([], [f"tcp/127.0.0.1:{zport}"])) as session:
        for _ in range(20):
            for reply in session.get("skinmap/map/contact", timeout=2.0):
                if reply.ok is not None:
                    return json.loads(reply.ok.payload.to_bytes())
            time.sleep(0.1)
    raise AssertionError("no contact message from the gateway")


def test_gateway_publishes_and_logs_contact_events(press_log):
    from skinmap.daemon.mcapread import iter_messages_file_order
    import json

    _tmp, log, _poses, latest = press_log
    assert latest["state"] in ("free", "contact") and latest["grid"]["step_mm"] == 2.0
    docs = [json.loads(m.data) for m in iter_messages_file_order(str(log)) if m.topic == "/contact"]
    states = [d["state"] for d in docs]
    assert states[:8] == ["baseline"] * 8 and "contact" in states and "free" in states
    assert max(d["events"] for d in docs) == 3
    pressed = [d for d in docs if d["state"] == "contact"]
    assert all(d["area_mm2"] > 0 and d["peak_depth_mm"] > 0.05 and d["feature_size_mm"] > 0 for d in pressed)
    assert len(pressed[0]["depth_mm"]) == pressed[0]["grid"]["rows"] * pressed[0]["grid"]["cols"]
    # the push beyond the rim, read from the bending round the contact, with its misfit (or why not)
    assert all(("push_mm" in d) != ("push_unread" in d) for d in pressed)
    read = [d for d in pressed if "push_mm" in d]
    assert read and all(math.isfinite(d["push_mm"]) and d["push_misfit_mm"] >= 0 for d in read)
    assert all(d["push_doubtful"] == (d["push_misfit_mm"] >= max(0.5 * abs(d["push_mm"]), 0.1)) for d in read)
    # each contact carries the pose in force when it began: the one put before its press
    carried = {d["press"]: d["pose"] for d in pressed}
    assert [tuple(carried[e][k] for k in ("x_mm", "y_mm", "angle_deg", "depth_mm")) for e in (1, 2, 3)] == PRESSES


def test_map_finds_every_press_and_writes_png_and_ply(press_log, capsys):
    tmp, log, poses, _ = press_log
    png, ply = tmp / "relief.png", tmp / "relief.ply"
    assert skinmap_main(["map", str(log), "--poses", str(poses), "--png", str(png), "--ply", str(ply)]) == 0
    out = capsys.readouterr().out
    assert "3 contact events" in out and "coverage" in out
    # each contact says whether it was placed by its free cells' bending, or why it stays on its rim
    lines = [line for line in out.splitlines() if line.lstrip().startswith("contact ")]
    assert len(lines) == 3 and all("placed by its bending" in line or "registered by its rim" in line for line in lines)
    assert "probe stiffness length 14.6 mm" in out
    assert skinmap_main(["map", str(log), "--poses", str(poses), "--reference", "floor"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.lstrip().startswith("contact ")]
    assert len(lines) == 3 and all("levelled on the floor" in line or "registered by its rim" in line for line in lines)
    assert skinmap_main(["map", str(log), "--poses", str(poses), "--rim"]) == 0
    out = capsys.readouterr().out
    assert "levelled" not in out and "placed by" not in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = ply.read_text().splitlines()
    count = int(next(line for line in text if line.startswith("element vertex")).split()[-1])
    assert count > 500 and len(text) == text.index("end_header") + 1 + count
    xyz = np.loadtxt(text[text.index("end_header") + 1:])
    # every mapped point lies under the sheet at one of the presses (half its diagonal: 59.4 mm)
    reach = np.min([np.hypot(xyz[:, 0] - x, xyz[:, 1] - y) for x, y, _, _ in PRESSES], axis=0)
    assert np.all(reach < 42.0 * np.sqrt(2) + 1.0)


def test_map_refuses_a_pose_file_that_does_not_match_the_presses(press_log, capsys, tmp_path):
    _tmp, log, _, _ = press_log
    short = tmp_path / "short.csv"
    short.write_text("x_mm,y_mm,angle_deg,depth_mm\n0,0,0,2\n")
    assert skinmap_main(["map", str(log), "--poses", str(short)]) == 1
    assert "3 contact events, but" in capsys.readouterr().err


def test_map_takes_the_cell_quantile_and_rim_and_refuses_a_quantile_outside_0_1_by_name(press_log, capsys):
    """``--cell-quantile 0.5 --rim-mm 2`` stitches the median of contacts without their outer
    2 mm: fewer cells (the rims) than the default, whole contacts; a quantile outside [0, 1] is
    refused, naming it."""
    tmp, log, poses, _ = press_log
    counts = []
    for extra in (["--cell-quantile", "0.5", "--rim-mm", "2"], []):
        ply = tmp / f"relief{len(extra)}.ply"
        assert skinmap_main(["map", str(log), "--poses", str(poses), "--ply", str(ply), *extra]) == 0
        capsys.readouterr()
        text = ply.read_text().splitlines()
        counts.append(int(next(line for line in text if line.startswith("element vertex")).split()[-1]))
    assert counts[1] > counts[0] > 0
    assert skinmap_main(["map", str(log), "--poses", str(poses), "--cell-quantile", "1.5"]) == 1
    assert "quantile must be in [0, 1]" in capsys.readouterr().err


def test_gateway_logs_the_poses_it_receives_and_refuses_a_malformed_one(press_log):
    import json

    from skinmap.daemon.mcapread import iter_messages_file_order
    from skinmap.daemon.poses import poses_in_log

    _tmp, log, _poses, _ = press_log
    logged = poses_in_log(log)
    assert [(p.pose.x_mm, p.pose.y_mm, p.pose.angle_deg, p.pose.depth_mm) for p in logged.topic] == PRESSES
    events = [m for m in iter_messages_file_order(str(log)) if m.topic == "/log"]
    assert any(b"pose on skinmap-in/map/pose refused" in m.data for m in events)
    assert json.loads(next(m.data for m in iter_messages_file_order(str(log)) if m.topic == "/pose"))["schema"] == \
        "skinmap.pose/1"


def test_map_takes_the_poses_from_the_contacts_and_the_topic_as_the_csv_gives_them(press_log, capsys):
    from skinmap.daemon.poses import assign_poses, poses_in_log
    from skinmap.daemon.tactile import ProbePose

    _tmp, log, poses, _ = press_log
    assert skinmap_main(["map", str(log), "--poses", str(poses)]) == 0
    with_csv = capsys.readouterr().out
    assert skinmap_main(["map", str(log)]) == 0
    from_contacts = capsys.readouterr().out
    assert "poses from the gateway's /contact messages" in from_contacts
    assert with_csv.splitlines()[-1] == from_contacts.splitlines()[-1]  # the same relief summary
    # the /pose topic, the next source, gives each event the same pose
    logged = poses_in_log(log)
    starts, prev = [], None
    for carried in sorted(logged.contact, key=lambda p: p.t_ns):
        if carried.pose != prev:
            starts.append(carried.t_ns)
            prev = carried.pose
    assert assign_poses(starts, logged.topic) == [ProbePose(*p) for p in PRESSES]


def test_map_estimates_poses_or_names_the_contacts_it_cannot_place(press_log, capsys):
    _tmp, log, _poses, _ = press_log
    assert skinmap_main(["map", str(log), "--estimate"]) == 0
    out = capsys.readouterr().out
    assert "estimated by registration" in out and "anchored by the first pose" in out
    # three presses 60 mm apart hardly overlap: the registration must refuse rather than guess
    assert out.count("not placed:") >= 1 and "cannot decide" in out
    # and whatever it placed, the map is said to rest on unverified poses
    assert "caution: poses estimated from the contacts' overlap are not verified" in out
