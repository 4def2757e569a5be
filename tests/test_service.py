"""End to end: emulator on a pseudo-terminal → skinmapd → Zenoh subscriber; then the MCAP log
replays to identical results.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from conftest import (drain_notify, explicit_elements, free_port, gateway_config, pty_emulator, rigid_motion, running_gateway,
                      notify_socket, wait_for)

from skinmap.client import SkinmapClient
from skinmap.daemon.mcapread import iter_messages_file_order
from skinmap.daemon.replay import replay_log
from skinmap.wire import messages
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.emulator.physics import make_shape

pytestmark = pytest.mark.slow


ELEMENT_UV = np.array([[u, v] for v in (-6.0, 6.0) for u in np.linspace(-20.0, 20.0, 9)])


def make_config(link: Path, tmp_path: Path, zport: int, **output):
    return gateway_config(tmp_path, zport, link, "e2e", 40, device={"stall_timeout_s": 1.0},
                          output={"status_rate_hz": 2, **output}, elements=explicit_elements(ELEMENT_UV),
                          log={"max_file_mb": 64})


@pytest.fixture
def emulator(tmp_path):
    shape = make_shape("gaussian", height=3.0, fwhm=24.0, u0=4.0, v0=-3.0)
    cfg = ScannerSpec(n=5, m=5, scan_rate_hz=40.0, seed=11,
                       electrical=ElectricalConfig(hysteresis=0.0, drift_rel_sd=0.0))
    with pty_emulator(tmp_path / "ttySKIN0", cfg, shape, element_uv=ELEMENT_UV) as emu:
        yield emu


def test_pty_to_zenoh_subscriber_matches_ground_truth_and_replays_identically(emulator, tmp_path):
    zport = free_port()
    cfg = make_config(tmp_path / "ttySKIN0", tmp_path, zport)
    errors = []
    with running_gateway(cfg) as gw:
        with SkinmapClient([f"tcp/127.0.0.1:{zport}"], prefix="skinmap", device="e2e") as client:
            first = client.elements(timeout=30.0)
            assert first.positions.shape == (len(ELEMENT_UV), 3)
            for _ in range(10):
                msg = client.elements(timeout=30.0)
                assert np.isfinite(msg.positions).all() and np.isfinite(msg.normals).all()
                assert (msg.flags & 1).all()
                result = next((r for r in list(gw.results) if r.seq == msg.seq), None)
                if result is None:
                    continue
                truth = emulator.ground_truth(msg.seq)
                r, t = rigid_motion(result.nodes_mm.reshape(-1, 3), truth.nodes.reshape(-1, 3))
                est = (msg.positions * 1000.0) @ r.T + t
                errors.append(np.linalg.norm(est - truth.element_positions, axis=1).mean())
            info = client.info()
            assert info["rows"] == 5 and info["elements"]["count"] == len(ELEMENT_UV)
            status = client.latest("status")
            assert status["connected"] is True
    assert errors, "no published scan could be matched with the reconstruction it came from"
    assert float(np.mean(errors)) < 0.5, f"element error {np.mean(errors):.3f} mm"

    logs = sorted((tmp_path / "logs").glob("*.mcap"))
    assert logs and not list((tmp_path / "logs").glob("*.active")), "SIGTERM-like stop must finish the file"
    report = replay_log(logs[0])
    assert report.compared >= 10
    assert report.identical, report.format()
    # 20 Hz of 40 scans/s: the scan before each one published is a lead scan, logged and
    # reconstructed (replay too, above), never published
    seqs: dict[str, list[int]] = {"/strains": [], "/strains/lead": [], "/elements": []}
    for m in iter_messages_file_order(logs[0]):
        if m.topic in seqs:
            seqs[m.topic].append(messages.decode_header(m.data).seq)
    leads, published = set(seqs["/strains/lead"]), set(seqs["/elements"])
    assert len(leads) >= 5 and report.leads == len(seqs["/strains/lead"]), report.format()
    assert not leads & published and set(seqs["/strains"]) == published
    assert sum(seq + 1 in published for seq in leads) >= 0.8 * len(leads)


def test_daemon_survives_unplug_and_replug_behind_the_same_link(emulator, tmp_path):
    zport = free_port()
    cfg = make_config(tmp_path / "ttySKIN0", tmp_path, zport)
    with running_gateway(cfg) as gw:
        with SkinmapClient([f"tcp/127.0.0.1:{zport}"], prefix="skinmap", device="e2e") as client:
            client.elements(timeout=30.0)
            emulator.disconnect(reconnect_after_s=0.5)
            wait_for(lambda: gw.link.stats.reconnects >= 1, what="a reconnect")
            t_back = time.time_ns()
            msg = client.elements(timeout=30.0)
            while msg.host_time_ns < t_back:  # skip anything queued from before the unplug
                msg = client.elements(timeout=30.0)
            assert np.isfinite(msg.positions).all()
    assert gw.link.stats.disconnects >= 1


def test_skinmapd_process_notifies_systemd_and_stops_cleanly_on_sigterm(emulator, tmp_path):
    import signal
    import subprocess
    import sys

    zport = free_port()
    cfg_file = tmp_path / "skinmapd.toml"
    cfg_file.write_text(f"""
