"""Service faults: tare files that are no tare, a scanner clock that stops or runs backwards,
a failing or blocked data path (systemd watchdog, SIGTERM), a Zenoh endpoint already in use,
a querying client that stops reading.

Everything runs on loopback: Zenoh on tcp/127.0.0.1:<free port> with multicast scouting off
(make_session_config), the emulated scanner on a pseudo-terminal.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import drain_notify, free_port, gateway_config, notify_socket, pty_emulator, running_gateway, wait_for

from skinmap.daemon import health, service
from skinmap.strains import save_tare, tare_path
from skinmap.client import SkinmapClient
from skinmap.daemon.notify import SystemdNotifier
from skinmap.daemon.device_setup import load_calibration
from skinmap.daemon.health import DeviceClockCheck
from skinmap.daemon.pacing import HostDecimator
from skinmap.daemon.zenoh_io import make_session_config
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.physics import make_shape

pytestmark = pytest.mark.slow

DEVICE = "svc"
N = M = 4


@pytest.fixture
def emulator(tmp_path):
    with pty_emulator(tmp_path / "tty", ScannerSpec(n=N, m=M, scan_rate_hz=40.0, seed=5),
                      make_shape("cylinder", radius=45.0)) as emu:
        yield emu


def faults_config(tmp_path: Path, zport: int, **output):
    return gateway_config(tmp_path, zport, tmp_path / "tty", DEVICE, 40, device={"stall_timeout_s": 1.0},
                          output=output)


def emulator_hello(emulator: Emulator):
    wait_for(lambda: emulator.device is not None, 30, "the emulated scanner")
    return emulator.device.hello()


# ---------------------------------------------------------------------------------------------
# Tare files that are valid JSON but no tare

SHAPE = [2, 2, N, M]
GOOD_VALUES = [7.0] * (4 * N * M)
BAD_TARES = {
    "empty list": ("[]", "not a JSON object but a list of 0"),
    "null": ("null", "not a JSON object but null"),
    "number": ("42", "not a JSON object but the number 42"),
    "string": ('"tare"', "not a JSON object but the string"),
    "empty object": ("{}", "'shape' must be a list of integers, got null"),
    "shape null": (json.dumps({"shape": None, "base_resistance_ohm": GOOD_VALUES}), "'shape' must be a list"),
    "shape of strings": (json.dumps({"shape": ["2", "2", "4", "4"], "base_resistance_ohm": GOOD_VALUES}),
                         "'shape' must be a list of integers"),
    "wrong shape": (json.dumps({"shape": [2, 2, 3, 3], "base_resistance_ohm": [7.0] * 36}),
                    "for an array shaped [2, 2, 3, 3], the scanner is [2, 2, 4, 4]"),
    "values missing": (json.dumps({"shape": SHAPE}), "'base_resistance_ohm' must be a list, got null"),
    "values null": (json.dumps({"shape": SHAPE, "base_resistance_ohm": None}), "must be a list, got null"),
    "values an object": (json.dumps({"shape": SHAPE, "base_resistance_ohm": {"a": 1}}), "must be a list, got an object"),
    "too few values": (json.dumps({"shape": SHAPE, "base_resistance_ohm": [7.0] * 10}),
                       "has 10 values, the scanner has 64 gauges"),
    "nested values": (json.dumps({"shape": SHAPE, "base_resistance_ohm": [[7.0]] * 64}),
                      "'base_resistance_ohm'[0] must be a number or null, got a list of 1"),
    "string value": (json.dumps({"shape": SHAPE, "base_resistance_ohm": ["7"] + GOOD_VALUES[1:]}),
                     "'base_resistance_ohm'[0] must be a number or null, got the string '7'"),
    "boolean value": (json.dumps({"shape": SHAPE, "base_resistance_ohm": GOOD_VALUES[1:] + [True]}),
                      "'base_resistance_ohm'[63] must be a number or null, got the boolean true"),
    "not JSON": ("{shape: 2", "not JSON"),
}


@pytest.mark.parametrize("name", list(BAD_TARES))
def test_a_tare_that_is_no_tare_is_ignored_naming_the_file_and_the_fault(emulator, tmp_path, name):
    text, expected = BAD_TARES[name]
    hello = emulator_hello(emulator)
    cfg = faults_config(tmp_path, free_port())
    path = tare_path(tmp_path / "state", hello.serial_number)
    path.parent.mkdir(parents=True)
    path.write_text(text)
    cal, problem = load_calibration(hello, cfg)
    assert cal.source == "factory"
    np.testing.assert_array_equal(cal.base_resistance, hello.base_resistance_ohm())
    assert problem.startswith(f"ignoring tare {path}: "), problem
    assert expected in problem, problem


def test_a_tare_with_null_gauges_keeps_their_factory_values(emulator, tmp_path):
    hello = emulator_hello(emulator)
    cfg = faults_config(tmp_path, free_port())
    values = np.full((2, 2, N, M), 7.0)
    values[0, 1, 2, 3] = np.nan
    save_tare(tmp_path / "state", hello.serial_number, values, 10)
    cal, problem = load_calibration(hello, cfg)
    assert problem == "" and cal.source.startswith("tare")
    assert cal.base_resistance[0, 1, 2, 3] == hello.base_resistance_ohm()[0, 1, 2, 3]
    assert cal.base_resistance[0, 0, 0, 0] == 7.0


def test_bad_tare_at_start_and_on_reload_streams_on_the_factory_calibration(emulator, tmp_path):
    """At start a tare of the wrong type left the processing thread failing every scan (nothing
    published, no READY); on reload it ended the main loop (exit 1)."""
    hello = emulator_hello(emulator)
    path = tare_path(tmp_path / "state", hello.serial_number)
    path.parent.mkdir(parents=True)
    path.write_text("[]")
    zport = free_port()
    sock = notify_socket(tmp_path / "notify.sock")
    notifier = SystemdNotifier(str(tmp_path / "notify.sock"))
    with running_gateway(faults_config(tmp_path, zport), notifier=notifier) as gw:
        with SkinmapClient([f"tcp/127.0.0.1:{zport}"], prefix="skinmap", device=DEVICE) as client:
            client.elements(timeout=30.0)
            wait_for(lambda: any(m.startswith("READY=1") for m in drain_notify(sock)), 30, "READY=1")
            st = gw.status()
            assert st["calibration"] == "factory"
            assert any(w.startswith(f"ignoring tare {path}: not a JSON object") for w in st["warnings"]), st["warnings"]

            save_tare(tmp_path / "state", hello.serial_number, np.full((2, 2, N, M), 7.0), 10)
            wait_for(lambda: gw.status()["calibration"].startswith("tare"), 30, "the good tare to load")
            assert not any("tare" in w for w in gw.status()["warnings"])

            for text in ("null", json.dumps({"shape": SHAPE, "base_resistance_ohm": None})):
                path.write_text(text)
                os.utime(path, (time.time() + 5, time.time() + 5))  # a new mtime even within one tick
                wait_for(lambda: gw.status()["calibration"] == "factory", 10, f"the tare {text[:20]} to be ignored")
                assert any(w.startswith(f"ignoring tare {path}") for w in gw.status()["warnings"])
                t_after = time.time_ns()
                msg = client.elements(timeout=30.0)
                while msg.host_time_ns < t_after:
                    msg = client.elements(timeout=30.0)
            assert not gw._stop.is_set(), "the main loop ended"
    sock.close()


def test_a_fifo_at_the_tare_path_is_refused_and_blocks_nothing(emulator, tmp_path):
    hello = emulator_hello(emulator)
    path = tare_path(tmp_path / "state", hello.serial_number)
    path.parent.mkdir(parents=True)
    os.mkfifo(path)
    zport = free_port()
    with running_gateway(faults_config(tmp_path, zport)) as gw:
        with SkinmapClient([f"tcp/127.0.0.1:{zport}"], prefix="skinmap", device=DEVICE) as client:
            client.elements(timeout=30.0)
            status = client.next("status", timeout=30.0)
            assert status["calibration"] == "factory"
            assert any(f"ignoring tare {path}: not a regular file (a FIFO)" in w for w in status["warnings"])
            # Replaced by a FIFO while running: the reload in the main loop must not block either.
            path.unlink()
            save_tare(tmp_path / "state", hello.serial_number, np.full((2, 2, N, M), 7.0), 10)
            wait_for(lambda: gw.status()["calibration"].startswith("tare"), 30, "the good tare to load")
            path.unlink()
            os.mkfifo(path)
            os.utime(path, (time.time() + 5, time.time() + 5))
            wait_for(lambda: gw.status()["calibration"] == "factory", 30, "the FIFO to be refused")
            t_after = time.time_ns()
            status = client.next("status", timeout=30.0)
            while status["host_time_ns"] < t_after:
                status = client.next("status", timeout=30.0)
            assert any("a FIFO" in w for w in status["warnings"]), status["warnings"]


# ---------------------------------------------------------------------------------------------
# The scanner's clock

def test_host_decimator_keeps_the_rate_through_jitter_and_bursts():
    d = HostDecimator(20.0)  # 50 ms
    t = np.arange(0, 2_000_000_000, 25_000_000)  # 40 scans/s for 2 s
    jitter = np.random.default_rng(1).integers(-6_000_000, 6_000_000, t.size)
    passed = sum(d.due(int(x)) for x in t + jitter)
    assert passed == 40  # every other scan
    same = HostDecimator(40.0)
    assert all(same.due(int(x)) for x in t + jitter)  # output rate = scan rate: every scan
    burst = HostDecimator(20.0)
    assert [burst.due(x) for x in (0, 0, 0, 60_000_000, 60_000_000)] == [True, False, False, True, False]
    assert all(HostDecimator(0).due(0) for _ in range(3))


def test_device_clock_check_names_stuck_backwards_and_jumps_and_accepts_a_good_clock():
    c = DeviceClockCheck()
    host = 0
    for i in range(10):
        assert c.check(i * 25_000, i, host) == ""
        host += 20_000_000 if i % 2 else 30_000_000  # arrival jitter
    assert "stuck at 225000" in c.check(225_000, 10, host)
    assert "running backwards" in c.check(100_000, 11, host + 25_000_000)
    assert "jumped ahead 5.000 s" in c.check(5_100_000, 12, host + 50_000_000)
    assert c.faults == 3
    c.reset()  # a new handshake: the device clock restarts
    assert c.check(0, 0, host) == "" and c.check(25_000, 1, host + 25_000_000) == ""
    assert c.check(50_000, 1, host) == ""  # the same scan again is not a clock fault


CLOCKS = {
    "zero": (lambda t: 0, "scanner clock stuck at 0 µs"),
    "stuck": (lambda t: 123_456_789, "scanner clock stuck at 123456789 µs"),
    "backwards": (lambda t: 10**10 - t, "scanner clock running backwards"),
    "jumping": (lambda t: t + (t // 500_000) * 3_000_000, "scanner clock jumped ahead"),
}


@pytest.mark.parametrize("name", list(CLOCKS))
def test_a_bad_scanner_clock_keeps_the_output_rate_and_is_named_in_status(emulator, tmp_path, name):
    fault, text = CLOCKS[name]
    zport = free_port()
    with running_gateway(faults_config(tmp_path, zport)) as gw:
        with SkinmapClient([f"tcp/127.0.0.1:{zport}"], prefix="skinmap", device=DEVICE) as client:
            client.elements(timeout=30.0)
            emulator.device.time_us = fault
            time.sleep(0.5)
            s = gw.stats
            scans0, passed0 = s.scans_in, s.results + s.scans_dropped_queue + s.processing_errors
            t_fault = time.time_ns()
            for _ in range(20):
                msg = client.elements(timeout=30.0)
            assert msg.host_time_ns > t_fault
            wait_for(lambda: gw.stats.scans_in - scans0 >= 80, 30, "80 scans with the bad clock")
            scans = s.scans_in - scans0
            passed = s.results + s.scans_dropped_queue + s.processing_errors - passed0
            # 20 Hz of 40 scans/s: every other scan is chosen, whatever the device clock says.
            assert 0.4 * scans <= passed <= 0.6 * scans + 2, (passed, scans)
            status = client.next("status", timeout=30.0)
            assert status["healthy"] is False
            assert any(w.startswith(text) for w in status["warnings"]), status["warnings"]
            assert gw.clock.faults > 0
            emulator.device.time_us = None
            wait_for(lambda: gw.status()["healthy"], 30, "status healthy again with a good clock")


# ---------------------------------------------------------------------------------------------
# The systemd watchdog watches the data path; SIGTERM is always honoured

def test_watchdog_is_not_fed_while_every_scan_fails_and_is_fed_again_after(emulator, tmp_path, monkeypatch):
    from skinmap.daemon.pipeline import FramePipeline

    monkeypatch.setenv("WATCHDOG_USEC", "1000000")
    monkeypatch.setattr(health, "DATA_PATH_TIMEOUT_S", 1.0)
    original = FramePipeline.process
    broken = {"on": False}

    def process(self, *args, **kwargs):
        if broken["on"]:
            raise FloatingPointError("injected solver failure")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(FramePipeline, "process", process)
    sock = notify_socket(tmp_path / "notify.sock")
    notifier = SystemdNotifier(str(tmp_path / "notify.sock"))
    with running_gateway(faults_config(tmp_path, free_port()), notifier=notifier) as gw:
        wait_for(lambda: gw.stats.results > 5, 30, "scans processed")
        wait_for(lambda: any("WATCHDOG=1" in m for m in drain_notify(sock)), 30, "WATCHDOG=1 while scans are processed")
        broken["on"] = True
        wait_for(lambda: not gw.watchdog_fed, 30, "the watchdog to be starved")
        drain_notify(sock)
        seen: list[str] = []
        t_end = time.monotonic() + 2.5
        while time.monotonic() < t_end:
            seen += drain_notify(sock)
        assert not any("WATCHDOG=1" in m for m in seen), seen
        assert gw.link.streaming.is_set()  # the link is fine; the data path is not
        st = gw.status()
        assert st["healthy"] is False
        assert any("systemd watchdog not fed" in w and "injected solver failure" in w for w in st["warnings"]), \
            st["warnings"]
        broken["on"] = False
        wait_for(lambda: any("WATCHDOG=1" in m for m in drain_notify(sock)), 30, "WATCHDOG=1 once scans process again")
        assert gw.watchdog_fed
    sock.close()


def test_watchdog_is_fed_while_the_scanner_is_quiet(emulator, tmp_path, monkeypatch):
    """No scans to process (firmware stalled) is not a data-path fault: restarting would not help."""
    monkeypatch.setenv("WATCHDOG_USEC", "1000000")
    monkeypatch.setattr(health, "DATA_PATH_TIMEOUT_S", 1.0)
    sock = notify_socket(tmp_path / "notify.sock")
    notifier = SystemdNotifier(str(tmp_path / "notify.sock"))
    with running_gateway(faults_config(tmp_path, free_port()), notifier=notifier) as gw:
        wait_for(lambda: gw.stats.results > 5, 30, "scans processed")
        emulator.stall(4.0)
        wait_for(lambda: gw.link.stats.state == "stalled", 30, "the link to see the stall")
        drain_notify(sock)
        wait_for(lambda: any("WATCHDOG=1" in m for m in drain_notify(sock)), 3, "WATCHDOG=1 during the stall")
        assert gw.watchdog_fed
    sock.close()


def test_sigterm_is_honoured_while_the_main_loop_is_blocked(emulator, tmp_path):
    """The console line goes to a pipe nobody reads: once it is full the main loop blocks in
    print(). The watchdog must starve, and SIGTERM must still stop the daemon and finish the log."""
    zport = free_port()
    cfg_file = tmp_path / "skinmapd.toml"
    cfg_file.write_text(textwrap.dedent(f"""
        [device]
        port = "{tmp_path / 'tty'}"
        name = "{DEVICE}"
        scan_rate_hz = 40
        [output]
        rate_hz = 20
        status_rate_hz = 100
        [elements]
        layout = "grid"
        rows = 1
        cols = 4
        [zenoh]
        listen = ["tcp/127.0.0.1:{zport}"]
        [log]
        directory = "logs"
        [state]
        directory = "state"
    """))
    sock = notify_socket(tmp_path / "notify.sock")
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "1000000"}
    stderr = open(tmp_path / "stderr.txt", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg_file), "--console"],
                            env=env, stdout=subprocess.PIPE, stderr=stderr, stdin=subprocess.DEVNULL)
    try:
        seen: list[str] = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(m.startswith("READY=1") for m in seen):
            seen += drain_notify(sock)
        assert any(m.startswith("READY=1") for m in seen), seen
        # About 2 s of console lines fill the pipe; then no WATCHDOG=1 for a whole second.
        deadline = time.monotonic() + 60
        last_feed = time.monotonic()
        while time.monotonic() - last_feed < 1.5:
            assert time.monotonic() < deadline, "the watchdog kept being fed with the main loop blocked"
            if any("WATCHDOG=1" in m for m in drain_notify(sock)):
                last_feed = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        stderr.close()
        sock.close()
    err = (tmp_path / "stderr.txt").read_text()
    assert proc.returncode == 1, err[-2000:]
    assert "did not begin stopping" in err, err[-2000:]
    logs = tmp_path / "logs"
    assert list(logs.glob("*.mcap")) and not list(logs.glob("*.mcap.active")), err[-2000:]


# ---------------------------------------------------------------------------------------------
# Zenoh

def test_zenoh_endpoint_in_use_is_one_line_naming_it(tmp_path):
    zport = free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    cfg_file = tmp_path / "skinmapd.toml"
    cfg_file.write_text(f'[device]\nport = "{tmp_path / "tty"}"\n[zenoh]\nlisten = ["{endpoint}"]\n'
                        f'[log]\ndirectory = "logs"\n[state]\ndirectory = "state"\n')
    with zenoh.open(make_session_config([endpoint])):
        proc = subprocess.run([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg_file)],
                              capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("skinmapd:")]
    assert lines == [f"skinmapd: cannot start: Zenoh: cannot listen on {endpoint}: Address already in use"], \
        proc.stderr
    assert not (tmp_path / "logs").exists()


STALLED_QUERIER = textwrap.dedent("""
    import sys, time, zenoh
    from skinmap.daemon.zenoh_io import make_session_config
    endpoint, selector, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    with zenoh.open(make_session_config([], [endpoint])) as session:
        # Replies land in one-place channels nobody reads: once they are full this session
        # stops reading its link, and the daemon's replies to it back up.
        handlers = [session.get(selector, zenoh.handlers.FifoChannel(1), timeout=60.0) for _ in range(n)]
        print("stalled", flush=True)
        time.sleep(60)
