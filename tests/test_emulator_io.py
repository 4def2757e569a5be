"""Emulator <-> codec over real links: a pseudo-terminal through pyserial, loopback TCP,
disconnect/reconnect behind the same symlink, byte faults, and the CLI process."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import termios
import time

import numpy as np
import pytest
import serial

from skinmap import protocol as p
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.emulator.emulator import Emulator, FaultSchedule
from skinmap.emulator.linkfaults import LinkFaults
from skinmap.emulator.physics import gauge_strains, make_shape
from skinmap.emulator.transport import PtyTransport, TcpTransport

pytestmark = pytest.mark.slow

SHAPE = "gaussian:height=4,fwhm=18,u0=3,v0=-2"


class Client:
    """A minimal host: request ids, reading frames until a condition holds."""

    def __init__(self, port: serial.SerialBase):
        self.port = port
        self.dec = p.StreamDecoder()
        self.seq = 0
        self.frames: list[p.Frame] = []

    def send(self, msg) -> None:
        self.port.write(p.encode_frame(msg, self.seq))
        self.seq += 1

    def read_until(self, pred, timeout=10.0) -> list[p.Frame]:
        end = time.monotonic() + timeout
        got: list[p.Frame] = []
        while time.monotonic() < end:
            got += self.dec.feed(self.port.read(self.port.in_waiting or 1))
            if pred(got):
                self.frames += got
                return got
        raise AssertionError(f"timed out; got {[f.msg_type.name for f in got]}")

    def scans(self, frames):
        return [f.msg for f in frames if f.msg_type == p.MsgType.SCAN]


def _n_scans(k):
    return lambda frames: sum(f.msg_type == p.MsgType.SCAN for f in frames) >= k


def _has(kind):
    return lambda frames: any(f.msg_type == kind for f in frames)


def _answer(frames, request_id):
    """The ACK/NAK of a request among frames, or None."""
    return next((f.msg for f in frames if f.msg_type in (p.MsgType.ACK, p.MsgType.NAK)
                 and f.msg.request_id == request_id), None)


def _answered(request_id):
    return lambda frames: _answer(frames, request_id) is not None


def _check_strains(hello: p.Hello, scans, shape, n, m, tol):
    """Host-side conversion with HELLO's calibration reproduces the forward model."""
    truth = np.stack(gauge_strains(shape, n, m))
    for scan in scans:
        r = scan.resistances_ohm()
        eps = (r / hello.base_resistance_ohm() - 1.0) / hello.gauge_factor()
        err = eps - truth
        assert np.abs(err).max() < tol, np.abs(err).max()
    return err


def test_pty_round_trip_through_pyserial(tmp_path):
    link = tmp_path / "ttySKIN0"
    shape = make_shape("gaussian", height=4.0, fwhm=18.0, centre=(3.0, -2.0))
    cfg = ScannerSpec(n=5, m=5, scan_rate_hz=50.0, seed=7)
    with Emulator(cfg, shape, PtyTransport(link)) as emu:
        assert link.is_symlink() and os.readlink(link) == emu.transport.path
        with serial.Serial(str(link), timeout=0.05) as port:
            host = Client(port)
            host.send(p.QueryInfo(1))

            def ack_then_hello(frames):
                kinds = [f.msg_type for f in frames]
                return _answer(frames, 1) is not None and p.MsgType.HELLO in kinds[kinds.index(p.MsgType.ACK):]

            frames = host.read_until(ack_then_hello)
            assert _answer(frames, 1) == p.Ack(1, int(p.MsgType.QUERY_INFO))
            hello = [f.msg for f in frames if f.msg_type == p.MsgType.HELLO][-1]
            assert (hello.n, hello.m, hello.serial_number) == (5, 5, emu.device.serial_number)
            host.send(p.Start(2))
            frames = host.read_until(_n_scans(12))
            scans = host.scans(frames)
            idx = [s.sample_index for s in scans]
            assert idx == list(range(idx[0], idx[0] + len(idx))) and idx[0] == 0
            # noise 0.007 % of R is ~6e-5 strain; drift and quantisation are far smaller
            err = _check_strains(hello, scans, shape, 5, 5, tol=5e-4)
            assert host.dec.crc_errors == host.dec.cobs_errors == 0
            gt = emu.ground_truth(scans[-1].sample_index)
            np.testing.assert_allclose(gt.nodes, shape.position(gt.nodes[..., :2]), atol=1e-12)
            host.send(p.Stop(3))
            assert _answer(host.read_until(_answered(3)), 3) == p.Ack(3, int(p.MsgType.STOP))
    assert not link.exists()  # the symlink goes with the emulator


