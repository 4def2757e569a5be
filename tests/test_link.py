"""ScannerLink against the emulated firmware state machine on an in-process line.

The port is the thin I/O edge swapped out: :class:`DeviceLoopback` runs the real device state
machine on the real clock, so handshake, streaming, stalls, reboots, unplug and loss are
exercised without a pseudo-terminal (tests/test_service.py covers the pty path).
"""
from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import wait_until

from skinmap.daemon.config import DeviceConfig as LinkConfig
from skinmap.daemon.link import ScannerLink
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.loopback import DeviceLoopback
from skinmap.emulator.physics import make_shape
from skinmap.ports import PortFactory, memory_pair


def lose_scan_frames(every: int):
    """A line that loses every `every`-th frame whole, counting only scan-sized ones (the device
    sends whole frames per chunk)."""
    count = 0

    def line(data: bytes, _now: float) -> bytes:
        nonlocal count
        out = bytearray()
        for part in data.split(b"\x00"):
            if not part:
                continue
            count += 1
            if len(part) > 200 and count % every == 0:
                continue
            out += part + b"\x00"
        return bytes(out)

    return line


def make_device(n=5, m=5, **kw) -> Device:
    return Device(ScannerSpec(n=n, m=m, scan_rate_hz=100.0, seed=3, **kw), make_shape("flat"), now_s=time.monotonic())


class Recorder:
    def __init__(self) -> None:
        self.hellos = []
        self.scans = []
        self.events = []
        self.frames = 0

    def link(self, cfg: LinkConfig, port_factory: PortFactory) -> ScannerLink:
        return ScannerLink(
            cfg,
            on_hello=self.hellos.append,
            on_scan=lambda scan, frame, t: self.scans.append(scan.sample_index),
            on_frame=lambda f, t: setattr(self, "frames", self.frames + 1),
            on_event=lambda level, text: self.events.append((level, text)),
            port_factory=port_factory,
        )


CFG = LinkConfig(port="/dev/fake-scanner", scan_rate_hz=100.0, handshake_timeout_s=1.0, stall_timeout_s=0.3,
                 reconnect_min_s=0.05, reconnect_max_s=0.2)


def test_handshake_and_streaming():
    dev = make_device()
    rec = Recorder()
    link = rec.link(CFG, DeviceLoopback(dev).open)
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
    link = rec.link(CFG, DeviceLoopback(dev, line=lose_scan_frames(4)).open)
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
    loop = DeviceLoopback(dev)
    link = rec.link(CFG, loop.open)
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        with loop.lock:
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
    loop = DeviceLoopback(dev)
    link = rec.link(CFG, loop.open)
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 10)
        loop.reboot()  # the firmware restarts and announces itself with HELLO
        assert wait_until(lambda: len(rec.hellos) >= 2)
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 10)
    finally:
        link.stop()
    assert link.stats.reboots >= 1
    assert rec.scans[-1] < 1000  # the index restarted with the device


def test_unplug_and_replug_reconnects_in_process():
    dev = make_device()
    loop = DeviceLoopback(dev)
    rec = Recorder()
    link = rec.link(CFG, loop.open)
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        loop.unplug()
        assert wait_until(lambda: link.stats.disconnects >= 2)  # lost, then at least one reopen refused
        assert "no scanner on the line" in link.stats.last_error
        time.sleep(0.3)  # a few failed reopen attempts
        loop.replug()
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 10)
    finally:
        link.stop()
    assert link.stats.reconnects >= 1
    assert loop.ports[0].closed and len(loop.ports) == 2
    assert link.stats.state in ("streaming", "stopped")


def test_device_larger_than_allowed_is_refused_with_a_clear_error():
    dev = make_device(6, 6)
    rec = Recorder()
    cfg = LinkConfig(port="/dev/fake-scanner", scan_rate_hz=100.0, handshake_timeout_s=0.5, max_cells=16,
                     reconnect_min_s=0.05, reconnect_max_s=0.1)
    link = rec.link(cfg, DeviceLoopback(dev).open)
    link.start()
    try:
        assert wait_until(lambda: link.stats.handshake_failures >= 2)
    finally:
        link.stop()
    assert not rec.scans and not rec.hellos
    assert "6×6 = 36 cells, more than device.max_cells = 16" in link.stats.last_error


def test_silent_port_gives_a_handshake_error_not_a_crash():
    far_ends = []

    def silent_port():
        host, far = memory_pair("silent")  # nobody reads or answers at the far end
        far_ends.append(far)
        return host

    rec = Recorder()
    cfg = LinkConfig(port="/dev/fake-scanner", handshake_timeout_s=0.3, reconnect_min_s=0.05, reconnect_max_s=0.1)
    link = rec.link(cfg, silent_port)
    link.start()
    try:
        assert wait_until(lambda: link.stats.handshake_failures >= 2)
    finally:
        link.stop()
    assert "no HELLO" in link.stats.last_error