[device]
port = "{tmp_path / 'ttySKIN0'}"
name = "proc"
scan_rate_hz = 40
[zenoh]
listen = ["tcp/127.0.0.1:{zport}"]
[log]
directory = "logs"
[state]
directory = "state"
""")
    sock = notify_socket(tmp_path / "notify.sock", 0.1)
    env = {**__import__("os").environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "1000000"}
    proc = subprocess.Popen([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg_file)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    messages_seen: list[str] = []
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (
            any(m.startswith("READY=1") for m in messages_seen) and any("WATCHDOG=1" in m for m in messages_seen)
        ):
            messages_seen += drain_notify(sock)
        assert any(m.startswith("READY=1") for m in messages_seen), messages_seen
        assert any("WATCHDOG=1" in m for m in messages_seen)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        sock.close()
    assert proc.returncode == 0, err.decode()[-2000:]
    logs = tmp_path / "logs"
    assert list(logs.glob("*.mcap")) and not list(logs.glob("*.mcap.active")), err.decode()[-2000:]


def test_skinmapd_refuses_a_bad_config_without_starting(tmp_path):
    import subprocess
    import sys

    bad = tmp_path / "bad.toml"
    bad.write_text('[device]\nscan_rate_hz = -3\n[log]\ndirectory = "logs"\n')
    proc = subprocess.run([sys.executable, "-m", "skinmap.daemon.service", "--config", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "device.scan_rate_hz" in proc.stderr and "-3" in proc.stderr
    assert not (tmp_path / "logs").exists()


def test_dead_gauge_degrades_nearby_elements_and_is_reported(emulator, tmp_path):
    mask = np.zeros((2, 2, 5, 5), dtype=bool)
    mask[0, 0, 2, 2] = True  # upper row-direction gauge of the centre cell
    emulator.set_open(mask)
    zport = free_port()
    cfg = make_config(tmp_path / "ttySKIN0", tmp_path, zport)
    with running_gateway(cfg) as gw:
        with SkinmapClient([f"tcp/127.0.0.1:{zport}"], prefix="skinmap", device="e2e") as client:
            client.elements(timeout=30.0)
            msg = client.elements(timeout=30.0)
            status = client.next("status", timeout=30.0)
            if status["healthy"]:  # the first report may predate the first processed scan
                status = client.next("status", timeout=30.0)
    assert np.isfinite(msg.positions).all() and np.isfinite(msg.uncertainty).all()
    assert msg.scatter is not None and (msg.scatter <= msg.uncertainty).all()
    degraded = (msg.flags & 0x04) != 0
    near = np.abs(ELEMENT_UV).max(axis=1) <= 18.0  # within 1.5 pitch of the centre cell
    assert degraded[near].all() and not degraded[~near].all()
    assert status["healthy"] is False
    assert any("unusable" in w for w in status["warnings"]) or "GAUGE_OPEN" in status["device_faults"]