""")


def test_a_querying_client_that_stops_reading_does_not_hold_up_other_queries(emulator, tmp_path, monkeypatch):
    # The stalled link stays open for the whole test (no help from Zenoh closing it): answers
    # to the other clients must not queue behind the blocked replies.
    monkeypatch.setattr(service, "BLOCK_CLOSE_US", 60_000_000, raising=False)
    zport = free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    # Big surfaces (40 000 points), so a few unread replies fill the stalled client's link.
    with running_gateway(faults_config(tmp_path, zport, points_per_pitch=50)) as gw:
        with SkinmapClient([endpoint], prefix="skinmap", device=DEVICE) as client:
            client.surface(timeout=30.0)
            stalled = subprocess.Popen([sys.executable, "-c", STALLED_QUERIER, endpoint, f"skinmap/{DEVICE}/*", "200"],
                                       stdout=subprocess.PIPE, text=True)
            try:
                assert stalled.stdout.readline().strip() == "stalled"
                time.sleep(0.5)
                answered = 0
                for _ in range(5):
                    with SkinmapClient([endpoint], prefix="skinmap", device=DEVICE) as other:
                        info = other.info()
                        assert info["rows"] == N
                        answered += 1
                assert stalled.poll() is None  # still connected and stuck
            finally:
                stalled.kill()
                stalled.wait()
                stalled.stdout.close()
            assert answered == 5
            assert gw.link.streaming.is_set()