def test_tcp_round_trip_through_serial_for_url():
    shape = make_shape("cylinder", radius=40.0)
    cfg = ScannerSpec(n=4, m=6, scan_rate_hz=40.0, electrical=ElectricalConfig.ideal())
    with Emulator(cfg, shape, TcpTransport(0)) as emu:
        url = emu.transport.url
        assert url.startswith("socket://127.0.0.1:")
        port = serial.serial_for_url(url, timeout=0.05)
        try:
            host = Client(port)
            host.send(p.QueryInfo(1))
            # the boot HELLO (sent when the client connected) may arrive before or after ours
            hello = next(f.msg for f in host.read_until(_has(p.MsgType.HELLO)) if f.msg_type == p.MsgType.HELLO)
            host.send(p.SetScanRate(2, 80_000))
            ack = _answer(host.read_until(_answered(2)), 2)
            assert ack == p.Ack(2, int(p.MsgType.SET_SCAN_RATE), (80_000).to_bytes(4, "little"))
            host.send(p.Start(3))
            scans = host.scans(host.read_until(_n_scans(8)))
            assert scans[0].step_period_ns == p.step_period_ns(80_000, 4, 6)
            _check_strains(hello, scans, shape, 4, 6, tol=1e-6)  # ideal electrical chain
        finally:
            port.close()


def test_disconnect_then_new_pty_behind_the_same_symlink(tmp_path):
    link = tmp_path / "tty"
    cfg = ScannerSpec(n=3, m=3, scan_rate_hz=50.0)
    with Emulator(cfg, make_shape("flat"), PtyTransport(link)) as emu:
        port = serial.Serial(str(link), timeout=0.05)
        host = Client(port)
        host.send(p.Start(1))
        host.read_until(_n_scans(3))
        emu.disconnect(reconnect_after_s=0.4)
        assert not link.exists()
        try:  # the old port is dead: flushing or reading it fails (EIO) or, at best, brings nothing
            port.reset_input_buffer()
            stale = port.read(4096)
        except (serial.SerialException, termios.error):
            stale = b""
        assert stale == b""
        port.close()
        deadline = time.monotonic() + 10.0
        while not link.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert link.exists() and os.readlink(link) == emu.transport.path
        assert emu.device.boot_count == 2  # powered up afresh
        with serial.Serial(str(link), timeout=0.05) as port2:
            host2 = Client(port2)
            host2.send(p.QueryInfo(9))
            frames = host2.read_until(_has(p.MsgType.HELLO))
            assert emu.device.state == p.DeviceState.IDLE  # a new boot does not scan by itself
            host2.send(p.Start(10))
            scans = host2.scans(host2.read_until(_n_scans(2)))
            assert scans[0].sample_index == 0


def test_byte_faults_are_survived_by_the_stream_decoder(tmp_path):
    faults = LinkFaults(garbage_rate_hz=20.0, bit_flip_rate=2e-4, drop_rate=5e-5)
    cfg = ScannerSpec(n=5, m=5, scan_rate_hz=100.0, seed=3)
    with Emulator(cfg, make_shape("flat"), PtyTransport(tmp_path / "tty"), faults) as emu:
        with serial.Serial(str(tmp_path / "tty"), timeout=0.05) as port:
            host = Client(port)
            host.send(p.Start(1))
            scans = host.scans(host.read_until(_n_scans(80), timeout=60.0))
        counters = emu.link.counters()
    d = host.dec.counters()
    assert len(scans) >= 80
    assert counters["garbage_bursts"] > 0 and counters["bits_flipped"] > 0
    damaged = sum(d[k] for k in ("crc_errors", "cobs_errors", "length_errors", "oversize_frames",
                                 "version_errors", "incompat_flag_drops", "field_errors"))
    assert damaged > 0  # damage was seen...
    idx = np.array([s.sample_index for s in scans])
    steps = np.diff(idx)
    assert np.all(steps >= 1)  # ...what got through is intact and in order...
    # ...and every run of missing scans is accounted for: a body the decoder dropped (one run
    # at most per damaged body), or the device saying it dropped scans itself.
    gaps = steps > 1
    flagged = np.array([bool(s.flags & p.ScanFlag.DROPPED_BEFORE) for s in scans[1:]])
    assert int((gaps & ~flagged).sum()) <= damaged, (int(gaps.sum()), damaged)


