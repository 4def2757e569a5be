"""ScannerLink against the emulated firmware state machine through an in-memory port.

The port fake is the thin I/O edge swapped out: it runs the real device state machine on the
real clock, so handshake, streaming, stalls, reboots, unplug and loss are exercised without a
pseudo-terminal (tests/test_service.py covers the pty path).
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import serial
from conftest import wait_until

from skinmap.daemon.config import DeviceConfig as LinkConfig
from skinmap.daemon.link import ScannerLink
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.physics import make_shape


class FakePort:
    """pyserial-like port backed by a Device; `drop_scan_every` loses whole frames."""

    def __init__(self, device: Device, *, drop_every: int = 0) -> None:
        self.device = device
        self.rx = bytearray()
        self.closed = False
        self.unplugged = False
        self.drop_every = drop_every
        self._frames = 0
        self.lock = threading.Lock()

    def _pump(self) -> None:
        data = self.device.poll(time.monotonic())
        if data:
            self._append(data)

    def _append(self, data: bytes) -> None:
        if not self.drop_every:
            self.rx += data
            return
        for part in data.split(b"\x00"):
            if not part:
                continue
            self._frames += 1
            if len(part) > 200 and self._frames % self.drop_every == 0:
                continue  # lose this (scan-sized) frame whole
            self.rx += part + b"\x00"

    @property
    def in_waiting(self) -> int:
        with self.lock:
            if self.unplugged:
                raise serial.SerialException("device disconnected")
            self._pump()
            return len(self.rx)

    def read(self, n: int) -> bytes:
        with self.lock:
            if self.unplugged:
                raise serial.SerialException("device disconnected")
            self._pump()
        if not self.rx:
            time.sleep(0.005)
        with self.lock:
            data = bytes(self.rx[:n])
            del self.rx[:n]
            return data

    def write(self, data: bytes) -> int:
        with self.lock:
            if self.unplugged:
                raise serial.SerialException("device disconnected")
            out = self.device.on_bytes(bytes(data), time.monotonic())
            if out:
                self._append(out)
        return len(data)

    def reset_input_buffer(self) -> None:
        self.rx.clear()

    def close(self) -> None:
        self.closed = True


def make_device(n=5, m=5, **kw) -> Device:
    return Device(ScannerSpec(n=n, m=m, scan_rate_hz=100.0, seed=3, **kw), make_shape("flat"), now_s=time.monotonic())


class Recorder:
    def __init__(self) -> None:
        self.hellos = []
        self.scans = []
        self.events = []
        self.frames = 0

    def link(self, cfg: LinkConfig, opener) -> ScannerLink:
        return ScannerLink(
            cfg,
            on_hello=self.hellos.append,
            on_scan=lambda scan, frame, t: self.scans.append(scan.sample_index),
            on_frame=lambda f, t: setattr(self, "frames", self.frames + 1),
            on_event=lambda level, text: self.events.append((level, text)),
            opener=opener,
        )


CFG = LinkConfig(port="/dev/fake-scanner", scan_rate_hz=100.0, handshake_timeout_s=1.0, stall_timeout_s=0.3,
                 reconnect_min_s=0.05, reconnect_max_s=0.2)


def test_handshake_and_streaming():
    dev = make_device()
    rec = Recorder()
    link = rec.link(CFG, lambda *a: FakePort(dev))
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 20)
    finally:
        link.stop()
    assert len(rec.hellos) == 1 and rec.hellos[0].n == 5
    assert np.all(np.diff(rec.scans) == 1)
    assert link.stats.scans_lost == 0 and link.stats.reconnects == 0
    assert any("streaming" in text for _, text in rec.events)


def test_lost_scans_are_counted_from_the_sample_index():
    dev = make_device()
    rec = Recorder()
    link = rec.link(CFG, lambda *a: FakePort(dev, drop_every=4))
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 30)
    finally:
        link.stop()
    expected_lost = (rec.scans[-1] - rec.scans[0] + 1) - len(rec.scans)
    assert expected_lost > 0
    assert link.stats.scans_lost == expected_lost


@pytest.mark.slow
def test_stall_is_reported_and_streaming_resumes():
    dev = make_device()
    rec = Recorder()
    link = rec.link(CFG, lambda *a: FakePort(dev))
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        dev.stall(time.monotonic(), 1.0)
        assert wait_until(lambda: link.stats.stalls >= 1)
        before = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > before + 10)
    finally:
        link.stop()
    assert any("resumed" in text for _, text in rec.events)
    assert link.stats.reconnects == 0  # a stall keeps the port open


def test_reboot_triggers_a_new_handshake():
    dev = make_device()
    rec = Recorder()
    port = FakePort(dev)
    link = rec.link(CFG, lambda *a: port)
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 10)
        with port.lock:  # the firmware restarts and announces itself with HELLO
            port._append(dev._reboot_now(time.monotonic(), True))
        assert wait_until(lambda: len(rec.hellos) >= 2)
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 10)
    finally:
        link.stop()
    assert link.stats.reboots >= 1
    assert rec.scans[-1] < 1000  # the index restarted with the device


def test_unplug_and_replug_reconnects_in_process():
    dev = make_device()
    ports: list[FakePort] = []
    available = threading.Event()
    available.set()

    def opener(*_a):
        if not available.is_set():
            raise serial.SerialException("could not open port /dev/fake-scanner: No such file or directory")
        ports.append(FakePort(dev))
        return ports[-1]

    rec = Recorder()
    link = rec.link(CFG, opener)
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        available.clear()
        ports[-1].unplugged = True
        assert wait_until(lambda: link.stats.disconnects >= 1)
        time.sleep(0.3)  # a few failed reopen attempts
        available.set()
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 10)
    finally:
        link.stop()
    assert link.stats.reconnects >= 1
    assert ports[0].closed
    assert link.stats.state in ("streaming", "stopped")


def test_device_larger_than_allowed_is_refused_with_a_clear_error():
    dev = make_device(6, 6)
    rec = Recorder()
    cfg = LinkConfig(port="/dev/fake-scanner", scan_rate_hz=100.0, handshake_timeout_s=0.5, max_cells=16,
                     reconnect_min_s=0.05, reconnect_max_s=0.1)
    link = rec.link(cfg, lambda *a: FakePort(dev))
    link.start()
    try:
        assert wait_until(lambda: link.stats.handshake_failures >= 2)
    finally:
        link.stop()
    assert not rec.scans and not rec.hellos
    assert "6×6 = 36 cells, more than device.max_cells = 16" in link.stats.last_error


def test_silent_port_gives_a_handshake_error_not_a_crash():
    class SilentPort(FakePort):
        def write(self, data):
            return len(data)

        def _pump(self):
            pass

    rec = Recorder()
    cfg = LinkConfig(port="/dev/fake-scanner", handshake_timeout_s=0.3, reconnect_min_s=0.05, reconnect_max_s=0.1)
    link = rec.link(cfg, lambda *a: SilentPort(make_device()))
    link.start()
    try:
        assert wait_until(lambda: link.stats.handshake_failures >= 2)
    finally:
        link.stop()
    assert "no HELLO" in link.stats.last_error