def test_scheduled_reboot_sends_hello_again(tmp_path):
    cfg = ScannerSpec(n=3, m=3, scan_rate_hz=50.0)
    sched = FaultSchedule(reboot_every_s=0.5)
    with Emulator(cfg, make_shape("flat"), TcpTransport(0), schedule=sched) as emu:
        port = serial.serial_for_url(emu.transport.url, timeout=0.05)
        try:
            host = Client(port)
            host.send(p.Start(1))
            host.read_until(_n_scans(2))
            frames = host.read_until(_has(p.MsgType.HELLO), timeout=2.0)
            hello_frame = next(f for f in frames if f.msg_type == p.MsgType.HELLO)
            assert hello_frame.seq == 0
            status = host.read_until(_has(p.MsgType.STATUS))
            st = [f.msg for f in status if f.msg_type == p.MsgType.STATUS][-1]
            assert st.fault_flags & p.FaultFlag.WATCHDOG_RESET and st.state == p.DeviceState.IDLE
        finally:
            port.close()
    assert emu.reboots >= 1


def test_cli_serves_pty_writes_truth_and_exits_cleanly_on_sigterm(tmp_path):
    link = tmp_path / "ttyCLI"
    truth = tmp_path / "truth.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-m", "skinmap.emulator.command", "--size", "4x5", "--shape", SHAPE,
         "--rate", "40", "--link", str(link), "--truth-file", str(truth), "--elements", "0,0;3,-2",
         "--dead-gauge", "upper,row,1,2", "--status-every", "0.5", "--seed", "5"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = proc.stdout.readline() + proc.stdout.readline()
        assert "serving" in line and str(link) in line, line
        with serial.Serial(str(link), timeout=0.05) as port:
            host = Client(port)
            host.send(p.Start(1))
            scans = host.scans(host.read_until(_n_scans(6)))
        assert scans[0].resistance_uohm[0, 0, 1, 2] == p.RES_OPEN
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped" in out
    assert not link.exists()
    records = [json.loads(x) for x in truth.read_text().splitlines()]
    by_index = {r["sample_index"]: r for r in records}
    for s in scans:
        r = by_index[s.sample_index]
        assert r["timestamp_us"] == s.timestamp_us
        assert np.shape(r["nodes"]) == (4, 5, 3)
        np.testing.assert_allclose(r["element_positions"][1], [3.0, -2.0, 4.0], atol=1e-6)


@pytest.mark.parametrize(
    "args, words",
    [
        (["--size", "5by5"], "size must look like"),
        (["--size", "1x5"], "ScannerSpec.n"),
        (["--shape", "blob"], "unknown shape kind"),
        (["--dead-gauge", "upper,row,9,9"], "outside the 5x5 array"),
        (["--dead-gauge", "middle,row,1,1"], "layer must be upper or lower"),
        (["--bit-flip-rate", "2"], "bit_flip_rate"),
        (["--rate", "1000"], "exceeds the maximum"),
    ],
)
def test_cli_bad_arguments_are_named(args, words):
    proc = subprocess.run([sys.executable, "-m", "skinmap.emulator.command", *args, "--duration", "0.1",
                           "--link", "/tmp/skinmap-emulator-test-unused"],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert words in proc.stderr, proc.stderr


def test_scheduled_stall_silences_the_device_then_flags_lost_scans(tmp_path):
    cfg = ScannerSpec(n=3, m=3, scan_rate_hz=50.0)
    sched = FaultSchedule(stall_every_s=0.6, stall_for_s=0.3)
    with Emulator(cfg, make_shape("flat"), PtyTransport(tmp_path / "tty"), schedule=sched) as emu:
        with serial.Serial(str(tmp_path / "tty"), timeout=0.05) as port:
            host = Client(port)
            host.send(p.Start(1))
            scans = host.scans(host.read_until(
                lambda fr: any(f.msg_type == p.MsgType.SCAN and f.msg.flags & p.ScanFlag.DROPPED_BEFORE
                               for f in fr), timeout=3.0))
    assert emu.stalls >= 1
    flagged = next(s for s in scans if s.flags & p.ScanFlag.DROPPED_BEFORE)
    before = scans[scans.index(flagged) - 1]
    assert flagged.sample_index - before.sample_index > 1  # the gap shows in sample_index


@pytest.mark.parametrize("kw, words", [
    (dict(stall_every_s=1.0), "stall_for_s"),
    (dict(disconnect_every_s=1.0), "disconnect_for_s"),
    (dict(reboot_every_s=-1.0), "reboot_every_s"),
])
def test_bad_schedules_are_named(kw, words):
    with pytest.raises(ValueError, match=words):
        FaultSchedule(**kw)
